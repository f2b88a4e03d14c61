"""A box's cut: GrabCut whose colour models also see the photo's local sharpness, as our own graph cut.

With a box the cut is :func:`feature_grabcut`: GrabCut whose colour models also see the photo's
local sharpness (:func:`sharpness`, a defocus cue: an object in focus before
a blurred background), run as our own graph cut (PyMaxflow), since OpenCV's
GrabCut takes 3 colour channels only; where the automatic cut runs on out of
the box (its *spill*, the squirrel's branch, :func:`.grabcut.box_prior`), the background's model also
holds a mixture learnt there.  On the 9 photos a box alone (the hand mask's
bounding box grown by 5 %) reached a mean IoU of 0.905 against the hand
masks (0.890 without the spill, 0.870 with OpenCV's GrabCut), the automatic
mask 0.812 (``scripts/mask_box.py``, ``docs/masks.md``; fitted on those
photos).  The salient net's saliency may weigh in as a prior (``prior``: the cut a person's strokes correct).
"""

from __future__ import annotations

import numpy as np

from .grabcut import GRABCUT_ITERATIONS

__all__ = [
    "MIN_SPILL",
    "MIXTURE_COMPONENTS",
    "SALIENT_PRIOR_WEIGHT",
    "SHARPNESS_WEIGHT",
    "SMOOTHNESS",
    "SPILL_FITS",
    "feature_grabcut",
    "sharpness",
]

# the salient net's cut with strokes: the weight of its log-odds beside the colour models' log-likelihoods
SALIENT_PRIOR_WEIGHT = 5.0
# a box's cut sees the photo's sharpness (:func:`sharpness`, about 0–6) times this beside its colours (0–255)
SHARPNESS_WEIGHT = 20.0
# a box's cut learns a mixture on where the automatic cut runs on out of the box (:func:`.grabcut.box_prior`) when it
# holds at least this many pixels (at WORK_SIDE), refitting it this many times after its k-means start
MIN_SPILL = 50
SPILL_FITS = 3
# the graph cut's smoothness weight (GrabCut's gamma) and the number of components of each colour mixture
SMOOTHNESS = 50.0
MIXTURE_COMPONENTS = 5


def _cv2():
    import cv2  # noqa: PLC0415  (OpenCV loads only when a photo needs a mask)

    return cv2


def sharpness(rgb: np.ndarray) -> np.ndarray:
    """(H, W) float32 local detail of a (H, W, 3) uint8 image (at :data:`.segment.WORK_SIDE`): a defocus cue.

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
    """GrabCut whose colour models also see the photo's sharpness: :func:`.grabcut.grabcut_models`' answer.

    The same algorithm as OpenCV's (5-component Gaussian mixtures, learnt by assigning each pixel to
    its likeliest component; the same contrast-sensitive smoothness; a graph cut per iteration), with
    each pixel's features BGR and :data:`SHARPNESS_WEIGHT` × :func:`sharpness`, so that an object in
    focus parts from a blurred background of its colours.  ``spill`` ((H, W) bool, sure background:
    :func:`.grabcut.box_prior`'s) adds to the background's model one fixed mixture learnt on its pixels, weighted
    by its share of the box (:func:`_spill_log_likelihood`): what the automatic cut joined to the object
    out of the box is background inside it too.  ``prior`` ((H, W) float in [0, 1], the salient net's
    saliency) adds :data:`SALIENT_PRIOR_WEIGHT` × its log-odds to each pixel's costs.  The models returned are the colour part of the
    object's and of the background's own mixture, in OpenCV's form, for :func:`.mask_doubt.model_overlap`.
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
