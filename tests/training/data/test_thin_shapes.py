"""The procedural flat and thin shapes (training/data/sources/thin.py) and their place in the training pack:
deterministic, normalised, thin, small, and never a test shape."""

from __future__ import annotations


import numpy as np
import pytest
import trimesh

from training.data.sources.thin import KINDS, MAX_FACES, thin_shapes
from support.tiny_data import write_manifest

COUNT = 6  # per kind: every sub-kind at least once (the most sub-kinds of a kind is 4)


@pytest.fixture(scope="module")
def shapes():
    return thin_shapes(COUNT)


def test_thin_shapes_are_deterministic(shapes):
    again = thin_shapes(COUNT)
    assert [s[:2] for s in again] == [s[:2] for s in shapes]
    for (_, _, a), (_, _, b) in zip(shapes, again):
        assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    # shape k does not depend on the count; another seed gives other shapes
    assert np.array_equal(thin_shapes(1)[0][2].vertices, shapes[0][2].vertices)
    assert not np.array_equal(thin_shapes(1, seed=1)[0][2].vertices, shapes[0][2].vertices)


def test_thin_shapes_ids_classes_and_counts(shapes):
    assert len(shapes) == COUNT * len(KINDS)
    assert [s[0] for s in shapes] == [f"thin-{kind}-{k:03d}" for kind in KINDS for k in range(COUNT)]
    assert [s[1] for s in shapes] == [f"thin-{kind}" for kind in KINDS for _ in range(COUNT)]
    assert thin_shapes(0) == []
    with pytest.raises(ValueError):
        thin_shapes(-1)


def test_thin_shapes_are_normalised_small_and_thin(shapes):
    ratios = {}
    for sid, cls, mesh in shapes:
        assert isinstance(mesh, trimesh.Trimesh) and 0 < len(mesh.faces) <= MAX_FACES, sid
        lo, hi = mesh.bounds
        assert abs(np.linalg.norm(hi - lo) - 1.0) < 1e-6, sid
        assert np.abs(lo + hi).max() < 1e-9, sid
        extents = np.sort(mesh.bounding_box_oriented.primitive.extents)
        ratios[sid] = extents[0] / extents[-1]
        if cls == "thin-bowl":
            # a bowl is deep; its wall is thin: volume / area is about half the wall (diagonal 1)
            assert mesh.is_watertight, sid
            assert 0 < mesh.volume / mesh.area < 0.02, sid
    flat = [r for sid, r in ratios.items() if not sid.startswith("thin-bowl-")]
    assert np.mean(np.asarray(flat) < 0.15) >= 0.9, sorted(ratios.items(), key=lambda kv: -kv[1])[:8]
    assert np.median(flat) < 0.1


def test_pack_adds_thin_shapes_and_still_holds_no_test_shape(tmp_path):
    from training.data.pack import build_pack, read_pack

    box = trimesh.creation.box(extents=(0.6, 0.3, 0.4))
    held_out = trimesh.creation.cylinder(0.3, 0.5)
    manifest = write_manifest(tmp_path, {"box": (box, "product-train"), "cyl": (held_out, "product-test")})
    meta = build_pack(manifest, tmp_path / "pack", thin=2)
    pack = read_pack(tmp_path / "pack")
    assert len(pack) == 1 + 2 * len(KINDS) and meta["thin"] == 2
    assert pack.ids == ["box"] + [f"thin-{kind}-{k:03d}" for kind in KINDS for k in range(2)]
    assert meta["classes"] == {"primitive": 1, **{f"thin-{kind}": 2 for kind in KINDS}}
    assert all(s["source"] == "procedural-thin" and s["licence"] == "CC0" for s in meta["shapes"][1:])
    # the thin shapes come back as they were made, to the quantisation step
    made = thin_shapes(2)
    for i, (sid, _, mesh) in enumerate(made, start=1):
        v, f = pack.mesh(i)
        assert len(f) <= len(mesh.faces)
        assert np.abs(v.min(0) - mesh.bounds[0]).max() < 1e-4 and np.abs(v.max(0) - mesh.bounds[1]).max() < 1e-4, sid
    assert build_pack(manifest, tmp_path / "plain")["thin"] == 0
    with pytest.raises(ValueError, match="never a test split"):
        build_pack(manifest, tmp_path / "bad", split="product-test", thin=2)
    with pytest.raises(ValueError, match="thin"):
        build_pack(manifest, tmp_path / "bad", thin=-1)


# ---------------------------------------------------------------- the flat-from-above eval shapes


def test_lying_rotation_is_a_rotation_that_puts_the_thinnest_axis_up():
    rng = np.random.default_rng(3)
    box = trimesh.creation.box(extents=(0.9, 0.5, 0.05))
    q = rng.normal(size=4)
    from training.data.sources.procedural import quaternion_matrix
    from training.data.sources.thin import lying_rotation

    turned = np.asarray(box.vertices) @ quaternion_matrix(q).T  # some pose
    for flip in (False, True):
        r = lying_rotation(turned, yaw=0.0, flip=flip)
        assert np.allclose(r @ r.T, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(r), 1.0)
        ext = np.ptp(turned @ r.T, axis=0)
        assert np.allclose(ext, (0.9, 0.5, 0.05), atol=1e-6)  # largest along X, thinnest along Z (yaw 0)


def test_flat_test_shapes_lie_flat_and_are_not_training_shapes():
    from training.data.sources.thin import FLAT_KINDS, flat_test_shape

    pack_vertices = [m.vertices for _, _, m in thin_shapes(2)]
    for kind in FLAT_KINDS:
        for k in range(2):
            sid, cls, mesh = flat_test_shape(kind, k)
            assert sid == f"flat-{kind}-{k:03d}" and cls == f"thin-{kind}"
            ext = mesh.extents
            assert np.isclose(np.linalg.norm(ext), 1.0) and ext[2] < 0.2 * max(ext[0], ext[1])  # lying flat
            assert not any(v.shape == mesh.vertices.shape and np.allclose(v, mesh.vertices) for v in pack_vertices)
            again = flat_test_shape(kind, k)[2]
            assert np.array_equal(again.vertices, mesh.vertices)
    with pytest.raises(ValueError, match="not a flat kind"):
        flat_test_shape("rod", 0)


def test_genre_data_flat_test_writes_a_manifest_the_renderer_reads(tmp_path):
    from training.data.cli import main
    from training.data.views import read_shapes

    assert main(["flat-test", "--out", str(tmp_path), "--per-kind", "1"]) == 0
    shapes = read_shapes(tmp_path / "manifest.json")
    assert [s.id for s in shapes] == ["flat-plate-000", "flat-card-000", "flat-book-000", "flat-leaf-000"]
    for s in shapes:
        assert s.split == "flat-test" and s.groups == ("flat-from-above",) and s.path.is_file()
        mesh = trimesh.load(s.path, force="mesh")
        assert mesh.extents[2] < 0.2 * mesh.extents[:2].max()
    assert main(["flat-test", "--out", str(tmp_path), "--per-kind", "0"]) == 2


def test_lying_thin_shapes_are_the_packs_meshes_laid_flat():
    from training.data.sources.thin import lying_thin_shape

    for (sid, cls, packed), kind in zip(thin_shapes(1), ("plate", "card", "book", "leaf", "bowl", "rod")):
        lid, lcls, lying = lying_thin_shape(kind, 0)
        assert (lid, lcls) == (sid, cls) == (f"thin-{kind}-000", f"thin-{kind}")
        assert np.isclose(np.linalg.norm(lying.extents), 1.0)
        # the same mesh in another pose: its faces, and its vertices' pairwise distances up to the scale of the
        # two normalisations (each is scaled to an axis-aligned diagonal of 1), are the pack's
        assert np.array_equal(lying.faces, packed.faces)
        d_lying = np.linalg.norm(lying.vertices[1:] - lying.vertices[0], axis=1)
        d_packed = np.linalg.norm(packed.vertices[1:] - packed.vertices[0], axis=1)
        assert np.allclose(d_lying / d_lying.max(), d_packed / d_packed.max(), atol=1e-9)
        # lying: the thinnest principal axis is vertical, so the vertical extent is the smallest
        assert lying.extents[2] <= lying.extents[:2].min() + 1e-9


def test_genre_data_thin_writes_training_shapes_the_renderer_reads(tmp_path):
    from training.data.cli import main
    from training.data.views import read_shapes

    assert main(["thin", "--out", str(tmp_path), "--per-kind", "1"]) == 0
    shapes = read_shapes(tmp_path / "manifest.json")
    assert [s.id for s in shapes] == [f"thin-{k}-000" for k in ("plate", "card", "book", "leaf", "bowl", "rod")]
    for s in shapes:
        assert s.split == "product-train" and s.groups == ("thin",) and s.path.is_file()
        mesh = trimesh.load(s.path, force="mesh")
        assert mesh.extents[2] <= mesh.extents[:2].min() + 1e-6
    assert main(["thin", "--out", str(tmp_path), "--per-kind", "0"]) == 2
