"""Do the renders show a shape's thickness in its shading? Luminance spread inside the silhouette against thickness.

For each view of a folder rendered from a manifest of procedural shapes (``genre data squashed``, ``genre data
thin``): the spread of the picture's luminance (Rec. 601 weights) inside the silhouette eroded by 2 px, its 90th
percentile minus its 10th, beside the shape's thickness (its extent along the up axis over its larger extent
across). Printed per kind of shape (the second word of its id, ``squashed-ellipsoid-004`` → ``ellipsoid``): the
Spearman correlation of the two and the median spread in four thickness bands. A shading cue a depth net could
read shows as a spread that rises with thickness; a flat top, evenly lit, as a small spread whatever the thickness.

Usage::

    python scripts/shading_spread.py --views $GENRE_HOME/views/squash_above --manifest $GENRE_HOME/squashed/manifest.json
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict

import numpy as np
from scipy.ndimage import binary_erosion
from scipy.stats import spearmanr

from training.data.views import find_views, load_view

LUMA = np.array([0.299, 0.587, 0.114])
BANDS = ((0.0, 0.08), (0.08, 0.2), (0.2, 0.5), (0.5, np.inf))


def luminance_spread(rgb: np.ndarray, mask: np.ndarray, erode: int = 2) -> float | None:
    """90th minus 10th percentile of the luminance of ``rgb`` (H, W, 3) uint8 over ``mask`` (H, W) > 0.5 eroded by
    ``erode`` px, in [0, 1]; None when fewer than 20 pixels are left."""
    inner = binary_erosion(mask > 0.5, iterations=erode)
    if inner.sum() < 20:
        return None
    lum = (rgb.astype(np.float64) / 255.0) @ LUMA
    low, high = np.percentile(lum[inner], [10, 90])
    return float(high - low)


def thickness(extents: list[float]) -> float:
    """The extent along the up axis (z) over the larger of the two across it."""
    return float(extents[2] / max(extents[0], extents[1]))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--views", required=True, help="a folder of rendered views of the manifest's shapes")
    parser.add_argument("--manifest", required=True, help="the manifest.json the views were rendered from")
    args = parser.parse_args(argv)
    extents = {s["id"]: s["extents"] for s in json.loads(open(args.manifest, encoding="utf-8").read())["shapes"]}
    rows: dict[str, list[tuple[float, float]]] = defaultdict(list)
    for ref in find_views(args.views, targets=False):
        view = load_view(ref.shape_dir, ref.view)
        spread = luminance_spread(view["rgb"], view["mask"])
        if spread is not None and ref.shape_id in extents:
            kind = ref.shape_id.split("-")[1] if "-" in ref.shape_id else ref.shape_id
            rows[kind].append((thickness(extents[ref.shape_id]), spread))
    if not rows:
        print(f"no views of the manifest's shapes in {args.views}", file=sys.stderr)
        return 1
    for kind, pairs in sorted(rows.items()):
        t, s = np.array(pairs).T
        bands = " | ".join(f"{lo:g}–{hi:g}: {np.median(s[(t >= lo) & (t < hi)]):.3f}" if ((t >= lo) & (t < hi)).any()
                           else f"{lo:g}–{hi:g}: –" for lo, hi in BANDS)
        print(f"{kind}: {len(t)} views, Spearman(thickness, spread) {spearmanr(t, s)[0]:.2f}; median spread by "
              f"thickness {bands}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
