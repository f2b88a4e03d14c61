"""The evaluation protocol: Table 1's rows and groups, the point counts, and which views are scored.

Every row runs on the same rendered views (``genre data render`` + ``genre
data targets`` of the seen-test and unseen shapes); a view belongs to the
groups of its shape's class and split (the manifest entry, else the view's
JSON).
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path


from ..data.views import manifest_index

__all__ = ['BASE_COLUMNS', 'DEPTH_BLENDS', 'DIAGNOSTIC_ROWS', 'EMPTY_CD', 'EvalView', 'FLOOR', 'FSCORE_AT', 'GROUPS', 'GROUP_LABEL', 'METRICS', 'POINTS_LARGE', 'POINTS_SMALL', 'REPO_ROOT', 'REPRESENTATION', 'ROWS', 'find_eval_views', 'sample_seen_test_views', 'metric_columns', 'resolve_mesh', 'threshold_key']


ROWS = ("GenRe", "GenRe-Oracle", "GenRe-SphOracle", "3D Completion", "3D Completion-Oracle", "GenRe-1step", "Nearest training shape",
        "Truth through the representation")
# diagnostic rows, produced only when --rows names them: the depth net's error split in two. GenRe's predicted depth
# moved along the view by the median of (true - predicted) over the mask (its relief at the true offset), and the
# true depth moved by the median of (predicted - true) (the true relief at the predicted offset); and the depth net's
# error scaled down: the true depth plus a share of (predicted - true) over the mask (DEPTH_BLENDS), from GenRe-Oracle
# (0) to GenRe (1), which shows how good the depth must be before a refiner that reads its inputs wins
DEPTH_BLENDS = {"GenRe-DepthBlend-25": 0.25, "GenRe-DepthBlend-50": 0.5, "GenRe-DepthBlend-75": 0.75}
DIAGNOSTIC_ROWS = ("GenRe-OffsetOracle", "GenRe-ReliefOracle", *DEPTH_BLENDS)
REPRESENTATION = "Truth through the representation"  # the true voxel target → marching cubes: the best a refiner can do


FLOOR = "Noise floor (truth resampled)"


# Table 1's three; the product model's test split; and its training split (the fit diagnostic: a fixed sample of
# training views, CD beside the test split's: while both are alike and far from the floor, the model underfits)
GROUPS = ("test", "unseen", "unseen-pix3d", "product-test", "product-train", "flat-from-above")


GROUP_LABEL = {"test": "seen-test", "unseen": "unseen", "unseen-pix3d": "unseen-pix3d", "product-test": "product-test",
               "product-train": "product-train", "flat-from-above": "flat-from-above"}


EMPTY_CD = 1.0  # the CD given to a threshold whose mesh is empty (normalised clouds: a large error)


POINTS_SMALL = 1024


POINTS_LARGE = 10_000


FSCORE_AT = (0.01, 0.02)


METRICS = ("cd1k", "cd10k", "f1", "f2")


REPO_ROOT = Path(__file__).resolve().parents[2]


def threshold_key(t: float) -> str:
    return f"{t:.2f}"


def metric_columns(thresholds: list[float]) -> list[str]:
    return [f"{m}@{threshold_key(t)}" for t in thresholds for m in (*METRICS, "empty", "closed", "dw")]


# dw_true, dw@t: the truth's and the prediction's depth ÷ width (height along the object's up over the width
# across it, genre_backend.geometry.metrics.depth_over_width), reported for the flat-from-above group
BASE_COLUMNS = ["key", "shape", "view", "class", "groups", "azimuth", "elevation", "row", "depth_abs_err", "retrieved", "dw_true"]


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


def find_eval_views(roots: list[Path], manifest: dict | None, groups: tuple[str, ...], max_views: int | None = None) -> list[EvalView]:
    """Every complete view (render + targets + surface points) of a shape in one of ``groups``.

    The class and split come from the manifest entry of the shape (else from the view JSON).
    """
    from training.data.corpus import groups_of

    from ..data.views import find_views, load_view_meta

    index = manifest_index(manifest)
    out = []
    for root in roots:
        if not Path(root).is_dir():
            raise FileNotFoundError(f"--data: no such folder: {root} (render it with 'genre data render --split test|unseen …' and 'genre data targets')")
        per_shape: dict[str, int] = defaultdict(int)
        for ref in find_views(Path(root), surface_points=True):
            meta = load_view_meta(ref.shape_dir, ref.view)
            entry = index.get(ref.shape_id, {})
            cls = entry.get("class") or meta.get("class")
            split = entry.get("split") or meta.get("split")
            if not cls or not split:
                continue
            # the manifest's groups (the product split is a property of the whole corpus), else the class's
            gs = tuple(g for g in (entry.get("groups") or meta.get("groups") or groups_of(cls, split)) if g in groups)
            if not gs:
                continue
            if max_views is not None and per_shape[ref.shape_id] >= max_views:
                continue
            per_shape[ref.shape_id] += 1
            out.append(EvalView(ref.shape_dir, ref.view, cls, gs, meta))
    return out


def sample_seen_test_views(views_dir: Path, manifest_path: Path | None, count: int, seed: int = 0,
                           groups: tuple[str, ...] = ("test",)) -> list[EvalView]:
    """A seeded sample of ``count`` seen-test views (one per shape), in their sorted order, for the diagnostics scripts.

    Seen-test only: what the diagnostics show is used to change the model, and
    the unseen classes must stay untouched by such choices.  ``groups`` may
    name the product model's own test split instead (``("product-test",)``:
    the product model trains on every class, and its rule is that split's
    mean), or the seen classes' *training* views (``("train",)``: what the
    nets make of views they were fitted on, against seen-test, tells a net
    that cannot fit from one that does not generalise).  Raises
    FileNotFoundError when there is none.
    """
    import json

    import numpy as np

    if manifest_path is None:  # the corpus's, in the GenRe home
        from training.data.corpus import data_dir

        manifest_path = data_dir() / "corpus" / "manifest.json"
    bad = [g for g in groups if g not in ("test", "product-test", "train")]
    if bad:
        raise ValueError(f"groups: the diagnostics look at 'test' (seen-test), 'product-test' or 'train' views only, got {bad}")
    views = find_eval_views([Path(views_dir)], json.loads(Path(manifest_path).read_text()), tuple(groups), max_views=1)
    if not views:
        raise FileNotFoundError(f"no {'/'.join(groups)} views under {views_dir}")
    pick = np.random.default_rng(seed).choice(len(views), min(count, len(views)), replace=False)
    return [views[i] for i in sorted(pick)]


def resolve_mesh(path: str) -> Path:
    p = Path(path)
    if p.is_file():
        return p
    if not p.is_absolute() and (REPO_ROOT / p).is_file():
        return REPO_ROOT / p
    raise FileNotFoundError(f"mesh {path} (from a view's JSON) not found")


def load_setting_views(weights, views_dir, manifest_path, groups: tuple[str, ...], max_views: int | None = None):
    """What a script that chooses a mesh setting on views needs: ``(model, views, dataset, manifest entries)``.

    ``weights``: a weights file (eval mode model); ``views_dir``: evaluation views; ``manifest_path``: the
    corpus manifest (None: ``$GENRE_HOME/corpus/manifest.json``); ``groups``: manifest groups to keep.
    Raises ``ValueError`` when no view of those groups is there.
    """
    import json

    from genre_backend.nets.model import load_model

    from ..data.dataset import ViewDataset, ViewRef

    if manifest_path is None:
        from ..data.corpus import data_dir

        manifest_path = data_dir() / "corpus" / "manifest.json"
    manifest = json.loads(Path(manifest_path).read_text())
    entries = {e["id"]: e for e in manifest["shapes"]}
    model = load_model(weights).eval()
    views = find_eval_views([Path(views_dir)], manifest, tuple(groups), max_views=max_views)
    if not views:
        raise ValueError(f"no views of the groups {','.join(groups)} under {views_dir}")
    return model, views, ViewDataset([ViewRef(v.shape_dir, v.view) for v in views], model.config), entries
