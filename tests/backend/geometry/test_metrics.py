import numpy as np
import pytest
import torch
import trimesh

from genre_backend.config import get_preset
from genre_backend.geometry.metrics import (
    CloudScorer,
    chamfer_distance,
    chamfer_distance_reference,
    depth_over_width,
    grid_thinness,
    thinnest_depth_over_width,
    mesh_chamfer,
    normalize_points,
    sample_surface,
)
from genre_backend.geometry.mesh_voxels import mesh_to_shell


def _sphere_points(n, r, seed):
    p = np.random.default_rng(seed).normal(size=(n, 3))
    return torch.tensor(p / np.linalg.norm(p, axis=1, keepdims=True) * r, dtype=torch.float32)


@pytest.mark.parametrize("method", ["kdtree", "brute"])
def test_identical_clouds_give_zero(method):
    p = _sphere_points(1024, 0.5, 0)
    assert chamfer_distance(p, p, method=method).item() == 0.0


@pytest.mark.parametrize("a, b", [(0.3, 0.5), (0.45, 0.4)])
def test_concentric_spheres_give_twice_the_gap(a, b):
    pa, pb = _sphere_points(20000, a, 1), _sphere_points(20000, b, 2)
    cd = chamfer_distance(pa, pb).item()
    assert cd == pytest.approx(2 * abs(a - b), rel=0.05)
    assert chamfer_distance(pb, pa).item() == pytest.approx(cd, rel=1e-6)


@pytest.mark.parametrize("method", ["kdtree", "brute"])
def test_matches_the_loop_reference_and_batches(method):
    gen = torch.Generator().manual_seed(0)
    a, b = torch.rand(3, 700, 3, generator=gen), torch.rand(3, 500, 3, generator=gen)
    fast = chamfer_distance(a, b, chunk=128, method=method)
    for i in range(3):
        assert fast[i].item() == pytest.approx(chamfer_distance_reference(a[i].numpy(), b[i].numpy()), rel=1e-5)


def test_brute_force_is_differentiable():
    a = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], requires_grad=True)
    b = torch.tensor([[0.0, 0.5, 0.0]])
    cd = chamfer_distance(a, b)  # auto picks the differentiable path
    cd.backward()
    # d/da0 of (|a0-b| + |a1-b|)/2 + min(...) : a0 is the nearest to b, so it gets both terms
    assert a.grad[0, 1].item() == pytest.approx(-0.5 - 1.0)


def test_sampling_is_uniform_by_area_and_deterministic():
    box = trimesh.creation.box(extents=(1.0, 0.2, 0.2))
    p = sample_surface(box.vertices, box.faces, 20000, seed=5)
    assert torch.equal(p, sample_surface(box.vertices, box.faces, 20000, seed=5))
    # the two 0.2×0.2 end caps hold 0.08 of the 0.88 area
    caps = (p[:, 0].abs() > 0.5 - 1e-6).float().mean().item()
    assert caps == pytest.approx(0.08 / 0.88, abs=0.01)
    with pytest.raises(ValueError, match="area"):
        sample_surface(np.zeros((3, 3)), np.array([[0, 1, 2]]), 10)


def test_normalisation_removes_translation_and_scale():
    box = trimesh.creation.box(extents=(0.4, 0.2, 0.1))
    moved = box.copy()
    moved.apply_scale(3.0)
    moved.apply_translation((0.3, -0.1, 0.2))
    p = normalize_points(sample_surface(moved.vertices, moved.faces, 2000))
    assert (p.max(0).values - p.min(0).values).max().item() == pytest.approx(1.0)
    assert mesh_chamfer((box.vertices, box.faces), (moved.vertices, moved.faces), 2048) < 0.1
    assert mesh_chamfer((box.vertices, box.faces), (moved.vertices, moved.faces), 2048, normalize=False) > 0.3


def test_threshold_sweep_covers_the_configured_range():
    from genre_backend.geometry.mesh_voxels import voxels_to_mesh

    g = get_preset("default").geometry
    assert g.thresholds() == [0.3, 0.35, 0.4, 0.45, 0.5, 0.55, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9]
    assert get_preset("paper").geometry.thresholds() == [0.3, 0.35, 0.4, 0.45, 0.5, 0.55, 0.6, 0.65, 0.7]
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.35)
    shell = mesh_to_shell(torch.tensor(sphere.vertices), torch.tensor(sphere.faces), 32, 1).float()
    prob = shell * 0.9 + 0.05  # 0.95 on the shell, 0.05 elsewhere
    result = {t: mesh_chamfer(voxels_to_mesh(prob, t), (sphere.vertices, sphere.faces), 1024, normalize=False) for t in g.thresholds()}
    # a binary shell's two sheets tighten toward the shell's voxel centres as the threshold rises
    assert all(0.0 < v < 0.2 for v in result.values())
    assert result[0.9] < result[0.7] < result[0.5] < result[0.3]


def _random_rotation(seed: int) -> torch.Tensor:
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64))
    return q * torch.sign(torch.det(q))


def test_depth_over_width_of_boxes_and_a_sphere():
    """A lying card's height over its caliper width, in any pose; turned on its side; a sphere's is 1."""
    card = trimesh.creation.box(extents=(0.8, 0.6, 0.08))
    pts = torch.from_numpy(trimesh.sample.sample_surface(card, 20000, seed=1)[0])
    rot = _random_rotation(5)
    posed = pts @ rot.T
    up = rot[:, 2]
    assert depth_over_width(posed, up) == pytest.approx(0.08 / 1.0, rel=0.03)  # the 0.8 x 0.6 card's diagonal is 1
    assert depth_over_width(posed, -3 * up) == pytest.approx(depth_over_width(posed, up))  # sign and length of up
    # on its long side: height 0.8 over the caliper width of a 0.6 x 0.08 rectangle (its diagonal 0.605)
    assert depth_over_width(posed, rot[:, 0]) == pytest.approx(0.8 / np.hypot(0.6, 0.08), rel=0.04)
    sphere = torch.from_numpy(trimesh.sample.sample_surface(trimesh.creation.icosphere(4), 20000, seed=2)[0])
    assert depth_over_width(sphere, torch.tensor([0.3, -0.2, 0.9])) == pytest.approx(1.0, rel=0.03)
    with pytest.raises(ValueError, match="zero width"):
        depth_over_width(torch.zeros(10, 3), torch.tensor([0.0, 0.0, 1.0]))


def test_thinnest_depth_over_width_finds_the_flat_axis_in_any_pose():
    """A disc 1 across and 0.1 thick reads 0.1 however it is turned (its up unknown); the card, its height over
    its diagonal; a sphere, 1; and a rod 1 x 0.2 x 0.1, its thinnest side over the diagonal of the other two."""
    rot = _random_rotation(7)
    disc = trimesh.creation.cylinder(radius=0.5, height=0.1, sections=128)
    card = trimesh.creation.box(extents=(0.8, 0.6, 0.08))
    rod = trimesh.creation.box(extents=(1.0, 0.2, 0.1))
    for mesh, want, rel in ((disc, 0.1, 0.04), (card, 0.08, 0.04), (rod, 0.1 / np.hypot(1.0, 0.2), 0.04)):
        pts = torch.from_numpy(trimesh.sample.sample_surface(mesh, 20000, seed=3)[0]) @ rot.T
        assert thinnest_depth_over_width(pts) == pytest.approx(want, rel=rel)
    sphere = torch.from_numpy(trimesh.sample.sample_surface(trimesh.creation.icosphere(4), 20000, seed=2)[0])
    assert thinnest_depth_over_width(sphere) == pytest.approx(1.0, rel=0.04)


def test_grid_thinness_reads_a_voxel_plate_and_ball():
    """The voxel centres at the level: a ball of radius 20 voxels reads about 1; a disc 48 voxels across and 4 thick,
    its centres' spread (3 voxels) over their width (47), whichever axis it lies on; too few voxels: nan."""
    n = 64
    c = torch.arange(n).double() + 0.5 - n / 2
    x, y, z = torch.meshgrid(c, c, c, indexing="ij")
    ball = ((x**2 + y**2 + z**2) < 20**2).float()
    assert grid_thinness(ball, 0.5)[0] == pytest.approx(1.0, abs=0.05) and grid_thinness(ball, 0.5)[1] == int(ball.sum())
    for a, b, t in ((x, z, y), (y, z, x)):
        disc = (((a**2 + b**2) < 24**2) & (t.abs() < 2.5)).float() * 0.8
        assert grid_thinness(disc, 0.5)[0] == pytest.approx(3 / 47, rel=0.05)
        assert np.isnan(grid_thinness(disc, 0.9)[0]) and grid_thinness(disc, 0.9)[1] == 0  # below the level: none


def test_cloud_scorer_reports_depth_over_width_with_an_up():
    card = trimesh.creation.box(extents=(0.8, 0.6, 0.08))
    gt = torch.from_numpy(trimesh.sample.sample_surface(card, 10000, seed=1)[0]).float()
    blob = torch.from_numpy(trimesh.sample.sample_surface(trimesh.creation.icosphere(3), 10000, seed=3)[0]).float() * 0.5
    up = torch.tensor([0.0, 0.0, 1.0])
    scorer = CloudScorer(gt[:1024], gt, up=up)
    assert scorer.dw_true == pytest.approx(0.08, rel=0.05)
    assert scorer.metrics(blob[:1024], blob)["dw"] == pytest.approx(1.0, rel=0.05)
    assert "dw" not in CloudScorer(gt[:1024], gt).metrics(blob[:1024], blob)


def test_chamfer_parts_add_up_to_the_chamfer_distance():
    from genre_backend.geometry.metrics import chamfer_parts

    gen = torch.Generator().manual_seed(7)
    a, b = torch.rand(300, 3, generator=gen), torch.rand(250, 3, generator=gen) * 1.3
    a_seen, b_seen = a[:, 2] > 0.5, b[:, 0] < 0.4
    parts = chamfer_parts(a, b, a_seen, b_seen)
    total = chamfer_distance_reference(normalize_points(a).numpy(), normalize_points(b).numpy())
    assert sum(parts.values()) == pytest.approx(total, rel=1e-6)
    # each direction's two parts: that direction's mean nearest-neighbour distance
    an, bn = normalize_points(a).double(), normalize_points(b).double()
    d_ab = torch.cdist(an, bn).min(dim=1).values
    assert parts["pred_seen"] == pytest.approx(float(d_ab[a_seen].sum() / len(a)), rel=1e-9)
    assert parts["pred_hidden"] == pytest.approx(float(d_ab[~a_seen].sum() / len(a)), rel=1e-9)
    everything = chamfer_parts(a, b, torch.ones(300, dtype=torch.bool), torch.ones(250, dtype=torch.bool))
    assert everything["pred_hidden"] == 0 and everything["gt_hidden"] == 0
    with pytest.raises(ValueError, match="pred_seen"):
        chamfer_parts(a, b, a_seen[:10], b_seen)
