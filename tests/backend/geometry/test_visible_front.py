"""The faces along the camera's rays made whole: the depth map's own distance grid, fused into holes; pits sealed; the back's
dents filled."""

import dataclasses
import pytest
import torch

from genre_backend.geometry.voxels import voxel_centres


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
    from genre_backend.geometry.visible_front import depth_to_distance

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
    from genre_backend.geometry.visible_front import fuse_visible_surface
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
    from genre_backend.geometry.visible_front import fuse_visible_surface
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
def test_sealing_pits_fills_a_narrow_well_in_the_front_with_the_front_around_it_and_nothing_else(monkeypatch):
    """(Without libigl, as in the slim runtime: the mesh stages measure with the pair tests.)"""
    import sys

    monkeypatch.setitem(sys.modules, "igl", None)  # import igl raises ImportError
    from genre_backend.geometry.visible_front import PIT_MIN_DEPTH_VOXELS, seal_pits
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


@pytest.mark.slow
def test_sealing_the_back_fills_a_dent_to_its_rim_and_leaves_a_convex_back_and_a_tunnel_alone(monkeypatch):
    """(Without libigl, as in the slim runtime.)"""
    import sys

    monkeypatch.setitem(sys.modules, "igl", None)
    from genre_backend.geometry.visible_front import seal_back
    from genre_backend.geometry.voxels import ray_last_hit

    camera, g, depth, (x, y, z), whole = _sphere_seen_and_its_tube()
    n, level, size = g.voxel_size, g.default_threshold, g.image_size
    obj = depth > 0
    assert torch.equal(seal_back(whole, obj, camera, g, level), whole)  # a ball's back is convex seen from behind
    # the back cap missing over a disc of radius 0.15 around the view axis: those rays last leave the grid at the
    # inside of the front, a dent about 0.5 deep inside a rim 0.26 behind the centre
    dent = torch.where((z < 0) & (x * x + y * y < 0.15 ** 2), torch.zeros_like(whole), whole)
    before = ray_last_hit(dent, level, camera, size)
    dish = obj & (before < camera.distance)  # the rays that end on the front's inside
    assert int(dish.sum()) > 100
    sealed = seal_back(dent, obj, camera, g, level)
    assert torch.equal(torch.maximum(sealed, dent), sealed)  # only ever adds
    changed = sealed != dent
    assert bool((z[changed] < -0.2).all()) and bool((x[changed] ** 2 + y[changed] ** 2 < 0.19 ** 2).all())  # a lid at the rim
    after = ray_last_hit(sealed, level, camera, size)
    rim = camera.distance + (0.3 ** 2 - 0.15 ** 2) ** 0.5 + 0.55 * g.distance_band / n  # the rim's crossing, on the axis
    lid = after[dish]
    assert bool(torch.isfinite(lid).all()) and float((lid - rim).abs().max()) < 2.0 / n  # flat at the rim, within 2 voxels
    assert float((after - ray_last_hit(whole, level, camera, size))[dish].max()) <= 0.5 / n  # never past the whole back
    # a tunnel through front and back along the view axis: its rays meet nothing, so the back drains into it
    tunnel = torch.where(x * x + y * y < 0.1 ** 2, torch.zeros_like(whole), whole)
    assert torch.equal(seal_back(tunnel, obj, camera, g, level), tunnel)
    with pytest.raises(ValueError, match="distance"):
        seal_back(dent, obj, camera, dataclasses.replace(g, target="shell"), level)
    with pytest.raises(ValueError, match="bool"):
        seal_back(dent, obj.float(), camera, g, level)
    with pytest.raises(ValueError, match="back_sealing"):
        dataclasses.replace(g, back_sealing=True, target="shell")
