#!/usr/bin/env python3
"""Choose the regular-shape stage's tolerance, ``geometry.primitive_snap``, on training-split views.

For each view the weights run once (GenRe, the view's true mask), the mesh is
made at the weights' level (with the weights' other mesh settings) and scored
(CD, 1,024 points, ``genre eval``'s metric); then every family of
:mod:`genre_backend.geometry.primitives` is fitted to the visible surface (the
masked predicted depth), the mask's outline and the mesh, and the best fit
(the highest silhouette IoU with the mask) is scored too.  A tolerance
``tau`` snaps the views whose fit's disagreement (1 − IoU, or twice the
mesh's mean distance to it over its diagonal, whichever is larger:
``PrimitiveFit.disagreement``) is at most ``tau``, so
one pass gives the mean CD at every ``tau`` of the grid.

The rule (``results/decisions.md``, fixed before any fit ran): the
views are one seeded view of each of ``--shapes`` seeded shapes of each
``--views`` folder named with ``:all`` omitted, and views 0 to ``--first-views``
− 1 of every shape of a folder named ``FOLDER:all``; the tolerance is the grid
value (0 = off first) with the lowest mean CD over all of them.  These are
training views: a test view never chooses the tolerance.

    .venv/bin/python scripts/primitive_snap.py --weights default \\
        --views $GENRE_HOME/views/product $GENRE_HOME/views/product_primitives:all \\
        --csv $GENRE_HOME/results/product/primitive_snap/per_view.csv --json $GENRE_HOME/results/product/primitive_snap.json
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from genre_backend.arguments import add_jobs, add_seed, add_weights  # noqa: E402
from genre_backend.geometry.primitives import MESH_FACTOR  # noqa: E402

GRID = [0.0] + [round(0.01 * k, 2) for k in range(1, 21)]  # off, then 0.01 … 0.20 (PrimitiveFit.disagreement)
COLUMNS = ["key", "folder", "shape", "view", "cd_mesh", "cd_fit", "family", "residual", "mesh_residual", "seconds"]


def pick_views(folders: list[str], manifest_path, shapes: int, first_views: int, seed: int):
    """[(folder label, EvalView)] by the rule in the module docstring; the shapes' manifest group is product-train."""
    from training.eval.protocol import find_eval_views

    manifest = json.loads(Path(manifest_path).read_text())
    rng = np.random.default_rng(seed)
    out = []
    for spec in folders:
        root, _, every = spec.partition(":")
        views = find_eval_views([Path(root)], manifest, ("product-train",))
        by_shape: dict[str, list] = {}
        for v in views:
            by_shape.setdefault(v.shape_dir.name, []).append(v)
        names = sorted(by_shape)
        if every == "all":
            chosen = [v for n in names for v in sorted(by_shape[n], key=lambda v: v.view)[:first_views]]
        else:
            picked = sorted(rng.choice(len(names), min(shapes, len(names)), replace=False))
            chosen = [by_shape[names[i]][int(rng.integers(len(by_shape[names[i]])))] for i in picked]
        out += [(Path(root).name, v) for v in chosen]
    return out


_W: dict = {}


def _init(weights: str) -> None:
    import torch

    from genre_backend.nets.model import load_model
    from training.eval.runner import Truth

    torch.set_num_threads(1)
    _W.update(model=load_model(weights).eval(), truth=Truth())


def _score(item) -> dict:
    import torch

    from genre_backend.geometry.mesh_voxels import grid_to_surface
    from genre_backend.nets.outputs import View
    from genre_backend.inference.options import MeshOptions
    from genre_backend.geometry.metrics import CloudScorer, sample_surface
    from genre_backend.geometry.primitives import POINTS, fit_primitive, visible_points
    from training.data.dataset import ViewDataset, ViewRef
    from training.eval.protocol import POINTS_SMALL
    from training.eval.runner import mesh_metrics

    folder, view = item
    model, truth = _W["model"], _W["truth"]
    g = model.config.geometry
    t0 = time.perf_counter()
    s = ViewDataset([ViewRef(view.shape_dir, view.view)], model.config).sample(0, None)
    with torch.no_grad():
        out = model(s["rgb"][None], mask=s["mask"][None], mirror=model.config.geometry.test_time_mirror)
    gt, _ = truth.posed(view)
    target = CloudScorer(gt[:POINTS_SMALL], gt)
    prob = torch.sigmoid(out.logits)[0, 0]
    # the weights' pits sealed first, as genre eval does before it fits (the record's step; neither carve nor fusion)
    prob = MeshOptions(silhouette_carve=False, visible_fusion=False).resolved(g).shape_grid(prob, View(s["mask"], None, model.config.camera), g)
    v, f = grid_to_surface(prob, g.default_threshold, g)
    rec = {"key": view.key, "folder": folder, "shape": view.shape_dir.name, "view": view.view}
    rec["cd_mesh"] = mesh_metrics(v, f, target)["cd1k"]
    if len(f) == 0:
        rec.update(cd_fit=rec["cd_mesh"], family="", residual=float("inf"), mesh_residual=float("inf"))
    else:
        d = out.masked_depth[0]
        fit = fit_primitive(visible_points(d, model.config.camera), sample_surface(v, f, POINTS).numpy(), depth=d, camera=model.config.camera)
        rec.update(cd_fit=mesh_metrics(*fit.mesh(), target)["cd1k"], family=fit.family, residual=fit.residual, mesh_residual=fit.mesh_residual)
    rec["seconds"] = time.perf_counter() - t0
    return rec


def choose(records: list[dict], grid=GRID) -> tuple[float, dict[float, float]]:
    """(the tolerance with the lowest mean CD, {tolerance: mean CD}); ties go to the smaller tolerance."""
    cd_mesh = np.array([float(r["cd_mesh"]) for r in records])
    cd_fit = np.array([float(r["cd_fit"]) for r in records])
    res = np.array([max(float(r["residual"]), MESH_FACTOR * float(r["mesh_residual"])) for r in records])
    means = {tau: float(np.where(res <= tau, cd_fit, cd_mesh).mean()) if tau > 0 else float(cd_mesh.mean()) for tau in grid}
    best = min(grid, key=lambda tau: (round(means[tau], 6), tau))
    return best, means


def family_table(records: list[dict], manifest_path) -> dict:
    """{primitive kind (the manifest's ``extra.subkind``): Counter of fitted families} over the views of procedural primitives."""
    from collections import Counter

    entries = {e["id"]: e for e in json.loads(Path(manifest_path).read_text())["shapes"]}
    out: dict[str, Counter] = {}
    for r in records:
        entry = entries.get(r["shape"], {})
        if entry.get("class") == "primitive" and r["family"]:
            out.setdefault(entry["extra"]["subkind"], Counter())[r["family"]] += 1
    return dict(sorted(out.items()))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_weights(p, default="default", help="'default', 'protocol' or a weights file (its mesh settings are used)")
    p.add_argument("--views", nargs="+", required=True, help="view folders; FOLDER:all takes the first views of every shape")
    p.add_argument("--manifest", default=None, help="the corpus manifest (default: $GENRE_HOME/corpus/manifest.json)")
    p.add_argument("--shapes", type=int, default=300, help="seeded shapes per folder (one seeded view each)")
    p.add_argument("--first-views", type=int, default=3, help="views per shape of a FOLDER:all")
    add_seed(p)
    add_jobs(p, default=2, help="worker processes (one thread each)")
    p.add_argument("--csv", required=True, help="per-view figures (appended; views already there are not redone)")
    p.add_argument("--json", default=None, help="also write the choice and the means here")
    args = p.parse_args(argv)
    from genre_backend.weights_file import resolve_weights
    from training.data.corpus import data_dir

    try:
        weights = str(resolve_weights(args.weights))
    except ValueError as exc:
        p.error(str(exc))
    manifest = args.manifest or data_dir() / "corpus" / "manifest.json"
    items = pick_views(args.views, manifest, args.shapes, args.first_views, args.seed)
    path = Path(args.csv)
    path.parent.mkdir(parents=True, exist_ok=True)
    done = {}
    if path.is_file():
        with path.open() as fh:
            done = {r["key"]: r for r in csv.DictReader(fh)}
    todo = [it for it in items if it[1].key not in done]
    print(f"{len(items)} views ({len(done)} already scored); weights {weights}", file=sys.stderr)
    new_file = not path.is_file()
    with path.open("a", newline="") as fh:
        w = csv.DictWriter(fh, COLUMNS)
        if new_file:
            w.writeheader()
        if todo:
            import multiprocessing as mp

            with mp.get_context("spawn").Pool(args.jobs, _init, (weights,)) as pool:
                for i, rec in enumerate(pool.imap(_score, todo, chunksize=4)):
                    w.writerow(rec)
                    fh.flush()
                    done[rec["key"]] = rec
                    if (i + 1) % 25 == 0:
                        print(f"  {i + 1}/{len(todo)} views", file=sys.stderr)
    records = [done[it[1].key] for it in items]
    best, means = choose(records)
    folders = sorted({r["folder"] for r in records})
    counts = ", ".join(f"{f}: {sum(r['folder'] == f for r in records)}" for f in folders)
    print(f"{len(records)} training-split views ({counts}); weights {weights}")
    print("| tolerance | snapped | mean CD | " + " | ".join(f"{f} CD" for f in folders) + " |")
    print("| ---: | ---: | ---: | " + " | ".join("---:" for _ in folders) + " |")
    for tau in GRID:
        snapped = sum(max(float(r["residual"]), MESH_FACTOR * float(r["mesh_residual"])) <= tau for r in records) if tau else 0
        row = [f"{tau:.2f}" if tau else "off", str(snapped), f"{means[tau]:.4f}"]
        for f in folders:
            sub = [r for r in records if r["folder"] == f]
            row.append(f"{choose(sub, [tau])[1][tau]:.4f}")
        print("| " + " | ".join(row) + " |")
    print(f"chosen (lowest mean CD): primitive_snap = {best}")
    kinds = family_table(records, manifest)
    if kinds:
        print("\nThe family fitted (the highest silhouette IoU) to the views of each kind of procedural primitive:")
        for kind, counts in kinds.items():
            print(f"  {kind} ({sum(counts.values())} views): " + ", ".join(f"{f} {n}" for f, n in counts.most_common()))
    if args.json:
        Path(args.json).write_text(json.dumps({"weights": weights, "views": len(records), "chosen": best,
                                               "means": {str(k): v for k, v in means.items()}}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
