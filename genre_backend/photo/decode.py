"""The photo and a person's guidance files, read safely: the image, a mask file, strokes and a box.

:func:`load_image` decodes any format Pillow reads, EXIF orientation applied, the first frame of animations,
16-bit / grayscale / palette / CMYK / bilevel converted to 8-bit RGB(A).  Images above :data:`MAX_PIXELS` are
refused before any pixel is decoded (JPEGs are first reduced by the decoder's DCT scaling when that brings them under
the limit), and larger ones are downscaled to at most :data:`WORK_SIDE` pixels on their long side, which is far more
than the network input needs.  :func:`load_mask`, :func:`load_strokes` and :func:`photo_box` read what a person
gives, in the photo's upright frame or as the file is stored (:data:`GUIDANCE_FRAMES`).

Every failure raises :class:`ImageError` whose ``code`` is one of the ``genre serve`` protocol's error codes
(``bad_image``, ``bad_mask``) and whose message is one line naming the file and the problem.
"""

from __future__ import annotations

import os
import re
import stat
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .grabcut import STROKE_BACKGROUND_MAX, STROKE_OBJECT_MIN

__all__ = [
    "ImageError",
    "LoadedImage",
    "MAX_PIXELS",
    "WORK_SIDE",
    "MIN_OBJECT_PIXELS",
    "ALPHA_OBJECT_MIN",
    "GUIDANCE_FRAMES",
    "load_image",
    "load_mask",
    "load_strokes",
    "photo_box",
    "stored_size",
    "upright_array",
    "upright_box",
]


# Images with more pixels than this are refused (8-bit RGBA at the limit: 256 MB).
MAX_PIXELS = 64_000_000
# Decoded images are downscaled to at most this many pixels on their long side.
WORK_SIDE = 4096
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
    (luminance) ≥ :data:`.grabcut.STROKE_OBJECT_MIN` (white) is sure object,
    ≤ :data:`.grabcut.STROKE_BACKGROUND_MAX` (black) sure background, anything
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
