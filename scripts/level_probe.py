#!/usr/bin/env python3
"""Can the mesh's level be read per view from the refiner's own grid?  A probe, not a setting.

``genre eval --levels`` scores each view at several levels; the best level per view, chosen *with the truth*, is
an upper bound on any rule that picks a level per view. This script asks how much of it a rule reading only the
grid gets: for each view it computes eleven features of the weights' grid (as ``genre eval`` makes it, the mirror
image averaged in): the log-ratios of the grid's volume above 0.30 ... 0.60 to its volume above the chosen level,
the share of the grid between 0.3 and 0.6, the mean of its columns' maxima along the view, the mask's area and the
depth's relief; a ridge regression maps them to each level's CD relative to the chosen level's, and the level with
the lowest prediction is picked. It reports 5-fold cross-validation on the training views, then, with the model
fitted on all of them, the test views once (the rule of ``results/decisions.md``, 2026-12-01 21:26).

    H=$GENRE_HOME
    genre eval --data $H/views/fresh88_s300 --groups product-train --max-views 1 --rows GenRe \\
        --levels 0.35,0.4,0.45,0.5,0.55 --weights genre_backend/weights/default.safetensors --no-figures --out TRAIN
    genre eval --data $H/views/product_eval --groups product-test --rows GenRe \\
        --levels 0.35,0.4,0.45,0.5,0.55 --weights genre_backend/weights/default.safetensors --no-figures --out TEST
    .venv/bin/python scripts/level_probe.py --weights genre_backend/weights/default.safetensors \\
        --train-views $H/views/fresh88_s300 --train-scores TRAIN --test-views $H/views/product_eval --test-scores TEST

(``views/fresh88_s300``: one folder link for each of 300 product-train shapes of ``views/fresh88`` drawn with
``random.seed(27); random.sample(sorted(shapes), 300)``.)
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np
import torch

from genre_backend.arguments import add_weights
from genre_backend.weights_file import resolve_weights

LEVELS = ("0.35", "0.40", "0.45", "0.50", "0.55")
BASE = LEVELS.index("0.45")
VOLUME_LEVELS = (0.3, 0.35, 0.4, 0.45, 0.5, 0.55, 0.6)


def features(weights: str, views_dir: str, group: str) -> dict[str, list[float]]:
    """{view key: its features} for one view of each shape of ``group`` under ``views_dir``."""
    from training.eval.protocol import load_setting_views

    model, views, data, _ = load_setting_views(weights, views_dir, None, (group,), max_views=1)
    out = {}
    with torch.no_grad():
        for i, view in enumerate(views):
            sample = data[i]
            nets = model(sample["rgb"][None], mask=sample["mask"][None], mirror=True)
            prob = torch.sigmoid(nets.logits)[0, 0].float()
            volume = {t: float((prob > t).float().mean()) for t in VOLUME_LEVELS}
            row = [float(np.log((volume[t] + 1e-6) / (volume[0.45] + 1e-6))) for t in VOLUME_LEVELS]
            row.append(float(((prob > 0.3) & (prob < 0.6)).float().sum() / (prob > 0.3).float().sum().clamp(min=1)))
            row.append(float(prob.amax(dim=2).mean()))
            mask = sample["mask"]
            depth = nets.masked_depth[0][mask]
            width = float(mask.float().sum().sqrt()) / mask.shape[0]
            row.append(float(mask.float().mean()))
            row.append(float(depth.std()) / (width + 1e-6) if depth.numel() > 1 else 0.0)
            out[view.key] = row
    return out


def scores(eval_dir: str) -> dict[str, list[float]]:
    """{view key: GenRe's CD at each of LEVELS} from ``genre eval``'s per_view.csv."""
    with open(Path(eval_dir) / "per_view.csv", newline="") as f:
        return {r["key"]: [float(r[f"cd1k@{t}"]) for t in LEVELS] for r in csv.DictReader(f) if r["row"] == "GenRe"}


def fit(x: np.ndarray, y: np.ndarray, lam: float):
    """Ridge regression of each level's CD relative to BASE's on standardised features; returns a predictor."""
    mu, sd = x.mean(0), x.std(0) + 1e-9
    z = np.c_[np.ones(len(x)), (x - mu) / sd]
    b = np.linalg.solve(z.T @ z + lam * np.eye(z.shape[1]), z.T @ (y / y[:, [BASE]] - 1))
    return lambda xn: np.c_[np.ones(len(xn)), (xn - mu) / sd] @ b


def choose(predicted: np.ndarray) -> np.ndarray:
    """The level index with the lowest predicted relative CD (BASE's is 0 by definition)."""
    p = predicted.copy()
    p[:, BASE] = 0.0
    return p.argmin(1)


def joined(feats: dict, cds: dict) -> tuple[np.ndarray, np.ndarray]:
    keys = sorted(set(feats) & set(cds))
    return np.array([feats[k] for k in keys]), np.array([cds[k] for k in keys])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_weights(p, default="default")
    p.add_argument("--train-views", required=True)
    p.add_argument("--train-scores", required=True, help="genre eval --levels output on the training views")
    p.add_argument("--train-group", default="product-train")
    p.add_argument("--test-views")
    p.add_argument("--test-scores")
    p.add_argument("--test-group", default="product-test")
    p.add_argument("--lam", type=float, default=10.0, help="the ridge penalty applied to the test (default 10)")
    args = p.parse_args()
    args.weights = str(resolve_weights(args.weights))
    torch.set_num_threads(1)
    xt, yt = joined(features(args.weights, args.train_views, args.train_group), scores(args.train_scores))
    base = yt[:, BASE].mean()
    print(f"{len(xt)} training views: CD {base:.5f} at {LEVELS[BASE]}, {yt.min(1).mean():.5f} with the best level per view")
    folds = np.random.default_rng(0).integers(0, 5, len(xt))
    for lam in (1.0, 10.0, 100.0):
        picked = np.zeros(len(xt), int)
        for k in range(5):
            picked[folds == k] = choose(fit(xt[folds != k], yt[folds != k], lam)(xt[folds == k]))
        cd = yt[np.arange(len(yt)), picked].mean()
        print(f"  ridge {lam:g}, 5-fold: {cd:.5f} ({(cd / base - 1) * 100:+.2f} %), {np.mean(picked != BASE):.0%} moved")
    if args.test_views and args.test_scores:
        xe, ye = joined(features(args.weights, args.test_views, args.test_group), scores(args.test_scores))
        picked = choose(fit(xt, yt, args.lam)(xe))
        cd, base = ye[np.arange(len(ye)), picked].mean(), ye[:, BASE].mean()
        print(f"{len(xe)} test views: CD {base:.5f} at {LEVELS[BASE]}, {ye.min(1).mean():.5f} with the best level per view")
        lower = int((ye[np.arange(len(ye)), picked] < ye[:, BASE]).sum())
        print(f"{len(xe)} test views, ridge {args.lam:g}: {cd:.5f} against {base:.5f} ({(cd / base - 1) * 100:+.2f} %), "
              f"lower on {lower}, {np.mean(picked != BASE):.0%} moved")


if __name__ == "__main__":
    main()
