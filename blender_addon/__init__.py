"""GenRe for Blender: turn one photo of an object into a mesh, from the 3D viewport's sidebar.

Loads as a Blender 4.2+ extension (``blender_manifest.toml``) and as a legacy
add-on in Blender 3.4–4.1 (``bl_info``).  The reconstruction runs in a
separate ``genre serve`` process (see ``docs/protocol.md``), started on first
use and stopped when the add-on is disabled or Blender quits.

The version lives in ``blender_manifest.toml``; ``bl_info["version"]`` must
repeat it (``build_addon.py`` refuses to build otherwise, and a test checks it).
"""

bl_info = {
    "name": "GenRe: Photo to Mesh",
    "author": "GenRe project",
    "version": (0, 1, 0),
    "blender": (3, 4, 0),
    "location": "3D Viewport > Sidebar > GenRe",
    "description": "Reconstruct a 3D mesh from one photo with GenRe, with a camera that matches the photo",
    "category": "Import-Export",
}

import atexit

if "ops" in locals():  # re-running register() after a script reload
    import importlib

    for _name in ("protocol", "annotations", "backend", "installer", "schema", "geometry", "jobs", "props", "ops", "ui"):
        importlib.reload(locals()[_name])

from . import annotations, backend, geometry, installer, jobs, ops, props, protocol, schema, ui  # noqa: E402, F401

_MODULES = (props, ops, ui)


def register():
    for module in _MODULES:
        module.register()
    atexit.register(ops.shutdown_backend)


def unregister():
    atexit.unregister(ops.shutdown_backend)
    for module in reversed(_MODULES):
        module.unregister()
