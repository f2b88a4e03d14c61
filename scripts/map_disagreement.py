#!/usr/bin/env python3
"""Can the pipeline tell where its full spherical map is wrong?  A probe for a confidence input to the refiner.

On the hidden side (pixels where the partial map has no hit and both the truth and the predicted full map hit) it
compares the map's error, ``|map − truth|``, with two disagreements the pipeline could compute without the truth:

* the map against the map of the mirror image, reflected back (``genre_backend.geometry.spherical.mirror_sph``);
* the map against a second inpainting net's map of the same partial map (``--other``).

It prints, pooled over pixels, Spearman's correlation and the AUROC with which each disagreement picks out the
worst quarter of the errors; and, over views, the correlation of the mean disagreement with the mean error.
``results/decisions.md`` (2026-12-01, the twenty-seventh session, (e)):

    .venv/bin/python scripts/map_disagreement.py --weights genre_backend/weights/default.safetensors \\
        --other $GENRE_HOME/cand/S50.safetensors --views $GENRE_HOME/views/fresh88 --group product-train --count 120
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from scipy.stats import mannwhitneyu, spearmanr


def auroc(positive: np.ndarray, score: np.ndarray) -> float:
    """The probability that a positive's score exceeds a negative's (ties half), by the Mann–Whitney U."""
    return float(mannwhitneyu(score[positive], score[~positive]).statistic / (positive.sum() * (~positive).sum()))


def main() -> None:
    from genre_backend.geometry.spherical import mirror_sph
    from genre_backend.nets.model import load_model
    from training.eval.protocol import load_setting_views

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--weights", required=True)
    p.add_argument("--other", required=True, help="weights whose inpainting net is the second opinion")
    p.add_argument("--views", required=True)
    p.add_argument("--group", default="product-train")
    p.add_argument("--count", type=int, default=120, help="views, spread evenly over the folder's order")
    args = p.parse_args()
    torch.set_num_threads(1)
    model, _, data, _ = load_setting_views(args.weights, args.views, None, (args.group,))
    other = load_model(args.other).eval()
    nohit = model.config.geometry.sph_nohit_min
    err, d_mirror, d_other, per_view = [], [], [], []
    with torch.no_grad():
        for i in np.linspace(0, len(data) - 1, min(args.count, len(data))).astype(int).tolist():
            s = data[i]
            rgb, mask, truth = s["rgb"][None], s["mask"][None], s["full_sph"][None]
            out = model(rgb, mask=mask)
            full = out.full_sph
            mirrored = mirror_sph(model(torch.flip(rgb, dims=(-1,)), mask=torch.flip(mask, dims=(-1,))).full_sph)
            second = other.full_sph(out.partial_sph)
            hidden = (out.partial_sph >= nohit) & (truth < nohit) & (full < nohit)
            if not hidden.any():
                continue
            e, m, o = ((full - x).abs()[hidden].numpy() for x in (truth, mirrored, second))
            err.append(e)
            d_mirror.append(m)
            d_other.append(o)
            per_view.append((e.mean(), m.mean(), o.mean()))
    e = np.concatenate(err)
    worst = e > np.quantile(e, 0.75)
    v = np.array(per_view)
    print(f"{len(per_view)} views of {len(data)}, {e.size} hidden-side pixels; error median {np.median(e):.4f}, "
          f"mean {e.mean():.4f}")
    for name, d, col in (("mirror image", np.concatenate(d_mirror), 1), ("other net", np.concatenate(d_other), 2)):
        print(f"  disagreement with the {name}: pixel Spearman {spearmanr(d, e)[0]:.3f}, AUROC for the worst quarter "
              f"{auroc(worst, d):.3f}; per view Spearman {spearmanr(v[:, col], v[:, 0])[0]:.3f}")


if __name__ == "__main__":
    main()
