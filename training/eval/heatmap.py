"""The viewpoint experiment (Figure 7): GenRe's error over a grid of azimuths and elevations.

Not a plot of existing results: it renders a few shapes from a grid of views,
builds their targets, scores every view and draws the heatmap.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from genre_backend.geometry.metrics import CloudScorer

from ..data.views import view_paths
from .protocol import EvalView, POINTS_SMALL, resolve_mesh
from .rows import predict
from .runner import Truth, score_grid
from .report import pyplot, save_figure

__all__ = ['viewpoint_heatmap']


@dataclass(frozen=True)
class HeatmapSpec:
    """The experiment: ``shapes`` shapes of class ``cls``, ``azimuths`` evenly spaced azimuths at each of ``elevations``."""

    cls: str
    shapes: int
    elevations: tuple[float, ...]
    azimuths: int
    render_samples: int = 16


def viewpoint_heatmap(out: Path, models, views, choice, spec: HeatmapSpec, device="cpu") -> str:
    """Render shapes of one class on an elevation × azimuth grid, run GenRe, plot the median CD per cell."""
    from training.data.targets import build_targets
    from training.data.views import ShapeEntry
    from training.render.scene import BlenderRenderer, RenderSettings, render_shape

    cls = spec.cls
    shapes = {}
    for v in views:
        if v.cls == cls and v.shape_dir.name not in shapes:
            shapes[v.shape_dir.name] = v
    shapes = dict(list(shapes.items())[: spec.shapes])
    if not shapes:
        return f"- viewpoint heatmap: not made (no {cls!r} shapes among the eval views)."
    elevations = list(spec.elevations)
    azimuths = [360.0 * k / spec.azimuths for k in range(spec.azimuths)]
    grid = [(a, e) for e in elevations for a in azimuths]
    root = out / "grid_views"
    config = models.config
    renderer = None
    try:
        for sid, v in shapes.items():
            if all(view_paths(root / sid, k)["json"].is_file() for k in range(len(grid))):
                continue
            if renderer is None:
                renderer = BlenderRenderer(config, RenderSettings(samples=spec.render_samples), scratch_dir=out / ".render_scratch")
            render_shape(renderer, ShapeEntry(sid, resolve_mesh(v.meta["mesh"]), cls, v.meta.get("split")), grid, root, seed=7)
    except Exception as exc:  # noqa: BLE001
        return f"- viewpoint heatmap: not made (Blender rendering failed: {type(exc).__name__}: {exc})."
    finally:
        if renderer is not None:
            renderer.close()
    build_targets(root, config, progress=False)
    from ..data.dataset import ViewDataset
    from ..data.views import ViewRef, load_view_meta

    t = choice["seen"].get("GenRe", config.geometry.default_threshold)
    cells = defaultdict(list)
    truth = Truth()
    csv_rows = ["shape,view,azimuth,elevation,cd1k"]
    for sid, v in shapes.items():
        for k, (az, el) in enumerate(grid):
            meta = load_view_meta(root / sid, k)
            ev = EvalView(root / sid, k, cls, v.groups, meta)
            sample = ViewDataset([ViewRef(root / sid, k)], config)[0]
            pred = predict(type(models)(models.genre), sample, device)
            gt_large, _ = truth.posed(ev)
            cd = score_grid(pred["GenRe"]["prob"], [t], CloudScorer(gt_large[:POINTS_SMALL], gt_large))[t]["cd1k"]
            cells[(el, az)].append(cd)
            csv_rows.append(f"{sid},{k},{az:.1f},{el:.1f},{cd:.6g}")
    (out / "viewpoint_heatmap.csv").write_text("\n".join(csv_rows) + "\n")
    med = np.array([[np.median(cells[(e, a)]) for a in azimuths] for e in elevations])
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(1.0 + 0.7 * len(azimuths), 1.0 + 0.6 * len(elevations)))
    im = ax.imshow(med, cmap="viridis", origin="lower", aspect="auto")
    ax.set_xticks(range(len(azimuths)))
    ax.set_xticklabels([f"{a:.0f}" for a in azimuths])
    ax.set_yticks(range(len(elevations)))
    ax.set_yticklabels([f"{e:.0f}" for e in elevations])
    ax.set_xlabel("azimuth (°)")
    ax.set_ylabel("elevation (°)")
    for i in range(len(elevations)):
        for j in range(len(azimuths)):
            ax.text(j, i, f"{med[i, j]:.3f}", ha="center", va="center", fontsize=6, color="w")
    fig.colorbar(im, ax=ax, label="median CD")
    ax.set_title(f"GenRe on {len(shapes)} {cls} shape(s): median CD by viewpoint (t = {t:.2f})")
    save_figure(fig, out / "viewpoint_heatmap.png")
    return (f"- `viewpoint_heatmap.png`: median CD of GenRe over {len(shapes)} {cls} shape(s) rendered on a "
            f"{len(elevations)} elevation × {len(azimuths)} azimuth grid (`grid_views/`, `viewpoint_heatmap.csv`).")
