"""Every mesh format lands upright in Blender, and all three land in the same place.

A tall thin box (taller than wide, in the view frame: +y up, +z toward the camera) with a marker on top
(toward +y) and a nose in front (toward +z) is written as obj, ply and glb by
:func:`genre_backend.output.mesh_export.write_mesh`, imported into bpy with Blender's own importers at
their default settings (``wm.obj_import``, ``wm.ply_import``, ``import_scene.gltf``), and its world-space
bounding box compared: tallest along +Z, the marker at the top (+Z), the nose toward −Y (Blender's front),
and the same box for every format.  A PLY written ``up="y"`` (the view frame) lies on its back: the reason
the default is ``z``.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from genre_backend.output.mesh_export import Y_UP_TO_Z_UP, resolve_up, write_mesh

# the test mesh, view frame: body x ±0.1, y ±0.4, z ±0.05; marker on top up to y 0.6; nose in front out to z 0.25
BODY = ((-0.1, -0.4, -0.05), (0.1, 0.4, 0.05))
MARKER = ((-0.05, 0.4, -0.05), (0.05, 0.6, 0.05))  # toward +y: up
NOSE = ((-0.05, 0.1, 0.05), (0.05, 0.2, 0.25))  # toward +z: the camera, the object's front
# the box Blender must show: (x, y, z) → (x, −z, y), front toward −Y
EXPECTED_MIN = np.array([-0.1, -0.25, -0.4])
EXPECTED_MAX = np.array([0.1, 0.05, 0.6])


def _box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))


def _test_mesh() -> tuple[np.ndarray, np.ndarray]:
    mesh = trimesh.util.concatenate([_box(*BODY), _box(*MARKER), _box(*NOSE)])
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


@pytest.fixture(scope="module")
def bpy():
    from genre_backend.output.blender import import_bpy, quiet_stdout

    bpy = import_bpy()
    with quiet_stdout(True):
        bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy


def _imported_box(bpy, path) -> tuple[np.ndarray, np.ndarray]:
    """Import ``path`` into an empty scene with Blender's default settings; (min, max) of every mesh vertex in world space."""
    from genre_backend.output.blender import quiet_stdout

    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj, do_unlink=True)
    with quiet_stdout(True):
        if path.suffix == ".obj":
            bpy.ops.wm.obj_import(filepath=str(path))
        elif path.suffix == ".ply":
            bpy.ops.wm.ply_import(filepath=str(path))
        else:
            bpy.ops.import_scene.gltf(filepath=str(path))
    bpy.context.view_layer.update()
    points = []
    for obj in bpy.context.scene.objects:
        if obj.type == "MESH":
            m = np.array(obj.matrix_world)
            co = np.array([v.co[:] for v in obj.data.vertices])
            points.append(co @ m[:3, :3].T + m[:3, 3])
    assert points, f"{path.name}: nothing imported"
    pts = np.concatenate(points)
    return pts.min(axis=0), pts.max(axis=0)


def test_the_rotation_is_proper_and_maps_up_and_front():
    assert np.isclose(np.linalg.det(Y_UP_TO_Z_UP), 1.0)  # a rotation: faces keep their winding
    assert np.allclose(Y_UP_TO_Z_UP @ [0, 1, 0], [0, 0, 1])  # view +y (up) → +Z
    assert np.allclose(Y_UP_TO_Z_UP @ [0, 0, 1], [0, -1, 0])  # view +z (toward the camera, the front) → −Y


def test_up_defaults_and_refusals():
    assert resolve_up("ply", None) == "z" and resolve_up("obj", None) == "y" and resolve_up("glb", None) == "y"
    assert resolve_up("ply", "y") == "y" and resolve_up("obj", "y") == "y"
    for fmt in ("obj", "glb"):
        with pytest.raises(ValueError, match="ply only"):
            resolve_up(fmt, "z")
    with pytest.raises(ValueError, match="'y' or 'z'"):
        resolve_up("ply", "x")


def test_ply_file_is_z_up_and_says_so(tmp_path):
    v, f = _test_mesh()
    write_mesh(tmp_path / "z.ply", v, f)
    write_mesh(tmp_path / "y.ply", v, f, up="y")
    z, y = (trimesh.load(tmp_path / n, process=False) for n in ("z.ply", "y.ply"))
    assert np.allclose(y.vertices, v, atol=1e-6) and np.allclose(z.vertices, v @ Y_UP_TO_Z_UP.T, atol=1e-6)
    assert np.array_equal(z.faces, f)
    assert z.volume > 0 and np.isclose(z.volume, trimesh.Trimesh(v, f, process=False).volume)  # winding kept (outward)
    head = (tmp_path / "z.ply").read_bytes().split(b"end_header")[0]
    assert head.startswith(b"ply\nformat ") and b"comment GenRe mesh: +x right, +z up, front toward -y" in head
    assert b"+y up, +z toward the camera" in (tmp_path / "y.ply").read_bytes().split(b"end_header")[0]


def test_every_format_imports_upright_and_alike_in_blender(bpy, tmp_path):
    v, f = _test_mesh()
    boxes = {}
    for fmt in ("obj", "ply", "glb"):
        path, used, _ = write_mesh(tmp_path / f"m.{fmt}", v, f)
        assert used == fmt
        lo, hi = boxes[fmt] = _imported_box(bpy, path)
        size = hi - lo
        assert size[2] > size[0] and size[2] > size[1], (fmt, size)  # tallest along Blender's Z
        assert np.allclose(lo, EXPECTED_MIN, atol=1e-4) and np.allclose(hi, EXPECTED_MAX, atol=1e-4), (fmt, lo, hi)
    for fmt in ("ply", "glb"):
        assert np.allclose(boxes[fmt][0], boxes["obj"][0], atol=1e-5) and np.allclose(boxes[fmt][1], boxes["obj"][1], atol=1e-5)


def test_a_y_up_ply_lies_on_its_back_in_blender(bpy, tmp_path):
    """``--up y``: the file is the view frame, and Blender's PLY importer reads it as +z up: the box's height is along Y."""
    v, f = _test_mesh()
    path, _, _ = write_mesh(tmp_path / "y.ply", v, f, up="y")
    lo, hi = _imported_box(bpy, path)
    size = hi - lo
    assert size[1] > size[2] and np.isclose(hi[1], 0.6, atol=1e-4), (lo, hi)


# ---- the shipped model on the demo photo: the option through save_mesh, genre reconstruct and genre serve ----------
REPO = __import__("pathlib").Path(__file__).resolve().parents[3]
DEMO = REPO / "examples" / "sofa.png"


@pytest.fixture(scope="module")
def demo_result():
    from genre_backend.inference.reconstruct import DEFAULT_WEIGHTS, Reconstructor

    return Reconstructor(DEFAULT_WEIGHTS).run(DEMO)


def test_save_mesh_writes_the_axis_asked_for(demo_result, tmp_path):
    v = demo_result.vertices
    for name, up, expected, rotated in (("a.ply", None, "z", True), ("b.ply", "y", "y", False), ("c.obj", None, "y", False),
                                        ("d.glb", "y", "y", False)):
        demo_result.save_mesh(tmp_path / name, up=up)
        assert demo_result.up == expected
        back = trimesh.load(tmp_path / name, force="mesh", process=False)
        want = v @ Y_UP_TO_Z_UP.T if rotated else v
        assert np.allclose(back.vertices, want, atol=1e-5), name
    with pytest.raises(ValueError, match="ply only"):
        demo_result.save_mesh(tmp_path / "e.obj", up="z")
    assert not (tmp_path / "e.obj").exists()


def test_reconstruct_cli_up(tmp_path, capsys):
    from genre_backend.frontends import reconstruct_cli

    with pytest.raises(SystemExit) as exc:  # before any work: the axis contradicts the format
        reconstruct_cli.main([str(DEMO), "-o", str(tmp_path / "x.obj"), "--up", "z"])
    assert exc.value.code == 2 and "--up: 'z' is for ply only" in capsys.readouterr().err
    assert reconstruct_cli.main([str(DEMO), "-o", str(tmp_path / "m.ply"), "--weights", "default"]) == 0
    out = capsys.readouterr().out
    assert "(ply, +z up, " in out, out
    assert b"+z up, front toward -y" in (tmp_path / "m.ply").read_bytes().split(b"end_header")[0]


def test_serve_up_option(tmp_path):
    import io
    import json

    from genre_backend.inference.reconstruct import DEFAULT_WEIGHTS, Reconstructor
    from genre_backend.frontends.server import Server

    requests = [
        {"type": "reconstruct", "id": "bad-axis", "image": str(DEMO), "output": str(tmp_path / "x.ply"), "options": {"up": "x"}},
        {"type": "reconstruct", "id": "z-obj", "image": str(DEMO), "output": str(tmp_path / "x.obj"), "options": {"up": "z"}},
        {"type": "reconstruct", "id": "z-glb", "image": str(DEMO), "output": str(tmp_path / "x.glb"), "options": {"up": "z", "format": "glb"}},
        {"type": "reconstruct", "id": "y-ply", "image": str(DEMO), "output": str(tmp_path / "y.ply"), "options": {"up": "y"}},
    ]
    out = io.StringIO()
    server = Server(Reconstructor(DEFAULT_WEIGHTS), out, "cpu")
    assert server.serve(io.StringIO("".join(json.dumps(r) + "\n" for r in requests))) == 0
    events = {e.get("id"): e for e in map(json.loads, out.getvalue().splitlines()) if e["type"] in ("error", "result")}
    assert events["bad-axis"]["code"] == "bad_field" and "expected one of 'y', 'z'" in events["bad-axis"]["message"]
    for rid in ("z-obj", "z-glb"):
        assert events[rid]["code"] == "bad_field" and "ply only" in events[rid]["message"], events[rid]
    res = events["y-ply"]
    assert res["type"] == "result" and res["format"] == "ply" and res["up"] == "y", res
    assert b"+y up, +z toward the camera" in (tmp_path / "y.ply").read_bytes().split(b"end_header")[0]
    assert not any((tmp_path / f"x.{e}").exists() for e in ("obj", "ply", "glb"))
