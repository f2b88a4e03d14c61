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
