"""The depth net's stage table: its depth on rendered views against the render's own, for several weights.

For each views folder (``genre data render``: the product test split's renders, the flat-from-above group) and
each weights file, the depth net runs on every view's picture and its depth is compared with the render's planar
depth inside the render's silhouette, eroded by 2 pixels (the outline, where any net blurs into the background,
is left out: it is the silhouette's error, not the relief's).  Each view's constant offset (the median error)
is removed first, since a constant offset moves the whole shape and the pipeline's voxels follow it; what is left
is the **relief** error:

* ``relief MAE``: the mean absolute error after removing the offset (median over views, and mean);
* ``relief ÷ truth``: the predicted relief's interquartile range over the true one (1 = as deep as the truth,
  > 1 too curved), median over views;
* ``offset``: the removed offset's size, ``|median error|``, median over views (the whole shape's shift along the
  view direction, which the relief leaves out);
* ``better``: on how many views the weights beat the first weights named (relief MAE);
* ``follows``: Spearman's rank correlation, over the folder's views, of the predicted relief's interquartile range
  with the true one's: whether a view that is deeper gets a deeper relief (1: in the same order; 0: no relation).

A last row per folder is the flat plane, a constant depth: its relief MAE is the true relief's own mean deviation,
what a net that learned no relief at all would score.  With ``--silhouette-only``, each weights file gets a second
row: the same net on the picture with the object painted one colour (its own mean; the background kept), so the
net sees the silhouette and nothing of the shading or texture inside it.  Where that row matches the first, the
net's relief comes from the outline alone.

Usage::

    python scripts/depth_errors.py --views $GENRE_HOME/views/product_eval $GENRE_HOME/views/flat_eval \\
        --weights default --weights $GENRE_HOME/runs/up88/depth/best.safetensors --out results/stage_errors/depth.md
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import binary_erosion
from scipy.stats import spearmanr

from genre_backend.arguments import add_out, add_weights
from genre_backend.nets.model import load_model
from genre_backend.weights_file import resolve_weights
from training.data.views import find_views, load_view

FLAT_PLANE = "flat plane (a constant depth; reference)"


def flat_coloured(view: dict) -> dict:
    """The view with its object painted its own mean colour (weighted by the mask), the background untouched."""
    alpha = np.clip(view["mask"], 0.0, 1.0)[..., None]
    rgb = view["rgb"].astype(np.float64)
    mean = (rgb * alpha).sum((0, 1)) / max(float(alpha.sum()), 1e-6)
    painted = mean * alpha + rgb * (1.0 - alpha)
    return dict(view, rgb=np.clip(np.round(painted), 0, 255).astype(np.uint8))


def view_errors(net, view: dict, erode: int = 2) -> tuple[float, float, float, float] | None:
    """(relief MAE, relief IQR ÷ the truth's, |offset|, the true relief's IQR) of one view, or None when the eroded silhouette is too small.

    ``net`` None: the flat plane, a constant depth (relief MAE: the true relief's mean deviation from its median;
    ratio 0; its offset is not a prediction, so NaN).
    """
    inner = binary_erosion(view["mask"] > 0.5, iterations=erode)
    if inner.sum() < 20:
        return None
    true = view["depth"][inner]
    iqr = lambda x: float(np.subtract(*np.percentile(x, [75, 25])))  # noqa: E731
    if net is None:
        return float(np.mean(np.abs(true - np.median(true)))), 0.0, float("nan"), iqr(true)
    rgb = torch.from_numpy(view["rgb"]).permute(2, 0, 1)[None].float() / 255.0
    with torch.no_grad():
        pred = net.depth_net(rgb)["depth"][0].numpy()[inner]
    err = pred - true
    offset = float(np.median(err))
    return float(np.mean(np.abs(err - offset))), iqr(pred) / max(iqr(true), 1e-6), abs(offset), iqr(true)


def summary_cells(errors: list[tuple[float, float, float, float]], first: np.ndarray, flat_plane: bool = False) -> list[str]:
    """One weights' row over a folder from its views' :func:`view_errors`: n, relief MAE median and mean, relief ÷
    truth (median), offset (median; "–" for the flat plane), views better than ``first`` (the first weights' relief
    MAEs), and *follows*: Spearman's correlation of the predicted relief's IQR with the true one's ("–" for the flat
    plane, which has none)."""
    mae, ratio, offset, true_iqr = (np.array([x[i] for x in errors]) for i in range(4))
    follows = "–" if flat_plane else f"{spearmanr(ratio * true_iqr, true_iqr).statistic:.2f}"
    return [f"{len(errors)}", f"{np.median(mae):.4f}", f"{np.mean(mae):.4f}", f"{np.median(ratio):.2f}",
            "–" if flat_plane else f"{np.median(offset):.4f}", f"{int((mae < first).sum())} / {len(errors)}", follows]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--views", nargs="+", required=True, help="folders of rendered views")
    add_weights(parser, action="append", required=True, help="weights (name or file); repeat to compare")
    parser.add_argument("--silhouette-only", action="store_true",
                        help="add a row per weights: the net on the picture with the object painted one colour")
    add_out(parser, default=None, help="write the table here (markdown) as well as printing it")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    nets = [load_model(resolve_weights(w)).eval() for w in args.weights]
    names = list(args.weights)
    painted = [False] * len(nets)
    if args.silhouette_only:
        names += [f"{w}, object one colour (silhouette only)" for w in args.weights]
        nets, painted = nets + nets, painted + [True] * len(nets)
    lines = ["| views | weights | n | relief MAE median | relief MAE mean | relief ÷ truth (median) | offset (median) | "
             "better than the first | follows |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    rowed = nets + [None]  # None: the flat plane's row
    painted += [False]
    for folder in args.views:
        rows = [[] for _ in rowed]
        for ref in find_views(folder, targets=False):
            view = load_view(ref.shape_dir, ref.view)
            flat = flat_coloured(view) if args.silhouette_only else None
            got = [view_errors(net, flat if p else view) for net, p in zip(rowed, painted)]
            if any(g is None for g in got):
                continue
            for k, g in enumerate(got):
                rows[k].append(g)
        first = np.array([r[0] for r in rows[0]])
        for w, r in zip(names + [FLAT_PLANE], rows):
            lines.append(f"| {Path(folder).name} | {w} | " + " | ".join(summary_cells(r, first, w == FLAT_PLANE)) + " |")
    text = "\n".join(lines) + "\n"
    print(text, end="")
    if args.out:
        Path(args.out).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
