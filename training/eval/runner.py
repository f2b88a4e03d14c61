"""Scoring views: every row's probability grid at every threshold, one CSV row per view (resumable).

**Metric** (:class:`genre_backend.geometry.metrics.CloudScorer`): the
Chamfer distance is the sum of the two mean nearest-neighbour distances (not
squared) between 1,024 points sampled on the predicted mesh and 1,024 of the
10,000 stored ground-truth surface points (posed in the view with
``rotation_cam_to_obj``), both clouds centred on their own bounding box and
scaled to a longest side of 1, in the view frame.  Also: the same at 10,000
points and the F-score at 1 % and 2 % of the (normalised) shape size, at
10,000 points.  A threshold whose mesh is empty scores ``EMPTY_CD`` and F 0.
``per_view.csv`` is appended view by view: an interrupted run continues
where it stopped.
"""

from __future__ import annotations

import csv
import math
import os
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from genre_backend import frame
from genre_backend.geometry.mesh_voxels import grid_to_surface, voxels_to_mesh
from genre_backend.geometry.metrics import CloudScorer, sample_surface

from ..data.views import surface_points_path
from .protocol import BASE_COLUMNS, EMPTY_CD, EvalView, FLOOR, POINTS_LARGE, POINTS_SMALL, metric_columns, resolve_mesh, threshold_key
from .rows import Models, predict
from .report import write_csv

__all__ = ['EMPTY', 'ModelSpec', 'Truth', 'is_closed', 'evaluate_views', 'grid_path', 'mesh_metrics', 'score_grid', 'score_view']


EMPTY = {"cd1k": EMPTY_CD, "cd10k": EMPTY_CD, "f1": 0.0, "f2": 0.0, "empty": 1.0, "closed": 0.0, "dw": math.nan}


def is_closed(faces) -> bool:
    """Whether every connected part of a mesh is a closed surface of genus 0 (no holes, no tunnels).

    Each such part has Euler characteristic V − E + F = 2; a part with a hole
    or a tunnel has less.  faces: (F, 3) int of a mesh whose parts share no
    vertices (marching cubes').
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, np.int64)
    if len(f) == 0:
        return False
    used = np.unique(f)
    edges = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1), axis=0)
    n = int(used.max()) + 1
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    parts = connected_components(graph, directed=False)[1][used]
    return len(used) - len(edges) + len(f) == 2 * len(np.unique(parts))


def mesh_metrics(verts, faces, target: CloudScorer, seed: int = 0) -> dict[str, float]:
    """Metrics of a predicted mesh (view frame) against the truth; EMPTY for no usable surface.

    ``closed`` is 1 when every part of the mesh is closed without holes or tunnels (:func:`is_closed`).
    """
    if len(faces) == 0:
        return dict(EMPTY)
    try:
        ps = sample_surface(verts, faces, POINTS_SMALL, seed=seed)
        pl = sample_surface(verts, faces, POINTS_LARGE, seed=seed + 1)
        return {**target.metrics(ps, pl), "closed": float(is_closed(faces))}
    except ValueError:  # zero area or zero extent
        return dict(EMPTY)


def score_grid(prob: torch.Tensor, thresholds: list[float], target: CloudScorer, geometry=None) -> dict[float, dict[str, float]]:
    """Metrics of the surface of a probability grid (N, N, N) at every threshold.

    With ``geometry`` (a GeometryConfig) the surface is the one the model's
    representation stands for (:func:`grid_to_surface`, what ``genre
    reconstruct`` gives); without, plain marching cubes.
    """
    out = {}
    for t in thresholds:
        v, f = grid_to_surface(prob, float(t), geometry) if geometry is not None else voxels_to_mesh(prob, float(t))
        out[t] = mesh_metrics(v, f, target)
    return out


class Truth:
    """Ground truth per shape: the stored surface points and a resampling of the mesh (the noise floor)."""

    def __init__(self):
        self._cache: dict[Path, tuple[torch.Tensor, torch.Tensor]] = {}

    def object_points(self, view: EvalView) -> tuple[torch.Tensor, torch.Tensor]:
        return self._load(view)[:2]

    def object_mesh(self, view: EvalView) -> tuple[np.ndarray, np.ndarray]:
        """The shape's mesh (vertices (V, 3), faces (F, 3)) in the object frame."""
        return self._load(view)[2]

    def _load(self, view: EvalView) -> tuple:
        if view.shape_dir not in self._cache:
            import trimesh

            with np.load(surface_points_path(view.shape_dir)) as z:
                stored = torch.from_numpy(z["points"].astype(np.float32))
            mesh = trimesh.load(resolve_mesh(view.meta["mesh"]), force="mesh", process=False)
            vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
            again = sample_surface(vertices, faces, POINTS_LARGE, seed=12345)
            self._cache = {view.shape_dir: (stored, again, (vertices, faces))}  # one shape at a time (views come sorted)
        return self._cache[view.shape_dir]

    def posed(self, view: EvalView) -> tuple[torch.Tensor, torch.Tensor]:
        rot = torch.tensor(view.meta["rotation_cam_to_obj"], dtype=torch.float64)[None]
        stored, again = self.object_points(view)
        pose = lambda p: frame.object_to_view(p.double()[None], rot)[0].float()  # noqa: E731
        return pose(stored), pose(again)

    @staticmethod
    def up(view: EvalView) -> torch.Tensor:
        """The object frame's up (+Z) in the view's frame, (3,)."""
        rot = torch.tensor(view.meta["rotation_cam_to_obj"], dtype=torch.float64)
        return rot[2].float()


def grid_path(grids_dir: Path, key: str) -> Path:
    """Where GenRe's probability grid of one view is kept for the figures."""
    return grids_dir / (key.replace("/", "__") + ".npz")


def _write_grid(grids_dir: Path, key: str, prob: torch.Tensor) -> None:
    from genre_backend.atomic import atomic_savez

    grids_dir.mkdir(exist_ok=True)
    atomic_savez(grid_path(grids_dir, key), prob=prob.numpy().astype(np.float16))


@torch.no_grad()
def _save_grids(models: Models, views: list[EvalView], grids_dir: Path, device) -> None:
    """GenRe's grid of each view that has none yet (its metrics are already in the CSV)."""
    from ..data.dataset import ViewDataset
    from ..data.views import ViewRef

    views = [v for v in views if not grid_path(grids_dir, v.key).is_file()]
    if not views:
        return
    data = ViewDataset([ViewRef(v.shape_dir, v.view) for v in views], models.config)
    for i, view in enumerate(views):
        sample = data.sample(i, None)
        out = models.genre(sample["rgb"][None].to(device), mask=sample["mask"][None].to(device))
        _write_grid(grids_dir, view.key, torch.sigmoid(out.logits)[0, 0].cpu())


def _read_done(path: Path, columns: list[str]) -> list[dict]:
    """Complete rows of an earlier run (a line cut by a kill is dropped; the file is rewritten cleanly)."""
    if not path.is_file():
        return []
    with path.open(newline="") as fh:
        reader = csv.DictReader(fh)
        if reader.fieldnames != columns:
            raise ValueError(f"{path} has other columns (another preset or version): use another --out")
        rows = [r for r in reader if r.get(columns[-1]) not in (None, "")]
    write_csv(path, rows, columns)
    return rows


@dataclass(frozen=True)
class ModelSpec:
    """How a worker process loads the models (picklable): weights paths, rows, device, the nearest index file."""

    genre: str
    completion: str | None
    onestep: str | None
    nearest_index: str | None
    wanted: tuple[str, ...]
    device: str = "cpu"
    sweeps: tuple[tuple[str, Any], ...] = ()  # Models.sweeps
    levels: tuple[float, ...] = ()  # Models.levels

    def load(self) -> Models:
        from genre_backend.nets.model import load_model

        from ..learn.baselines import NearestIndex, load_baseline

        models = Models(load_model(self.genre, self.device),
                        load_baseline(self.completion, "completion", self.device) if self.completion else None,
                        load_baseline(self.onestep, "onestep", self.device) if self.onestep else None,
                        wanted=self.wanted, sweeps=self.sweeps, levels=self.levels)
        if self.nearest_index:
            models.nearest = NearestIndex.load(self.nearest_index)
        return models


def score_view(models: Models, view: EvalView, sample: dict, truth: Truth, device, grids_dir: Path | None = None) -> list[dict]:
    """Every row of one view at every threshold, as CSV records (strings); GenRe's grid saved when ``grids_dir`` is given."""
    thresholds = models.thresholds()
    gt_large, again_large = truth.posed(view)
    gt_small, again_small = gt_large[:POINTS_SMALL], again_large[:POINTS_SMALL]
    pred = predict(models, sample, device)
    base = {"key": view.key, "shape": view.shape_dir.name, "view": view.view, "class": view.cls, "groups": "|".join(view.groups),
            "azimuth": view.meta.get("azimuth_deg", ""), "elevation": view.meta.get("elevation_deg", ""), "depth_abs_err": "", "retrieved": ""}
    target = CloudScorer(gt_small, gt_large, up=truth.up(view))
    base["dw_true"] = f"{target.dw_true:.6g}"
    floor = {**target.metrics(again_small, again_large), "closed": float("nan")}
    results = {FLOOR: {t: floor for t in thresholds}}
    for row in models.rows():
        p = pred[row]
        if grids_dir is not None and row == "GenRe":
            _write_grid(grids_dir, view.key, p["prob"])
        if "mesh" in p:  # a fitted regular shape: the same mesh at every level
            m = mesh_metrics(*p["mesh"], target)
            results[row] = {t: m for t in thresholds}
        elif "prob" in p:
            results[row] = score_grid(p["prob"], thresholds, target, p.get("geometry", models.config.geometry))
        else:
            pts = p["points"]
            m = {**target.metrics(pts[:POINTS_SMALL], pts), "closed": float("nan")}  # (points: no surface to judge)
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
                rec[f"{k}@{threshold_key(t)}"] = f"{v:.6g}"
        new.append({k: str(v) for k, v in rec.items()})
    return new


_WORKER: dict = {}


def _worker_init(spec: ModelSpec, grids_dir: str, save_grids: frozenset) -> None:
    torch.set_num_threads(1)  # one process per core
    _WORKER.update(models=spec.load(), truth=Truth(), grids_dir=Path(grids_dir), save_grids=save_grids, device=spec.device)


def _worker_shape(views: list[EvalView]) -> list[list[dict]]:
    """One shape's views (so its truth is loaded once), scored in a worker process."""
    from ..data.dataset import ViewDataset
    from ..data.views import ViewRef

    w = _WORKER
    data = ViewDataset([ViewRef(v.shape_dir, v.view) for v in views], w["models"].config)
    return [score_view(w["models"], v, data.sample(i, None), w["truth"], w["device"],
                       w["grids_dir"] if v.key in w["save_grids"] else None) for i, v in enumerate(views)]


def evaluate_views(models: Models, views: list[EvalView], out_dir: Path, *, device="cpu", progress: bool = True,
                   save_grids: set[str] | None = None, jobs: int = 1, spec: ModelSpec | None = None) -> list[dict]:
    """Score every row on every view, appending to ``out_dir/per_view.csv``; returns all rows (old and new).

    ``jobs`` > 1 scores shapes in that many worker processes (each loads the
    models from ``spec``, one thread each); rows are written by this process
    as views finish, so an interrupted run resumes the same way.
    """
    from tqdm import tqdm

    from ..data.dataset import ViewDataset
    from ..data.views import ViewRef

    thresholds = models.thresholds()
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
        write_csv(path, records, columns)
    todo = [v for v in views if v.key not in complete]
    grids_dir = out_dir / "grids"  # (made when the first grid is written)
    save_grids = set(save_grids or ())
    if save_grids:  # views scored earlier (or by another process) whose grid the figures still need
        _save_grids(models, [v for v in views if v.key in save_grids and v.key in complete], grids_dir, device)
    new_file = not path.is_file()
    fh = path.open("a", newline="")
    writer = csv.DictWriter(fh, fieldnames=columns)
    if new_file:
        writer.writeheader()

    def write(new: list[dict]) -> None:
        writer.writerows(new)  # one view's rows together, then flushed: a kill loses at most this view
        fh.flush()
        os.fsync(fh.fileno())
        records.extend(new)

    bar = tqdm(total=len(todo), desc="eval", unit="view", disable=not progress, dynamic_ncols=True)
    try:
        if jobs > 1 and len(todo) > 1:
            import multiprocessing as mp

            if spec is None:
                raise ValueError("evaluate_views: jobs > 1 needs the ModelSpec the workers load")
            by_shape: dict[Path, list[EvalView]] = defaultdict(list)
            for v in todo:
                by_shape[v.shape_dir].append(v)
            tasks = sorted(by_shape.values(), key=len, reverse=True)  # the longest first: the workers end together
            with mp.get_context("spawn").Pool(jobs, _worker_init, (spec, str(grids_dir), frozenset(save_grids))) as pool:
                for shape_rows in pool.imap_unordered(_worker_shape, tasks):
                    for new in shape_rows:
                        write(new)
                        bar.update(1)
        else:
            data = ViewDataset([ViewRef(v.shape_dir, v.view) for v in todo], models.config) if todo else None
            truth = Truth()
            for i, view in enumerate(todo):
                write(score_view(models, view, data.sample(i, None), truth, device, grids_dir if view.key in save_grids else None))
                bar.update(1)
    finally:
        bar.close()
        fh.close()
    keys = {v.key for v in views}
    return [r for r in records if r["key"] in keys and (r["row"] in rows or r["row"] == FLOOR)]
