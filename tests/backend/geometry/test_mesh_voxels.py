import dataclasses
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

def test_distance_target_of_a_sphere_is_the_analytic_distance():
    from genre_backend.geometry.mesh_voxels import mesh_to_distance

    n, r, band = 32, 0.31, 2.0
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=r)
    grid = mesh_to_distance(torch.tensor(mesh.vertices), torch.tensor(mesh.faces), n, band)
    d = (_centre_radii(n) - r).abs() * n
    expect = torch.clamp(1 - d / band, 0, 1).float()
    # the icosphere's facets lie up to 2.4e-4 inside the sphere: 0.008 voxel at n = 32
    assert (grid - expect).abs().max() < 0.01 / band
    assert torch.equal(grid > 0, expect > 0.01 / band) or ((grid > 0) != (expect > 0)).sum() < 10


def test_distance_target_matches_the_loop_reference_on_an_open_skewed_mesh():
    from genre_backend.geometry.mesh_voxels import mesh_to_distance, point_mesh_distance_reference

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


def _distance_geometry():
    from genre_backend.config import get_preset

    cfg = get_preset("default")
    return cfg.camera, dataclasses.replace(cfg.geometry, target="distance")


def _sphere_seen_and_its_tube(radius: float = 0.3):
    """(camera, distance geometry, the sphere's depth map (S, S), voxel centres' (x, y, z), its exact distance target)."""
    from genre_backend.geometry.analytic import sphere_depth

    camera, g = _distance_geometry()
    n = g.voxel_size
    depth = sphere_depth(camera, g.image_size, radius, dtype=torch.float32)[0]
    x, y, z = torch.meshgrid(*(voxel_centres(n, dtype=torch.float64),) * 3, indexing="ij")
    r = torch.sqrt(x * x + y * y + z * z)
    return camera, g, depth, (x, y, z), (1.0 - (r - radius).abs() * n / g.distance_band).clamp(0.0, 1.0).float()


def test_depth_to_distance_of_a_sphere_is_the_distance_to_its_front_cap():
    from genre_backend.geometry.analytic import sphere_depth
    from genre_backend.geometry.mesh_voxels import depth_to_distance

    camera, g = _distance_geometry()
    radius, n = 0.3, g.voxel_size
    depth = sphere_depth(camera, g.image_size, radius, dtype=torch.float32)[0]
    grid = depth_to_distance(depth, camera, g)
    x, y, z = torch.meshgrid(*(voxel_centres(n, dtype=torch.float64),) * 3, indexing="ij")
    r = torch.sqrt(x * x + y * y + z * z)
    # voxels near the cap the camera sees (+z faces the camera): the analytic distance to the sphere
    near = (grid > 0) & (z > 0.1)
    want = (1.0 - (r - radius).abs() * n / g.distance_band).clamp(0.0, 1.0)
    err = (grid.double() - want)[near].abs()
    assert int(near.sum()) > 500 and float(err.median()) < 0.05 and float(err.max()) < 0.3  # a triangulated cap, 0.67 voxel pixels
    assert float(grid[z < -0.05].max()) == 0.0  # nothing behind: only the visible side
    # a mask keeps only its pixels' surface; an empty one gives an empty grid
    left = (depth > 0) & (torch.arange(g.image_size)[None, :] < g.image_size // 2)
    half = depth_to_distance(depth, camera, g, left)
    assert float(half[x > 0.05].max()) == 0.0 and float(half[x < -0.05].max()) > 0.9
    assert float(depth_to_distance(torch.zeros_like(depth), camera, g).max()) == 0.0


def test_fusing_the_visible_surface_fills_a_hole_in_the_front_and_changes_nothing_else():
    from genre_backend.geometry.mesh_voxels import fuse_visible_surface
    from genre_backend.geometry.voxels import ray_first_hit

    camera, g, depth, (x, y, z), whole = _sphere_seen_and_its_tube()
    level = g.default_threshold
    # a prediction that covers the whole object: returned as it is
    assert torch.equal(fuse_visible_surface(whole, depth, camera, g, level), whole)
    # a hole through the front and the back (a tunnel along the view axis, 0.1 wide): filled in front only
    holed = torch.where((x.abs() < 0.05) & (y.abs() < 0.05), torch.zeros_like(whole), whole)
    obj = depth > 0
    lost = obj & ~torch.isfinite(ray_first_hit(holed, level, camera, g.image_size))
    assert int(lost.sum()) > 50
    fused = fuse_visible_surface(holed, depth, camera, g, level)
    assert not (obj & ~torch.isfinite(ray_first_hit(fused, level, camera, g.image_size))).any()
    assert torch.equal(torch.maximum(fused, holed), fused)  # only ever adds
    changed = fused != holed
    assert bool((z[changed] > 0.2).all())  # the patch lies on the front cap, around the hole
    assert bool(((x[changed].abs() < 0.1) & (y[changed].abs() < 0.1)).all())
    # the patch is the sphere's own surface: where it was added, the analytic value within a voxel's error
    assert float((fused - whole)[changed].abs().max()) < 0.35
    shell = dataclasses.replace(g, target="shell")
    with pytest.raises(ValueError, match="distance"):
        fuse_visible_surface(holed, depth, camera, shell, level)


@pytest.mark.slow
def test_a_pit_in_the_front_is_filled_where_the_depth_map_says_and_an_offset_depth_map_changes_nothing():
    from genre_backend.geometry.mesh_voxels import fuse_visible_surface
    from genre_backend.geometry.voxels import ray_first_hit

    camera, g, depth, (x, y, z), whole = _sphere_seen_and_its_tube()
    n, level = g.voxel_size, g.default_threshold
    # the depth net's constant offset (3 voxels nearer than the truth) is not a pit: nothing is added
    nearer = torch.where(depth > 0, depth - 3.0 / n, depth)
    assert torch.equal(fuse_visible_surface(whole, nearer, camera, g, level, pit_voxels=3.0), whole)
    # the front cap missing over a disc: the rays there meet the inside of the back, a pit 0.5 deep
    pit = torch.where((z > 0) & (x * x + y * y < 0.1 ** 2), torch.zeros_like(whole), whole)
    hit = ray_first_hit(pit, level, camera, g.image_size)
    assert torch.isfinite(hit[depth > 0]).all()  # no ray goes through: a pit, not a hole
    assert torch.equal(fuse_visible_surface(pit, depth, camera, g, level), pit)  # holes only: left alone
    for d in (depth, nearer):  # filled on the sphere's front, the offset depth map moved onto the grid's surface
        fused = fuse_visible_surface(pit, d, camera, g, level, pit_voxels=3.0)
        changed = fused != pit
        assert int(changed.sum()) > 100 and bool((z[changed] > 0.15).all())
        assert float((fused - whole)[changed].abs().max()) < 0.35  # the sphere's own distance, within a voxel's error
        refilled = ray_first_hit(fused, level, camera, g.image_size)
        inner = (depth > 0) & ((refilled - ray_first_hit(whole, level, camera, g.image_size)).abs() < 1.5 / n)
        assert float(inner.float().sum() / (depth > 0).sum()) > 0.97  # the front is where the whole sphere's is


@pytest.mark.slow
def test_sealing_pits_fills_a_narrow_well_in_the_front_with_the_front_around_it_and_nothing_else():
    from genre_backend.geometry.mesh_voxels import PIT_MIN_DEPTH_VOXELS, seal_pits
    from genre_backend.geometry.voxels import ray_first_hit

    camera, g, depth, (x, y, z), whole = _sphere_seen_and_its_tube()
    n, level, size = g.voxel_size, g.default_threshold, g.image_size
    obj = depth > 0
    front = ray_first_hit(whole, level, camera, size)
    # a convex front falls away toward the outline everywhere: nothing to seal, at any width
    for k in (1, 4, 8):
        assert torch.equal(seal_pits(whole, obj, camera, g, level, k), whole)
    assert torch.equal(seal_pits(whole, obj, camera, g, level, 0), whole)  # 0: off

    def well(radius: float) -> torch.Tensor:  # the front cap missing over a disc: its rays meet the inside of the back
        return torch.where((z > 0) & (x * x + y * y < radius ** 2), torch.zeros_like(whole), whole)

    narrow = well(0.025)  # 3.2 voxels across
    hit = ray_first_hit(narrow, level, camera, size)
    assert torch.isfinite(hit[obj]).all()  # a pit, not a hole
    pit = obj & (hit - front > PIT_MIN_DEPTH_VOXELS / n)
    assert int(pit.sum()) > 20
    sealed = seal_pits(narrow, obj, camera, g, level, 2)
    assert torch.equal(torch.maximum(sealed, narrow), sealed)  # only ever adds
    changed = sealed != narrow
    assert bool((z[changed] > 0.2).all()) and bool((x[changed] ** 2 + y[changed] ** 2 < 0.12 ** 2).all())  # on the cap, around the well
    assert float((sealed - whole)[changed].abs().max()) < 0.35  # the sphere's own distance, within a voxel's error
    refilled = ray_first_hit(sealed, level, camera, size)
    assert float((refilled - front)[obj].abs().max()) < 1.0 / n  # the front is the whole sphere's again, within a voxel
    # a well wider than the limit is a feature (a bowl's inside), not a pit: left alone at that width, sealed at a wider one
    wide = well(0.1)  # 12.8 voxels across
    assert torch.equal(seal_pits(wide, obj, camera, g, level, 2), wide)
    lid = ray_first_hit(seal_pits(wide, obj, camera, g, level, 8), level, camera, size)
    assert torch.isfinite(lid[obj]).all() and float((lid - front)[obj].max()) < 2.5 / n  # a flat lid at the rim: the cap's 1.1-voxel sagitta lost
    # a narrow tunnel through front and back (its rays meet nothing) is sealed in front, the back left open
    tunnel = torch.where((x.abs() < 0.02) & (y.abs() < 0.02), torch.zeros_like(whole), whole)
    assert not torch.isfinite(ray_first_hit(tunnel, level, camera, size)[obj]).all()
    closed = seal_pits(tunnel, obj, camera, g, level, 2)
    assert torch.isfinite(ray_first_hit(closed, level, camera, size)[obj]).all()
    assert bool((z[closed != tunnel] > 0.2).all())
    with pytest.raises(ValueError, match="distance"):
        seal_pits(narrow, obj, camera, dataclasses.replace(g, target="shell"), level, 2)
    for bad in (-1, 9, 2.0, True):
        with pytest.raises(ValueError, match="width_voxels"):
            seal_pits(narrow, obj, camera, g, level, bad)
    with pytest.raises(ValueError, match="bool"):
        seal_pits(narrow, obj.float(), camera, g, level, 2)
    with pytest.raises(ValueError, match="pit_sealing"):
        dataclasses.replace(g, pit_sealing=9)
    with pytest.raises(ValueError, match="pit_sealing"):
        dataclasses.replace(g, pit_sealing=1, target="shell")
