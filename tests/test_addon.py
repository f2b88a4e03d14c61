"""The Blender add-on (blender_addon/) with the bpy module: packaging, install, register, and real reconstructions.

Every test that touches bpy runs in its own subprocess (this file, run as a
script with a scenario name), because bpy's global state (registered classes,
preferences, the scene) outlives a test.  Each subprocess gets its own
BLENDER_USER_RESOURCES and XDG_CACHE_HOME.  The tests that reconstruct talk to
a real ``genre serve`` started by the add-on, with weights trained here by the
project's own training code on a tiny rendered data set.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ADDON = REPO / "blender_addon"
RESULT_TAG = "ADDON-RESULT "


def _load(name: str, path: Path):
    """Import one bpy-free add-on module by file (the package's __init__ needs bpy)."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


# =====================================================================================
# Scenarios: run inside a fresh Python process with bpy (python tests/test_addon.py NAME ARGS_JSON)
# =====================================================================================
def _install_legacy(bpy, zip_path: str) -> str:
    bpy.ops.preferences.addon_install(filepath=zip_path, overwrite=True)
    bpy.ops.preferences.addon_enable(module="genre")
    return "genre"


def _install_extension(bpy, zip_path: str) -> str:
    bpy.ops.extensions.package_install_files(repo="user_default", filepath=zip_path, enable_on_install=True)
    return "bl_ext.user_default.genre"


def _registration_state(bpy, module: str) -> dict:
    import addon_utils

    return {
        "enabled": module in {a.module for a in bpy.context.preferences.addons},
        "ops": sorted(n for n in ("reconstruct", "cancel", "check_backend", "choose_file") if n in dir(bpy.ops.genre)),
        "panel": hasattr(bpy.types, "GENRE_PT_panel"),
        "scene_settings": hasattr(bpy.types.Scene, "genre"),
        "status": hasattr(bpy.types.WindowManager, "genre_status"),
        "prefs": module in bpy.context.preferences.addons and bpy.context.preferences.addons[module].preferences is not None,
        "loaded": addon_utils.check(module)[1],
    }


def scenario_install(args: dict) -> dict:
    import bpy

    installer = _install_extension if args["kind"] == "extension" else _install_legacy
    module = installer(bpy, args["zip"])
    out = {"module": module, "after_enable": _registration_state(bpy, module)}
    mod = sys.modules[module]
    out["package"] = mod.ops.ADDON_PACKAGE
    out["installed_at"] = os.path.dirname(mod.__file__)
    # the panel draws (a UILayout needs a real region, so check the class is a registered sidebar panel)
    panel = bpy.types.GENRE_PT_panel
    out["panel_place"] = [panel.bl_space_type, panel.bl_region_type, panel.bl_category]
    prefs = bpy.context.preferences.addons[module].preferences
    out["prefs_idname"] = type(prefs).bl_idname
    # the Model choice: the shipped weights by name, or a custom file (its path used only then)
    out["model_default"] = prefs.model
    out["model_items"] = [(i.identifier, i.name) for i in type(prefs).bl_rna.properties["model"].enum_items]
    prefs.backend_command = sys.executable
    prefs.weights = "/some/w.safetensors"
    out["argv"] = {}
    for model in ("default", "protocol", "custom"):
        prefs.model = model
        out["argv"][model] = mod.ops.backend_argv(prefs)[4:]
    prefs.weights = ""
    try:
        mod.ops.backend_argv(prefs)
    except mod.backend.BackendError as exc:
        out["custom_without_file"] = str(exc)
    prefs.model = "default"
    bpy.ops.preferences.addon_disable(module=module)
    out["after_disable"] = _registration_state(bpy, module)
    bpy.ops.preferences.addon_enable(module=module)
    out["after_reenable"] = _registration_state(bpy, module)
    return out


class _Snapshot:
    """The datablocks that a failed reconstruction must not leave behind."""

    KINDS = ("objects", "meshes", "cameras", "collections", "images", "materials")

    def __init__(self, bpy):
        self.bpy = bpy
        self.before = {k: set(getattr(bpy.data, k).keys()) for k in self.KINDS}

    def added(self) -> dict:
        return {k: sorted(set(getattr(self.bpy.data, k).keys()) - self.before[k]) for k in self.KINDS
                if set(getattr(self.bpy.data, k).keys()) - self.before[k]}


def _setup_backend(bpy, module: str, args: dict):
    prefs = bpy.context.preferences.addons[module].preferences
    prefs.backend_command = args.get("command", sys.executable)
    prefs.model = "custom"
    prefs.weights = args["weights"]
    prefs.device = "cpu"
    prefs.startup_timeout = 120.0
    prefs.job_timeout = 300.0
    return prefs


def _drive(ops, settings, prefs, status, scene, *, on_tick=None, limit=300.0) -> tuple:
    """What the modal operator does, tick by tick: start, advance until done (sleeping between ticks)."""
    job = ops.start_job(settings, prefs, status)
    states = []
    deadline = time.monotonic() + limit
    while time.monotonic() < deadline:
        outcome = ops.advance(job, scene, status, scene.cursor.location.copy())
        states.append((job.state, job.request.stage, round(status.progress, 3), status.running))
        if outcome is not None:
            return job, outcome, states
        if on_tick is not None:
            on_tick(job)
        time.sleep(0.05)
    raise AssertionError(f"the job did not finish within {limit} s: {states[-5:]}")


def _job_dirs(ops) -> list[str]:
    from importlib import import_module

    jobs = import_module(ops.__name__.rsplit(".", 1)[0] + ".jobs")
    root = jobs.work_root(ops.ADDON_PACKAGE)
    return sorted(os.listdir(root))


def _mesh_report(obj, bpy) -> dict:
    mesh = obj.data
    zs = [v.co.z for v in mesh.vertices]
    cam = next((c for c in obj.children if c.type == "CAMERA"), None)
    out = {
        "name": obj.name,
        "collections": [c.name for c in obj.users_collection],
        "vertices": len(mesh.vertices),
        "faces": len(mesh.polygons),
        "smooth": all(p.use_smooth for p in mesh.polygons),
        "location": list(obj.location),
        "z_range": [min(zs), max(zs)],
        "modifiers": [m.type for m in obj.modifiers],
        "camera": None,
        "material": None,
    }
    if mesh.materials and mesh.materials[0] is not None:
        mat = mesh.materials[0]
        bsdf = mat.node_tree.nodes["Principled BSDF"]
        links = bsdf.inputs["Base Color"].links
        image = links[0].from_node.image if links and links[0].from_node.type == "TEX_IMAGE" else None
        layer = mesh.uv_layers.get("Photo")
        loops = [(tuple(mesh.vertices[loop.vertex_index].co), tuple(layer.data[loop.index].uv)) for loop in mesh.loops] if layer else []
        out["material"] = {
            "name": mat.name,
            "image": image.name if image else None,
            "packed": bool(image and image.packed_file),
            "image_size": list(image.size) if image else None,
            "loops": loops,
        }
    if cam is not None:
        out["camera"] = {
            "name": cam.name,
            "lens": cam.data.lens,
            "sensor": cam.data.sensor_width,
            "world_location": list(cam.matrix_world.translation),
            "forward": list(cam.matrix_world.to_3x3() @ __import__("mathutils").Vector((0, 0, -1))),
            "background": [bg.image.name for bg in cam.data.background_images if bg.image],
            "shows_background": cam.data.show_background_images,
        }
    return out


def scenario_reconstruct(args: dict) -> dict:
    """A real reconstruction driven step by step, a second one through the operator, and Check backend."""
    import bpy

    module = _install_legacy(bpy, args["zip"])
    addon = sys.modules[module]
    ops = addon.ops
    prefs = _setup_backend(bpy, module, args)
    scene = bpy.context.scene
    scene.cursor.location = (1.0, 2.0, 0.5)
    settings = scene.genre
    settings.photo_path = args["photo"]
    settings.smoothing = 1
    settings.target_faces = 10
    if args.get("threshold") is not None:
        settings.use_threshold = True
        settings.threshold = args["threshold"]
    else:
        settings.threshold = 0.2  # not the weights' level: a plain run should bring the field to it
    settings.hole_closing = 7  # likewise the hole sealing
    settings.pit_sealing = 5  # and the pit sealing (the test weights do not seal pits)
    settings.silhouette_carve = True  # and the outline trim (the test weights do not carve)
    settings.primitive_snap = 0.3  # and the regular-shape snapping (the test weights do not snap)
    settings.test_time_mirror = True  # and the mirror averaging (the test weights do not mirror)
    status = bpy.context.window_manager.genre_status
    out = {}
    snap = _Snapshot(bpy)
    t0 = time.monotonic()
    job, outcome, states = _drive(ops, settings, prefs, status, scene)
    out["first_seconds"] = time.monotonic() - t0
    out["threshold_field_after"] = settings.threshold
    out["hole_closing_field_after"] = settings.hole_closing
    out["pit_sealing_field_after"] = settings.pit_sealing
    out["silhouette_carve_field_after"] = settings.silhouette_carve
    out["primitive_snap_field_after"] = settings.primitive_snap
    out["test_time_mirror_field_after"] = settings.test_time_mirror
    out["outcome"] = list(outcome)
    out["result_event"] = job.request.result
    out["stages"] = sorted({s[1] for s in states})
    out["progress_seen"] = sorted({s[2] for s in states})
    out["added"] = snap.added()
    bpy.context.view_layer.update()  # matrix_world of the parented camera
    out["mesh"] = _mesh_report(bpy.data.objects[job.objects[0].name], bpy)
    out["status_after"] = {"running": status.running, "message": status.message, "error": status.message_is_error,
                           "mask_warning": status.mask_warning}
    out["job_dirs_after"] = _job_dirs(ops)
    pid = ops.manager.client.pid

    # the operator's execute() path (scripts, background mode) reuses the same backend process
    settings.add_camera = False
    t0 = time.monotonic()
    out["operator"] = sorted(bpy.ops.genre.reconstruct())
    out["second_seconds"] = time.monotonic() - t0
    out["same_backend"] = ops.manager.client.pid == pid
    out["objects_after_second"] = sorted(o.name for o in bpy.data.collections["GenRe"].objects)
    out["check"] = sorted(bpy.ops.genre.check_backend())
    out["backend_info"] = status.backend_info
    # a mask that covers the whole photo: the backend doubts it and the panel says so
    from PIL import Image

    with Image.open(args["photo"]) as im:
        full = os.path.join(tempfile.gettempdir(), "full_mask.png")
        Image.new("L", im.size, 255).save(full)
    settings.mask_path = full
    job, outcome, _ = _drive(ops, settings, prefs, status, scene)
    out["doubtful"] = {"outcome": list(outcome), "mask_warning": status.mask_warning, "event": job.request.result.get("mask_warning")}
    settings.mask_path = ""
    # a photo stored turned, with the EXIF tag that says so (as phones save them): Blender shows the stored
    # pixels, the backend reads it upright, and the matching camera gets the photo as the mesh was made from it
    import numpy as np

    with Image.open(args["photo"]) as im:  # widened with its own background, so that a turn changes its shape
        photo = im.convert("RGBA")
    upright = Image.new("RGBA", (photo.width + 24, photo.height), photo.getpixel((0, 0)))
    upright.paste(photo, (12, 0))
    exif = Image.Exif()
    exif[0x0112] = 6  # turn 90° clockwise to show
    turned = os.path.join(tempfile.gettempdir(), "turned.png")
    upright.transpose(Image.Transpose.ROTATE_90).save(turned, exif=exif.tobytes())
    settings.photo_path = turned
    settings.add_camera = True
    before = set(bpy.data.images)
    job, outcome, _ = _drive(ops, settings, prefs, status, scene)
    cam = next(c for c in bpy.data.objects[job.objects[0].name].children if c.type == "CAMERA")
    bg = cam.data.background_images[0].image
    px = np.empty(bg.size[0] * bg.size[1] * 4, np.float32)
    bg.pixels.foreach_get(px)
    want = np.asarray(upright, np.float32)[::-1] / 255.0  # Blender's rows: bottom first
    out["exif"] = {"outcome": list(outcome), "camera_event": job.request.result["camera"], "background": bg.name,
                   "size": list(bg.size), "packed": bool(bg.packed_file), "upright_size": list(upright.size),
                   "max_pixel_error": float(np.abs(px.reshape(want.shape) - want).max()),
                   "resolution": [scene.render.resolution_x, scene.render.resolution_y],
                   "new_images": sorted(i.name for i in set(bpy.data.images) - before)}
    settings.photo_path = args["photo"]
    # the backend stops when the add-on is disabled
    proc = ops.manager.client._proc
    bpy.ops.preferences.addon_disable(module=module)
    out["backend_exit_after_disable"] = proc.poll()
    return out


def scenario_failures(args: dict) -> dict:
    """Every failure ends cleanly, leaves no half-made objects, says why; the next attempt works."""
    import signal

    import bpy

    module = _install_extension(bpy, args["zip"]) if args.get("extension") else _install_legacy(bpy, args["zip"])
    addon = sys.modules[module]
    ops = addon.ops
    prefs = _setup_backend(bpy, module, args)
    scene = bpy.context.scene
    settings = scene.genre
    settings.photo_path = args["photo"]
    if args.get("threshold") is not None:
        settings.use_threshold = True
        settings.threshold = args["threshold"]
    status = bpy.context.window_manager.genre_status
    out: dict = {}

    def attempt(name, *, on_tick=None, via_operator=False, expect_start_error=False):
        snap = _Snapshot(bpy)
        rec = {}
        if via_operator:
            try:
                bpy.ops.genre.reconstruct()
                rec["raised"] = None
            except RuntimeError as exc:
                rec["raised"] = str(exc)
        elif expect_start_error:
            try:
                ops.start_job(settings, prefs, status)
                rec["raised"] = None
            except Exception as exc:  # UserError / BackendError
                rec["raised"] = f"{type(exc).__name__}: {exc}"
        else:
            job, outcome, states = _drive(ops, settings, prefs, status, scene, on_tick=on_tick)
            rec["outcome"] = list(outcome)
            rec["state"] = job.state
        rec["added"] = snap.added()
        rec["running"] = status.running
        rec["message"] = status.message
        rec["job_dirs"] = _job_dirs(ops)
        rec["active_job"] = ops.active.job is not None
        out[name] = rec

    def works(name):
        attempt(name)

    good_command = prefs.backend_command
    # 1. backend command missing
    prefs.backend_command = "/nonexistent/bin/python3"
    attempt("missing_command", expect_start_error=True)
    attempt("missing_command_operator", via_operator=True)
    # 2. a program that is not a GenRe backend (exits at once)
    prefs.backend_command = args["foreign_python"]
    attempt("not_a_backend")
    prefs.backend_command = good_command
    works("works_after_missing_command")
    # 3. photo missing (refused before anything starts), and a corrupt photo (the server's bad_image error)
    settings.photo_path = os.path.join(args["tmp"], "no-such-photo.png")
    attempt("missing_photo", expect_start_error=True)
    settings.photo_path = args["corrupt_photo"]
    attempt("bad_photo")
    # 4. an error event: a mask of the wrong size
    settings.photo_path = args["photo"]
    settings.mask_path = args["bad_mask"]
    attempt("error_event")
    settings.mask_path = ""
    # 5. the backend crashes mid-job (frozen first, so it cannot answer before the kill on a loaded machine)
    os.kill(ops.manager.client.pid, signal.SIGSTOP)
    pids = []

    def kill_when_running(job):
        if job.request.state == "running" and not pids:
            pids.append(ops.manager.client.pid)
            os.kill(pids[0], signal.SIGKILL)

    attempt("crash", on_tick=kill_when_running)
    works("works_after_crash")
    out["restarted_after_crash"] = ops.manager.client.pid != pids[0]
    # 6. time-out.  The warm backend answers the box in ~0.1 s, which on a loaded machine can beat the
    # next tick; freeze it (SIGSTOP) so no answer can come and the time-out is the only way out.  The
    # add-on then kills it (SIGKILL ends a stopped process too) and the next request starts a fresh one.
    prefs.job_timeout = 0.001
    frozen = ops.manager.client.pid
    os.kill(frozen, signal.SIGSTOP)
    attempt("timeout")
    out["timed_out_backend_replaced"] = ops.manager.client is None or ops.manager.client.pid != frozen
    prefs.job_timeout = 300.0
    works("works_after_timeout")
    # 7. cancel while it runs.  The warm backend answers the box in ~0.1 s (and the mesh's last stage,
    # colour and writing, has no cancel point), so a cancel sent on a later tick can arrive too late on a
    # loaded machine: freeze the backend, let the request and the cancel both reach its pipe, then thaw it.
    frozen = ops.manager.client.pid
    os.kill(frozen, signal.SIGSTOP)

    steps = []

    def cancel_then_thaw(job):
        # tick k: the request went out (state running) → ask to cancel; the next tick writes the cancel line;
        # then thaw the backend, which finds both lines in its pipe
        if not steps and job.request.state == "running":
            steps.append("cancel")
            job.cancel()
        elif steps == ["cancel"]:
            steps.append("thaw")
            os.kill(frozen, signal.SIGCONT)

    attempt("cancel", on_tick=cancel_then_thaw)
    # 8. the result cannot be added (a broken mesh file): nothing half-made stays
    def when_answered(job, action):
        # Between two ticks: wait for the backend's answer, then spoil something before the result is added.
        while job.request.state in ("starting", "running"):
            job.request.tick()
            time.sleep(0.02)
        if job.request.state == "done":
            action(job)

    def write_broken_mesh(job):
        with open(job.spec.output_path, "w") as fh:
            fh.write("v 0 0 0\nf 1 2 3\n")

    def break_mesh(job):
        when_answered(job, write_broken_mesh)

    attempt("broken_mesh", on_tick=break_mesh)
    # 9. the photo disappears before the camera is made (after the mesh object exists): all of it is removed
    import shutil

    gone = os.path.join(args["tmp"], "vanishing.png")
    shutil.copy(args["photo"], gone)
    settings.photo_path = gone

    def remove_photo(job):
        when_answered(job, lambda job: os.remove(gone))

    attempt("photo_gone", on_tick=remove_photo)
    settings.photo_path = args["photo"]
    works("works_at_the_end")
    # Check backend's exact reasons
    prefs.backend_command = "/nonexistent/bin/python3"
    try:
        bpy.ops.genre.check_backend()
    except RuntimeError:
        pass
    out["check_missing"] = status.backend_info
    prefs.backend_command = good_command
    prefs.weights = os.path.join(args["tmp"], "missing.safetensors")
    try:
        bpy.ops.genre.check_backend()
    except RuntimeError:
        pass
    out["check_bad_weights"] = status.backend_info
    return out


SCENARIOS = {"install": scenario_install, "reconstruct": scenario_reconstruct, "failures": scenario_failures}


def _scenario_main(argv: list[str]) -> int:
    name, args = argv[0], json.loads(argv[1])
    result = SCENARIOS[name](args)
    print(RESULT_TAG + json.dumps(result, default=str), flush=True)
    # bpy's exit can be slow or noisy; the result is out
    sys.stdout.flush()
    os._exit(0)


if __name__ == "__main__":
    sys.exit(_scenario_main(sys.argv[1:]))


# =====================================================================================
# The tests (pytest side: no bpy in this process)
# =====================================================================================
import numpy as np  # noqa: E402
import pytest  # noqa: E402


def run_scenario(name: str, args: dict, tmp_path: Path, timeout: float = 600.0) -> dict:
    env = dict(os.environ)
    env["BLENDER_USER_RESOURCES"] = str(tmp_path / "blender-user")
    env["XDG_CACHE_HOME"] = str(tmp_path / "cache")
    env["TMPDIR"] = str(tmp_path / "tmp")
    (tmp_path / "tmp").mkdir(exist_ok=True)
    proc = subprocess.run([sys.executable, __file__, name, json.dumps(args)], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=timeout)
    for line in proc.stdout.splitlines():
        if line.startswith(RESULT_TAG):
            return json.loads(line[len(RESULT_TAG):])
    raise AssertionError(f"scenario {name} failed (exit {proc.returncode}):\n{proc.stdout[-4000:]}\n{proc.stderr[-6000:]}")


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    sys.path.insert(0, str(REPO))
    try:
        import build_addon
    finally:
        sys.path.remove(str(REPO))
    return build_addon.build(tmp_path_factory.mktemp("dist"))


def test_version_comes_from_the_manifest():
    import ast
    import tomllib

    manifest = tomllib.loads((ADDON / "blender_manifest.toml").read_text())
    tree = ast.parse((ADDON / "__init__.py").read_text())
    info = next(ast.literal_eval(n.value) for n in tree.body if isinstance(n, ast.Assign) and getattr(n.targets[0], "id", "") == "bl_info")
    assert manifest["id"] == "genre"
    assert manifest["schema_version"] == "1.0.0"
    assert ".".join(map(str, info["version"])) == manifest["version"]
    assert tuple(info["blender"]) == (3, 4, 0)
    assert manifest["blender_version_min"] >= "4.2.0"
    assert set(manifest["permissions"]) == {"files"}


def test_rotation_is_the_backends():
    from genre_backend.frame import VIEW_TO_BLENDER_FRONT

    geometry = _load("genre_addon_geometry", ADDON / "geometry.py")
    assert VIEW_TO_BLENDER_FRONT.tolist() == [list(r) for r in geometry.VIEW_TO_BLENDER_FRONT]
    # view +y (up in the photo) becomes Blender's +Z; the camera side (+z) becomes -Y
    assert geometry.to_blender_frame([(0, 1, 0), (0, 0, 1)]) == [(0, 0, 1), (0, -1, 0)]


def test_camera_setup_lines_up_the_crop_with_the_photo():
    geometry = _load("genre_addon_geometry", ADDON / "geometry.py")
    cam = {"lens_mm": 50.0, "sensor_mm": 30.594, "distance": 2.2}
    # a square photo reconstructed whole: the backend's own camera
    s = geometry.camera_setup(cam, (64, 64))
    assert (s.lens_mm, s.sensor_mm, s.shift_x, s.shift_y) == (50.0, 30.594, 0.0, 0.0)
    assert s.location == (0.0, -2.2, 0.0) and s.resolution == (64, 64)
    # a 400x200 photo whose 100-px crop is centred at (100, 150): the sensor widens 4x, the frame shifts
    s = geometry.camera_setup({**cam, "crop_box": [50, 100, 150, 200]}, (400, 200))
    assert s.sensor_mm == pytest.approx(30.594 * 4)
    assert s.shift_x == pytest.approx((200 - 100) / 400) and s.shift_y == pytest.approx((150 - 100) / 400)
    with pytest.raises(ValueError, match="incomplete"):
        geometry.camera_setup({"lens_mm": 50}, (64, 64))


@pytest.mark.parametrize("orientation", range(1, 9))
def test_upright_pixels_is_pillows_exif_transpose(tmp_path, orientation):
    """The add-on turns a tagged photo's pixels (Blender's order, bottom row first) exactly as Pillow does."""
    from PIL import Image, ImageOps

    geometry = _load("genre_addon_geometry", ADDON / "geometry.py")
    rng = np.random.default_rng(orientation)
    stored = rng.integers(0, 256, (5, 9, 4), dtype=np.uint8)  # as in the file, top row first; no symmetry
    exif = Image.Exif()
    exif[0x0112] = orientation
    Image.fromarray(stored).save(tmp_path / "p.png", exif=exif.tobytes())
    with Image.open(tmp_path / "p.png") as im:
        want = np.asarray(ImageOps.exif_transpose(im))
    got = geometry.upright_pixels(stored[::-1], orientation)[::-1]  # Blender's rows in, Blender's rows out
    np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError, match="orientation"):
        geometry.upright_pixels(stored, 9)
    with pytest.raises(ValueError, match="height, width, channels"):
        geometry.upright_pixels(stored[..., 0], orientation)


def test_read_obj(tmp_path):
    geometry = _load("genre_addon_geometry", ADDON / "geometry.py")
    p = tmp_path / "m.obj"
    p.write_text("# c\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nvn 0 0 1\nf 1//1 2//1 3//1\nf -4 -3 -1\n")
    m = geometry.read_obj(p)
    assert len(m.vertices) == 4 and m.faces == [(0, 1, 2), (0, 1, 3)]
    assert m.face_uvs is None and m.uvs == []
    # texture coordinates, as the backend writes them with --texture
    p.write_text("mtllib m.mtl\nusemtl photo\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0.25 0.5\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\nf 3/-1 2/-2 1/-3\n")
    m = geometry.read_obj(p)
    assert m.uvs == [(0.25, 0.5), (1.0, 0.0), (0.0, 1.0)] and m.face_uvs == [(0, 1, 2), (2, 1, 0)]
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/2 3/1\n")
    with pytest.raises(geometry.MeshFileError, match="texture coordinate"):
        geometry.read_obj(p)
    p.write_text("v 0 0 0\nf 1 2 3\n")
    with pytest.raises(geometry.MeshFileError, match="vertex 2"):
        geometry.read_obj(p)


def test_build_command(tmp_path):
    backend = _load("genre_addon_backend", ADDON / "backend.py")
    py = sys.executable
    assert backend.build_command(py, "w.safetensors", "cpu")[:4] == [py, "-m", "genre_backend.cli", "serve"]
    assert backend.build_command(py, "", "auto") == [py, "-m", "genre_backend.cli", "serve"]
    assert backend.build_command("genre", "", "cuda", which=lambda n: "/usr/bin/genre") == ["/usr/bin/genre", "serve", "--device", "cuda"]
    with pytest.raises(backend.BackendError, match="not found: /nope/python"):
        backend.build_command("/nope/python")
    with pytest.raises(backend.BackendError, match="no backend command set"):
        backend.build_command("", which=lambda n: None)


def test_model_choice_becomes_the_weights_argument(tmp_path):
    """Model: Product -> --weights default, Research protocol -> --weights protocol, Custom file -> its absolute path."""
    backend = _load("genre_addon_backend", ADDON / "backend.py")
    py = sys.executable
    assert [m[0] for m in backend.MODELS] == ["default", "protocol", "custom"]
    for model in ("default", "protocol"):
        assert backend.weights_argument(model, "/ignored.safetensors") == model
        assert backend.build_command(py, backend.weights_argument(model), "cpu")[4:] == ["--weights", model, "--device", "cpu"]
    w = tmp_path / "w.safetensors"
    assert backend.build_command(py, backend.weights_argument("custom", str(w)))[4:] == ["--weights", str(w)]
    assert backend.build_command(py, "rel/w.safetensors")[4:] == ["--weights", os.path.abspath("rel/w.safetensors")]
    with pytest.raises(backend.BackendError, match="no weights file is set"):
        backend.weights_argument("custom", "  ")
    with pytest.raises(backend.BackendError, match="unknown model 'product'"):
        backend.weights_argument("product")


def test_build_writes_validated_extension_and_legacy_zip(built):
    import zipfile

    assert built["extension"].name == "genre-0.1.0.zip" and built["legacy"].name == "genre-0.1.0-legacy.zip"
    ext = zipfile.ZipFile(built["extension"]).namelist()
    legacy = zipfile.ZipFile(built["legacy"]).namelist()
    assert "blender_manifest.toml" in ext and "__init__.py" in ext
    assert "genre/__init__.py" in legacy and not any(n.endswith("blender_manifest.toml") for n in legacy)
    assert not any("__pycache__" in n for n in ext + legacy)


@pytest.mark.parametrize("kind", ["extension", "legacy"])
def test_zip_installs_enables_and_unregisters_cleanly(built, kind, tmp_path):
    r = run_scenario("install", {"kind": kind, "zip": str(built[kind])}, tmp_path)
    module = "bl_ext.user_default.genre" if kind == "extension" else "genre"
    assert r["module"] == module and r["package"] == module and r["prefs_idname"] == module
    everything = {"enabled": True, "ops": ["cancel", "check_backend", "choose_file", "reconstruct"], "panel": True,
                  "scene_settings": True, "status": True, "prefs": True, "loaded": True}
    assert r["after_enable"] == everything
    assert r["after_disable"] == {"enabled": False, "ops": [], "panel": False, "scene_settings": False, "status": False,
                                  "prefs": False, "loaded": False}
    assert r["after_reenable"] == everything
    assert r["panel_place"] == ["VIEW_3D", "UI", "GenRe"]
    assert r["model_default"] == "default"
    assert r["model_items"] == [["default", "Product"], ["protocol", "Research protocol"], ["custom", "Custom file"]]
    assert r["argv"] == {"default": ["--weights", "default"], "protocol": ["--weights", "protocol"],
                         "custom": ["--weights", "/some/w.safetensors"]}
    assert "no weights file is set" in r["custom_without_file"]
    assert str(tmp_path / "blender-user") in r["installed_at"]


# ------------------------------------------------------------------ against a real `genre serve`


def make_weights(root: Path, steps: tuple[int, int, int] = (3, 3, 3), lr: float | None = None) -> Path:
    """Weights from the project's own training code: tiny rendered views, a few steps of each stage (for the GUI
    end-to-end run, tests/e2e/run_gui_e2e.py; the tests here use the session's model, conftest.py).

    ``steps``: (depth, inpaint, refine) training steps; ``lr``: one learning rate for all (None: the stage defaults).
    """
    code = f"""
import sys
from pathlib import Path
sys.path[:0] = [{str(REPO / 'tests')!r}, {str(REPO)!r}]
from tiny_data import TINY, make_tiny_views
from training.learn.train import TrainConfig, train
root = Path({str(root)!r})
views = make_tiny_views(root)
prev = None
for stage, steps in zip(("depth", "inpaint", "refine"), {tuple(steps)!r}):
    cfg = TrainConfig(stage=stage, data=str(views), out=str(root / "train"), steps=steps, batch_size=2, lr={lr!r},
                      val_fraction=0.0, augment=False, progress=False, log_every=10, init=prev)
    train(cfg, TINY if prev is None else None)
    prev = str(root / "train" / stage / "final.safetensors")
"""
    env = {**os.environ, "BLENDER_USER_RESOURCES": str(root / "blender-user"), "XDG_CACHE_HOME": str(root / "cache")}
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, timeout=900)
    if proc.returncode != 0:
        raise AssertionError(f"making the test weights failed:\n{proc.stderr[-4000:]}")
    return root / "train" / "refine" / "final.safetensors"


def make_photo(root: Path) -> Path:
    """The photo: a rendered view of the tiny views under ``root`` (``root/views``) with its object mask as alpha
    (a cut-out product shot), so that the few training steps need not have taught the depth net a silhouette yet."""
    photo = root / "box.png"
    if not photo.is_file():
        import numpy as np
        from PIL import Image

        rgb = np.asarray(Image.open(root / "views" / "box" / "view_000.png").convert("RGB"))
        mask = np.load(root / "views" / "box" / "view_000.npz")["mask"] > 0
        Image.fromarray(np.dstack([rgb, mask.astype(np.uint8) * 255]), "RGBA").save(photo)
    return photo


@pytest.fixture(scope="session")
def trained(trained):
    """(weights, photo): the session's tiny model (conftest.py's ``trained``, trained once) and a cut-out photo of
    one of its views; shared by every add-on test module of the session."""
    weights, views = trained
    return weights, make_photo(views.parent)


def test_reconstruct_against_genre_serve(built, trained, tmp_path):
    weights, photo = trained
    r = run_scenario("reconstruct", {"zip": str(built["legacy"]), "weights": str(weights), "photo": str(photo)}, tmp_path)
    ev = r["result_event"]
    assert r["outcome"][0] == "INFO", r["outcome"]
    # no override: the mesh is cut at the weights' level, and the panel's Threshold field now shows it
    from genre_backend.nets.model import load_model

    level = load_model(weights).config.geometry.default_threshold
    assert ev["threshold"] == level and r["threshold_field_after"] == pytest.approx(level)
    assert ev["hole_closing"] == load_model(weights).config.geometry.hole_closing == r["hole_closing_field_after"]
    assert ev["pit_sealing"] == load_model(weights).config.geometry.pit_sealing == r["pit_sealing_field_after"] == 0
    assert ev["silhouette_carve"] is load_model(weights).config.geometry.silhouette_carve is r["silhouette_carve_field_after"] is False
    assert ev["primitive_snap"] == load_model(weights).config.geometry.primitive_snap == r["primitive_snap_field_after"] == 0.0
    assert ev["primitive"] is None
    assert ev["test_time_mirror"] is load_model(weights).config.geometry.test_time_mirror is r["test_time_mirror_field_after"] is False
    mesh = r["mesh"]
    assert mesh["name"] == "box"
    assert mesh["collections"] == ["GenRe"]
    assert mesh["vertices"] == ev["vertices"] and mesh["faces"] == ev["faces"]
    assert mesh["smooth"]
    assert mesh["location"] == pytest.approx([1.0, 2.0, 0.5])  # the 3D cursor
    assert mesh["modifiers"] == ["SMOOTH", "DECIMATE"]
    assert -0.6 <= mesh["z_range"][0] < mesh["z_range"][1] <= 0.6  # inside the unit voxel cube, upright
    cam = mesh["camera"]
    dist = ev["camera"]["distance"]
    assert cam["lens"] == pytest.approx(ev["camera"]["lens_mm"])
    assert cam["world_location"] == pytest.approx([1.0, 2.0 - dist, 0.5], abs=1e-5)  # in front of the mesh (-Y)
    assert cam["forward"] == pytest.approx([0.0, 1.0, 0.0], abs=1e-6)  # looking along +Y at it
    assert cam["background"] == ["box.png"] and cam["shows_background"]
    assert r["added"] == {"objects": ["box", "box camera"], "meshes": ["box"], "cameras": ["box camera"],
                          "collections": ["GenRe"], "images": ["box photo", "box.png"], "materials": ["box photo"]}
    # Colour from Photo (default on): the photo's texture packed into the file, UVs that are the vertices'
    # own projections through the backend's camera for the part the photo sees
    mat = mesh["material"]
    assert mat["image"] == "box photo" and mat["packed"] and mat["image_size"][0] == mat["image_size"][1] > 0
    k = ev["camera"]["lens_mm"] / ev["camera"]["sensor_mm"]  # focal length in units of the image side
    co = np.array([c for c, _ in mat["loops"]])  # mesh coordinates (the object sits at the cursor)
    uv = np.array([t for _, t in mat["loops"]])
    x, y, z = co[:, 0], co[:, 2], -co[:, 1]  # Blender (Z up, camera on −Y) → view frame
    proj = np.stack([0.5 + k * x / (dist - z), 0.5 + k * y / (dist - z)], axis=1)
    own = np.abs(uv - proj).max(axis=1) < 1e-4
    assert 0.1 < own.mean() < 0.9, own.mean()  # the front is projected, the back borrows
    assert ((uv > -0.05) & (uv < 1.05)).all()
    assert r["status_after"]["running"] is False and not r["status_after"]["error"]
    assert f"{ev['vertices']:,} vertices" in r["status_after"]["message"]
    assert ev["mask_warning"] is None and r["status_after"]["mask_warning"] == ""
    # a doubtful mask: the job still succeeds, and the panel keeps the backend's warning
    warning = "the mask covers 100% of the photo and touches 100% of its border: it is probably the photo's frame, not the object"
    assert r["doubtful"] == {"outcome": r["doubtful"]["outcome"], "mask_warning": warning, "event": warning}
    assert r["doubtful"]["outcome"][0] == "INFO"
    assert r["job_dirs_after"] == []  # temporary files removed
    assert "write" in r["stages"] or "mesh" in r["stages"]
    assert max(r["progress_seen"]) > 0
    # the operator reuses the running backend
    assert r["operator"] == ["FINISHED"] and r["same_backend"]
    assert len(r["objects_after_second"]) == 3
    assert r["check"] == ["FINISHED"]
    assert "preset tiny" in r["backend_info"] and "device cpu" in r["backend_info"] and f"threshold {level}" in r["backend_info"]
    assert r["backend_exit_after_disable"] is not None
    # the turned photo: the backend reports the tag; the camera shows the upright photo, packed, at the right size
    exif = r["exif"]
    assert exif["outcome"][0] == "INFO", exif["outcome"]
    assert exif["camera_event"]["exif_orientation"] == 6 and exif["camera_event"]["image_size"] == exif["upright_size"]
    assert exif["upright_size"][0] > exif["upright_size"][1]  # wider than tall, stored taller than wide
    assert exif["size"] == exif["upright_size"] == exif["resolution"] and exif["packed"]
    assert exif["max_pixel_error"] < 1e-6  # the very pixels Pillow shows
    assert exif["background"] == "turned.png (upright)" and "turned.png" not in exif["new_images"]


def test_failures_leave_nothing_behind_and_say_why(built, trained, tmp_path):
    weights, photo = trained
    corrupt = tmp_path / "corrupt.png"
    corrupt.write_bytes(b"\x89PNG\r\n\x1a\n this is not really a png")
    from PIL import Image

    bad_mask = tmp_path / "mask.png"
    Image.new("L", (13, 7), 255).save(bad_mask)
    args = {"zip": str(built["extension"]), "extension": True, "weights": str(weights), "photo": str(photo),
            "corrupt_photo": str(corrupt), "bad_mask": str(bad_mask), "tmp": str(tmp_path), "foreign_python": "/usr/bin/python3"}
    r = run_scenario("failures", args, tmp_path)
    clean = {"added": {}, "running": False, "job_dirs": [], "active_job": False}

    def check(name, *needles, level="ERROR"):
        rec = r[name]
        for key, value in clean.items():
            assert rec[key] == value, (name, key, rec)
        text = rec.get("raised") or rec.get("outcome", ["", ""])[1]
        if "outcome" in rec:
            assert rec["outcome"][0] == level, (name, rec)
        for needle in needles:
            assert needle in text, (name, needle, text)

    check("missing_command", "backend command not found: /nonexistent/bin/python3")
    check("missing_command_operator", "backend command not found: /nonexistent/bin/python3")
    check("not_a_backend", "the backend exited with code 1", "No module named")
    check("missing_photo", "photo not found:", "no-such-photo.png")
    check("bad_photo", "(bad_image)", "corrupt.png")
    check("error_event", "(bad_mask)")
    check("crash", "killed by signal 9")
    check("timeout", "timed out after 0.001 s")
    check("cancel", "cancelled", level="WARNING")
    check("broken_mesh", "could not add the result", "vertex")
    check("photo_gone", "could not add the result", "vanishing.png")
    assert r["restarted_after_crash"]
    assert r["timed_out_backend_replaced"]
    for name in ("works_after_missing_command", "works_after_crash", "works_after_timeout", "works_at_the_end"):
        rec = r[name]
        assert rec["outcome"][0] == "INFO", (name, rec)
        assert rec["job_dirs"] == [] and rec["running"] is False
    assert "backend command not found" in r["check_missing"]
    assert "backend could not start" in r["check_bad_weights"] and "missing.safetensors" in r["check_bad_weights"]
    assert "(bad_weights)" in r["check_bad_weights"]
