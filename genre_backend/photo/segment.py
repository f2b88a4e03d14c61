"""Object masks from the photo itself: the salient net's, or GrabCut's, and whether they are doubtful.

The depth net's silhouette was trained on renders; on real photos it often
misses the object or takes the photo's frame for it.  :func:`segment` turns a
photo into an object mask: by default the salient-object net's (:mod:`.salient`), guided by a person's box and
strokes when given; GrabCut's (:mod:`.grabcut`, a box's cut :mod:`.feature_cut`) when the net cannot be loaded or
another seeding is asked for; and the doubt of the mask it made (:mod:`.mask_doubt`).

On our 9 real photos with hand masks (``examples/photos``,
``scripts/eval_photos.py --seedings``) the mean IoU was 0.81 with the border
prior, 0.45 with network seeding, 0.45 with ``"auto"`` (no whole-photo
silhouette there was doubtful) and 0.44 for the depth net's silhouette
alone, so the border prior is GrabCut's default; per photo in ``results/photos/``.  The work is done on the photo
reduced to :data:`WORK_SIDE` pixels on its long side (GrabCut: about 0.3 s); its result keeps
the largest connected part, with holes filled, and is scaled back to the
photo's pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .feature_cut import feature_grabcut
from .grabcut import (BORDER_BAND, border_seeds, box_prior, box_seeds, grabcut_models, guided_seeds, largest_part,
                      network_seeds, salient_labels)
from .mask_doubt import cut_doubt, doubt, salient_doubt
from .salient import SALIENT_THRESHOLD

__all__ = [
    "BOX_KEEPS",
    "BOX_MARGIN",
    "DEFAULT_SEEDING",
    "SEEDINGS",
    "Segmentation",
    "WORK_SIDE",
    "refine_mask",
    "segment",
]

SEEDINGS = ("salient", "border", "network", "auto")
DEFAULT_SEEDING = "salient"
# a box's crop for the net: the box grown by this fraction of its width and height on each side (clipped to the photo)
BOX_MARGIN = 0.10
# a box keeps the whole photo's net mask when at least this share of it lies in the box; else the net sees the box's crop
BOX_KEEPS = 0.99
# masks are made on the photo reduced to this many pixels on its long side (the net's cut and GrabCut alike)
WORK_SIDE = 320


def _cv2():
    import cv2  # noqa: PLC0415  (OpenCV loads only when a photo needs a mask)

    return cv2


@dataclass
class Segmentation:
    """A mask found by :func:`segment`.

    ``mask``: (H, W) bool at the photo's pixels (may be empty).
    ``seeding``: ``"salient"``, ``"border"``, ``"network"``, ``"box"``,
    ``"strokes"`` or ``"box+strokes"``.  ``doubt``: :func:`.mask_doubt.salient_doubt`'s
    or :func:`.mask_doubt.cut_doubt`'s warning, else None.  ``fallback``: one line when
    the salient net could not be loaded and GrabCut's mask was made instead,
    else None.  ``net``: whether the salient net made or guided the mask.
    """

    mask: np.ndarray
    seeding: str
    doubt: str | None = None
    fallback: str | None = None
    net: bool = False


def _shrink_marks(marks: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H, W) bool strokes → (h, w) bool at ``size`` (w, h): a small pixel is marked when any of its area is."""
    cv2 = _cv2()
    if marks.shape == (size[1], size[0]):
        return marks
    return cv2.resize(marks.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.0


def _net_saliency(rgb: np.ndarray, size: tuple[int, int], window: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """The salient net's saliency of the (H, W, 3) uint8 photo at ``size`` (w, h), float32 in [0, 1].

    ``window``: (c0, r0, c1, r1) of the photo (its own pixels): the net sees that crop alone, and the saliency is 0
    outside it.  Raises :class:`.salient.SalientNetError` when the net cannot be loaded.
    """
    from . import salient  # noqa: PLC0415  (the net loads only when a photo needs a mask)

    net = salient.load()
    if window is None:
        return net(rgb, size)
    h, w = rgb.shape[:2]
    c0, r0, c1, r1 = window
    sw, sh = size
    kx, ky = sw / w, sh / h
    out = np.zeros((sh, sw), np.float32)
    s0, t0 = int(round(c0 * kx)), int(round(r0 * ky))
    s1, t1 = max(s0 + 1, int(round(c1 * kx))), max(t0 + 1, int(round(r1 * ky)))
    out[t0:t1, s0:s1] = net(rgb[r0:r1, c0:c1], (s1 - s0, t1 - t0))
    return out


def _box_window(box: tuple[float, float, float, float], width: int, height: int) -> tuple[int, int, int, int]:
    """A box (x0, y0, x1, y1) grown by :data:`BOX_MARGIN` of its size on each side → whole pixels (c0, r0, c1, r1) of the photo."""
    x0, y0, x1, y1 = box
    dx, dy = BOX_MARGIN * (x1 - x0), BOX_MARGIN * (y1 - y0)
    c0, r0 = max(0, int(np.floor(x0 - dx))), max(0, int(np.floor(y0 - dy)))
    c1, r1 = min(width, int(np.ceil(x1 + dx))), min(height, int(np.ceil(y1 + dy)))
    return c0, r0, max(c0 + 1, c1), max(r0 + 1, r1)


def _box_saliency(rgb: np.ndarray, whole: np.ndarray, inside: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray:
    """The saliency a box's mask is cut from: the whole photo's when its mask keeps to the box, else the box crop's.

    ``whole``: (h, w) saliency of the whole photo; ``inside``: (h, w) bool, the box.  When the whole photo's mask
    (its largest part) has at least :data:`BOX_KEEPS` of its pixels in the box, the box confirms it: that saliency
    is kept (a box cannot make a right mask worse).  Else the net found something else, or something that runs on
    out of the box (the squirrel's branch): it looks again at the box's crop, grown by :data:`BOX_MARGIN` (:func:`_box_window`).
    """
    auto = largest_part(whole > SALIENT_THRESHOLD)
    if auto.any() and float((auto & inside).sum()) >= BOX_KEEPS * float(auto.sum()):
        return whole
    h, w = rgb.shape[:2]
    return _net_saliency(rgb, whole.shape[::-1], _box_window(box, w, h))


def _fallback_line(exc: Exception, guided: bool) -> str:
    """The one-line warning of a mask made by GrabCut because the salient net could not be loaded."""
    return f"the salient-object net cannot be used ({exc}): the mask is GrabCut's" + ("" if guided else ", seeded by the photo's border")


def _salient_cut(small: np.ndarray, prob: np.ndarray, box: tuple[float, float, float, float] | None,
                 fg: np.ndarray | None, bg: np.ndarray | None) -> tuple[np.ndarray, str | None]:
    """The net's (h, w) bool mask of the work-size photo ``small`` from its saliency ``prob`` and its doubt.

    ``box`` (work-size pixels): a hard limit; ``fg``, ``bg``: the strokes at the work size, hard constraints of a
    cut (:func:`.feature_cut.feature_grabcut`) started from the net's labels, its log-odds the prior.  Without strokes the
    saliency is cut at :data:`.salient.SALIENT_THRESHOLD`.
    """
    cv2 = _cv2()
    sh, sw = prob.shape
    box_labels = None if box is None else box_seeds(sh, sw, box)
    window = None if box is None else box_labels != cv2.GC_BGD
    if fg is None and bg is None:
        cut = prob > SALIENT_THRESHOLD
        if window is not None:
            cut &= window
    else:
        cut = feature_grabcut(small, guided_seeds(salient_labels(prob, box_labels), fg, bg), prior=prob)[0]
    mask = largest_part(cut, fg)
    if bg is not None:  # background strokes stay background, even in a hole the filling closed
        mask &= ~bg
    return mask, (salient_doubt(prob, mask, window) if mask.any() else None)


def _grabcut_cut(small: np.ndarray, seeding: str | None, prob: np.ndarray | None, box: tuple[float, float, float, float] | None,
                 fg: np.ndarray | None, bg: np.ndarray | None) -> tuple[np.ndarray, str | None]:
    """GrabCut's (h, w) bool mask of the work-size photo ``small`` and its doubt (without the net).

    ``seeding``: ``"border"`` or ``"network"`` (``prob``: the depth net's silhouette at the work size), or None for
    a person's guidance: ``box`` (work-size pixels; :func:`.grabcut.box_prior`, :func:`.feature_cut.feature_grabcut`) and the strokes.
    """
    cv2 = _cv2()
    sh, sw = small.shape[:2]
    spill = band = None
    if seeding is None:
        labels = border_seeds(sh, sw)
        if box is not None:
            labels, spill = box_prior(small, box_seeds(sh, sw, box))
        labels = guided_seeds(labels, fg, bg)
        spill = None if spill is None else spill & (labels == cv2.GC_BGD)
    elif seeding == "border":
        labels = border_seeds(sh, sw)
        band = max(1, min(BORDER_BAND, (min(sh, sw) - 1) // 4))
    else:
        labels = network_seeds(prob)
        band = 1
    cut, fgd, bgd = feature_grabcut(small, labels, spill=spill) if box is not None else grabcut_models(small, labels)
    mask = largest_part(cut, fg)
    return mask, (cut_doubt(small, mask, fgd, bgd, band) if mask.any() else None)


def segment(rgb: np.ndarray, probability: np.ndarray | None = None, seeding: str = DEFAULT_SEEDING,
            work_side: int | None = None, *, box: tuple[float, float, float, float] | None = None,
            object_strokes: np.ndarray | None = None, background_strokes: np.ndarray | None = None) -> Segmentation:
    """The object's mask in a photo, and whether it is doubtful.

    ``rgb``: (H, W, 3) uint8 photo.  ``seeding``: one of :data:`SEEDINGS`:
    ``"salient"`` (the default) is the salient net's mask (:mod:`.salient`:
    its saliency above :data:`.salient.SALIENT_THRESHOLD`), or GrabCut's ``"border"``
    seeding when the net cannot be loaded (``fallback`` says so).
    ``probability``: (H, W) float in [0, 1], the depth net's silhouette at
    the photo's pixels (needed by the ``"network"`` and ``"auto"`` GrabCut
    seedings; ``"auto"`` resolves to ``"border"`` when the network's
    silhouette is doubtful (:func:`.mask_doubt.doubt`), else ``"network"``).  A person's
    ``box`` (x0, y0, x1, y1, the photo's pixels) and strokes
    (``object_strokes``, ``background_strokes``: (H, W) bool) replace the
    seeding.  With the net, a box alone is the net's mask of the box's crop
    grown by :data:`BOX_MARGIN`, cut to the box; strokes are hard
    constraints of a cut (:func:`.feature_cut.feature_grabcut`) started from the net's
    labels (:func:`.grabcut.salient_labels`) with its log-odds as a prior.  Without
    the net, GrabCut (:func:`.grabcut.box_prior`, :func:`.grabcut.guided_seeds`).  The work is
    done at ``work_side`` pixels on the photo's long side (default
    :data:`WORK_SIDE`); the largest part and every part under an object
    stroke are kept, holes filled.
    """
    cv2 = _cv2()
    work_side = WORK_SIDE if work_side is None else work_side
    if seeding not in SEEDINGS:
        raise ValueError(f"seeding: expected one of {', '.join(SEEDINGS)}, got {seeding!r}")
    h, w = rgb.shape[:2]
    guided = box is not None or object_strokes is not None or background_strokes is not None
    fallback = None
    if guided:
        for name, marks in (("object_strokes", object_strokes), ("background_strokes", background_strokes)):
            if marks is not None and marks.shape != (h, w):
                raise ValueError(f"{name}: expected the photo's {w}×{h} pixels, got {marks.shape[1]}×{marks.shape[0]}")
        use_net = seeding == "salient"
        seeding = "+".join(n for n, v in (("box", box), ("strokes", object_strokes is not None or background_strokes is not None)) if v)
    else:
        use_net = seeding == "salient"
        if seeding in ("network", "auto"):
            if probability is None or probability.shape != (h, w):
                raise ValueError(f"seeding {seeding!r} needs the silhouette probability at the photo's {w}×{h} pixels")
            if seeding == "auto":
                seeding = "border" if doubt(probability > 0.5) else "network"
    k = min(1.0, work_side / max(h, w))
    sw, sh = max(1, round(w * k)), max(1, round(h * k))
    small = cv2.resize(rgb, (sw, sh), interpolation=cv2.INTER_AREA) if k < 1.0 else rgb
    prob = None
    if use_net:
        from .salient import SalientNetError  # noqa: PLC0415

        try:
            prob = _net_saliency(rgb, (sw, sh))
            if box is not None:
                inside = box_seeds(sh, sw, tuple(v * k for v in box)) != cv2.GC_BGD
                prob = _box_saliency(rgb, prob, inside, box)
        except SalientNetError as exc:
            fallback = _fallback_line(exc, guided)
            if not guided:
                seeding = "border"
    fg_small = bg_small = None
    if guided:
        fg_small = None if object_strokes is None else _shrink_marks(object_strokes, (sw, sh))
        bg_small = None if background_strokes is None else _shrink_marks(background_strokes, (sw, sh))
    box_small = None if box is None else tuple(v * k for v in box)
    if prob is not None:
        mask, warning = _salient_cut(small, prob, box_small, fg_small, bg_small)
    else:
        small_prob = None
        if seeding == "network" and not guided:
            small_prob = cv2.resize(probability.astype(np.float32), (sw, sh), interpolation=cv2.INTER_AREA) if k < 1.0 \
                else probability
        mask, warning = _grabcut_cut(small, seeding if not guided else None, small_prob, box_small, fg_small, bg_small)
    if k < 1.0:
        mask = cv2.resize(mask.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR) > 0.5
    return Segmentation(mask, seeding, warning, fallback, prob is not None)


def refine_mask(rgb: np.ndarray, probability: np.ndarray | None = None, seeding: str = DEFAULT_SEEDING,
                work_side: int | None = None) -> tuple[np.ndarray, str]:
    """The object's mask in a photo by GrabCut; returns ((H, W) bool, the seeding used).

    :func:`segment` without a person's guidance and without the doubt.
    The mask may be empty when GrabCut finds nothing.
    """
    found = segment(rgb, probability, seeding, work_side)
    return found.mask, found.seeding
