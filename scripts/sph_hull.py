#!/usr/bin/env python3
"""What trimming the refiner's grid to its spherical map's hull does: ``geometry.sph_hull_carve``.

A full spherical map's pixel of direction ``d`` holds the *largest* radius at
which the ray ``t·d`` from the view frame's origin meets the surface, so no
surface point lies beyond it: the map bounds the object (its radial hull,
:func:`genre_backend.geometry.spherical.sph_hull_ramp`).  The refiner does not
always stay inside it: given the *true* map of a plate lying flat it still
makes a slab several times too thick (GenRe-SphOracle on the flat-from-above
group, ``results/flat_from_above.md``).  ``min(probability, ramp)`` trims what
the refiner puts beyond its own map's surface.

For each view this script runs the weights once (their mirror setting) and
scores the mesh at the weights' level without the trim and with it at each
``--spreads`` (how many map pixels the hull is widened by), the steps after it
as ``genre reconstruct`` takes them (outline carve, visible fusion, pit
sealing; hole closing): mean CD (1,024 points, ``genre eval``'s metric) and,
where the views know the object's up (the flat group), the median ratio of
the mesh's depth ÷ width to the truth's.  ``--oracle`` scores
GenRe-SphOracle too (the true depth and the true full map in, the hull of
the true map).

The rule (``results/decisions.md``, 2026-11-30 17:29 UTC, fixed before any
measure): the spread with the lowest mean CD on the training shapes' views
(``views/product_train_eval``); the setting on when, on the product test, the
mean CD with it is no higher than without and the primitives' not higher by
more than 1 % (``genre eval --sweep sph_hull_carve=...``).

    .venv/bin/python scripts/sph_hull.py --weights default --views $GENRE_HOME/views/product_train_eval \
        --groups product-train --spreads 0,1,2
    .venv/bin/python scripts/sph_hull.py --weights default --views $GENRE_HOME/views/flat_eval \
        --groups flat-from-above --manifest $GENRE_HOME/flat_test/manifest.json --oracle
    .venv/bin/python scripts/sph_hull.py --weights $GENRE_HOME/cand/S50.safetensors --views $GENRE_HOME/views/fresh88 \
        --groups product-train --max-views 1 --every 10 --spreads 2 --offsets 0,2,4 --nohit-open

The trim where the trimmed shape reads flat (the gate of ``results/decisions.md``, 2026-12-02 05:16 UTC):
``--per-view CSV`` writes each view's CD and two features of each trim, ``thin`` (the trimmed grid's occupied voxel
centres' :func:`~genre_backend.geometry.metrics.thinnest_depth_over_width`) and ``kept`` (its occupied voxels over
the untrimmed grid's); ``--choose-gate`` reads such files of the choosing views and prints every candidate gate's
mean CD (the mean of the files' means), the lowest first; ``--gate FEATURE:TAU`` scores one gate on such files.

    .venv/bin/python scripts/sph_hull.py --views $GENRE_HOME/views/fresh88 --groups product-train --max-views 1 \
        --every 10 --spreads 2 --per-view fresh88.csv        # and views/fresh_prim, views/thin_gate (--manifest)
    .venv/bin/python scripts/sph_hull.py --choose-gate fresh88.csv,fresh_prim.csv thin_gate.csv
    .venv/bin/python scripts/sph_hull.py --choose-gate product_eval.csv flat_eval.csv --gate thin:0.29
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from genre_backend.arguments import add_weights  # noqa: E402
from genre_backend.geometry.metrics import CloudScorer, grid_thinness  # noqa: E402
from genre_backend.geometry.spherical import sph_hull_ramp  # noqa: E402
from genre_backend.inference.options import MeshOptions  # noqa: E402
from genre_backend.nets.outputs import View  # noqa: E402
from genre_backend.weights_file import resolve_weights  # noqa: E402
from training.eval.protocol import POINTS_SMALL, load_setting_views  # noqa: E402
from training.eval.runner import Truth, score_grid  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_weights(p, default="default")
    p.add_argument("--views", default=None, help="evaluation views (genre data render + targets); required but with "
                   "--choose-gate")
    p.add_argument("--manifest", default=None, help="the corpus manifest (default: $GENRE_HOME/corpus/manifest.json)")
    p.add_argument("--groups", default="product-test", help="manifest groups of the views to score (comma-separated)")
    p.add_argument("--max-views", type=int, default=None, help="at most this many views of each shape (default: all)")
    p.add_argument("--level", type=float, default=None, help="isosurface level (default: the weights')")
    p.add_argument("--spreads", default="0,1,2", help="the hull's widenings to score, in map pixels (comma-separated)")
    p.add_argument("--offsets", default="0", help="voxels the hull is moved outward, scored at every spread "
                   "(comma-separated; geometry.sph_hull_offset)")
    p.add_argument("--nohit-open", action="store_true", help="read the map's no-hit pixels as unknown (the hull "
                   "open there: no trim along them) instead of as radius 0")
    p.add_argument("--every", type=int, default=1, help="score every K-th view only (a spread-out subset of many)")
    p.add_argument("--oracle", action="store_true", help="also GenRe-SphOracle (the true depth and full map)")
    p.add_argument("--json", default=None, help="also write the figures here")
    p.add_argument("--per-view", default=None, metavar="CSV", help="also write each view's CD, ratio and the gate's "
                   "features (thin, kept) of every trim here (GenRe row)")
    p.add_argument("--choose-gate", nargs="+", default=None, metavar="SET", help="score no weights: read --per-view "
                   "files (a set: comma-separated files pooled by view) and print every candidate gate's mean CD")
    p.add_argument("--gate", default=None, metavar="FEATURE:TAU", help="with --choose-gate's files: this gate only")
    p.add_argument("--trim", default="spread 2", help="the trim the gate switches (a --per-view file's trim name)")
    args = p.parse_args(argv)
    if args.choose_gate:
        try:
            return report_gates([[Path(f) for f in group.split(",")] for group in args.choose_gate], args.trim,
                                args.gate)
        except (OSError, ValueError, KeyError) as exc:
            p.error(str(exc))
    if args.views is None:
        p.error("--views is required (but with --choose-gate)")
    try:
        weights = resolve_weights(args.weights)
        spreads = [int(s) for s in args.spreads.split(",")]
        offsets = [float(o) for o in args.offsets.split(",")]
        if args.every < 1:
            raise ValueError(f"--every: expected a count >= 1, got {args.every}")
        model, views, data, _ = load_setting_views(weights, args.views, args.manifest, tuple(args.groups.split(",")),
                                                  args.max_views)
    except ValueError as exc:
        p.error(str(exc))
    picked = range(0, len(views), args.every)
    geometry, camera = model.config.geometry, model.config.camera
    opts = MeshOptions(sph_hull_carve=False).resolved(geometry)
    level = opts.threshold if args.level is None else args.level
    opts = dataclasses.replace(opts, threshold=level)
    rows = ["GenRe"] + (["GenRe-SphOracle"] if args.oracle else [])
    trims = {f"spread {s}" + (f" offset {o:g}" if o else ""): (s, o) for s in spreads for o in offsets}
    names = ["off", *trims]
    truth = Truth()
    cd: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    ratio: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    per_view: list[dict] = []
    with torch.no_grad():
        for n, i in enumerate(picked):
            view = views[i]
            s = data.sample(i, None)
            gt, _ = truth.posed(view)
            target = CloudScorer(gt[:POINTS_SMALL], gt, up=truth.up(view))
            mask = s["mask"][None]
            runs = {"GenRe": model(s["rgb"][None], mask=mask, mirror=opts.test_time_mirror)}
            if args.oracle:
                runs["GenRe-SphOracle"] = model(s["rgb"][None], mask=mask, depth=s["depth"][None],
                                                full_sph=s["full_sph"][None], mirror=opts.test_time_mirror)
            for row, out in runs.items():
                prob = torch.sigmoid(out.logits)[0, 0]
                v = View(out.mask[0], out.masked_depth[0], camera)
                sph = out.full_sph
                if args.nohit_open:  # the cube's corner radius: nothing of the grid lies beyond it
                    sph = torch.where(sph >= geometry.sph_nohit_min, torch.full_like(sph, 1.0 - math.sqrt(3) / 2), sph)
                occupied_off = None
                for name in names:
                    grid = prob
                    if name != "off":
                        spread, offset = trims[name]
                        grid = torch.minimum(prob, sph_hull_ramp(sph, prob.shape[-1], geometry.sph_nohit_min,
                                                                 spread=spread, offset=offset)[0, 0])
                    shaped = opts.shape_grid(grid, v, geometry)
                    m = score_grid(shaped, [level], target, geometry)[level]
                    cd[row][name].append(m["cd1k"])
                    r = math.nan
                    if math.isfinite(target.dw_true) and math.isfinite(m.get("dw", math.nan)):
                        r = m["dw"] / target.dw_true
                        ratio[row][name].append(r)
                    if args.per_view and row == "GenRe":
                        thin, occupied = grid_thinness(shaped, level)
                        occupied_off = occupied if name == "off" else occupied_off
                        per_view.append({"key": f"{view.shape_dir.name}/{view.view}", "trim": name, "cd": m["cd1k"],
                                         "ratio": r, "thin": thin, "kept": occupied / max(occupied_off, 1)})
            if (n + 1) % 25 == 0:
                print(f"  {n + 1}/{len(picked)} views", file=sys.stderr)
    print(f"{len(picked)} views of {args.views} ({args.groups}); weights {weights}; level {level:.2f}; "
          f"fusion {opts.visible_fusion}; pits {opts.pit_sealing}; mirror {opts.test_time_mirror}"
          + ("; no-hit pixels open" if args.nohit_open else ""))
    print("| row | trim | CD (mean) | change | lower on | depth ÷ width over the truth's (median) |")
    print("| --- | --- | ---: | ---: | ---: | ---: |")
    result = {"weights": str(weights), "views": len(picked), "level": level, "rows": {}}
    for row in rows:
        base = np.array(cd[row]["off"])
        for name in names:
            c = np.array(cd[row][name])
            r = np.median(ratio[row][name]) if ratio[row][name] else math.nan
            result["rows"].setdefault(row, {})[name] = {"cd": float(c.mean()), "ratio": float(r)}
            print(f"| {row} | {name} | {c.mean():.5f} | {100 * (c.mean() / base.mean() - 1):+.2f} % | "
                  f"{int((c < base).sum())}/{len(c)} | {r:.2f} |")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    if args.per_view:
        with open(args.per_view, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(per_view[0]), lineterminator="\n")
            w.writeheader()
            w.writerows(per_view)
    return 0


GATE_FEATURES = ("thin", "kept")  # results/decisions.md, 2026-12-02 05:16 UTC
GATE_QUANTILES = tuple(q / 100 for q in range(5, 100, 5))


def _read_set(files: list[Path], trim: str) -> dict[str, dict[str, float]]:
    """One choosing set: per view key, its CD off and trimmed and the trim's features."""
    views: dict[str, dict[str, float]] = {}
    for file in files:
        with open(file, newline="") as f:
            for row in csv.DictReader(f):
                key = f"{file.stem}:{row['key']}"
                if row["trim"] == "off":
                    views.setdefault(key, {})["off"] = float(row["cd"])
                    views[key]["ratio_off"] = float(row["ratio"])
                elif row["trim"] == trim:
                    v = views.setdefault(key, {})
                    v.update(trim=float(row["cd"]), ratio_trim=float(row["ratio"]), thin=float(row["thin"]),
                             kept=float(row["kept"]))
    complete = {k: v for k, v in views.items() if "off" in v and "trim" in v}
    if not complete:
        raise ValueError(f"no view with both 'off' and {trim!r} in {', '.join(map(str, files))}")
    return complete


def _gated(views: dict[str, dict[str, float]], feature: str | None, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """Per view: the gated CD and ratio (trimmed where ``feature`` < ``tau``; a nan feature never trims;
    ``feature`` None: ``tau`` +inf always trims, -inf never)."""
    cds, ratios = [], []
    for v in views.values():
        on = (tau > 0) if feature is None else (math.isfinite(v[feature]) and v[feature] < tau)
        cds.append(v["trim"] if on else v["off"])
        ratios.append(v["ratio_trim"] if on else v["ratio_off"])
    return np.array(cds), np.array(ratios)


def report_gates(groups: list[list[Path]], trim: str, only: str | None) -> int:
    """Every candidate gate's mean CD over the sets (the mean of their means), lowest first; or ``only``'s
    figures on each set.  Prints a markdown table."""
    sets = [_read_set(files, trim) for files in groups]
    names = [",".join(f.stem for f in files) for files in groups]
    if only is not None:
        feature, _, tau = only.partition(":")
        if feature not in GATE_FEATURES:
            raise ValueError(f"--gate: the feature must be one of {', '.join(GATE_FEATURES)}, got {feature!r}")
        print(f"gate {feature} < {float(tau):g} on {trim}")
        print("| set | views | off | gated | change | lower on / higher on | trimmed | ratio off / gated (median) |")
        print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
        for name, views in zip(names, sets):
            off = np.array([v["off"] for v in views.values()])
            ratio_off = np.array([v["ratio_off"] for v in views.values()])
            gated, ratio = _gated(views, feature, float(tau))
            on = int((gated != off).sum())
            print(f"| {name} | {len(off)} | {off.mean():.5f} | {gated.mean():.5f} | {100 * (gated.mean() / off.mean() - 1):+.2f} % "
                  f"| {int((gated < off).sum())} / {int((gated > off).sum())} | {on} | "
                  f"{np.nanmedian(ratio_off) if np.isfinite(ratio_off).any() else math.nan:.2f} / "
                  f"{np.nanmedian(ratio) if np.isfinite(ratio).any() else math.nan:.2f} |")
        return 0
    pooled = {f: np.array([v[f] for views in sets for v in views.values() if math.isfinite(v[f])]) for f in GATE_FEATURES}
    candidates = [("never", None, -math.inf), ("always", None, math.inf)]
    for feature in GATE_FEATURES:
        for q in GATE_QUANTILES:
            candidates.append((f"{feature} < q{round(100 * q)}", feature, float(np.quantile(pooled[feature], q))))
    scored = []
    for label, feature, tau in candidates:
        means = [_gated(views, feature, tau)[0].mean() for views in sets]
        scored.append((float(np.mean(means)), label, tau, means))
    scored.sort(key=lambda s: s[0])
    print(f"{trim}: {' | '.join(f'{n} ({len(s)} views)' for n, s in zip(names, sets))}")
    print("| gate | τ | mean of the sets' means | " + " | ".join(names) + " |")
    print("| --- | ---: | ---: |" + " ---: |" * len(names))
    for score, label, tau, means in scored:
        print(f"| {label} | {tau:.4f} | {score:.5f} | " + " | ".join(f"{m:.5f}" for m in means) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
