"""The add-on's properties: per-scene settings, the window manager's run status, and the preferences."""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from .backend import MODELS

# The add-on's module name: "genre" as a legacy add-on, "bl_ext.<repo>.genre" as an extension.
ADDON_PACKAGE = __package__


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
        description="Guide the mask with what is drawn over the photo in an Image Editor with the Annotate tool: "
                    "strokes on the object; strokes on a layer named 'Background' mark background; strokes on a layer "
                    "named 'Box' give a box around the object. A mask file, when chosen, is used instead",
        default=True,
    )
    use_threshold: BoolProperty(name="Custom Threshold", description="Override the weights' isosurface threshold", default=False)
    threshold: FloatProperty(
        name="Threshold", description="Isosurface threshold of the voxel grid: lower gives a fuller shape",
        # The shipped 'default' weights' level (tests/test_layout.py holds the two together); the field
        # follows the level the backend reports for whatever weights it runs.
        default=0.45, min=0.01, max=0.99, step=1, precision=2,
    )
    use_hole_closing: BoolProperty(name="Custom Hole Sealing", description="Override the weights' hole sealing", default=False)
    hole_closing: IntProperty(
        name="Seal Holes", description="Seal holes in the mesh up to about twice this many voxels across "
                                       "(0: none; more also fills narrow gaps between parts)",
        # The shipped 'default' weights' setting; the field follows what the backend reports.
        default=1, min=0, max=8,
    )
    use_pit_sealing: BoolProperty(name="Custom Pit Sealing", description="Override the weights' pit sealing", default=False)
    pit_sealing: IntProperty(
        name="Seal Pits", description="Fill narrow, deep pits in the side the photo shows, up to about twice this many "
                                      "voxels across, with the surface around them (0: none)",
        # The shipped 'default' weights' setting; the field follows what the backend reports.
        default=4, min=0, max=8,
    )
    use_silhouette_carve: BoolProperty(name="Custom Outline Trim", description="Override the weights' outline trim", default=False)
    silhouette_carve: BoolProperty(
        name="Trim to Outline", description="Cut away whatever would stick out past the object's outline in the photo "
                                            "(the mask), so the mesh matches the photo from its viewpoint",
        # The shipped 'default' weights' setting; the field follows what the backend reports.
        default=False,
    )
    use_test_time_mirror: BoolProperty(name="Custom Mirror Average", description="Override the weights' mirror averaging", default=False)
    test_time_mirror: BoolProperty(
        name="Mirror Average", description="Also reconstruct the photo's mirror image and average the two meshes' "
                                           "voxels (the networks' errors that are not mirror-symmetric partly cancel); "
                                           "about twice the networks' time",
        # The shipped 'default' weights' setting; the field follows what the backend reports.
        default=True,
    )
    smoothing: IntProperty(
        name="Smoothing", description="Smoothing iterations (a Smooth modifier; 0 for none)", default=2, min=0, max=50,
    )
    target_faces: IntProperty(
        name="Target Faces", description="Decimate to about this many faces (a Decimate modifier; 0 keeps every face)",
        default=0, min=0, soft_max=200000,
    )
    colour_from_photo: BoolProperty(
        name="Colour from Photo",
        description="Colour the mesh with the photo: UVs into the photo and a material with it as base colour "
                    "(sides the photo does not show take the colour of the nearest surface it shows)",
        default=True,
    )
    use_primitive_snap: BoolProperty(name="Custom Shape Snapping", description="Override the weights' regular-shape snapping", default=False)
    primitive_snap: FloatProperty(
        name="Snap Shapes", description="When the photo shows a plain box, cylinder, cone, torus or ellipsoid, give that "
                                        "exact shape instead of the network's rounded mesh if its outline matches the "
                                        "object's and it stays on the mesh within this tolerance (0: never)",
        # The shipped 'default' weights' setting; the field follows what the backend reports.
        default=0.0, min=0.0, max=0.5, step=1, precision=2,
    )
    keep_all_parts: BoolProperty(
        name="Keep All Parts",
        description="Keep every separate piece of the mesh (off: pieces smaller than 5% of the largest are dropped)",
        default=False,
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

    def draw(self, context):
        layout = self.layout
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


def get_preferences(context=None):
    """The add-on's preferences, or None when the add-on is registered without being enabled (tests from source)."""
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON_PACKAGE)
    return addon.preferences if addon is not None else None


CLASSES = (GENRE_PG_settings, GENRE_PG_status, GENRE_AP_preferences)


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
