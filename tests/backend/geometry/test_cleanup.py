"""Mesh clean-up (genre_backend.geometry.cleanup) against trimesh and analytic shapes."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from genre_backend.geometry.cleanup import clean_mesh, is_watertight, mesh_parts, part_measures
from genre_backend.geometry.mesh_voxels import voxels_to_mesh


def _sphere(radius: float, centre=(0.0, 0.0, 0.0), inward: bool = False, subdivisions: int = 3) -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    m.apply_translation(centre)
    if inward:
        m.faces = m.faces[:, ::-1]
    return m


def _join(*meshes: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    joined = trimesh.util.concatenate(meshes)
    return np.asarray(joined.vertices), np.asarray(joined.faces)


def test_parts_and_measures_match_trimesh_and_analytic_volumes():
    big, small, cavity = _sphere(0.4), _sphere(0.05, (0.7, 0, 0)), _sphere(0.2, inward=True)
    v, f = _join(big, small, cavity)
    count, labels = mesh_parts(f, len(v))
    assert count == len(trimesh.Trimesh(v, f, process=False).split(only_watertight=False)) == 3
    area, volume = part_measures(v, f, labels, count)
    # parts in face order: big, small, cavity
    for i, ref in enumerate((big, small, cavity)):
        assert area[i] == pytest.approx(ref.area, rel=1e-9)
        assert volume[i] == pytest.approx(ref.volume, rel=1e-9)
    # against the analytic sphere (an icosphere at 3 subdivisions is within 1 % of it)
    assert volume[0] == pytest.approx(4 / 3 * np.pi * 0.4**3, rel=0.01)
    assert volume[2] == pytest.approx(-4 / 3 * np.pi * 0.2**3, rel=0.01)


def test_watertight_agrees_with_trimesh():
    m = _sphere(0.3, subdivisions=2)
    assert is_watertight(m.faces) and m.is_watertight and m.is_winding_consistent
    opened = m.faces[1:]  # a hole
    assert not is_watertight(opened) and not trimesh.Trimesh(m.vertices, opened, process=False).is_watertight
    flipped = m.faces.copy()
    flipped[0] = flipped[0, ::-1]  # closed, but one face wound the wrong way
    t = trimesh.Trimesh(m.vertices, flipped, process=False)
    assert not is_watertight(flipped) and not t.is_winding_consistent
    assert not is_watertight(np.zeros((0, 3), np.int64))


def test_clean_drops_cavities_and_small_parts_and_keeps_all_on_request():
    big, small, cavity = _sphere(0.4), _sphere(0.05, (0.7, 0, 0)), _sphere(0.2, inward=True)
    v, f = _join(big, small, cavity)
    # small sphere's area is (0.05/0.4)² = 1.6 % of the big one's
    v1, f1, rep = clean_mesh(v, f, keep_fraction=0.05)
    assert (rep.parts_before, rep.parts, rep.cavities_dropped, rep.small_dropped) == (3, 1, 1, 1)
    assert rep.watertight
    assert len(f1) == len(big.faces) and len(v1) == len(big.vertices)
    assert np.allclose(np.sort(v1, axis=0), np.sort(big.vertices, axis=0), atol=1e-6)
    v2, f2, rep2 = clean_mesh(v, f, keep_fraction=0.0)
    assert (rep2.parts, rep2.cavities_dropped, rep2.small_dropped) == (2, 1, 0)
    assert trimesh.Trimesh(v2, f2).volume == pytest.approx(big.volume + small.volume, rel=1e-6)
    v3, f3, rep3 = clean_mesh(v, f, keep_fraction=0.01)  # 1.6 % > 1 %: the small sphere stays
    assert rep3.parts == 2
    with pytest.raises(ValueError, match="keep_fraction"):
        clean_mesh(v, f, keep_fraction=1.5)
    with pytest.raises(ValueError, match="faces"):
        clean_mesh(v, f + len(v))


def test_a_hollow_voxel_shell_with_a_floater_becomes_one_closed_outward_part():
    """The refiner predicts surface *shells*: marching cubes gives an outer and an inner (cavity) surface."""
    n = 32
    c = (np.arange(n) + 0.5) / n - 0.5
    x, y, z = np.meshgrid(c, c, c, indexing="ij")
    r = np.sqrt(x**2 + y**2 + z**2)
    grid = ((r > 0.25) & (r < 0.35)).astype(np.float32)  # a hollow ball, 3 voxels thick
    grid[2:4, 2:4, 2:4] = 1.0  # a floater in a corner
    v, f = voxels_to_mesh(grid, 0.5)
    count, _ = mesh_parts(f, len(v))
    assert count == 3  # outer wall, inner wall, floater
    v1, f1, rep = clean_mesh(v, f)
    assert (rep.parts, rep.cavities_dropped, rep.small_dropped, rep.watertight) == (1, 1, 1, True)
    t = trimesh.Trimesh(v1, f1, process=False)
    assert t.is_watertight and t.is_winding_consistent and t.volume > 0  # normals outward
    # the kept surface is the outer wall: the ball of radius ~0.35 (voxel-staircase, 1/32 units)
    assert np.linalg.norm(v1, axis=1).mean() == pytest.approx(0.35, abs=1.0 / n)
