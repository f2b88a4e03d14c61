"""The "GenRe" tab of the 3D viewport's sidebar: the main panel an artist needs, and the research knobs under Advanced."""

import json
import os

import bpy

from . import jobs, ops, schema
from .props import draw_progress


# the one-line hint under "Use Annotation": how to fix a wrong automatic mask (the property's tooltip says it at length)
ANNOTATION_HINT = "Wrong mask? Draw a box or strokes (layers Box, Background)"
# the characters of one line of text the sidebar shows uncut at its default width (longer lines are wrapped)
LINE_CHARS = 24


# the size of the mask's picture in the panel, in icon units (20 px each at the interface's scale 1)
MASK_PREVIEW_SCALE = 9.0


class GENRE_PT_panel(bpy.types.Panel):
    bl_label = "GenRe: Photo to Mesh"
    bl_idname = "GENRE_PT_panel"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "GenRe"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.genre
        status = context.window_manager.genre_status
        running = ops.active.job is not None and not ops.active.job.finished

        col = layout.column()
        col.enabled = not running
        col.row().prop(settings, "source", expand=True)
        if settings.source == "FILE":
            # the button shows the file's name (a path field cuts long paths off); its tooltip the whole path
            name = os.path.basename(settings.photo_path) if settings.photo_path else "Choose Photo…"
            col.operator("genre.choose_file", text=name, icon="FILE_IMAGE").target = "PHOTO"
        else:
            col.template_ID(settings, "image", open="image.open")
        row = col.row(align=True)
        row.operator("genre.choose_file", text=os.path.basename(settings.mask_path) if settings.mask_path else "Mask (optional)…",
                     icon="MOD_MASK").target = "MASK"
        if settings.mask_path:
            row.operator("genre.clear_mask", text="", icon="X")
        col.prop(settings, "use_annotation")
        for i, part in enumerate(_wrap(ANNOTATION_HINT, LINE_CHARS)):  # the checkbox's tooltip in short, seen without hovering
            col.label(text=part, icon="INFO" if i == 0 else "BLANK1")
        col.separator()
        col.row().prop(settings, "quality", expand=True)
        col.prop(settings, "colour_from_photo")
        col.prop(settings, "add_camera")

        if running:
            label = status.stage or "Working"
            draw_progress(layout, status.progress, label)
            layout.operator("genre.cancel", icon="CANCEL")
        else:
            row = layout.row()
            row.scale_y = 1.5
            row.operator("genre.reconstruct", icon="MESH_MONKEY")
        if status.message and not running:
            # "name: counts in time" on two lines, so the sidebar does not cut it off
            col = layout.column(align=True)
            head, sep, rest = status.message.partition(": ")
            if status.message_is_error or not sep:
                for i, part in enumerate(_wrap(status.message, LINE_CHARS)):
                    col.label(text=part, icon=("ERROR" if status.message_is_error else "CHECKMARK") if i == 0 else "BLANK1")
            else:
                counts, _, seconds = rest.rpartition(" in ")
                col.label(text=f"{head} ({seconds})" if counts else head, icon="CHECKMARK")
                counts, _, mask = (counts or rest).partition(", mask: ")
                col.label(text=counts.replace(" vertices,", " verts,"), icon="BLANK1")
                if mask:
                    col.label(text=f"mask: {mask}", icon="BLANK1")
            overlay = bpy.data.images.get(jobs.MASK_IMAGE)
            if overlay is not None and not status.message_is_error:
                # the mask the backend used over the photo (background dimmed, outline yellow): a wrong one is seen at once
                col = layout.column(align=True)
                col.label(text="Mask used (yellow outline):", icon="MOD_MASK")
                preview = getattr(overlay, "preview", None)
                if preview is not None:
                    col.template_icon(icon_value=preview.icon_id, scale=MASK_PREVIEW_SCALE)
            if status.mask_warning and not status.message_is_error:
                # the backend doubts the mask (probably the photo's frame): say so, with the way out
                col = layout.column(align=True)
                for i, part in enumerate(_wrap(f"Doubtful mask: {status.mask_warning}. Choose a mask file (white object on black), or annotate the photo in an Image Editor (object strokes; a Background layer; a Box layer), and reconstruct again.", LINE_CHARS)):
                    col.label(text=part, icon="ERROR" if i == 0 else "BLANK1")


def _wrap(text, width):
    """Split a message into lines of at most ``width`` characters at spaces."""
    lines, line = [], ""
    for word in text.split():
        if line and len(line) + 1 + len(word) > width:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}" if line else word
    return lines + [line] if line else lines


class GENRE_PT_advanced(bpy.types.Panel):
    """The mesh options the backend publishes (one row each: tick to override the model's own value) and the add-on's own."""

    bl_label = "Advanced"
    bl_idname = "GENRE_PT_advanced"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "GenRe"
    bl_parent_id = "GENRE_PT_panel"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        settings = context.scene.genre
        layout.enabled = not (ops.active.job is not None and not ops.active.job.finished)
        col = layout.column(align=True)
        if not len(settings.options):  # (the cached schema fills them on load: this shows only if it could not)
            col.label(text="The model's options show here once the backend has started.", icon="INFO")
            col.operator("genre.check_backend", text="Load Options", icon="PLUGIN")
        for row in settings.options:
            draw_option_row(col, row)
        layout.separator()
        layout.prop(settings, "smoothing")
        layout.prop(settings, "target_faces")


VALUE_PROPERTY = {"float": "float_value", "int": "int_value", "bool": "bool_value", "choice": "choice_value"}


def draw_option_row(layout, row) -> None:
    """One option: its label on the one checkbox (ticked: override), the value (editable when ticked), the model's own value."""
    try:
        weights = json.loads(row.weights_value)
    except ValueError:
        weights = None
    entry = {"type": row.kind}
    line = layout.row(align=True)
    split = line.split(factor=0.55, align=True)
    split.prop(row, "override", text=row.label)
    right = split.row(align=True)
    own = schema.shown(entry, weights)
    if row.override:
        if row.kind == "bool":
            right.prop(row, "bool_value", text="On" if row.bool_value else "Off", toggle=True)
        else:
            right.prop(row, VALUE_PROPERTY.get(row.kind, "choice_value"), text="")
        right.label(text=f"model: {own}")
    else:
        right.label(text=f"{own} (model)")
    line.operator("genre.option_help", text="", icon="QUESTION", emboss=False).option = row.name


CLASSES = (GENRE_PT_panel, GENRE_PT_advanced)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
