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
* ``seen up ÷ width``: the seen surface alone (the depth map inside the render's silhouette, back-projected into
  the object's frame) measured as ``genre eval`` measures a mesh: its height along the object's up over its widest
  spread across it (1st–99th percentiles), the prediction's over the truth's, median over views.  For a flat thing
  seen from above this is where a domed or mis-tilted surface shows, which the relief inside the eroded outline,
  offset removed, hardly does (1 = as thin as the truth).

With ``--plain-backdrop`` every pixel outside the render's silhouette is painted the neutral grey first, as
``genre reconstruct`` does when the weights' ``plain_backdrop`` is on (the renders here are composited over
photos).

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
from genre_backend.config import CameraConfig
from genre_backend.frame import depth_to_points
from genre_backend.nets.model import load_model
from genre_backend.photo.preprocess import on_plain_backdrop
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


def on_backdrop(view: dict) -> dict:
    """The view with every pixel outside its silhouette the neutral grey (``plain_backdrop`` on)."""
    rgb = torch.from_numpy(view["rgb"]).permute(2, 0, 1).float() / 255.0
    grey = on_plain_backdrop(rgb, torch.from_numpy(view["mask"] > 0.5))
    return dict(view, rgb=np.round(grey.permute(1, 2, 0).numpy() * 255.0).astype(np.uint8))


def predict(net, view: dict) -> np.ndarray:
    """The depth net's (S, S) depth map of the view's picture."""
    rgb = torch.from_numpy(view["rgb"]).permute(2, 0, 1)[None].float() / 255.0
    with torch.no_grad():
        return net.depth_net(rgb)["depth"][0].numpy()


def up_over_width(depth: np.ndarray, view: dict, camera: CameraConfig | None = None) -> float:
    """The seen surface's height along the object's up (+z of its frame) over its widest spread across it (x or y),
    1st–99th percentiles, from a depth map inside the view's silhouette."""
    points = depth_to_points(torch.from_numpy(depth.astype(np.float32))[None], camera or CameraConfig())[0].numpy()[view["mask"] > 0.5]
    obj = points @ np.asarray(view["camera"]["rotation_cam_to_obj"], dtype=np.float64).T
    spread = lambda x: float(np.subtract(*np.percentile(x, [99, 1])))  # noqa: E731
    return spread(obj[:, 2]) / max(spread(obj[:, 0]), spread(obj[:, 1]), 1e-9)


def seen_up_ratio(net, view: dict, depth: np.ndarray | None = None) -> float:
    """The prediction's seen up ÷ width over the truth's (:func:`up_over_width`); ``depth``: the net's map of the
    view when already made."""
    pred = predict(net, view) if depth is None else depth
    return up_over_width(pred, view) / max(up_over_width(view["depth"], view), 1e-9)


def view_errors(net, view: dict, erode: int = 2, depth: np.ndarray | None = None) -> tuple[float, float, float, float] | None:
    """(relief MAE, relief IQR ÷ the truth's, |offset|, the true relief's IQR) of one view, or None when the eroded silhouette is too small.

    ``net`` None: the flat plane, a constant depth (relief MAE: the true relief's mean deviation from its median;
    ratio 0; its offset is not a prediction, so NaN).  ``depth``: the net's map of the view when already made.
    """
    inner = binary_erosion(view["mask"] > 0.5, iterations=erode)
    if inner.sum() < 20:
        return None
    true = view["depth"][inner]
    iqr = lambda x: float(np.subtract(*np.percentile(x, [75, 25])))  # noqa: E731
    if net is None:
        return float(np.mean(np.abs(true - np.median(true)))), 0.0, float("nan"), iqr(true)
    pred = (predict(net, view) if depth is None else depth)[inner]
    err = pred - true
    offset = float(np.median(err))
    return float(np.mean(np.abs(err - offset))), iqr(pred) / max(iqr(true), 1e-6), abs(offset), iqr(true)


def summary_cells(errors: list[tuple[float, float, float, float]], first: np.ndarray, flat_plane: bool = False,
                  up: list[float] | None = None) -> list[str]:
    """One weights' row over a folder from its views' :func:`view_errors`: n, relief MAE median and mean, relief ÷
    truth (median), offset (median; "–" for the flat plane), views better than ``first`` (the first weights' relief
    MAEs), *follows*: Spearman's correlation of the predicted relief's IQR with the true one's ("–" for the flat
    plane, which has none), and the median of ``up``, the views' :func:`seen_up_ratio` ("–" without)."""
    mae, ratio, offset, true_iqr = (np.array([x[i] for x in errors]) for i in range(4))
    follows = "–" if flat_plane else f"{spearmanr(ratio * true_iqr, true_iqr).statistic:.2f}"
    return [f"{len(errors)}", f"{np.median(mae):.4f}", f"{np.mean(mae):.4f}", f"{np.median(ratio):.2f}",
            "–" if flat_plane else f"{np.median(offset):.4f}", f"{int((mae < first).sum())} / {len(errors)}", follows,
            "–" if not up else f"{np.median(up):.2f}"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--views", nargs="+", required=True, help="folders of rendered views")
    add_weights(parser, action="append", required=True, help="weights (name or file); repeat to compare")
    parser.add_argument("--silhouette-only", action="store_true",
                        help="add a row per weights: the net on the picture with the object painted one colour")
    parser.add_argument("--plain-backdrop", action="store_true",
                        help="paint every pixel outside the silhouette the neutral grey first (plain_backdrop on)")
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
             "better than the first | follows | seen up ÷ width, × truth (median) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    rowed = nets + [None]  # None: the flat plane's row
    painted += [False]
    for folder in args.views:
        rows, ups = [[] for _ in rowed], [[] for _ in rowed]
        for ref in find_views(folder, targets=False):
            view = load_view(ref.shape_dir, ref.view)
            if args.plain_backdrop:
                view = on_backdrop(view)
            flat = flat_coloured(view) if args.silhouette_only else None
            seen = [flat if p else view for p in painted]
            maps = [None if net is None else predict(net, v) for net, v in zip(rowed, seen)]  # each net once a view
            got = [view_errors(net, v, depth=d) for net, v, d in zip(rowed, seen, maps)]
            if any(g is None for g in got):
                continue
            for k, (g, net, v, d) in enumerate(zip(got, rowed, seen, maps)):
                rows[k].append(g)
                if net is not None:
                    ups[k].append(seen_up_ratio(net, v, depth=d))
        first = np.array([r[0] for r in rows[0]])
        for w, r, u in zip(names + [FLAT_PLANE], rows, ups):
            cells = summary_cells(r, first, w == FLAT_PLANE, u)
            lines.append(f"| {Path(folder).name} | {w} | " + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"
    print(text, end="")
    if args.out:
        Path(args.out).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
