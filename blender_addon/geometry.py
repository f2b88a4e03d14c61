"""Plain geometry for the add-on, without ``bpy``: reading the backend's mesh, standing it up, matching its camera.

The backend writes meshes in its *view frame* (``genre_backend/frame.py``):
+x right in the photo, +y up, +z toward the camera, the camera at
``(0, 0, distance)``.  Blender is Z-up, so the add-on turns the mesh with
:data:`VIEW_TO_BLENDER_FRONT` (view +y → world +Z, view +z → world −Y); the
camera then sits at ``(0, −distance, 0)`` looking along +Y.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

__all__ = [
    "VIEW_TO_BLENDER_FRONT",
    "MeshData",
    "MeshFileError",
    "read_obj",
    "to_blender_frame",
    "CameraSetup",
    "camera_setup",
]

# A copy of genre_backend.frame.VIEW_TO_BLENDER_FRONT (the add-on cannot import
# the backend: it runs in Blender's Python, the backend in its own).  Rows are
# world X, Y, Z; columns are the view frame's x, y, z axes in world
# coordinates.  tests/addon/test_addon.py asserts that both stay equal.
VIEW_TO_BLENDER_FRONT = (
    (1.0, 0.0, 0.0),
    (0.0, 0.0, -1.0),
    (0.0, 1.0, 0.0),
)


class MeshFileError(ValueError):
    """The backend's mesh file cannot be read (one-line reason)."""


@dataclass
class MeshData:
    """An OBJ's polygons: ``faces`` index ``vertices``; ``face_uvs`` (one tuple per face, or None when the
    file has no texture coordinates) index ``uvs``."""

    vertices: list[tuple[float, float, float]]
    faces: list[tuple[int, ...]]
    uvs: list[tuple[float, float]] = field(default_factory=list)
    face_uvs: list[tuple[int, ...]] | None = None


def _index(token: str, count: int, path, lineno: int) -> int:
    """A 1-based (or negative, from the end) OBJ index → 0-based; a clear error for anything else."""
    try:
        i = int(token)
    except ValueError:
        raise MeshFileError(f"{path}:{lineno}: bad face line") from None
    return i - 1 if i > 0 else count + i


def read_obj(path: str | os.PathLike) -> MeshData:
    """Vertices, faces and texture coordinates of a Wavefront OBJ (``v``, ``vt`` and ``f`` lines; negative indices allowed).

    Everything else (normals, groups, materials) is ignored: the backend writes
    one object.  ``face_uvs`` is set only when every face has ``v/vt`` indices.
    """
    vertices: list[tuple[float, float, float]] = []
    uvs: list[tuple[float, float]] = []
    faces: list[tuple[int, ...]] = []
    face_uvs: list[tuple[int, ...]] = []
    try:
        fh = open(path, encoding="utf-8", errors="replace")
    except OSError as exc:
        raise MeshFileError(f"cannot read the mesh {path}: {exc.strerror or exc}") from None
    with fh:
        for lineno, line in enumerate(fh, 1):
            if line.startswith("v "):
                parts = line.split()
                try:
                    vertices.append((float(parts[1]), float(parts[2]), float(parts[3])))
                except (IndexError, ValueError):
                    raise MeshFileError(f"{path}:{lineno}: bad vertex line") from None
            elif line.startswith("vt "):
                parts = line.split()
                try:
                    uvs.append((float(parts[1]), float(parts[2]) if len(parts) > 2 else 0.0))
                except (IndexError, ValueError):
                    raise MeshFileError(f"{path}:{lineno}: bad texture coordinate line") from None
            elif line.startswith("f "):
                idx, tidx = [], []
                for token in line.split()[1:]:
                    fields = token.split("/")
                    idx.append(_index(fields[0], len(vertices), path, lineno))
                    if len(fields) > 1 and fields[1]:
                        tidx.append(_index(fields[1], len(uvs), path, lineno))
                if len(idx) < 3:
                    raise MeshFileError(f"{path}:{lineno}: a face needs at least 3 vertices")
                faces.append(tuple(idx))
                face_uvs.append(tuple(tidx))
    n = len(vertices)
    for face in faces:
        for i in face:
            if not 0 <= i < n:
                raise MeshFileError(f"{path}: a face refers to vertex {i + 1}, but there are {n} vertices")
    if not vertices or not faces:
        raise MeshFileError(f"{path}: the mesh is empty ({n} vertices, {len(faces)} faces)")
    textured = bool(uvs) and all(len(t) == len(f) for t, f in zip(face_uvs, faces))
    if textured and any(not 0 <= i < len(uvs) for t in face_uvs for i in t):
        raise MeshFileError(f"{path}: a face refers to a texture coordinate past the {len(uvs)} in the file")
    return MeshData(vertices, faces, uvs if textured else [], face_uvs if textured else None)


def to_blender_frame(vertices, rotation=VIEW_TO_BLENDER_FRONT) -> list[tuple[float, float, float]]:
    """View-frame points → Blender's Z-up frame (``rotation @ p`` for each point)."""
    (a, b, c), (d, e, f), (g, h, i) = rotation
    return [(a * x + b * y + c * z, d * x + e * y + f * z, g * x + h * y + i * z) for x, y, z in vertices]


@dataclass
class CameraSetup:
    """A Blender camera that sees the photo as the backend's camera saw the mesh.

    ``location`` is in the mesh's (Blender, Z-up) frame; the camera's rotation
    is :data:`VIEW_TO_BLENDER_FRONT`.  ``sensor_mm`` spans the photo's longer
    side (``sensor_fit`` AUTO); ``shift_x``/``shift_y`` move the optical axis
    to the centre of the backend's square crop; ``resolution`` is the photo's
    size in pixels, so the camera frame has the photo's aspect ratio.
    """

    lens_mm: float
    sensor_mm: float
    shift_x: float
    shift_y: float
    location: tuple[float, float, float]
    resolution: tuple[int, int]


def upright_pixels(pixels, width: int, height: int, channels: int, orientation: int):
    """A photo's pixels as stored in its file → as its EXIF ``orientation`` says to show them.

    ``pixels``: the flat (height × width × channels) floats in Blender's
    order (the bottom row first, as ``Image.pixels`` holds them).
    ``orientation``: the EXIF tag, 1-8 (TIFF's meaning; the result's
    ``camera.exif_orientation``).  Returns ``(pixels', width', height')``:
    an ``array('f')``, bottom row first, that Pillow's
    ``ImageOps.exif_transpose`` would give (Blender's image loader ignores
    the tag, the backend applies it).  Plain Python (Debian's Blender has no
    numpy): whole rows and columns move as (extended) slices.
    """
    from array import array

    if isinstance(orientation, bool) or orientation not in range(1, 9):
        raise ValueError(f"orientation: expected an EXIF orientation 1-8, got {orientation!r}")
    w, h, c = int(width), int(height), int(channels)
    flat = pixels if isinstance(pixels, array) and pixels.typecode == "f" else array("f", pixels)
    if w < 1 or h < 1 or c < 1 or len(flat) != w * h * c:
        raise ValueError(f"pixels: expected width × height × channels = {w}×{h}×{c} values, got {len(flat)}")
    stride = w * c

    def row(i):  # the stored row i, counted from the top
        return flat[(h - 1 - i) * stride:(h - i) * stride]

    def mirrored(r):  # a row's pixels right to left (channels kept in order)
        out = array("f", r)
        for k in range(c):
            out[k::c] = r[k::c][::-1]
        return out

    def column(j, bottom_first):  # the stored column j as a row of pixels
        out = array("f", bytes(4 * h * c))
        for k in range(c):
            values = flat[j * c + k::stride]  # bottom first, as Blender stores them
            out[k::c] = values if bottom_first else values[::-1]
        return out

    rows = {  # the shown image's rows, top first
        1: lambda: [row(i) for i in range(h)],
        2: lambda: [mirrored(row(i)) for i in range(h)],  # mirrored left to right
        3: lambda: [mirrored(row(h - 1 - i)) for i in range(h)],  # turned 180°
        4: lambda: [row(h - 1 - i) for i in range(h)],  # mirrored top to bottom
        5: lambda: [column(i, False) for i in range(w)],  # mirrored across the main diagonal
        6: lambda: [column(i, True) for i in range(w)],  # stored turned 90° anticlockwise: turn it clockwise
        7: lambda: [column(w - 1 - i, True) for i in range(w)],  # mirrored across the other diagonal
        8: lambda: [column(w - 1 - i, False) for i in range(w)],  # stored turned 90° clockwise: turn it anticlockwise
    }[orientation]()
    out = array("f")
    for r in reversed(rows):  # back to Blender's order: the bottom row first
        out.extend(r)
    return (out, w, h) if orientation <= 4 else (out, h, w)


def camera_setup(camera: dict, photo_size: tuple[int, int], crop_box=None) -> CameraSetup:
    """The camera that lines the mesh up with the whole photo.

    ``camera``: the result event's ``camera`` (``lens_mm``, ``sensor_mm``,
    ``distance``; ``crop_box`` and ``image_size`` are used when present).
    ``photo_size``: (width, height) of the photo in pixels.  ``crop_box``:
    (x0, y0, x1, y1), the square of the photo the backend reconstructed, in
    the photo's pixels (rows grow downward); by default the one in ``camera``,
    else the centred square on the photo's longer side (the whole photo,
    padded).  The backend's camera sees exactly that square on its square
    sensor; the Blender camera keeps the lens, widens the sensor to the whole
    photo and shifts the frame so the square lands where it is in the photo.
    """
    try:
        lens = float(camera["lens_mm"])
        sensor = float(camera["sensor_mm"])
        distance = float(camera["distance"])
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"the result's camera is incomplete: {camera!r}") from None
    if not (lens > 0 and sensor > 0 and distance > 0):
        raise ValueError(f"the result's camera has non-positive values: {camera!r}")
    w, h = int(photo_size[0]), int(photo_size[1])
    size_in_event = camera.get("image_size")
    if isinstance(size_in_event, (list, tuple)) and len(size_in_event) == 2 and min(size_in_event) > 0:
        w, h = int(size_in_event[0]), int(size_in_event[1])
    if w <= 0 or h <= 0:
        raise ValueError(f"the photo has no pixels ({w}×{h})")
    box = crop_box if crop_box is not None else camera.get("crop_box")
    if box is None:
        side = float(max(w, h))
        box = ((w - side) / 2.0, (h - side) / 2.0, (w + side) / 2.0, (h + side) / 2.0)
    x0, y0, x1, y1 = (float(v) for v in box)
    side = x1 - x0
    if side <= 0 or not math.isclose(side, y1 - y0, rel_tol=1e-3, abs_tol=1e-3):
        raise ValueError(f"the crop box must be a non-empty square, got {box!r}")
    longer = float(max(w, h))
    cx, cy = (x0 + x1) / 2.0, (y0 + y1) / 2.0
    return CameraSetup(
        lens_mm=lens,
        sensor_mm=sensor * longer / side,
        shift_x=(w / 2.0 - cx) / longer,
        shift_y=(cy - h / 2.0) / longer,
        location=to_blender_frame([(0.0, 0.0, distance)])[0],
        resolution=(w, h),
    )
