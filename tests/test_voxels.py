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


# ---- the silhouette's voxels (the one-view visual hull) ------------------------------------------
from genre_backend.config import CameraConfig  # noqa: E402
from genre_backend.geometry.voxels import silhouette_voxels, silhouette_voxels_reference  # noqa: E402


def test_silhouette_voxels_match_the_reference_on_random_masks():
    g = torch.Generator().manual_seed(3)
    mask = torch.rand(2, 24, 24, generator=g) > 0.4
    for camera in (CameraConfig(), CameraConfig(lens_mm=35.0, distance=1.4)):
        fast = silhouette_voxels(mask, camera, 10)
        ref = silhouette_voxels_reference(mask, camera, 10)
        assert fast.shape == (2, 1, 10, 10, 10) and fast.dtype == torch.bool
        assert torch.equal(fast, ref)
        assert 0 < int(fast.sum()) < fast.numel()  # neither empty nor full: the test can fail


def test_silhouette_of_a_sphere_keeps_the_sphere_and_carves_outside_its_cone():
    """A ball of radius R at the origin seen from distance d: its outline is the circle of angular radius asin(R/d)."""
    camera, size, n, radius = CameraConfig(), 96, 32, 0.3
    f = camera.focal_px(size)
    centre = torch.arange(size, dtype=torch.float64) + 0.5 - size / 2
    rays = torch.stack([centre.view(1, -1).expand(size, size) / f, -centre.view(-1, 1).expand(size, size) / f,
                        -torch.ones(size, size, dtype=torch.float64)], dim=-1)
    rays = rays / rays.norm(dim=-1, keepdim=True)
    eye = torch.tensor([0.0, 0.0, camera.distance], dtype=torch.float64)
    # a pixel is the ball's when its centre ray passes within R of the origin
    along = -(rays @ eye)
    miss = (eye.square().sum() - along.square()).clamp(min=0).sqrt()
    mask = (miss <= radius)[None]
    kept = silhouette_voxels(mask, camera, n)[0, 0]
    c = voxel_centres(n, dtype=torch.float64)
    p = torch.stack(torch.meshgrid(c, c, c, indexing="ij"), dim=-1)
    pitch = 1.0 / n
    inside_ball = p.norm(dim=-1) < radius - 2 * pitch
    to_eye = eye - p
    # the voxel centre's distance from the axis of the cone, as an angle from the camera
    angle = torch.atan2(to_eye[..., :2].norm(dim=-1), to_eye[..., 2])
    outline = math.asin(radius / camera.distance)
    assert bool(kept[inside_ball].all())  # nothing of the ball is carved
    far_out = angle > outline + 2.5 * pitch / camera.distance
    assert far_out.any() and not bool(kept[far_out].any())  # everything well outside the cone is
    assert int(kept.sum()) > int(inside_ball.sum())  # the cone is more than the ball (a visual hull)


def test_silhouette_voxels_refuse_bad_inputs():
    with pytest.raises(ValueError):
        silhouette_voxels(torch.ones(8, 8, dtype=torch.bool), CameraConfig(), 8)  # no batch axis
    with pytest.raises(ValueError):
        silhouette_voxels(torch.ones(1, 8, 6, dtype=torch.bool), CameraConfig(), 8)  # not square
    with pytest.raises(ValueError):
        silhouette_voxels(torch.ones(1, 8, 8, dtype=torch.bool), CameraConfig(), 0)
