"""Photo → network input: mask selection and the canonical framing (the decoding: :mod:`.decode`).

Training views are rendered in the canonical framing of :mod:`genre_backend.frame`
(object centred at the origin, bounding-box diagonal 1, camera 2.2 units away),
so the object sits in the middle of the image.  A photo is brought to that
framing here, and only here:

1. **Decode** (:func:`.decode.load_image`): any format Pillow reads, EXIF orientation
   applied, 8-bit RGB(A), too large images refused before any pixel is decoded.
2. **Mask** (:func:`preprocess`), in this order: a mask file given by the user
   (same size as the image, not empty), else a box and/or strokes given by the
   user (:func:`.decode.photo_box`, :func:`.decode.load_strokes`: the salient net's mask
   guided by them, :func:`.segment.segment`), else the image's alpha channel when it
   has real transparency, else a mask found in the photo by a pretrained
   salient-object net (:mod:`.salient`, :mod:`.segment`; GrabCut seeded by
   the photo's border when the net cannot be loaded, with a warning),
   else the depth net's own silhouette (two passes: the whole image padded
   to a square, then the crop around that silhouette).  A final mask that
   covers most of the photo or touches most of its border is reported as
   doubtful (:func:`.mask_doubt.doubt`, done by the caller).
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

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from ..config import GenreConfig, GeometryConfig
from .decode import ALPHA_OBJECT_MIN, MIN_OBJECT_PIXELS, ImageError, LoadedImage, load_mask, load_strokes, photo_box
from .guidance import MaskGuidance
from .mask_doubt import doubt
from .segment import SEEDINGS, segment

__all__ = [
    "Preprocessed",
    "NEUTRAL_BACKGROUND",
    "mask_bbox",
    "square_crop_box",
    "crop_resize",
    "composite",
    "on_plain_backdrop",
    "uncrop",
    "preprocess",
]

# RGB (in [0, 1]) that transparent pixels are composited over.
NEUTRAL_BACKGROUND = (0.5, 0.5, 0.5)


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
    (:func:`.mask_doubt.doubt`), why; else None.  ``mask_doubt``: when the
    found mask is doubtful (:func:`.mask_doubt.salient_doubt`,
    :func:`.mask_doubt.cut_doubt`) or was made without the salient net because
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


def on_plain_backdrop(rgb: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``rgb`` (..., 3, S, S) in [0, 1] with every pixel outside ``mask`` (..., S, S) bool set to the neutral grey
    (:data:`NEUTRAL_BACKGROUND`): the picture the networks see with ``geometry.plain_backdrop`` on."""
    if rgb.shape[-3] != 3 or mask.shape[-2:] != rgb.shape[-2:]:
        raise ValueError(f"on_plain_backdrop: rgb (..., 3, S, S) and mask (..., S, S) expected, got {tuple(rgb.shape)} "
                         f"and {tuple(mask.shape)}")
    grey = torch.tensor(NEUTRAL_BACKGROUND, dtype=rgb.dtype, device=rgb.device).view(3, 1, 1)
    return torch.where(mask.bool().unsqueeze(-3), rgb, grey)


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


def preprocess(image: LoadedImage, config: GenreConfig, guidance: MaskGuidance | None = None, *,
               silhouette: SilhouetteFn | None = None) -> Preprocessed:
    """Select the mask and bring the image to the canonical framing.

    ``guidance``: the mask inputs and switches (:class:`.guidance.MaskGuidance`; None: none given, the automatic
    mask).  ``silhouette``: a function (3, S, S) float RGB → (S, S) silhouette
    logits (float) or mask (bool) of the depth net, needed only when neither
    a mask file nor real alpha is there; it runs once on the whole image
    padded to a square.  Then, with ``guidance.refine`` (the default), the object's
    mask is found in the photo (:func:`.segment.segment`, ``guidance.seeding`` one of
    :data:`.segment.SEEDINGS`: by default the salient-object net's, else
    GrabCut's) and used like a mask file (``mask_source`` ``"salient"`` or
    ``"grabcut"``); without it (or when nothing is found) the returned ``mask`` is None so that the caller takes the
    silhouette of the final crop (``mask_source`` ``"silhouette"``).
    ``guidance.box`` (x0, y0, x1, y1, the photo's pixels, :func:`photo_box`) and
    ``guidance.strokes`` (:func:`load_strokes`): a person's guidance for the mask
    (:func:`.segment.segment`); they take the place of the alpha channel and
    of the automatic seeding, not of a mask file (giving both is a
    ``ValueError``), over the pixels ``guidance.frame`` says
    (:data:`GUIDANCE_FRAMES`: ``"upright"``, the photo with its EXIF
    orientation applied; ``"stored"``, as stored in its file).  Raises :class:`ImageError`.
    """
    guidance = MaskGuidance() if guidance is None else guidance
    g = config.geometry
    size = g.image_size
    rgb = composite(image)
    h, w = rgb.shape[:2]
    notes = list(image.notes)

    if guidance.guided:
        if guidance.mask is not None:
            raise ValueError("give either a mask file or a box and strokes, not both")
        return _guided(image, rgb, g, notes, guidance)

    if guidance.mask is not None or image.has_transparency():
        if guidance.mask is not None:
            mask, source = load_mask(guidance.mask, image), "file"
        else:
            mask, source = image.alpha >= ALPHA_OBJECT_MIN, "alpha"
            if int(mask.sum()) < MIN_OBJECT_PIXELS:
                raise ImageError("no_object", f"{image.path}: no object: the alpha channel is fully transparent")
        return _framed(image, rgb, g, notes, mask, source)

    if silhouette is None:
        raise ValueError("preprocess: an image without mask file or transparency needs the silhouette function")
    seeding = guidance.seeding
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
    if guidance.refine:
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


def _guided(image: LoadedImage, rgb: np.ndarray, g: GeometryConfig, notes: list[str], guidance: MaskGuidance) -> Preprocessed:
    """The mask from the salient net (GrabCut without it) guided by a person's box and/or strokes file (over the photo's
    ``guidance.frame``), framed."""
    box, strokes, frame = guidance.box, guidance.strokes, guidance.frame
    fg, bg = load_strokes(strokes, image, frame) if strokes is not None else (None, None)
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
