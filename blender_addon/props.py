"""The add-on's properties: per-scene settings, the window manager's run status, and the preferences."""

from __future__ import annotations

import math
import os

import bpy
from bpy.props import BoolProperty, CollectionProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from . import installer
from .backend import MODELS
from .schema import QUALITIES

# The add-on's module name: "genre" as a legacy add-on, "bl_ext.<repo>.genre" as an extension.
ADDON_PACKAGE = __package__

_user_folder: dict = {}


def addon_user_folder() -> str:
    """The add-on's own writable folder (the extension's user folder on 4.2+, else the config folder's ``genre``)."""
    if "path" not in _user_folder:
        _user_folder["path"] = installer.user_folder(ADDON_PACKAGE, tuple(bpy.app.version),
                                                     getattr(bpy.utils, "extension_path_user", None), bpy.utils.user_resource)
    return _user_folder["path"]


def backend_env() -> str:
    """The backend's private Python environment (Install Backend makes it) inside :func:`addon_user_folder`."""
    return installer.env_folder(addon_user_folder())


def _clamp(self, context):
    """Keep a row's number inside the option's range (an open end: one step inside it)."""
    if self.kind == "float":
        lo = self.lo + (0.001 if self.lo_open else 0.0)
        hi = self.hi - (0.001 if self.hi_open else 0.0)
        value = min(max(self.float_value, lo), hi)
        if abs(value - self.float_value) > 1e-6:  # (the property is float32: an exact comparison would never settle)
            self.float_value = value
    elif self.kind == "int":
        value = int(min(max(self.int_value, math.ceil(self.lo)), math.floor(self.hi)))
        if value != self.int_value:
            self.int_value = value


class GENRE_PG_option(bpy.types.PropertyGroup):
    """One mesh option's row in the Advanced panel, made from the backend's schema (``name``: the option's name).

    ``override`` on: the value here is sent (``float_value``, ``int_value``, ``bool_value`` or ``choice_value`` by
    ``kind``); off: the weights' own (``weights_value``, the schema's default as JSON) is used and shown.
    """

    label: StringProperty(name="Label")
    help: StringProperty(name="Help")
    kind: StringProperty(name="Kind")  # float | int | bool | choice
    lo: FloatProperty(name="Minimum")
    hi: FloatProperty(name="Maximum")
    lo_open: BoolProperty(name="Minimum Excluded")
    hi_open: BoolProperty(name="Maximum Excluded")
    choices: StringProperty(name="Choices")  # JSON list
    weights_value: StringProperty(name="Weights' Value", default="null")  # JSON
    override: BoolProperty(name="Override", description="Use the value beside this box instead of the model's own setting",
                           default=False)
    float_value: FloatProperty(name="Value", precision=3, step=1, update=_clamp)
    int_value: IntProperty(name="Value", update=_clamp)
    bool_value: BoolProperty(name="Value")
    choice_value: StringProperty(name="Value")


class GENRE_PG_settings(bpy.types.PropertyGroup):
    """What to reconstruct and how (``scene.genre``)."""

    source: EnumProperty(
        name="Source",
        description="Where the photo comes from",
        items=(
            ("FILE", "File", "A photo file on disk"),
            ("IMAGE", "Image", "An image already loaded in Blender"),
        ),
        default="FILE",
    )
    # No FILE_PATH subtype: its built-in browser shows every file; the panel's button opens one filtered to images.
    photo_path: StringProperty(name="Photo", description="The photo of one object to reconstruct")
    image: PointerProperty(name="Image", description="An image loaded in Blender to reconstruct from", type=bpy.types.Image)
    mask_path: StringProperty(
        name="Mask",
        description="Optional black-and-white mask of the object, the photo's size (else the photo's alpha, else the network's own silhouette)",
    )
    use_annotation: BoolProperty(
        name="Use Annotation",
        description="The mask is found by a salient-object net, which takes the photo's most eye-catching object. "
                    "If it is wrong, guide it with what is drawn over the photo in an Image Editor with the Annotate tool: "
                    "a box (draw it on a layer named 'Box'), or strokes: on the object, and on a layer named 'Background' "
                    "for background. A mask file, when chosen, is used instead",
        default=True,
    )
    quality: EnumProperty(
        name="Quality",
        description="How hard the backend works: a named set of its options (the Advanced rows you tick override it)",
        items=[(ident, label, text) for ident, label, text, _ in QUALITIES],
        default="BEST",
    )
    colour_from_photo: BoolProperty(
        name="Colour from Photo",
        description="Colour the mesh with the photo: UVs into the photo and a material with it as base colour "
                    "(sides the photo does not show take the colour of the nearest surface it shows)",
        default=True,
    )
    # the Advanced rows: one per mesh option the backend publishes (its `ready` event's schema), filled by ops.sync_options
    options: CollectionProperty(type=GENRE_PG_option)
    smoothing: IntProperty(
        name="Smoothing", description="Smoothing iterations (a Smooth modifier; 0 for none)", default=2, min=0, max=50,
    )
    target_faces: IntProperty(
        name="Target Faces", description="Decimate to about this many faces (a Decimate modifier; 0 keeps every face)",
        default=0, min=0, soft_max=200000,
    )
    add_camera: BoolProperty(
        name="Add Matching Camera",
        description="Add a camera that sees the mesh as the photo saw the object, with the photo as its background",
        default=True,
    )


class GENRE_PG_status(bpy.types.PropertyGroup):
    """What the add-on is doing now (``window_manager.genre_status``; not saved in files)."""

    running: BoolProperty(name="Running", default=False)
    progress: FloatProperty(name="Progress", default=0.0, min=0.0, max=1.0, subtype="FACTOR")
    stage: StringProperty(name="Stage", default="")
    message: StringProperty(name="Result", default="")
    message_is_error: BoolProperty(default=False)
    mask_warning: StringProperty(name="Mask Warning", default="")
    checking: BoolProperty(name="Checking Backend", default=False)
    backend_info: StringProperty(name="Backend", default="")
    backend_ok: BoolProperty(default=False)
    installing: BoolProperty(name="Installing Backend", default=False)
    install_progress: FloatProperty(name="Install Progress", default=0.0, min=0.0, max=1.0, subtype="FACTOR")
    install_stage: StringProperty(name="Install Step", default="")
    install_line: StringProperty(name="Last Log Line", default="")
    install_message: StringProperty(name="Install Result", default="")
    install_ok: BoolProperty(default=False)


def draw_progress(layout, factor: float, text: str) -> None:
    """A progress bar: ``layout.progress`` where Blender has it (4.0+); before, a label with a bar of characters
    (a greyed slider there reads as a setting)."""
    if hasattr(layout, "progress"):
        layout.progress(factor=factor, type="BAR", text=f"{text} ({factor:.0%})")
        return
    filled = int(round(max(0.0, min(1.0, factor)) * PROGRESS_CELLS))
    layout.label(text=f"{text} ({factor:.0%})", icon="TIME")
    layout.label(text="\u2588" * filled + "\u2591" * (PROGRESS_CELLS - filled))


PROGRESS_CELLS = 20  # the characters of the fallback bar


class GENRE_AP_preferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_PACKAGE

    backend_command: StringProperty(
        name="Backend Command",
        description="A Python interpreter with the GenRe backend installed (run as 'python -m genre_backend.cli serve') "
                    "or the 'genre' program; empty: 'genre' on the PATH",
        subtype="FILE_PATH",
    )
    model: EnumProperty(
        name="Model",
        description="Which weights the backend runs: the product model, the research protocol's, or a file of your own",
        items=MODELS,
        default="default",
    )
    weights: StringProperty(name="Weights", description="The weights file (.safetensors) used when Model is 'Custom file'", subtype="FILE_PATH")
    device: EnumProperty(
        name="Device",
        items=(
            ("auto", "Automatic", "Let the backend choose"),
            ("cpu", "CPU", "Run on the CPU"),
            ("cuda", "CUDA", "Run on an NVIDIA GPU"),
        ),
        default="auto",
    )
    startup_timeout: FloatProperty(
        name="Start-up Time-out", description="Seconds the backend may take to load its model", default=120.0, min=1.0, unit="TIME_ABSOLUTE",
    )
    job_timeout: FloatProperty(
        name="Reconstruction Time-out", description="Seconds one reconstruction may take", default=600.0, min=0.001, unit="TIME_ABSOLUTE",
    )
    backend_python: StringProperty(
        name="Python for the Backend",
        description="The Python 3.11 that Install Backend makes the backend's environment with; empty: Blender's own "
                    "(3.11 in Blender 4.2 to 5.0)",
        subtype="FILE_PATH",
    )
    wheel_folder: StringProperty(
        name="Offline Wheels",
        description="Install from this folder of wheels (pip download) instead of the internet; empty: download",
        subtype="DIR_PATH",
    )

    def draw(self, context):
        layout = self.layout
        self.draw_install(layout.box(), context.window_manager.genre_status)
        layout.prop(self, "backend_command")
        layout.prop(self, "model")
        if self.model == "custom":
            layout.prop(self, "weights")
        row = layout.row()
        row.prop(self, "device")
        row = layout.row()
        row.prop(self, "startup_timeout")
        row.prop(self, "job_timeout")
        status = context.window_manager.genre_status
        row = layout.row()
        row.enabled = not status.checking
        row.operator("genre.check_backend", icon="PLUGIN")
        if status.checking:
            layout.label(text="Checking the backend…", icon="TIME")
        elif status.backend_info:
            layout.label(text=status.backend_info, icon="CHECKMARK" if status.backend_ok else "ERROR")


    def draw_install(self, box, status):
        """Install Backend: the buttons, the Python and the wheel folder, the progress and the outcome."""
        box.label(text="Backend: PyTorch (CPU) and GenRe in a private environment, about 1.2 GB", icon="PACKAGE")
        if status.installing:
            draw_progress(box, status.install_progress, status.install_stage or "Installing")
            if status.install_line:
                box.label(text=status.install_line[:100], icon="BLANK1")
            row = box.row()
            row.operator("genre.cancel_install", icon="CANCEL")
            row.operator("genre.show_install_log", icon="TEXT")
            return
        env = backend_env()
        row = box.row()
        row.operator("genre.install_backend", icon="IMPORT",
                     text="Reinstall Backend" if installer.installed(env) else "Install Backend")
        sub = row.row()
        sub.enabled = os.path.lexists(env)
        sub.operator("genre.remove_backend", icon="TRASH")
        box.prop(self, "backend_python")
        box.prop(self, "wheel_folder")
        if status.install_message:
            row = box.row()
            row.label(text=status.install_message, icon="CHECKMARK" if status.install_ok else "ERROR")
            if os.path.isfile(os.path.join(addon_user_folder(), installer.LOG_NAME)):
                row.operator("genre.show_install_log", icon="TEXT")
        elif installer.installed(env):
            box.label(text=f"Installed in {env}", icon="CHECKMARK")


def get_preferences(context=None):
    """The add-on's preferences, or None when the add-on is registered without being enabled (tests from source)."""
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON_PACKAGE)
    return addon.preferences if addon is not None else None


CLASSES = (GENRE_PG_option, GENRE_PG_settings, GENRE_PG_status, GENRE_AP_preferences)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.genre = PointerProperty(type=GENRE_PG_settings)
    bpy.types.WindowManager.genre_status = PointerProperty(type=GENRE_PG_status)


def unregister():
    del bpy.types.WindowManager.genre_status
    del bpy.types.Scene.genre
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
