"""Inside a GUI Blender (``blender --python THIS -- ARGS.json``): annotate over a photo in a drawn Image Editor.

Loads the photo into the largest area turned Image Editor, waits until the
editor has been drawn (its view space set), draws one stroke with the real
Annotate operator through the region pixels of known view-space points, and
writes to ``out`` the points Blender stored, where it stored the annotation,
the image's size and the add-on's conversion of that annotation to photo
pixels (``blender_addon/annotations.py``, loaded by file).  Quits Blender.
"""

import importlib.util
import json
import sys
import traceback

import bpy

ARGS = json.loads(open(sys.argv[sys.argv.index("--") + 1]).read())
POINTS = [(0.25, 0.3), (0.5, 0.5), (0.7, 0.8)]  # view space: 0-1 over the image, y up
out = {"version": bpy.app.version_string}
state = {"ticks": 0}


def step():
    state["ticks"] += 1
    try:
        window = bpy.context.window_manager.windows[0]
        area = max(window.screen.areas, key=lambda a: a.width * a.height)
        if area.type != "IMAGE_EDITOR":
            area.type = "IMAGE_EDITOR"
            area.spaces.active.image = bpy.data.images.load(ARGS["photo"])
            return 1.0
        region = next(r for r in area.regions if r.type == "WINDOW")
        mouse = [region.view2d.view_to_region(u, v, clip=False) for u, v in POINTS]
        if mouse[0][0] < -10000 and state["ticks"] < 20:  # not drawn yet
            return 1.0
        keys = {p.identifier for p in bpy.types.OperatorStrokeElement.bl_rna.properties}
        elements = [{k: v for k, v in {"name": "", "mouse": m, "mouse_event": m, "location": (0, 0, 0), "pressure": 1.0, "size": 0.0,
                                        "pen_flip": False, "x_tilt": 0.0, "y_tilt": 0.0, "time": 0.0, "is_start": i == 0}.items() if k in keys}
                    for i, m in enumerate(mouse)]
        with bpy.context.temp_override(window=window, area=area, region=region):
            out["op"] = sorted(bpy.ops.gpencil.annotate(mode="DRAW", stroke=elements, wait_for_input=False))
        space = area.spaces.active
        annotation = getattr(space, "annotation", None) or getattr(space, "grease_pencil", None)
        out["stored_on"] = "annotation" if getattr(space, "annotation", None) is not None else "grease_pencil"
        out["co"] = [[list(p.co) for p in s.points] for layer in annotation.layers for s in layer.active_frame.strokes]
        out["size"] = list(space.image.size)
        spec = importlib.util.spec_from_file_location("genre_annotations", ARGS["annotations_py"])
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        out["found_same"] = module.find_annotation(space.image, bpy.context.window_manager) == annotation
        lines = module.layer_lines(annotation, *space.image.size)
        out["object_pixels"] = [[list(p) for p in line] for line in lines["object"]]
    except Exception:
        out["error"] = traceback.format_exc()
    with open(ARGS["out"], "w") as f:
        json.dump(out, f, default=str)
    bpy.ops.wm.quit_blender()
    return None


bpy.app.timers.register(step, first_interval=3.0)
