"""The "GenRe" tab of the 3D viewport's sidebar."""

import bpy

from . import ops


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
            row = col.row(align=True)
            row.prop(settings, "photo_path", text="")
            row.operator("genre.choose_file", text="", icon="FILE_IMAGE").target = "PHOTO"
        else:
            col.template_ID(settings, "image", open="image.open")
        col.label(text="Mask (optional):")
        row = col.row(align=True)
        row.prop(settings, "mask_path", text="")
        row.operator("genre.choose_file", text="", icon="FILE_IMAGE").target = "MASK"
        col.prop(settings, "use_annotation")

        box = col.box()
        row = box.row(align=True)
        row.prop(settings, "use_threshold", text="")
        sub = row.row()
        sub.enabled = settings.use_threshold
        sub.prop(settings, "threshold")
        row = box.row(align=True)
        row.prop(settings, "use_hole_closing", text="")
        sub = row.row()
        sub.enabled = settings.use_hole_closing
        sub.prop(settings, "hole_closing")
        row = box.row(align=True)
        row.prop(settings, "use_pit_sealing", text="")
        sub = row.row()
        sub.enabled = settings.use_pit_sealing
        sub.prop(settings, "pit_sealing")
        row = box.row(align=True)
        row.prop(settings, "use_silhouette_carve", text="")
        sub = row.row()
        sub.enabled = settings.use_silhouette_carve
        sub.prop(settings, "silhouette_carve")
        row = box.row(align=True)
        row.prop(settings, "use_test_time_mirror", text="")
        sub = row.row()
        sub.enabled = settings.use_test_time_mirror
        sub.prop(settings, "test_time_mirror")
        box.prop(settings, "smoothing")
        box.prop(settings, "target_faces")
        box.prop(settings, "colour_from_photo")
        row = box.row(align=True)
        row.prop(settings, "use_primitive_snap", text="")
        sub = row.row()
        sub.enabled = settings.use_primitive_snap
        sub.prop(settings, "primitive_snap")
        box.prop(settings, "keep_all_parts")
        box.prop(settings, "add_camera")

        if running:
            label = status.stage or "Working"
            if hasattr(layout, "progress"):  # Blender 4.0+
                layout.progress(factor=status.progress, type="BAR", text=f"{label} ({status.progress:.0%})")
            else:
                row = layout.row()
                row.enabled = False  # a display, not a control
                row.prop(status, "progress", text=label, slider=True)
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
                for i, part in enumerate(_wrap(status.message, 38)):
                    col.label(text=part, icon=("ERROR" if status.message_is_error else "CHECKMARK") if i == 0 else "BLANK1")
            else:
                counts, _, seconds = rest.rpartition(" in ")
                col.label(text=f"{head} ({seconds})" if counts else head, icon="CHECKMARK")
                counts, _, mask = (counts or rest).partition(", mask: ")
                col.label(text=counts.replace(" vertices,", " verts,"), icon="BLANK1")
                if mask:
                    col.label(text=f"mask: {mask}", icon="BLANK1")
            if status.mask_warning and not status.message_is_error:
                # the backend doubts the mask (probably the photo's frame): say so, with the way out
                col = layout.column(align=True)
                for i, part in enumerate(_wrap(f"Doubtful mask: {status.mask_warning}. Choose a mask file (white object on black), or annotate the photo in an Image Editor (object strokes; a Background layer; a Box layer), and reconstruct again.", 38)):
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


CLASSES = (GENRE_PT_panel,)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
