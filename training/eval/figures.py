"""Figures of ``genre eval`` (PNG): bars per class, the viewpoint heatmap (Figure 7),
depth error against class dissimilarity (Figure 3, right) and a Blender gallery.

Each figure function returns a line for the report; a figure that cannot be
made (no Blender, no training views) says why instead of failing the run.
"""

from __future__ import annotations

import json
import math
import os
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

__all__ = ["bar_chart", "depth_vs_dissimilarity", "viewpoint_heatmap", "render_meshes", "gallery", "make_all"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=110, bbox_inches="tight")
    _plt().close(fig)
    os.replace(tmp, path)


def bar_chart(per_class: list[dict], rows: list[str], path: Path) -> str:
    """CD per class (seen t*) for every row, with 95 % intervals; classes grouped seen-test first."""
    from .runner import GROUPS

    plt = _plt()
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
    _save(fig, path)
    return f"- `{path.name}`: CD per class for every row (seen-test threshold), 95 % intervals."


def depth_vs_dissimilarity(per_class: list[dict], dissimilarity: dict[str, float], path: Path) -> str:
    """Figure 3 (right): GenRe's mean depth error per class against the class's dissimilarity to the training shapes."""
    plt = _plt()
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
    _save(fig, path)
    return (f"- `{path.name}`: GenRe's depth error per class against the class's dissimilarity "
            "(mean over its shapes of the CD, object frame, to the nearest training shape); blue: seen, red: unseen.")


# ---- viewpoint heatmap (Figure 7) ---------------------------------------------------------
def viewpoint_heatmap(out: Path, models, views, choice, args) -> str:
    """Render shapes of one class on an elevation × azimuth grid, run GenRe, plot the median CD per cell."""
    from training.data.views import ShapeEntry
    from training.render.scene import BlenderRenderer, RenderSettings, render_shape
    from training.data.targets import build_targets

    from .runner import POINTS_SMALL, EvalView, Target, Truth, _resolve_mesh, predict, score_grid

    cls = args.heatmap_class
    shapes = {}
    for v in views:
        if v.cls == cls and v.shape_dir.name not in shapes:
            shapes[v.shape_dir.name] = v
    shapes = dict(list(shapes.items())[: args.heatmap_shapes])
    if not shapes:
        return f"- viewpoint heatmap: not made (no {cls!r} shapes among the eval views)."
    elevations = [float(e) for e in args.heatmap_elevations.split(",")]
    azimuths = [360.0 * k / args.heatmap_azimuths for k in range(args.heatmap_azimuths)]
    grid = [(a, e) for e in elevations for a in azimuths]
    root = out / "grid_views"
    config = models.config
    renderer = None
    try:
        for sid, v in shapes.items():
            if all((root / sid / f"view_{k:03d}.json").is_file() for k in range(len(grid))):
                continue
            if renderer is None:
                renderer = BlenderRenderer(config, RenderSettings(samples=args.render_samples), scratch_dir=out / ".render_scratch")
            render_shape(renderer, ShapeEntry(sid, _resolve_mesh(v.meta["mesh"]), cls, v.meta.get("split")), grid, root, seed=7)
    except Exception as exc:  # noqa: BLE001
        return f"- viewpoint heatmap: not made (Blender rendering failed: {type(exc).__name__}: {exc})."
    finally:
        if renderer is not None:
            renderer.close()
    build_targets(root, config, progress=False)
    from ..data.dataset import ViewDataset, ViewRef

    t = choice["seen"].get("GenRe", config.geometry.default_threshold)
    cells = defaultdict(list)
    truth = Truth()
    csv_rows = ["shape,view,azimuth,elevation,cd1k"]
    for sid, v in shapes.items():
        for k, (az, el) in enumerate(grid):
            meta = json.loads((root / sid / f"view_{k:03d}.json").read_text())
            ev = EvalView(root / sid, k, cls, v.groups, meta)
            sample = ViewDataset([ViewRef(root / sid, k)], config)[0]
            pred = predict(type(models)(models.genre), sample, args.device)
            gt_large, _ = truth.posed(ev)
            cd = score_grid(pred["GenRe"]["prob"], [t], Target(gt_large[:POINTS_SMALL], gt_large))[t]["cd1k"]
            cells[(el, az)].append(cd)
            csv_rows.append(f"{sid},{k},{az:.1f},{el:.1f},{cd:.6g}")
    (out / "viewpoint_heatmap.csv").write_text("\n".join(csv_rows) + "\n")
    med = np.array([[np.median(cells[(e, a)]) for a in azimuths] for e in elevations])
    plt = _plt()
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
    _save(fig, out / "viewpoint_heatmap.png")
    return (f"- `viewpoint_heatmap.png`: median CD of GenRe over {len(shapes)} {cls} shape(s) rendered on a "
            f"{len(elevations)} elevation × {len(azimuths)} azimuth grid (`grid_views/`, `viewpoint_heatmap.csv`).")


# ---- Blender gallery ----------------------------------------------------------------------
def render_meshes(meshes, size: int = 160, samples: int = 16):
    """:func:`genre_backend.inference.blender.render_meshes`, after forgetting any training renderer (its scene is reset)."""
    from genre_backend.inference.blender import render_meshes as render

    from training.render.scene import release_active_renderer

    release_active_renderer()
    return render(meshes, size=size, samples=samples)


def gallery(out: Path, views, gallery_keys: list[str], choice, samples: int) -> str:
    """Input photo | GenRe's mesh from the input view and the side | the truth from both, for a few shapes per group."""
    import trimesh
    from PIL import Image

    from genre_backend import frame
    from genre_backend.geometry.mesh_voxels import voxels_to_mesh

    from .runner import GROUP_LABEL, _resolve_mesh, grid_path

    by_key = {v.key: v for v in views}
    t = choice["seen"].get("GenRe", 0.5)
    items, meshes = [], []
    for key in gallery_keys:
        grid_file = grid_path(out / "grids", key)
        if key not in by_key or not grid_file.is_file():
            continue
        v = by_key[key]
        with np.load(grid_file) as z:
            prob = z["prob"].astype(np.float32)
        pv, pf = voxels_to_mesh(prob, t)
        gt = trimesh.load(_resolve_mesh(v.meta["mesh"]), force="mesh", process=False)
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
    plt = _plt()
    cols = ["input photo", "GenRe (input view)", "GenRe (side)", "truth (input view)", "truth (side)"]
    fig, axes = plt.subplots(len(items), 5, figsize=(10, 2.1 * len(items)), squeeze=False)
    for i, v in enumerate(items):
        with Image.open(v.shape_dir / f"view_{v.view:03d}.png") as im:
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
    _save(fig, out / "gallery.png")
    return f"- `gallery.png`: {len(items)} shapes (Blender Cycles, {samples} samples): input photo, GenRe's mesh at t = {t:.2f} from the input view and from the side, the truth."


def make_all(out: Path, per_class, group_means, models, views, records, choice, args, train_ids, gallery_keys) -> list[str]:
    """Every figure; returns the report lines."""
    from .runner import FLOOR, class_dissimilarity

    notes = [bar_chart(per_class, models.rows() + [FLOOR], out / "bars.png")]
    if args.train_views:
        shapes = {v.shape_dir.name: (v.shape_dir, v.cls) for v in views}
        dis = class_dissimilarity(shapes, [Path(p) for p in args.train_views], train_ids, progress=not args.no_progress)
        (out / "dissimilarity.json").write_text(json.dumps(dis, indent=2))
        notes.append(depth_vs_dissimilarity(per_class, dis, out / "depth_vs_dissimilarity.png"))
    else:
        notes.append("- depth error vs dissimilarity: not made (pass --train-views).")
    if args.heatmap_shapes > 0:
        notes.append(viewpoint_heatmap(out, models, views, choice, args))
    if gallery_keys:
        notes.append(gallery(out, views, gallery_keys, choice, args.render_samples))
    return notes
