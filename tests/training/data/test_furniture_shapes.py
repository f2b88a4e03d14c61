"""training/data/sources/furniture.py and ``genre data furniture``: furniture built from parts, standing upright."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial import ConvexHull, Delaunay

from training.data.cli import main as data_main
from training.data.sources.furniture import KINDS, STYLES, furniture_shape


def _stands(mesh) -> bool:
    """Whether the mesh stands on its lowest points: the centroid of its volume-less parts, taken as the mean of its
    triangles' centres weighted by area, lies over the convex hull of the vertices within 1 mm of the floor."""
    v = np.asarray(mesh.vertices)
    floor = v[v[:, 2] <= v[:, 2].min() + 1e-3][:, :2]
    centre = (mesh.triangles_center * mesh.area_faces[:, None]).sum(axis=0)[:2] / mesh.area
    if len(np.unique(np.round(floor, 6), axis=0)) < 3:
        return False
    hull = floor[ConvexHull(floor).vertices]
    return bool(Delaunay(hull).find_simplex(centre) >= 0)


def _covers(tri_xy: np.ndarray, point: np.ndarray) -> bool:
    """Whether any triangle's projection (T, 3, 2) contains ``point`` (2,) (barycentric signs)."""
    a, b, c = tri_xy[:, 0], tri_xy[:, 1], tri_xy[:, 2]

    def cross(u, v, p):
        return (v[:, 0] - u[:, 0]) * (p[1] - u[:, 1]) - (v[:, 1] - u[:, 1]) * (p[0] - u[:, 0])

    d = np.stack([cross(a, b, point), cross(b, c, point), cross(c, a, point)], axis=1)
    inside = (d >= 0).all(axis=1) | (d <= 0).all(axis=1)
    return bool((inside & (np.abs(d).sum(axis=1) > 0)).any())  # (a vertical triangle's projection covers nothing)


@pytest.mark.parametrize("kind", KINDS)
def test_every_style_of_every_kind_is_normalised_upright_and_stands(kind):
    styles = STYLES[kind]
    for k in range(3 * len(styles)):
        sid, cls, mesh = furniture_shape(kind, k)
        assert sid == f"furniture-{kind}-{k:04d}" and cls == f"procedural-{kind}"
        lo, hi = mesh.bounds
        assert np.allclose((lo + hi) / 2, 0.0, atol=1e-9) and np.linalg.norm(hi - lo) == pytest.approx(1.0)
        assert 0 < len(mesh.faces) <= 2000 and np.isfinite(mesh.vertices).all()
        assert _stands(mesh), sid
    # the same shape on every call; another seed another shape
    np.testing.assert_array_equal(furniture_shape(kind, 3)[2].vertices, furniture_shape(kind, 3)[2].vertices)
    assert not np.allclose(furniture_shape(kind, 3, seed=1)[2].extents, furniture_shape(kind, 3)[2].extents)


def test_the_kinds_have_their_proportions():
    """Median proportions over 30 shapes a kind, along (x, y, z) with z up: what makes a bed a bed."""
    def median_extents(kind):
        return np.median([furniture_shape(kind, k)[2].extents for k in range(30)], axis=0)

    bed, shelf, lamp, bench = (median_extents(k) for k in ("bed", "shelf", "lamp", "bench"))
    assert bed[1] > bed[0] > bed[2]  # long, wide, low
    assert shelf[2] > shelf[0] > shelf[1]  # tall, wide, shallow
    assert lamp[2] > max(lamp[0], lamp[1])  # taller than wide
    assert bench[0] > 1.5 * max(bench[1], bench[2])  # long
    # chairs and tables stand on legs: no triangle in their lowest 30 % covers the point under the middle (a block would)
    for kind, k in (("chair", 0), ("chair", 1), ("table", 0)):
        mesh = furniture_shape(kind, k)[2]
        z = mesh.vertices[:, 2]
        tri = mesh.triangles[(mesh.triangles[:, :, 2] < z.min() + 0.3 * np.ptp(z)).all(axis=1)]
        assert len(tri) and not _covers(tri[:, :, :2], np.zeros(2)), (kind, k)
    assert _covers(furniture_shape("cabinet", 1)[2].triangles[:, :, :2], np.zeros(2))  # a plinth cabinet does


def test_the_command_writes_meshes_and_a_manifest_the_renderer_reads(tmp_path, capsys):
    assert data_main(["furniture", "--out", str(tmp_path), "--per-kind", "2"]) == 0
    rows = json.loads((tmp_path / "manifest.json").read_text())["shapes"]
    assert [r["id"] for r in rows] == [f"furniture-{kind}-{k:04d}" for kind in KINDS for k in range(2)]
    for row in rows:
        assert (tmp_path / row["mesh"]).is_file() and row["split"] == "product-train"
        assert row["source"] == "procedural-furniture" and row["licence"] == "CC0"
    assert data_main(["furniture", "--out", str(tmp_path), "--per-kind", "0"]) == 2
    assert "--per-kind" in capsys.readouterr().err
