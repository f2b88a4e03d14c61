"""Figures of ``genre eval`` (PNG): bars per class, depth error against class dissimilarity
(Figure 3, right) and a Blender gallery; :func:`make_all` makes them and the viewpoint heatmap.

Each figure function returns a line for the report; a figure that cannot be
made (no Blender, no training views) says why instead of failing the run.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from genre_backend.atomic import atomic_write_text

from .protocol import FLOOR, GROUPS, GROUP_LABEL, resolve_mesh
from ..data.views import view_paths
from .report import pyplot, save_figure
from .runner import grid_path
from .statistics import class_dissimilarity
from .heatmap import HeatmapSpec, viewpoint_heatmap

__all__ = ['bar_chart', 'depth_vs_dissimilarity', 'gallery', 'make_all', 'render_meshes']


def bar_chart(per_class: list[dict], rows: list[str], path: Path) -> str:
    """CD per class (seen t*) for every row, with 95 % intervals; classes grouped seen-test first."""

    plt = pyplot()
    order = {g: i for i, g in enumerate(GROUPS)}
    classes = sorted({(min(order[g] for g in c["groups"].split("|")), c["class"]) for c in per_class})
    classes = [c for _, c in classes]
    idx = {(c["row"], c["class"]): c for c in per_class}
    width = 0.8 / len(rows)
    fig, ax = plt.subplots(figsize=(max(6, 1.2 * len(classes) + 2), 4))
    for k, row in enumerate(rows):
        xs = np.arange(len(classes)) + (k - (len(rows) - 1) / 2) * width
        ys = [idx[(row, c)]["cd1k_seen"] if (row, c) in idx else np.nan for c in classes]
        err = [idx[(row, c)]["cd1k_seen_ci95"] if (row, c) in idx else np.nan for c in classes]
        err = [0 if not np.isfinite(e) else e for e in err]
        ax.bar(xs, ys, width, yerr=err, label=row, capsize=2, hatch="//" if row.startswith("Noise") else None,
               color="lightgrey" if row.startswith("Noise") else None)
    ax.set_xticks(np.arange(len(classes)))
    ax.set_xticklabels(classes, rotation=30, ha="right")
    ax.set_ylabel("Chamfer distance (1,024 pts, normalised)")
    ax.set_title("CD per class (threshold chosen on seen-test data)")
    ax.legend(fontsize=7, ncol=2)
    save_figure(fig, path)
    return f"- `{path.name}`: CD per class for every row (seen-test threshold), 95 % intervals."


def depth_vs_dissimilarity(per_class: list[dict], dissimilarity: dict[str, float], path: Path) -> str:
    """Figure 3 (right): GenRe's mean depth error per class against the class's dissimilarity to the training shapes."""
    plt = pyplot()
    pts = [(dissimilarity[c["class"]], c["depth_abs_err"], c["class"], c["groups"]) for c in per_class
           if c["row"] == "GenRe" and c["class"] in dissimilarity and math.isfinite(c["depth_abs_err"])]
    if not pts:
        return "- depth error vs dissimilarity: not made (no training views given with --train-views)."
    fig, ax = plt.subplots(figsize=(5, 4))
    for x, y, name, groups in pts:
        seen = "test" in groups.split("|")
        ax.scatter([x], [y], c="tab:blue" if seen else "tab:red", marker="o" if seen else "^")
        ax.annotate(name, (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
    if len(pts) >= 2:
        xs, ys = np.array([p[0] for p in pts]), np.array([p[1] for p in pts])
        r = float(np.corrcoef(xs, ys)[0, 1]) if xs.std() > 0 and ys.std() > 0 else math.nan
        ax.set_title(f"Depth error vs class dissimilarity (r = {r:.2f})")
    ax.set_xlabel("dissimilarity: mean CD to the nearest training shape")
    ax.set_ylabel("GenRe depth error (mean |Δ depth| in the mask)")
    save_figure(fig, path)
    return (f"- `{path.name}`: GenRe's depth error per class against the class's dissimilarity "
            "(mean over its shapes of the CD, object frame, to the nearest training shape); blue: seen, red: unseen.")


def render_meshes(meshes, size: int = 160, samples: int = 16):
    """:func:`genre_backend.output.blender.render_meshes`, after forgetting any training renderer (its scene is reset)."""
    from genre_backend.output.blender import render_meshes as render

    from training.render.scene import release_active_renderer

    release_active_renderer()
    return render(meshes, size=size, samples=samples)


def gallery(out: Path, views, gallery_keys: list[str], choice, samples: int, default_threshold: float, geometry) -> str:
    """Input photo | GenRe's mesh from the input view and the side | the truth from both, for a few shapes per group."""
    import trimesh
    from PIL import Image

    from genre_backend import frame
    from genre_backend.geometry.mesh_voxels import grid_to_surface

    by_key = {v.key: v for v in views}
    # what a user gets: the shipped threshold (closed meshes), else the seen-test CD choice, else the weights' own
    product = choice.get("product", {}).get("GenRe")
    t = product[0] if product else choice["seen"].get("GenRe", default_threshold)
    items, meshes = [], []
    for key in gallery_keys:
        grid_file = grid_path(out / "grids", key)
        if key not in by_key or not grid_file.is_file():
            continue
        v = by_key[key]
        with np.load(grid_file) as z:
            prob = z["prob"].astype(np.float32)
        pv, pf = grid_to_surface(prob, t, geometry)
        gt = trimesh.load(resolve_mesh(v.meta["mesh"]), force="mesh", process=False)
        rot = torch.tensor(v.meta["rotation_cam_to_obj"], dtype=torch.float64)[None]
        gv = frame.object_to_view(torch.tensor(np.asarray(gt.vertices), dtype=torch.float64)[None], rot)[0].numpy()
        items.append(v)
        meshes += [(pv, pf), (gv, np.asarray(gt.faces))]
    if not items:
        return "- gallery: not made (no saved predictions)."
    try:
        renders = render_meshes([m if len(m[1]) else (np.zeros((3, 3)), np.array([[0, 1, 2]])) for m in meshes], samples=samples)
    except Exception as exc:  # noqa: BLE001
        return f"- gallery: not made (Blender rendering failed: {type(exc).__name__}: {exc})."
    plt = pyplot()
    cols = ["input photo", "GenRe (input view)", "GenRe (side)", "truth (input view)", "truth (side)"]
    fig, axes = plt.subplots(len(items), 5, figsize=(10, 2.1 * len(items)), squeeze=False)
    for i, v in enumerate(items):
        with Image.open(view_paths(v.shape_dir, v.view)["png"]) as im:
            photo = np.asarray(im.convert("RGB"))
        pics = [photo, *renders[2 * i], *renders[2 * i + 1]]
        for j, pic in enumerate(pics):
            ax = axes[i, j]
            ax.imshow(pic)
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(cols[j], fontsize=8)
        axes[i, 0].set_ylabel(f"{v.cls}\n({GROUP_LABEL[v.groups[0]]})", fontsize=8)
    fig.tight_layout()
    save_figure(fig, out / "gallery.png")
    return f"- `gallery.png`: {len(items)} shapes (Blender Cycles, {samples} samples): input photo, GenRe's mesh at t = {t:.2f} from the input view and from the side, the truth."


def make_all(out: Path, per_class: list[dict], models, views, choice: dict, *, train_views: list[Path], train_ids: set[str] | None,
             gallery_keys: list[str], render_samples: int, heatmap: HeatmapSpec | None, device="cpu", progress: bool = True) -> list[str]:
    """Every figure (bars, depth vs dissimilarity with ``train_views``, the heatmap experiment with a
    ``heatmap`` spec, the gallery of ``gallery_keys``); returns the report lines."""
    notes = [bar_chart(per_class, models.rows() + [FLOOR], out / "bars.png")]
    if train_views:
        shapes = {v.shape_dir.name: (v.shape_dir, v.cls) for v in views}
        dis = class_dissimilarity(shapes, [Path(p) for p in train_views], train_ids, progress=progress)
        atomic_write_text(out / "dissimilarity.json", json.dumps(dis, indent=2))
        notes.append(depth_vs_dissimilarity(per_class, dis, out / "depth_vs_dissimilarity.png"))
    else:
        notes.append("- depth error vs dissimilarity: not made (pass --train-views).")
    if heatmap is not None and heatmap.shapes > 0:
        notes.append(viewpoint_heatmap(out, models, views, choice, heatmap, device))
    if gallery_keys:
        notes.append(gallery(out, views, gallery_keys, choice, render_samples, models.config.geometry.default_threshold, models.config.geometry))
    return notes
