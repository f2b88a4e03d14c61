#!/usr/bin/env python3
"""How many holes GenRe's meshes have, and what sealing them costs: ``geometry.hole_closing``.

A blurry distance-target prediction has gaps in its tube around the surface,
through which the tube's inner sheet joins the outer one: the artist sees a
hole into the object (one hole: a pit; two: a tunnel).  ``hole_closing = k``
seals gaps up to about 2·k voxels across before the inside is filled
(:func:`genre_backend.geometry.mesh_voxels.fill_enclosed`).  For each view
this script runs the weights once (their narrow pits sealed first when they
say so, as ``genre reconstruct`` does) and scores the mesh at the weights' level
for every k: CD (1,024 points, ``genre eval``'s metric), the share of closed
meshes (every part genus 0: :func:`training.eval.runner.is_closed`: no
tunnel; a single pit keeps genus 0 and is not counted).

The rule that picks k (fixed before measuring; seen-test views only, like
every setting of the protocol): the smallest k whose closed share on the
seen-test views reaches ``CLOSED_SHARE`` (0.9); when none does, the k with
the highest closed share (ties: the smaller k).  The other groups are
reported, never used to choose.

    .venv/bin/python scripts/hole_closing.py --weights default --views $GENRE_HOME/views/product_eval --groups product-test
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from genre_backend.geometry.metrics import CloudScorer  # noqa: E402
from genre_backend.inference.net_outputs import View  # noqa: E402
from genre_backend.inference.options import MeshOptions  # noqa: E402
from genre_backend.weights_file import resolve_weights  # noqa: E402
from training.eval.protocol import POINTS_SMALL, load_setting_views  # noqa: E402
from training.eval.runner import Truth, score_grid  # noqa: E402
from training.eval.statistics import CLOSED_SHARE, choose_hole_closing  # noqa: E402

SEEN_TEST = "test"  # the manifest group of the seen classes' test shapes


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--weights", default="default", help="'default', 'protocol' or a weights file")
    p.add_argument("--views", required=True, help="evaluation views (genre data render + targets)")
    p.add_argument("--manifest", default=None, help="the corpus manifest (default: $GENRE_HOME/corpus/manifest.json)")
    p.add_argument("--groups", default="product-test", help="manifest groups of the views to score (comma-separated)")
    p.add_argument("--closings", default="0,1,2,3", help="hole_closing values to compare (voxels)")
    p.add_argument("--level", type=float, default=None, help="isosurface level (default: the weights')")
    p.add_argument("--json", default=None, help="also write the figures here")
    args = p.parse_args(argv)
    try:
        weights = resolve_weights(args.weights)
        closings = [int(k) for k in args.closings.split(",")]
    except ValueError as exc:
        p.error(str(exc))
    from training.eval.product import group_of_shape

    try:
        model, views, data, entries = load_setting_views(weights, args.views, args.manifest, tuple(args.groups.split(",")), None)
    except ValueError as exc:
        p.error(str(exc))
    geometry = model.config.geometry
    level = geometry.default_threshold if args.level is None else args.level
    truth = Truth()
    # the weights' narrow pits sealed, as reconstruction and genre eval do (the record's step; neither carve nor fusion)
    pits_only = MeshOptions(threshold=level, silhouette_carve=False, visible_fusion=False).resolved(geometry)
    # per group, per k: lists of cd, closed
    figures: dict[str, dict[int, dict[str, list[float]]]] = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    with torch.no_grad():
        for i, view in enumerate(views):
            s = data.sample(i, None)
            gt, _ = truth.posed(view)
            target = CloudScorer(gt[:POINTS_SMALL], gt)
            prob = torch.sigmoid(model(s["rgb"][None], mask=s["mask"][None], mirror=model.config.geometry.test_time_mirror)["logits"])[0, 0]
            prob = pits_only.shape_grid(prob, View(s["mask"], None, model.config.camera), geometry)  # before the hole sealing
            groups = list(group_of_shape(entries.get(view.shape_dir.name, {"class": view.cls})))
            if SEEN_TEST in view.groups:
                groups.append("seen-test (chooses k)")
            for k in closings:
                m = score_grid(prob, [level], target, dataclasses.replace(geometry, hole_closing=k))[level]
                for g in groups:
                    figures[g][k]["cd"].append(m["cd1k"])
                    figures[g][k]["closed"].append(m["closed"])
            if (i + 1) % 25 == 0:
                print(f"  {i + 1}/{len(views)} views", file=sys.stderr)
    out = {"weights": str(weights), "level": level, "views": len(views), "groups": {}}
    print(f"{len(views)} views of {args.views} ({args.groups}); weights {weights}; level {level:.2f}")
    print("| group | views | " + " | ".join(f"k={k}: CD / closed" for k in closings) + " |")
    print("| --- | ---: | " + " | ".join("---" for _ in closings) + " |")
    for g in sorted(figures, key=lambda g: (g != "all", g)):
        per_k = {k: {name: float(np.mean(vals)) for name, vals in figures[g][k].items()} for k in closings}
        out["groups"][g] = per_k
        n = len(figures[g][closings[0]]["cd"])
        print(f"| {g} | {n} | " + " | ".join(f"{per_k[k]['cd']:.4f} / {100 * per_k[k]['closed']:.0f} %" for k in closings) + " |")
    seen = out["groups"].get("seen-test (chooses k)")
    if seen:
        chosen = choose_hole_closing({k: seen[k]["closed"] for k in closings})
        out["chosen"] = chosen
        print(f"chosen on the seen-test views (smallest k with >= {100 * CLOSED_SHARE:.0f} % closed, else the most closed): "
              f"hole_closing = {chosen}")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
