"""Where a reconstruction's Chamfer distance is lost: each view's CD split by the side of the shape the camera sees.

For every evaluation view and every row, the mesh ``genre eval`` scores (the weights' own steps after the
networks, at one level) is sampled as ``genre eval`` samples it (1,024 points, seed 0) against the same 1,024
stored true points, both normalised the one way (:func:`~genre_backend.geometry.metrics.normalize_points`).
Each point is *seen* when the camera sees it on its own mesh (:func:`~genre_backend.geometry.raster.seen_from_camera`,
a 256² z-buffer, 0.02 of the objects' diagonal), and the CD splits exactly into four parts
(:func:`~genre_backend.geometry.metrics.chamfer_parts`):

* ``pred seen`` / ``pred hidden``: the prediction's points on the side it shows / hides, their distances to the truth
  (each summed and divided by all 1,024: the two add up to the prediction-to-truth term);
* ``truth seen`` / ``truth hidden``: the same for the true points, their distances to the prediction.

The four parts of a view add up to its CD (``genre eval``'s ``cd1k`` at that level; ``tests/training/eval/test_evaluate.py`` checks it), so
their means say which side of the shape the mean CD is lost on.  ``Noise floor`` is the truth resampled, split the
same way (the best any row can do on each side).  Rows as ``genre eval``'s (``GenRe``, ``GenRe-Oracle``: true depth,
``GenRe-SphOracle``: true depth and full map).

Results go to ``OUT/per_view.csv`` (one line a view, weights and row; a run resumes where it stopped, and several
invocations with other ``--weights`` add to the same folder) and ``OUT/table.md`` (every weights and row there).

Usage::

    python scripts/cd_split.py --data $GENRE_HOME/views/product_eval --groups product-test --weights default \\
        --name X0 --rows GenRe,GenRe-Oracle,GenRe-SphOracle --level 0.45 --jobs 2 --out OUT
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from genre_backend import frame
from genre_backend.arguments import add_jobs, add_out, add_weights
from genre_backend.geometry.mesh_voxels import grid_to_surface
from genre_backend.geometry.metrics import chamfer_parts, sample_surface
from genre_backend.geometry.raster import seen_from_camera
from genre_backend.weights_file import resolve_weights
from training.eval.protocol import FLOOR, POINTS_SMALL, find_eval_views
from training.eval.report import write_csv
from training.eval.runner import ModelSpec, Truth

PARTS = ("pred_seen", "pred_hidden", "gt_seen", "gt_hidden")
COLUMNS = ["key", "weights", "row", "cd", *PARTS, "pred_seen_share", "gt_seen_share"]


def _triangles(vertices, faces) -> torch.Tensor:
    v = torch.as_tensor(np.asarray(vertices), dtype=torch.float64)
    return v[torch.as_tensor(np.asarray(faces), dtype=torch.int64)]


def split_view(models, view, sample, truth: Truth, level: float) -> list[dict]:
    """{row, cd, the four parts, the seen shares} of one view, for every row and the noise floor."""
    from training.eval.rows import predict

    camera = models.config.camera
    gt_large, again_large = truth.posed(view)
    gt, again = gt_large[:POINTS_SMALL], again_large[:POINTS_SMALL]
    verts, faces = truth.object_mesh(view)
    rot = torch.tensor(view.meta["rotation_cam_to_obj"], dtype=torch.float64)[None]
    true_tri = _triangles(frame.object_to_view(torch.as_tensor(verts, dtype=torch.float64)[None], rot)[0], faces)
    gt_seen = seen_from_camera(gt, true_tri, camera)
    out = []

    def record(row: str, points: torch.Tensor, seen: torch.Tensor) -> None:
        parts = chamfer_parts(points, gt, seen, gt_seen)
        out.append({"row": row, "cd": sum(parts.values()), **parts,
                    "pred_seen_share": float(seen.float().mean()), "gt_seen_share": float(gt_seen.float().mean())})

    record(FLOOR, again, seen_from_camera(again, true_tri, camera))
    pred = predict(models, sample, "cpu")
    for row in models.rows():
        p = pred[row]
        v, f = p["mesh"] if "mesh" in p else grid_to_surface(p["prob"], level, p.get("geometry", models.config.geometry))
        if len(f) == 0:  # no sides to split (genre eval scores it EMPTY_CD): a row of NaN, left out of the means
            out.append({"row": row, **{c: float("nan") for c in COLUMNS[3:]}})
            continue
        points = sample_surface(v, f, POINTS_SMALL, seed=0)
        record(row, points, seen_from_camera(points, _triangles(v, f), camera))
    return out


_WORKER: dict = {}


def _init(spec: ModelSpec, level: float) -> None:
    torch.set_num_threads(1)
    _WORKER.update(models=spec.load(), truth=Truth(), level=level)


def _shape(views: list) -> list[tuple[str, list[dict]]]:
    from training.data.dataset import ViewDataset
    from training.data.views import ViewRef

    w = _WORKER
    data = ViewDataset([ViewRef(v.shape_dir, v.view) for v in views], w["models"].config)
    return [(v.key, split_view(w["models"], v, data.sample(i, None), w["truth"], w["level"]))
            for i, v in enumerate(views)]


def _table(records: list[dict], level: float) -> str:
    groups: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for r in records:
        groups[(r["weights"], r["row"])].append(r)
    lines = [f"Level {level:g}; means over views (CD = the four parts' sum; 1,024 points a cloud, normalised).\n",
             "| weights | row | views | CD | pred seen | pred hidden | truth seen | truth hidden | pred seen share | truth seen share |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for (weights, row), rs in groups.items():
        rs = [r for r in rs if np.isfinite(float(r["cd"]))]  # (an empty mesh's row is NaN)
        mean = {c: float(np.mean([float(r[c]) for r in rs])) for c in COLUMNS[3:]}
        lines.append(f"| {weights} | {row} | {len(rs)} | {mean['cd']:.4f} | " + " | ".join(f"{mean[c]:.4f}" for c in PARTS)
                     + f" | {mean['pred_seen_share']:.2f} | {mean['gt_seen_share']:.2f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, nargs="+", required=True, help="eval view folders (genre data render + targets)")
    parser.add_argument("--groups", default="product-test", help="comma-separated evaluation groups")
    parser.add_argument("--manifest", type=Path, help="the shapes' manifest (default: the corpus's)")
    add_weights(parser)
    parser.add_argument("--name", help="the weights' name in the table (default: the file's stem)")
    parser.add_argument("--rows", default="GenRe", help="comma-separated rows (GenRe, GenRe-Oracle, GenRe-SphOracle)")
    parser.add_argument("--level", type=float, default=0.45, help="the isosurface level (default 0.45)")
    parser.add_argument("--max-views", type=int, help="at most this many views a shape")
    add_jobs(parser)
    parser.add_argument("--shapes", type=int, help="the first this many shapes only (a quick look)")
    add_out(parser, required=True, help="folder for per_view.csv and table.md")
    args = parser.parse_args(argv)

    from training.data.corpus import load_manifest
    from training.data.views import read_manifest

    weights = resolve_weights(args.weights)
    name = args.name or Path(weights).stem
    manifest = read_manifest(args.manifest) if args.manifest else load_manifest()
    views = find_eval_views(args.data, manifest, tuple(args.groups.split(",")), args.max_views)
    if not views:
        print(f"cd_split: no complete eval views of {args.groups} under {args.data}", file=sys.stderr)
        return 1
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "per_view.csv"
    records = []
    if path.is_file():
        text = path.read_text()
        if not text.endswith("\n"):  # a line cut by a kill: not a record, even where its last field looks whole
            text = text[: text.rfind("\n") + 1]
        records = list(csv.DictReader(text.splitlines()))
    wanted = {FLOOR, *args.rows.split(",")}
    got: dict[str, set] = defaultdict(set)
    for r in records:
        if r["weights"] == name and r.get(COLUMNS[-1]) not in (None, ""):
            got[r["key"]].add(r["row"])
    done = {k for k, rows in got.items() if wanted <= rows}
    kept = [r for r in records if r["weights"] != name or r["key"] in done]
    if len(kept) < len(records):  # a view cut short by a kill (or scored with fewer rows): its lines go, it is scored again
        records = kept
        write_csv(path, records, COLUMNS)
    todo = [v for v in views if v.key not in done]
    by_shape: dict[Path, list] = defaultdict(list)
    for v in todo:
        by_shape[v.shape_dir].append(v)
    if args.shapes is not None:
        by_shape = dict(list(by_shape.items())[: args.shapes])
    spec = ModelSpec(str(weights), None, None, None, tuple(args.rows.split(",")), "cpu", (), (args.level,))
    new_file = not path.is_file()
    with path.open("a", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=COLUMNS, lineterminator="\n")
        if new_file:
            writer.writeheader()
        import multiprocessing as mp

        shapes = list(by_shape.values())
        if args.jobs > 1:
            pool = mp.get_context("fork").Pool(args.jobs, initializer=_init, initargs=(spec, args.level))
            done_shapes = pool.imap_unordered(_shape, shapes)
        else:
            pool = None
            _init(spec, args.level)
            done_shapes = map(_shape, shapes)
        try:
            for n, shape in enumerate(done_shapes, 1):
                for key, rows in shape:
                    new = [{"key": key, "weights": name, **{k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()}}
                           for r in rows]
                    writer.writerows(new)  # one view's rows together
                    records.extend(new)
                fh.flush()
                os.fsync(fh.fileno())
                print(f"cd_split: {n}/{len(shapes)} shapes", file=sys.stderr, flush=True)
        finally:
            if pool is not None:
                pool.terminate()
    table = _table(records, args.level)
    (out / "table.md").write_text(table)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
