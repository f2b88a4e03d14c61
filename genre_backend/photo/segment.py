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

A person can guide it (:func:`guided_seeds`): a **box** (x0, y0, x1, y1)
around the object makes everything outside it sure background and, inside
it, probable object where the automatic (``"border"``) cut finds the object,
probable background elsewhere (:func:`box_prior`; GrabCut's own rectangle
start, all of the box probable object, when that cut misses the box); **strokes**, an
image the photo's size, mark sure object (white, grey level ≥
:data:`STROKE_OBJECT_MIN`) and sure background (black, ≤
:data:`STROKE_BACKGROUND_MAX`); anything between (mid grey, 128) and
transparent pixels say nothing.  Strokes alone correct the ``"border"``
seeding; with a box they correct the box's.  With a box the cut is
:func:`feature_grabcut`: GrabCut whose colour models also see the photo's
local sharpness (:func:`sharpness`, a defocus cue: an object in focus before
a blurred background), run as our own graph cut (PyMaxflow), since OpenCV's
GrabCut takes 3 colour channels only; where the automatic cut runs on out of
the box (its *spill*, the squirrel's branch), the background's model also
holds a mixture learnt there.  On the 9 photos a box alone (the hand mask's
bounding box grown by 5 %) reached a mean IoU of 0.905 against the hand
masks (0.890 without the spill, 0.870 with OpenCV's GrabCut), the automatic
mask 0.812 (``scripts/mask_box.py``, ``docs/masks.md``; fitted on those
photos).

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
than :data:`MAX_BORDER_TOUCH` of its border.  :func:`cut_doubt` says when a
GrabCut mask is doubtful for reasons of its own: its colour models barely
separate object from background (more than :data:`MAX_MODEL_OVERLAP` of
the object's pixels are better explained by the background's colours,
:func:`model_overlap`), or, for the automatic seedings, it runs into the
sure-background band along the photo's edge over more than
:data:`MAX_EDGE_RUN` of it (:func:`edge_run`: the object is cut by the
frame, or joined to something that is).  Both levels were set on the 9
photos (``docs/masks.md``), so they are fitted there, not tested.
"""

from __future__ import annotations

from dataclasses import dataclass

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
    "grabcut_models",
    "largest_part",
    "refine_mask",
    "STROKE_OBJECT_MIN",
    "STROKE_BACKGROUND_MAX",
    "MAX_MODEL_OVERLAP",
    "MAX_EDGE_RUN",
    "Segmentation",
    "edge_run",
    "model_overlap",
    "cut_doubt",
    "box_seeds",
    "box_prior",
    "MIN_BOX_PRIOR",
    "MIN_SPILL",
    "SHARPNESS_WEIGHT",
    "sharpness",
    "feature_grabcut",
    "guided_seeds",
    "segment",
    "SALIENT_THRESHOLD",
    "BOX_MARGIN",
    "salient_labels",
    "salient_doubt",
]

SEEDINGS = ("salient", "border", "network", "auto")
DEFAULT_SEEDING = "salient"
# the salient net's (min–max normalised) saliency above this is object
SALIENT_THRESHOLD = 0.5
# a box's crop for the net: the box grown by this fraction of its width and height on each side (clipped to the photo)
BOX_MARGIN = 0.10
# a box keeps the whole photo's net mask when at least this share of it lies in the box; else the net sees the box's crop
BOX_KEEPS = 0.99
# the salient net's cut with strokes: the weight of its log-odds beside the colour models' log-likelihoods
SALIENT_PRIOR_WEIGHT = 5.0
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
# strokes images: grey levels at or above this are sure object, at or below the next sure background
STROKE_OBJECT_MIN = 192
STROKE_BACKGROUND_MAX = 63
# a GrabCut mask more than this share of whose pixels the background's colour model explains better is doubtful
MAX_MODEL_OVERLAP = 0.12
# an automatic mask running along the sure-background band at the photo's edge for more than this share
# of the band's inner ring is doubtful (cut by the frame, or joined to something that is)
MAX_EDGE_RUN = 0.01
# a box keeps its plain start (all of it probable object) when the automatic cut finds less than this share of it
MIN_BOX_PRIOR = 0.05
# a box's cut sees the photo's sharpness (:func:`sharpness`, about 0–6) times this beside its colours (0–255)
SHARPNESS_WEIGHT = 20.0
# a box's cut learns a mixture on where the automatic cut runs on out of the box (:func:`box_prior`) when it
# holds at least this many pixels (at WORK_SIDE), refitting it this many times after its k-means start
MIN_SPILL = 50
SPILL_FITS = 3
# the graph cut's smoothness weight (GrabCut's gamma) and the number of components of each colour mixture
SMOOTHNESS = 50.0
MIXTURE_COMPONENTS = 5


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
    return grabcut_models(rgb, labels, iterations)[0]


def grabcut_models(rgb: np.ndarray, labels: np.ndarray, iterations: int | None = None
                   ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """:func:`grabcut`, also returning its colour models: ((H, W) bool, object model, background model).

    Each model is OpenCV's (1, 65) float64 array of a 5-component Gaussian
    mixture in BGR (5 weights, 5×3 means, 5×3×3 covariances); both None
    when GrabCut did not run (a seeding with only one kind of pixel).
    """
    cv2 = _cv2()
    iterations = GRABCUT_ITERATIONS if iterations is None else iterations
    fg = (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)
    if not fg.any() or fg.all():
        return fg, None, None
    work = np.ascontiguousarray(labels, np.uint8).copy()
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.setRNGSeed(0)
    try:
        cv2.grabCut(np.ascontiguousarray(rgb[:, :, ::-1]), work, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:  # too few pixels of one kind for its colour model
        return fg, None, None
    return (work == cv2.GC_FGD) | (work == cv2.GC_PR_FGD), fgd, bgd


def largest_part(mask: np.ndarray, keep: np.ndarray | None = None) -> np.ndarray:
    """The largest 8-connected part of a (H, W) bool mask with its holes filled (empty stays empty).

    ``keep``: (H, W) bool; parts that hold any of its pixels are kept too
    (a person's object strokes on two separate parts).
    """
    from scipy.ndimage import binary_fill_holes

    cv2 = _cv2()
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(mask, dtype=bool)
    chosen = {1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))}
    if keep is not None:
        chosen |= {int(v) for v in np.unique(labels[keep & mask])}
    return binary_fill_holes(np.isin(labels, sorted(chosen)))


# ---------------------------------------------------------------------------- the doubt of a cut
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
    :func:`grabcut_models` returns them.  0 for an empty mask.  A high share
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
    ran; the models from :func:`grabcut_models` (None: not judged on
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


# ---------------------------------------------------------------------------- guided seeding
def box_seeds(height: int, width: int, box: tuple[float, float, float, float]) -> np.ndarray:
    """(H, W) uint8 GrabCut labels of a box (x0, y0, x1, y1) in pixels: probable object inside, sure background outside.

    The box is rounded outward to whole pixels and clipped to the image.
    """
    cv2 = _cv2()
    x0, y0, x1, y1 = box
    c0, r0 = max(0, int(np.floor(x0))), max(0, int(np.floor(y0)))
    c1, r1 = min(width, int(np.ceil(x1))), min(height, int(np.ceil(y1)))
    labels = np.full((height, width), cv2.GC_BGD, np.uint8)
    labels[r0:r1, c0:c1] = cv2.GC_PR_FGD
    return labels


def box_prior(rgb: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """A box's (H, W) uint8 labels (:func:`box_seeds`) with the automatic guess inside it: where the
    ``"border"`` seeding's cut of the (H, W, 3) uint8 ``rgb`` finds no object, probable background.

    Returns (labels, spill): spill, (H, W) bool, is where that cut runs on out of the box (what the
    object is joined to there, the squirrel's branch; :func:`feature_grabcut`).  Labels left as they
    are and no spill (None) when that cut holds less than :data:`MIN_BOX_PRIOR` of the box.  On the 9
    photos (boxes: the hand masks' grown by 5 %) the guess raised the mean IoU of OpenCV's GrabCut
    from 0.82 to 0.87 (``docs/masks.md``).
    """
    cv2 = _cv2()
    inside = labels == cv2.GC_PR_FGD
    auto = largest_part(grabcut(rgb, border_seeds(*labels.shape)))
    if int((auto & inside).sum()) < MIN_BOX_PRIOR * max(1, int(inside.sum())):
        return labels, None
    out = labels.copy()
    out[inside & ~auto] = cv2.GC_PR_BGD
    return out, auto & (labels == cv2.GC_BGD)


# ---------------------------------------------------------------------------- the box's cut: colours and sharpness
def sharpness(rgb: np.ndarray) -> np.ndarray:
    """(H, W) float32 local detail of a (H, W, 3) uint8 image (at :data:`WORK_SIDE`): a defocus cue.

    log(1 + |Laplacian of the grey image|, Gaussian-smoothed with sigma 3 px), then its minimum over a
    7 px disc, so that the halo the smoothing spreads around a sharp outline does not reach the blurred
    background beside it.  High on an object in focus (its texture and outline), low on a blurred
    background; low too inside a smooth object, so it is one more feature for the colour models, not a seed.
    """
    cv2 = _cv2()
    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY).astype(np.float32)
    detail = np.log1p(cv2.GaussianBlur(np.abs(cv2.Laplacian(grey, cv2.CV_32F, ksize=3)), (0, 0), 3.0))
    return cv2.erode(detail, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7)))


def _mixture(features: np.ndarray, assignment: np.ndarray) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """A Gaussian mixture (weight, mean, covariance) per component from (N, D) features and (N,) component numbers."""
    d, parts = features.shape[1], []
    for k in range(MIXTURE_COMPONENTS):
        chosen = features[assignment == k]
        if len(chosen) > d:
            parts.append((len(chosen) / len(features), chosen.mean(0), np.cov(chosen.T) + np.eye(d) * 0.01))
    return parts


def _component_log_likelihoods(mixture, features: np.ndarray) -> np.ndarray:
    """(K, N) log(weight × density) of (N, D) features under each component of a :func:`_mixture`."""
    terms = []
    for weight, mean, cov in mixture:
        d = features - mean
        q = np.einsum("ni,ij,nj->n", d, np.linalg.inv(cov), d)
        terms.append(np.log(weight) - 0.5 * (q + np.log(np.linalg.det(cov)) + features.shape[1] * np.log(2.0 * np.pi)))
    return np.stack(terms)


def _fit_mixture(features: np.ndarray, mixture=None):
    """GrabCut's learning step: each of the (N, D) features to its likeliest component of ``mixture``, then refit.

    Without a mixture: the first one, its components from k-means (OpenCV's, seeded: deterministic).
    """
    cv2 = _cv2()
    if mixture is not None:
        return _mixture(features, np.argmax(_component_log_likelihoods(mixture, features), axis=0))
    cv2.setRNGSeed(0)
    criteria = (cv2.TERM_CRITERIA_MAX_ITER, 10, 0.0)
    _, assignment, _ = cv2.kmeans(features.astype(np.float32), MIXTURE_COMPONENTS, None, criteria, 1,
                                  cv2.KMEANS_PP_CENTERS)
    return _mixture(features, assignment.ravel())


def _smoothness_edges(rgb: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """GrabCut's contrast-sensitive smoothness over 8 neighbours: (3×3 structure, (H, W) weights) per direction.

    Weight :data:`SMOOTHNESS` / distance × exp(-beta ‖colour difference‖²), beta = 1 / (2 × its mean).
    """
    image, (h, w) = rgb.astype(np.float64), rgb.shape[:2]
    pairs = []
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        a = image[:h - dy, max(0, -dx):w - max(0, dx)]
        b = image[dy:, max(0, dx):w - max(0, -dx)]
        pairs.append((dy, dx, ((a - b) ** 2).sum(-1)))
    beta = 1.0 / (2.0 * np.mean(np.concatenate([p[2].ravel() for p in pairs])) + 1e-9)
    edges = []
    for dy, dx, squared in pairs:
        weights = np.zeros((h, w))
        weights[:h - dy, max(0, -dx):w - max(0, dx)] = SMOOTHNESS / np.hypot(dy, dx) * np.exp(-beta * squared)
        structure = np.zeros((3, 3))
        structure[1 + dy, 1 + dx] = 1.0
        edges.append((structure, weights))
    return edges


def _min_cut(object_cost: np.ndarray, background_cost: np.ndarray, edges, sure_object: np.ndarray,
             sure_background: np.ndarray) -> np.ndarray:
    """The (H, W) bool labelling of least cost (PyMaxflow's graph cut): per-pixel costs plus the smoothness edges."""
    import maxflow  # noqa: PLC0415  (PyMaxflow loads only when a box is cut)

    graph = maxflow.Graph[float]()
    nodes = graph.add_grid_nodes(object_cost.shape)
    for structure, weights in edges:
        graph.add_grid_edges(nodes, weights=weights, structure=structure, symmetric=True)
    big = 1e9
    to_source = np.where(sure_object, big, np.where(sure_background, 0.0, background_cost))  # paid when cut off: background
    to_sink = np.where(sure_background, big, np.where(sure_object, 0.0, object_cost))
    graph.add_grid_tedges(nodes, to_source, to_sink)
    graph.maxflow()
    return ~graph.get_grid_segments(nodes)


def _opencv_model(mixture) -> np.ndarray:
    """A :func:`_mixture`'s colour part (its first 3 features, BGR) as OpenCV's (1, 65) GrabCut model."""
    model = np.zeros((1, 65), np.float64)
    for k, (weight, mean, cov) in enumerate(mixture):
        model[0, k] = weight
        model[0, 5 + 3 * k:8 + 3 * k] = mean[:3]
        model[0, 20 + 9 * k:29 + 9 * k] = cov[:3, :3].ravel()
    return model


def _spill_log_likelihood(features: np.ndarray, spill: np.ndarray | None, box_pixels: int
                          ) -> tuple[float, np.ndarray] | None:
    """(share, (N,) log-density) of (N, D) features under a mixture learnt on the (H, W) bool ``spill``'s
    pixels, share = min(0.5, spill pixels / ``box_pixels``); None with fewer than :data:`MIN_SPILL` of them."""
    if spill is None or int(spill.sum()) < MIN_SPILL:
        return None
    chosen = features[spill.ravel()]
    try:
        mixture = _fit_mixture(chosen)
        for _ in range(SPILL_FITS):
            mixture = _fit_mixture(chosen, mixture)
        density = np.logaddexp.reduce(_component_log_likelihoods(mixture, features), axis=0)
    except ValueError:  # every component lost its pixels: no spill model
        return None
    return min(0.5, float(spill.sum()) / max(1, box_pixels)), density


def feature_grabcut(rgb: np.ndarray, labels: np.ndarray, iterations: int | None = None,
                    spill: np.ndarray | None = None, prior: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """GrabCut whose colour models also see the photo's sharpness: :func:`grabcut_models`' answer.

    The same algorithm as OpenCV's (5-component Gaussian mixtures, learnt by assigning each pixel to
    its likeliest component; the same contrast-sensitive smoothness; a graph cut per iteration), with
    each pixel's features BGR and :data:`SHARPNESS_WEIGHT` × :func:`sharpness`, so that an object in
    focus parts from a blurred background of its colours.  ``spill`` ((H, W) bool, sure background:
    :func:`box_prior`'s) adds to the background's model one fixed mixture learnt on its pixels, weighted
    by its share of the box (:func:`_spill_log_likelihood`): what the automatic cut joined to the object
    out of the box is background inside it too.  ``prior`` ((H, W) float in [0, 1], the salient net's
    saliency) adds :data:`SALIENT_PRIOR_WEIGHT` × its log-odds to each pixel's costs.  The models returned are the colour part of the
    object's and of the background's own mixture, in OpenCV's form, for :func:`model_overlap`.
    """
    cv2 = _cv2()
    iterations = GRABCUT_ITERATIONS if iterations is None else iterations
    fg = (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)
    if not fg.any() or fg.all():
        return fg, None, None
    features = np.concatenate([rgb[:, :, ::-1].astype(np.float64), SHARPNESS_WEIGHT * sharpness(rgb)[..., None]], -1)
    features = features.reshape(-1, 4)
    edges = _smoothness_edges(rgb)
    spilt = _spill_log_likelihood(features, spill, int((labels != cv2.GC_BGD).sum()))
    try:
        objects, backgrounds = _fit_mixture(features[fg.ravel()]), _fit_mixture(features[~fg.ravel()])
        for _ in range(iterations):
            objects = _fit_mixture(features[fg.ravel()], objects)
            backgrounds = _fit_mixture(features[~fg.ravel()], backgrounds)
            fit = [np.logaddexp.reduce(_component_log_likelihoods(m, features), axis=0) for m in (objects, backgrounds)]
            if spilt is not None:  # the background: its own mixture and the spill's, by their shares
                fit[1] = np.logaddexp(fit[1] + np.log1p(-spilt[0]), spilt[1] + np.log(spilt[0]))
            object_cost, background_cost = -fit[0].reshape(fg.shape), -fit[1].reshape(fg.shape)
            if prior is not None:
                p = np.clip(prior, 1e-3, 1.0 - 1e-3)
                object_cost, background_cost = (object_cost - SALIENT_PRIOR_WEIGHT * np.log(p),
                                                background_cost - SALIENT_PRIOR_WEIGHT * np.log1p(-p))
            fg = _min_cut(object_cost, background_cost, edges, labels == cv2.GC_FGD, labels == cv2.GC_BGD)
    except (cv2.error, ValueError):  # too few pixels of one kind for its mixture
        return (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD), None, None
    return fg, _opencv_model(objects), _opencv_model(backgrounds)


def guided_seeds(labels: np.ndarray, object_strokes: np.ndarray | None, background_strokes: np.ndarray | None) -> np.ndarray:
    """(H, W) uint8 labels with a person's strokes written over them: object → GC_FGD, background → GC_BGD.

    ``object_strokes``, ``background_strokes``: (H, W) bool or None.  A pixel
    marked both ways keeps its label.
    """
    cv2 = _cv2()
    out = labels.copy()
    fg = np.zeros(labels.shape, bool) if object_strokes is None else object_strokes
    bg = np.zeros(labels.shape, bool) if background_strokes is None else background_strokes
    out[fg & ~bg] = cv2.GC_FGD
    out[bg & ~fg] = cv2.GC_BGD
    return out


@dataclass
class Segmentation:
    """A mask found by :func:`segment`.

    ``mask``: (H, W) bool at the photo's pixels (may be empty).
    ``seeding``: ``"salient"``, ``"border"``, ``"network"``, ``"box"``,
    ``"strokes"`` or ``"box+strokes"``.  ``doubt``: :func:`salient_doubt`'s
    or :func:`cut_doubt`'s warning, else None.  ``fallback``: one line when
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


# ---------------------------------------------------------------------------- the salient net's masks
# the doubt of a net's mask: its outline's band (saliency between these) wider on average than MAX_UNSURE_WIDTH pixels
# (at WORK_SIDE); a second part of the thresholded saliency at least MIN_SECOND_PART of the largest; a mask whose pixels on
# the photo's edge are more than MAX_FRAME_CUT of its outline; one covering less than MIN_COVER of the photo
UNSURE_LOW, UNSURE_HIGH = 0.1, 0.9
MAX_UNSURE_WIDTH = 4.0
MIN_SECOND_PART = 0.25
MAX_FRAME_CUT = 0.10
MIN_COVER = 0.01


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


def salient_labels(prob: np.ndarray, box_labels: np.ndarray | None = None) -> np.ndarray:
    """(H, W) uint8 GrabCut labels from the net's saliency: probable object above :data:`SALIENT_THRESHOLD`,
    probable background below; sure background where ``box_labels`` (:func:`box_seeds`) say so."""
    cv2 = _cv2()
    labels = np.where(prob > SALIENT_THRESHOLD, cv2.GC_PR_FGD, cv2.GC_PR_BGD).astype(np.uint8)
    if box_labels is not None:
        labels[box_labels == cv2.GC_BGD] = cv2.GC_BGD
    return labels


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


def _fallback_line(exc: Exception, guided: bool) -> str:
    """The one-line warning of a mask made by GrabCut because the salient net could not be loaded."""
    return f"the salient-object net cannot be used ({exc}): the mask is GrabCut's" + ("" if guided else ", seeded by the photo's border")


def _salient_cut(small: np.ndarray, prob: np.ndarray, box: tuple[float, float, float, float] | None,
                 fg: np.ndarray | None, bg: np.ndarray | None) -> tuple[np.ndarray, str | None]:
    """The net's (h, w) bool mask of the work-size photo ``small`` from its saliency ``prob`` and its doubt.

    ``box`` (work-size pixels): a hard limit; ``fg``, ``bg``: the strokes at the work size, hard constraints of a
    cut (:func:`feature_grabcut`) started from the net's labels, its log-odds the prior.  Without strokes the
    saliency is cut at :data:`SALIENT_THRESHOLD`.
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
    a person's guidance: ``box`` (work-size pixels; :func:`box_prior`, :func:`feature_grabcut`) and the strokes.
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
    its saliency above :data:`SALIENT_THRESHOLD`), or GrabCut's ``"border"``
    seeding when the net cannot be loaded (``fallback`` says so).
    ``probability``: (H, W) float in [0, 1], the depth net's silhouette at
    the photo's pixels (needed by the ``"network"`` and ``"auto"`` GrabCut
    seedings; ``"auto"`` resolves to ``"border"`` when the network's
    silhouette is doubtful (:func:`doubt`), else ``"network"``).  A person's
    ``box`` (x0, y0, x1, y1, the photo's pixels) and strokes
    (``object_strokes``, ``background_strokes``: (H, W) bool) replace the
    seeding.  With the net, a box alone is the net's mask of the box's crop
    grown by :data:`BOX_MARGIN`, cut to the box; strokes are hard
    constraints of a cut (:func:`feature_grabcut`) started from the net's
    labels (:func:`salient_labels`) with its log-odds as a prior.  Without
    the net, GrabCut (:func:`box_prior`, :func:`guided_seeds`).  The work is
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
