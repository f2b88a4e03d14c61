"""Runs inside a GUI Blender (3.4+; here Debian's 3.4.1 under Xvfb): the add-on end to end, timer ticks and all.

``blender --factory-startup --enable-event-simulate --python blender_gui_script.py -- ARGS.json``

Installs the legacy zip, points the preferences at the backend, opens the
sidebar on the "GenRe" tab, presses Reconstruct (the operator invoked as the
button does), lets the modal operator's timer run the job, notes when the
mesh appears, frames it, saves screenshots of the window (viewport with the
panel) and of the view through the matching camera, writes RESULT.json and
quits.  Any failure is written to RESULT.json too, and Blender exits non-zero.
"""

import json
import os
import sys
import time
import traceback

import bpy

ARGS = json.loads(open(sys.argv[sys.argv.index("--") + 1]).read())
OUT = ARGS["out"]
RESULT = {"blender": bpy.app.version_string, "python": sys.version.split()[0], "ticks": 0, "log": []}
T = {}


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
    window, area, region, sidebar = view3d()
    area.spaces.active.show_region_ui = True
    # show what an artist sees with Colour from Photo on: the material's image in solid shading
    area.spaces.active.shading.type = "SOLID"
    area.spaces.active.shading.color_type = "TEXTURE"
    log("add-on installed and enabled")
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
        bpy.app.timers.register(press_reconstruct, first_interval=0.5)
        return None
    RESULT["warm_press_to_mesh_s"] = round(T["mesh"] - T["press"], 3)
    obj = meshes[-1]
    RESULT["message"] = status.message
    RESULT["mesh"] = {"name": obj.name, "vertices": len(obj.data.vertices), "faces": len(obj.data.polygons),
                      "camera": [c.name for c in obj.children]}
    log(f"mesh in the scene after {RESULT['warm_press_to_mesh_s']} s (backend running): {status.message}")
    window, area, region, sidebar = view3d()
    meshes[0].hide_set(True)  # the first result sits at the same place
    for o in bpy.context.view_layer.objects:
        o.select_set(o == obj)
    bpy.context.view_layer.objects.active = obj
    with bpy.context.temp_override(window=window, area=area, region=region):
        bpy.ops.view3d.view_selected()
    bpy.app.timers.register(shoot_panel, first_interval=1.0)
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
