#!/usr/bin/env python3
"""What fusing the visible surface into the refiner's grid does: ``geometry.visible_fusion``.

A refiner's grid can have a gap in the face the camera sees: the artist gets a
mesh with a hole through its front, or a part the photo plainly shows left
out, and the textured mesh no longer covers the object's mask (the real-photo
check in ``tests/backend/output/test_colour.py`` asks for 90 %).  The depth map sees that
face.  ``visible_fusion`` finds the object's pixels whose ray meets nothing
(with ``--pit-voxels P`` also those that meet the grid more than P voxels
behind the depth map: a pit, the front missing) and adds the masked depth
map's own surface there, moved onto the grid's front,
``max(grid, its distance target)``, before the mesh is made
(:func:`genre_backend.geometry.visible_front.fuse_visible_surface`).  (Fusing the
depth map's surface over the whole object instead cost CD on the seen-test
views: +2.5 % for the protocol weights, +4.4 % for the default ones; filling
the holes alone, +0.1 % and +1.8 %.)

For each view this script runs the weights once and makes the mesh at the
weights' level with and without fusion, as ``genre reconstruct`` makes it
(carved when the weights carve; hole sealing; small parts dropped):

* CD (1,024 points, ``genre eval``'s metric, on the mesh ``genre eval`` scores);
* coverage: the share of the mask's pixels the mesh covers through the
  view's camera (:func:`genre_backend.output.colour.zbuffer`), and the
  share of views below 90 %.

The rule that picks the setting (fixed before measuring; seen-test views only,
like every setting of the protocol): fusion is on when, on the seen-test
views, it does not raise the mean CD by more than ``CD_TOLERANCE`` (1 %); its
purpose is the front faces, not the Chamfer distance, and 1 % is within what
re-rendering the same views moves it (0.1 %) by an order of magnitude less than
the differences between weights.  The other groups are reported, never used
to choose.

The sealing of the narrow wells in the grid's own front (*Seal Pits*) is compared by ``genre eval --sweep``
(``docs/lab/reconstruct-settings.md``); its rule (``results/decisions.md``) picks the largest width whose CD rises
by at most 1 % on the product test split.

    .venv/bin/python scripts/visible_fusion.py --weights protocol --views $GENRE_HOME/views/eval --groups test
    .venv/bin/python scripts/visible_fusion.py --weights default --views $GENRE_HOME/views/product_eval \
        --groups product-test --choose-group all
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from genre_backend.arguments import add_weights  # noqa: E402
from genre_backend.geometry.visible_front import fuse_visible_surface  # noqa: E402
from genre_backend.geometry.metrics import CloudScorer  # noqa: E402
from genre_backend.geometry.voxels import silhouette_ramp  # noqa: E402
from genre_backend.output.colour import zbuffer  # noqa: E402
from genre_backend.inference.reconstruct import mesh_of_probability  # noqa: E402
from genre_backend.weights_file import resolve_weights  # noqa: E402
from training.eval.protocol import POINTS_SMALL, load_setting_views  # noqa: E402
from training.eval.runner import Truth, score_grid  # noqa: E402

SEEN_TEST = "test"  # the manifest group of the seen classes' test shapes
CD_TOLERANCE = 0.01
COVERED = 0.9  # the real-photo check's bar


def coverage(prob: torch.Tensor, mask: torch.Tensor, level: float, geometry, camera) -> float:
    """The share of ``mask`` (S, S) the mesh ``genre reconstruct`` would make of ``prob`` covers."""
    _, v, f, clean = mesh_of_probability(prob, level, geometry, geometry.hole_closing)
    if clean is None:
        return 0.0
    hit = np.isfinite(zbuffer(v, f, camera, mask.shape[-1]))
    m = mask.numpy()
    return float((hit & m).sum() / max(m.sum(), 1))


def choose(seen: dict[bool, dict[str, float]]) -> bool:
    """The rule: on when the seen-test mean CD with fusion is at most (1 + CD_TOLERANCE) × without."""
    return bool(seen[True]["cd"] <= (1.0 + CD_TOLERANCE) * seen[False]["cd"])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_weights(p, default="default")
    p.add_argument("--views", required=True, help="evaluation views (genre data render + targets)")
    p.add_argument("--manifest", default=None, help="the corpus manifest (default: $GENRE_HOME/corpus/manifest.json)")
    p.add_argument("--groups", default="test", help="manifest groups of the views to score (comma-separated)")
    p.add_argument("--max-views", type=int, default=None, help="at most this many views of each shape (default: all)")
    p.add_argument("--level", type=float, default=None, help="isosurface level (default: the weights')")
    p.add_argument("--pit-voxels", type=float, default=None, metavar="P",
                   help="also fill pits deeper than P voxels behind the depth map (default: holes only, as the setting does)")
    p.add_argument("--choose-group", default="seen-test (chooses)",
                   help="the group whose mean chooses (default: the seen-test views; 'all' for the product test split)")
    p.add_argument("--json", default=None, help="also write the figures here")
    args = p.parse_args(argv)
    try:
        weights = resolve_weights(args.weights)
    except ValueError as exc:
        p.error(str(exc))
    from training.eval.product import group_of_shape

    try:
        model, views, data, entries = load_setting_views(weights, args.views, args.manifest, tuple(args.groups.split(",")), args.max_views)
    except ValueError as exc:
        p.error(str(exc))
    geometry, camera = model.config.geometry, model.config.camera
    if geometry.target != "distance":
        p.error(f"{weights}: the visible surface is fused only into distance-target grids (these weights: {geometry.target})")
    level = geometry.default_threshold if args.level is None else args.level
    variants = {"off": lambda prob, depth, mask: prob,
                "fused": lambda prob, depth, mask: fuse_visible_surface(prob, depth, camera, geometry, level, pit_voxels=args.pit_voxels)}
    truth = Truth()
    figures: dict[str, dict[str, dict[str, list[float]]]] = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    with torch.no_grad():
        for i, view in enumerate(views):
            s = data.sample(i, None)
            gt, _ = truth.posed(view)
            target = CloudScorer(gt[:POINTS_SMALL], gt)
            mask = s["mask"]
            out = model(s["rgb"][None], mask=mask[None], mirror=model.config.geometry.test_time_mirror)
            prob = torch.sigmoid(out.logits)[0, 0]
            if geometry.silhouette_carve:
                prob = torch.minimum(prob, silhouette_ramp(mask[None], camera, geometry.voxel_size)[0, 0])
            groups = list(group_of_shape(entries.get(view.shape_dir.name, {"class": view.cls})))
            if SEEN_TEST in view.groups:
                groups.append("seen-test (chooses)")
            for name, variant in variants.items():
                grid = variant(prob, out.masked_depth[0], mask.bool())
                m = score_grid(grid, [level], target, geometry)[level]
                c = coverage(grid, mask, level, geometry, camera)
                for g in groups:
                    figures[g][name]["cd"].append(m["cd1k"])
                    figures[g][name]["coverage"].append(c)
                    figures[g][name]["under"].append(float(c < COVERED))
            if (i + 1) % 25 == 0:
                print(f"  {i + 1}/{len(views)} views", file=sys.stderr)
    result = {"weights": str(weights), "level": level, "views": len(views), "pit_voxels": args.pit_voxels, "groups": {}}
    what = "filled: holes" + (f" and pits deeper than {args.pit_voxels:g} voxels" if args.pit_voxels is not None else " only")
    print(f"{len(views)} views of {args.views} ({args.groups}); weights {weights}; level {level:.2f}; "
          f"hole_closing {geometry.hole_closing}; carve {geometry.silhouette_carve}; {what}")
    names = list(variants)
    print("| group | views | " + " | ".join(f"CD {n}" for n in names) + " | " + " | ".join(f"coverage {n}" for n in names)
          + " | " + " | ".join(f"views < 90 % {n}" for n in names) + " |")
    print("| --- | ---: |" + " ---: |" * (3 * len(names)))
    for g in sorted(figures, key=lambda g: (g != "all", g)):
        per = {name: {k: float(np.mean(v)) for k, v in figures[g][name].items()} for name in names}
        result["groups"][g] = per
        n = len(figures[g]["off"]["cd"])
        print(f"| {g} | {n} | " + " | ".join(f"{per[v]['cd']:.4f}" for v in names) + " | "
              + " | ".join(f"{100 * per[v]['coverage']:.1f} %" for v in names) + " | "
              + " | ".join(f"{100 * per[v]['under']:.0f} %" for v in names) + " |")
    chooser = result["groups"].get(args.choose_group)
    if chooser:
        chosen = choose({False: chooser["off"], True: chooser["fused"]})
        print(f"chosen on {args.choose_group} (on when CD rises by <= {100 * CD_TOLERANCE:.0f} %): visible_fusion = {chosen}")
        result["chosen"] = chosen
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
