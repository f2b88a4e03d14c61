"""``genre eval``: the paper's Table 1 on our data, with its baselines, oracles and figures.

Output ``OUT/``: ``per_view.csv`` (resumable), ``per_shape.csv``,
``per_class.csv``, ``thresholds.json``, ``table.md`` and the figures
(:mod:`training.eval.figures`, :mod:`training.eval.heatmap`).  Without
seen-test views in the run, pass the ``thresholds.json`` of a seen-test run
with ``--thresholds-from``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import torch

from genre_backend.atomic import atomic_write_text
from genre_backend.weights_file import DEFAULT_WEIGHTS_NAME, named_weights, resolve_weights, weights_extra
from genre_backend.inference.options import BY_NAME, MeshOptions, OptionError
from genre_backend.nets.model import WeightsError, load_model
from genre_backend.arguments import add_device, add_jobs, add_out, add_weights

from .protocol import DIAGNOSTIC_ROWS, GROUPS, ROWS, find_eval_views
from .rows import SWEEPABLE, Models
from .runner import ModelSpec, evaluate_views
from .statistics import CLOSED_SHARE, aggregate, choose_thresholds
from .report import flatness_table, format_table, sweep_table, write_csv

__all__ = ['HINTS', 'main']


def _digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()[:16]


def _weights_paths(args) -> dict[str, Path | None]:
    run = Path(args.run) if args.run else None

    def pick(explicit, *candidates):
        if explicit:
            return Path(explicit)
        if run is None:
            return None
        for c in candidates:
            if (run / c).is_file():
                return run / c
        return run / candidates[0]

    return {
        "genre": pick(args.weights, "joint/best.safetensors", "refine/best.safetensors"),
        "completion": pick(args.completion, "completion/best.safetensors"),
        "onestep": pick(args.onestep, "onestep/best.safetensors"),
    }


HINTS = {
    "genre": "train it with 'genre train depth|inpaint|refine|joint --out RUN …' or pass --weights",
    "completion": "train it with 'genre train completion --init RUN/depth/best.safetensors --out RUN …', pass --completion, or leave the row out with --rows",
    "onestep": "train it with 'genre train onestep --out RUN …', pass --onestep, or leave the row out with --rows",
}


def _parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description="Evaluate GenRe, its oracles and baselines over seen-test and unseen views (the paper's Table 1).")
    p.add_argument("--data", nargs="+", required=True, help="folders of rendered eval views with targets ('genre data render --split test|unseen' + 'genre data targets')")
    p.add_argument("--run", help="training run folder (weights RUN/joint|refine/best.safetensors, RUN/completion/…, RUN/onestep/…)")
    add_weights(p, help="GenRe weights: a file, or 'protocol' (the shipped research weights, seen classes only: "
                                     "Table 1's) (default: RUN/joint/best.safetensors, else RUN/refine/best.safetensors)")
    p.add_argument("--completion", help="3D Completion baseline weights (default RUN/completion/best.safetensors)")
    p.add_argument("--onestep", help="GenRe-1step weights (default RUN/onestep/best.safetensors)")
    p.add_argument("--train-views", nargs="*", default=[], help="training views (nearest-shape baseline and class dissimilarity)")
    p.add_argument("--train-shapes", help="file of training shape ids (default: every shape in --train-views)")
    p.add_argument("--manifest", help="manifest JSON for classes and splits (default $GENRE_HOME/corpus/manifest.json if present)")
    add_out(p, help="results folder (default $GENRE_HOME/results/<run name>; results/ in the repository holds the committed ones)")
    p.add_argument("--groups", default="test,unseen,unseen-pix3d", help="groups to evaluate: test (seen-test), unseen, unseen-pix3d (Table 1, the default); product-test (the product model's test split); flat-from-above (genre data flat-test's shapes)")
    p.add_argument("--rows", help=f"comma-separated rows (default all): {', '.join(ROWS)}; "
                   f"diagnostics, only when named: {', '.join(DIAGNOSTIC_ROWS)}")
    p.add_argument("--sweep", action="append", default=[], metavar="OPTION=V1,V2",
                   help=f"score GenRe again with one mesh option at each value (rows 'GenRe [OPTION=V]', the networks run "
                        f"once; the others at the weights' setting); repeatable; options: {', '.join(SWEEPABLE)}; "
                        "booleans on/off")
    p.add_argument("--levels", default=None, metavar="T1,T2",
                   help="score only these isosurface levels (e.g. 0.45, the installed one) instead of the weights' sweep "
                        "(threshold_min to threshold_max): a rule at one level needs no more, and each level costs a mesh "
                        "a row a view")
    p.add_argument("--max-views", type=int, default=None, help="at most this many views per shape")
    p.add_argument("--thresholds-from", help="thresholds.json of a run on seen-test data (when this run has none)")
    add_device(p)
    add_jobs(p, help="worker processes scoring views side by side (one thread each; e.g. the number of cores)")
    p.add_argument("--gallery", type=int, default=3, help="shapes per group in the Blender gallery (0: none)")
    p.add_argument("--heatmap-class", default="table", help="class of the viewpoint heatmap (Figure 7)")
    p.add_argument("--heatmap-shapes", type=int, default=0, help="shapes rendered on the elevation × azimuth grid (0: no heatmap)")
    p.add_argument("--heatmap-elevations", default="-10,5,20,35", help="elevations (degrees) of the grid")
    p.add_argument("--heatmap-azimuths", type=int, default=8, help="azimuths of the grid (evenly spaced)")
    p.add_argument("--render-samples", type=int, default=16, help="Cycles samples of grid views and gallery images")
    p.add_argument("--no-figures", action="store_true")
    p.add_argument("--no-progress", action="store_true")
    return p


def _fail(prog: str, message: str) -> int:
    print(f"{prog}: error: {message}", file=sys.stderr)
    return 2


def _closed_at(records: list[dict], t: float) -> float:
    vals = [float(r[f"closed@{t:.2f}"]) for r in records if r["row"] == "GenRe" and "test" in r["groups"].split("|")]
    return sum(vals) / len(vals) if vals else float("nan")


class _Refused(Exception):
    """A reason ``genre eval`` stops before scoring (one line, exit status 2)."""


def _rows_and_groups(args: argparse.Namespace) -> tuple[list[str], tuple[str, ...]]:
    """The rows and view groups asked for, checked; the GenRe weights resolved (``--weights protocol`` → a file)."""
    rows_wanted = [r.strip() for r in args.rows.split(",")] if args.rows else list(ROWS)
    unknown = [r for r in rows_wanted if r not in ROWS + DIAGNOSTIC_ROWS]
    if unknown:
        raise _Refused(f"--rows: unknown {unknown}; choose from {list(ROWS + DIAGNOSTIC_ROWS)}")
    groups = tuple(g.strip() for g in args.groups.split(","))
    if any(g not in GROUPS for g in groups):
        raise _Refused(f"--groups: choose from {list(GROUPS)}")
    if not args.run and not args.weights:
        raise _Refused("give the training run (--run RUN) or the GenRe weights (--weights FILE, or --weights protocol)")
    if args.weights:
        try:
            args.weights = str(resolve_weights(args.weights))
        except WeightsError as exc:
            raise _Refused(f"--weights: {exc}") from None
    return rows_wanted, groups


_BOOLS = {"on": True, "true": True, "1": True, "yes": True, "off": False, "false": False, "0": False, "no": False}


def parse_sweeps(texts: list[str], geometry) -> tuple[tuple[str, object], ...]:
    """``--sweep`` texts (``OPTION=V1,V2``) as ``((option, value), ...)``, each checked against the weights' ``geometry``
    (a value these weights cannot take is refused); :class:`_Refused` with the reason."""
    sweeps = []
    for text in texts:
        name, sep, values = text.partition("=")
        name = name.strip().replace("-", "_")
        if not sep or name not in SWEEPABLE or not values.strip():
            raise _Refused(f"--sweep {text!r}: expected OPTION=V1[,V2...] with OPTION one of {', '.join(SWEEPABLE)}")
        spec = BY_NAME[name]
        for raw in values.split(","):
            raw = raw.strip().lower()
            try:
                value = _BOOLS[raw] if spec.kind == "bool" else int(raw) if spec.kind == "int" else float(raw) \
                    if spec.kind == "float" else raw
                MeshOptions(**{name: value}).resolved(geometry)
            except (KeyError, ValueError, OptionError) as exc:
                raise _Refused(f"--sweep {name}: {raw!r} is not a value these weights take ({spec.expected()}; "
                               f"{exc if isinstance(exc, OptionError) else 'not a ' + spec.kind})") from None
            if (name, value) not in sweeps:
                sweeps.append((name, spec.check(value)))
    return tuple(sweeps)


def _needed_weights(args: argparse.Namespace, paths: dict[str, Path | None], rows_wanted: list[str]) -> dict[str, bool]:
    """Which of the three weights the rows need (each present, or :class:`_Refused` with every one missing)."""
    need = {"genre": True, "completion": bool({"3D Completion", "3D Completion-Oracle"} & set(rows_wanted)), "onestep": "GenRe-1step" in rows_wanted}
    missing = [f"{k} weights not found: {paths[k]} ({HINTS[k]})" for k, needed in need.items() if needed and (paths[k] is None or not paths[k].is_file())]
    if "Nearest training shape" in rows_wanted and not args.train_views:
        missing.append("the nearest-training-shape row needs the training views: pass --train-views DIR (or leave the row out with --rows)")
    if missing:
        raise _Refused("; ".join(missing))
    return need


def _views(args: argparse.Namespace, groups: tuple[str, ...]) -> list:
    """The complete evaluation views of ``groups`` under ``--data`` (the manifest names each shape's groups)."""
    manifest = None
    if args.manifest:
        from ..data.views import read_manifest

        try:
            manifest = read_manifest(args.manifest)
        except (FileNotFoundError, ValueError) as exc:
            raise _Refused(f"--manifest: {exc}") from None
    else:
        try:
            from training.data.corpus import load_manifest

            manifest = load_manifest()
        except FileNotFoundError:
            manifest = None
    try:
        views = find_eval_views([Path(d) for d in args.data], manifest, groups, args.max_views)
    except FileNotFoundError as exc:
        raise _Refused(str(exc)) from None
    if not views:
        raise _Refused(f"no complete eval views (render + targets + surface_points.npz) of groups {list(groups)} under {args.data}; "
                       "render them with 'genre data render --shapes $GENRE_HOME/corpus/manifest.json --split test|unseen --views 4 --out DIR' and 'genre data targets --views DIR'")
    return views


def _levels(text: str | None) -> tuple[float, ...]:
    """``--levels``' isosurface levels, sorted and distinct, each strictly between 0 and 1 (empty: not given)."""
    if text is None:
        return ()
    try:
        levels = sorted({round(float(t), 6) for t in text.split(",")})
    except ValueError:
        levels = []
    if not levels or not all(0.0 < t < 1.0 for t in levels):
        raise _Refused(f"--levels: expected isosurface levels between 0 and 1, comma-separated (e.g. 0.45), got {text!r}")
    return tuple(levels)


def _models(args: argparse.Namespace, paths: dict[str, Path | None], need: dict[str, bool], rows_wanted: list[str]) -> Models:
    """GenRe and the baselines the rows need, loaded and checked."""
    try:
        genre = load_model(paths["genre"], args.device)
        from ..learn.baselines import load_baseline

        completion = load_baseline(paths["completion"], "completion", args.device) if need["completion"] else None
        onestep = load_baseline(paths["onestep"], "onestep", args.device) if need["onestep"] else None
        models = Models(genre, completion, onestep, wanted=tuple(rows_wanted), sweeps=parse_sweeps(args.sweep, genre.config.geometry),
                        levels=_levels(args.levels))
        models.check()
    except WeightsError as exc:
        raise _Refused(str(exc)) from None
    return models


def _out_folder(args: argparse.Namespace, paths: dict[str, Path | None], need: dict[str, bool], models: Models,
                rows_wanted: list[str]) -> Path:
    """``--out`` (default: the GenRe home's results/RUN), made, with the run's identity in ``eval_config.json``:
    the same weights and views, or :class:`_Refused` instead of mixed results."""
    if args.out:
        out = Path(args.out)
    else:
        from ..data.corpus import data_dir

        out = data_dir() / "results" / (Path(args.run).name if args.run else Path(args.weights).stem)
    out.mkdir(parents=True, exist_ok=True)
    ident = {"weights": {k: (str(v), _digest(v)) for k, v in paths.items() if need[k] and v is not None},
             "preset": models.genre.config.preset, "rows": rows_wanted, "train_views": [str(p) for p in args.train_views],
             **({"sweeps": [list(s) for s in models.sweeps]} if models.sweeps else {}),
             **({"levels": list(models.levels)} if models.levels else {})}
    ident = json.loads(json.dumps(ident))  # as it reads back (lists, not tuples)
    ident_path = out / "eval_config.json"
    if ident_path.is_file() and json.loads(ident_path.read_text()) != ident:
        if (out / "per_view.csv").is_file():
            raise _Refused(f"{out} holds results of other weights or rows ({ident_path}); use another --out or delete it")
    ident_path.write_text(json.dumps(ident, indent=2))
    return out


def _nearest_index(args: argparse.Namespace, models: Models, out: Path, train_ids: set[str] | None) -> None:
    """The nearest-training-shape row's index of the training views: read from ``out`` or built and saved there."""
    from ..learn.baselines import NearestIndex, build_nearest_index

    genre = models.genre
    index_path = out / "nearest_index.safetensors"
    try:
        if index_path.is_file():
            models.nearest = NearestIndex.load(index_path)
        else:
            parts = [build_nearest_index(d, genre.config, train_ids, progress=not args.no_progress) for d in args.train_views]
            models.nearest = NearestIndex(torch.cat([p.thumbs for p in parts]), torch.cat([p.rotations for p in parts]),
                                          sum((p.shape_dirs for p in parts), []), sum((p.views for p in parts), []))
            models.nearest.save(index_path, genre.config)
    except (FileNotFoundError, WeightsError) as exc:
        raise _Refused(str(exc)) from None


def _gallery_keys(args: argparse.Namespace, groups: tuple[str, ...], views: list) -> list[str]:
    """The gallery's views: the first view of the first ``--gallery`` shapes of each group."""
    gallery_keys: list[str] = []
    if args.gallery > 0 and not args.no_figures:
        for g in groups:
            firsts = {}
            for v in views:
                if g in v.groups and v.shape_dir.name not in firsts:
                    firsts[v.shape_dir.name] = v.key
            gallery_keys += [k for k in list(firsts.values())[: args.gallery] if k not in gallery_keys]
    return gallery_keys


def _shipped_threshold_note(records: list[dict], choice: dict) -> str:
    """The table's section on the threshold installed for users (empty without product-split thresholds)."""
    if "GenRe" not in choice.get("product", {}):
        return ""
    tp, share = choice["product"]["GenRe"]
    _, _, at_product = aggregate(records, dict(choice, seen=dict(choice["seen"], GenRe=tp)))
    cds = ", ".join(f"{g} {v['GenRe']:.3f}" for g, v in at_product["seen"].items() if "GenRe" in v)
    return (f"\n## The shipped threshold\n\nThe threshold installed for users (`python -m training.eval.install`) is chosen on "
            f"seen-test views too, as the lowest mean CD among thresholds whose GenRe meshes are closed (no holes, no tunnels) "
            f"in at least {100 * CLOSED_SHARE:.0f} % of the views"
            + ("" if share >= CLOSED_SHARE else " (none is here, so: the threshold whose meshes are most often closed)")
            + f": t = {tp:.2f}, closed in {100 * share:.0f} % of the "
            f"seen-test views (at the CD-optimal {choice['seen']['GenRe']:.2f}: "
            f"{100 * _closed_at(records, choice['seen']['GenRe']):.0f} %). GenRe's CD at t = {tp:.2f}: {cds}.\n")


def _figures(args: argparse.Namespace, out: Path, per_class, models: Models, views: list, choice: dict,
             train_ids: set[str] | None, gallery_keys: list[str]) -> str:
    """The figures (unless ``--no-figures``) and the table's section that lists them (empty without any)."""
    if args.no_figures:
        return ""
    from . import figures
    from .heatmap import HeatmapSpec

    heatmap = HeatmapSpec(args.heatmap_class, args.heatmap_shapes, tuple(float(e) for e in args.heatmap_elevations.split(",")),
                          args.heatmap_azimuths, args.render_samples)
    notes = figures.make_all(out, per_class, models, views, choice, train_views=[Path(p) for p in args.train_views or []],
                             train_ids=train_ids, gallery_keys=gallery_keys, render_samples=args.render_samples,
                             heatmap=heatmap, device=args.device, progress=not args.no_progress)
    return "\n## Figures\n\n" + "\n".join(notes) + "\n" if notes else ""


def _shipped_note(path: Path | None, shipped_as: str | None) -> str:
    """The report's word on a weights file that records a shipped name: the shipped file itself, or one made from it.

    A file grafted, averaged or re-estimated from a shipped one keeps its record (``"model": NAME``), so the name
    alone does not say that it is the shipped file; the path does.
    """
    if path is None or not shipped_as:
        return ""
    try:
        shipped = named_weights(shipped_as)
    except ValueError:  # a name installed under another word: not a shipped file of this checkout
        return f" (made from weights installed as '{shipped_as}')"
    if Path(path).resolve() == shipped.resolve():
        return f" (the shipped '{shipped_as}' weights)"
    return f" (made from the shipped '{shipped_as}' weights, not that file)"


def _prepare(args: argparse.Namespace, prog: str) -> tuple:
    """Everything before the scoring: (rows, groups, weights' paths, needed, the shipped name, views, models, out)."""
    rows_wanted, groups = _rows_and_groups(args)
    paths = _weights_paths(args)
    shipped_as = weights_extra(paths["genre"]).get("model") if paths["genre"] is not None else None
    if shipped_as == DEFAULT_WEIGHTS_NAME:
        print(f"{prog}: warning: {paths['genre']} are the product weights ('default', meant to be trained on every class); "
              "research numbers come from 'protocol' (--weights protocol)", file=sys.stderr)
    need = _needed_weights(args, paths, rows_wanted)
    views = _views(args, groups)
    models = _models(args, paths, need, rows_wanted)
    out = _out_folder(args, paths, need, models, rows_wanted)
    return rows_wanted, groups, paths, need, shipped_as, views, models, out


def main(argv: list[str] | None = None, prog: str = "genre eval") -> int:
    args = _parser(prog).parse_args(argv)
    t_start = time.perf_counter()
    try:
        rows_wanted, groups, paths, need, shipped_as, views, models, out = _prepare(args, prog)
        train_ids = None
        if args.train_shapes:
            train_ids = {line.strip() for line in Path(args.train_shapes).read_text().splitlines() if line.strip()}
        if "Nearest training shape" in rows_wanted:
            _nearest_index(args, models, out, train_ids)
        gallery_keys = _gallery_keys(args, groups, views)
        if args.jobs < 1:
            raise _Refused(f"--jobs: expected a positive number of processes, got {args.jobs}")
    except _Refused as exc:
        return _fail(prog, str(exc))
    genre = models.genre
    spec = ModelSpec(str(paths["genre"]), str(paths["completion"]) if need["completion"] else None,
                     str(paths["onestep"]) if need["onestep"] else None,
                     str(out / "nearest_index.safetensors") if models.nearest is not None else None, tuple(rows_wanted), args.device,
                     models.sweeps, models.levels)
    t_views = time.perf_counter()
    records = evaluate_views(models, views, out, device=args.device, progress=not args.no_progress, save_grids=set(gallery_keys),
                             jobs=args.jobs, spec=spec)
    t_views = time.perf_counter() - t_views
    fixed = json.loads(Path(args.thresholds_from).read_text())["seen"] if args.thresholds_from else None
    choice = choose_thresholds(records, models.thresholds(), genre.config.geometry.default_threshold, fixed)
    per_shape, per_class, group_means = aggregate(records, choice)
    (out / "thresholds.json").write_text(json.dumps(choice, indent=2))
    write_csv(out / "per_shape.csv", per_shape)
    write_csv(out / "per_class.csv", per_class)
    n_shapes = len({v.shape_dir.name for v in views})
    header = (f"# GenRe evaluation: {out.name}\n\n{len(views)} views of {n_shapes} shapes; preset {genre.config.preset} "
              f"(voxel target: {genre.config.geometry.target}); weights {paths['genre']}"
              + _shipped_note(paths["genre"], shipped_as) + ".\n\n"
              f"Command: `genre eval {' '.join(argv if argv is not None else sys.argv[1:])}`\n\n"
              f"Scoring the views took {t_views / 60:.1f} min in this invocation ({args.jobs} process{'es' if args.jobs > 1 else ''}; "
              "views already in `per_view.csv` from an earlier invocation are not scored again, nor counted).\n")
    table = format_table(per_class, group_means, choice, models.rows(), header) + _shipped_threshold_note(records, choice)
    table += flatness_table(records, choice, models.rows())
    level = min(models.thresholds(), key=lambda t: abs(t - genre.config.geometry.default_threshold))
    table += sweep_table(records, models.sweeps, level)
    table += _figures(args, out, per_class, models, views, choice, train_ids, gallery_keys)
    atomic_write_text(out / "table.md", table)
    print(table)
    print(f"wrote {out}/ in {time.perf_counter() - t_start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
