import math

import pytest
import torch

from genre_backend.geometry.voxels import points_to_voxels, points_to_voxels_reference, voxel_centres


def test_single_point_at_a_voxel_centre_gives_one():
    n = 8
    c = voxel_centres(n)
    pts = torch.tensor([[[c[2], c[5], c[7]]]])
    grid = points_to_voxels(pts, n)
    assert grid.shape == (1, 1, n, n, n)
    assert grid[0, 0, 2, 5, 7].item() == pytest.approx(1.0)
    assert grid.sum().item() == pytest.approx(1.0)


def test_mean_distance_rule_by_hand():
    n = 4  # pitch 0.25, voxel (1,1,1) centred at (-0.125,)*3
    centre = torch.full((3,), -0.125)
    pts = torch.stack([centre + torch.tensor([0.05, 0.0, 0.0]), centre + torch.tensor([0.0, -0.1, 0.0])])[None]
    grid = points_to_voxels(pts, n)
    expected = 1.0 - (0.05 / 0.25 + 0.1 / 0.25) / 2
    assert grid[0, 0, 1, 1, 1].item() == pytest.approx(expected, abs=1e-6)
    assert (grid > 0).sum().item() == 1


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device"))])
def test_matches_reference_on_random_points(device):
    gen = torch.Generator().manual_seed(0)
    pts = (torch.rand(2, 300, 3, generator=gen) - 0.5) * 1.2  # some fall outside the cube
    mask = torch.rand(2, 300, generator=gen) > 0.3
    fast = points_to_voxels(pts.to(device), 6, mask.to(device)).cpu()
    ref = points_to_voxels_reference(pts, 6, mask)
    assert torch.allclose(fast, ref, atol=1e-6)
    hit = fast > 0
    assert hit.any() and (fast[hit] > 1 - 3**0.5 / 2 - 1e-6).all() and (fast <= 1).all()


def test_gradcheck_with_respect_to_points():
    gen = torch.Generator().manual_seed(1)
    # keep points away from voxel faces so that finite differences do not cross cells
    cells = torch.randint(0, 4, (1, 12, 3), generator=gen).double()
    offs = 0.2 + 0.6 * torch.rand(1, 12, 3, generator=gen, dtype=torch.float64)
    pts = ((cells + offs) / 4 - 0.5).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: points_to_voxels(p, 4), (pts,), eps=1e-6, atol=1e-5)


def test_rejects_bad_inputs():
    with pytest.raises(ValueError, match="points"):
        points_to_voxels(torch.zeros(10, 3), 4)
    with pytest.raises(ValueError, match="resolution"):
        points_to_voxels(torch.zeros(1, 10, 3), 0)
    with pytest.raises(ValueError, match="mask"):
        points_to_voxels(torch.zeros(1, 10, 3), 4, torch.ones(1, 9, dtype=torch.bool))


# ---- the silhouette's ramp (the one-view visual hull) -------------------------------------------
from genre_backend.config import CameraConfig  # noqa: E402
from genre_backend.geometry.voxels import silhouette_ramp, silhouette_ramp_reference  # noqa: E402


def test_silhouette_ramp_matches_the_reference_on_random_masks():
    g = torch.Generator().manual_seed(3)
    mask = torch.rand(2, 16, 16, generator=g) > 0.4
    mask[1] = False
    mask[1, 4:11, 5:9] = True  # a block: distances of several pixels
    for camera, width in ((CameraConfig(), 1.0), (CameraConfig(lens_mm=35.0, distance=1.4), 2.5)):
        fast = silhouette_ramp(mask, camera, 9, width)
        ref = silhouette_ramp_reference(mask, camera, 9, width)
        assert fast.shape == (2, 1, 9, 9, 9) and fast.dtype == torch.float32
        assert torch.allclose(fast, ref, atol=1e-5)
        assert float(fast.min()) == 0.0 and float(fast.max()) == 1.0 and ((fast > 0) & (fast < 1)).any()


def _ball_mask(camera, size, radius):
    """The pixels whose centre ray passes within ``radius`` of the origin, seen from ``camera``."""
    f = camera.focal_px(size)
    centre = torch.arange(size, dtype=torch.float64) + 0.5 - size / 2
    rays = torch.stack([centre.view(1, -1).expand(size, size) / f, -centre.view(-1, 1).expand(size, size) / f,
                        -torch.ones(size, size, dtype=torch.float64)], dim=-1)
    rays = rays / rays.norm(dim=-1, keepdim=True)
    eye = torch.tensor([0.0, 0.0, camera.distance], dtype=torch.float64)
    along = -(rays @ eye)
    return ((eye.square().sum() - along.square()).clamp(min=0).sqrt() <= radius)[None]


def test_silhouette_ramp_of_a_ball_crosses_one_half_on_its_outline_cone():
    """A ball of radius R at the origin seen from distance d: its outline is the cone of half-angle asin(R/d)."""
    camera, size, n, radius = CameraConfig(), 128, 32, 0.3
    ramp = silhouette_ramp(_ball_mask(camera, size, radius), camera, n)[0, 0].double()
    c = voxel_centres(n, dtype=torch.float64)
    p = torch.stack(torch.meshgrid(c, c, c, indexing="ij"), dim=-1)
    to_eye = torch.tensor([0.0, 0.0, camera.distance], dtype=torch.float64) - p
    angle = torch.atan2(to_eye[..., :2].norm(dim=-1), to_eye[..., 2])
    # the signed distance to the cone, in voxels at the centre's depth (the same small-angle measure the ramp uses)
    depth = to_eye[..., 2]
    d_vox = (math.asin(radius / camera.distance) - angle) * camera.focal_px(size) * depth / camera.focal_px(size) * n
    expected = (0.5 + d_vox).clamp(0, 1)
    near = d_vox.abs() < 3
    assert near.sum() > 500
    err = (ramp - expected).abs()
    assert float(err[near].max()) < 0.2  # the pixel grid's staircase, a fraction of a pixel
    assert bool((ramp[p.norm(dim=-1) < radius - 2.0 / n] == 1).all())  # nothing of the ball is cut
    assert bool((ramp[d_vox < -1.5] == 0).all())  # everything well outside the cone is


def test_silhouette_ramp_refuses_bad_inputs():
    with pytest.raises(ValueError):
        silhouette_ramp(torch.ones(8, 8, dtype=torch.bool), CameraConfig(), 8)  # no batch axis
    with pytest.raises(ValueError):
        silhouette_ramp(torch.ones(1, 8, 6, dtype=torch.bool), CameraConfig(), 8)  # not square
    with pytest.raises(ValueError):
        silhouette_ramp(torch.ones(1, 8, 8, dtype=torch.bool), CameraConfig(), 0)
    with pytest.raises(ValueError):
        silhouette_ramp(torch.ones(1, 8, 8, dtype=torch.bool), CameraConfig(), 8, width=0.0)


def _sphere_distance_grid(n: int, radius: float, band: float = 2.0) -> torch.Tensor:
    """The distance target of a sphere, exactly: clip(1 − |r − radius|·n/band, 0, 1) at the voxel centres."""
    c = voxel_centres(n, dtype=torch.float64)
    x, y, z = torch.meshgrid(c, c, c, indexing="ij")
    r = torch.sqrt(x * x + y * y + z * z)
    return (1.0 - (r - radius).abs() * n / band).clamp(0.0, 1.0).float()


def _lumpy_grid(seed: int) -> tuple[int, int, torch.Tensor]:
    """(N, image size, grid): two offset spheres' tubes and noise, on a small grid and image (the references are slow)."""
    g = torch.Generator().manual_seed(seed)
    n, size = 12, 20
    grid = torch.maximum(_sphere_distance_grid(n, 0.3), _sphere_distance_grid(n, 0.15).roll(3, dims=0))
    return n, size, (grid + 0.2 * torch.rand(n, n, n, generator=g)).clamp(0.0, 1.0)


def test_first_hits_match_the_marched_reference_the_sphere_and_the_marching_cubes_surface():
    import numpy as np

    from genre_backend.config import get_preset
    from genre_backend.geometry.analytic import sphere_depth
    from genre_backend.geometry.mesh_voxels import voxels_to_mesh
    from genre_backend.geometry.voxels import ray_first_hit, ray_first_hit_reference
    from genre_backend.output.colour import zbuffer

    camera = get_preset("default").camera
    n, size, grid = _lumpy_grid(3)
    fast = ray_first_hit(grid, 0.6, camera, size).numpy()
    ref = ray_first_hit_reference(grid, 0.6, camera, size)
    both = np.isfinite(fast) & np.isfinite(ref)
    assert 0 < both.sum() < size * size
    assert (np.isfinite(fast) != np.isfinite(ref)).sum() <= 2  # a ray grazing a corner may differ between step sizes
    with np.errstate(invalid="ignore"):  # inf − inf where neither meets anything (masked out)
        assert np.abs(np.where(both, fast - ref, 0.0)).max() <= 0.5 / n + 1e-6  # the fast op's samples are half a voxel apart
    # a sphere's tube: the first hit is where the ray crosses the level, on the sphere (1 − t)·band voxels larger
    sphere = _sphere_distance_grid(64, 0.3)
    hit = ray_first_hit(sphere, 0.45, camera, 128)
    crossing = sphere_depth(camera, 128, 0.3 + 0.55 * 2.0 / 64, dtype=torch.float64)[0]
    inner = (crossing > 0) & (torch.nn.functional.avg_pool2d((crossing > 0).double()[None], 5, 1, 2)[0] == 1)  # off the rim
    err = (hit.double() - crossing)[inner]
    assert int(inner.sum()) > 2000 and float(err.median()) > 0 and float(err.max()) < 0.6 / 64 and float(err.min()) > -0.1 / 64
    # the pixels the marching-cubes mesh covers are those whose ray meets the grid
    v, f = voxels_to_mesh(sphere, 0.45)
    drawn = np.isfinite(zbuffer(v, f, camera, 128))
    seen = torch.isfinite(hit).numpy()
    assert drawn.sum() > 2000 and (drawn != seen).sum() <= 0.01 * drawn.sum()
    assert not torch.isfinite(ray_first_hit(torch.zeros(64, 64, 64), 0.45, camera, 128)).any()
    with pytest.raises(ValueError, match="level"):
        ray_first_hit(sphere, 1.5, camera, 128)



def test_last_hits_match_the_reference_marched_from_behind_and_the_far_side_of_a_sphere():
    import numpy as np

    from genre_backend.config import get_preset
    from genre_backend.geometry.voxels import ray_first_hit, ray_last_hit, ray_first_hit_reference

    camera = get_preset("default").camera
    n, size, grid = _lumpy_grid(4)
    fast = ray_last_hit(grid, 0.6, camera, size).numpy()
    ref = ray_first_hit_reference(grid, 0.6, camera, size, last=True)
    both = np.isfinite(fast) & np.isfinite(ref)
    assert 0 < both.sum() < size * size and (np.isfinite(fast) != np.isfinite(ref)).sum() <= 2
    with np.errstate(invalid="ignore"):
        assert np.abs(np.where(both, fast - ref, 0.0)).max() <= 0.5 / n + 1e-6
    front = ray_first_hit(grid, 0.6, camera, size).numpy()
    assert (np.isfinite(front) == np.isfinite(fast)).all() and bool((fast[both] >= front[both]).all())  # never before the front
    # a sphere's tube: the last hit is where the ray leaves the sphere (1 − t)·band voxels larger, on its far side
    radius = 0.3 + 0.55 * 2.0 / 64
    hit = ray_last_hit(_sphere_distance_grid(64, 0.3), 0.45, camera, 128).double()
    f = camera.lens_mm / camera.sensor_mm * 128
    c = (torch.arange(128, dtype=torch.float64) + 0.5 - 64.0) / f
    q = c[None, :] ** 2 + c[:, None] ** 2 + 1.0  # planar depth p: |(p·dx, p·dy, D − p)|² = radius²
    disc = camera.distance ** 2 - q * (camera.distance ** 2 - radius ** 2)
    far = (camera.distance + disc.clamp(min=0).sqrt()) / q
    inner = (disc > 0) & (torch.nn.functional.avg_pool2d((disc > 0).double()[None], 5, 1, 2)[0] == 1)  # off the rim
    err = (hit - far)[inner]
    assert int(inner.sum()) > 2000 and float(err.median()) < 0 and float(err.min()) > -0.6 / 64 and float(err.max()) < 0.1 / 64


def test_ray_max_matches_its_reference_and_a_ball_s_disc_and_carries_gradient():
    import numpy as np

    from genre_backend.config import get_preset
    from genre_backend.geometry.analytic import sphere_depth
    from genre_backend.geometry.voxels import ray_max, ray_max_reference

    camera = get_preset("default").camera
    g = torch.Generator().manual_seed(5)
    n, size = 10, 14
    grid = (_sphere_distance_grid(n, 0.25) * torch.rand(n, n, n, generator=g)).clamp(0.0, 1.0)
    fast = ray_max(grid[None, None], camera, size).numpy()[0]
    assert np.abs(fast - ray_max_reference(grid, camera, size)).max() < 1e-5
    assert 0 < (fast > 0.5).sum() < size * size
    # a solid ball (a voxel is in when its centre is): its silhouette is the sphere's disc through the same camera,
    # up to the pixels along the rim, where the interpolated edge falls between voxel centres
    n, size, radius = 48, 64, 0.3
    c = (torch.arange(n, dtype=torch.float64) + 0.5) / n - 0.5
    x, y, z = torch.meshgrid(c, c, c, indexing="ij")
    ball = ((x * x + y * y + z * z).sqrt() <= radius).float()
    shown = ray_max(torch.stack([ball, torch.zeros_like(ball)])[:, None], camera, size)
    disc = sphere_depth(camera, size, radius, dtype=torch.float64)[0] > 0
    pool = torch.nn.functional.avg_pool2d(disc.double()[None], 5, 1, 2)[0]
    inside, outside = pool == 1, pool == 0  # two pixels or more from the rim
    assert int(inside.sum()) > 400 and bool((shown[0][inside] > 0.99).all()) and bool((shown[0][outside] < 0.01).all())
    assert float((shown[0] > 0.5).float().sub(disc.float()).abs().sum()) <= 0.1 * float(disc.sum())
    assert float(shown[1].abs().max()) == 0.0  # an empty grid shows nothing
    # the gradient of a pixel's value reaches the voxels on its ray only
    probe = grid.clone().requires_grad_(True)
    ray_max(probe[None, None], camera, 14)[0, 7, 7].backward()
    touched = probe.grad.abs() > 0
    assert 0 < int(touched.sum()) <= 8  # the corners of the one sample the maximum took
    with pytest.raises(ValueError, match="grid"):
        ray_max(grid, camera, 14)


def test_separable_dilation_equals_repeated_cube_dilation():
    from genre_backend.geometry.mesh_voxels import dilate, dilate_reference

    gen = torch.Generator().manual_seed(3)
    grid = torch.rand(23, 17, 29, generator=gen) > 0.995  # a few seeds, some near the faces
    grid[0, 0, 0] = grid[-1, 5, -1] = True
    for times in (0, 1, 2, 5):
        got, ref = dilate(grid, times), dilate_reference(grid, times)
        assert torch.equal(got, ref), times
    assert int(dilate(grid, 2).sum()) > 10 * int(grid.sum())  # it does grow
