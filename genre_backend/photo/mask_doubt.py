"""Whether a mask is doubtful: the photo's frame, GrabCut's own doubts, the salient net's.

:func:`doubt` says when a mask is probably the photo's frame rather than an
object: it covers more than :data:`MAX_COVER` of the photo or touches more
than :data:`MAX_BORDER_TOUCH` of its border.  :func:`cut_doubt` says when a
GrabCut mask is doubtful for reasons of its own: its colour models barely
separate object from background (more than :data:`MAX_MODEL_OVERLAP` of
the object's pixels are better explained by the background's colours,
:func:`model_overlap`), or, for the automatic seedings, it runs into the
sure-background band along the photo's edge over more than
:data:`MAX_EDGE_RUN` of it (:func:`edge_run`: the object is cut by the
frame, or joined to something that is).  Both levels were set on the 9
photos (``docs/masks.md``), so they are fitted there, not tested.
:func:`salient_doubt` says when the salient net's mask is: an unsure outline, one of several objects, cut by the
frame, tiny.
"""

from __future__ import annotations

import numpy as np

from .salient import SALIENT_THRESHOLD

__all__ = [
    "MAX_BORDER_TOUCH",
    "MAX_COVER",
    "MAX_EDGE_RUN",
    "MAX_FRAME_CUT",
    "MAX_MODEL_OVERLAP",
    "MAX_UNSURE_WIDTH",
    "MIN_COVER",
    "MIN_SECOND_PART",
    "UNSURE_HIGH",
    "UNSURE_LOW",
    "border_touch",
    "cover",
    "cut_doubt",
    "doubt",
    "edge_run",
    "model_overlap",
    "salient_doubt",
]

# a mask covering more than this fraction of the photo, or touching more than this fraction
# of its border, is doubtful (probably the photo's frame rather than an object)
MAX_COVER = 0.85
MAX_BORDER_TOUCH = 0.5
# a GrabCut mask more than this share of whose pixels the background's colour model explains better is doubtful
MAX_MODEL_OVERLAP = 0.12
# an automatic mask running along the sure-background band at the photo's edge for more than this share
# of the band's inner ring is doubtful (cut by the frame, or joined to something that is)
MAX_EDGE_RUN = 0.01


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


def _gmm_log_likelihood(model: np.ndarray, colours: np.ndarray) -> np.ndarray:
    """Log-likelihood of (N, 3) float colours (BGR, 0–255) under OpenCV's (1, 65) GrabCut mixture → (N,)."""
    weights, means, covs = model[0, :5], model[0, 5:20].reshape(5, 3), model[0, 20:].reshape(5, 3, 3)
    terms = []
    for k in range(5):
        if weights[k] <= 0:
            continue
        cov = covs[k] + np.eye(3) * 1e-3  # (OpenCV adds the same to a singular covariance)
        d = colours - means[k]
        q = np.einsum("ni,ij,nj->n", d, np.linalg.inv(cov), d)
        terms.append(np.log(weights[k]) - 0.5 * (q + np.log(np.linalg.det(cov)) + 3.0 * np.log(2.0 * np.pi)))
    return np.logaddexp.reduce(np.stack(terms), axis=0)


def model_overlap(rgb: np.ndarray, mask: np.ndarray, object_model: np.ndarray, background_model: np.ndarray) -> float:
    """Share of the (H, W) bool ``mask``'s pixels whose colour the background's model explains better.

    ``rgb``: the (H, W, 3) uint8 image GrabCut ran on; the models as
    :func:`.grabcut.grabcut_models` returns them.  0 for an empty mask.  A high share
    means the object's colours barely separate from the background's: the
    cut then follows edges more than colours and may take in a neighbour.
    """
    if not mask.any():
        return 0.0
    colours = rgb[mask][:, ::-1].astype(np.float64)  # RGB → BGR, as GrabCut saw them
    ratio = _gmm_log_likelihood(object_model, colours) - _gmm_log_likelihood(background_model, colours)
    return float((ratio < 0).mean())


def edge_run(mask: np.ndarray, inset: int = 0) -> float:
    """Longest run of object pixels along the ring ``inset`` pixels in from the (H, W) bool mask's edge.

    As a share of the ring's length (0: never on it, 1: all around).  With
    ``inset`` = the border seeding's band of sure background, the ring is
    the innermost pixels GrabCut may give the object: a long run there means
    the object was stopped by the band, not by its own outline.
    """
    h, w = mask.shape
    if h - 2 * inset < 3 or w - 2 * inset < 3:
        return cover(mask)
    m = mask[inset:h - inset, inset:w - inset]
    ring = np.concatenate([m[0], m[1:, -1], m[-1, -2::-1], m[-2:0:-1, 0]])
    if ring.all():
        return 1.0
    if not ring.any():
        return 0.0
    ring = np.roll(ring, -int(np.argmin(ring)))  # start on a background pixel: no run wraps around
    edges = np.diff(np.concatenate([[0], ring.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return float((ends - starts).max()) / ring.size


def cut_doubt(rgb: np.ndarray, mask: np.ndarray, object_model: np.ndarray | None, background_model: np.ndarray | None,
              band: int | None = None) -> str | None:
    """A one-line warning when a GrabCut mask is doubtful for reasons of its own (see the module docstring), else None.

    ``rgb`` (H, W, 3) uint8 and ``mask`` (H, W) bool at the size GrabCut
    ran; the models from :func:`.grabcut.grabcut_models` (None: not judged on
    colour); ``band``: the sure-background band along the edge (automatic
    seedings; None: not judged on the edge).
    """
    facts = []
    if object_model is not None and background_model is not None:
        overlap = model_overlap(rgb, mask, object_model, background_model)
        if overlap > MAX_MODEL_OVERLAP:
            facts.append(f"has colours that barely separate from the background's ({overlap:.0%} of it looks more like "
                         f"background): it may take in a neighbour or miss a part")
    if band is not None:
        run = edge_run(mask, band)
        if run > MAX_EDGE_RUN:
            facts.append(f"runs along the photo's edge for {run:.0%} of it: the object is cut by the frame, or joined "
                         f"to something that is")
    return f"the mask {'; it also '.join(facts)}" if facts else None


# the doubt of a net's mask: its outline's band (saliency between these) wider on average than MAX_UNSURE_WIDTH pixels
# (at WORK_SIDE); a second part of the thresholded saliency at least MIN_SECOND_PART of the largest; a mask whose pixels on
# the photo's edge are more than MAX_FRAME_CUT of its outline; one covering less than MIN_COVER of the photo
UNSURE_LOW, UNSURE_HIGH = 0.1, 0.9
MAX_UNSURE_WIDTH = 4.0
MIN_SECOND_PART = 0.25
MAX_FRAME_CUT = 0.10
MIN_COVER = 0.01


def _parts(mask: np.ndarray) -> np.ndarray:
    """The areas of a (H, W) bool mask's 8-connected parts, largest first."""
    cv2 = _cv2()
    n, _, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    return np.sort(stats[1:, cv2.CC_STAT_AREA])[::-1] if n > 1 else np.zeros(0, int)


def _outline_length(mask: np.ndarray) -> int:
    """The number of pixels on the outer outlines of a (H, W) bool mask's parts."""
    cv2 = _cv2()
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    return sum(len(c) for c in contours)


def _frame_cut(mask: np.ndarray) -> float:
    """The (H, W) bool mask's pixels on the photo's one-pixel edge, as a share of its outline's length (0 … 1)."""
    if not mask.any():
        return 0.0
    frame = np.concatenate([mask[0], mask[-1], mask[1:-1, 0], mask[1:-1, -1]])
    return float(frame.sum()) / max(1, _outline_length(mask))


def salient_doubt(prob: np.ndarray, mask: np.ndarray, window: np.ndarray | None = None) -> str | None:
    """A one-line warning when the salient net's mask is doubtful, else None.

    ``prob``: (H, W) saliency; ``mask``: the (H, W) bool mask made of it.  Doubtful (levels at the top of the
    file, ``docs/masks.md``): the net is unsure of the outline (its pixels between :data:`UNSURE_LOW` and
    :data:`UNSURE_HIGH` in the mask's bounding box, over the outline's length, are a band wider than
    :data:`MAX_UNSURE_WIDTH` pixels);
    it found a second large object (a part of the thresholded saliency of :data:`MIN_SECOND_PART` of the largest
    or more); the mask is cut off by the frame (its pixels on the photo's edge are more than :data:`MAX_FRAME_CUT` of
    its outline); it covers almost nothing (:data:`MIN_COVER`).  ``window``: (H, W) bool or None, the box the net
    was given (its crop has a frame of its own): the frame is then not judged.  (Too much of the photo and the border: :func:`doubt`.)
    """
    facts = []
    if mask.any():
        rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
        near = prob[max(0, rows[0] - 2):rows[-1] + 3, max(0, cols[0] - 2):cols[-1] + 3]
        width = float(((near > UNSURE_LOW) & (near < UNSURE_HIGH)).sum()) / max(1, _outline_length(mask))
        if width > MAX_UNSURE_WIDTH:
            facts.append(f"has an outline the salient net is unsure of (a band {width:.1f} px wide at {max(mask.shape)} px)")
    parts = _parts(prob > SALIENT_THRESHOLD)
    if len(parts) > 1 and parts[1] >= MIN_SECOND_PART * parts[0]:
        facts.append(f"is one of {int((parts >= MIN_SECOND_PART * parts[0]).sum())} large objects the salient net found")
    if window is None:
        cut = _frame_cut(mask)
        if cut > MAX_FRAME_CUT:
            facts.append(f"is cut off by the photo's edge ({cut:.0%} of its outline)")
    c = cover(mask)
    if c < MIN_COVER:
        facts.append(f"covers only {c:.1%} of the photo")
    return f"the mask {'; it also '.join(facts)}" if facts else None
