import math

import numpy as np
import pytest
import torch
import trimesh

from genre_backend.geometry import spherical as sph
from genre_backend.config import CameraConfig, get_preset
from genre_backend.geometry.mesh_voxels import voxels_to_mesh
from genre_backend.geometry.metrics import sample_surface
from genre_backend.geometry.analytic import sphere_depth, sphere_silhouette_radius_px

CAM = CameraConfig()


def test_direction_convention():
    d = sph.sph_directions(8, 16, dtype=torch.float64)
    assert torch.allclose(torch.linalg.vector_norm(d, dim=-1), torch.ones(8, 16, dtype=torch.float64))
    eq = 3  # row just above the equator
    assert d[eq, 0, 2] < -0.9  # column 0: away from the camera (seam behind the object)
    assert d[eq, 8, 2] > 0.9  # column W/2: toward the camera
    assert d[eq, 4, 0] < -0.9  # column W/4: left
    assert d[0, 5, 1] > 0.9  # row 0: up
    pix = sph.directions_to_pixels(d, 8, 16)
    rows, cols = torch.meshgrid(torch.arange(8.0), torch.arange(16.0), indexing="ij")
    assert torch.allclose(pix[..., 0], rows.double(), atol=1e-9)
    assert torch.allclose(pix[..., 1], cols.double(), atol=1e-9)


DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device"))]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_raycast_matches_reference_on_random_triangles(seed, device):
    gen = torch.Generator().manual_seed(seed)
    tri = ((torch.rand(60, 3, 3, generator=gen, dtype=torch.float64) - 0.5) * 1.4)
    tri[:20] = tri[:20] * 0.1 + tri[:20, :1] * 0.9  # some small triangles
    batch = torch.randint(0, 2, (60,), generator=gen)
    fast = sph.raycast_triangles(tri.to(device), batch.to(device), 2, 12, 20, chunk_pairs=500).cpu()
    for b in range(2):
        ref = sph.raycast_triangles_reference(tri[batch == b].numpy(), 12, 20)
        assert np.abs(fast[b].numpy() - ref).max() < 1e-9
        assert (ref < 1).sum() > 10


def test_full_map_of_a_sphere_mesh_is_one_minus_r():
    r = 0.4
    mesh = trimesh.creation.icosphere(subdivisions=6, radius=r)
    s = sph.mesh_to_sph(torch.tensor(mesh.vertices), torch.tensor(mesh.faces), 64)
    assert s.shape == (64, 64)
    assert (s - (1 - r)).abs().max().item() < 1e-4


def test_full_map_of_an_open_mesh():
    # an open hemisphere (z > 0 half of a sphere): rays toward +z hit, rays toward -z do not
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=0.3)
    keep = mesh.triangles_center[:, 2] > 0
    mesh.update_faces(keep)
    s = sph.mesh_to_sph(torch.tensor(mesh.vertices), torch.tensor(mesh.faces), 32)
    d = sph.sph_directions(32, dtype=torch.float64)
    assert (s[d[..., 2] > 0.2] < 0.72).all()
    assert (s[d[..., 2] < -0.2] == 1.0).all()


@pytest.mark.parametrize("preset", ["default", "paper"])
def test_partial_map_of_a_sphere(preset):
    g = get_preset(preset).geometry
    r = 0.4
    depth = sphere_depth(CAM, g.image_size, r).float()
    s = sph.depth_to_sph(depth, CAM, g.sph_size, g.depth_edge_max_ratio)[0]
    d = sph.sph_directions(g.sph_size, dtype=torch.float64)
    # the surface point of each direction, and how far inside the silhouette it projects
    f = CAM.focal_px(g.image_size)
    p = d * r
    rho = f * torch.sqrt(p[..., 0] ** 2 + p[..., 1] ** 2) / (CAM.distance - p[..., 2])
    inside_px = sphere_silhouette_radius_px(CAM, g.image_size, r) - rho
    visible = d[..., 2] > r / CAM.distance  # the cap seen from the camera
    sure = visible & (inside_px > 2.0)  # well sampled by the depth pixels
    assert sure.sum() > 0.1 * g.sph_size**2
    assert (s[sure] - (1 - r)).abs().max().item() < 5e-4  # flat facets between pixels: sagitta only
    assert (s[~visible] == 1.0).all()
    # the visible cap is centred in the map
    hit = (s < 1).double()
    rows, cols = torch.meshgrid(torch.arange(g.sph_size.__float__()), torch.arange(g.sph_size.__float__()), indexing="ij")
    assert (hit * rows.double()).sum() / hit.sum() == pytest.approx((g.sph_size - 1) / 2, abs=0.01)
    assert (hit * cols.double()).sum() / hit.sum() == pytest.approx(g.sph_size / 2, abs=0.01)


def test_partial_map_is_differentiable_in_depth():
    depth = sphere_depth(CAM, 32, 0.4).requires_grad_(True)
    s = sph.depth_to_sph(depth, CAM, 16, 10.0)
    hit = s < 1
    assert hit.any()
    s[hit].sum().backward()
    assert depth.grad.abs().sum() > 0
    # moving the whole surface away from the camera by δ moves hits inward: s grows for the front cap
    eps = 1e-4
    s2 = sph.depth_to_sph((depth + eps).detach(), CAM, 16, 10.0)
    front = hit & (sph.sph_directions(16, dtype=torch.float64)[..., 2] > 0.95)[None]
    assert ((s2 - s.detach())[front] > 0).all()


@pytest.mark.parametrize("preset", ["default", "paper"])
def test_sphere_map_to_voxels_to_mesh(preset):
    g = get_preset(preset).geometry
    r = 0.4
    full = torch.full((1, g.sph_size, g.sph_size), 1 - r)
    vox = sph.sph_to_voxels(full, g.voxel_size, g.sph_nohit_min, g.sph_supersample)
    verts, faces = voxels_to_mesh(vox[0, 0], g.default_threshold)
    # Chamfer against the exact sphere with dense sampling (so sampling noise stays far below a voxel)
    pts = sample_surface(verts, faces, 200_000).double().numpy()
    pred_to_true = np.abs(np.linalg.norm(pts, axis=1) - r).mean()
    from scipy.spatial import cKDTree

    true = np.random.default_rng(0).normal(size=(50_000, 3))
    true = true / np.linalg.norm(true, axis=1, keepdims=True) * r
    true_to_pred = cKDTree(pts).query(true)[0].mean()
    assert (pred_to_true + true_to_pred) * g.voxel_size < 1.5


def test_no_hit_pixels_are_masked_out():
    s = torch.ones(1, 8, 8)
    s[0, 2:4, 3:5] = 0.6
    pts, mask = sph.sph_to_points(s)
    assert mask.sum() == 4
    assert torch.allclose(torch.linalg.vector_norm(pts[mask], dim=-1), torch.full((4,), 0.4))
    vox = sph.sph_to_voxels(s, 16)
    assert vox[0, 0, 8, 8, 8] == 0  # nothing piled up at the centre voxel
    # supersampled: only fine pixels between hit pixels survive, all at the hit radius
    pts, mask = sph.sph_to_points(s, supersample=2)
    assert 0 < mask.sum() < 16
    assert torch.allclose(torch.linalg.vector_norm(pts[mask], dim=-1), torch.full((int(mask.sum()),), 0.4))


def test_resample_matches_bilinear_reference():
    gen = torch.Generator().manual_seed(3)
    s = torch.rand(1, 6, 10, generator=gen, dtype=torch.float64)
    fine = sph.resample_sph(s, 2)
    assert fine.shape == (1, 12, 20)
    h, w = 6, 10
    for i in range(12):
        for j in range(20):
            r = min(max((i + 0.5) / 2 - 0.5, 0.0), h - 1.0)
            c = j / 2
            r0, c0 = int(math.floor(r)), int(math.floor(c))
            r1, c1 = min(r0 + 1, h - 1), (c0 + 1) % w
            a, b = r - r0, c - c0
            v = (1 - a) * ((1 - b) * s[0, r0, c0] + b * s[0, r0, c1]) + a * ((1 - b) * s[0, r1, c0] + b * s[0, r1, c1])
            assert fine[0, i, j].item() == pytest.approx(v.item(), abs=1e-12)


def test_padding_wraps_azimuth_and_replicates_poles():
    x = torch.arange(2 * 3 * 4 * 6, dtype=torch.float32).reshape(2, 3, 4, 6)
    p = sph.pad_sph(x, 2)
    assert p.shape == (2, 3, 8, 10)
    assert torch.equal(p[..., 2:6, :2], x[..., :, -2:])  # left pad = last columns
    assert torch.equal(p[..., 2:6, -2:], x[..., :, :2])  # right pad = first columns
    assert torch.equal(p[..., 0, 2:8], x[..., 0, :])  # top pad replicates row 0
    assert torch.equal(p[..., 7, 2:8], x[..., -1, :])
    assert torch.equal(sph.crop_sph(p, 2), x)
    with pytest.raises(ValueError, match="pad"):
        sph.pad_sph(x, -1)


def test_rejects_bad_inputs():
    with pytest.raises(ValueError, match="triangles"):
        sph.raycast_triangles(torch.zeros(4, 3), torch.zeros(4, dtype=torch.int64), 1, 8)
    with pytest.raises(ValueError, match="batch_index"):
        sph.raycast_triangles(torch.zeros(4, 3, 3), torch.zeros(4, dtype=torch.int64) + 3, 1, 8)
    with pytest.raises(ValueError, match="faces"):
        sph.mesh_to_sph(torch.zeros(3, 3), torch.tensor([[0, 1, 5]]), 8)
    with pytest.raises(ValueError, match="NaN"):
        sph.sph_to_points(torch.full((1, 4, 4), float("nan")))


def test_cached_directions_made_during_inference_still_work_with_autograd():
    """A reconstruction (inference mode) and then training in one process: the cached directions must not be
    inference tensors (CI saw 'Inference tensors cannot be saved for backward')."""
    from genre_backend.geometry.spherical import sph_directions, sph_to_points

    with torch.inference_mode():
        sph_directions(37, 41)
    sph = torch.full((1, 37, 41), 0.5, requires_grad=True)
    points, _ = sph_to_points(sph, supersample=1)
    points.sum().backward()
    assert sph.grad is not None and torch.isfinite(sph.grad).all()


def test_mirror_sph_and_mirror_voxels_are_the_reflected_scene():
    """x → −x of the view frame: the map of the reflected mesh is mirror_sph of the mesh's map, and the
    voxels of the reflected points are mirror_voxels of the points' voxels (both exact)."""
    import trimesh

    from genre_backend.geometry.spherical import mesh_to_sph, mirror_sph
    from genre_backend.geometry.voxels import mirror_voxels, points_to_voxels

    mesh = trimesh.creation.box(extents=(0.4, 0.3, 0.2))
    mesh.apply_translation((0.15, 0.05, -0.07))  # off-centre: not its own mirror image (no face through the origin)
    flip = torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    verts = torch.tensor(mesh.vertices)
    faces = torch.tensor(mesh.faces)
    plain = mesh_to_sph(verts, faces, 32)
    reflected = mesh_to_sph(verts * flip, faces.flip(-1), 32)
    assert (plain - reflected).abs().max() > 0.1  # the two maps differ ...
    assert torch.allclose(mirror_sph(plain), reflected, atol=1e-9)  # ... by the mirror exactly
    assert torch.equal(mirror_sph(mirror_sph(plain)), plain)
    points = torch.rand(2, 500, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) - 0.5
    grid = points_to_voxels(points, 16)
    assert torch.allclose(mirror_voxels(grid), points_to_voxels(points * flip, 16), atol=1e-9)
    with pytest.raises(ValueError, match="N, N, N"):
        mirror_voxels(torch.zeros(4, 4, 5))


@pytest.mark.parametrize("spread,offset", [(0, 0.0), (1, 0.7), (2, 2.0)])
def test_hull_ramp_matches_its_reference(spread, offset):
    gen = torch.Generator().manual_seed(spread)
    s = torch.rand((2, 8, 12), generator=gen) * 0.6 + 0.3
    s[0, 2, 3] = s[0, 0, 11] = s[0, 7, 0] = sph.NO_HIT  # no-hit pixels, one at each pole row and at the seam
    s[1, :2] = sph.NO_HIT
    fast = sph.sph_hull_ramp(s, 7, spread=spread, width=1.5, offset=offset)
    assert fast.shape == (2, 1, 7, 7, 7) and fast.dtype == torch.float32
    assert (fast - sph.sph_hull_ramp_reference(s, 7, spread=spread, width=1.5, offset=offset)).abs().max() < 1e-5


def test_hull_of_a_sphere_map_is_the_ball():
    n, r = 32, 0.3
    s = sph.mesh_to_sph(*(torch.tensor(a) for a in (trimesh.creation.icosphere(5, radius=r).vertices,
                                                   trimesh.creation.icosphere(5, radius=r).faces)), 64)[None]
    ramp = sph.sph_hull_ramp(s, n, spread=0)[0, 0]
    c = (torch.arange(n) + 0.5) / n - 0.5
    rho = torch.linalg.vector_norm(torch.stack(torch.meshgrid(c, c, c, indexing="ij"), dim=-1), dim=-1)
    want = (0.5 + (r - rho) * n).clamp(0, 1)  # one voxel wide, 0.5 on the sphere
    assert (ramp - want).abs().max() < 0.02
    moved = sph.sph_hull_ramp(s, n, spread=0, offset=2.0)[0, 0]  # the ball two voxels larger
    assert (moved - (0.5 + (r + 2.0 / n - rho) * n).clamp(0, 1)).abs().max() < 0.02
    assert sph.sph_hull_ramp(torch.full((1, 16, 16), sph.NO_HIT), 8).abs().max() == 0  # no surface: nothing kept


def test_hull_of_a_lying_plate_trims_a_slab_to_the_plate():
    """The true map of a thin box (a plate lying in the view's x–z plane) bounds it: a slab ten times thicker around
    it, capped by the map's hull, keeps the plate and loses what lies more than a few voxels above or below it."""
    n = 64
    plate = trimesh.creation.box(extents=(0.6, 0.03, 0.5))
    s = sph.mesh_to_sph(torch.tensor(plate.vertices), torch.tensor(plate.faces), 64)[None]
    c = (torch.arange(n) + 0.5) / n - 0.5
    x, y, z = torch.meshgrid(c, c, c, indexing="ij")
    slab = ((x.abs() < 0.3) & (y.abs() < 0.15) & (z.abs() < 0.25)).float()
    for spread in (0, 1):
        kept = torch.minimum(slab, sph.sph_hull_ramp(s, n, spread=spread)[0, 0])
        inside = (x.abs() < 0.27) & (y.abs() < 0.01) & (z.abs() < 0.22)  # the plate, a voxel in from its faces
        assert float(kept[inside].min()) > 0.5
        far = y.abs() > 0.015 + (2 + 3 * spread) / n  # a few voxels off the plate's faces (more with the spread)
        assert float(slab[far].sum()) > 5e3 and float(kept[far].max()) < 0.5


def test_hull_ramp_carries_gradients_to_the_map():
    """A refiner trained with the trim (training/learn/stage.py: hull_trimmed) teaches the inpainting net through it."""
    s = torch.full((1, 16, 16), 0.7, requires_grad=True)
    ramp = sph.sph_hull_ramp(s, 16, spread=1)
    ramp.sum().backward()
    assert s.grad is not None and float(s.grad.abs().sum()) > 0 and bool((s.grad <= 0).all())  # a smaller s (a larger
    # radius) keeps more


def test_a_widened_hull_passes_gradient_to_few_pixels():
    """Why weights trained with the trim store spread 0: through a widened hull only each neighbourhood's largest
    radius gets a gradient (joint-40 grew a lattice of spikes in its maps), through the plain one nearly every pixel."""
    gen = torch.Generator().manual_seed(0)
    share = {}
    for spread in (0, 2):
        s = (torch.rand((1, 32, 32), generator=gen) * 0.3 + 0.55).requires_grad_()
        sph.sph_hull_ramp(s, 32, spread=spread).sum().backward()
        share[spread] = float((s.grad != 0).float().mean())
    assert share[0] > 0.8 and share[2] < 0.2


def test_hull_ramp_rejects_bad_inputs():
    s = torch.full((1, 8, 8), 0.5)
    for kwargs in ({"spread": -1}, {"spread": 5}, {"spread": True}, {"width": 0.0}, {"width": math.nan},
                   {"offset": -0.5}, {"offset": math.inf}):
        with pytest.raises(ValueError):
            sph.sph_hull_ramp(s, 4, **kwargs)
    with pytest.raises(ValueError):
        sph.sph_hull_ramp(torch.full((8, 8), 0.5), 4)
