"""``genre train session``: the schedule, resuming bit for bit, the distance-grid cache, and the fast CPU path
against the plain fp32 one."""

from __future__ import annotations

import csv
import math

import pytest
import torch
import trimesh

from genre_backend.nets.model import GenRe, load_model, save_model
from support.tiny_data import TINY, write_manifest


@pytest.fixture(scope="module")
def prim_pack(tmp_path_factory):
    """A pack of three analytic shapes (no rendering needed) and weights of the tiny preset to start from."""
    from training.data.pack import build_pack

    tmp = tmp_path_factory.mktemp("session")
    shapes = {"box": trimesh.creation.box(extents=(0.6, 0.3, 0.4)),
              "cyl": trimesh.creation.cylinder(radius=0.25, height=0.5, sections=16),
              "ball": trimesh.creation.icosphere(subdivisions=2, radius=0.35)}
    manifest = write_manifest(tmp, {k: (m, "product-train") for k, m in shapes.items()})
    build_pack(manifest, tmp / "pack", max_faces=4000)
    torch.manual_seed(0)
    model = GenRe(TINY)
    save_model(model, tmp / "init.safetensors")
    return tmp / "pack", tmp / "init.safetensors"


def test_the_schedule_warms_up_then_follows_a_cosine_then_stays_flat():
    from training.learn.recipe import BurstRecipe
    from training.learn.session import lr_at

    r = BurstRecipe(name="t", description="", lr=1e-3, lr_final=0.1, total_steps=1000, warmup_steps=10)
    assert lr_at(r, 0) == pytest.approx(1e-4)  # (0 + 1) / 10 of the way up
    assert lr_at(r, 9) == pytest.approx(1e-3 * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * 9 / 1000))))
    assert lr_at(r, 500) == pytest.approx(1e-3 * (0.1 + 0.9 * 0.5))  # half-way down the cosine
    assert lr_at(r, 1000) == pytest.approx(1e-4) and lr_at(r, 5000) == pytest.approx(1e-4)


def _spec(pack, init, out, **kw):
    from training.learn.session import SessionSpec

    return SessionSpec(pack=str(pack), out=str(out), init=str(init), batch_size=2, threads=1, log_every=1,
                       grid_cache=str(out / "grids"), **kw)


def test_a_session_cut_in_two_ends_where_an_unbroken_one_does(prim_pack, tmp_path):
    from training.learn.session import _load_state, run_session

    pack, init = prim_pack
    run_session(_spec(pack, init, tmp_path / "whole", max_steps=4), say=lambda m: None)
    run_session(_spec(pack, init, tmp_path / "cut", max_steps=2), say=lambda m: None)
    summary = run_session(_spec(pack, init, tmp_path / "cut", max_steps=4), say=lambda m: None)
    assert summary["step"] == 4 and summary["samples"] == 8
    a = _load_state(tmp_path / "whole" / "inpaint")[0].state_dict()
    b = _load_state(tmp_path / "cut" / "inpaint")[0].state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    # the weights file beside the state is the same model in float16 storage
    w = load_model(tmp_path / "cut" / "inpaint" / "weights.safetensors").state_dict()
    assert all(torch.allclose(w[k].float(), b[k].float(), rtol=1e-3, atol=1e-4) for k in b if b[k].is_floating_point())
    # the nets it does not train are the init's, the inpainting net moved
    ref = load_model(init).state_dict()
    moved = [k for k in a if k.startswith("inpaint_net.") and a[k].is_floating_point() and not torch.equal(a[k], ref[k])]
    assert moved
    assert all(torch.equal(a[k], ref[k]) for k in a if k.startswith(("refiner.", "depth_net.")))
    with open(tmp_path / "cut" / "inpaint" / "log.csv") as fh:
        assert [int(r["step"]) for r in csv.DictReader(fh)] == [1, 2, 3, 4]


def test_the_distance_grid_cache_returns_what_it_would_make(prim_pack, tmp_path):
    from training.data.pack import read_pack
    from training.learn.burst import ViewMaker, object_distance_grid

    pack = read_pack(prim_pack[0])
    first = ViewMaker(pack, TINY, torch.device("cpu"), grid_factor=2, grid_cache=tmp_path)
    files = sorted(tmp_path.rglob("*.npz"))
    assert len(files) == len(pack)
    again = ViewMaker(pack, TINY, torch.device("cpu"), grid_factor=2, grid_cache=tmp_path)
    assert torch.equal(first.grids, again.grids)
    v, f = pack.mesh(1)
    direct = object_distance_grid(torch.from_numpy(v), torch.from_numpy(f), TINY.geometry, 2)
    assert torch.equal(direct, again.grids[1]) and int((direct > 0).sum()) > 100
    # a grid made for another geometry is never read: its folder's name differs
    import dataclasses

    other = dataclasses.replace(TINY, geometry=dataclasses.replace(TINY.geometry, distance_band=TINY.geometry.distance_band + 1))
    ViewMaker(pack, other, torch.device("cpu"), grid_factor=2, grid_cache=tmp_path)
    assert len({p.parent for p in tmp_path.rglob("*.npz")}) == 2


@pytest.mark.parametrize("fast", ["channels-last", "channels-last+bf16",
                                  pytest.param("channels-last+compile", marks=pytest.mark.slow)])
def test_the_fast_cpu_path_follows_the_plain_fp32_path(prim_pack, fast):
    """Each fast way of the CPU (burst.WAYS: channels-last; with bf16 autocast, as CPU_SPEED has it where oneDNN runs
    bf16 natively; or with the refiner compiled) against fp32 contiguous: the same losses over the first five steps
    of training from the same weights on the same samples, within 5 %. At the first step (the same weights, one
    pass) within 1e-3 in fp32 (measured 2e-4 with channels-last: other convolution kernels, other rounding), 1e-2
    under bf16 (measured 1.4e-3 on a native-bf16 EPYC: bf16 keeps 8 bits of mantissa); Adam's steps amplify the
    difference in small gradients (by the fifth: 1.7 % channels-last on the Xeon, 3.3 % compiled on the AVX-512
    EPYC)."""
    from training.data.pack import read_pack
    from training.learn.burst import REFERENCE_SPEED, Speed, ViewMaker, _step_loss, apply_speed
    from training.learn.recipe import get_burst_recipe

    assert Speed.from_way(fast).fused_adam and not REFERENCE_SPEED.fused_adam
    recipe = get_burst_recipe("session")
    pack = read_pack(prim_pack[0])
    maker = ViewMaker(pack, TINY, torch.device("cpu"), grid_factor=2)
    curves = {}
    fast_speed = Speed.from_way(fast)
    for name, speed in (("plain", REFERENCE_SPEED), ("fast", fast_speed)):
        model = apply_speed(load_model(prim_pack[1]), speed)
        model.train()
        params = [p for n in (model.inpaint_net, model.refiner) for p in n.parameters()]
        opt = speed.optimiser(params, lr=1e-3)  # the fast ways' Adam is fused, the reference's a loop over tensors
        losses = []
        for k in range(5):
            gen = torch.Generator().manual_seed(k)
            shape, az, el = maker.draw(gen, 2, recipe)
            loss, _ = _step_loss(model, maker.make(shape, az, el, recipe.depth_noise, gen), recipe, speed=speed)
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(float(loss.detach()))
        curves[name] = losses
        assert not any("_orig_mod" in k for k in model.state_dict())  # a compiled net saves under its own names
    assert all(math.isfinite(x) for x in curves["fast"])
    first = 1e-2 if fast_speed.refiner_bf16 else 1e-3
    assert abs(curves["plain"][0] - curves["fast"][0]) <= first * curves["plain"][0]  # the same weights, one pass
    for a, b in zip(curves["plain"], curves["fast"]):
        assert abs(a - b) <= 0.05 * abs(a), curves
    assert curves["plain"][-1] < curves["plain"][0]  # and the steps do train


def test_the_cpu_distance_grid_matches_the_pair_tests():
    """libigl's AABB tree (the CPU's way) and the exact pair tests (any device) give the same grid."""
    from training.learn.burst import object_distance_grid

    mesh = trimesh.creation.annulus(r_min=0.15, r_max=0.3, height=0.2, sections=20)
    v, f = torch.from_numpy(mesh.vertices).float(), torch.from_numpy(mesh.faces)
    a = object_distance_grid(v, f, TINY.geometry, 2, exact="igl")
    b = object_distance_grid(v, f, TINY.geometry, 2, exact="torch")
    assert int((b > 0).sum()) > 500
    assert int((a.int() - b.int()).abs().max()) <= 1  # uint8 steps: float32 against float64 rounding at most


def test_a_bad_session_spec_is_refused_with_its_field():
    from training.learn.session import SessionSpec

    with pytest.raises(ValueError, match="nets"):
        SessionSpec(pack="p", out="o", nets="depth")
    with pytest.raises(ValueError, match="hours"):
        SessionSpec(pack="p", out="o", hours=-1.0)
    with pytest.raises(ValueError, match="batch_size"):
        SessionSpec(pack="p", out="o", batch_size=0)


def test_exact_view_targets_match_the_resampled_grid(prim_pack):
    """The CPU's per-view exact targets (libigl) against the burst's resampled object-frame grid: the same band."""
    from training.data.pack import read_pack
    from training.learn.burst import ViewMaker

    pack = read_pack(prim_pack[0])
    grid = ViewMaker(pack, TINY, torch.device("cpu"), grid_factor=2)
    exact = ViewMaker(pack, TINY, torch.device("cpu"), targets="exact")
    args = (torch.tensor([0, 1, 2]), torch.tensor([30.0, 200.0, 95.0]), torch.tensor([20.0, 70.0, -5.0]))
    a, b = grid.make(*args)["voxels"], exact.make(*args)["voxels"]
    band = (a > 0) | (b > 0)
    assert int(band.sum()) > 300
    assert float((a - b)[band].abs().mean()) < 0.05
    iou = ((a > 0.45) & (b > 0.45)).sum() / ((a > 0.45) | (b > 0.45)).sum()
    assert float(iou) > 0.9


def _write_bank_views(pack_dir, folder, config, poses, seed=0):
    """Views of the pack's shapes written in the renders' format without Blender: each one's depth and mask are the
    pack mesh's own at the pose (what a render of it measures), its picture random, its camera the frame's."""
    import numpy as np

    from genre_backend.frame import camera_rotation
    from training.data.pack import read_pack
    from training.data.views import write_view
    from training.learn.burst import ViewMaker

    pack = read_pack(pack_dir)
    maker = ViewMaker(pack, config, torch.device("cpu"), voxels=False)
    rng = np.random.default_rng(seed)
    s = config.geometry.image_size
    for k, (i, az, el) in enumerate(poses):
        made = maker.make(torch.tensor([i]), torch.tensor([az]), torch.tensor([el]))
        rot = camera_rotation(az, el, dtype=torch.float64)[0].tolist()
        (folder / pack.ids[i]).mkdir(parents=True, exist_ok=True)
        write_view(folder / pack.ids[i], k, rng.integers(0, 256, (s, s, 3), dtype=np.uint8),
                   made["true_depth"][0].numpy(), made["mask"][0].numpy().astype(np.float32),
                   {"shape_id": pack.ids[i], "azimuth_deg": az, "elevation_deg": el, "rotation_cam_to_obj": rot})
    return pack


def test_rendered_views_give_the_depth_nets_prediction_and_the_targets_at_their_pose(prim_pack, tmp_path):
    """--views: a bank sample's depth is the depth net's masked prediction on its picture, its full map and voxel
    target those of its shape at its pose; the predictions are cached per depth net."""
    import numpy as np

    from training.data.views import load_view
    from training.learn import view_bank
    from training.learn.recipe import get_burst_recipe
    from training.learn.session import SampleStream

    pack_dir, init = prim_pack
    model = load_model(init)
    poses = [(0, 30.0, 80.0), (1, 200.0, -5.0), (2, 95.0, 45.0)]
    pack = _write_bank_views(pack_dir, tmp_path / "views", model.config, poses)
    bank = view_bank.load_view_bank(tmp_path / "views", list(pack.ids), model, torch.device("cpu"), say=lambda m: None)
    assert len(bank) == 3
    by_key = dict(zip(bank.keys, range(3)))
    for k, (i, az, el) in enumerate(poses):
        j = by_key[f"{pack.ids[i]}/{k:03d}"]
        assert int(bank.shape[j]) == i and float(bank.azimuth[j]) == pytest.approx(az) and float(bank.elevation[j]) == pytest.approx(el)
        v = load_view(tmp_path / "views" / pack.ids[i], k)
        with torch.no_grad():
            pred = model.depth_net(torch.from_numpy(v["rgb"]).permute(2, 0, 1)[None].float() / 255)["depth"][0]
        mask = torch.from_numpy(v["mask"] > 0.5)
        assert mask.any() and torch.allclose(bank.depth[j].float(), torch.where(mask, pred, 0.0), atol=2e-3)
        assert (bank.depth[j][~mask] == 0).all()
    # the second load reads the cache; another depth net makes its own
    cached = list((tmp_path / "views").glob("depth_predictions-*.npz"))
    assert len(cached) == 1
    again = view_bank.load_view_bank(tmp_path / "views", list(pack.ids), model, torch.device("cpu"), say=lambda m: None)
    assert torch.equal(again.depth, bank.depth)
    other = load_model(init)
    with torch.no_grad():
        next(other.depth_net.parameters()).add_(0.1)
    view_bank.load_view_bank(tmp_path / "views", list(pack.ids), other, torch.device("cpu"), say=lambda m: None)
    assert len(list((tmp_path / "views").glob("depth_predictions-*.npz"))) == 2
    # every fresh sample from the bank (bank_share 1): its depth is a bank view's, its targets the maker's at that pose
    from training.learn.burst import ViewMaker
    from dataclasses import replace

    maker = ViewMaker(pack, model.config, torch.device("cpu"), voxels=True, targets="exact")
    recipe = replace(get_burst_recipe("session-bank"), bank_share=1.0, reuse=1, sph_teacher=0.0)
    stream = SampleStream(maker, model, recipe, 2, seed=3, inpaint_only=False, bank=bank)
    sample = stream.make(0)
    for b in range(2):
        j = next(j for j in range(3) if torch.equal(sample["depth"][b], bank.depth[j].float()))
        ref = maker.make(bank.shape[j:j + 1], bank.azimuth[j:j + 1], bank.elevation[j:j + 1])
        assert torch.allclose(sample["full_sph"][b], ref["full_sph"][0]) and torch.allclose(sample["voxels"][b], ref["voxels"][0])
        assert torch.allclose(sample["partial"][b], model.partial_sph(bank.depth[j:j + 1].float())[0])
    assert np.isfinite(sample["voxels"].numpy()).all()


def test_a_view_whose_camera_disagrees_with_its_angles_is_refused(prim_pack, tmp_path):
    import json

    from training.learn.view_bank import load_view_bank

    pack_dir, init = prim_pack
    model = load_model(init)
    pack = _write_bank_views(pack_dir, tmp_path / "views", model.config, [(0, 10.0, 20.0)])
    meta_path = tmp_path / "views" / pack.ids[0] / "view_000.json"
    meta = json.loads(meta_path.read_text())
    meta["azimuth_deg"] = 40.0
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="recorded rotation"):
        load_view_bank(tmp_path / "views", list(pack.ids), model, torch.device("cpu"), say=lambda m: None)
    with pytest.raises(FileNotFoundError, match="no complete rendered view"):
        load_view_bank(tmp_path / "views", ["another"], model, torch.device("cpu"), say=lambda m: None)


def test_views_and_the_recipes_bank_share_go_together():
    from training.learn.session import SessionSpec

    with pytest.raises(ValueError, match="names no renders"):
        SessionSpec(pack="p", out="o", nets="both", recipe="session-bank")
    with pytest.raises(ValueError, match="bank_share > 0"):
        SessionSpec(pack="p", out="o", nets="both", recipe="session-both", views="v")
