"""Runs inside a GUI Blender (3.4+; here Debian's 3.4.1 under Xvfb): the add-on end to end, timer ticks and all.

``blender --factory-startup --enable-event-simulate --python blender_gui_script.py -- ARGS.json``

Installs the legacy zip, points the preferences at the backend, opens the
sidebar on the "GenRe" tab, presses Reconstruct (the operator invoked as the
button does), lets the modal operator's timer run the job, notes when the
mesh appears, frames it, saves screenshots of the window (viewport with the
panel) and of the view through the matching camera, writes RESULT.json and
quits.  Any failure is written to RESULT.json too, and Blender exits non-zero.

With ``"scenario": "install"`` (``run_gui_e2e.py --scenario install``) nothing is set but the Python and the
folder of wheels: Edit > Preferences opens on the add-on, Install Backend is pressed (``install_progress.png``
while it runs, ``installed.png`` when it has checked the backend), the window is closed, and Reconstruct runs as
above with the backend it installed and its shipped default weights.

With ``"scenario": "annotate"`` in ARGS (``run_gui_e2e.py``'s second run) the
3D view is split and one part turned into an Image Editor showing the
photo; the object strokes, background strokes and box of ARGS["annotation"]
(the photo's pixels, x right, y down) are drawn over it with the real
Annotate operator (``gpencil.annotate``, through the region pixels of each
point) on layers "Note", "Background" and "Box"; the editor is saved as
``annotated_photo.png``; Reconstruct is pressed once, and the window with the
mesh, the panel's result line and the annotated photo is saved as
``annotate_result.png``.  The request the add-on sent is recorded (with
``save_intermediates`` added, so that the mask the backend used is kept) and
its strokes image copied to ``annotation_strokes.png``.
"""

import json
import os
import shutil
import sys
import time
import traceback

import bpy

ARGS = json.loads(open(sys.argv[sys.argv.index("--") + 1]).read())
OUT = ARGS["out"]
RESULT = {"blender": bpy.app.version_string, "python": sys.version.split()[0], "ticks": 0, "log": []}
T = {}
ANNOTATE = ARGS.get("scenario") == "annotate"
INSTALL = ARGS.get("scenario") == "install"  # Install Backend pressed in the preferences first (a folder of wheels)
# annotation layers: name → colour (the add-on reads the names: docs/masks.md "In Blender")
LAYERS = {"Note": (0.1, 1.0, 0.2), "Background": (1.0, 0.15, 0.15), "Box": (1.0, 0.85, 0.0)}


def log(msg):
    RESULT["log"].append(f"{time.monotonic() - T['launch']:.2f}s {msg}")
    print("[e2e]", msg, flush=True)


def finish(code):
    RESULT["exit_code"] = code
    with open(os.path.join(OUT, "result.json"), "w") as fh:
        json.dump(RESULT, fh, indent=2, default=str)
    log(f"done, exit {code}")
    os._exit(code) if code else bpy.ops.wm.quit_blender()


def guarded(fn):
    def run():
        try:
            return fn()
        except Exception:
            RESULT["error"] = traceback.format_exc()
            print(RESULT["error"], flush=True)
            finish(1)
            return None
    return run


def view3d():
    window = bpy.context.window_manager.windows[0]
    area = max((a for a in window.screen.areas if a.type == "VIEW_3D"), key=lambda a: a.width * a.height)
    region = next(r for r in area.regions if r.type == "WINDOW")
    sidebar = next(r for r in area.regions if r.type == "UI")
    return window, area, region, sidebar


@guarded
def setup():
    T["setup"] = time.monotonic()
    bpy.ops.preferences.addon_install(filepath=ARGS["zip"], overwrite=True)
    bpy.ops.preferences.addon_enable(module="genre")
    prefs = bpy.context.preferences.addons["genre"].preferences
    if INSTALL:  # Install Backend fills in Backend Command; the shipped default weights come with the backend
        prefs.backend_python = ARGS["install"]["python"]
        prefs.wheel_folder = ARGS["install"]["wheels"]
        prefs.model = "default"
    else:
        prefs.backend_command = ARGS["backend_python"]
        prefs.model = "custom"  # the weights file given (run_gui_e2e.py: the shipped default.safetensors, or tiny test weights)
        prefs.weights = ARGS["weights"]
    prefs.device = "cpu"
    for obj in list(bpy.data.objects):  # an empty stage: no default cube, camera or light
        bpy.data.objects.remove(obj)
    scene = bpy.context.scene
    scene.genre.photo_path = ARGS["photo"]
    scene.genre.mask_path = ARGS.get("mask") or ""
    scene.genre.smoothing = 1
    if ANNOTATE:
        split_for_photo()
    window, area, region, sidebar = view3d()
    area.spaces.active.show_region_ui = True
    # show what an artist sees with Colour from Photo on: the material's image in solid shading
    area.spaces.active.shading.type = "SOLID"
    area.spaces.active.shading.color_type = "TEXTURE"
    log("add-on installed and enabled")
    if INSTALL:
        open_preferences()
        bpy.app.timers.register(press_install, first_interval=1.0)
    else:
        bpy.app.timers.register(fit_photo if ANNOTATE else show_tab, first_interval=0.5)


def open_preferences():
    """Edit > Preferences > Add-ons, filtered to GenRe and expanded: where an artist finds Install Backend."""
    bpy.context.preferences.active_section = "ADDONS"
    bpy.context.window_manager.addon_search = "GenRe"
    bpy.ops.screen.userpref_show()
    bpy.ops.preferences.addon_expand(module="genre")


def preferences_window():
    for window in bpy.context.window_manager.windows:
        area = next((a for a in window.screen.areas if a.type == "PREFERENCES"), None)
        if area is not None:
            return window, area, next(r for r in area.regions if r.type == "WINDOW")
    raise RuntimeError("no Preferences window")


@guarded
def press_install():
    window, area, region = preferences_window()
    log("pressing Install Backend")
    T["install"] = time.monotonic()
    with bpy.context.temp_override(window=window, area=area, region=region):
        RESULT["install_invoke"] = sorted(bpy.ops.genre.install_backend("INVOKE_DEFAULT"))
    bpy.app.timers.register(watch_install, first_interval=0.1)


@guarded
def watch_install():
    status = bpy.context.window_manager.genre_status
    if status.installing:
        step = (status.install_stage, round(status.install_progress, 2))
        if not RESULT.get("install_steps") or RESULT["install_steps"][-1] != list(step):
            RESULT.setdefault("install_steps", []).append(list(step))
        if "install_screenshot" not in RESULT and status.install_stage == "Installing the backend":
            shoot_preferences("install_progress.png", "install_screenshot")
        if time.monotonic() - T["install"] > ARGS.get("timeout", 300) + 600:
            RESULT["error"] = "timed out installing the backend"
            finish(1)
        return 0.2
    if status.checking:  # Install Backend ends by checking the backend it made
        return 0.2
    RESULT["install_s"] = round(time.monotonic() - T["install"], 1)
    RESULT["install_message"], RESULT["install_ok"] = status.install_message, status.install_ok
    RESULT["backend_info"], RESULT["backend_ok"] = status.backend_info, status.backend_ok
    RESULT["backend_command"] = bpy.context.preferences.addons["genre"].preferences.backend_command
    log(f"install ended after {RESULT['install_s']} s: {status.install_message}; check: {status.backend_info}")
    if not (status.install_ok and status.backend_ok):
        RESULT["error"] = f"install: {status.install_message}; check: {status.backend_info}"
        shoot_preferences("install_failed.png", "install_screenshot")
        finish(1)
        return None
    bpy.app.timers.register(shoot_installed, first_interval=0.5)
    return None


def shoot_preferences(name, key):
    window, area, region = preferences_window()
    path = os.path.join(OUT, name)
    with bpy.context.temp_override(window=window, area=area, region=region):
        bpy.ops.screen.screenshot(filepath=path)
    RESULT[key] = path
    log(f"screenshot {path}")


@guarded
def shoot_installed():
    shoot_preferences("installed.png", "installed_screenshot")
    window, area, region = preferences_window()
    with bpy.context.temp_override(window=window, area=area, region=region):
        bpy.ops.wm.window_close()
    bpy.app.timers.register(show_tab, first_interval=0.5)


def image_editor():
    window = bpy.context.window_manager.windows[0]
    area = next(a for a in window.screen.areas if a.type == "IMAGE_EDITOR")
    return window, area, next(r for r in area.regions if r.type == "WINDOW")


def split_for_photo():
    """Split the 3D view; one part becomes an Image Editor showing the photo (as an artist would set it up)."""
    window, area, region, sidebar = view3d()
    with bpy.context.temp_override(window=window, area=area, region=region):
        bpy.ops.screen.area_split(direction="VERTICAL", factor=0.45)
    left = min((a for a in window.screen.areas if a.type == "VIEW_3D"), key=lambda a: a.x)
    left.type = "IMAGE_EDITOR"
    image = bpy.data.images.load(ARGS["photo"])
    left.spaces.active.image = image
    RESULT["image_size"] = list(image.size)  # Blender's own loader: the pixels as stored (EXIF orientation ignored)


@guarded
def fit_photo():
    window, area, region = image_editor()
    with bpy.context.temp_override(window=window, area=area, region=region):
        bpy.ops.image.view_all(fit_view=True)
    bpy.app.timers.register(annotate_photo, first_interval=1.0)  # drawn again: the view space is set


def densify(line, step=3.0):
    """``line`` with points at most ``step`` apart, as a mouse drag gives them (the Annotate tool smooths a stroke's
    points with their neighbours: a few far-apart points, a rectangle's corners, would be pulled out of place)."""
    out = [tuple(line[0])]
    for (ax, ay), (bx, by) in zip(line[:-1], line[1:]):
        n = max(1, int(((bx - ax) ** 2 + (by - ay) ** 2) ** 0.5 / step + 0.999))
        out.extend((ax + (bx - ax) * i / n, ay + (by - ay) * i / n) for i in range(1, n + 1))
    return out


def draw_stroke(window, area, region, line, size):
    """One stroke with the Annotate tool through the region pixels of ``line`` (the photo's pixels, y down)."""
    width, height = size
    mouse = [region.view2d.view_to_region(x / width, 1.0 - y / height, clip=False) for x, y in densify(line)]
    if min(min(m) for m in mouse) < -10000:
        raise RuntimeError(f"the Image Editor is not drawn yet (view to region gives {mouse[0]})")
    keys = {p.identifier for p in bpy.types.OperatorStrokeElement.bl_rna.properties}
    elements = [{k: v for k, v in {"name": "", "mouse": m, "mouse_event": m, "location": (0, 0, 0), "pressure": 1.0, "size": 0.0,
                                    "pen_flip": False, "x_tilt": 0.0, "y_tilt": 0.0, "time": 0.0, "is_start": i == 0}.items() if k in keys}
                for i, m in enumerate(mouse)]
    with bpy.context.temp_override(window=window, area=area, region=region):
        done = bpy.ops.gpencil.annotate(mode="DRAW", stroke=elements, wait_for_input=False)
    if done != {"FINISHED"}:
        raise RuntimeError(f"gpencil.annotate returned {done}")


@guarded
def annotate_photo():
    window, area, region = image_editor()
    space = area.spaces.active
    size = tuple(space.image.size)
    drawn = ARGS["annotation"]
    for name, lines in (("Note", drawn["object"]), ("Background", drawn["background"]), ("Box", [drawn["box"]])):
        annotation = getattr(space, "annotation", None) or getattr(space, "grease_pencil", None)  # (Blender < 4.3)
        if annotation is not None and name != "Note":
            annotation.layers.new(name, set_active=True)
        for line in lines:
            draw_stroke(window, area, region, line, size)
        annotation = getattr(space, "annotation", None) or getattr(space, "grease_pencil", None)
        layer = annotation.layers.active
        layer.color, layer.thickness = LAYERS[name], 4
    RESULT["annotation_layers"] = {layer.info: [len(s.points) for s in layer.active_frame.strokes] for layer in annotation.layers}
    log(f"annotated the photo: {RESULT['annotation_layers']}")
    record_requests()
    bpy.app.timers.register(shoot_annotation, first_interval=1.0)


def record_requests():
    """Keep what the add-on sends: the request (with save_intermediates added: the mask the backend used) and its strokes image."""
    jobs = sys.modules["genre"].jobs
    original = jobs.JobSpec.request_payload

    def recorded(spec):
        payload = original(spec)
        payload["options"]["save_intermediates"] = os.path.join(OUT, "intermediates")
        RESULT["request"] = payload
        if spec.strokes_path:
            shutil.copyfile(spec.strokes_path, os.path.join(OUT, "annotation_strokes.png"))
        return payload

    jobs.JobSpec.request_payload = recorded


@guarded
def shoot_annotation():
    window, area, region = image_editor()
    path = os.path.join(OUT, "annotated_photo.png")
    with bpy.context.temp_override(window=window, area=area, region=region):
        bpy.ops.screen.screenshot_area(filepath=path)
    RESULT["annotation_screenshot"] = path
    log(f"screenshot {path}")
    bpy.app.timers.register(show_tab, first_interval=0.5)


@guarded
def show_tab():
    # Blender 3.4 has no API for the sidebar's active tab: Ctrl+Wheel over the sidebar cycles the
    # tabs (Item, Tool, View, GenRe), as a user would.
    if not ARGS.get("event_simulate"):
        bpy.app.timers.register(press_reconstruct, first_interval=1.0)
        return None
    window, area, region, sidebar = view3d()
    # over the tab strip at the sidebar's right edge
    x, y = sidebar.x + sidebar.width - 8, sidebar.y + sidebar.height - 120
    window.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x, y=y)
    for _ in range(ARGS.get("tab_steps", 3)):
        window.event_simulate(type="WHEELDOWNMOUSE", value="PRESS", x=x, y=y, ctrl=True)
    bpy.app.timers.register(press_reconstruct, first_interval=1.0)


@guarded
def press_reconstruct():
    window, area, region, sidebar = view3d()
    RESULT["presses"] = RESULT.get("presses", 0) + 1
    log(f"pressing Reconstruct (press {RESULT['presses']})")
    T["press"] = time.monotonic()
    RESULT["ticks"] = 0
    with bpy.context.temp_override(window=window, area=area, region=sidebar):
        RESULT["invoke"] = sorted(bpy.ops.genre.reconstruct("INVOKE_DEFAULT"))
    log(f"operator returned {RESULT['invoke']} (modal: the timer does the rest)")
    bpy.app.timers.register(watch, first_interval=0.02)


@guarded
def watch():
    status = bpy.context.window_manager.genre_status
    RESULT["ticks"] += 1
    coll = bpy.data.collections.get("GenRe")
    meshes = [o for o in coll.objects if o.type == "MESH"] if coll else []
    if len(meshes) < RESULT["presses"]:
        meshes = []
    if status.running:
        if "running_screenshot" not in RESULT and time.monotonic() - T["press"] > 1.0:
            # the panel while a job runs: progress bar with the stage, and Cancel
            window, area, region, sidebar = view3d()
            path = os.path.join(OUT, "panel_while_running.png")
            with bpy.context.temp_override(window=window, area=area, region=region):
                bpy.ops.screen.screenshot(filepath=path)
            RESULT["running_screenshot"] = path
        stage = (status.stage, round(status.progress, 2))
        if not RESULT.get("stages") or RESULT["stages"][-1] != list(stage):
            RESULT.setdefault("stages", []).append(list(stage))
        if time.monotonic() - T["press"] > ARGS.get("timeout", 300):
            RESULT["error"] = "timed out waiting for the mesh"
            finish(1)
        return 0.02
    if not meshes:
        if RESULT["ticks"] < 3:  # the modal operator starts on the next event loop turn
            return 0.02
        RESULT["error"] = f"no mesh; panel says: {status.message}"
        finish(1)
        return None
    T["mesh"] = time.monotonic()
    if RESULT["presses"] == 1:
        # First press: the backend starts (Python, torch, the model).  Press again for the warm figure.
        RESULT["press_to_mesh_s"] = round(T["mesh"] - T["press"], 3)
        RESULT["first_message"] = status.message
        log(f"mesh in the scene after {RESULT['press_to_mesh_s']} s (backend started): {status.message}")
        if not ANNOTATE:
            bpy.app.timers.register(press_reconstruct, first_interval=0.5)
            return None
    else:
        RESULT["warm_press_to_mesh_s"] = round(T["mesh"] - T["press"], 3)
        log(f"mesh in the scene after {RESULT['warm_press_to_mesh_s']} s (backend running): {status.message}")
    obj = meshes[-1]
    RESULT["message"] = status.message
    RESULT["mask_warning"] = status.mask_warning
    RESULT["mesh"] = {"name": obj.name, "vertices": len(obj.data.vertices), "faces": len(obj.data.polygons),
                      "camera": [c.name for c in obj.children]}
    overlay = bpy.data.images.get("GenRe mask")  # the mask over the photo, which the panel shows under the result line
    RESULT["mask_overlay"] = None if overlay is None else {"size": list(overlay.size), "packed": overlay.packed_file is not None}
    window, area, region, sidebar = view3d()
    if len(meshes) > 1:
        meshes[0].hide_set(True)  # the first result sits at the same place
    for o in bpy.context.view_layer.objects:
        o.select_set(o == obj)
    bpy.context.view_layer.objects.active = obj
    with bpy.context.temp_override(window=window, area=area, region=region):
        bpy.ops.view3d.view_selected()
    bpy.app.timers.register(shoot_result if ANNOTATE else shoot_panel, first_interval=1.0)
    return None


@guarded
def shoot_result():
    screenshot("annotate_result.png", "screenshot")  # the annotated photo, the mesh and the panel's result line
    finish(0)
    return None


def screenshot(name: str, key: str) -> tuple:
    """Save the window as OUT/name, record it under RESULT[key]; returns (window, area, region) of the 3D view."""
    window, area, region, sidebar = view3d()
    path = os.path.join(OUT, name)
    with bpy.context.temp_override(window=window, area=area, region=region):
        bpy.ops.screen.screenshot(filepath=path)
    RESULT[key] = path
    log(f"screenshot {path}")
    return window, area, region


@guarded
def shoot_panel():
    window, area, region = screenshot("viewport_with_panel.png", "screenshot")
    cam = bpy.context.scene.camera
    if cam is not None:
        with bpy.context.temp_override(window=window, area=area, region=region):
            bpy.ops.view3d.view_camera()
        space = area.spaces.active
        space.overlay.show_overlays = True
        bpy.app.timers.register(shoot_camera, first_interval=1.0)
    else:
        finish(0)
    return None


@guarded
def shoot_camera():
    window, area, region = screenshot("through_camera.png", "camera_screenshot")
    with bpy.context.temp_override(window=window, area=area, region=region):
        bpy.ops.view3d.view_axis(type="RIGHT")  # the side: how deep the mesh is, and the colour of its unseen side
        bpy.ops.view3d.view_selected()
    bpy.app.timers.register(shoot_side, first_interval=1.0)
    return None


@guarded
def shoot_side():
    screenshot("side.png", "side_screenshot")
    finish(0)
    return None


T["launch"] = time.monotonic()
bpy.app.timers.register(setup, first_interval=0.5)
