"""Statistics of ``genre eval``: thresholds chosen on seen-test views, class and group means, intervals.

Two figures per row and class: (a) the best threshold per class (the
paper's) and (b) **one threshold per row chosen on seen-test views only**
(lowest mean CD there) and applied to every group (the honest figure).  A
class's mean is the mean of its shapes' mean CD (each shape weighs the same
whatever its number of views); the 95 % interval is Student's t over those
per-shape means; a group's mean is the mean of its class means.
"""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from genre_backend.geometry.metrics import chamfer_distance, normalize_points

from ..data.views import surface_points_path
from .protocol import GROUPS, METRICS, POINTS_SMALL, threshold_key

__all__ = ['aggregate', 'choose_hole_closing', 'choose_thresholds', 'class_dissimilarity']


def _mean_by_threshold(records: list[dict], thresholds: list[float]) -> dict[float, float]:
    """Mean CD (1,024 points) per threshold over records, each shape weighing the same."""
    out = {}
    for t in thresholds:
        per_shape = defaultdict(list)
        for r in records:
            per_shape[r["shape"]].append(float(r[f"cd1k@{threshold_key(t)}"]))
        out[t] = float(np.mean([np.mean(v) for v in per_shape.values()])) if per_shape else math.nan
    return out


def _argmin(scores: dict[float, float], default: float) -> float:
    finite = {t: s for t, s in scores.items() if math.isfinite(s)}
    if not finite:
        return default
    best = min(finite.values())
    # ties (e.g. rows without a threshold): the one closest to the default
    return min((t for t, s in finite.items() if s == best), key=lambda t: (abs(t - default), t))


CLOSED_SHARE = 0.9  # the product threshold: at least this share of seen-test meshes closed


def _closed_share(records: list[dict], thresholds: list[float]) -> dict[float, float]:
    """Share of records whose mesh is closed (no holes, no tunnels) per threshold; nan for rows without meshes."""
    out = {}
    for t in thresholds:
        vals = [float(r.get(f"closed@{threshold_key(t)}", "nan")) for r in records]
        vals = [v for v in vals if math.isfinite(v)]
        out[t] = float(np.mean(vals)) if vals else math.nan
    return out


def product_threshold(records: list[dict], thresholds: list[float], default: float) -> tuple[float, float]:
    """The threshold shipped for users, chosen on the (seen-test) ``records``: ``(t, closed share at t)``.

    The lowest mean CD among the thresholds whose meshes are closed (no
    holes or tunnels: :func:`training.eval.runner.is_closed`) in at least
    ``CLOSED_SHARE`` of the views; when none is, the most often closed (ties:
    lower CD).  A mesh with a hole costs Chamfer distance little and an
    artist a lot.
    """
    cd, closed = _mean_by_threshold(records, thresholds), _closed_share(records, thresholds)
    ok = {t: cd[t] for t in thresholds if math.isfinite(closed[t]) and closed[t] >= CLOSED_SHARE}
    if ok:
        t = _argmin(ok, default)
    elif any(math.isfinite(v) for v in closed.values()):
        t = max((t for t in thresholds if math.isfinite(closed[t])), key=lambda t: (closed[t], -cd[t]))
    else:
        return default, math.nan
    return t, closed[t]


def choose_hole_closing(closed_share: dict[int, float]) -> int:
    """The mesh setting ``geometry.hole_closing`` for users, from the seen-test closed share of each candidate k.

    The smallest k whose share of closed meshes reaches ``CLOSED_SHARE``; when
    none does, the k closed most often (ties: the smaller k).  Sealing more
    also fills narrow gaps between parts, so no more than needed.
    """
    finite = {int(k): float(v) for k, v in closed_share.items() if math.isfinite(v)}
    if not finite:
        raise ValueError("no closed share to choose a hole closing from")
    ok = [k for k in sorted(finite) if finite[k] >= CLOSED_SHARE]
    if ok:
        return ok[0]
    return max(sorted(finite), key=lambda k: (finite[k], -k))


def choose_thresholds(records: list[dict], thresholds: list[float], default: float, fixed: dict[str, float] | None = None) -> dict:
    """``{"seen": {row: t}, "per_class": {row: {class: t}}, "product": {row: [t, closed share]}, "source": ...}``.

    ``seen``: the threshold of lowest mean CD over **seen-test views only**
    (group ``test``), or ``fixed`` (from another run's thresholds.json) when
    given or when there are no seen-test views.  ``product``: the threshold
    for users, also from seen-test views only (:func:`product_threshold`).
    """
    by_row = defaultdict(list)
    for r in records:
        by_row[r["row"]].append(r)
    seen, per_class, product = {}, {}, {}
    source = "seen-test views of this run"
    for row, recs in by_row.items():
        test = [r for r in recs if "test" in r["groups"].split("|")]
        if fixed is not None:
            seen[row] = float(fixed.get(row, default))
            source = "--thresholds-from"
        elif test:
            seen[row] = _argmin(_mean_by_threshold(test, thresholds), default)
        if test:
            t, share = product_threshold(test, thresholds, default)
            if math.isfinite(share):  # (rows that give no meshes have none)
                product[row] = [t, share]
        else:
            seen[row] = default
            source = f"no seen-test views: the default threshold {default}"
        classes = defaultdict(list)
        for r in recs:
            classes[r["class"]].append(r)
        per_class[row] = {c: _argmin(_mean_by_threshold(v, thresholds), default) for c, v in classes.items()}
    return {"seen": seen, "per_class": per_class, "product": product, "source": source, "thresholds": thresholds}


def _interval(values: list[float]) -> tuple[float, float]:
    """Mean and the half-width of Student's 95 % interval (nan for fewer than 2 values)."""
    from scipy import stats

    v = np.asarray(values, np.float64)
    if len(v) < 2:
        return float(v.mean()) if len(v) else math.nan, math.nan
    half = float(stats.t.ppf(0.975, len(v) - 1) * v.std(ddof=1) / math.sqrt(len(v)))
    return float(v.mean()), half


def aggregate(records: list[dict], choice: dict) -> tuple[list[dict], list[dict], dict]:
    """Per-shape rows, per-class rows (both threshold modes) and group means.

    Returns ``(per_shape, per_class, groups)`` with ``groups[mode][group][row]`` the
    mean of class means; ``mode`` is ``seen`` (one threshold chosen on seen-test
    data) or ``per_class`` (the best per class).
    """
    shapes: dict[tuple, list[dict]] = defaultdict(list)
    for r in records:
        shapes[(r["row"], r["class"], r["shape"])].append(r)
    per_shape = []
    for (row, cls, shape), recs in sorted(shapes.items()):
        entry = {"row": row, "class": cls, "shape": shape, "groups": recs[0]["groups"], "views": len(recs)}
        for mode in ("seen", "per_class"):
            t = choice["seen"][row] if mode == "seen" else choice["per_class"][row][cls]
            entry[f"threshold_{mode}"] = t
            for m in METRICS:
                entry[f"{m}_{mode}"] = float(np.mean([float(r[f"{m}@{threshold_key(t)}"]) for r in recs]))
            entry[f"empty_{mode}"] = int(sum(float(r[f"empty@{threshold_key(t)}"]) for r in recs))
        errs = [float(r["depth_abs_err"]) for r in recs if r.get("depth_abs_err")]
        entry["depth_abs_err"] = float(np.mean(errs)) if errs else math.nan
        per_shape.append(entry)
    classes: dict[tuple, list[dict]] = defaultdict(list)
    for s in per_shape:
        classes[(s["row"], s["class"])].append(s)
    per_class = []
    for (row, cls), ss in sorted(classes.items()):
        entry = {"row": row, "class": cls, "groups": ss[0]["groups"], "shapes": len(ss), "views": sum(s["views"] for s in ss)}
        for mode in ("seen", "per_class"):
            entry[f"threshold_{mode}"] = ss[0][f"threshold_{mode}"]
            for m in METRICS:
                mean, half = _interval([s[f"{m}_{mode}"] for s in ss])
                entry[f"{m}_{mode}"] = mean
                entry[f"{m}_{mode}_ci95"] = half
            entry[f"empty_{mode}"] = sum(s[f"empty_{mode}"] for s in ss)
        errs = [s["depth_abs_err"] for s in ss if math.isfinite(s["depth_abs_err"])]
        entry["depth_abs_err"] = float(np.mean(errs)) if errs else math.nan
        per_class.append(entry)
    groups: dict = {"seen": defaultdict(dict), "per_class": defaultdict(dict)}
    for mode in groups:
        for g in GROUPS:
            for row in dict.fromkeys(c["row"] for c in per_class):
                vals = [c[f"cd1k_{mode}"] for c in per_class if c["row"] == row and g in c["groups"].split("|")]
                if vals:
                    groups[mode][g][row] = float(np.mean(vals))
    return per_shape, per_class, groups


def class_dissimilarity(eval_shape_dirs: dict[str, tuple[Path, str]], train_roots: list[Path], train_ids: set[str] | None = None,
                        points: int = POINTS_SMALL, progress: bool = False) -> dict[str, float]:
    """Per class: the mean over its shapes of the CD (object frame, normalised) to the nearest training shape."""
    from tqdm import tqdm

    train = []
    for root in train_roots:
        for d in sorted(p for p in Path(root).iterdir() if p.is_dir() and surface_points_path(p).is_file()):
            if train_ids is None or d.name in train_ids:
                with np.load(surface_points_path(d)) as z:
                    train.append((d.name, normalize_points(torch.from_numpy(z["points"][:points].astype(np.float32)))))
    if not train:
        return {}
    per_class = defaultdict(list)
    for shape, (d, cls) in tqdm(sorted(eval_shape_dirs.items()), desc="dissimilarity", unit="shape", disable=not progress):
        with np.load(surface_points_path(d)) as z:
            p = normalize_points(torch.from_numpy(z["points"][:points].astype(np.float32)))
        per_class[cls].append(min(float(chamfer_distance(p, q)) for name, q in train if name != shape))
    return {c: float(np.mean(v)) for c, v in per_class.items()}
