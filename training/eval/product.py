"""The product model against the protocol model, and the product model's learning curve.

Both read what ``genre eval --groups product-test`` wrote (``per_view.csv`` and
``thresholds.json``): each model is scored at its own threshold, the one its
weights install for users, so that nothing is tuned on the product test split.

Groups of the product test split (every class holds out shapes, see
:func:`training.data.corpus.product_groups`):

=========================  ====================================================================
seen by protocol           airplane, car, chair: the classes the protocol model trained on
unseen by protocol         every other class of the corpus (furniture, vessels, the unassigned)
procedural                 the generated shapes (``training/data/sources/procedural.py``)
regular primitives         the procedural cubes, cylinders, cones and tori (random poses, colours)
=========================  ====================================================================

``python -m training.eval.product compare`` writes the side-by-side table;
``python -m training.eval.product fit`` writes the fit diagnostic (CD on a fixed
sample of training views beside CD on the test split, each against its noise
floor: while the two are alike and far from the floor, the model underfits);
``python -m training.eval.product verdict`` applies the install rule (:class:`ProductRule`; with ``--pareto`` also the
second path, :class:`ParetoRule`) to two folders of the rule's score sets; ``python -m training.eval.product curve`` appends one point (cumulative
processor hours of a product run, its mean CD on the product test split) to
the learning curve and plots it.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from collections import defaultdict
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from genre_backend.atomic import atomic_write_text
from genre_backend.arguments import add_out

from ..data.corpus import SEEN_CLASSES
from .protocol import FLOOR, REPRESENTATION, threshold_key
from .report import depth_width_ratios

__all__ = ["PRIMITIVE_KINDS", "GROUPS", "group_of_shape", "load_scores", "compare_table", "rule_figures", "RULE_SETS", "ProductRule", "ParetoRule", "pooled_change", "flat_ratio",
           "flat_photos", "verdict", "verdict_text", "curve_point", "fit_table", "main"]

PRIMITIVE_KINDS = ("cube", "cylinder", "cone", "torus")  # the regular primitives
GROUPS = ("all", "seen by protocol", "unseen by protocol", "procedural", "regular primitives")


def group_of_shape(entry: dict) -> tuple[str, ...]:
    """The comparison groups of one manifest entry (``all`` always)."""
    out = ["all"]
    if entry.get("source") == "procedural":
        out.append("procedural")
        if _primitive_kind(entry) in PRIMITIVE_KINDS:
            out.append("regular primitives")
    elif entry.get("class") in SEEN_CLASSES:
        out.append("seen by protocol")
    else:
        out.append("unseen by protocol")
    return tuple(out)


def _primitive_kind(entry: dict) -> str | None:
    if entry.get("class") != "primitive":
        return None
    return (entry.get("extra") or {}).get("subkind")  # (the generating parameters, training/data/sources/procedural.py)


def load_scores(eval_dir: Path, row: str = "GenRe", threshold: float | None = None) -> dict[str, dict]:
    """``{view key: {"shape", "class", "cd", "floor", "representation"}}`` of one ``genre eval`` folder.

    ``cd``: the row's CD (1,024 points) at ``threshold``, else at the run's chosen one (``thresholds.json``, ``seen``);
    ``floor`` and ``representation``: the same view's noise floor and truth through the representation.
    """
    eval_dir = Path(eval_dir)
    chosen = json.loads((eval_dir / "thresholds.json").read_text())["seen"]
    if threshold is not None:
        chosen = {**chosen, row: threshold}
    if row not in chosen:
        raise ValueError(f"{eval_dir}: no row {row!r} in thresholds.json")
    out: dict[str, dict] = {}
    with (eval_dir / "per_view.csv").open(newline="") as fh:
        for rec in csv.DictReader(fh):
            if rec["row"] not in (row, FLOOR, REPRESENTATION):
                continue
            t = chosen.get(rec["row"], chosen[row])
            view = out.setdefault(rec["key"], {"shape": rec["shape"], "class": rec["class"]})
            value = float(rec[f"cd1k@{threshold_key(t)}"])
            view[{row: "cd", FLOOR: "floor", REPRESENTATION: "representation"}[rec["row"]]] = value
    return {k: v for k, v in out.items() if "cd" in v}


def _mean(values) -> float:
    values = [v for v in values if math.isfinite(v)]
    return float(np.mean(values)) if values else math.nan


def _shape_means(scores: dict[str, dict], field: str) -> dict[str, float]:
    per_shape = defaultdict(list)
    for v in scores.values():
        if field in v:
            per_shape[v["shape"]].append(v[field])
    return {s: float(np.mean(vals)) for s, vals in per_shape.items()}


def compare_table(product_dir: Path, protocol_dir: Path, manifest: dict, title: str = "",
                  thresholds: tuple[float | None, float | None] = (None, None), product_row: str = "GenRe") -> str:
    """Markdown: mean CD per group and per class of the two models on the views both scored.

    Means are over shapes (a shape's views averaged first). ``thresholds``: the
    product's and the protocol's level (None: each run's ``thresholds.json``). ``product_row``: the row of the
    product folder to read (``GenRe-Oracle``, ``GenRe-SphOracle``: the product weights given true inputs); the
    protocol folder's is always ``GenRe``.
    """
    a = load_scores(product_dir, row=product_row, threshold=thresholds[0])
    b = load_scores(protocol_dir, threshold=thresholds[1])
    common = sorted(set(a) & set(b))
    if not common:
        raise ValueError(f"{product_dir} and {protocol_dir} have no view in common")
    a = {k: a[k] for k in common}
    b = {k: b[k] for k in common}
    entries = {e["id"]: e for e in manifest["shapes"]}
    cd_a, cd_b = _shape_means(a, "cd"), _shape_means(b, "cd")
    floor, rep = _shape_means(a, "floor"), _shape_means(a, "representation")
    shapes = sorted(cd_a)
    cls_of = {v["shape"]: v["class"] for v in a.values()}
    groups = {s: group_of_shape(entries.get(s, {"class": cls_of[s]})) for s in shapes}
    ta = thresholds[0] if thresholds[0] is not None else json.loads((Path(product_dir) / "thresholds.json").read_text())["seen"][product_row]
    tb = thresholds[1] if thresholds[1] is not None else json.loads((Path(protocol_dir) / "thresholds.json").read_text())["seen"]["GenRe"]
    lines = [f"# {title or 'The product model against the protocol model'}", "",
             f"{len(common)} views of {len(shapes)} shapes of the product test split; each model at the threshold its "
             f"weights install (product t = {ta:.2f}, protocol t = {tb:.2f}); CD with 1,024 points, means over shapes. "
             f"Product: `{product_dir}`" + (f", its row {product_row}" if product_row != "GenRe" else "")
             + f"; protocol: `{protocol_dir}`.", "",
             "| group | shapes | product | protocol | product ÷ protocol | noise floor | product ÷ floor | truth through the representation |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for g in GROUPS:
        members = [s for s in shapes if g in groups[s]]
        if not members:
            continue
        ma, mb = _mean(cd_a[s] for s in members), _mean(cd_b[s] for s in members)
        mf, mr = _mean(floor.get(s, math.nan) for s in members), _mean(rep.get(s, math.nan) for s in members)
        lines.append(f"| {g} | {len(members)} | {ma:.3f} | {mb:.3f} | {ma / mb:.3f} | {mf:.3f} | {ma / mf:.2f}× | {mr:.3f} |")
    prims = [s for s in shapes if "regular primitives" in groups[s]]
    if prims:
        lines += ["", "Regular primitives by kind (product model; noise floor):", ""]
        by_kind = defaultdict(list)
        for s in prims:
            by_kind[_primitive_kind(entries[s])].append(s)
        for kind in PRIMITIVE_KINDS:
            ss = by_kind.get(kind, [])
            if ss:
                lines.append(f"- {kind} ({len(ss)}): {_mean(cd_a[s] for s in ss):.3f} (floor {_mean(floor[s] for s in ss):.3f}, "
                             f"{_mean(cd_a[s] for s in ss) / _mean(floor[s] for s in ss):.2f}×; protocol {_mean(cd_b[s] for s in ss):.3f})")
    lines += ["", "## Per class", "", "| class | group | shapes | product | protocol | product ÷ protocol |", "| --- | --- | ---: | ---: | ---: | ---: |"]
    by_class = defaultdict(list)
    for s in shapes:
        by_class[cls_of[s]].append(s)
    for cls in sorted(by_class, key=lambda c: (groups[by_class[c][0]][1], c)):
        ss = by_class[cls]
        ma, mb = _mean(cd_a[s] for s in ss), _mean(cd_b[s] for s in ss)
        lines.append(f"| {cls} | {groups[ss[0]][1]} | {len(ss)} | {ma:.3f} | {mb:.3f} | {ma / mb:.3f} |")
    return "\n".join(lines) + "\n"


def _kind(entry: dict) -> str:
    """A primitive's kind (cube, sphere, cone…), else the shape's class."""
    return _primitive_kind(entry) or entry.get("class", "?")


def _change(a: dict[str, dict], b: dict[str, dict], keys: list[str]) -> dict:
    ma, mb = (float(np.mean([s[k]["cd"] for k in keys])) for s in (a, b))
    floor = _mean(b[k].get("floor", math.nan) for k in keys)  # the same views' noise floor (nan where none is scored)
    return {"views": len(keys), "installed": ma, "candidate": mb, "change_percent": 100.0 * (mb / ma - 1.0),
            "better": sum(b[k]["cd"] < a[k]["cd"] for k in keys), "floor": floor}


def rule_figures(installed_dir: Path, candidate_dir: Path, threshold: float | None = None, row: str = "GenRe",
                 candidate_row: str | None = None, manifest: dict | None = None) -> dict:
    """The product rule's figures (``results/decisions.md``): the per-view mean CD of the installed weights' and a
    candidate's ``genre eval`` folders over the views both hold, the change in percent, and on how many views the
    candidate is lower, for ``row`` (e.g. GenRe-SphOracle).  Means over views, not over shapes (one view a shape on
    the product test split).  ``candidate_row``: the candidate's row when it is another (default ``row``): its
    weights with a mesh option its rule changes, ``GenRe [visible_fusion=on]`` of ``genre eval --sweep``.
    ``manifest``: also the same figures per kind (a primitive's kind, else the class) under ``"by_kind"``, to show
    where a change lands."""
    a = load_scores(installed_dir, row, threshold)
    b = load_scores(candidate_dir, candidate_row or row, threshold)
    keys = sorted(k for k in set(a) & set(b) if math.isfinite(a[k]["cd"]) and math.isfinite(b[k]["cd"]))
    if not keys:
        raise ValueError(f"{installed_dir} and {candidate_dir} share no scored view")
    out = _change(a, b, keys)
    if manifest is not None:
        entries = {e["id"]: e for e in manifest["shapes"]}
        by_kind = defaultdict(list)
        for k in keys:
            by_kind[_kind(entries.get(a[k]["shape"], {"class": a[k]["class"]}))].append(k)
        out["by_kind"] = {kind: _change(a, b, ks) for kind, ks in sorted(by_kind.items())}
    return out


RULE_SETS = {"photo-like": ("product_eval_photo", "product_up_photo"), "as rendered": ("product_eval", "product_up"),
             "primitives": ("primitives_eval",)}
"""The rule's score sets: ``genre eval`` folders of these names under one folder a weights file (the product test's
views below 45° and from 45–88°, made photo-like by ``scripts/photo_views.py`` and as rendered; the primitives)."""


@dataclass(frozen=True)
class ProductRule:
    """The install rule of ``results/decisions.md`` (2026-12-04 14:04), as data: bars on the change in percent of a
    candidate's per-view mean CD against the installed file's, each set at ``level``.  Installed only if every bar
    holds.  ``flat_no_worse``: the flat-from-above group's median depth ÷ width ratio (``flat/`` beside the sets) may
    not exceed the installed file's, as the reads since 2026-12-05 name it."""

    level: float = 0.45
    photo_mean_max: float = -1.0  # (a) the mean of the photo-like halves' changes
    rendered_half_max: float = 2.0  # (b) each half as rendered
    rendered_mean_max: float = -1.0  # (b) the mean of the halves as rendered
    primitives_max: float = 1.0  # (b) the primitives
    flat_no_worse: bool = True


@dataclass(frozen=True)
class ParetoRule:
    """The second install path of ``results/decisions.md`` (2026-12-06 08:42), as data: a candidate no worse on the
    product sets and clearly flatter on the flat-from-above group, where :class:`ProductRule` asks for a product gain
    of 1 % that a change of a few tenths cannot show through the views' noise.  Every bar must hold: the upper end of
    the 95 % interval of the four product sets' pooled change (:func:`pooled_change`, shapes resampled) at most
    ``product_upper_max`` percent; no product set's own change above ``set_max``; the primitives' change at most
    ``primitives_max`` (the issue's "no worse"); the flat group's median depth ÷ width ratio at most ``flat_share`` of
    the installed file's."""

    level: float = 0.45
    product_upper_max: float = 0.5
    set_max: float = 1.0
    primitives_max: float = 0.0
    flat_share: float = 0.85
    resamples: int = 2000
    seed: int = 0


def pooled_change(installed_dirs: list[Path], candidate_dirs: list[Path], level: float, resamples: int = 2000,
                  seed: int = 0) -> dict:
    """The change in percent of the summed CD of several sets' views (each pair of ``genre eval`` folders over the
    views both hold, at ``level``), and its 95 % interval by resampling the *shapes* with replacement (a shape's views
    in every set go together: the sets show the same shapes, so their views are not independent).  ``{"change",
    "low", "high", "shapes", "views"}``."""
    sums: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0])
    views = 0
    for di, dc in zip(installed_dirs, candidate_dirs, strict=True):
        a, b = load_scores(di, threshold=level), load_scores(dc, threshold=level)
        for k in sorted(set(a) & set(b)):
            if math.isfinite(a[k]["cd"]) and math.isfinite(b[k]["cd"]):
                s = sums[a[k]["shape"]]
                s[0] += a[k]["cd"]
                s[1] += b[k]["cd"]
                views += 1
    if not sums:
        raise ValueError("the folders share no scored view")
    sa, sb = np.array(list(sums.values())).T
    pick = np.random.default_rng(seed).integers(0, len(sa), size=(resamples, len(sa)))
    boot = 100.0 * (sb[pick].sum(1) / sa[pick].sum(1) - 1.0)
    low, high = np.percentile(boot, [2.5, 97.5])
    return {"change": float(100.0 * (sb.sum() / sa.sum() - 1.0)), "low": float(low), "high": float(high),
            "shapes": len(sa), "views": views}


def _pareto_parts(installed_root: Path, candidate_root: Path, sets: dict, flat: tuple[float, float],
                  rule: ParetoRule) -> dict:
    """:class:`ParetoRule`'s parts (figure, bar, holds, unit), given :func:`verdict`'s per-set figures and the flat
    group's ratios (installed, candidate)."""
    names = [n for k in ("photo-like", "as rendered") for n in RULE_SETS[k]]
    pooled = pooled_change([Path(installed_root) / n for n in names], [Path(candidate_root) / n for n in names],
                           rule.level, rule.resamples, rule.seed)
    worst = max(names, key=lambda n: sets[n]["change_percent"])
    flat_a, flat_b = flat
    parts = {"product sets pooled, upper 95 %": (pooled["high"], rule.product_upper_max, "%"),
             f"worst product set ({worst})": (sets[worst]["change_percent"], rule.set_max, "%"),
             "primitives": (sets["primitives_eval"]["change_percent"], rule.primitives_max, "%"),
             "flat group depth ÷ width ratio": (flat_b, rule.flat_share * flat_a, "×")}
    return {"rule": asdict(rule), "pooled": pooled,
            "parts": {k: {"figure": f, "bar": bar, "holds": f <= bar, "unit": u} for k, (f, bar, u) in parts.items()}}


def flat_ratio(eval_dir: Path, level: float, row: str = "GenRe") -> float:
    """The flat-from-above group's median over views of the mesh's depth ÷ width over the truth's
    (:func:`training.eval.report.flatness_table`'s ratio) at ``level``, from a ``genre eval`` folder's per_view.csv."""
    with (Path(eval_dir) / "per_view.csv").open(newline="") as fh:
        ratios = depth_width_ratios(list(csv.DictReader(fh)), row, level)[2]
    ratios = ratios[np.isfinite(ratios)]
    if not len(ratios):
        raise ValueError(f"{eval_dir}: no flat-from-above view of row {row!r} with a depth ÷ width at "
                         f"{threshold_key(level)}")
    return float(np.median(ratios))


def flat_photos(root: Path) -> dict[str, dict]:
    """``{photo: {"thinnest", "truth"}}``: each real flat photo's mesh depth ÷ width along its thinnest axis and the
    judged truth, from ``photos_flat/photos.csv`` under ``root`` (``scripts/eval_photos.py --photos examples/flat``);
    empty when there is none."""
    path = Path(root) / "photos_flat" / "photos.csv"
    if not path.is_file():
        return {}
    with path.open(newline="") as fh:
        rows = list(csv.reader(fh))
    i = rows[0].index("thinnest depth/width")  # the judged truth is the column after it
    return {r[0]: {"thinnest": float(r[i]), "truth": float(r[i + 1])} for r in rows[1:] if r and r[0] != "mean"}


def verdict(installed_root: Path, candidate_root: Path, rule: ProductRule = ProductRule(),
            pareto: ParetoRule | None = None) -> dict:
    """The rule applied: each set's figures (:func:`rule_figures`), each part's figure against its bar,
    ``"install"``, true only if every part holds, and beside them (choosing nothing) ``"product_mean"``, the mean of
    the four product sets' changes (how near a read came to the bars, joint-80's measure).  The roots hold one ``genre eval`` folder per :data:`RULE_SETS`
    name, and ``flat/`` when ``rule.flat_no_worse``.  With ``pareto``, the second path too (:func:`_pareto_parts`,
    under ``"pareto"`` with its own ``"install"``): ``"install"`` is then true if either path's parts all hold, and
    ``"product_rule_install"`` keeps the first path's outcome."""
    if pareto is not None and pareto.level != rule.level:
        raise ValueError(f"the two paths read one level: ProductRule's {rule.level}, ParetoRule's {pareto.level}")
    sets = {name: rule_figures(Path(installed_root) / name, Path(candidate_root) / name, rule.level)
            for names in RULE_SETS.values() for name in names}
    photo, rendered = ([sets[n]["change_percent"] for n in RULE_SETS[k]] for k in ("photo-like", "as rendered"))
    parts = {
        "photo-like mean": (float(np.mean(photo)), rule.photo_mean_max),
        **{f"as rendered, {n}": (sets[n]["change_percent"], rule.rendered_half_max) for n in RULE_SETS["as rendered"]},
        "as rendered mean": (float(np.mean(rendered)), rule.rendered_mean_max),
        "primitives": (sets["primitives_eval"]["change_percent"], rule.primitives_max),
    }
    out = {"rule": asdict(rule), "sets": sets, "product_mean": float(np.mean(photo + rendered)),
           "parts": {k: {"figure": v, "bar": bar, "holds": v <= bar, "unit": "%"} for k, (v, bar) in parts.items()}}
    if rule.flat_no_worse or pareto is not None:
        flat = tuple(flat_ratio(Path(root) / "flat", rule.level) for root in (installed_root, candidate_root))
    if rule.flat_no_worse:
        a, b = flat
        out["parts"]["flat group depth ÷ width ratio"] = {"figure": b, "bar": a, "holds": b <= a, "unit": "×"}
    out["install"] = all(p["holds"] for p in out["parts"].values())
    if pareto is not None:
        out["pareto"] = _pareto_parts(installed_root, candidate_root, sets, flat, pareto)
        out["pareto"]["install"] = all(p["holds"] for p in out["pareto"]["parts"].values())
        out["product_rule_install"] = out["install"]
        out["install"] = out["install"] or out["pareto"]["install"]
    a, b = flat_photos(installed_root), flat_photos(candidate_root)
    out["beside"] = {name: {"installed": a[name]["thinnest"], "candidate": b[name]["thinnest"],
                            "truth": b[name]["truth"]} for name in sorted(set(a) & set(b))}
    return out


def _part_line(name: str, p: dict) -> str:
    fmt = (lambda x: f"{x:+.2f} %") if p["unit"] == "%" else (lambda x: f"{x:.2f}×")  # changes signed, ratios not
    return f"| {name} | {fmt(p['figure'])} | ≤ {fmt(p['bar'])} | {'yes' if p['holds'] else '**no**'} |"


def verdict_text(v: dict) -> str:
    """:func:`verdict` as Markdown: the sets, then the parts with their bars, then the outcome."""
    lines = ["| set | views | installed | candidate | change | lower on |", "|---|---|---|---|---|---|"]
    lines += [f"| {n} | {f['views']} | {f['installed']:.5f} | {f['candidate']:.5f} | {f['change_percent']:+.2f} % | "
              f"{f['better']} |" for n, f in v["sets"].items()]
    lines += ["", "| part | figure | bar | holds |", "|---|---|---|---|"]
    lines += [_part_line(name, p) for name, p in v["parts"].items()]
    if "pareto" in v:
        pooled = v["pareto"]["pooled"]
        lines += ["", f"Second path (ParetoRule): the four product sets pooled {pooled['change']:+.2f} % "
                  f"(95 % interval {pooled['low']:+.2f} to {pooled['high']:+.2f} %, {pooled['shapes']} shapes "
                  f"resampled, {pooled['views']} views)", "", "| part | figure | bar | holds |", "|---|---|---|---|"]
        lines += [_part_line(name, p) for name, p in v["pareto"]["parts"].items()]
        lines += ["", f"by ProductRule: {'yes' if v['product_rule_install'] else 'no'}; by ParetoRule: "
                  f"{'yes' if v['pareto']['install'] else 'no'}"]
    lines += ["", f"install: {'yes' if v['install'] else 'no'} (level {v['rule']['level']})",
              "", f"Beside: the mean of the four product sets' changes {v['product_mean']:+.2f} %"]
    if v.get("beside"):
        lines += ["", "Beside, choosing nothing: the real flat photos' thinnest depth ÷ width, installed → candidate "
                  "(judged truth): " + ", ".join(f"{n} {f['installed']:.2f} → {f['candidate']:.2f} ({f['truth']:.2f})"
                                                for n, f in v["beside"].items())]
    return "\n".join(lines) + "\n"


def _stage_cpu_seconds(stage_dir: Path) -> tuple[int, float]:
    """(steps, processor seconds) a stage has trained so far, from its checkpoint (0, 0 without one)."""
    state = stage_dir / "checkpoint" / "state.json"
    if not state.is_file():
        return 0, 0.0
    meta = json.loads(state.read_text())
    return int(meta["step"]), float(meta.get("cpu_s", 0.0))


CURVE_STAGES = ("depth", "inpaint", "refine", "joint")


def curve_point(run_dir: Path | None, eval_dir: Path, stages=CURVE_STAGES,
                threshold: float | None = None, base_hours: float = 0.0) -> dict:
    """One learning-curve point: the run's steps and processor hours per stage, and the mean CD on the product test split.

    ``run_dir`` None: the starting point (the weights the run warm-starts from).  ``stages``: those of the
    run behind the scored weights (a stage's output scored before the later stages ran: ``("depth",)``).  ``base_hours``: the
    processor hours that made those starting weights (earlier runs, on this machine or another), added
    to ``cpu_h`` so that the curve's hours are cumulative over every run.
    """
    if not (math.isfinite(base_hours) and base_hours >= 0):
        raise ValueError(f"base hours must be a finite number >= 0, got {base_hours}")
    unknown = [s for s in stages if s not in CURVE_STAGES]
    if unknown or not stages:
        raise ValueError(f"stages: expected some of {', '.join(CURVE_STAGES)}, got {', '.join(stages) or 'none'}")
    point: dict = {"run": str(run_dir or ""), "eval": str(eval_dir)}
    total = base_hours * 3600
    for stage in CURVE_STAGES:  # a stage left out (its weights are not in the scored file) counts 0
        steps, cpu = _stage_cpu_seconds(Path(run_dir) / stage) if run_dir and stage in stages else (0, 0.0)
        point[f"{stage}_steps"] = steps
        point[f"{stage}_cpu_h"] = round(cpu / 3600, 3)
        total += cpu
    point["cpu_h"] = round(total / 3600, 3)
    scores = load_scores(Path(eval_dir), threshold=threshold)
    point["views"] = len(scores)
    point["mean_cd"] = round(_mean(_shape_means(scores, "cd").values()), 5)
    return point


CURVE_FIELDS = ["label", "cpu_h", "mean_cd", "views", *(f"{s}_{k}" for s in CURVE_STAGES for k in ("steps", "cpu_h")),
                "run", "eval", "installed"]


def append_curve(csv_path: Path, point: dict, label: str, installed: bool = False) -> list[dict]:
    """Add (or replace, by label) one point of the learning curve; returns every point, by processor hours.

    ``installed``: the point's weights were installed as ``default`` (the line the curve follows; the
    other points are branches scored and not installed).  A CSV written before the column existed
    reads as no point installed.
    """
    rows = []
    if csv_path.is_file():
        with csv_path.open(newline="") as fh:
            rows = [r for r in csv.DictReader(fh) if r["label"] != label]
    rows.append({k: point.get(k, "") for k in CURVE_FIELDS} | {"label": label, "installed": "yes" if installed else ""})
    rows.sort(key=lambda r: float(r["cpu_h"]))
    lines = [",".join(CURVE_FIELDS)] + [",".join(str(r.get(k, "")) for k in CURVE_FIELDS) for r in rows]
    atomic_write_text(csv_path, "\n".join(lines) + "\n")
    return rows


def plot_curve(rows: list[dict], png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    line = [r for r in rows if r.get("installed") == "yes"]
    branches = [r for r in rows if r.get("installed") != "yes"]
    fig, ax = plt.subplots(figsize=(6, 3.6))
    if branches:
        ax.plot([float(r["cpu_h"]) for r in branches], [float(r["mean_cd"]) for r in branches], "o", mfc="none",
                color="0.55", label="other points: branches not installed, re-scores")
    if line:
        x = [float(r["cpu_h"]) for r in line]
        y = [float(r["mean_cd"]) for r in line]
        ax.plot(x, y, "o-", color="C0", label="installed as default")
        for r, xi, yi in zip(line, x, y):
            ax.annotate(r["label"], (xi, yi), fontsize=7, xytext=(3, 4), textcoords="offset points")
    ax.set_xlabel("product training, processor hours (cumulative)")
    ax.set_ylabel("mean CD, product test split")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(png, dpi=120)
    plt.close(fig)


def fit_table(models: list[tuple[str, Path, Path]], threshold: float | None = None) -> str:
    """The fit diagnostic, one line per model: ``(label, train eval folder, test eval folder)``.

    Each figure is the mean over shapes of the GenRe row's CD (1,024 points)
    at ``threshold`` (else each folder's chosen level), beside the noise floor
    of the same views; the last column is train ÷ test.
    """
    lines = ["| weights | training views | CD (train) | ÷ floor | test views | CD (test) | ÷ floor | train ÷ test |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for label, train_dir, test_dir in models:
        figures = []
        for folder in (train_dir, test_dir):
            scores = load_scores(folder, threshold=threshold)
            cd = _mean(_shape_means(scores, "cd").values())
            floor = _mean(_shape_means(scores, "floor").values())
            figures.append((len(scores), cd, floor))
        (n_tr, cd_tr, fl_tr), (n_te, cd_te, fl_te) = figures
        lines.append(f"| {label} | {n_tr} | {cd_tr:.4f} | {cd_tr / fl_tr:.2f}× | {n_te} | {cd_te:.4f} | "
                     f"{cd_te / fl_te:.2f}× | {cd_tr / cd_te:.3f} |")
    return "\n".join(lines) + "\n"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m training.eval.product", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("compare", help="side-by-side table of two 'genre eval --groups product-test' folders")
    c.add_argument("--product", required=True, help="genre eval folder of the product weights")
    c.add_argument("--protocol", required=True, help="genre eval folder of the protocol weights (the same views)")
    c.add_argument("--manifest", required=True)
    add_out(c, required=True, help="markdown file to write")
    c.add_argument("--threshold", type=float, help="score both models at this level (default: each run's thresholds.json)")
    c.add_argument("--title", default="", help="the table's heading (default: 'The product model against the protocol model')")
    c.add_argument("--product-row", default="GenRe",
                   help="the product folder's row (default GenRe; GenRe-Oracle or GenRe-SphOracle: the product weights "
                        "given the true depth, or the true depth and full spherical map); the protocol's is GenRe")
    f = sub.add_parser("fit", help="the fit diagnostic: CD on training views beside CD on the test split")
    f.add_argument("--model", nargs=3, action="append", required=True, metavar=("LABEL", "TRAIN_EVAL", "TEST_EVAL"),
                   help="a model's label and its genre eval folders on product-train and product-test views (repeatable)")
    f.add_argument("--threshold", type=float, help="score at this level (default: each folder's thresholds.json)")
    add_out(f, required=True, help="markdown file to write")
    r = sub.add_parser("rule", help="the product rule's figures: per-view mean CD of a candidate against the installed "
                                    "weights on the views both folders hold, the change and the views it is lower on")
    r.add_argument("--installed", required=True, help="genre eval folder of the installed weights")
    r.add_argument("--candidate", required=True, help="genre eval folder of the candidate (the same views)")
    r.add_argument("--threshold", type=float, help="score both at this level (default: each folder's thresholds.json)")
    r.add_argument("--row", default="GenRe", help="the row compared (default GenRe; e.g. GenRe-SphOracle)")
    r.add_argument("--candidate-row", help="the candidate's row when it is another (e.g. 'GenRe [visible_fusion=on]' "
                   "of 'genre eval --sweep visible_fusion=on'); default --row")
    r.add_argument("--by-kind", metavar="MANIFEST",
                   help="the shapes' manifest: also a line per kind (a primitive's kind, else the class)")
    v = sub.add_parser("verdict", help="the install rule (ProductRule, results/decisions.md) applied to a candidate's "
                                       "score sets against the installed file's; prints each part and the outcome")
    v.add_argument("--installed", required=True, help="folder of the installed file's score sets (" +
                   ", ".join(n for ns in RULE_SETS.values() for n in ns) + ", flat)")
    v.add_argument("--candidate", required=True, help="the same folder of the candidate's")
    v.add_argument("--level", type=float, default=ProductRule.level, help="the level both are scored at (default %(default)s)")
    v.add_argument("--no-flat", action="store_true", help="leave out the flat group's part (no flat/ folders)")
    v.add_argument("--pareto", action="store_true",
                   help="apply the second path too (ParetoRule: no worse on the product sets, flatter on the flat "
                        "group); install if either path holds")
    v.add_argument("--json", help="also write the figures here")
    k = sub.add_parser("curve", help="append a point to the learning curve (CSV + PNG beside it)")
    k.add_argument("--run", help="the product training run (its stages' checkpoints hold their processor time); "
                                 "leave out for the starting point (0 hours)")
    k.add_argument("--eval", required=True, help="genre eval folder of the run's weights on the product test split")
    k.add_argument("--label", required=True)
    k.add_argument("--csv", required=True)
    k.add_argument("--threshold", type=float, help="score at this level (default: the run's thresholds.json)")
    k.add_argument("--stages", default=",".join(CURVE_STAGES),
                   help="the run's stages behind the scored weights, comma-separated (default: all; e.g. 'depth' for "
                        "a depth stage's output scored before the later stages ran)")
    k.add_argument("--installed", action="store_true",
                   help="the scored weights were installed as 'default' (drawn on the curve's line; others are branches)")
    k.add_argument("--base-hours", type=float, default=0.0,
                   help="processor hours behind the weights the run started from (earlier runs), added to the point's hours")
    return p


def main(argv: list[str] | None = None) -> int:
    p = _parser()
    args = p.parse_args(argv)
    try:
        if args.cmd == "compare":
            manifest = json.loads(Path(args.manifest).read_text())
            text = compare_table(Path(args.product), Path(args.protocol), manifest, title=args.title,
                                 thresholds=(args.threshold, args.threshold), product_row=args.product_row)
            atomic_write_text(Path(args.out), text)
            print(text)
        elif args.cmd == "rule":
            manifest = json.loads(Path(args.by_kind).read_text()) if args.by_kind else None
            f = rule_figures(Path(args.installed), Path(args.candidate), args.threshold, args.row, args.candidate_row,
                             manifest)
            for label, g in [(None, f), *f.get("by_kind", {}).items()]:
                print(f"{'  ' + label + ': ' if label else ''}{g['views']} views: candidate {g['candidate']:.5f} against "
                      f"installed {g['installed']:.5f} ({g['change_percent']:+.2f} %), lower on {g['better']}"
                      + (f"; noise floor {g['floor']:.5f}, the candidate {g['candidate'] / g['floor']:.2f}× it"
                         if math.isfinite(g["floor"]) and g["floor"] > 0 else ""))
        elif args.cmd == "verdict":
            if args.pareto and args.no_flat:
                p.error("--pareto reads the flat group: it cannot go with --no-flat")
            result = verdict(Path(args.installed), Path(args.candidate),
                             ProductRule(level=args.level, flat_no_worse=not args.no_flat),
                             ParetoRule(level=args.level) if args.pareto else None)
            if args.json:
                atomic_write_text(Path(args.json), json.dumps(result, indent=1) + "\n")
            print(verdict_text(result), end="")
        elif args.cmd == "fit":
            text = fit_table([(label, Path(tr), Path(te)) for label, tr, te in args.model], args.threshold)
            atomic_write_text(Path(args.out), text)
            print(text, end="")
        else:
            point = curve_point(Path(args.run) if args.run else None, Path(args.eval), threshold=args.threshold,
                                base_hours=args.base_hours, stages=tuple(s.strip() for s in args.stages.split(",") if s.strip()))
            rows = append_curve(Path(args.csv), point, args.label, installed=args.installed)
            plot_curve(rows, Path(args.csv).with_suffix(".png"))
            print(json.dumps(point))
    except (OSError, ValueError, KeyError) as exc:
        print(f"{p.prog}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
