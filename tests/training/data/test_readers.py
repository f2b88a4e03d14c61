"""AC3D/.acc and 3DS readers on small files written by the tests (no packages needed)."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from training.data.readers import read_3ds, read_ac3d, read_pmd
from training.data.readers.ac3d import read_ac3d_parts, triangulate_polygon

CUBE_VERTS = [(x, y, z) for x in (0, 1) for y in (0, 1) for z in (0, 1)]
# quads of the unit cube, outward winding, indices into CUBE_VERTS (index = 4x + 2y + z)
CUBE_QUADS = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]


def _object(name, verts, surfaces, kids="0", loc=None, rot=None, extra=""):
    lines = ["OBJECT poly", f'name "{name}"']
    if rot is not None:
        lines.append("rot " + " ".join(str(v) for v in rot))
    if loc is not None:
        lines.append("loc " + " ".join(str(v) for v in loc))
    lines.append(extra) if extra else None
    lines.append(f"numvert {len(verts)}")
    lines += [" ".join(str(c) for c in v) for v in verts]
    lines.append(f"numsurf {len(surfaces)}")
    for flags, mat, refs in surfaces:
        lines += [f"SURF {flags}", f"mat {mat}", f"refs {len(refs)}"]
        lines += [f"{r} 0 0" for r in refs]
    lines.append(f"kids {kids}")
    return "\n".join(lines)


HEADER = (
    "AC3Db\n"
    'MATERIAL "red" rgb 1 0 0  amb 0.2 0.2 0.2  emis 0 0 0  spec 0.5 0.5 0.5  shi 10  trans 0\n'
    'MATERIAL "half blue" rgb 0 0 1  amb 0.2 0.2 0.2  emis 0 0 0  spec 0.5 0.5 0.5  shi 10  trans 0.5\n'
)


def _cube_file(loc=(10, 0, 0)):
    cube = _object("cube", CUBE_VERTS, [("0x10", 0, q) for q in CUBE_QUADS], loc=loc)
    return (HEADER + "OBJECT world\nkids 1\n" + cube + "\n").encode()


def test_ac3d_cube_with_loc_offset(tmp_path):
    path = tmp_path / "cube.ac"
    path.write_bytes(_cube_file())
    mesh = read_ac3d(path)
    assert len(mesh.faces) == 12
    assert len(mesh.vertices) == 8
    np.testing.assert_allclose(mesh.vertices, np.array(CUBE_VERTS, float) + [10, 0, 0])
    assert mesh.area == pytest.approx(6.0)
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(1.0)  # outward winding kept
    np.testing.assert_array_equal(mesh.visual.face_colors[0], [255, 0, 0, 255])


def test_ac3d_nested_kids_rotation_and_loc():
    # parent: rot rows (0 1 0 / -1 0 0 / 0 0 1) and loc (1 2 3); child: loc (0 0 1).
    # A child vertex v goes to ((v + (0,0,1)) @ M) + (1,2,3) with M the rows above.
    child = _object("child", [(1, 0, 0), (0, 1, 0), (0, 0, 0)], [("0x10", 1, (0, 1, 2))], loc=(0, 0, 1))
    parent = _object(
        "parent", [(0, 0, 0), (1, 0, 0), (0, 0, 1)], [("0x10", 0, (0, 1, 2))], kids="1",
        loc=(1, 2, 3), rot=(0, 1, 0, -1, 0, 0, 0, 0, 1),
    )
    data = (HEADER + "OBJECT world\nkids 1\n" + parent + "\n" + child + "\n").encode()
    parts = read_ac3d_parts(data)
    assert [p.name for p in parts] == ["parent", "child"]
    assert parts[1].path == ("", "parent", "child")
    # parent's own vertices: (1,0,0) @ M = (0,1,0) -> + loc = (1,3,3)
    np.testing.assert_allclose(parts[0].vertices, [[1, 2, 3], [1, 3, 3], [1, 2, 4]])
    # child: (1,0,0)+(0,0,1) = (1,0,1) -> @M = (0,1,1) -> +(1,2,3) = (1,3,4)
    np.testing.assert_allclose(parts[1].vertices, [[1, 3, 4], [0, 2, 4], [1, 2, 4]])
    merged = read_ac3d(data)
    assert len(merged.faces) == 2 and len(merged.vertices) == 6
    np.testing.assert_array_equal(merged.visual.face_colors[1], [0, 0, 255, 128])
    # dropping the parent by name drops its child too
    assert read_ac3d_parts(data, skip_object=lambda n: n == "parent") == []
    only_parent = read_ac3d_parts(data, skip_object=lambda n: n == "child")
    assert [p.name for p in only_parent] == ["parent"]
    # a group without surfaces of its own is never dropped by name
    group = "OBJECT group\nname \"GROUND\"\nkids 1\n" + child
    grouped = (HEADER + "OBJECT world\nkids 1\n" + group + "\n").encode()
    kept = read_ac3d_parts(grouped, skip_object=lambda n: n == "GROUND")
    assert [p.path for p in kept] == [("", "GROUND", "child")]


def test_acc_triangle_strip_and_lines_skipped():
    # five points on a zig-zag in the z=0 plane, with .acc-style normals after the position
    verts = [(0, 0, 0, 0, 0, 1), (0, 1, 0, 0, 0, 1), (1, 0, 0, 0, 0, 1), (1, 1, 0, 0, 0, 1), (2, 0, 0, 0, 0, 1)]
    surfaces = [("0x14", 0, (0, 1, 2, 3, 4)), ("0x22", 0, (0, 4)), ("0x21", 0, (0, 1, 2))]
    data = (HEADER + "OBJECT world\nkids 1\n" + _object("strip", verts, surfaces) + "\n").encode()
    mesh = read_ac3d(data)
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [2, 1, 3], [2, 3, 4]])
    np.testing.assert_allclose(mesh.vertices[:, :3], np.array(verts)[:, :3])
    # alternating winding keeps every triangle facing the same way
    normals = mesh.face_normals
    np.testing.assert_allclose(normals, np.tile(normals[0], (3, 1)), atol=1e-12)
    assert abs(normals[0][2]) == pytest.approx(1.0)
    assert mesh.area == pytest.approx(1.5)


def test_concave_polygon_ear_clipping():
    # an L-shaped hexagon of area 3 (three unit squares)
    pts = np.array([(0, 0, 0), (2, 0, 0), (2, 1, 0), (1, 1, 0), (1, 2, 0), (0, 2, 0)], float)
    tris = triangulate_polygon(pts)
    assert tris.shape == (4, 3)
    a, b, c = pts[tris[:, 0]], pts[tris[:, 1]], pts[tris[:, 2]]
    areas = 0.5 * np.cross(b - a, c - a)[:, 2]
    assert np.all(areas > 0)  # same winding as the polygon, no flipped ear
    assert areas.sum() == pytest.approx(3.0)
    # through the reader: one 6-gon -> 4 triangles of total area 3
    data = (HEADER + "OBJECT world\nkids 1\n" + _object("L", pts.tolist(), [("0x10", 0, range(6))]) + "\n").encode()
    assert read_ac3d(data).area == pytest.approx(3.0)


def test_ac3d_data_block_and_unknown_fields():
    extra = 'data 11\nhello\nworld\ntexture "skin.png"\ntexrep 1 1\ncrease 30.0\nurl "x"'
    obj = _object("with data", [(0, 0, 0), (1, 0, 0), (0, 1, 0)], [("0x30", 0, (0, 1, 2))], extra=extra)
    data = (HEADER + "OBJECT world\nkids 1\n" + obj + "\n").encode()
    parts = read_ac3d_parts(data)
    assert parts[0].texture == "skin.png" and len(parts[0].faces) == 1


@pytest.mark.parametrize(
    "payload, message",
    [
        (b"not an ac3d file\n", "not an AC3D file"),
        (b"", "not an AC3D file"),
        (_cube_file()[:-200], "end of file"),
        (HEADER.encode() + b"OBJECT world\nkids 1\n" + _object("x", [(0, 0, 0)], [("0x10", 0, (0, 1, 2))]).encode(),
         "refers to vertex"),
        (HEADER.encode() + b"OBJECT world\nkids 1\nOBJECT poly\nnumvert 1\n1 2 banana\n", "not a number"),
        (HEADER.encode() + b"OBJECT world\nkids 0\n", "no polygons"),
    ],
)
def test_ac3d_bad_input_raises_value_error(payload, message):
    with pytest.raises(ValueError, match=message):
        read_ac3d(payload)


def test_ac3d_missing_file(tmp_path):
    with pytest.raises(ValueError, match="no such file"):
        read_ac3d(tmp_path / "nope.ac")


# ----------------------------------------------------------------------------- 3DS


def _chunk(cid: int, payload: bytes) -> bytes:
    return struct.pack("<HI", cid, 6 + len(payload)) + payload


def _object_3ds(name: str, verts, faces, material: str | None) -> bytes:
    vbytes = struct.pack("<H", len(verts)) + b"".join(struct.pack("<3f", *v) for v in verts)
    fbytes = struct.pack("<H", len(faces)) + b"".join(struct.pack("<4H", *f, 7) for f in faces)
    if material:
        fbytes += _chunk(0x4130, material.encode() + b"\0" + struct.pack("<H", len(faces))
                         + b"".join(struct.pack("<H", i) for i in range(len(faces))))
    local = _chunk(0x4160, struct.pack("<12f", 1, 0, 0, 0, 1, 0, 0, 0, 1, 50, 50, 50))  # must be ignored
    mesh = _chunk(0x4100, _chunk(0x4110, vbytes) + _chunk(0x4120, fbytes) + local)
    return _chunk(0x4000, name.encode() + b"\0" + mesh)


def _material_3ds(name: str, rgb: tuple[int, int, int]) -> bytes:
    return _chunk(0xAFFF, _chunk(0xA000, name.encode() + b"\0") + _chunk(0xA020, _chunk(0x0011, bytes(rgb))))


def _file_3ds() -> bytes:
    tri = _object_3ds("tri", [(0, 0, 0), (1, 0, 0), (0, 1, 0)], [(0, 1, 2)], "green")
    quad = _object_3ds("quad", [(0, 0, 5), (2, 0, 5), (2, 3, 5), (0, 3, 5)], [(0, 1, 2), (0, 2, 3)], None)
    editor = _chunk(0x3D3D, _chunk(0x3D3E, struct.pack("<I", 3)) + _material_3ds("green", (0, 200, 0)) + tri + quad)
    return _chunk(0x4D4D, _chunk(0x0002, struct.pack("<I", 3)) + editor + _chunk(0xB000, b""))


def test_3ds_two_objects_merged(tmp_path):
    path = tmp_path / "two.3ds"
    path.write_bytes(_file_3ds())
    mesh = read_3ds(path)
    assert mesh.metadata["parts"] == ["tri", "quad"]
    assert len(mesh.faces) == 3 and len(mesh.vertices) == 7
    np.testing.assert_allclose(mesh.vertices[3:], [(0, 0, 5), (2, 0, 5), (2, 3, 5), (0, 3, 5)])
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [3, 4, 5], [3, 5, 6]])
    assert mesh.area == pytest.approx(0.5 + 6.0)
    np.testing.assert_array_equal(mesh.visual.face_colors[0], [0, 200, 0, 255])
    np.testing.assert_array_equal(mesh.visual.face_colors[1], [200, 200, 200, 255])


@pytest.mark.parametrize(
    "payload, message",
    [
        (b"\x00\x01garbage", "not a 3DS file"),
        (_file_3ds()[:40], "bad length|truncated"),
        (_chunk(0x4D4D, _chunk(0x3D3D, b"")), "no triangle meshes"),
    ],
)
def test_3ds_bad_input_raises_value_error(payload, message):
    with pytest.raises(ValueError, match=message):
        read_3ds(payload)


def test_3ds_face_index_out_of_range():
    bad = _chunk(0x4D4D, _chunk(0x3D3D, _object_3ds("bad", [(0, 0, 0), (1, 0, 0)], [(0, 1, 5)], None)))
    with pytest.raises(ValueError, match="refers to vertex"):
        read_3ds(bad)


# --- 0 A.D. .pmd: files written here from the layout in training/data/readers/pmd.py, read back exactly


def _file_pmd(positions, faces, uvs, *, version=4, n_uv=1, bones=0, size_delta=0) -> bytes:
    """A PMD file: each vertex's normal is +z and its UV sets are ``uv``, ``uv + 10``, …; one bone blend."""
    body = struct.pack("<I", len(positions)) + (struct.pack("<I", n_uv) if version >= 4 else b"")
    for p, uv in zip(positions, uvs):
        sets = b"".join(struct.pack("<2f", uv[0] + 10 * k, uv[1] + 10 * k) for k in range(n_uv))
        body += struct.pack("<6f", *p, 0, 0, 1) + sets + bytes((0, 255, 255, 255)) + struct.pack("<4f", 1, 0, 0, 0)
    body += struct.pack("<I", len(faces)) + b"".join(struct.pack("<3H", *f) for f in faces)
    body += struct.pack("<I", bones) + b"".join(struct.pack("<7f", k, 0, 0, 0, 0, 0, 1) for k in range(bones))
    body += struct.pack("<I", 0) if version >= 2 else b""  # no prop points
    return b"PSMD" + struct.pack("<II", version, len(body) + size_delta) + body


_TETRA = [(0.0, 0.0, 0.0), (2.0, 0.0, 0.0), (0.0, 3.0, 0.0), (0.0, 0.0, 4.0)]
_TETRA_FACES = [(0, 2, 1), (0, 1, 3), (0, 3, 2), (1, 2, 3)]
_TETRA_UV = [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (0.5, 0.5)]


@pytest.mark.parametrize("version, n_uv", [(3, 1), (4, 1), (4, 2)])
def test_pmd_tetrahedron_read_back(tmp_path, version, n_uv):
    path = tmp_path / "tetra.pmd"
    path.write_bytes(_file_pmd(_TETRA, _TETRA_FACES, _TETRA_UV, version=version, n_uv=n_uv, bones=2))
    mesh = read_pmd(path)
    np.testing.assert_array_equal(mesh.vertices, _TETRA)
    np.testing.assert_array_equal(mesh.faces, _TETRA_FACES)
    np.testing.assert_array_equal(mesh.metadata["uv"], _TETRA_UV)  # the first UV set, whatever follows it
    assert mesh.metadata["bones"] == 2 and mesh.metadata["pmd_version"] == version
    assert mesh.is_watertight and mesh.volume == pytest.approx(2 * 3 * 4 / 6)  # the corner tetrahedron, outward faces


@pytest.mark.parametrize(
    "payload, message",
    [
        (b"PSMX" + bytes(20), "not a PMD file"),
        (_file_pmd(_TETRA, _TETRA_FACES, _TETRA_UV, version=5), "version 5"),
        (_file_pmd(_TETRA, _TETRA_FACES, _TETRA_UV, size_delta=8), "declares"),
        (_file_pmd(_TETRA, [(0, 1, 4)], _TETRA_UV), "uses vertex 4 of 4"),
        (_file_pmd(_TETRA, [], _TETRA_UV), "no triangles"),
        (_file_pmd([(0.0, float("nan"), 0.0)] + _TETRA[1:], _TETRA_FACES, _TETRA_UV), "non-finite"),
    ],
)
def test_pmd_bad_input_raises_value_error(payload, message):
    with pytest.raises(ValueError, match=message):
        read_pmd(payload)


def test_pmd_truncated_file_names_the_part():
    whole = _file_pmd(_TETRA, _TETRA_FACES, _TETRA_UV)
    cut = whole[:60]
    cut = cut[:8] + struct.pack("<I", len(cut) - 12) + cut[12:]  # a consistent size, so the cut itself is what fails
    with pytest.raises(ValueError, match="truncated in the vertices"):
        read_pmd(cut)
