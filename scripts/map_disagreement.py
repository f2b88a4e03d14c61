#!/usr/bin/env python3
"""Can the pipeline tell where its full spherical map is wrong?  A probe for a confidence input to the refiner.

On the hidden side (pixels where the partial map has no hit and both the truth and the predicted full map hit) it
compares the map's error, ``|map − truth|``, with two disagreements the pipeline could compute without the truth:

* the map against the map of the mirror image, reflected back (``genre_backend.geometry.spherical.mirror_sph``);
* the map against a second inpainting net's map of the same partial map (``--other``).

It prints, pooled over pixels, Spearman's correlation and the AUROC with which each disagreement picks out the
worst quarter of the errors; and, over views, the correlation of the mean disagreement with the mean error.
With ``--learn STEPS`` it also trains a small convolutional head (five dilated 3 × 3 layers of 32 channels) for
STEPS steps of 8 views to predict the log error from the maps (partial, full, mirrored, the second net's, the two
disagreements, the pixel's place) on the views of three quarters of the shapes, and scores it on the other quarter.
``results/decisions.md`` (2026-12-01, the twenty-seventh session, (e)):

    .venv/bin/python scripts/map_disagreement.py --weights genre_backend/weights/default.safetensors \\
        --other $GENRE_HOME/cand/S50.safetensors --views $GENRE_HOME/views/fresh88 --group product-train --count 120
    .venv/bin/python scripts/map_disagreement.py ... --count 480 --learn 800          # (f): the learned head
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from scipy.stats import mannwhitneyu, spearmanr

from genre_backend.arguments import add_weights
from genre_backend.weights_file import resolve_weights

LOG_EPS = 1e-3  # the floor under the errors whose log the head predicts


def auroc(positive: np.ndarray, score: np.ndarray) -> float:
    """The probability that a positive's score exceeds a negative's (ties half), by the Mann–Whitney U."""
    return float(mannwhitneyu(score[positive], score[~positive]).statistic / (positive.sum() * (~positive).sum()))


def learned_head(inputs: np.ndarray, errors: np.ndarray, hidden: np.ndarray, shapes: np.ndarray, steps: int):
    """Train the head on three quarters of the shapes; return (held-out predictions, their errors, their mirror
    disagreements), pooled over the held-out views' hidden-side pixels."""
    rng = np.random.default_rng(0)
    torch.manual_seed(0)
    names = sorted(set(shapes.tolist()))
    rng.shuffle(names)
    held = np.isin(shapes, names[: len(names) // 4])
    n, size = len(inputs), inputs.shape[-1]
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, size), torch.linspace(-1, 1, size), indexing="ij")
    x = torch.cat([torch.tensor(inputs, dtype=torch.float32), yy.expand(n, 1, size, size), xx.expand(n, 1, size, size)], 1)
    y, m = torch.tensor(np.log(errors + LOG_EPS), dtype=torch.float32), torch.tensor(hidden)
    layers, width = [], x.shape[1]
    for dilation in (1, 2, 4, 8, 1):
        layers += [torch.nn.Conv2d(width, 32, 3, padding=dilation, dilation=dilation), torch.nn.ReLU()]
        width = 32
    net = torch.nn.Sequential(*layers, torch.nn.Conv2d(32, 1, 1))
    opt = torch.optim.Adam(net.parameters(), 2e-3)
    train = np.where(~held)[0]
    for _ in range(steps):
        b = torch.tensor(rng.choice(train, 8))
        if not m[b].any():
            continue
        loss = ((net(x[b])[:, 0] - y[b]) ** 2)[m[b]].mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    test = torch.tensor(np.where(held)[0])
    with torch.no_grad():
        pred = net(x[test])[:, 0][m[test]].numpy()
    return pred, errors[held][hidden[held]], inputs[held][:, 5][hidden[held]], int(held.sum())


def main() -> None:
    from genre_backend.geometry.spherical import mirror_sph
    from genre_backend.nets.model import load_model
    from training.eval.protocol import load_setting_views

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_weights(p, default="default")
    p.add_argument("--other", required=True, help="weights whose inpainting net is the second opinion")
    p.add_argument("--views", required=True)
    p.add_argument("--group", default="product-train")
    p.add_argument("--count", type=int, default=120, help="views, spread evenly over the folder's order")
    p.add_argument("--learn", type=int, default=0, metavar="STEPS", help="also train and score a learned head")
    args = p.parse_args()
    args.weights = str(resolve_weights(args.weights))
    torch.set_num_threads(1 if not args.learn else 2)
    model, views, data, _ = load_setting_views(args.weights, args.views, None, (args.group,))
    other = load_model(args.other).eval()
    nohit = model.config.geometry.sph_nohit_min
    inputs, errors, hiddens, shapes = [], [], [], []
    with torch.no_grad():
        for i in np.linspace(0, len(data) - 1, min(args.count, len(data))).astype(int).tolist():
            s = data[i]
            rgb, mask, truth = s["rgb"][None], s["mask"][None], s["full_sph"][None]
            out = model(rgb, mask=mask)
            part, full = out.partial_sph, out.full_sph
            mirrored = mirror_sph(model(torch.flip(rgb, dims=(-1,)), mask=torch.flip(mask, dims=(-1,))).full_sph)
            second = other.full_sph(part)
            seen = (part < nohit).float()
            inputs.append(torch.cat([part.clamp(max=1) * seen, seen, full, mirrored, second, (full - mirrored).abs(),
                                     (full - second).abs()]).numpy())
            errors.append((full - truth).abs()[0].numpy())
            hiddens.append(((part >= nohit) & (truth < nohit) & (full < nohit))[0].numpy())
            shapes.append(views[i].shape_dir.name)
    inputs, errors, hiddens, shapes = np.stack(inputs), np.stack(errors), np.stack(hiddens), np.array(shapes)
    some = hiddens.any(axis=(1, 2))
    e = errors[hiddens]
    worst = e > np.quantile(e, 0.75)
    print(f"{int(some.sum())} views of {len(data)}, {e.size} hidden-side pixels; error median {np.median(e):.4f}, "
          f"mean {e.mean():.4f}")
    mean_err = np.array([errors[k][hiddens[k]].mean() for k in np.where(some)[0]])
    for name, channel in (("mirror image", 5), ("other net", 6)):
        d = inputs[:, channel][hiddens]
        per_view = np.array([inputs[k, channel][hiddens[k]].mean() for k in np.where(some)[0]])
        print(f"  disagreement with the {name}: pixel Spearman {spearmanr(d, e)[0]:.3f}, AUROC for the worst quarter "
              f"{auroc(worst, d):.3f}; per view Spearman {spearmanr(per_view, mean_err)[0]:.3f}")
    if args.learn:
        pred, held_err, held_mirror, n_held = learned_head(inputs, errors, hiddens, shapes, args.learn)
        worst = held_err > np.quantile(held_err, 0.75)
        print(f"  learned head ({args.learn} steps) on {n_held} held-out views of other shapes ({held_err.size} pixels): "
              f"Spearman {spearmanr(pred, held_err)[0]:.3f}, AUROC {auroc(worst, pred):.3f}; the mirror disagreement "
              f"there {spearmanr(held_mirror, held_err)[0]:.3f}, {auroc(worst, held_mirror):.3f}")


if __name__ == "__main__":
    main()
