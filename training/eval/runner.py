"""``genre eval``: the paper's Table 1 on our data, with its baselines, oracles and figures.

Every row runs on the same rendered views (``genre data render`` + ``genre
data targets`` of the seen-test and unseen shapes):

==========================  =====================================================================
GenRe                       the full model (depth net → partial map → inpainting → voxels → refiner)
GenRe-Oracle                the true depth (and mask) in place of the depth net
GenRe-SphOracle             the true depth and the true full spherical map: the refiner's inputs
                            all true (the paper's upper bound for the refiner, nested in Oracle)
3D Completion               depth net → depth voxels → a completion net of the refiner's size
GenRe-1step                 RGB → full spherical map in one U-ResNet → GenRe's projection and refiner
                            (the depth channel from GenRe's depth net)
Nearest training shape      the training view whose depth thumbnail is closest to the predicted
                            masked depth; its shape posed as it appears in that view
Noise floor                 the truth against itself resampled (the best any row can do)
==========================  =====================================================================

Every network gets the view's true mask (the film alpha), as the paper's
evaluation did.

**Metric** (:mod:`genre_backend.geometry.metrics`): the Chamfer distance is the sum of
the two mean nearest-neighbour distances (not squared) between 1,024 points
sampled on the predicted mesh and 1,024 of the 10,000 stored ground-truth
surface points (``surface_points.npz`` posed in the view with
``rotation_cam_to_obj``), both clouds centred on their own bounding box and
scaled to a longest side of 1, in the view frame.  Also reported: the same at
10,000 points and the F-score at 1 % and 2 % of the (normalised) shape size,
at 10,000 points.  A threshold whose mesh is empty scores ``EMPTY_CD`` and F 0.

**Thresholds**: every isosurface threshold of ``GeometryConfig.thresholds()``
(the ``default`` preset: 0.30–0.90, step 0.05) is scored per view.  Two figures per row and class:
(a) the best threshold per class (the paper's) and (b) **one threshold per row
chosen on seen-test views only** (lowest mean CD there) and applied to every
group (the honest figure).  Without seen-test views in the run, pass the
``thresholds.json`` of a seen-test run with ``--thresholds-from``.

**Statistics**: a class's mean is the mean of its shapes' mean CD (each shape
weighs the same whatever its number of views); the 95 % interval is
Student's t over those per-shape means; a group's mean is the mean of its
class means.

Output ``OUT/``: ``per_view.csv`` (appended view by view: an interrupted run
continues where it stopped), ``per_shape.csv``, ``per_class.csv``,
``thresholds.json``, ``table.md`` and the figures (:mod:`training.eval.figures`).
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import math
import os
import sys
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from genre_backend import frame
from genre_backend.config import GenreConfig
from genre_backend.geometry.mesh_voxels import voxels_to_mesh
from genre_backend.geometry.metrics import chamfer_distance, fscore, normalize_points, sample_surface
from genre_backend.nets.model import GenRe, WeightsError, load_model

__all__ = [
    "ROWS",
    "FLOOR",
    "GROUPS",
    "EMPTY_CD",
    "Models",
    "EvalView",
    "find_eval_views",
    "Target",
    "cloud_metrics",
    "score_grid",
    "evaluate_views",
    "choose_thresholds",
    "aggregate",
    "format_table",
    "main",
]

ROWS = ("GenRe", "GenRe-Oracle", "GenRe-SphOracle", "3D Completion", "GenRe-1step", "Nearest training shape")
FLOOR = "Noise floor (truth resampled)"
GROUPS = ("test", "unseen", "unseen-pix3d")
GROUP_LABEL = {"test": "seen-test", "unseen": "unseen", "unseen-pix3d": "unseen-pix3d"}
EMPTY_CD = 1.0  # the CD given to a threshold whose mesh is empty (normalised clouds: a large error)
POINTS_SMALL = 1024
POINTS_LARGE = 10_000
FSCORE_AT = (0.01, 0.02)
METRICS = ("cd1k", "cd10k", "f1", "f2")
REPO_ROOT = Path(__file__).resolve().parents[2]


def _tkey(t: float) -> str:
    return f"{t:.2f}"


def metric_columns(thresholds: list[float]) -> list[str]:
    return [f"{m}@{_tkey(t)}" for t in thresholds for m in (*METRICS, "empty")]


BASE_COLUMNS = ["key", "shape", "view", "class", "groups", "azimuth", "elevation", "row", "depth_abs_err", "retrieved"]


# ---- metrics of one prediction ------------------------------------------------------------
class Target:
    """The truth of one view, normalised once, with a k-d tree of its large cloud (reused for every row and threshold)."""

    def __init__(self, gt_small: torch.Tensor, gt_large: torch.Tensor):
        from scipy.spatial import cKDTree

        self.small = normalize_points(gt_small.float())
        self.large = normalize_points(gt_large.float()).double().numpy()
        self.tree = cKDTree(self.large)

    def metrics(self, pred_small: torch.Tensor, pred_large: torch.Tensor) -> dict[str, float]:
        """CD at 1,024 points (:func:`chamfer_distance`) and, from one pair of nearest-neighbour
        queries at 10,000 points, CD and the F-scores at 1 % / 2 % (equal to :func:`fscore`)."""
        from scipy.spatial import cKDTree

        a = normalize_points(pred_small.float())
        big = normalize_points(pred_large.float()).double().numpy()
        d_pg = self.tree.query(big)[0]
        d_gp = cKDTree(big).query(self.large)[0]
        out = {"cd1k": float(chamfer_distance(a, self.small)), "cd10k": float(d_pg.mean() + d_gp.mean())}
        for name, t in zip(("f1", "f2"), FSCORE_AT):
            p, r = float((d_pg <= t).mean()), float((d_gp <= t).mean())
            out[name] = 0.0 if p + r == 0 else 2 * p * r / (p + r)
        out["empty"] = 0.0
        return out


def cloud_metrics(pred_small: torch.Tensor, pred_large: torch.Tensor, gt_small: torch.Tensor, gt_large: torch.Tensor) -> dict[str, float]:
    """CD at 1,024 and 10,000 points and F-scores at 1 % / 2 % (10,000 points), each cloud normalised."""
    return Target(gt_small, gt_large).metrics(pred_small, pred_large)


EMPTY = {"cd1k": EMPTY_CD, "cd10k": EMPTY_CD, "f1": 0.0, "f2": 0.0, "empty": 1.0}


def mesh_metrics(verts, faces, target: Target, seed: int = 0) -> dict[str, float]:
    """Metrics of a predicted mesh (view frame) against the truth; EMPTY for no usable surface."""
    if len(faces) == 0:
        return dict(EMPTY)
    try:
        ps = sample_surface(verts, faces, POINTS_SMALL, seed=seed)
        pl = sample_surface(verts, faces, POINTS_LARGE, seed=seed + 1)
        return target.metrics(ps, pl)
    except ValueError:  # zero area or zero extent
        return dict(EMPTY)


def score_grid(prob: torch.Tensor, thresholds: list[float], target: Target) -> dict[float, dict[str, float]]:
    """Metrics of the marching-cubes mesh of a probability grid (N, N, N) at every threshold."""
    out = {}
    for t in thresholds:
        v, f = voxels_to_mesh(prob, float(t))
        out[t] = mesh_metrics(v, f, target)
    return out


# ---- the models ---------------------------------------------------------------------------
@dataclass
class Models:
    genre: GenRe
    completion: torch.nn.Module | None = None
    onestep: torch.nn.Module | None = None
    nearest: object | None = None  # training.learn.baselines.NearestIndex
    wanted: tuple[str, ...] = ROWS  # the rows to produce

    @property
    def config(self) -> GenreConfig:
        return self.genre.config

    def rows(self) -> list[str]:
        rows = ["GenRe", "GenRe-Oracle", "GenRe-SphOracle"]
        if self.completion is not None:
            rows.append("3D Completion")
        if self.onestep is not None:
            rows.append("GenRe-1step")
        if self.nearest is not None:
            rows.append("Nearest training shape")
        return [r for r in rows if r in self.wanted]

    def check(self) -> None:
        g = self.config.geometry
        for name, net in (("3D Completion", self.completion), ("GenRe-1step", self.onestep)):
            if net is not None and (net.config.geometry.image_size, net.config.geometry.sph_size, net.config.geometry.voxel_size) != (g.image_size, g.sph_size, g.voxel_size):
                raise WeightsError(f"{name}: its weights were made for another preset than GenRe's ({net.config.preset} vs {self.config.preset})")


@torch.no_grad()
def predict(models: Models, sample: dict[str, torch.Tensor], device) -> dict[str, dict]:
    """Every row's prediction for one view: {row: {"prob": (N³) or "points": (P, 3)}, plus "depth"}."""
    m = models.genre
    rgb = sample["rgb"][None].to(device)
    mask = sample["mask"][None].to(device)
    depth = sample["depth"][None].to(device)
    full = sample["full_sph"][None].to(device)
    out: dict[str, dict] = {}
    g = m(rgb, mask=mask)
    out["GenRe"] = {"prob": torch.sigmoid(g["logits"])[0, 0].cpu()}
    pred_depth = g["masked_depth"]
    valid = mask & (depth > 0)
    err = float(((g["depth"] - depth).abs() * valid).sum() / valid.sum().clamp(min=1))
    out["depth_abs_err"] = err
    if "GenRe-Oracle" in models.wanted:
        out["GenRe-Oracle"] = {"prob": torch.sigmoid(m(rgb, mask=mask, depth=depth)["logits"])[0, 0].cpu()}
    if "GenRe-SphOracle" in models.wanted:
        out["GenRe-SphOracle"] = {"prob": torch.sigmoid(m(rgb, mask=mask, depth=depth, full_sph=full)["logits"])[0, 0].cpu()}
    if models.completion is not None:
        out["3D Completion"] = {"prob": torch.sigmoid(models.completion(rgb, mask=mask)["logits"])[0, 0].cpu()}
    if models.onestep is not None:
        sph = models.onestep(rgb).clamp(0.0, 1.0)
        logits = m.refine(m.sph_voxels(sph), m.depth_voxels(pred_depth))
        out["GenRe-1step"] = {"prob": torch.sigmoid(logits)[0, 0].cpu()}
    if models.nearest is not None:
        i = models.nearest.query(pred_depth)[0]
        out["Nearest training shape"] = {"points": models.nearest.view_points(i), "retrieved": f"{models.nearest.shape_id(i)}/{models.nearest.views[i]}"}
    return out


# ---- the views ----------------------------------------------------------------------------
@dataclass(frozen=True)
class EvalView:
    shape_dir: Path
    view: int
    cls: str
    groups: tuple[str, ...]
    meta: dict

    @property
    def key(self) -> str:
        return f"{self.shape_dir.name}/{self.view:03d}"


def _manifest_index(manifest: dict | None) -> dict[str, dict]:
    if not manifest:
        return {}
    return {s["id"]: s for s in manifest.get("shapes", [])}


def find_eval_views(roots: list[Path], manifest: dict | None, groups: tuple[str, ...], max_views: int | None = None) -> list[EvalView]:
    """Every complete view (render + targets + surface points) of a shape in one of ``groups``.

    The class and split come from the manifest entry of the shape (else from the view JSON).
    """
    from training.data.corpus import groups_of

    from ..data.dataset import find_views

    index = _manifest_index(manifest)
    out = []
    for root in roots:
        if not Path(root).is_dir():
            raise FileNotFoundError(f"--data: no such folder: {root} (render it with 'genre data render --split test|unseen …' and 'genre data targets')")
        per_shape: dict[str, int] = defaultdict(int)
        for ref in find_views(Path(root)):
            if not (ref.shape_dir / "surface_points.npz").is_file():
                continue
            meta = json.loads((ref.shape_dir / f"view_{ref.view:03d}.json").read_text())
            entry = index.get(ref.shape_id, {})
            cls = entry.get("class") or meta.get("class")
            split = entry.get("split") or meta.get("split")
            if not cls or not split:
                continue
            gs = tuple(g for g in groups_of(cls, split) if g in groups)
            if not gs:
                continue
            if max_views is not None and per_shape[ref.shape_id] >= max_views:
                continue
            per_shape[ref.shape_id] += 1
            out.append(EvalView(ref.shape_dir, ref.view, cls, gs, meta))
    return out


def _resolve_mesh(path: str) -> Path:
    p = Path(path)
    if p.is_file():
        return p
    if not p.is_absolute() and (REPO_ROOT / p).is_file():
        return REPO_ROOT / p
    raise FileNotFoundError(f"mesh {path} (from a view's JSON) not found")


class Truth:
    """Ground truth per shape: the stored surface points and a resampling of the mesh (the noise floor)."""

    def __init__(self):
        self._cache: dict[Path, tuple[torch.Tensor, torch.Tensor]] = {}

    def object_points(self, view: EvalView) -> tuple[torch.Tensor, torch.Tensor]:
        if view.shape_dir not in self._cache:
            import trimesh

            with np.load(view.shape_dir / "surface_points.npz") as z:
                stored = torch.from_numpy(z["points"].astype(np.float32))
            mesh = trimesh.load(_resolve_mesh(view.meta["mesh"]), force="mesh", process=False)
            again = sample_surface(np.asarray(mesh.vertices), np.asarray(mesh.faces), POINTS_LARGE, seed=12345)
            self._cache = {view.shape_dir: (stored, again)}  # one shape at a time (views come sorted)
        return self._cache[view.shape_dir]

    def posed(self, view: EvalView) -> tuple[torch.Tensor, torch.Tensor]:
        rot = torch.tensor(view.meta["rotation_cam_to_obj"], dtype=torch.float64)[None]
        stored, again = self.object_points(view)
        pose = lambda p: frame.object_to_view(p.double()[None], rot)[0].float()  # noqa: E731
        return pose(stored), pose(again)


def grid_path(grids_dir: Path, key: str) -> Path:
    """Where GenRe's probability grid of one view is kept for the figures."""
    return grids_dir / (key.replace("/", "__") + ".npz")


def _write_grid(grids_dir: Path, key: str, prob: torch.Tensor) -> None:
    grids_dir.mkdir(exist_ok=True)
    np.savez_compressed(grid_path(grids_dir, key), prob=prob.numpy().astype(np.float16))


@torch.no_grad()
def _save_grids(models: Models, views: list["EvalView"], grids_dir: Path, device) -> None:
    """GenRe's grid of each view that has none yet (its metrics are already in the CSV)."""
    from ..data.dataset import ViewDataset, ViewRef

    views = [v for v in views if not grid_path(grids_dir, v.key).is_file()]
    if not views:
        return
    data = ViewDataset([ViewRef(v.shape_dir, v.view) for v in views], models.config)
    for i, view in enumerate(views):
        sample = data.sample(i, None)
        out = models.genre(sample["rgb"][None].to(device), mask=sample["mask"][None].to(device))
        _write_grid(grids_dir, view.key, torch.sigmoid(out["logits"])[0, 0].cpu())


# ---- the per-view CSV (resumable) ---------------------------------------------------------
def _read_done(path: Path, columns: list[str]) -> list[dict]:
    """Complete rows of an earlier run (a line cut by a kill is dropped; the file is rewritten cleanly)."""
    if not path.is_file():
        return []
    with path.open(newline="") as fh:
        reader = csv.DictReader(fh)
        if reader.fieldnames != columns:
            raise ValueError(f"{path} has other columns (another preset or version): use another --out")
        rows = [r for r in reader if r.get(columns[-1]) not in (None, "")]
    _write_csv(path, rows, columns)
    return rows


def evaluate_views(models: Models, views: list[EvalView], out_dir: Path, *, device="cpu", progress: bool = True,
                   save_grids: set[str] | None = None) -> list[dict]:
    """Score every row on every view, appending to ``out_dir/per_view.csv``; returns all rows (old and new)."""
    from tqdm import tqdm

    from ..data.dataset import ViewDataset, ViewRef

    thresholds = models.config.geometry.thresholds()
    columns = BASE_COLUMNS + metric_columns(thresholds)
    path = out_dir / "per_view.csv"
    records = _read_done(path, columns)
    rows = models.rows()
    done = defaultdict(set)
    for r in records:
        done[r["key"]].add(r["row"])
    complete = {k for k, got in done.items() if set(rows + [FLOOR]) <= got}
    if any(r["key"] not in complete for r in records):  # a view cut short by a kill: drop its rows, redo it
        records = [r for r in records if r["key"] in complete]
        _write_csv(path, records, columns)
    todo = [v for v in views if v.key not in complete]
    grids_dir = out_dir / "grids"
    if save_grids:  # views scored earlier (or by another process) whose grid the figures still need
        _save_grids(models, [v for v in views if v.key in save_grids and v.key in complete], grids_dir, device)
    data = ViewDataset([ViewRef(v.shape_dir, v.view) for v in todo], models.config) if todo else None
    truth = Truth()
    new_file = not path.is_file()
    fh = path.open("a", newline="")
    writer = csv.DictWriter(fh, fieldnames=columns)
    if new_file:
        writer.writeheader()
    try:
        for i, view in enumerate(tqdm(todo, desc="eval", unit="view", disable=not progress, dynamic_ncols=True)):
            sample = data.sample(i, None)
            gt_large, again_large = truth.posed(view)
            gt_small, again_small = gt_large[:POINTS_SMALL], again_large[:POINTS_SMALL]
            pred = predict(models, sample, device)
            base = {"key": view.key, "shape": view.shape_dir.name, "view": view.view, "class": view.cls, "groups": "|".join(view.groups),
                    "azimuth": view.meta.get("azimuth_deg", ""), "elevation": view.meta.get("elevation_deg", ""), "depth_abs_err": "", "retrieved": ""}
            target = Target(gt_small, gt_large)
            floor = target.metrics(again_small, again_large)
            results = {FLOOR: {t: floor for t in thresholds}}
            for row in rows:
                p = pred[row]
                if "prob" in p:
                    results[row] = score_grid(p["prob"], thresholds, target)
                    if save_grids is not None and view.key in save_grids and row == "GenRe":
                        _write_grid(grids_dir, view.key, p["prob"])
                else:
                    pts = p["points"]
                    m = target.metrics(pts[:POINTS_SMALL], pts)
                    results[row] = {t: m for t in thresholds}
            new = []
            for row, per_t in results.items():
                rec = dict(base, row=row)
                if row == "GenRe":
                    rec["depth_abs_err"] = f"{pred['depth_abs_err']:.6g}"
                if row == "Nearest training shape":
                    rec["retrieved"] = pred[row]["retrieved"]
                for t, mt in per_t.items():
                    for k, v in mt.items():
                        rec[f"{k}@{_tkey(t)}"] = f"{v:.6g}"
                new.append({k: str(v) for k, v in rec.items()})
            writer.writerows(new)  # one view's rows together, then flushed: a kill loses at most this view
            fh.flush()
            os.fsync(fh.fileno())
            records.extend(new)
    finally:
        fh.close()
    keys = {v.key for v in views}
    return [r for r in records if r["key"] in keys and (r["row"] in rows or r["row"] == FLOOR)]


# ---- thresholds and statistics ------------------------------------------------------------
def _mean_by_threshold(records: list[dict], thresholds: list[float]) -> dict[float, float]:
    """Mean CD (1,024 points) per threshold over records, each shape weighing the same."""
    out = {}
    for t in thresholds:
        per_shape = defaultdict(list)
        for r in records:
            per_shape[r["shape"]].append(float(r[f"cd1k@{_tkey(t)}"]))
        out[t] = float(np.mean([np.mean(v) for v in per_shape.values()])) if per_shape else math.nan
    return out


def _argmin(scores: dict[float, float], default: float) -> float:
    finite = {t: s for t, s in scores.items() if math.isfinite(s)}
    if not finite:
        return default
    best = min(finite.values())
    # ties (e.g. rows without a threshold): the one closest to the default
    return min((t for t, s in finite.items() if s == best), key=lambda t: (abs(t - default), t))


def choose_thresholds(records: list[dict], thresholds: list[float], default: float, fixed: dict[str, float] | None = None) -> dict:
    """``{"seen": {row: t}, "per_class": {row: {class: t}}, "source": ...}``.

    ``seen``: the threshold of lowest mean CD over **seen-test views only**
    (group ``test``), or ``fixed`` (from another run's thresholds.json) when
    given or when there are no seen-test views.
    """
    by_row = defaultdict(list)
    for r in records:
        by_row[r["row"]].append(r)
    seen, per_class = {}, {}
    source = "seen-test views of this run"
    for row, recs in by_row.items():
        test = [r for r in recs if "test" in r["groups"].split("|")]
        if fixed is not None:
            seen[row] = float(fixed.get(row, default))
            source = "--thresholds-from"
        elif test:
            seen[row] = _argmin(_mean_by_threshold(test, thresholds), default)
        else:
            seen[row] = default
            source = f"no seen-test views: the default threshold {default}"
        classes = defaultdict(list)
        for r in recs:
            classes[r["class"]].append(r)
        per_class[row] = {c: _argmin(_mean_by_threshold(v, thresholds), default) for c, v in classes.items()}
    return {"seen": seen, "per_class": per_class, "source": source, "thresholds": thresholds}


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
                entry[f"{m}_{mode}"] = float(np.mean([float(r[f"{m}@{_tkey(t)}"]) for r in recs]))
            entry[f"empty_{mode}"] = int(sum(float(r[f"empty@{_tkey(t)}"]) for r in recs))
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


def _write_csv(path: Path, rows: list[dict], columns: list[str] | None = None) -> None:
    """Write ``rows`` atomically (temporary file, then rename); floats with 6 significant digits.

    Without ``columns`` the first row's keys are the header and no rows means no file.
    """
    if not rows and columns is None:
        return
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=columns or list(rows[0]))
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    os.replace(tmp, path)


def _fmt(v: float, half: float | None = None) -> str:
    if v is None or not math.isfinite(v):
        return "–"
    return f"{v:.3f}" if half is None or not math.isfinite(half) else f"{v:.3f} ± {half:.3f}"


def format_table(per_class: list[dict], groups: dict, choice: dict, rows: list[str], header: str = "") -> str:
    """The Markdown report: group means (both threshold modes), then per group a per-class table."""
    rows = list(rows) + [FLOOR]
    present = [g for g in GROUPS if any(g in c["groups"].split("|") for c in per_class)]
    lines = [header] if header else []
    lines += [
        "Chamfer distance (CD): sum of the two mean nearest-neighbour distances (not squared), "
        f"{POINTS_SMALL:,} points per shape (CD10k: {POINTS_LARGE:,}), each cloud centred on its bounding box and scaled "
        "to a longest side of 1, in the view frame. F@1%/F@2%: F-score at 0.01/0.02 of that size (10,000 points). "
        "Lower CD is better; the noise floor is the truth against itself resampled. "
        f"*Seen t*: one threshold per row chosen on seen-test views only ({choice['source']}), applied everywhere. "
        f"*Best t/class*: the best of {min(choice['thresholds']):.2f}–{max(choice['thresholds']):.2f} per class (the paper's protocol). "
        "Class means weigh shapes equally; ± is the 95 % t-interval over shapes; group means are means of class means.",
        "",
        "## Group means (CD, 1,024 points)",
        "",
        "| method | seen t* | " + " | ".join(f"{GROUP_LABEL[g]} (seen t*)" for g in present) + " | " + " | ".join(f"{GROUP_LABEL[g]} (best t/class)" for g in present) + " |",
        "|---|---|" + "---|" * (2 * len(present)),
    ]
    for row in rows:
        t = "–" if row in (FLOOR, "Nearest training shape") else f"{choice['seen'].get(row, math.nan):.2f}"
        cells = [_fmt(groups["seen"][g].get(row, math.nan)) for g in present] + [_fmt(groups["per_class"][g].get(row, math.nan)) for g in present]
        lines.append(f"| {row} | {t} | " + " | ".join(cells) + " |")
    for g in present:
        classes = sorted({c["class"] for c in per_class if g in c["groups"].split("|")})
        lines += ["", f"## {GROUP_LABEL[g]}: CD per class (seen t*), mean ± 95 % interval", ""]
        lines.append("| method | " + " | ".join(classes) + " | mean |")
        lines.append("|---|" + "---|" * (len(classes) + 1))
        idx = {(c["row"], c["class"]): c for c in per_class}
        for row in rows:
            cells = [_fmt(idx[(row, c)]["cd1k_seen"], idx[(row, c)]["cd1k_seen_ci95"]) if (row, c) in idx else "–" for c in classes]
            lines.append(f"| {row} | " + " | ".join(cells) + f" | {_fmt(groups['seen'][g].get(row, math.nan))} |")
        counts = [f"{c}: {idx[(rows[0], c)]['shapes']} shapes / {idx[(rows[0], c)]['views']} views" for c in classes if (rows[0], c) in idx]
        lines += ["", "Counts: " + "; ".join(counts) + "."]
        lines += ["", f"### {GROUP_LABEL[g]}: details", "",
                  "| method | class | shapes | views | CD (seen t*) | CD (best t/class) | t/class | CD10k | F@1% | F@2% | empty meshes |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for row in rows:
            for c in classes:
                e = idx.get((row, c))
                if e is None:
                    continue
                tc = "–" if row in (FLOOR, "Nearest training shape") else f"{e['threshold_per_class']:.2f}"
                lines.append(f"| {row} | {c} | {e['shapes']} | {e['views']} | {_fmt(e['cd1k_seen'], e['cd1k_seen_ci95'])} | {_fmt(e['cd1k_per_class'])} | {tc} | "
                             f"{_fmt(e['cd10k_seen'])} | {_fmt(e['f1_seen'])} | {_fmt(e['f2_seen'])} | {e['empty_seen']} |")
    return "\n".join(lines) + "\n"


# ---- class dissimilarity (Figure 3, right) ------------------------------------------------
def class_dissimilarity(eval_shape_dirs: dict[str, tuple[Path, str]], train_roots: list[Path], train_ids: set[str] | None = None,
                        points: int = POINTS_SMALL, progress: bool = False) -> dict[str, float]:
    """Per class: the mean over its shapes of the CD (object frame, normalised) to the nearest training shape."""
    from tqdm import tqdm

    train = []
    for root in train_roots:
        for d in sorted(p for p in Path(root).iterdir() if p.is_dir() and (p / "surface_points.npz").is_file()):
            if train_ids is None or d.name in train_ids:
                with np.load(d / "surface_points.npz") as z:
                    train.append((d.name, normalize_points(torch.from_numpy(z["points"][:points].astype(np.float32)))))
    if not train:
        return {}
    per_class = defaultdict(list)
    for shape, (d, cls) in tqdm(sorted(eval_shape_dirs.items()), desc="dissimilarity", unit="shape", disable=not progress):
        with np.load(d / "surface_points.npz") as z:
            p = normalize_points(torch.from_numpy(z["points"][:points].astype(np.float32)))
        per_class[cls].append(min(float(chamfer_distance(p, q)) for name, q in train if name != shape))
    return {c: float(np.mean(v)) for c, v in per_class.items()}


# ---- command line ---------------------------------------------------------------------------
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
    p.add_argument("--weights", help="GenRe weights (default: RUN/joint/best.safetensors, else RUN/refine/best.safetensors)")
    p.add_argument("--completion", help="3D Completion baseline weights (default RUN/completion/best.safetensors)")
    p.add_argument("--onestep", help="GenRe-1step weights (default RUN/onestep/best.safetensors)")
    p.add_argument("--train-views", nargs="*", default=[], help="training views (nearest-shape baseline and class dissimilarity)")
    p.add_argument("--train-shapes", help="file of training shape ids (default: every shape in --train-views)")
    p.add_argument("--manifest", help="manifest JSON for classes and splits (default data/corpus/manifest.json if present)")
    p.add_argument("--out", help="results folder (default results/<run name>)")
    p.add_argument("--groups", default=",".join(GROUPS), help="groups to evaluate: test (seen-test), unseen, unseen-pix3d")
    p.add_argument("--rows", help=f"comma-separated rows (default all): {', '.join(ROWS)}")
    p.add_argument("--max-views", type=int, default=None, help="at most this many views per shape")
    p.add_argument("--thresholds-from", help="thresholds.json of a run on seen-test data (when this run has none)")
    p.add_argument("--device", default="cpu")
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


def main(argv: list[str] | None = None, prog: str = "genre eval") -> int:
    args = _parser(prog).parse_args(argv)
    t_start = time.perf_counter()
    rows_wanted = [r.strip() for r in args.rows.split(",")] if args.rows else list(ROWS)
    unknown = [r for r in rows_wanted if r not in ROWS]
    if unknown:
        return _fail(prog, f"--rows: unknown {unknown}; choose from {list(ROWS)}")
    groups = tuple(g.strip() for g in args.groups.split(","))
    if any(g not in GROUPS for g in groups):
        return _fail(prog, f"--groups: choose from {list(GROUPS)}")
    if not args.run and not args.weights:
        return _fail(prog, "give the training run (--run RUN) or the GenRe weights (--weights FILE)")
    paths = _weights_paths(args)
    need = {"genre": True, "completion": "3D Completion" in rows_wanted, "onestep": "GenRe-1step" in rows_wanted}
    missing = [f"{k} weights not found: {paths[k]} ({HINTS[k]})" for k, needed in need.items() if needed and (paths[k] is None or not paths[k].is_file())]
    if "Nearest training shape" in rows_wanted and not args.train_views:
        missing.append("the nearest-training-shape row needs the training views: pass --train-views DIR (or leave the row out with --rows)")
    if missing:
        return _fail(prog, "; ".join(missing))
    manifest = None
    if args.manifest:
        manifest = json.loads(Path(args.manifest).read_text())
    else:
        try:
            from training.data.corpus import load_manifest

            manifest = load_manifest()
        except FileNotFoundError:
            manifest = None
    try:
        views = find_eval_views([Path(d) for d in args.data], manifest, groups, args.max_views)
    except FileNotFoundError as exc:
        return _fail(prog, str(exc))
    if not views:
        return _fail(prog, f"no complete eval views (render + targets + surface_points.npz) of groups {list(groups)} under {args.data}; "
                     "render them with 'genre data render --shapes data/corpus/manifest.json --split test|unseen --views 4 --out DIR' and 'genre data targets --views DIR'")
    try:
        genre = load_model(paths["genre"], args.device)
        from ..learn.baselines import NearestIndex, build_nearest_index, load_baseline

        completion = load_baseline(paths["completion"], "completion", args.device) if need["completion"] else None
        onestep = load_baseline(paths["onestep"], "onestep", args.device) if need["onestep"] else None
        models = Models(genre, completion, onestep, wanted=tuple(rows_wanted))
        models.check()
    except WeightsError as exc:
        return _fail(prog, str(exc))
    out = Path(args.out) if args.out else Path("results") / (Path(args.run).name if args.run else Path(args.weights).stem)
    out.mkdir(parents=True, exist_ok=True)
    train_ids = None
    if args.train_shapes:
        train_ids = {line.strip() for line in Path(args.train_shapes).read_text().splitlines() if line.strip()}
    # the run's identity: the same weights and views, or a clear error instead of mixed results
    ident = {"weights": {k: (str(v), _digest(v)) for k, v in paths.items() if need[k] and v is not None},
             "preset": genre.config.preset, "rows": rows_wanted, "train_views": [str(p) for p in args.train_views]}
    ident = json.loads(json.dumps(ident))  # as it reads back (lists, not tuples)
    ident_path = out / "eval_config.json"
    if ident_path.is_file() and json.loads(ident_path.read_text()) != ident:
        if (out / "per_view.csv").is_file():
            return _fail(prog, f"{out} holds results of other weights or rows ({ident_path}); use another --out or delete it")
    ident_path.write_text(json.dumps(ident, indent=2))
    if "Nearest training shape" in rows_wanted:
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
            return _fail(prog, str(exc))
    # the gallery's views: the first view of the first shapes of each group
    gallery_keys: list[str] = []
    if args.gallery > 0 and not args.no_figures:
        for g in groups:
            firsts = {}
            for v in views:
                if g in v.groups and v.shape_dir.name not in firsts:
                    firsts[v.shape_dir.name] = v.key
            gallery_keys += [k for k in list(firsts.values())[: args.gallery] if k not in gallery_keys]
    records = evaluate_views(models, views, out, device=args.device, progress=not args.no_progress, save_grids=set(gallery_keys))
    thresholds = genre.config.geometry.thresholds()
    fixed = None
    if args.thresholds_from:
        fixed = json.loads(Path(args.thresholds_from).read_text())["seen"]
    choice = choose_thresholds(records, thresholds, genre.config.geometry.default_threshold, fixed)
    per_shape, per_class, group_means = aggregate(records, choice)
    (out / "thresholds.json").write_text(json.dumps(choice, indent=2))
    _write_csv(out / "per_shape.csv", per_shape)
    _write_csv(out / "per_class.csv", per_class)
    n_shapes = len({v.shape_dir.name for v in views})
    header = (f"# GenRe evaluation: {out.name}\n\n{len(views)} views of {n_shapes} shapes; preset {genre.config.preset}; "
              f"weights {paths['genre']}.\n\nCommand: `genre eval {' '.join(argv if argv is not None else sys.argv[1:])}`\n")
    table = format_table(per_class, group_means, choice, models.rows(), header)
    notes = []
    if not args.no_figures:
        from . import figures

        notes += figures.make_all(out, per_class, group_means, models, views, records, choice, args, train_ids, gallery_keys)
    if notes:
        table += "\n## Figures\n\n" + "\n".join(notes) + "\n"
    tmp = out / "table.md.tmp"
    tmp.write_text(table)
    os.replace(tmp, out / "table.md")
    print(table)
    print(f"wrote {out}/ in {time.perf_counter() - t_start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
