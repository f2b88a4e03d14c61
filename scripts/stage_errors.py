#!/usr/bin/env python3
"""Where a GenRe model loses accuracy, stage by stage, on seen-test views.

For each view (one per shape, a seeded sample of ``--views`` of them) it
scores, with ``genre eval``'s metric (CD at 1,024 points, both clouds
normalised):

* ``true target, marching cubes``  the refiner's target itself (the shell or the
                                   truncated distance, as the weights' config names it) at
                                   each threshold: the best that representation can do
* ``true spherical map, projected`` the true full map → voxels, every hit voxel kept
* ``GenRe spherical map, projected`` GenRe's inpainted map → voxels, likewise
* ``refiner <- true depth + true map`` (GenRe-SphOracle), ``refiner <- true depth``
  (GenRe-Oracle) and GenRe, each at several isosurface thresholds;
* with ``--completion FILE`` (a ``genre train completion`` run's weights), the
  3D Completion baseline from the true depth and from its own predicted depth
  at the same thresholds: whether a better depth would widen GenRe's margin
  over it, or lift both alike; and, for GenRe and (with ``--completion``) the
  baseline, the predicted depth less its offset from the truth (the view's
  median error): the object's distance against the surface's shape;
* GenRe with the refiner's spherical channel emptied (zeros): how much the
  refiner leans on the inpainted map at all; GenRe trimmed to the outline
  (``geometry.silhouette_carve``; the plain GenRe row is never trimmed,
  whatever the weights say);
* the depth net's error inside the true mask, taken apart: its median absolute
  value, what is left after removing the view's median offset (the object's
  distance), and after removing the best-fitting plane (offset and tilt:
  the surface turned as a whole), all in world units (a voxel is 1/N); and
  the correlation of that error (less its offset) with the image's
  brightness, per view: whether the net reads shading as depth;
* the inpainting alone: the partial maps of GenRe's and of the true depth
  projected, the inpainted map of the true depth's partial map projected,
  and the maps' own errors (MSE against the true full map on the partial
  map's hits and elsewhere; the spread of the hit values; the share of pixels
  whose hit/no-hit agrees with the true map, and the MSE on the unseen pixels
  that both call hits; the shares of no-hit pixels in the true map and of hits
  in the inpainted one; for the hit head, the true depth's inpainted map
  projected at several hit-probability levels).

With weights that average each view with its mirror image
(``geometry.test_time_mirror``), the GenRe model's rows that go through the
refiner to a mesh (the two oracles, GenRe, the depth offset removed) are
averaged likewise; the emptied spherical channel, the projected maps, the
depth's errors and the 3D Completion rows are the view's own pass.

Seen classes only: what it shows is used to change the model, and the
unseen classes must stay untouched by such choices.  ``--groups train`` (on
the training views) scores the same rows on views the nets were fitted on:
a gap to seen-test says a stage does not generalise, no gap that it cannot fit.

    .venv/bin/python scripts/stage_errors.py --weights protocol --views ~/.cache/genre/views/eval --views-count 8

``--weights`` defaults to the shipped research weights, ``protocol`` (seen classes only); a
training run's file (``$GENRE_HOME/runs/default/joint/best.safetensors``) works too.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from genre_backend.arguments import add_seed, add_weights  # noqa: E402
from genre_backend.weights_file import resolve_weights, weights_extra  # noqa: E402
from genre_backend.nets.model import load_model  # noqa: E402
from training.data.dataset import ViewDataset, ViewRef  # noqa: E402
from genre_backend.geometry.metrics import CloudScorer  # noqa: E402
from training.eval.protocol import POINTS_SMALL, sample_seen_test_views  # noqa: E402
from training.eval.runner import Truth, score_grid  # noqa: E402
from genre_backend.geometry.spherical import crop_sph, pad_sph  # noqa: E402
from genre_backend.geometry.voxels import silhouette_ramp  # noqa: E402

HIT = 0.05  # a projected-map voxel counts as surface above this (hit voxels hold 0.13–1)


def depth_error_parts(pred: torch.Tensor, true: torch.Tensor, mask: torch.Tensor,
                      brightness: torch.Tensor | None = None) -> dict[str, float]:
    """Median |pred − true| over the mask (S, S) pixels with a true depth: as it is, less its median, less its least-squares plane.

    ``brightness`` (S, S): the image's brightness; adds the correlation (Pearson, over the same pixels) of the
    error less its median with it: positive when the net puts bright pixels too far and dark ones too near,
    negative the other way (shading read as depth).
    """
    m = mask & (true > 0)
    err = (pred - true)[m].double()
    yy, xx = torch.nonzero(m, as_tuple=True)
    n = m.shape[0]
    a = torch.stack([torch.ones_like(err), xx.double() / n, yy.double() / n], 1)
    plane = torch.linalg.lstsq(a, err[:, None]).solution[:, 0]
    parts = {
        "depth |error| (median)": float(err.abs().median()),
        "depth |error| less its offset": float((err - err.median()).abs().median()),
        "depth |error| less its plane": float((err - a @ plane).abs().median()),
    }
    if brightness is not None:
        b = brightness[m].double()
        e = err - err.median()
        parts["depth error vs brightness (corr.)"] = float(torch.corrcoef(torch.stack([e, b]))[0, 1]) \
            if e.std() > 0 and b.std() > 0 else 0.0
    return parts


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_weights(p, default="protocol",
                   help="'protocol' (default: the shipped research weights, seen classes only) or a weights file")
    p.add_argument("--views", required=True, help="evaluation views (genre data render + targets of the test split)")
    p.add_argument("--manifest", default=None, help="the corpus manifest (default: $GENRE_HOME/corpus/manifest.json)")
    p.add_argument("--views-count", type=int, default=8)
    p.add_argument("--thresholds", default="0.5,0.7,0.9")
    add_seed(p)
    p.add_argument("--hit-levels", default="0.1,0.2,0.3,0.5",
                   help="the hit head's decision levels (geometry.sph_hit_probability) to sweep: the inpainted map, from "
                        "the true depth and from GenRe's own, projected at each (hit-head weights only)")
    p.add_argument("--groups", default="test", choices=("test", "product-test", "train"),
                   help="which views: 'test' (seen-test, for the protocol weights), 'product-test' (the product "
                        "model's held-out split, e.g. $GENRE_HOME/views/primitives_eval) or 'train' (the seen "
                        "classes' training views, $GENRE_HOME/views/default: fitting against generalising)")
    p.add_argument("--completion", default=None,
                   help="a 3D Completion baseline's weights (OUT/completion/best.safetensors): adds its rows")
    args = p.parse_args(argv)
    try:
        weights = resolve_weights(args.weights)
    except ValueError as exc:
        p.error(str(exc))
    if weights_extra(weights).get("model") == "default":
        print(f"warning: {weights} are the product weights ('default'); research figures come from 'protocol'", file=sys.stderr)
    model = load_model(weights)
    mirror = model.config.geometry.test_time_mirror  # the rows that reach a mesh, as genre eval and reconstruct make it
    completion = None
    if args.completion:
        from training.learn.baselines import load_baseline
        completion = load_baseline(args.completion, "completion")
    thresholds = [float(t) for t in args.thresholds.split(",")]
    hit_levels = [float(h) for h in args.hit_levels.split(",")]
    if not all(0.0 < h < 1.0 for h in hit_levels):
        p.error(f"--hit-levels: every level must be in (0, 1), got {args.hit_levels}")
    try:
        views = sample_seen_test_views(Path(args.views), Path(args.manifest) if args.manifest else None,
                                       args.views_count, args.seed, groups=(args.groups,))
    except FileNotFoundError as exc:
        p.error(str(exc))
    data = ViewDataset([ViewRef(v.shape_dir, v.view) for v in views], model.config)
    truth, scores, target_fraction, maps = Truth(), {}, [], {}

    def add(name: str, per_t: dict) -> None:
        for t, m in per_t.items():
            scores.setdefault(name, {}).setdefault(t, []).append(m["cd1k"])

    with torch.no_grad():
        for i, view in enumerate(views):
            s = data.sample(i, None)
            gt, _ = truth.posed(view)
            target = CloudScorer(gt[:POINTS_SMALL], gt)
            rgb, mask, depth, full = s["rgb"][None], s["mask"][None], s["depth"][None], s["full_sph"][None]
            target_fraction.append(float((s["voxels"] > 0).float().mean()))
            add(f"true {model.config.geometry.target}, its surface", score_grid(s["voxels"], thresholds, target, model.config.geometry))
            sph_oracle = model(rgb, mask=mask, depth=depth, full_sph=full, mirror=mirror)
            add("true spherical map, projected", score_grid(sph_oracle.vox_sph[0, 0], [HIT], target))
            add("refiner <- true depth + true map", score_grid(torch.sigmoid(sph_oracle.logits)[0, 0], thresholds, target, model.config.geometry))
            oracle = model(rgb, mask=mask, depth=depth, mirror=mirror)
            add("refiner <- true depth", score_grid(torch.sigmoid(oracle.logits)[0, 0], thresholds, target, model.config.geometry))
            genre = model(rgb, mask=mask, mirror=mirror)
            # how much the refiner leans on the spherical channel: the same depth voxels, the spherical ones emptied
            emptied = model.refine(torch.zeros_like(genre.vox_sph), genre.vox_depth)
            add("GenRe, spherical channel emptied", score_grid(torch.sigmoid(emptied)[0, 0], thresholds, target, model.config.geometry))
            # the predicted depth less its offset from the truth (the view's median error inside the mask): is the
            # object's distance, which one photo leaves ambiguous, what GenRe loses on, or the surface's shape?
            valid = mask & (depth > 0)
            offset = (genre.depth - depth)[valid].median()
            shifted = genre.depth - offset
            add("GenRe, depth offset removed", score_grid(torch.sigmoid(model(rgb, mask=mask, depth=shifted, mirror=mirror).logits)[0, 0],
                                                          thresholds, target, model.config.geometry))
            if completion is not None:
                own = completion.depth_net(rgb)["depth"]  # the baseline's own (frozen) depth net
                for name, d in (("3D Completion <- true depth", depth),
                                ("3D Completion, depth offset removed", own - (own - depth)[valid].median()),
                                ("3D Completion", own)):
                    logits = completion(rgb, mask=mask, depth=d)["logits"]
                    add(name, score_grid(torch.sigmoid(logits)[0, 0], thresholds, target, model.config.geometry))
            for name, value in depth_error_parts(genre.depth[0], depth[0], mask[0], brightness=rgb[0].mean(0)).items():
                maps.setdefault(name, []).append(value)
            add("GenRe spherical map, projected", score_grid(genre.vox_sph[0, 0], [HIT], target))
            # the inpainting alone: the partial maps it starts from, and what it makes of the true depth's
            partial = model.partial_sph(genre.masked_depth)
            partial_true = model.partial_sph(depth)
            add("partial map (GenRe depth), projected", score_grid(model.sph_voxels(partial)[0, 0], [HIT], target))
            add("partial map (true depth), projected", score_grid(model.sph_voxels(partial_true)[0, 0], [HIT], target))
            add("inpainted from true depth, projected", score_grid(model.sph_voxels(model.inpaint_net(partial_true))[0, 0], [HIT], target))
            if model.config.network.inpaint_head == "hit":  # the hit head's decision level (geometry.sph_hit_probability)
                g = model.config.geometry
                for source, part in (("true depth", partial_true), ("GenRe depth", partial)):
                    parts = model.inpaint_net.forward_parts(pad_sph(part[:, None], g.sph_pad))
                    for p_min in hit_levels:
                        swept = crop_sph(model.inpaint_net.compose(parts["hit_logits"], parts["radius"], p_min), g.sph_pad)[:, 0]
                        add(f"  inpainted from {source}, hit where p > {p_min}",
                            score_grid(model.sph_voxels(swept)[0, 0], [HIT], target))
            seen = partial < 1
            maps.setdefault("GenRe partial map: MSE on its hits", []).append(float(((partial - full) ** 2)[seen].mean()))
            maps.setdefault("inpainted map: MSE on those pixels", []).append(float(((genre.full_sph - full) ** 2)[seen].mean()))
            maps.setdefault("inpainted map: MSE elsewhere", []).append(float(((genre.full_sph - full) ** 2)[~seen].mean()))
            maps.setdefault("inpainted map: std of its hits", []).append(float(genre.full_sph[genre.full_sph < 0.9999].std()))
            maps.setdefault("true map: std of its hits", []).append(float(full[full < 0.9999].std()))
            maps.setdefault("true map: share of no-hit pixels", []).append(float((full >= 0.9999).float().mean()))
            maps.setdefault("inpainted map: share of hit pixels", []).append(float((genre.full_sph < 0.9999).float().mean()))
            pred_hit, true_hit = genre.full_sph < 0.9999, full < 0.9999
            maps.setdefault("inpainted map: hit/no-hit as the true map", []).append(float((pred_hit == true_hit).float().mean()))
            both = pred_hit & true_hit & ~seen
            if both.any():  # (a view whose unseen part the map calls empty has none)
                maps.setdefault("inpainted map: MSE on unseen true hits", []).append(float(((genre.full_sph - full) ** 2)[both].mean()))
            add("GenRe", score_grid(torch.sigmoid(genre.logits)[0, 0], thresholds, target, model.config.geometry))
            ramp = silhouette_ramp(mask, model.config.camera, model.config.geometry.voxel_size)[0, 0]
            add("GenRe, trimmed to the outline", score_grid(torch.minimum(torch.sigmoid(genre.logits)[0, 0], ramp),
                                                            thresholds, target, model.config.geometry))
    print(f"{len(views)} {'seen-test' if args.groups == 'test' else args.groups} views; mean CD (1,024 points) per threshold; "
          f"the true {model.config.geometry.target} target is non-zero in {100 * np.mean(target_fraction):.1f} % of the grid")
    for name, per_t in scores.items():
        print(f"{name:36s} " + "  ".join(f"t={t:.2f}: {np.mean(v):.4f}" for t, v in per_t.items()))
    for name, values in maps.items():
        print(f"{name:36s} {np.mean(values):.5f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
