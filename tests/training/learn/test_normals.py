"""The depth net's training-only normals head: its target against analytic surfaces, its loss, its stage."""

import math

import pytest
import torch

from genre_backend.config import CameraConfig
from genre_backend.nets.model import GenRe, load_model
from support.tiny_data import TINY, tiny_train_config
from training.learn.normals import MAX_DEPTH_STEP, depth_normals, normals_loss
from training.learn.train import StageModule, train, weights_digest

CAMERA = CameraConfig()
SIZE = 128


def _rays(size: int = SIZE) -> torch.Tensor:
    """(S, S, 3) view-frame directions of the pixel centres, z = −1 (from the camera, which sits at (0, 0, d))."""
    f = CAMERA.focal_px(size)
    c = torch.arange(size, dtype=torch.float64) + 0.5 - size / 2.0
    x = (c / f).view(1, size).expand(size, size)
    y = (-c / f).view(size, 1).expand(size, size)
    return torch.stack([x, y, -torch.ones_like(x)], dim=-1)


def _sphere(centre, radius, size=SIZE):
    """Planar depth (1, S, S) of a sphere and its analytic normals (S, S, 3) where the ray hits it."""
    eye = torch.tensor([0.0, 0.0, CAMERA.distance], dtype=torch.float64)
    d = _rays(size)
    u = d / d.norm(dim=-1, keepdim=True)
    oc = eye - torch.tensor(centre, dtype=torch.float64)
    b = (u * oc).sum(-1)
    disc = b ** 2 - (oc @ oc - radius ** 2)
    hit = disc > 0
    t = -b - disc.clamp(min=0).sqrt()
    p = eye + t[..., None] * u
    depth = torch.where(hit, CAMERA.distance - p[..., 2], torch.zeros_like(t))
    n = (p - torch.tensor(centre, dtype=torch.float64)) / radius
    return depth[None].float(), n.float(), hit


def _angles_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.rad2deg(torch.acos((a * b).sum(-1).clamp(-1, 1)))


def test_a_sphere_s_normals_are_its_radii_inside_the_rim():
    depth, truth, hit = _sphere((0.05, -0.03, 0.0), 0.3)
    normals, valid = depth_normals(depth, CAMERA)
    got = normals[0].permute(1, 2, 0)
    assert valid[0].sum() > 0.85 * hit.sum()  # everything but a rim of steep pixels and the border
    assert not (valid[0] & ~hit).any()
    err = _angles_deg(got[valid[0]], truth[valid[0]])
    # central differences of a sphere ~30 px across: a fraction of a degree where it faces the camera, a few
    # degrees at the rim where the curve turns fastest between neighbours
    facing = truth[valid[0]][:, 2] > 0.5
    assert float(err.median()) < 0.1 and float(err[facing].max()) < 1.0 and float(err.max()) < 6.0
    assert (got[valid[0]][:, 2] > 0).all()  # they face the camera
    assert torch.allclose(got[valid[0]].norm(dim=-1), torch.ones(int(valid[0].sum())), atol=1e-5)


def test_a_tilted_plane_has_one_normal_and_a_step_breaks_the_surface():
    # the plane z = −0.4 x (view frame), seen through every pixel: planar depth d = D − z along each ray
    d = _rays()
    slope = -0.4
    t = CAMERA.distance / (1.0 + slope * d[..., 0])  # eye + t d on the plane: D − t = slope · t x
    depth = t.float()[None]
    depth[0, :, 70:] += 0.2  # the right part stands back: a step, not a surface
    normals, valid = depth_normals(depth, CAMERA)
    expect = torch.tensor([-slope, 0.0, 1.0]) / math.hypot(slope, 1.0)
    left = valid[0].clone()
    left[:, 69:] = False  # the part moved back is no longer that plane (planar depth + 0.2 bends it)
    got = normals[0].permute(1, 2, 0)[left]
    assert float(_angles_deg(got, expect.expand_as(got)).max()) < 0.05
    assert not valid[0, :, 69:71].any() and valid[0, 5:-5, 60:68].all() and valid[0, 5:-5, 72:120].all()
    assert not valid[0, 0].any() and not valid[0, :, -1].any()  # the border has no central difference
    with pytest.raises(ValueError, match="max_step"):
        depth_normals(depth, CAMERA, max_step=0.0)
    assert MAX_DEPTH_STEP > 0.2 * CAMERA.distance / CAMERA.focal_px(SIZE)  # a 78° slope is one surface


def test_normals_loss_is_one_minus_cosine_over_the_valid_pixels():
    true = torch.zeros(2, 3, 4, 4)
    true[:, 2] = 1.0
    valid = torch.zeros(2, 4, 4, dtype=torch.bool)
    valid[:, 1:3, 1:3] = True
    assert float(normals_loss(5.0 * true, true, valid)) == pytest.approx(0.0, abs=1e-7)  # any length
    assert float(normals_loss(-true, true, valid)) == pytest.approx(2.0)
    side = torch.zeros_like(true)
    side[:, 0] = 1.0
    mixed = torch.where(torch.arange(4).view(1, 1, 1, 4) < 2, side, -true)  # columns 1 | 2 of the valid block
    assert float(normals_loss(mixed, true, valid)) == pytest.approx(1.5)
    assert float(normals_loss(-true, true, torch.zeros_like(valid))) == 0.0
    mixed[:, :, 0, 0] = float("nan")
    with pytest.raises(ValueError):
        normals_loss(mixed, true, valid)


def test_the_normals_head_adds_its_term_in_training_only(tiny_views):
    from training.data.dataset import ViewDataset, find_views

    data = ViewDataset(find_views(tiny_views), TINY)
    batch = {k: torch.stack([data[i][k] for i in range(2)]) for k in data[0]}
    model = GenRe(TINY)
    plain = StageModule(model, "depth", 0.1)
    with_head = StageModule(model, "depth", 0.1, normals_weight=2.0)
    with torch.no_grad():
        plain.eval(), with_head.eval()
        assert torch.equal(plain(batch)[0], with_head(batch)[0])  # validation: the depth loss alone
        plain.train(), with_head.train()
        torch.manual_seed(0)
        base, base_terms = plain(batch)
        torch.manual_seed(0)
        loss, terms = with_head(batch)
        true, valid = depth_normals(batch["depth"], TINY.camera)
        skips, deep = model.depth_net.encode(batch["rgb"])
        own = normals_loss(with_head.aux["normals"](skips, deep), true, valid)
    assert "normals_cos" not in base_terms and valid.any()
    assert 0 < float(terms["normals_cos"]) <= 2
    assert torch.allclose(loss - base, 2.0 * own, rtol=1e-4, atol=1e-6)
    with pytest.raises(ValueError, match="normals_weight"):
        StageModule(model, "joint", 0.1, normals_weight=1.0)


@pytest.mark.slow
def test_the_normals_head_trains_resumes_and_stays_out_of_the_weights(tiny_views, tmp_path):
    run = tmp_path / "run"
    cfg = tiny_train_config("depth", tiny_views, run, steps=2, normals_weight=1.0, checkpoint_every=1)
    train(cfg, TINY)
    state = (run / "depth" / "checkpoint")
    from training.learn.checkpoint import read_state

    tensors, _ = read_state(run / "depth")
    aux = {k for k in tensors if k.startswith("aux.normals.")}
    assert aux and state.is_dir()
    weights = load_model(run / "depth" / "final.safetensors")
    assert not any("normals" in k for k in weights.state_dict())  # the file holds GenRe's nets alone
    train(tiny_train_config("depth", tiny_views, run, steps=4, normals_weight=1.0, checkpoint_every=1), TINY)
    tensors4, meta4 = read_state(run / "depth")
    assert meta4["step"] == 4
    moved = [k for k in aux if not torch.equal(tensors[k], tensors4[k]) and tensors[k].is_floating_point()]
    assert moved  # the resumed run went on training the head it had saved
    assert weights_digest(load_model(run / "depth" / "final.safetensors")) != weights_digest(weights)
