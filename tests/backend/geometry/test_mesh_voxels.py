import dataclasses
import sys
import numpy as np
import pytest
import torch
import trimesh

from genre_backend.geometry.mesh_voxels import grid_index_to_view, mesh_to_shell, mesh_to_surface_voxels, voxels_to_mesh
from genre_backend.geometry.voxels import voxel_centres


def _centre_radii(n):
    c = voxel_centres(n, dtype=torch.float64)
    x, y, z = torch.meshgrid(c, c, c, indexing="ij")
    return torch.sqrt(x**2 + y**2 + z**2)


@pytest.mark.parametrize("n", [32, 64])
def test_surface_voxels_of_a_sphere(n):
    r = 0.37
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=r)
    vox = mesh_to_surface_voxels(torch.tensor(mesh.vertices), torch.tensor(mesh.faces), n)
    dist = (_centre_radii(n) - r).abs() * n  # distance of each voxel centre to the sphere, in voxels
    assert vox[dist < 0.2].all()  # every voxel the surface clearly passes through is marked
    assert not vox[dist > 3**0.5 / 2 + 0.01].any()  # and none it cannot touch


def test_open_mesh_shell():
    # a single square plate z = 0.11 (open, not watertight)
    v = torch.tensor([[-0.29, -0.29, 0.11], [0.29, -0.29, 0.11], [0.29, 0.29, 0.11], [-0.29, 0.29, 0.11]], dtype=torch.float64)
    f = torch.tensor([[0, 1, 2], [0, 2, 3]])
    n = 20  # pitch 0.05: the plane z = 0.11 lies inside voxel layer iz = 12
    surf = mesh_to_surface_voxels(v, f, n)
    assert surf[:, :, 12].sum() == 12 * 12  # x, y from -0.29 to 0.29 cover voxels 4..15
    assert surf.sum() == 12 * 12
    shell = mesh_to_shell(v, f, n, 1)
    assert shell.sum() == 14 * 14 * 3  # one dilation in the 26-neighbourhood
    assert torch.equal(mesh_to_shell(v, f, n, 0), surf)


def test_marching_cubes_places_vertices_in_the_view_frame():
    n = 16
    grid = np.zeros((n, n, n), np.float32)
    grid[3:9, 5:7, 10:14] = 1.0  # a box of voxels
    verts, faces = voxels_to_mesh(grid, 0.5)
    lo, hi = verts.min(0), verts.max(0)
    # the 0.5 level lies half-way between a full voxel centre and an empty one: at the voxel faces
    expect_lo = grid_index_to_view(np.array([3, 5, 10]) - 0.5, n)
    expect_hi = grid_index_to_view(np.array([8, 6, 13]) + 0.5, n)
    assert np.allclose(lo, expect_lo, atol=1e-6) and np.allclose(hi, expect_hi, atol=1e-6)
    # closed, and normals point outward (positive signed volume)
    mesh = trimesh.Trimesh(verts, faces, process=True)
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(np.prod(expect_hi - expect_lo), rel=0.2)  # corners are cut
    assert mesh.volume > 0


def test_marching_cubes_closes_surfaces_at_the_border_and_handles_empty():
    grid = torch.ones(8, 8, 8)
    verts, faces = voxels_to_mesh(grid, 0.5)
    assert trimesh.Trimesh(verts, faces).is_watertight
    assert np.allclose(verts.min(0), -0.5, atol=1e-6) and np.allclose(verts.max(0), 0.5, atol=1e-6)
    v, f = voxels_to_mesh(torch.zeros(8, 8, 8), 0.5)
    assert v.shape == (0, 3) and f.shape == (0, 3)


def test_sphere_round_trip_through_shell_and_marching_cubes():
    n, r = 48, 0.35
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=r)
    shell = mesh_to_shell(torch.tensor(mesh.vertices), torch.tensor(mesh.faces), n, 1).float()
    verts, faces = voxels_to_mesh(shell, 0.5)
    radii = np.linalg.norm(verts, axis=1)
    # a shell straddling the surface gives an outer and an inner sheet around it: every vertex
    # lies within the dilated shell's reach (√3/2 + √3 + 1/2 voxels) and the sheets balance
    assert np.abs(radii - r).max() * n < 3.1
    assert (radii > r + 0.5 / n).any() and (radii < r - 0.5 / n).any()
    sheets = trimesh.Trimesh(verts, faces).split(only_watertight=False)
    assert len(sheets) == 2
    mean_radii = sorted(np.linalg.norm(m.vertices, axis=1).mean() for m in sheets)
    assert abs(0.5 * sum(mean_radii) - r) * n < 0.5


def test_rejects_bad_inputs():
    with pytest.raises(ValueError, match="faces"):
        mesh_to_surface_voxels(torch.zeros(3, 3), torch.zeros(1, 4, dtype=torch.int64), 8)
    with pytest.raises(ValueError, match="threshold"):
        voxels_to_mesh(np.zeros((4, 4, 4), np.float32), 1.5)
    with pytest.raises(ValueError, match="cubic"):
        voxels_to_mesh(np.zeros((4, 4, 5), np.float32), 0.5)
    with pytest.raises(ValueError, match="shell_dilation"):
        mesh_to_shell(torch.zeros(3, 3), torch.tensor([[0, 1, 2]]), 8, -1)


# ---- the truncated-distance target --------------------------------------------------------

@pytest.fixture(params=["libigl", "pair tests"])
def distance_way(request, monkeypatch):
    """mesh_to_distance's two ways: libigl's AABB tree (training installs), and without libigl (the slim runtime,
    whose pit sealing measures a few voxels) the exact pair tests."""
    if request.param == "pair tests":
        monkeypatch.setitem(sys.modules, "igl", None)  # import igl raises ImportError
    return request.param


def test_the_pair_tests_asked_for_match_the_tree():
    from genre_backend.geometry.mesh_voxels import mesh_to_distance

    mesh = trimesh.creation.annulus(r_min=0.12, r_max=0.3, height=0.15, sections=24)
    v, f = torch.tensor(mesh.vertices), torch.tensor(mesh.faces)
    tree, pairs = mesh_to_distance(v, f, 24, 2.0), mesh_to_distance(v, f, 24, 2.0, tree=False)
    assert (tree > 0).sum() > 500 and torch.allclose(tree, pairs, atol=1e-5)


def test_distance_target_of_a_sphere_is_the_analytic_distance(distance_way):
    from genre_backend.geometry.mesh_voxels import mesh_to_distance

    n, r, band = 32, 0.31, 2.0
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=r)
    grid = mesh_to_distance(torch.tensor(mesh.vertices), torch.tensor(mesh.faces), n, band)
    d = (_centre_radii(n) - r).abs() * n
    expect = torch.clamp(1 - d / band, 0, 1).float()
    # the icosphere's facets lie up to 2.4e-4 inside the sphere: 0.008 voxel at n = 32
    assert (grid - expect).abs().max() < 0.01 / band
    assert torch.equal(grid > 0, expect > 0.01 / band) or ((grid > 0) != (expect > 0)).sum() < 10


def test_distance_target_matches_the_loop_reference_on_an_open_skewed_mesh(distance_way):
    from genre_backend.geometry.mesh_voxels import mesh_to_distance
    from genre_backend.geometry.triangle_distance import point_mesh_distance_reference

    rng = np.random.default_rng(3)
    v = rng.uniform(-0.35, 0.35, (6, 3))
    f = np.array([[0, 1, 2], [2, 3, 4], [1, 4, 5]])
    n, band = 16, 1.5
    grid = mesh_to_distance(torch.tensor(v), torch.tensor(f), n, band).numpy()
    idx = np.argwhere(grid > 0)
    ref = point_mesh_distance_reference((idx + 0.5) / n - 0.5, v, f) * n
    assert len(idx) > 50
    assert np.abs(grid[tuple(idx.T)] - np.clip(1 - ref / band, 0, 1)).max() < 1e-5
    # and the band is complete: no voxel left at 0 lies within it
    zeros = np.argwhere(grid == 0)
    pick = zeros[rng.choice(len(zeros), 400, replace=False)]
    assert (point_mesh_distance_reference((pick + 0.5) / n - 0.5, v, f) * n >= band - 1e-6).all()


@pytest.mark.parametrize("level", [0.25, 0.5, 0.6])
def test_marching_cubes_of_the_distance_target_lies_at_the_level(level):
    """The sheets of threshold t lie (1 − t)·band voxels from the surface (a sphere: two concentric sheets).

    Closer than ~0.6 voxel the two sheets start to touch where no voxel centre
    lies between them (measured: at 0.5 voxel 1 part, sheets up to 0.34 voxel off).
    """
    from genre_backend.geometry.mesh_voxels import mesh_to_distance

    n, r, band = 48, 0.3, 2.0
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=r)
    grid = mesh_to_distance(torch.tensor(mesh.vertices), torch.tensor(mesh.faces), n, band)
    verts, faces = voxels_to_mesh(grid, level)
    off = np.abs(np.linalg.norm(verts, axis=1) - r) * n  # voxels from the sphere
    # trilinear interpolation of a distance (not linear across the sheet's voxels) bends it by < 0.1 voxel
    assert np.abs(off - (1 - level) * band).max() < 0.09
    assert len(trimesh.Trimesh(verts, faces).split(only_watertight=False)) == 2


def test_a_plate_thinner_than_a_voxel_survives_the_distance_target_but_has_two_sheets_apart():
    """Thin parts: an open plate gives a closed slab of thickness 2·(1 − t)·band voxels.

    At t = 0.5 (1 voxel off) both sheets are exact; nearer, the sheet on the side
    whose voxel centre is farther from the plate is interpolated across the
    distance's kink (at t = 0.75 here: 0.3 voxel off).
    """
    from genre_backend.geometry.mesh_voxels import mesh_to_distance

    v = torch.tensor([[-0.29, -0.29, 0.11], [0.29, -0.29, 0.11], [0.29, 0.29, 0.11], [-0.29, 0.29, 0.11]], dtype=torch.float64)
    f = torch.tensor([[0, 1, 2], [0, 2, 3]])
    n, band, level = 20, 2.0, 0.5
    verts, faces = voxels_to_mesh(mesh_to_distance(v, f, n, band), level)
    inner = (np.abs(verts[:, 0]) < 0.2) & (np.abs(verts[:, 1]) < 0.2)
    z = verts[inner, 2]
    half = (1 - level) * band / n
    assert np.allclose(np.sort(np.unique(np.round(z, 6))), [0.11 - half, 0.11 + half], atol=1e-5)
    assert trimesh.Trimesh(verts, faces).is_watertight
    # its surface keeps a slab 2·surface_margin voxels thick instead of two coincident sheets
    from genre_backend.config import GeometryConfig
    from genre_backend.geometry.mesh_voxels import grid_to_surface

    g = GeometryConfig(voxel_size=n, target="distance", distance_band=band)
    sv, _ = grid_to_surface(mesh_to_distance(v, f, n, band), level, g)
    z = sv[inner, 2]
    assert np.allclose(np.sort(np.unique(np.round(z, 6))), [0.11 - g.surface_margin / n, 0.11 + g.surface_margin / n], atol=1e-5)


def test_mesh_to_target_follows_the_config():
    from genre_backend.config import GeometryConfig
    from genre_backend.geometry.mesh_voxels import mesh_to_target

    mesh = trimesh.creation.box((0.4, 0.3, 0.2))
    v, f = torch.tensor(mesh.vertices), torch.tensor(mesh.faces)
    shell = mesh_to_target(v, f, GeometryConfig(voxel_size=16, target="shell"))
    assert torch.equal(shell, mesh_to_shell(v, f, 16, 1).float())
    dist = mesh_to_target(v, f, GeometryConfig(voxel_size=16, target="distance"))
    assert dist.max() <= 1 and dist.min() >= 0 and ((dist > 0) & (dist < 1)).any()
    with pytest.raises(ValueError, match="geometry.target"):
        GeometryConfig(target="occupancy")


def test_the_distance_grid_surface_lands_on_the_sphere_at_every_level():
    """grid_to_surface moves both sheets of the distance target onto the surface they surround."""
    from genre_backend.config import GeometryConfig
    from genre_backend.geometry.mesh_voxels import grid_to_surface, mesh_to_target, vertex_normals

    g = GeometryConfig(voxel_size=48, target="distance")
    assert g.surface_margin == 0.25
    r = 0.3
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=r)
    grid = mesh_to_target(torch.tensor(mesh.vertices), torch.tensor(mesh.faces), g)
    for level in (0.3, 0.5, 0.6):
        plain, _ = voxels_to_mesh(grid, level)
        verts, faces = grid_to_surface(grid, level, g)
        assert np.abs(np.linalg.norm(plain, axis=1) - r).mean() * 48 > 0.5 * (1 - level) * g.distance_band
        # the sheets end surface_margin voxels off the sphere, outside and inside
        assert np.abs(np.abs(np.linalg.norm(verts, axis=1) - r) * 48 - g.surface_margin).mean() < 0.05
    # a shell grid is left as marching cubes made it
    shell = GeometryConfig(voxel_size=48, target="shell")
    v0, f0 = voxels_to_mesh(grid, 0.5)
    assert np.array_equal(grid_to_surface(grid, 0.5, shell)[0], v0)
    # the normals: area-weighted face normals summed per vertex, against a plain loop
    v0, f0 = v0.astype(np.float64), f0[:300]
    ref = np.zeros_like(v0)
    for a, b, c in f0:
        n = np.cross(v0[b] - v0[a], v0[c] - v0[a])
        for k in (a, b, c):
            ref[k] += n
    used = np.linalg.norm(ref, axis=1) > 0
    ref[used] /= np.linalg.norm(ref[used], axis=1, keepdims=True)
    assert np.allclose(vertex_normals(v0, f0), ref, atol=1e-9)


def _euler_closed(verts, faces):  # (verts unused: the rule is on the faces)
    from training.eval.runner import is_closed

    return is_closed(faces)


def test_hole_closing_seals_small_holes_and_keeps_wide_openings():
    """A sphere's distance tube with two punched holes: plain filling leaves them (the inner sheet
    joined to the outer one: a genus-1 surface), closing=2 seals them; a torus's hole (far wider) stays; a grid without holes is
    left exactly as plain filling leaves it."""
    from genre_backend.config import GeometryConfig
    from genre_backend.geometry.mesh_voxels import fill_enclosed, grid_to_surface, mesh_to_target, voxels_to_mesh

    n, level = 40, 0.45
    g = GeometryConfig(voxel_size=n, target="distance")
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.3)
    grid = mesh_to_target(torch.tensor(sphere.vertices), torch.tensor(sphere.faces), g).numpy()
    c = (np.arange(n) + 0.5) / n - 0.5
    x, y, z = np.meshgrid(c, c, c, indexing="ij")
    # holes of radius 1.5 voxels through the tube along +x and -x
    holed = np.where((np.abs(x) > 0.15) & (y ** 2 + z ** 2 < (1.5 / n) ** 2), 0.0, grid).astype(np.float32)
    pv, pf = voxels_to_mesh(fill_enclosed(holed, level), level)
    assert not _euler_closed(pv, pf)  # the holes join the sheets: a tunnel
    assert np.linalg.norm(pv, axis=1).min() < 0.3  # the inner sheet is in the mesh
    sealed = fill_enclosed(holed, level, closing=2)
    v, f = voxels_to_mesh(sealed, level)
    assert _euler_closed(v, f)
    # the sealed surface is the outer sheet (radius 0.3 + (1 - t)·band voxels), the hole's lid included
    r = np.linalg.norm(v, axis=1)
    assert abs(np.median(r) - (0.3 + (1 - level) * g.distance_band / n)) < 0.5 / n and r.min() > 0.3
    # without holes, closing changes nothing
    assert np.array_equal(fill_enclosed(grid, level, closing=3), fill_enclosed(grid, level))
    # a torus keeps its hole (genus 1: not "closed" by the Euler rule) and its inside is filled
    torus = trimesh.creation.torus(major_radius=0.25, minor_radius=0.08)
    tgrid = mesh_to_target(torch.tensor(torus.vertices), torch.tensor(torus.faces), g).numpy()
    tv, tf = voxels_to_mesh(fill_enclosed(tgrid, level, closing=2), level)
    assert trimesh.Trimesh(tv, tf).is_watertight and not _euler_closed(tv, tf)
    assert (fill_enclosed(tgrid, level, closing=2)[np.hypot(x, y) < 0.1] < 1).all()  # the hole is still empty
    # grid_to_surface takes the setting from the config
    v2, f2 = grid_to_surface(holed, level, dataclasses.replace(g, hole_closing=2))
    assert _euler_closed(v2, f2) and not _euler_closed(*grid_to_surface(holed, level, g))
    with pytest.raises(ValueError, match="hole_closing"):
        GeometryConfig(hole_closing=-1)
    with pytest.raises(ValueError, match="closing"):
        fill_enclosed(grid, level, closing=-1)
