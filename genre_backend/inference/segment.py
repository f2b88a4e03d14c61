"""Object masks from the photo itself: GrabCut refinement and the doubt test.

The depth net's silhouette was trained on renders; on real photos it often
misses the object or takes the photo's frame for it.  This module turns a
photo into an object mask with OpenCV's GrabCut (a graph cut over colour
models, no training), seeded in one of two ways:

``"border"`` (the default, a product-photo prior)
    the outermost pixels are sure background, a rectangle inset by
    :data:`BORDER_INSET` of each side is probably object, the band between
    probably background.
``"network"``
    the depth net's silhouette probability: > :data:`SURE_FG` sure object,
    < :data:`SURE_BG` sure background, the rest probably one or the other by
    the 0.5 cut.
``"auto"``
    ``"network"``, unless the network's silhouette is doubtful
    (:func:`doubt`), then ``"border"``.

On our 9 real photos with hand masks (``examples/photos``,
``scripts/eval_photos.py --seedings``) the mean IoU was 0.81 with the border
prior, 0.45 with network seeding, 0.45 with ``"auto"`` (no whole-photo
silhouette there was doubtful) and 0.44 for the depth net's silhouette
alone, so the border prior is the default; per photo in ``results/photos/``.  GrabCut runs on the photo reduced to
:data:`WORK_SIDE` pixels on its long side (about 0.3 s); its result keeps
the largest connected part, with holes filled, and is scaled back to the
photo's pixels.

:func:`doubt` says when a mask is probably the photo's frame rather than an
object: it covers more than :data:`MAX_COVER` of the photo or touches more
than :data:`MAX_BORDER_TOUCH` of its border.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "SEEDINGS",
    "DEFAULT_SEEDING",
    "WORK_SIDE",
    "BORDER_INSET",
    "SURE_FG",
    "SURE_BG",
    "MAX_COVER",
    "MAX_BORDER_TOUCH",
    "cover",
    "border_touch",
    "doubt",
    "network_seeds",
    "border_seeds",
    "grabcut",
    "largest_part",
    "refine_mask",
]

SEEDINGS = ("border", "network", "auto")
DEFAULT_SEEDING = "border"
# GrabCut runs on the photo reduced to this many pixels on its long side
WORK_SIDE = 320
# the "border" seeding's rectangle of probable object is inset by this fraction of each side
BORDER_INSET = 0.10
# pixels this thick (at WORK_SIDE) along the photo's edge are sure background for the "border" seeding
BORDER_BAND = 2
# silhouette probabilities above SURE_FG are sure object, below SURE_BG sure background ("network" seeding)
SURE_FG = 0.9
SURE_BG = 0.1
GRABCUT_ITERATIONS = 5
# a mask covering more than this fraction of the photo, or touching more than this fraction
# of its border, is doubtful (probably the photo's frame rather than an object)
MAX_COVER = 0.85
MAX_BORDER_TOUCH = 0.5


def _cv2():
    import cv2  # noqa: PLC0415  (OpenCV loads only when a photo needs a mask)

    return cv2


def cover(mask: np.ndarray) -> float:
    """Fraction of the (H, W) bool ``mask`` that is object."""
    return float(mask.mean()) if mask.size else 0.0


def border_touch(mask: np.ndarray) -> float:
    """Fraction of the (H, W) bool ``mask``'s outermost pixels (its one-pixel frame) that are object."""
    if mask.shape[0] < 3 or mask.shape[1] < 3:
        return cover(mask)
    frame = np.concatenate([mask[0], mask[-1], mask[1:-1, 0], mask[1:-1, -1]])
    return float(frame.mean())


def doubt(mask: np.ndarray, what: str = "mask") -> str | None:
    """A one-line warning when ``mask`` (H, W) bool is probably the photo's frame, else None.

    Doubtful: it covers more than :data:`MAX_COVER` of the photo or touches
    more than :data:`MAX_BORDER_TOUCH` of its border.  ``what`` names the
    mask in the message.
    """
    c, t = cover(mask), border_touch(mask)
    if c <= MAX_COVER and t <= MAX_BORDER_TOUCH:
        return None
    facts = []
    if c > MAX_COVER:
        facts.append(f"covers {c:.0%} of the photo")
    if t > MAX_BORDER_TOUCH:
        facts.append(f"touches {t:.0%} of its border")
    return f"the {what} {' and '.join(facts)}: it is probably the photo's frame, not the object"


def network_seeds(probability: np.ndarray) -> np.ndarray:
    """(H, W) silhouette probability → (H, W) uint8 GrabCut labels (the ``"network"`` seeding)."""
    cv2 = _cv2()
    labels = np.where(probability > 0.5, cv2.GC_PR_FGD, cv2.GC_PR_BGD).astype(np.uint8)
    labels[probability > SURE_FG] = cv2.GC_FGD
    labels[probability < SURE_BG] = cv2.GC_BGD
    return labels


def border_seeds(height: int, width: int, inset: float | None = None, band: int | None = None) -> np.ndarray:
    """(H, W) uint8 GrabCut labels of the ``"border"`` seeding (the product-photo prior).

    Sure background: ``band`` pixels along the edge; probable object: the
    rectangle inset by ``inset`` of each side; probable background: the rest
    (defaults :data:`BORDER_INSET`, :data:`BORDER_BAND`).
    """
    cv2 = _cv2()
    inset = BORDER_INSET if inset is None else inset
    band = BORDER_BAND if band is None else band
    labels = np.full((height, width), cv2.GC_PR_BGD, np.uint8)
    dx, dy = max(1, round(inset * width)), max(1, round(inset * height))
    labels[dy:height - dy, dx:width - dx] = cv2.GC_PR_FGD
    b = max(1, min(band, (min(height, width) - 1) // 4))
    labels[:b] = labels[-b:] = cv2.GC_BGD
    labels[:, :b] = labels[:, -b:] = cv2.GC_BGD
    return labels


def grabcut(rgb: np.ndarray, labels: np.ndarray, iterations: int | None = None) -> np.ndarray:
    """GrabCut of a (H, W, 3) uint8 RGB image from (H, W) uint8 seed labels → (H, W) bool object.

    Deterministic (OpenCV's random generator is seeded before each call).
    A seeding with no possible object or no possible background returns the
    seeds' own object pixels.  ``iterations``: default :data:`GRABCUT_ITERATIONS`.
    """
    cv2 = _cv2()
    iterations = GRABCUT_ITERATIONS if iterations is None else iterations
    fg = (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)
    if not fg.any() or fg.all():
        return fg
    work = np.ascontiguousarray(labels, np.uint8).copy()
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.setRNGSeed(0)
    try:
        cv2.grabCut(np.ascontiguousarray(rgb[:, :, ::-1]), work, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:  # too few pixels of one kind for its colour model
        return fg
    return (work == cv2.GC_FGD) | (work == cv2.GC_PR_FGD)


def largest_part(mask: np.ndarray) -> np.ndarray:
    """The largest 8-connected part of a (H, W) bool mask with its holes filled (empty stays empty)."""
    from scipy.ndimage import binary_fill_holes

    cv2 = _cv2()
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(mask, dtype=bool)
    keep = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return binary_fill_holes(labels == keep)


def refine_mask(rgb: np.ndarray, probability: np.ndarray | None = None, seeding: str = DEFAULT_SEEDING,
                work_side: int | None = None) -> tuple[np.ndarray, str]:
    """The object's mask in a photo by GrabCut; returns ((H, W) bool, the seeding used).

    ``rgb``: (H, W, 3) uint8 photo.  ``probability``: (H, W) float in [0, 1],
    the depth net's silhouette at the photo's pixels (needed by the
    ``"network"`` and ``"auto"`` seedings).  ``seeding``: one of
    :data:`SEEDINGS`; ``"auto"`` resolves to ``"border"`` when the
    network's silhouette is doubtful (:func:`doubt`), else ``"network"``.
    GrabCut runs at ``work_side`` pixels on the photo's long side (default
    :data:`WORK_SIDE`).  The mask may be empty when GrabCut finds nothing.
    """
    cv2 = _cv2()
    work_side = WORK_SIDE if work_side is None else work_side
    if seeding not in SEEDINGS:
        raise ValueError(f"seeding: expected one of {', '.join(SEEDINGS)}, got {seeding!r}")
    h, w = rgb.shape[:2]
    if seeding != "border":
        if probability is None or probability.shape != (h, w):
            raise ValueError(f"seeding {seeding!r} needs the silhouette probability at the photo's {w}×{h} pixels")
        if seeding == "auto":
            seeding = "border" if doubt(probability > 0.5) else "network"
    k = min(1.0, work_side / max(h, w))
    sw, sh = max(1, round(w * k)), max(1, round(h * k))
    small = cv2.resize(rgb, (sw, sh), interpolation=cv2.INTER_AREA) if k < 1.0 else rgb
    if seeding == "border":
        labels = border_seeds(sh, sw)
    else:
        p = cv2.resize(probability.astype(np.float32), (sw, sh), interpolation=cv2.INTER_AREA) if k < 1.0 else probability
        labels = network_seeds(p)
    mask = largest_part(grabcut(small, labels))
    if k < 1.0:
        mask = cv2.resize(mask.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR) > 0.5
    return mask, seeding
