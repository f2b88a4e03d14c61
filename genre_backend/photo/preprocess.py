"""Photo → network input: decoding, mask selection and the canonical framing.

Training views are rendered in the canonical framing of :mod:`genre_backend.frame`
(object centred at the origin, bounding-box diagonal 1, camera 2.2 units away),
so the object sits in the middle of the image.  A photo is brought to that
framing here, and only here:

1. **Decode** (:func:`load_image`): any format Pillow reads, EXIF orientation
   applied, the first frame of animations, 16-bit / grayscale / palette /
   CMYK / bilevel converted to 8-bit RGB(A).  Images above
   :data:`MAX_PIXELS` are refused before any pixel is decoded (JPEGs are
   first reduced by the decoder's DCT scaling when that brings them under the
   limit), and larger ones are downscaled to at most :data:`WORK_SIDE` pixels
   on their long side, which is far more than the network input needs.
2. **Mask** (:func:`preprocess`), in this order: a mask file given by the user
   (same size as the image, not empty), else a box and/or strokes given by the
   user (:func:`photo_box`, :func:`load_strokes`: the salient net's mask
   guided by them, :func:`.segment.segment`), else the image's alpha channel when it
   has real transparency, else a mask found in the photo by a pretrained
   salient-object net (:mod:`.salient`, :mod:`.segment`; GrabCut seeded by
   the photo's border when the net cannot be loaded, with a warning),
   else the depth net's own silhouette (two passes: the whole image padded
   to a square, then the crop around that silhouette).  A final mask that
   covers most of the photo or touches most of its border is reported as
   doubtful (:func:`.segment.doubt`, done by the caller).
3. **Framing** (:func:`square_crop_box`, :func:`crop_resize`): a square
   centred on the mask's bounding box whose side makes the box's longest side
   span ``GeometryConfig.object_fraction`` of the image; parts outside the
   photo are filled with the photo's border colour (or, for images with
   transparency, the neutral background), then resized to ``image_size``.
   RGBA images are composited over :data:`NEUTRAL_BACKGROUND`.

Every failure raises :class:`ImageError` whose ``code`` is one of the
``genre serve`` protocol's error codes (``bad_image``, ``bad_mask``,
``no_object``) and whose message is one line naming the file and the problem.
"""

from __future__ import annotations

import os
import re
import stat
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..config import GenreConfig, GeometryConfig
from .segment import DEFAULT_SEEDING, SEEDINGS, STROKE_BACKGROUND_MAX, STROKE_OBJECT_MIN, doubt, segment

__all__ = [
    "ImageError",
    "LoadedImage",
    "Preprocessed",
    "MAX_PIXELS",
    "WORK_SIDE",
    "NEUTRAL_BACKGROUND",
    "MIN_OBJECT_PIXELS",
    "load_image",
    "load_mask",
    "load_strokes",
    "photo_box",
    "GUIDANCE_FRAMES",
    "stored_size",
    "upright_array",
    "upright_box",
    "mask_bbox",
    "square_crop_box",
    "crop_resize",
    "composite",
    "uncrop",
    "preprocess",
]

# Images with more pixels than this are refused (8-bit RGBA at the limit: 256 MB).
MAX_PIXELS = 64_000_000
# Decoded images are downscaled to at most this many pixels on their long side.
WORK_SIDE = 4096
# RGB (in [0, 1]) that transparent pixels are composited over.
NEUTRAL_BACKGROUND = (0.5, 0.5, 0.5)
# A mask (file, alpha or silhouette) with fewer object pixels than this is "empty".
MIN_OBJECT_PIXELS = 4
# Alpha values (0–255) at or above this count as object.
ALPHA_OBJECT_MIN = 128
# The frames a person's box and strokes may be given in: "upright", the photo as shown with its EXIF orientation
# applied (as every other pixel coordinate here), or "stored", the file's pixels as stored, the tag ignored (what
# a viewer that ignores the tag shows: Blender's Image Editor).  (docs/protocol.md, ``guidance_frame``.)
GUIDANCE_FRAMES = ("upright", "stored")


class ImageError(ValueError):
    """An image or mask that cannot be used; ``code`` is a protocol error code.

    ``code``: ``"bad_image"`` (unreadable, empty, corrupt, truncated,
    unsupported or too large), ``"bad_mask"`` (unreadable, empty or of the
    wrong size) or ``"no_object"`` (nothing found to reconstruct).
    """

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


@dataclass
class LoadedImage:
    """A decoded image.

    ``rgb``: (H, W, 3) uint8.  ``alpha``: (H, W) uint8 or None (no alpha
    channel).  ``original_size``: (width, height) as stored in the file
    (after EXIF rotation); ``scale``: ``rgb``'s size / the original size
    (< 1 when the image was downscaled).  ``notes``: what was converted.
    ``exif_orientation``: the file's EXIF orientation tag (1-8, as TIFF
    defines it; 1 when absent or out of range), already applied to ``rgb``:
    a viewer that ignores the tag (Blender's image loader) shows the
    pixels as stored, turned or mirrored from ``rgb``.
    """

    path: Path
    rgb: np.ndarray
    alpha: np.ndarray | None
    original_size: tuple[int, int]
    scale: float
    notes: list[str]
    exif_orientation: int = 1

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the decoded arrays."""
        return self.rgb.shape[1], self.rgb.shape[0]

    def has_transparency(self) -> bool:
        """True when the alpha channel exists and some pixels are transparent."""
        return self.alpha is not None and int(self.alpha.min()) < ALPHA_OBJECT_MIN


@dataclass
class Preprocessed:
    """The network input of one photo.

    ``rgb``: (3, S, S) float32 in [0, 1].  ``mask``: (S, S) bool, or None when
    the depth net's silhouette is to be used (``mask_source`` ``"silhouette"``;
    the silhouette of the final crop then becomes the mask).  ``mask_source``:
    ``"file"``, ``"alpha"``, ``"salient"`` (the salient-object net's), ``"grabcut"`` (GrabCut's, when the net
    cannot be loaded or another seeding is asked for) or ``"silhouette"``.  ``crop_box``: (x0, y0, x1, y1)
    the square crop in the original image's pixel coordinates (may extend past
    the image).  ``image_size``: (width, height) of the original image.
    ``fill``: the RGB (uint8) that parts of the crop outside the photo got.
    ``photo_mask``: (H, W) bool, the mask at the decoded photo's pixels
    (None for ``"silhouette"``: the caller projects the crop's silhouette
    back with :func:`uncrop`).  ``network_doubt``: when the depth net's own
    silhouette of the whole photo was doubtful
    (:func:`.segment.doubt`), why; else None.  ``mask_doubt``: when the
    found mask is doubtful (:func:`.segment.salient_doubt`,
    :func:`.segment.cut_doubt`) or was made without the salient net because
    it could not be loaded, why; else None.
    ``mask_source`` is also ``"box"``, ``"strokes"`` or ``"box+strokes"``
    for a mask found from a person's box and strokes.
    """

    rgb: torch.Tensor
    mask: torch.Tensor | None
    mask_source: str
    crop_box: tuple[float, float, float, float]
    image_size: tuple[int, int]
    notes: list[str]
    fill: tuple[int, int, int]
    photo_mask: np.ndarray | None = None
    network_doubt: str | None = None
    mask_doubt: str | None = None


# ---------------------------------------------------------------------------------- decoding
def _article(word: str) -> str:
    """"an" before a vowel sound ("an image"), else "a" ("a strokes file", "a mask file")."""
    return "an" if word[:1].lower() in "aeio" else "a"


def _check_file(path: Path, what: str, code: str) -> None:
    try:
        st = path.stat()
    except (FileNotFoundError, NotADirectoryError):
        raise ImageError(code, f"{path}: no such file") from None
    except OSError as exc:  # a name too long, a folder on the way that cannot be searched, a link loop
        raise ImageError(code, f"{path}: cannot open: {exc.strerror or exc}") from None
    except ValueError as exc:  # a NUL character, or a lone surrogate no file name can hold
        raise ImageError(code, f"{str(path)!r}: not a usable path ({exc})") from None
    if stat.S_ISDIR(st.st_mode):
        raise ImageError(code, f"{path}: is a directory, not {_article(what)} {what} file")
    if not stat.S_ISREG(st.st_mode):
        raise ImageError(code, f"{path}: not a regular file")
    if st.st_size == 0:
        raise ImageError(code, f"{path}: empty file (0 bytes)")
    if not os.access(path, os.R_OK):
        raise ImageError(code, f"{path}: not readable (permission denied)")


def _to_8bit(im, path: Path, notes: list[str]):
    """Any Pillow mode → an "RGB" or "RGBA" image (16-bit and float scaled to 8 bits)."""
    from PIL import Image

    mode = im.mode
    if mode in ("RGB", "RGBA"):
        return im
    if mode in ("I;16", "I;16B", "I;16L", "I;16N", "I", "F"):
        a = np.asarray(im, dtype=np.float64)
        if not np.isfinite(a).all():
            raise ImageError("bad_image", f"{path}: {mode} image with non-finite values")
        if mode == "F":
            hi = 1.0 if a.max() <= 1.0 else float(a.max())
        else:
            hi = 65535.0 if a.max() <= 65535 else float(a.max())
        notes.append(f"{mode} ({'float' if mode == 'F' else '16-bit'}) grayscale scaled to 8 bits")
        g = np.clip(np.rint(a / hi * 255.0), 0, 255).astype(np.uint8)
        return Image.fromarray(np.repeat(g[:, :, None], 3, axis=2), "RGB")
    has_alpha = mode in ("LA", "La", "PA", "RGBa") or (mode == "P" and "transparency" in im.info)
    notes.append(f"{mode} converted to {'RGBA' if has_alpha else 'RGB'}")
    try:
        return im.convert("RGBA" if has_alpha else "RGB")
    except (ValueError, OSError) as exc:
        raise ImageError("bad_image", f"{path}: unsupported image mode {mode} ({exc})") from None


def load_image(path: str | os.PathLike, *, max_pixels: int = MAX_PIXELS, work_side: int = WORK_SIDE, code: str = "bad_image", what: str = "image") -> LoadedImage:
    """Decode an image file safely; see the module docstring for what is accepted.

    Raises :class:`ImageError` (``code``, default ``"bad_image"``) with a
    one-line message for a missing path, a directory, an empty file, a file
    that is not an image, a truncated or corrupt one, an unsupported mode or
    one above ``max_pixels``.
    """
    from PIL import Image, ImageOps, UnidentifiedImageError

    path = Path(path)
    _check_file(path, what, code)
    notes: list[str] = []
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            im = Image.open(path)  # reads the header only
    except Image.DecompressionBombError as exc:  # Pillow refuses to even open it (its own limit)
        found = re.search(r"\((\d+) pixels\)", str(exc))
        size = f"{int(found.group(1)) / 1e6:.0f} Mpx" if found else f"more than {2 * Image.MAX_IMAGE_PIXELS / 1e6:.0f} Mpx"
        raise ImageError(code, f"{path}: image too large ({size}; limit {max_pixels / 1e6:.0f} Mpx)") from None
    except UnidentifiedImageError:
        raise ImageError(code, f"{path}: not an image (unrecognised file format)") from None
    except (OSError, SyntaxError, ValueError, EOFError) as exc:
        raise ImageError(code, f"{path}: corrupt image header ({exc})") from None
    with im:
        width, height = im.size
        fmt = im.format or "image"
        if width < 1 or height < 1:
            raise ImageError(code, f"{path}: {fmt} image with no pixels ({width}×{height})")
        frames = getattr(im, "n_frames", 1)
        if frames > 1:
            notes.append(f"animated ({frames} frames): using the first")
            im.seek(0)
        if width * height > max_pixels and fmt == "JPEG":
            # DCT scaling in the decoder: 1/2, 1/4 or 1/8 of the size, never the full image in memory
            # the decoder picks the largest reduction whose size stays ≥ the request, i.e. < 2× it
            k = (max_pixels / (width * height)) ** 0.5 / 2.0
            im.draft("RGB", (max(1, int(width * k)), max(1, int(height * k))))
            notes.append(f"JPEG decoded at reduced size {im.size[0]}×{im.size[1]}")
        dw, dh = im.size
        if dw * dh > max_pixels:
            raise ImageError(code, f"{path}: image too large ({width * height / 1e6:.0f} Mpx, {width}×{height}; limit {max_pixels / 1e6:.0f} Mpx)")
        try:
            im.load()
            orientation = im.getexif().get(0x0112, 1)
            orientation = orientation if isinstance(orientation, int) and 1 <= orientation <= 8 else 1
            swapped = orientation in (5, 6, 7, 8)  # EXIF orientations that turn by 90°
            orig = (height, width) if swapped else (width, height)
            im = ImageOps.exif_transpose(im)
            im = _to_8bit(im, path, notes)
        except ImageError:
            raise
        except (OSError, SyntaxError, ValueError, EOFError, IndexError, MemoryError) as exc:
            reason = str(exc).splitlines()[0] if str(exc) else exc.__class__.__name__
            raise ImageError(code, f"{path}: corrupt or truncated {fmt} image ({reason})") from None
        if orientation != 1:
            notes.append(f"EXIF orientation {orientation} applied")
        if max(im.size) > work_side:
            s = work_side / max(im.size)
            new = (max(1, round(im.size[0] * s)), max(1, round(im.size[1] * s)))
            im = im.resize(new, Image.BOX, reducing_gap=2.0)
            notes.append(f"downscaled to {new[0]}×{new[1]}")
        arr = np.asarray(im)
    rgb = np.ascontiguousarray(arr[:, :, :3])
    alpha = np.ascontiguousarray(arr[:, :, 3]) if arr.shape[2] == 4 else None
    return LoadedImage(path, rgb, alpha, (int(orig[0]), int(orig[1])), im.size[0] / orig[0], notes, orientation)


def load_mask(path: str | os.PathLike, image: LoadedImage) -> np.ndarray:
    """A user's mask file → (H, W) bool at the decoded image's resolution.

    Object pixels are bright (luminance ≥ 50%); where the file has
    transparency, transparent pixels are background.  The file must have the
    image's size (after EXIF rotation of both) and mark at least
    :data:`MIN_OBJECT_PIXELS` pixels.  Raises :class:`ImageError` ``bad_mask``.
    """
    from PIL import Image

    m, lum = _same_size_luminance(path, image, "mask", "mask")
    mask = lum >= 127.5
    if m.alpha is not None:
        mask &= m.alpha >= ALPHA_OBJECT_MIN
    if mask.shape != image.rgb.shape[:2]:  # the image was downscaled: bring the mask along
        im = Image.fromarray(mask.astype(np.uint8) * 255, "L").resize(image.size, Image.BOX, reducing_gap=2.0)
        mask = np.asarray(im) >= 128
    if int(mask.sum()) < MIN_OBJECT_PIXELS:
        raise ImageError("bad_mask", f"{m.path}: empty mask (no object pixels: expected white object on black)")
    return mask


def _same_size_luminance(path: str | os.PathLike, image: LoadedImage, what: str, called: str,
                         stored: bool = False) -> tuple[LoadedImage, np.ndarray]:
    """A mask-like file for ``image``: (the loaded file, its (H, W) float32 luminance); ``bad_mask`` unless it has the
    photo's size (``called`` names it in the message).  ``stored``: the file is drawn over the photo's pixels as
    stored (:data:`GUIDANCE_FRAMES`): it must have their size, and is turned by the photo's EXIF orientation."""
    m = load_image(path, code="bad_mask", what=what)
    want = stored_size(image) if stored else image.original_size
    if m.original_size != want:
        ow, oh = m.original_size
        raise ImageError("bad_mask", f"{m.path}: {called} is {ow}×{oh}, the image is {want[0]}×{want[1]}"
                                     f"{' as stored (before its EXIF orientation)' if stored else ''}")
    if stored and image.exif_orientation != 1:
        o = image.exif_orientation
        w, h = m.original_size
        m = LoadedImage(m.path, upright_array(m.rgb, o), None if m.alpha is None else upright_array(m.alpha, o),
                        (h, w) if o in (5, 6, 7, 8) else (w, h), m.scale, m.notes, m.exif_orientation)
    return m, m.rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)


def stored_size(image: LoadedImage) -> tuple[int, int]:
    """(width, height) of ``image``'s pixels as stored in its file, before its EXIF orientation turned them."""
    w, h = image.original_size
    return (h, w) if image.exif_orientation in (5, 6, 7, 8) else (w, h)


def upright_array(a: np.ndarray, orientation: int) -> np.ndarray:
    """An (H, W, …) array of a file's pixels as stored (top row first) → as its EXIF ``orientation`` (1-8) shows them.

    The same turn or mirror as Pillow's ``ImageOps.exif_transpose`` (which :func:`load_image` applies to the photo).
    """
    turn = {
        1: lambda t: t,
        2: lambda t: t[:, ::-1],  # mirrored left to right
        3: lambda t: t[::-1, ::-1],  # turned 180°
        4: lambda t: t[::-1],  # mirrored top to bottom
        5: lambda t: t.swapaxes(0, 1),  # mirrored across the main diagonal
        6: lambda t: np.rot90(t, -1),  # stored turned 90° anticlockwise: turn it clockwise
        7: lambda t: t[::-1, ::-1].swapaxes(0, 1),  # mirrored across the other diagonal
        8: lambda t: np.rot90(t, 1),  # stored turned 90° clockwise: turn it anticlockwise
    }
    if isinstance(orientation, bool) or orientation not in turn:
        raise ValueError(f"orientation: expected an EXIF orientation 1-8, got {orientation!r}")
    return np.ascontiguousarray(turn[orientation](a))


def upright_box(box: tuple[float, float, float, float], orientation: int, size: tuple[int, int]) -> tuple[float, float, float, float]:
    """A box (x0, y0, x1, y1) over a file's pixels as stored → the same pixels once its EXIF ``orientation`` is applied.

    ``size``: (width, height) as stored.  Corners are pixel edges (0 … width), so a box around a pixel
    stays around that pixel (:func:`upright_array`).
    """
    w, h = float(size[0]), float(size[1])
    to = {
        1: lambda x, y: (x, y),
        2: lambda x, y: (w - x, y),
        3: lambda x, y: (w - x, h - y),
        4: lambda x, y: (x, h - y),
        5: lambda x, y: (y, x),
        6: lambda x, y: (h - y, x),
        7: lambda x, y: (h - y, w - x),
        8: lambda x, y: (y, w - x),
    }
    if isinstance(orientation, bool) or orientation not in to:
        raise ValueError(f"orientation: expected an EXIF orientation 1-8, got {orientation!r}")
    x0, y0, x1, y1 = box
    (ax, ay), (bx, by) = to[orientation](x0, y0), to[orientation](x1, y1)
    return min(ax, bx), min(ay, by), max(ax, bx), max(ay, by)


def load_strokes(path: str | os.PathLike, image: LoadedImage, frame: str = "upright") -> tuple[np.ndarray, np.ndarray]:
    """A person's strokes file → ((H, W) bool object, (H, W) bool background) at the decoded image's resolution.

    The file has the image's size (after EXIF rotation of both; with ``frame``
    ``"stored"``, :data:`GUIDANCE_FRAMES`, the size of the photo's pixels as
    stored, and it is turned by the photo's EXIF orientation): grey level
    (luminance) ≥ :data:`.segment.STROKE_OBJECT_MIN` (white) is sure object,
    ≤ :data:`.segment.STROKE_BACKGROUND_MAX` (black) sure background, anything
    between (mid grey, 128) says nothing, and so do transparent pixels (alpha
    < 128), so strokes may be drawn on a transparent layer.  It must mark at
    least one pixel.  Raises :class:`ImageError` ``bad_mask``.
    """
    from PIL import Image

    m, lum = _same_size_luminance(path, image, "strokes", "strokes image", stored=_stored(frame))
    seen = np.ones(lum.shape, bool) if m.alpha is None else m.alpha >= ALPHA_OBJECT_MIN
    marks = []
    for kind in (lum >= STROKE_OBJECT_MIN - 0.5, lum <= STROKE_BACKGROUND_MAX + 0.5):
        kind &= seen
        if kind.shape != image.rgb.shape[:2]:  # the image was downscaled: a pixel is marked when any of it is
            im = Image.fromarray(kind.astype(np.uint8) * 255, "L").resize(image.size, Image.BOX, reducing_gap=2.0)
            kind = np.asarray(im) > 0
        marks.append(kind)
    if not (marks[0].any() or marks[1].any()):
        raise ImageError("bad_mask", f"{m.path}: no strokes (expected white object and/or black background strokes on grey 128 or transparency)")
    return marks[0], marks[1]


def _stored(frame: str) -> bool:
    """Whether a box or strokes ``frame`` (:data:`GUIDANCE_FRAMES`) is the photo's pixels as stored."""
    if frame not in GUIDANCE_FRAMES:
        raise ValueError(f"frame: expected one of {', '.join(GUIDANCE_FRAMES)}, got {frame!r}")
    return frame == "stored"


def photo_box(box: tuple[float, float, float, float], image: LoadedImage, frame: str = "upright") -> tuple[float, float, float, float]:
    """A box (x0, y0, x1, y1) in the photo's pixels (as displayed, after EXIF rotation) → the decoded image's pixels.

    With ``frame`` ``"stored"`` (:data:`GUIDANCE_FRAMES`) the box is over the
    photo's pixels as stored, and is first turned by its EXIF orientation
    (:func:`upright_box`).  Clipped to the photo; raises :class:`ImageError`
    ``bad_mask`` when less than a pixel of it is inside the photo.  (Its form
    is checked before, :func:`genre_backend.validation.check_box`.)
    """
    w, h = image.original_size
    stored = _stored(frame)
    x0, y0, x1, y1 = upright_box(box, image.exif_orientation, stored_size(image)) if stored else box
    c = (max(0.0, x0), max(0.0, y0), min(float(w), x1), min(float(h), y1))
    if c[2] - c[0] < 1.0 or c[3] - c[1] < 1.0:
        sw, sh = stored_size(image) if stored else (w, h)
        raise ImageError("bad_mask", f"{image.path}: the box {','.join(f'{v:g}' for v in box)} is not inside the {sw}×{sh} photo"
                                     f"{' as stored' if stored else ''} (less than a pixel of it is)")
    return tuple(v * image.scale for v in c)


# ---------------------------------------------------------------------------------- framing
def mask_bbox(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """Bounding box (x0, y0, x1, y1), exclusive upper bounds, of a (H, W) bool mask; None if empty."""
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return None
    return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1


def square_crop_box(bbox: tuple[float, float, float, float], object_fraction: float) -> tuple[float, float, float, float]:
    """The square (x0, y0, x1, y1) centred on ``bbox`` whose side is its longest side / ``object_fraction``."""
    if not 0.0 < object_fraction <= 1.0:
        raise ValueError(f"object_fraction: expected a value in (0, 1], got {object_fraction}")
    x0, y0, x1, y1 = bbox
    side = max(x1 - x0, y1 - y0, 1.0) / object_fraction
    cx, cy = (x0 + x1) / 2.0, (y0 + y1) / 2.0
    return cx - side / 2.0, cy - side / 2.0, cx + side / 2.0, cy + side / 2.0


def _border_colour(rgb: np.ndarray) -> tuple[int, int, int]:
    """Median colour (uint8 RGB) of the outermost pixels of a (H, W, 3) image."""
    border = np.concatenate([rgb[0], rgb[-1], rgb[:, 0], rgb[:, -1]], axis=0)
    return tuple(int(v) for v in np.median(border, axis=0))


def crop_resize(array: np.ndarray, box: tuple[float, float, float, float], size: int, fill) -> np.ndarray:
    """Crop ``array`` (H, W, C) or (H, W) uint8 to the square ``box`` and resize it to (size, size[, C]).

    Only the part of the box inside the image is resampled (area-averaging when
    shrinking); the rest is ``fill`` (a value or a per-channel tuple).  Memory
    stays O(image + size²) however far the box extends past the image.
    """
    from PIL import Image

    h, w = array.shape[:2]
    x0, y0, x1, y1 = box
    scale = size / (x1 - x0)
    mode = "L" if array.ndim == 2 else "RGB"
    out = Image.new(mode, (size, size), fill if mode == "L" else tuple(fill))
    # destination pixels covered by the image, rounded to whole pixels
    dx0, dy0 = max(0, round((0 - x0) * scale)), max(0, round((0 - y0) * scale))
    dx1, dy1 = min(size, round((w - x0) * scale)), min(size, round((h - y0) * scale))
    if dx1 > dx0 and dy1 > dy0:
        src = (
            min(max(x0 + dx0 / scale, 0.0), w),
            min(max(y0 + dy0 / scale, 0.0), h),
            min(max(x0 + dx1 / scale, 0.0), w),
            min(max(y0 + dy1 / scale, 0.0), h),
        )
        part = Image.fromarray(array, mode).resize((dx1 - dx0, dy1 - dy0), Image.BILINEAR, box=src, reducing_gap=2.0)
        out.paste(part, (dx0, dy0))
    return np.asarray(out)


def composite(image: LoadedImage) -> np.ndarray:
    """RGB (H, W, 3) uint8 of the image, RGBA composited over the neutral background."""
    if image.alpha is None:
        return image.rgb
    a = image.alpha.astype(np.float32)[:, :, None] / 255.0
    bg = np.array(NEUTRAL_BACKGROUND, np.float32) * 255.0
    return np.clip(np.rint(image.rgb.astype(np.float32) * a + bg * (1.0 - a)), 0, 255).astype(np.uint8)


def _to_tensor(rgb: np.ndarray) -> torch.Tensor:
    """(S, S, 3) uint8 → (3, S, S) float32 in [0, 1]."""
    return torch.from_numpy(rgb.astype(np.float32) / 255.0).permute(2, 0, 1).contiguous()


SilhouetteFn = Callable[[torch.Tensor], torch.Tensor]


def uncrop(values: np.ndarray, box: tuple[float, float, float, float], size: tuple[int, int], linear: bool = False) -> np.ndarray:
    """A crop's (S, S) values back at the photo's pixels: the inverse of :func:`crop_resize`'s framing.

    ``box``: the crop's square (x0, y0, x1, y1) in the photo's (decoded)
    pixels; ``size``: the photo's (width, height).  Returns (height, width)
    of ``values``' dtype: each photo pixel takes the crop pixel under its
    centre (``linear``: interpolated between the four nearest, float32);
    pixels outside the box get 0.
    """
    w, h = size
    s = values.shape[0]
    x0, y0, x1, y1 = box
    k = s / (x1 - x0)
    u = (np.arange(w) + 0.5 - x0) * k
    v = (np.arange(h) + 0.5 - y0) * k
    if linear:
        import cv2

        mx, my = np.meshgrid((u - 0.5).astype(np.float32), (v - 0.5).astype(np.float32))
        return cv2.remap(values.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    iu, iv = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    ok_u, ok_v = (iu >= 0) & (iu < s), (iv >= 0) & (iv < s)
    out = np.zeros((h, w), values.dtype)
    out[np.ix_(ok_v, ok_u)] = values[np.ix_(iv[ok_v], iu[ok_u])]
    return out


def _probability(silhouette_out: torch.Tensor) -> np.ndarray:
    """A silhouette function's output → (S, S) float32 probability (bool: 0/1; float: logits → sigmoid)."""
    if silhouette_out.dtype == torch.bool:
        return silhouette_out.detach().cpu().numpy().astype(np.float32)
    return torch.sigmoid(silhouette_out.detach().float()).cpu().numpy()


def preprocess(
    image: LoadedImage,
    config: GenreConfig,
    *,
    mask_path: str | os.PathLike | None = None,
    silhouette: SilhouetteFn | None = None,
    refine: bool = True,
    seeding: str = DEFAULT_SEEDING,
    box: tuple[float, float, float, float] | None = None,
    strokes_path: str | os.PathLike | None = None,
    guidance_frame: str = "upright",
) -> Preprocessed:
    """Select the mask and bring the image to the canonical framing.

    ``silhouette``: a function (3, S, S) float RGB → (S, S) silhouette
    logits (float) or mask (bool) of the depth net, needed only when neither
    a mask file nor real alpha is there; it runs once on the whole image
    padded to a square.  Then, with ``refine`` (the default), the object's
    mask is found in the photo (:func:`.segment.segment`, ``seeding`` one of
    :data:`.segment.SEEDINGS`: by default the salient-object net's, else
    GrabCut's) and used like a mask file (``mask_source`` ``"salient"`` or
    ``"grabcut"``); without it (or when nothing is found) the returned ``mask`` is None so that the caller takes the
    silhouette of the final crop (``mask_source`` ``"silhouette"``).
    ``box`` (x0, y0, x1, y1, the photo's pixels, :func:`photo_box`) and
    ``strokes_path`` (:func:`load_strokes`): a person's guidance for the mask
    (:func:`.segment.segment`); they take the place of the alpha channel and
    of the automatic seeding, not of a mask file (giving both is a
    ``ValueError``).  ``guidance_frame``: the pixels they are drawn over
    (:data:`GUIDANCE_FRAMES`: ``"upright"``, the photo with its EXIF
    orientation applied; ``"stored"``, as stored in its file).  Raises :class:`ImageError`.
    """
    g = config.geometry
    size = g.image_size
    rgb = composite(image)
    h, w = rgb.shape[:2]
    notes = list(image.notes)

    if box is not None or strokes_path is not None:
        if mask_path is not None:
            raise ValueError("give either a mask file or a box and strokes, not both")
        return _guided(image, rgb, g, notes, box, strokes_path, guidance_frame)

    if mask_path is not None or image.has_transparency():
        if mask_path is not None:
            mask, source = load_mask(mask_path, image), "file"
        else:
            mask, source = image.alpha >= ALPHA_OBJECT_MIN, "alpha"
            if int(mask.sum()) < MIN_OBJECT_PIXELS:
                raise ImageError("no_object", f"{image.path}: no object: the alpha channel is fully transparent")
        return _framed(image, rgb, g, notes, mask, source)

    if silhouette is None:
        raise ValueError("preprocess: an image without mask file or transparency needs the silhouette function")
    if seeding not in SEEDINGS:
        raise ValueError(f"seeding: expected one of {', '.join(SEEDINGS)}, got {seeding!r}")
    # pass 1: the whole image, padded to a square, to find the object
    side = float(max(w, h))
    whole = ((w - side) / 2.0, (h - side) / 2.0, (w + side) / 2.0, (h + side) / 2.0)
    fill = _border_colour(rgb)
    prob = _probability(silhouette(_to_tensor(crop_resize(rgb, whole, size, fill))))
    photo_prob = uncrop(prob, whole, (w, h), linear=True)
    network_doubt = doubt(photo_prob > 0.5, "depth net's silhouette")
    if network_doubt:
        notes.append(network_doubt)
    if refine:
        found = segment(rgb, photo_prob, seeding)
        if int(found.mask.sum()) >= MIN_OBJECT_PIXELS:
            notes.append(_mask_note(found))
            return _framed(image, rgb, g, notes, found.mask, "salient" if found.net else "grabcut", network_doubt,
                           _found_doubt(found))
        notes.append(f"{'the salient net' if found.net else 'GrabCut'} found no object: the depth net's silhouette is used")
    return _silhouette_framed(image, rgb, g, notes, prob, whole, fill, network_doubt)


def _mask_note(found) -> str:
    """The note that says how a :class:`.segment.Segmentation`'s mask was found."""
    if found.net:
        guide = found.seeding.replace("+", " and ")
        return "mask: the salient-object net (U²-Netp)" + ("" if found.seeding == "salient" else f", guided by the {guide}")
    seeds = {"border": "photo border", "network": "depth net silhouette"}.get(found.seeding, found.seeding.replace("+", " and "))
    return f"mask: GrabCut seeded by the {seeds}"


def _found_doubt(found) -> str | None:
    """A :class:`.segment.Segmentation`'s one-line warning: the net's fallback and the mask's doubt, joined."""
    return "; ".join(w for w in (found.fallback, found.doubt) if w) or None


def _original_box(box: tuple[float, float, float, float], image: LoadedImage) -> tuple[float, ...]:
    """A crop box in decoded pixels → the same box in the original photo's pixels."""
    inv = 1.0 / image.scale  # decoded pixels → original pixels
    return tuple(float(v) * inv for v in box)


def _framed(image: LoadedImage, rgb: np.ndarray, g: GeometryConfig, notes: list[str], mask: np.ndarray, source: str,
            network_doubt: str | None = None, mask_doubt: str | None = None) -> Preprocessed:
    """Crop the (H, W, 3) photo ``rgb`` and its (H, W) bool ``mask`` to the canonical framing of the mask's object."""
    size = g.image_size
    box = square_crop_box(mask_bbox(mask), g.object_fraction)
    fill = tuple(int(round(255 * c)) for c in NEUTRAL_BACKGROUND) if image.alpha is not None else _border_colour(rgb)
    crop = crop_resize(rgb, box, size, fill)
    crop_mask = crop_resize(mask.astype(np.uint8) * 255, box, size, 0) >= 128
    if int(crop_mask.sum()) < MIN_OBJECT_PIXELS:
        raise ImageError("no_object", f"{image.path}: no object: the {source} mask is too small to see at {size}² pixels")
    return Preprocessed(_to_tensor(crop), torch.from_numpy(crop_mask), source, _original_box(box, image), image.original_size, notes, fill,
                        photo_mask=mask, network_doubt=network_doubt, mask_doubt=mask_doubt)


def _guided(image: LoadedImage, rgb: np.ndarray, g: GeometryConfig, notes: list[str], box: tuple[float, float, float, float] | None,
            strokes_path: str | os.PathLike | None, frame: str = "upright") -> Preprocessed:
    """The mask from the salient net (GrabCut without it) guided by a person's ``box`` and/or strokes file (over the photo's ``frame``), framed."""
    fg, bg = load_strokes(strokes_path, image, frame) if strokes_path is not None else (None, None)
    found = segment(rgb, box=None if box is None else photo_box(box, image, frame), object_strokes=fg, background_strokes=bg)
    if int(found.mask.sum()) < MIN_OBJECT_PIXELS:
        raise ImageError("no_object", f"{image.path}: no object found inside the {found.seeding.replace('+', ' and ')}")
    notes.append(_mask_note(found))
    return _framed(image, rgb, g, notes, found.mask, found.seeding, mask_doubt=_found_doubt(found))


def _silhouette_framed(image: LoadedImage, rgb: np.ndarray, g: GeometryConfig, notes: list[str], prob: np.ndarray,
                       whole: tuple[float, float, float, float], fill, network_doubt: str | None) -> Preprocessed:
    """Frame the photo on the first pass's (S, S) silhouette probability ``prob`` of the square ``whole``; no mask."""
    size = g.image_size
    h, w = rgb.shape[:2]
    side = float(max(w, h))  # the side of ``whole``
    sil = prob > 0.5
    bbox = mask_bbox(sil)
    if bbox is None or int(sil.sum()) < MIN_OBJECT_PIXELS:
        raise ImageError("no_object", f"{image.path}: no object found (the depth net's silhouette is empty; give a mask with --mask or an alpha channel)")
    k = side / size  # pass-1 pixels → decoded pixels
    bbox = (whole[0] + bbox[0] * k, whole[1] + bbox[1] * k, whole[0] + bbox[2] * k, whole[1] + bbox[3] * k)
    box = square_crop_box(bbox, g.object_fraction)
    if _close_boxes(box, whole):
        # already framed (e.g. a render): the first pass's input is the framed image, and
        # the caller may reuse that pass's outputs instead of running the net again
        box = whole
        notes.append("already framed: first silhouette pass reused")
    crop = crop_resize(rgb, box, size, fill)
    return Preprocessed(_to_tensor(crop), None, "silhouette", _original_box(box, image), image.original_size, notes, fill,
                        network_doubt=network_doubt)


# a crop this close to the first pass's square is within the spread of training framings
# (the mask's longest side spans 0.28–0.68 of the real default renders)
_REFRAME_SIDE_TOL = 0.10
_REFRAME_CENTRE_TOL = 0.05


def _close_boxes(a: tuple[float, float, float, float], b: tuple[float, float, float, float]) -> bool:
    """True when square boxes ``a`` and ``b`` differ by ≤ 10% in side and ≤ 5% of the side in centre."""
    side_a, side_b = a[2] - a[0], b[2] - b[0]
    centre = max(abs((a[0] + a[2]) - (b[0] + b[2])), abs((a[1] + a[3]) - (b[1] + b[3]))) / 2.0
    return abs(side_a / side_b - 1.0) <= _REFRAME_SIDE_TOL and centre <= _REFRAME_CENTRE_TOL * side_b
