"""The procedural shape source (training/data/sources/procedural.py): counts, determinism, classes outside
the research protocol, analytic volumes, clean meshes, and what the corpus builder makes of them."""

from __future__ import annotations

import json
import math
import re
import types
from collections import Counter

import numpy as np
import pytest
import trimesh

from training.data import corpus
from training.data.sources import procedural

ALLOWED = {"primitive", "csg", "extrusion", "lathe", "assembly"}


@pytest.fixture(scope="module")
def records():
    return procedural.enumerate_shapes(None)


@pytest.fixture(scope="module")
def loaded(records):
    """``{shape_id: parts}`` for every record (about 1.5 s for the 400)."""
    return {r.shape_id: r.load() for r in records}


def _of(records, kind, sub=None):
    return [r for r in records if r.extra["kind"] == kind and (sub is None or r.extra["subkind"] == sub)]


def _min_height(mesh: trimesh.Trimesh) -> float:
    """Smallest triangle height (twice the area over the longest edge)."""
    tri = mesh.triangles
    edges = np.linalg.norm(np.roll(tri, -1, axis=1) - tri, axis=2)
    return float((2.0 * mesh.area_faces / edges.max(axis=1)).min())


# ----------------------------------------------------------------------------- records


def test_counts_ids_and_metadata(records):
    assert len(records) == sum(procedural.COUNTS.values()) == 400
    kinds = Counter(r.extra["kind"] for r in records)
    assert kinds == {"primitive": 120, "csg": 80, "extrusion": 60, "lathe": 60, "assembly": 80}
    assert Counter(r.extra["subkind"] for r in _of(records, "primitive")) == {
        s: 20 for s in ("cube", "box", "cylinder", "cone", "torus", "sphere")}
    assert Counter(r.extra["subkind"] for r in _of(records, "assembly")) == {
        "chair": 14, "stool": 14, "table": 13, "shelf": 13, "cabinet": 13, "bench": 13}
    assert len({r.shape_id for r in records}) == len(records)
    for r in records:
        kind = r.extra["kind"]
        m = re.fullmatch(r"procedural-([a-z]+)-(\d{3})", r.shape_id)
        assert m and m.group(1) == kind
        index = int(m.group(2))
        assert r.path == f"procedural:{kind}/{index:03d}" and isinstance(r.path, str)
        assert r.source == "procedural" and r.package is None
        assert r.creator == "GenRe project (generated)" and r.licence == "CC0"
        assert r.family == r.shape_id and r.category == kind
        assert r.extra["subkind"] == procedural.SUBKINDS[kind][index % len(procedural.SUBKINDS[kind])]
        assert not r.align_long_axis
        json.dumps(r.extra)  # the manifest must be able to hold the parameters
        assert set(r.extra) >= {"kind", "subkind", "size", "params", "pose", "seed"}


def test_class_hints_stay_out_of_the_protocol(records):
    hints = {r.class_hint for r in records}
    assert hints == ALLOWED
    protocol = set(corpus.SEEN_CLASSES) | set(corpus.UNSEEN_CLASSES) | set(corpus.UNSEEN_PIX3D_CLASSES)
    assert not hints & protocol
    for r in records[::25]:
        cls = corpus.classify(r.name, r.category, r.class_hint)
        assert cls == r.class_hint  # no alias maps it onto a protocol class (e.g. "assembly chair" stays "assembly")
        assert corpus.split_of(r.shape_id, cls) == "unassigned" and corpus.groups_of(cls, "unassigned") == []


def test_registered_as_a_corpus_source():
    assert corpus.SOURCES["procedural"] is procedural
    assert procedural.PACKAGES == ()
    assert len(corpus.enumerate_records(None, ["procedural"])) == 400


def test_enumeration_is_deterministic(records):
    again = procedural.enumerate_shapes("/nonexistent")
    assert [r.shape_id for r in again] == [r.shape_id for r in records]
    assert [r.extra for r in again] == [r.extra for r in records]
    assert all(np.array_equal(a.rotation, b.rotation) for a, b in zip(again, records))
    # a shape does not depend on how many shapes the other kinds have
    few = procedural.enumerate_shapes(counts={"lathe": 3, "csg": 2})
    assert [r.shape_id for r in few] == ["procedural-csg-000", "procedural-csg-001", "procedural-lathe-000",
                                        "procedural-lathe-001", "procedural-lathe-002"]
    by_id = {r.shape_id: r for r in records}
    assert all(r.extra == by_id[r.shape_id].extra for r in few)
    # the meshes: one of each sub-kind, loaded from both enumerations, byte for byte
    sample = {}
    for r in records:
        sample.setdefault((r.extra["kind"], r.extra["subkind"]), r.shape_id)
    again_by_id = {r.shape_id: r for r in again}
    for shape_id in sample.values():
        first, second = by_id[shape_id].load(), again_by_id[shape_id].load()
        assert len(first) == len(second)
        for p, q in zip(first, second):
            assert np.asarray(p.vertices).tobytes() == np.asarray(q.vertices).tobytes()
            assert np.array_equal(p.faces, q.faces)


def test_rotations_are_proper_and_poses_random(records):
    for r in records:
        R = r.rotation
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert abs(np.linalg.det(R) - 1.0) < 1e-12
    for r in _of(records, "assembly"):  # upright: only a heading about Z
        np.testing.assert_allclose(r.rotation[2], [0, 0, 1], atol=1e-12)
        np.testing.assert_allclose(r.rotation[:, 2], [0, 0, 1], atol=1e-12)
        heading = math.radians(r.extra["pose"]["heading_deg"])
        np.testing.assert_allclose(r.rotation[:2, 0], [math.cos(heading), math.sin(heading)], atol=1e-12)
    posed = [r for r in records if r.extra["kind"] != "assembly"]
    for r in posed:
        np.testing.assert_allclose(r.rotation, procedural.quaternion_matrix(r.extra["pose"]["quaternion_wxyz"]))
    # a uniform rotation sends +Z to a uniform direction: its Z component is uniform on [-1, 1]
    up_z = np.array([r.rotation[2, 2] for r in posed])
    assert (np.abs(up_z) > 0.99).sum() < 0.05 * len(posed)
    assert abs(up_z.mean()) < 0.15 and 0.5 < up_z.std() < 0.65  # U(-1, 1): mean 0, std 1/sqrt(3) = 0.577
    headings = np.array([r.extra["pose"]["heading_deg"] for r in _of(records, "assembly")])
    assert headings.min() < 60 and headings.max() > 300


# ----------------------------------------------------------------------------- geometry


def test_primitive_volumes_match_the_formulas(records, loaded):
    n = procedural.CYLINDER_SECTIONS
    polygon = n / 2 * math.sin(2 * math.pi / n) / math.pi  # area of the inscribed n-gon / area of the circle
    big_n, small_n = procedural.TORUS_SECTIONS
    unit_ico = trimesh.creation.icosphere(subdivisions=procedural.SPHERE_SUBDIVISIONS).volume
    round_spheres = 0
    for r in _of(records, "primitive"):
        spec, sub = r.extra["params"], r.extra["subkind"]
        (mesh,) = loaded[r.shape_id]
        v = mesh.volume
        if sub in ("cube", "box"):
            ext = spec["extents"]
            if sub == "cube":
                assert ext[0] == ext[1] == ext[2]
            assert v == pytest.approx(ext[0] * ext[1] * ext[2], rel=1e-12)
        elif sub in ("cylinder", "cone"):
            exact = math.pi * spec["radius"] ** 2 * spec["height"] / (1 if sub == "cylinder" else 3)
            assert v == pytest.approx(exact * polygon, rel=1e-9)
            assert v < exact and v == pytest.approx(exact, rel=0.003)  # 48 segments: 0.29 % less
        elif sub == "torus":
            big, small = spec["major_radius"], spec["minor_radius"]
            exact = 2 * math.pi**2 * big * small**2
            tube = small_n / 2 * small**2 * math.sin(2 * math.pi / small_n)
            assert v == pytest.approx(big_n * math.sin(2 * math.pi / big_n) * big * tube, rel=1e-9)  # Pappus, polygonal
            assert v < exact and v == pytest.approx(exact, rel=0.015)
        else:
            a, b, c = spec["radii"]
            exact = 4 / 3 * math.pi * a * b * c
            assert v == pytest.approx(a * b * c * unit_ico, rel=1e-9)
            assert v < exact and v == pytest.approx(exact, rel=0.01)  # icosphere 3: 0.86 % less
            round_spheres += a == b == c
    assert round_spheres == 1


def test_csg_booleans_replayed(records, loaded):
    """Every step of a CSG shape: a difference removes exactly the intersection, a union adds the tool
    less the intersection; the final mesh is the replayed one (slivers removed)."""
    for r in _of(records, "csg")[::2]:  # 40 shapes, each sub-kind 5 times
        steps = r.extra["params"]["steps"]
        assert steps[0][0] == "base" and 2 <= len(steps) <= 3
        current = procedural.primitive_mesh(steps[0][1])
        for op, spec in steps[1:]:
            tool = procedural.primitive_mesh(spec)
            common = trimesh.boolean.intersection([current, tool], engine="manifold").volume
            assert common > 1e-4 * current.volume  # the tool really meets the base
            if op == "difference":
                after = trimesh.boolean.difference([current, tool], engine="manifold")
                assert after.volume < current.volume - common / 2
                assert after.volume == pytest.approx(current.volume - common, rel=1e-5)
            else:
                after = trimesh.boolean.union([current, tool], engine="manifold")
                assert after.volume > current.volume
                assert after.volume == pytest.approx(current.volume + tool.volume - common, rel=1e-5)
            current = after
        (mesh,) = loaded[r.shape_id]
        assert mesh.volume == pytest.approx(current.volume, rel=1e-6)


def test_extrusion_and_lathe_volumes(records, loaded):
    from shapely.geometry import Polygon

    for r in _of(records, "extrusion"):
        p = r.extra["params"]
        (mesh,) = loaded[r.shape_id]
        area = Polygon(p["shell"], p["holes"]).area
        assert mesh.volume == pytest.approx(area * p["depth"], rel=1e-9)
        assert len(p["holes"]) == (1 if r.extra["subkind"] == "polygon_with_hole" else 0)
        assert mesh.euler_number == (0 if p["holes"] else 2)  # a hole makes a genus-1 solid
    n = procedural.LATHE_SECTIONS
    for r in _of(records, "lathe"):
        profile = np.array(r.extra["params"]["profile"])
        assert profile[0, 0] == profile[-1, 0] == 0.0
        region = Polygon(profile)
        (mesh,) = loaded[r.shape_id]
        # Pappus for the 48-sided revolution: every horizontal section is a 48-gon
        assert mesh.volume == pytest.approx(n * math.sin(2 * math.pi / n) * region.area * region.centroid.x, rel=1e-9)


def test_meshes_are_clean(records, loaded):
    for r in records:
        parts = loaded[r.shape_id]
        faces = sum(len(p.faces) for p in parts)
        assert 12 <= faces <= 20_000, r.shape_id
        diagonal = float(np.linalg.norm(np.ptp(np.concatenate([p.vertices for p in parts]), axis=0)))
        if r.extra["kind"] == "assembly":
            assert len(parts) == len(r.extra["params"]["parts"]) >= 3
        else:
            assert len(parts) == 1
        for p in parts:  # every part (all of a non-assembly) is a closed solid with outward normals
            assert p.is_watertight and p.is_winding_consistent, r.shape_id
            assert p.volume > 0 and p.body_count == 1, r.shape_id
            assert _min_height(p) > 1e-6 * diagonal, r.shape_id  # no degenerate (or float32-degenerate) triangles
            assert len(trimesh.grouping.unique_rows(np.sort(p.faces, axis=1))[0]) == len(p.faces)
        size = np.asarray(r.extra["size"])
        raw = np.ptp(np.concatenate([p.vertices for p in parts]), axis=0)
        assert np.abs(raw - size).max() < 0.005 * np.linalg.norm(size), r.shape_id  # recorded = built
        assert size.min() >= procedural.MIN_SIDE * np.linalg.norm(size) - 1e-4


def test_assemblies_stand_on_the_floor_with_the_back_at_plus_y(records, loaded):
    for r in _of(records, "assembly"):
        verts = np.concatenate([p.vertices for p in loaded[r.shape_id]])
        assert abs(verts[:, 2].min()) <= 1e-4 + 1e-12, r.shape_id  # parameters are rounded to 1e-4
    for r in _of(records, "assembly", "chair"):
        seat_height = r.extra["params"]["seat"][2]
        verts = np.concatenate([p.vertices for p in loaded[r.shape_id]])
        back = verts[verts[:, 2] > seat_height + 0.05]
        assert back[:, 2].max() > seat_height + 0.25  # a back ...
        assert back[:, 1].min() > 0.05  # ... wholly behind the seat's centre: the front faces -Y


# ----------------------------------------------------------------------------- what the corpus builder makes of them


def test_the_builder_keeps_every_shape(records, loaded):
    entries = []
    for r in records:
        parts = loaded[r.shape_id]
        assert corpus.check_geometry(parts) is None
        normalised, _ = corpus.normalise_parts(parts, r.rotation)
        assert corpus.junk_reason(r.name, normalised) is None, r.shape_id
        extents = np.ptp(np.concatenate([p.vertices for p in normalised]), axis=0)
        assert extents.min() > 0.1 > corpus.MIN_THICKNESS
        entries.append(types.SimpleNamespace(
            id=r.shape_id, source=r.source, cls=r.class_hint, family=r.family, extents=extents.tolist(),
            faces=sum(len(p.faces) for p in normalised), vertices=sum(len(p.vertices) for p in normalised)))
    assert corpus.find_near_duplicates(entries) == {}


def test_process_record_writes_normalised_glbs(records, tmp_path):
    shapes = tmp_path / "shapes"
    shapes.mkdir()
    by_id = {r.shape_id: r for r in records}
    chosen = ["procedural-primitive-004", "procedural-csg-005", "procedural-extrusion-005", "procedural-lathe-003",
              "procedural-assembly-000"]
    for shape_id in chosen:
        record = by_id[shape_id]
        result = corpus.process_record(record, tmp_path, shapes)
        assert "entry" in result, result
        entry = result["entry"]
        assert entry.cls == record.class_hint and entry.split == "unassigned" and entry.groups == []
        assert entry.watertight  # an assembly too: its parts are closed, each edge has two faces
        assert entry.path == record.path and entry.licence == "CC0"
        assert entry.extra["subkind"] == record.extra["subkind"] and "source_rotation" in entry.extra
        np.testing.assert_allclose(np.array(entry.extra["source_rotation"]), record.rotation, atol=1e-8)
        assert np.linalg.norm(entry.extents) == pytest.approx(1.0, abs=1e-6)
        glb = trimesh.load(shapes / f"{shape_id}.glb", force="scene")
        lo, hi = glb.bounds
        assert np.linalg.norm(hi - lo) == pytest.approx(1.0, abs=1e-5)
        np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-5)
        assert sum(len(g.faces) for g in glb.geometry.values()) == entry.faces


# ----------------------------------------------------------------------------- validation


@pytest.mark.parametrize("spec", [
    {"type": "blob", "radius": 1.0},
    {"type": "box", "extents": [1.0, -1.0, 1.0]},
    {"type": "box", "extents": [1.0, 1.0]},
    {"type": "cylinder", "radius": 0.0, "height": 1.0},
    {"type": "cylinder", "radius": 1.0, "height": 1.0, "axis": "w"},
    {"type": "cone", "radius": 1.0},
    {"type": "torus", "major_radius": 0.5, "minor_radius": 0.5},
    {"type": "sphere", "radii": [1.0, float("nan"), 1.0]},
    {"type": "box", "extents": [1.0, 1.0, 1.0], "centre": [0.0, 0.0]},
])
def test_bad_specs_are_refused(spec):
    with pytest.raises(ValueError):
        procedural.primitive_mesh(spec)


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="unknown procedural kind"):
        procedural.build_parts("blob", {})
    with pytest.raises(ValueError, match="axis"):
        procedural.build_parts("lathe", {"profile": [[0.1, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]})
    with pytest.raises(ValueError, match="crosses itself"):
        procedural.build_parts("lathe", {"profile": [[0.0, 0.0], [1.0, 0.0], [0.5, 1.0], [1.0, 1.0], [0.5, 0.0],
                                                     [0.0, 1.0]]})
    with pytest.raises(ValueError, match="csg operation"):
        procedural.build_parts("csg", {"steps": [["base", {"type": "box", "extents": [1, 1, 1]}],
                                                 ["xor", {"type": "box", "extents": [1, 1, 1]}]]})
    with pytest.raises(ValueError, match="unknown procedural kinds"):
        procedural.enumerate_shapes(counts={"blob": 1})
    with pytest.raises(ValueError, match="quaternion"):
        procedural.quaternion_matrix([0.0, 0.0, 0.0, 0.0])
