"""The 0 A.D. source (training/data/sources/zeroad.py) on a small ``public.zip`` written here.

The archive mimics ``0ad-data``'s layout: meshes as ``art/meshes/<folder>/<name>.dae.cached.pmd``
(written by the PMD layout the reader tests use), textures as ``art/textures/skins/<file>.cached.dds``
(Pillow writes DDS), actors as ``art/actors/**/*.xml`` naming each variant's mesh and ``baseTex``.
"""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest
import trimesh
from PIL import Image

from tests.training.data.test_readers import _file_pmd
from training.data import corpus
from training.data.sources import zeroad

_ZIP = "0ad-data/usr/share/games/0ad/mods/public/public.zip"


def _sphere(v_range=(0.0, 1.0)):
    """An icosphere (320 triangles, above MIN_FACES) with UVs: u from the azimuth, v squeezed into ``v_range``."""
    s = trimesh.creation.icosphere(subdivisions=2)
    x, y, z = s.vertices.T
    u = (np.arctan2(y, x) / (2 * np.pi)) % 1.0
    v = v_range[0] + (z + 1) / 2 * (v_range[1] - v_range[0])
    return s.vertices.tolist(), s.faces.tolist(), np.column_stack([u, v]).tolist()


def _dds(top_rgba, bottom_rgba, size=64) -> bytes:
    """A texture whose top half (rows 0..size/2 of the image) and bottom half are two colours."""
    a = np.zeros((size, size, 4), np.uint8)
    a[: size // 2] = top_rgba
    a[size // 2:] = bottom_rgba
    out = io.BytesIO()
    Image.fromarray(a, "RGBA").save(out, "DDS")
    return out.getvalue()


def _actor(mesh: str, texture: str, material: str = "player_trans.xml") -> bytes:
    return (f'<?xml version="1.0"?><actor version="1"><group><variant name="a"><mesh>{mesh}</mesh>'
            f'<textures><texture file="{texture}" name="baseTex"/></textures></variant></group>'
            f"<material>{material}</material></actor>").encode()


def _write_package(root):
    path = root / _ZIP
    path.parent.mkdir(parents=True)
    red_over_blue = _dds((255, 0, 0, 255), (0, 0, 255, 255))
    clear_bottom = _dds((0, 255, 0, 255), (0, 0, 0, 0))  # cut-out texture: transparent lower half
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("art/textures/skins/structural/house.png.cached.dds", red_over_blue)
        z.writestr("art/textures/skins/props/leaves.png.cached.dds", clear_bottom)
        # a building; its variant mark "_b" is dropped from its family
        z.writestr("art/meshes/structural/athen_house_b.dae.cached.pmd", _file_pmd(*_sphere()))
        z.writestr("art/actors/structures/athen/house.xml", _actor("structural/athen_house_b.dae", "structural/house.png"))
        # alpha-tested: one mesh on the opaque upper half of the texture (kept), one on the clear lower half
        z.writestr("art/meshes/props/rock_1.dae.cached.pmd", _file_pmd(*_sphere((0.6, 0.95))))
        z.writestr("art/meshes/props/bush_1.dae.cached.pmd", _file_pmd(*_sphere((0.05, 0.4))))
        for name in ("rock_1", "bush_1"):
            z.writestr(f"art/actors/props/{name}.xml", _actor(f"props/{name}.dae", "props/leaves.png", "basic_trans.xml"))
        # left out: a skinned mesh, a mesh under MIN_FACES, a mesh no actor shows, a folder not in CLASSES
        z.writestr("art/meshes/props/body.dae.cached.pmd", _file_pmd(*_sphere(), bones=3))
        z.writestr("art/actors/props/body.xml", _actor("props/body.dae", "structural/house.png"))
        tetra = ([(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)], [(0, 2, 1), (0, 1, 3), (0, 3, 2), (1, 2, 3)],
                 [(0, 0), (1, 0), (0, 1), (0.5, 0.5)])
        z.writestr("art/meshes/props/peg.dae.cached.pmd", _file_pmd(*tetra))
        z.writestr("art/actors/props/peg.xml", _actor("props/peg.dae", "structural/house.png"))
        z.writestr("art/meshes/props/orphan.dae.cached.pmd", _file_pmd(*_sphere()))
        z.writestr("art/meshes/skeletal/rider.dae.cached.pmd", _file_pmd(*_sphere()))
        z.writestr("art/actors/units/rider.xml", _actor("skeletal/rider.dae", "structural/house.png"))
        z.writestr("art/actors/broken.xml", b"<actor><group>")  # unparsable actors are passed over
    return path


def test_family_drops_variant_marks():
    assert zeroad.family_of("athen_house_b_2") == "athen_house"
    assert zeroad.family_of("bush_1") == "bush"
    assert zeroad.family_of("palm_new") == "palm"
    assert zeroad.family_of("barracks") == "barracks"
    assert zeroad.family_of("_1") == "_1"  # nothing left: the stem itself


def test_cut_out_fraction_counts_area_on_clear_texels():
    # two triangles of areas 0.5 and 2.5; UV centres (0.27, 0.37) and (0.55, 0.63)
    mesh = trimesh.Trimesh([(0, 0, 0), (1, 0, 0), (3, 3, 0), (0, 1, 0)], [(0, 1, 3), (1, 2, 3)], process=False)
    mesh.metadata["uv"] = np.array([(0.1, 0.1), (0.6, 0.1), (0.95, 0.9), (0.1, 0.9)], np.float32)
    assert mesh.area_faces == pytest.approx([0.5, 2.5])
    alpha = np.full((8, 8), 255, np.uint8)
    alpha[:, :4] = 0  # the image's left half is clear: only the small triangle's centre lies there
    assert zeroad.cut_out_fraction(mesh, alpha) == pytest.approx(0.5 / 3)
    alpha[:] = 255
    alpha[4:] = 0  # the image's bottom rows are clear: v counts from the bottom, so the small triangle (v 0.37)
    assert zeroad.cut_out_fraction(mesh, alpha) == pytest.approx(0.5 / 3)
    alpha[:] = 255
    alpha[:4] = 0  # ...and the top rows hold the large one (v 0.63)
    assert zeroad.cut_out_fraction(mesh, alpha) == pytest.approx(2.5 / 3)


def test_enumerate_keeps_rigid_textured_meshes_of_known_folders(tmp_path):
    _write_package(tmp_path)
    records = {r.shape_id: r for r in zeroad.enumerate_shapes(tmp_path)}
    assert sorted(records) == ["zeroad-props-bush_1", "zeroad-props-rock_1", "zeroad-structural-athen_house_b"]
    house = records["zeroad-structural-athen_house_b"]
    assert (house.class_hint, house.family, house.licence) == ("building", "zeroad-structural-athen_house", "CC-BY-SA-3.0")
    assert house.extra["texture"] == "structural/house.png.cached.dds"
    assert records["zeroad-props-rock_1"].class_hint == "prop"


def test_enumerate_without_the_package_is_empty(tmp_path):
    assert zeroad.enumerate_shapes(tmp_path) == []


def test_load_textures_with_v_from_the_bottom_and_refuses_cut_outs(tmp_path):
    _write_package(tmp_path)
    records = {r.shape_id: r for r in zeroad.enumerate_shapes(tmp_path)}
    (house,) = records["zeroad-structural-athen_house_b"].load()
    assert isinstance(house.visual, trimesh.visual.TextureVisuals)
    # the sphere's north pole has v = 1: the image's top row, red; its south pole v = 0: blue
    colours = house.visual.to_color().vertex_colors
    z = house.vertices[:, 2]
    assert tuple(colours[np.argmax(z)][:3]) == (255, 0, 0)
    assert tuple(colours[np.argmin(z)][:3]) == (0, 0, 255)
    (rock,) = records["zeroad-props-rock_1"].load()
    assert len(rock.faces) == 320
    with pytest.raises(ValueError, match="cut-out texture: 100% of the surface"):
        records["zeroad-props-bush_1"].load()


def test_corpus_build_gives_own_classes_outside_the_protocol(tmp_path):
    unpacked = tmp_path / "cache" / "unpacked"
    unpacked.mkdir(parents=True)
    _write_package(unpacked)
    manifest = corpus.build(tmp_path, sources=["zeroad"])
    shapes = {s["id"]: s for s in manifest["shapes"]}
    assert sorted(shapes) == ["zeroad-props-rock_1", "zeroad-structural-athen_house_b"]
    for s in shapes.values():
        assert s["split"] == "unassigned" and s["textured"]
        assert s["class"] not in corpus.SEEN_CLASSES + corpus.UNSEEN_CLASSES + corpus.UNSEEN_PIX3D_CLASSES
    skipped = {s["id"]: s["reason"] for s in manifest["skipped"]}
    assert "cut-out texture" in skipped["zeroad-props-bush_1"]
    assert manifest["splits"]["train"] == [] and manifest["splits"]["unseen"] == []


def test_default_build_leaves_the_opt_in_source_out(tmp_path):
    unpacked = tmp_path / "cache" / "unpacked"
    unpacked.mkdir(parents=True)
    _write_package(unpacked)
    assert "0ad-data" not in corpus.DEBIAN_PACKAGES  # `genre data fetch` does not download it unless named
    records = corpus.enumerate_records(tmp_path, sources=None)
    assert not [r for r in records if r.source == "zeroad"]
    assert len([r for r in corpus.enumerate_records(tmp_path, sources=["zeroad"])]) == 3
