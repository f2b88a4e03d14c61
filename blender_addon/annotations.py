"""Annotations drawn over the photo in Blender's Image Editor → the backend's strokes image and box.

The artist shows the photo in an Image Editor and draws on it with the
Annotate tool; the next Reconstruct sends what was drawn (``docs/masks.md``):

* strokes on a layer named **Background** (any name that starts with "back"
  or "bg", in any case) mark background: the backend's mask keeps them
  out of the mask;
* strokes on a layer named **Box** give a box: the bounding box of all its
  points (a rectangle or any loop around the object);
* strokes on every other layer (Blender's first layer is "Note") mark the
  object.

Hidden layers are skipped; each layer's active frame is read (the first
frame when none is active).  In Blender 4.3+ (and 5.x) the Image Editor
keeps its annotation on the space (``SpaceImageEditor.annotation``, an
``Annotation`` datablock: layers → frames → strokes → points); a point's
``co`` is in the editor's view space, where the image spans 0–1 on both
axes, y up (Blender's ``image_main_region_set_view2d`` normalises the
view by the image's size; measured in a drawn Blender 3.4.1 editor,
``tests/addon/test_addon_gui.py``).  Before 4.3 the same data is
``SpaceImageEditor.grease_pencil``.  Strokes are drawn :data:`STROKE_WIDTH_SHARE`
of the photo's long side wide into a grey image the photo's size
(:func:`rasterise`): 255 object, 0 background, 128 elsewhere, the backend's
convention.  Blender shows a photo's pixels as stored in its file, ignoring
its EXIF orientation, so the annotation is over the stored pixels; the
request says so (``guidance_frame`` ``"stored"``, ``jobs.annotation_guidance``)
and the backend turns the strokes image and box as it turns the photo.

The conversion (:func:`layer_lines`, :func:`rasterise`, :func:`write_png_gray`)
needs no running editor; :func:`find_annotation` looks for the editor.
"""

from __future__ import annotations

import math
import os
import struct
import zlib

__all__ = [
    "STROKE_WIDTH_SHARE",
    "OBJECT",
    "BACKGROUND",
    "BOX",
    "layer_kind",
    "find_annotation",
    "layer_lines",
    "rasterise",
    "line_box",
    "write_png_gray",
    "guidance_from_annotation",
]

# strokes are drawn this share of the photo's long side wide (at least 3 pixels)
STROKE_WIDTH_SHARE = 0.012
OBJECT, BACKGROUND, BOX = "object", "background", "box"
UNKNOWN_GREY, OBJECT_GREY, BACKGROUND_GREY = 128, 255, 0


def layer_kind(name: str) -> str:
    """What an annotation layer's strokes mean, by its name: :data:`BACKGROUND`, :data:`BOX` or :data:`OBJECT`."""
    low = name.strip().lower()
    if low.startswith(("back", "bg")):
        return BACKGROUND
    if low == "box":
        return BOX
    return OBJECT


def find_annotation(image, window_manager):
    """The annotation of an Image Editor that shows ``image`` (an Image datablock) in any window, else None.

    An editor whose annotation has strokes is preferred to one without.
    """
    found = None
    for window in window_manager.windows:
        screen = window.screen
        if screen is None:
            continue
        for area in screen.areas:
            if area.type != "IMAGE_EDITOR":
                continue
            space = area.spaces.active
            annotation = getattr(space, "annotation", None) or getattr(space, "grease_pencil", None)  # (Blender < 4.3)
            if getattr(space, "image", None) != image or annotation is None:
                continue
            if any(layer_lines(annotation, 1, 1).values()):
                return annotation
            found = found or annotation
    return found


def layer_lines(annotation, width: int, height: int) -> dict[str, list[list[tuple[float, float]]]]:
    """The annotation's strokes in the photo's pixels: kind → list of polylines, each a list of (x, y) (x right, y down).

    ``width`` and ``height``: the photo's pixels (the editor's 0–1 view
    space is scaled by them, y turned downward).  Points that are not
    finite are dropped.
    """
    out: dict[str, list[list[tuple[float, float]]]] = {OBJECT: [], BACKGROUND: [], BOX: []}
    for layer in annotation.layers:
        if getattr(layer, "annotation_hide", getattr(layer, "hide", False)):
            continue
        frame = layer.active_frame
        if frame is None and len(layer.frames):
            frame = layer.frames[0]
        if frame is None:
            continue
        for stroke in frame.strokes:
            line = [(float(p.co[0]) * width, (1.0 - float(p.co[1])) * height) for p in stroke.points]
            line = [(x, y) for x, y in line if math.isfinite(x) and math.isfinite(y)]
            if line:
                out[layer_kind(layer.info)].append(line)
    return out


def rasterise(lines: dict[str, list[list[tuple[float, float]]]], width: int, height: int,
              stroke_width: float | None = None) -> bytearray:
    """Object and background polylines (:func:`layer_lines`) → the strokes image: (height × width) grey bytes, rows top down.

    255 under object strokes, 0 under background strokes (drawn last: they
    win where both cross), 128 elsewhere.  Each polyline is drawn as discs
    of diameter ``stroke_width`` pixels (default :data:`STROKE_WIDTH_SHARE`
    of the long side, at least 3) every quarter of that width (at most half
    a pixel apart) along it; a pixel is covered when its centre is inside a
    disc; a single point is one disc.  Box lines are not drawn.  Plain
    Python (Blender builds without numpy exist, Debian's among them).
    """
    if stroke_width is None:
        stroke_width = max(3.0, STROKE_WIDTH_SHARE * max(width, height))
    r = stroke_width / 2.0
    step = max(0.5, r / 2.0)
    image = bytearray([UNKNOWN_GREY]) * (width * height)
    for kind, value in ((OBJECT, OBJECT_GREY), (BACKGROUND, BACKGROUND_GREY)):
        for line in lines.get(kind, []):
            points = [line[0]]
            for (ax, ay), (bx, by) in zip(line[:-1], line[1:]):
                n = max(1, math.ceil(math.hypot(bx - ax, by - ay) / step))
                points.extend((ax + (bx - ax) * i / n, ay + (by - ay) * i / n) for i in range(1, n + 1))
            for x, y in points:
                for row in range(max(0, math.floor(y - r)), min(height, math.ceil(y + r) + 1)):
                    dy = row + 0.5 - y
                    if dy * dy > r * r:
                        continue
                    half = math.sqrt(r * r - dy * dy)
                    c0, c1 = max(0, math.ceil(x - half - 0.5)), min(width, math.floor(x + half - 0.5) + 1)  # centres in reach
                    if c0 < c1:
                        image[row * width + c0: row * width + c1] = bytes([value]) * (c1 - c0)
    return image


def line_box(lines: list[list[tuple[float, float]]], width: int, height: int) -> tuple[float, float, float, float] | None:
    """The bounding box (x0, y0, x1, y1) of polylines in pixels, clipped to the photo; None without points or area."""
    points = [p for line in lines for p in line]
    if not points:
        return None
    x0, y0 = max(0.0, min(p[0] for p in points)), max(0.0, min(p[1] for p in points))
    x1, y1 = min(float(width), max(p[0] for p in points)), min(float(height), max(p[1] for p in points))
    if x1 - x0 < 1.0 or y1 - y0 < 1.0:
        return None
    return round(x0, 2), round(y0, 2), round(x1, 2), round(y1, 2)


def write_png_gray(path: str, image: bytes | bytearray, width: int, height: int) -> None:
    """Write (height × width) grey bytes, rows top down, as an 8-bit grayscale PNG (no filter, zlib level 6)."""
    if len(image) != width * height:
        raise ValueError(f"write_png_gray: {len(image)} bytes for {width}×{height} pixels")

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    rows = b"".join(b"\x00" + bytes(image[y * width:(y + 1) * width]) for y in range(height))
    data = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)) \
        + chunk(b"IDAT", zlib.compress(rows, 6)) + chunk(b"IEND", b"")
    tmp = f"{path}.tmp"
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def guidance_from_annotation(annotation, width: int, height: int, folder: str
                             ) -> tuple[str, tuple[float, float, float, float] | None]:
    """(strokes file written in ``folder``, or ''; box, or None) from an annotation over a ``width``×``height`` photo."""
    lines = layer_lines(annotation, width, height)
    strokes = ""
    if lines[OBJECT] or lines[BACKGROUND]:
        strokes = os.path.join(folder, "strokes.png")
        write_png_gray(strokes, rasterise(lines, width, height), width, height)
    return strokes, line_box(lines[BOX], width, height)
