"""Corpus building on small catalogues and folders made in the test (no network, no packages)."""

from __future__ import annotations

import json
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh

from training.data import corpus
from training.data.cli import format_credits, format_stats
from training.data.cli import main as data_main
from training.data.sources import Y_UP_FRONT_POS_Z, rotation_from_axes, sweethome3d


def _box_obj(sx: float, sy: float, sz: float, offset=(0.0, 0.0, 0.0), mtl: str | None = None) -> str:
    """An OBJ box of size (sx, sy, sz) with its min corner at ``offset``."""
    ox, oy, oz = offset
    lines = [f"mtllib {mtl}", "usemtl wood"] if mtl else []
    for x in (0, sx):
        for y in (0, sy):
            for z in (0, sz):
                lines.append(f"v {x + ox} {y + oy} {z + oz}")
    quads = [(1, 2, 4, 3), (5, 7, 8, 6), (1, 5, 6, 2), (3, 4, 8, 7), (1, 3, 7, 5), (2, 6, 8, 4)]
    lines += [f"f {a} {b} {c} {d}" for a, b, c, d in quads]
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- properties / Sweet Home 3D


def test_parse_properties_latin1_escapes_and_continuations():
    data = (
        "# comment\n! other comment\n"
        "name#1=Fauteuil \\u00e0 bascule\n"
        "name#2 = Caf\xe9 table\n"
        "category#1:Living room\n"
        "creator#1=Jane \\\n    Doe\n"
        "model#1=/cat/chair/chair.obj\n"
        "modelRotation#1=1 0 0 0 0 1 0 -1 0\n"
        "key\\=with\\:colon=v\n"
    ).encode("latin-1")
    props = sweethome3d.parse_properties(data)
    assert props["name#1"] == "Fauteuil à bascule"
    assert props["name#2"] == "Café table"
    assert props["category#1"] == "Living room"
    assert props["creator#1"] == "Jane Doe"
    assert props["key=with:colon"] == "v"
    entries = sweethome3d.catalogue_entries(props)
    assert len(entries) == 1 and entries[0]["index"] == "1" and entries[0]["model"] == "/cat/chair/chair.obj"
    r = sweethome3d.parse_model_rotation(entries[0]["modelRotation"])
    np.testing.assert_allclose(r @ np.array([0.0, 0.0, 1.0]), [0, 1, 0])  # file's +Z becomes SH3D's up (+Y)


def _write_catalogue(root: Path) -> Path:
    """A fake sweethome3d-furniture tree with a CC0 catalogue of two pieces."""
    folder = root / "sweethome3d-furniture" / "usr/share/sweethome3d/furniture"
    folder.mkdir(parents=True)
    archive = folder / "BlendSwap-CC-0.sh3f"
    props = (
        "id=test\nname=Test catalogue\n"
        # piece 1: a Z-up chair-like tall box (40 wide, 50 deep, 100 high in SH3D terms), needs modelRotation
        "id#1=Test#tallchair\nname#1=Bar stool\ncategory#1=Kitchen\ncreator#1=Ann \\u00c5berg\n"
        "model#1=/cat/stool/stool.obj\nmultiPartModel#1=true\nmodelRotation#1=1 0 0 0 0 1 0 -1 0\n"
        "width#1=40\ndepth#1=50\nheight#1=100\n"
        # piece 2: a Y-up table (120 wide, 75 high, 80 deep), no rotation
        "id#2=Test#table\nname#2=Dining table\ncategory#2=Kitchen\ncreator#2=Bo\n"
        "model#2=/cat/table.obj\nwidth#2=120\ndepth#2=80\nheight#2=75\n"
    ).encode("latin-1")
    mtl = "newmtl wood\nKd 0.6 0.4 0.2\n"
    with zipfile.ZipFile(archive, "w") as zf:
        zf.writestr("PluginFurnitureCatalog.properties", props)
        # Z-up file: x = width 40, y = -depth (any sign), z = height 100
        zf.writestr("cat/stool/stool.obj", _box_obj(40, 50, 100, offset=(5, 5, 0), mtl="stool.mtl"))
        zf.writestr("cat/stool/stool.mtl", mtl)
        zf.writestr("cat/table.obj", _box_obj(120, 75, 80))
    return archive


def test_sweethome3d_catalogue_rotation_class_and_licence(tmp_path):
    _write_catalogue(tmp_path / "cache" / "unpacked")
    records = sweethome3d.enumerate_shapes(tmp_path / "cache" / "unpacked")
    assert [r.name for r in records] == ["Bar stool", "Dining table"]
    stool, table = records
    assert stool.licence == "CC0" and stool.creator == "Ann Åberg" and stool.category == "Kitchen"
    np.testing.assert_allclose(table.rotation, Y_UP_FRONT_POS_Z)
    shapes = tmp_path / "shapes"
    shapes.mkdir()
    out = corpus.process_record(stool, tmp_path, shapes)
    entry = out["entry"]
    assert entry.cls == "chair" and entry.split in ("train", "test")
    # canonical extents follow the catalogue's width/depth/height on X/Y/Z
    expected = np.array([40, 50, 100]) / np.linalg.norm([40, 50, 100])
    np.testing.assert_allclose(entry.extents, expected, atol=1e-6)
    assert entry.extra["catalogue_extent_error"] < 1e-6
    assert entry.faces == 12 and entry.parts == 1 and entry.watertight
    # the written GLB is normalised: bbox centre 0, diagonal 1
    glb = trimesh.load(shapes / f"{stool.shape_id}.glb", force="mesh")
    lo, hi = glb.bounds
    np.testing.assert_allclose((lo + hi) / 2, 0, atol=1e-6)
    assert np.linalg.norm(hi - lo) == pytest.approx(1.0, abs=1e-6)
    assert hi[2] - lo[2] == pytest.approx(expected[2], abs=1e-6)  # the stool stands along Z
    # the table (Y-up file): its 75 cm height ends up on Z
    t = corpus.process_record(table, tmp_path, shapes)["entry"]
    np.testing.assert_allclose(t.extents, np.array([120, 80, 75]) / np.linalg.norm([120, 80, 75]), atol=1e-6)
    assert t.cls == "table" and t.split == "unseen" and t.groups == ["unseen", "unseen-pix3d"]


# ----------------------------------------------------------------------------- geometry


def test_normalise_parts_centre_diagonal_and_transform():
    rng = np.random.default_rng(0)
    a = trimesh.creation.box(extents=(2.0, 4.0, 1.0))
    a.apply_translation((100.0, -20.0, 3.0))
    b = trimesh.Trimesh(rng.normal(size=(5, 3)) * 3 + 100, [[0, 1, 2], [2, 3, 4]])
    rotation = rotation_from_axes("+y", "+z")
    parts, transform = corpus.normalise_parts([a, b], rotation)
    v = np.concatenate([p.vertices for p in parts])
    lo, hi = v.min(0), v.max(0)
    np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-9)
    assert np.linalg.norm(hi - lo) == pytest.approx(1.0, abs=1e-9)
    # the transform maps the original vertices to the returned ones
    orig = np.concatenate([a.vertices, b.vertices])
    np.testing.assert_allclose(orig @ transform[:3, :3].T + transform[:3, 3], v, atol=1e-12)
    scale = np.linalg.norm(transform[:3, 0])
    np.testing.assert_allclose(transform[:3, :3] / scale, rotation, atol=1e-12)


def test_align_long_axis_turns_length_onto_y():
    hull = trimesh.creation.box(extents=(10.0, 2.0, 1.0))
    parts, transform = corpus.normalise_parts([hull], np.eye(3), align_long_axis=True)
    ext = np.ptp(parts[0].vertices, axis=0)
    assert ext[1] > ext[0] and ext[1] == pytest.approx(10 / np.linalg.norm([10, 2, 1]))
    assert np.linalg.det(transform[:3, :3]) > 0


def test_rotation_from_axes():
    np.testing.assert_allclose(rotation_from_axes("y", "+z"), Y_UP_FRONT_POS_Z)
    np.testing.assert_allclose(rotation_from_axes("+z", "-y"), np.eye(3))
    r = rotation_from_axes("z", "x")  # front +X must end at -Y
    np.testing.assert_allclose(r @ [1, 0, 0], [0, -1, 0], atol=1e-12)
    with pytest.raises(ValueError):
        rotation_from_axes("y", "y")


def test_check_geometry_reasons():
    good = trimesh.creation.box()
    assert corpus.check_geometry([good]) is None
    assert corpus.check_geometry([]) == "empty"
    nan = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [np.nan, 1, 0]], [[0, 1, 2]], process=False)
    assert corpus.check_geometry([nan]) == "nan-vertices"
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], process=False)
    assert corpus.check_geometry([flat]) == "zero-area"
    huge = trimesh.creation.box(extents=(1e6, 1, 1))
    assert corpus.check_geometry([huge]).startswith("absurd-size")


def test_junk_rules():
    plane = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0], [0, 0, 1e-6]] , [[0, 1, 2], [0, 2, 3]] * 7)
    assert corpus.junk_reason("sea", [plane]).startswith("junk: flat")
    assert corpus.junk_reason("x", [trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 1]], [[0, 1, 2]])]).startswith(
        "junk: 1 triangles"
    )
    assert "name" in corpus.junk_reason("Shadow", [trimesh.creation.box()])
    assert corpus.junk_reason("Chair", [trimesh.creation.box()]) is None


# ----------------------------------------------------------------------------- classes and split

CLASS_CASES = [
    ("Armchair", "chair"), ("Bar stool", "chair"), ("Office chair", "chair"), ("Rocking chair", "chair"),
    ("Wheelchair", "other"), ("Sofa bed", "sofa"), ("Corner sofa", "sofa"), ("Double bed", "bed"),
    ("Bunk bed", "bed"), ("Bedside table", "cabinet"), ("Coffee table", "table"), ("Table lamp", "lamp"),
    ("Desk lamp", "lamp"), ("Desk", "desk"), ("Bookcase", "bookcase"), ("Wall shelves", "bookcase"),
    ("Wardrobe", "wardrobe"), ("Kitchen cabinet", "cabinet"), ("Chest of drawers", "cabinet"),
    ("Flat screen TV", "display"), ("Computer monitor", "display"), ("Speaker", "speaker"),
    ("Telephone", "phone"), ("Headphones", "other"), ("Garden bench", "bench"), ("Workbench", "other"),
    ("Sailboat", "vessel"), ("Rowboat", "vessel"), ("Shipping container", "other"), ("Car", "car"),
    ("Humvee-pickup-odrab-low-poly", "car"), ("VW new beetle", "car"), ("Bathtub", "other"),
    ("Rocking horse", "other"), ("TV remote control", "other"), ("TV stand", "cabinet"), ("Table fan", "other"),
    ("Table tennis bat", "other"), ("Wardrobe with drawers", "wardrobe"), ("Apple iPhone", "phone"),
]


@pytest.mark.parametrize("name, expected", CLASS_CASES)
def test_class_rules(name, expected):
    assert corpus.classify(name) == expected


def test_class_hint_aliases_and_category():
    assert corpus.classify("whatever", class_hint="Armchair") == "chair"
    assert corpus.classify("whatever", class_hint="watercraft") == "vessel"
    assert corpus.classify("Chair", class_hint="airplane") == "airplane"  # the source's class wins
    assert corpus.classify("Halogen", category="Lights") == "lamp"
    assert corpus.classify("Halogen", category="Kitchen") == "other"


def test_split_is_deterministic_and_near_15_percent():
    ids = [f"src-shape-{i}" for i in range(4000)]
    first = [corpus.split_of(i, "chair") for i in ids]
    assert first == [corpus.split_of(i, "chair") for i in ids]
    frac = first.count("test") / len(first)
    assert 0.13 < frac < 0.17
    assert set(first) == {"train", "test"}
    assert corpus.split_of("x", "sofa") == "unseen" and corpus.groups_of("sofa", "unseen") == ["unseen", "unseen-pix3d"]
    assert corpus.groups_of("bed", "unseen") == ["unseen-pix3d"]
    assert corpus.groups_of("lamp", "unseen") == ["unseen"]
    assert corpus.split_of("x", "helicopter") == "unassigned" and corpus.groups_of("helicopter", "unassigned") == []


def test_product_split_holds_out_every_class_and_keeps_families_and_seen_test():
    shapes = [(f"air-{i}", "airplane", corpus.split_of(f"air-{i}", "airplane"), f"air-{i}") for i in range(300)]
    shapes += [(f"lamp-{i}", "lamp", "unseen", f"lamp-fam-{i // 3}") for i in range(600)]  # families of 3 variants
    shapes += [("pair-a", "speaker", "unseen", "pair-a"), ("pair-b", "speaker", "unseen", "pair-b")]
    shapes += [("lonely", "balloon", "unassigned", "lonely")]
    groups = corpus.product_groups(shapes)
    assert groups == corpus.product_groups(list(reversed(shapes)))  # order does not matter
    assert set(groups) == {s[0] for s in shapes} and set(groups.values()) <= set(corpus.PRODUCT_GROUPS)
    # seen classes: exactly the protocol's test split (the protocol model never trained on a product test shape)
    assert all((groups[sid] == "product-test") == (split == "test") for sid, cls, split, _ in shapes if cls == "airplane")
    # other classes: about the fraction, whole families on one side
    lamps = [s for s in shapes if s[1] == "lamp"]
    frac = sum(groups[s[0]] == "product-test" for s in lamps) / len(lamps)
    assert 0.10 < frac < 0.20
    by_family: dict[str, set] = {}
    for sid, _, _, fam in lamps:
        by_family.setdefault(fam, set()).add(groups[sid])
    assert all(len(v) == 1 for v in by_family.values())
    # a class of two still holds one out; a class of one trains
    assert sorted(groups[s] for s in ("pair-a", "pair-b")) == ["product-test", "product-train"]
    assert groups["lonely"] == "product-train"


# ----------------------------------------------------------------------------- whole build on a folder


def _write_folder(root: Path) -> Path:
    meshes = root / "meshes"
    (meshes / "armchair").mkdir(parents=True)
    (meshes / "table").mkdir()
    (meshes / "armchair" / "a.obj").write_text(_box_obj(1, 1, 2))
    (meshes / "armchair" / "b_copy.obj").write_text(_box_obj(1, 1, 2, offset=(7, 7, 7)))  # same geometry
    (meshes / "armchair" / "broken.ac").write_text("AC3Db\nOBJECT world\nkids 1\nOBJECT poly\nnumvert 3\n0 0\n")
    (meshes / "table" / "t.obj").write_text(_box_obj(3, 2, 1))
    (meshes / "table" / "flat.obj").write_text(_box_obj(3, 2, 0))
    tri = "OBJECT poly\nnumvert 3\n{}\nnumsurf 1\nSURF 0x10\nmat 0\nrefs 3\n0 0 0\n1 0 0\n2 0 0\nkids 0\n"
    (meshes / "table" / "nan.ac").write_text("AC3Db\nOBJECT world\nkids 1\n" + tri.format("0 0 0\n1 0 0\nnan 1 0"))
    (meshes / "table" / "line.ac").write_text("AC3Db\nOBJECT world\nkids 1\n" + tri.format("0 0 0\n1 0 0\n2 0 0"))
    return meshes


def test_build_folder_skips_bad_files_and_collapses_duplicates(tmp_path, capsys):
    meshes = _write_folder(tmp_path)
    data = tmp_path / "data"
    manifest = corpus.build(data, sources=[], extra_specs=[("folder", str(meshes), {})], jobs=1)
    kept = {s["name"]: s for s in manifest["shapes"]}
    assert set(kept) == {"a", "t"}
    reasons = {s["name"]: s["reason"] for s in manifest["skipped"]}
    assert reasons["broken"].startswith("unreadable")
    assert reasons["b_copy"] == f"near-duplicate of {kept['a']['id']}"
    assert reasons["flat"].startswith("junk: flat")
    assert reasons["nan"] == "nan-vertices"
    assert reasons["line"] == "zero-area"
    assert len(reasons) == 5
    a = kept["a"]
    assert a["class"] == "chair" and a["split"] in ("train", "test") and a["faces"] == 12
    assert a["licence"] == "unknown" and a["source"] == "folder"
    np.testing.assert_allclose(np.linalg.norm(a["extents"]), 1.0, atol=1e-6)
    np.testing.assert_allclose(a["extents"], np.array([1, 1, 2]) / np.sqrt(6), atol=1e-6)
    t = np.array(a["transform"])
    assert t.shape == (4, 4) and t[3].tolist() == [0, 0, 0, 1]
    on_disk = json.loads((data / "corpus" / "manifest.json").read_text())
    assert on_disk["splits"]["unseen"] == [kept["t"]["id"]] == on_disk["splits"]["unseen-pix3d"]
    glbs = sorted(p.name for p in (data / "corpus" / "shapes").glob("*.glb"))
    assert glbs == sorted(f"{s['id']}.glb" for s in manifest["shapes"])
    mesh = trimesh.load(data / "corpus" / "shapes" / glbs[0], force="mesh")
    lo, hi = mesh.bounds
    np.testing.assert_allclose((lo + hi) / 2, 0, atol=1e-6)
    assert np.linalg.norm(hi - lo) == pytest.approx(1.0, abs=1e-6)
    # stats through the CLI
    assert data_main(["stats", "--data-dir", str(data)], prog="genre data") == 0
    out = capsys.readouterr().out
    assert "Class rules" in out and "near-duplicate [folder]" in out
    assert "chair" in out and "unreadable [folder]" in out
    text = format_stats(on_disk)
    assert "TOTAL" in text
    # credits: one table row per shape of the split, with its creator and licence
    assert data_main(["credits", "--data-dir", str(data), "--split", "unseen", "--out", str(tmp_path / "c.md")], prog="genre data") == 0
    rows = [line for line in (tmp_path / "c.md").read_text().splitlines() if line.startswith(f"| {kept['t']['id']} ")]
    assert len(rows) == 1 and kept["t"]["licence"] in rows[0]
    with pytest.raises(ValueError, match="no shapes"):
        format_credits(on_disk, "no-such-split")


def test_fetch_downloads_unpacks_then_caches(tmp_path):
    calls = []

    def runner(cmd, cwd=None, capture_output=True, text=True):
        calls.append(cmd[:2])
        if cmd[:2] == ["apt-get", "download"]:
            (Path(cwd) / f"{cmd[2]}_1.0_all.deb").write_bytes(b"deb")
        elif cmd[:2] == ["dpkg", "-x"]:
            (Path(cmd[3]) / "usr").mkdir()
            (Path(cmd[3]) / "usr" / "file").write_text("x")
        return subprocess.CompletedProcess(cmd, 0, "", "")

    status = corpus.fetch(["gl-117-data"], tmp_path, runner=runner)
    assert status == {"gl-117-data": "unpacked"}
    assert calls == [["apt-get", "download"], ["dpkg", "-x"]]
    target = tmp_path / "cache" / "unpacked" / "gl-117-data"
    assert (target / "usr" / "file").read_text() == "x" and (target / ".complete").is_file()
    assert corpus.fetch(["gl-117-data"], tmp_path, runner=runner) == {"gl-117-data": "cached"}
    assert len(calls) == 2

    def failing(cmd, cwd=None, capture_output=True, text=True):
        return subprocess.CompletedProcess(cmd, 100, "", "E: Unable to locate package")

    assert corpus.fetch(["no-such-pkg"], tmp_path, runner=failing)["no-such-pkg"].startswith("failed")
    assert corpus.fetch(["Bad Name"], tmp_path, runner=failing)["Bad Name"].startswith("failed")


def test_data_dir_resolution_order(monkeypatch, tmp_path):
    """explicit → $GENRE_HOME → $GENRE_DATA_DIR (the old name) → $XDG_CACHE_HOME/genre → ~/.cache/genre."""
    for name in ("GENRE_HOME", "GENRE_DATA_DIR", "XDG_CACHE_HOME"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert corpus.data_dir() == (tmp_path / "home" / ".cache" / "genre").resolve()
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/cache")  # the XDG spec: a relative path is ignored
    assert corpus.data_dir() == (tmp_path / "home" / ".cache" / "genre").resolve()
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert corpus.data_dir() == (tmp_path / "xdg" / "genre").resolve()
    monkeypatch.setenv("GENRE_DATA_DIR", str(tmp_path / "old"))
    assert corpus.data_dir() == (tmp_path / "old").resolve()
    monkeypatch.setenv("GENRE_HOME", str(tmp_path / "new"))
    assert corpus.data_dir() == (tmp_path / "new").resolve()
    assert corpus.data_dir(tmp_path / "explicit") == (tmp_path / "explicit").resolve()
    monkeypatch.setenv("GENRE_HOME", "")  # empty counts as unset
    assert corpus.data_dir() == (tmp_path / "old").resolve()
    monkeypatch.setenv("GENRE_HOME", "~/g")
    assert corpus.data_dir() == (tmp_path / "home" / "g").resolve()
    # the home lies outside the checkout unless asked for, and nothing is created
    monkeypatch.delenv("GENRE_HOME"), monkeypatch.delenv("GENRE_DATA_DIR")
    assert corpus.REPO_ROOT not in corpus.data_dir().parents and not (tmp_path / "xdg").exists()


def test_the_chains_resolve_the_home_as_python_does(monkeypatch, tmp_path, capsys):
    """genre chain asks data_dir() (--dry-run: nothing written): its paths lie under the same home."""
    from training.chain import main

    for name in ("GENRE_HOME", "GENRE_DATA_DIR"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert main(["protocol", "--dry-run"]) == 0
    eval_line = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("eval:"))
    assert "--data $GENRE_HOME/views/eval " in eval_line and "--run $GENRE_HOME/runs/default " in eval_line
    assert "--manifest $GENRE_HOME/corpus/manifest.json " in eval_line and "--out results/default " in eval_line
    from training.chain import CHAINS

    home = (tmp_path / "xdg" / "genre").resolve()
    chain = CHAINS["protocol"].build("protocol", corpus.data_dir())
    step = next(s for s in chain.steps if s.name == "eval")
    assert home / "views" / "eval" in step.reads and step.action.args[:3] == ("eval", "--data", str(home / "views" / "eval"))
    assert not (tmp_path / "xdg").exists()


def _entry(shape_id: str, faces: int, vertices: int, extents, family: str = "") -> corpus.ManifestRecord:
    return corpus.ManifestRecord(
        id=shape_id, source="s", package=None, path="p", name=shape_id, category="", creator="", licence="x",
        cls="vessel", split="unseen", groups=["unseen"], faces=faces, vertices=vertices, parts=1,
        watertight=False, textured=False, extents=list(extents), transform=np.eye(4).tolist(), mesh="m",
        family=family or shape_id,
    )


def test_near_duplicate_rules():
    e = [0.15, 0.97, 0.18]
    entries = [
        _entry("a-livery1", 500, 300, e),
        _entry("a-livery2", 500, 300, [0.1505, 0.9695, 0.18]),  # (a): same counts, extents within 1e-3
        _entry("b-hull1", 2314, 1500, [0.30, 0.90, 0.31]),
        _entry("b-hull2", 2132, 1400, [0.3004, 0.9, 0.31]),  # (c): >= 1000 faces, 8% fewer faces
        _entry("c-small1", 200, 120, [0.5, 0.5, 0.7071]),
        _entry("c-small2", 190, 110, [0.5, 0.5, 0.7071]),  # too simple for (c): kept
        _entry("d-body-kit", 1000, 600, [0.4, 0.85, 0.34], family="d"),
        _entry("d-body-wrc", 1040, 640, [0.41, 0.845, 0.335], family="d"),  # (b): same family, 4% faces
        _entry("e-other", 500, 300, [0.1505, 0.9695, 0.19]),  # extents differ by 0.01: kept
    ]
    assert corpus.find_near_duplicates(entries) == {
        "a-livery2": "a-livery1",
        "b-hull2": "b-hull1",
        "d-body-wrc": "d-body-kit",
    }
