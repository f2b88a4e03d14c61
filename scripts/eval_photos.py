#!/usr/bin/env python3
"""GenRe on real photographs with hand-drawn masks: masks, shape ratios, tilt, parts.

For every photo ``NAME.jpg``/``.png`` in ``--photos`` that has a hand mask
``NAME_mask.png`` beside it (``examples/photos``, see its README), with the
shipped weights (or ``--weights``):

* **mask IoU** of the automatic mask (no user mask) against the hand mask,
  *before* (the depth net's silhouette alone: ``genre reconstruct
  --no-refine``) and *after* (the default automatic mask: GrabCut's when
  ``results/photos/`` was written, the salient net's since issue 48,
  ``docs/masks.md``), both at the photo's pixels; with ``--seedings`` also the IoU of each GrabCut seeding
  (``border``, ``network``, ``auto``: :mod:`genre_backend.photo.grabcut`;
  ``auto`` judges the silhouette of the whole photo, the first pass) and
  ``auto*``: the same rule judged on the silhouette the old pipeline used as
  mask (the second pass, the *before* mask): border seeding when that is
  doubtful, network seeding otherwise; the numbers that chose the default;
* whether the final automatic mask is **doubtful** (the warning ``genre
  reconstruct`` prints: it covers > 85 % of the photo or touches > 50 % of
  its border, or GrabCut's colours barely separate it, or it runs along the
  photo's edge: ``docs/masks.md``; ``results/photos/table.md`` was written
  before the last two tests);
* the **side-view depth/width ratio** of the mesh reconstructed with the hand
  mask (extent along the view's z over extent along its x, the view frame
  of ``genre_backend/frame.py``) next to our judgement of the true ratio
  (``truth.json`` beside the photos: ``{"NAME": {"depth_over_width": r,
  "why": "..."}}``);
* the **seen side's depth/width**: the masked depth map alone, back-projected, its spread along the view over its
  widest spread across it (the surface the depth net made, before any hidden side: :func:`seen_ratio`);
* the **flatness** of that mesh: its depth ÷ width along its own thinnest principal axis
  (:func:`genre_backend.geometry.metrics.thinnest_depth_over_width`, frame-free: a plate seen from
  above should read about 0.1 whatever the camera's elevation) next to our judgement
  (``"thinnest_depth_over_width"`` in ``truth.json``, given for the flat things);
* the **tilt** of the reconstructed vertical axis: of the three principal
  axes of the mesh's surface (1,000 area-uniform points), the one closest to
  the view's up (+y), turned so that it points up; tilt = its angle from +y
  seen from the side (in the y–z plane, positive = the top leans toward the
  camera), roll = seen from the camera (in the x–y plane, positive = the top
  leans right).  Marked ``~`` when that axis is ill-defined (its spread is
  within 15 % of another axis's: a round object);
* the **part count** of the meshes (after clean-up; before it in brackets);

and writes ``table.md``, ``photos.csv`` and ``gallery.png`` (photo with the
hand outline, the automatic mask before and after, the mesh from the
automatic mask from the photo's view and the side, the mesh from the hand
mask from the side; Blender Cycles) into ``--out``.

    .venv/bin/python scripts/eval_photos.py                 # → results/photos/
    .venv/bin/python scripts/eval_photos.py --no-gallery --seedings
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from genre_backend.arguments import add_out, add_weights  # noqa: E402
from genre_backend.photo.decode import ImageError, load_image, load_mask  # noqa: E402
from genre_backend.photo.preprocess import preprocess  # noqa: E402
from genre_backend.inference.reconstruct import MaskGuidance, Reconstructor  # noqa: E402
from genre_backend.weights_file import resolve_weights  # noqa: E402
from genre_backend.photo.mask_doubt import border_touch, cover, doubt  # noqa: E402
from genre_backend.photo.segment import SEEDINGS  # noqa: E402

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")
ROUND_AXES = 1.15  # the up axis is ill-defined when its spread is within 15 % of another's


def find_photos(folder: Path) -> list[tuple[str, Path, Path]]:
    """(name, photo, hand mask) of every photo in ``folder`` with a ``NAME_mask.png`` beside it, by name."""
    found = []
    for p in sorted(folder.iterdir()):
        if p.suffix.lower() in PHOTO_SUFFIXES and not p.stem.endswith("_mask") and (folder / f"{p.stem}_mask.png").is_file():
            found.append((p.stem, p, folder / f"{p.stem}_mask.png"))
    return found


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two (H, W) bool masks (1 when both are empty)."""
    union = int((a | b).sum())
    return float((a & b).sum()) / union if union else 1.0


def side_ratio(vertices: np.ndarray) -> float:
    """Extent along the view's z over extent along its x of (V, 3) view-frame vertices."""
    ext = vertices.max(axis=0) - vertices.min(axis=0)
    return float(ext[2] / max(ext[0], 1e-9))


def seen_ratio(result, camera) -> float:
    """The seen surface's depth ÷ width along the view: the masked depth map back-projected (only the side the photo
    shows), its spread along the view's z over its widest spread across it (:func:`depth_over_width`, up = +z).
    Beside the mesh's ratio it says how much of the mesh's depth the depth net made and how much the hidden side."""
    import torch

    from genre_backend.frame import depth_to_points
    from genre_backend.geometry.metrics import depth_over_width

    depth = result.intermediates["masked_depth"]
    points = depth_to_points(depth[None], camera)[0][depth > 0]
    return depth_over_width(points, torch.tensor([0.0, 0.0, 1.0]))


def flatness(vertices: np.ndarray, faces: np.ndarray, points: int = 4000) -> float:
    """Depth ÷ width of the mesh's area-uniform surface points along their thinnest principal axis."""
    import torch
    import trimesh

    from genre_backend.geometry.metrics import thinnest_depth_over_width

    pts, _ = trimesh.sample.sample_surface(trimesh.Trimesh(vertices=vertices, faces=faces, process=False), points, seed=0)
    return thinnest_depth_over_width(torch.from_numpy(pts))


def tilt(vertices: np.ndarray, faces: np.ndarray, points: int = 1000) -> tuple[float, float, bool]:
    """(tilt°, roll°, well defined) of the mesh's principal axis closest to the view's up; see the module docstring."""
    import trimesh

    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    pts, _ = trimesh.sample.sample_surface(mesh, points, seed=0)
    pts = pts - pts.mean(axis=0)
    values, vectors = np.linalg.eigh(pts.T @ pts / len(pts))  # ascending
    i = int(np.argmax(np.abs(vectors[1])))  # the axis with the largest +y component
    axis = vectors[:, i] * np.sign(vectors[1, i])
    spread = np.sqrt(np.maximum(values, 0.0))
    others = np.delete(spread, i)
    defined = bool(np.all(np.maximum(spread[i], others) / np.maximum(np.minimum(spread[i], others), 1e-12) > ROUND_AXES))
    return math.degrees(math.atan2(axis[2], axis[1])), math.degrees(math.atan2(axis[0], axis[1])), defined


def auto_masks(rec: Reconstructor, photo: Path, seedings) -> dict[str, np.ndarray]:
    """The automatic mask at the photo's pixels for each GrabCut seeding (preprocessing only)."""
    import torch

    image = load_image(photo)
    out = {}
    for s in seedings:
        with torch.inference_mode():
            rec._first_pass = None
            out[s] = preprocess(image, rec.config, MaskGuidance(seeding=s), silhouette=rec._silhouette).photo_mask
    return out


def outline(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool: the one-pixel inner edge of a mask."""
    from scipy.ndimage import binary_erosion

    return mask & ~binary_erosion(mask, iterations=max(1, round(max(mask.shape) / 250)))


def overlay(rgb: np.ndarray, mask: np.ndarray | None, edge: np.ndarray | None = None) -> np.ndarray:
    """The photo with ``mask`` tinted magenta and ``edge`` drawn in green."""
    out = rgb.astype(np.float32).copy()
    if mask is not None:
        out[mask] = out[mask] * 0.45 + np.array([255.0, 0.0, 255.0]) * 0.55
    if edge is not None:
        out[edge] = (0.0, 255.0, 0.0)
    return out.astype(np.uint8)


def gallery(rows: list[dict], path: Path, size: int, samples: int) -> None:
    """One row per photo: photo + hand outline, auto mask before/after, auto mesh front/side, hand-mask mesh side."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from genre_backend.output.blender import render_meshes
    from genre_backend.atomic import atomic_write_bytes as write_bytes_atomic

    meshes = []
    for r in rows:
        meshes += [(r["auto"].vertices, r["auto"].faces), (r["hand"].vertices, r["hand"].faces)]
    renders = render_meshes(meshes, size=size, samples=samples, camera=rows[0]["auto"].config.camera)
    cols = ["photo (green: hand mask)", "before: the depth net's silhouette", "after: the automatic mask", "mesh (auto mask), photo's view", "the same from the right", "mesh (hand mask), from the right"]
    fig, axes = plt.subplots(len(rows), len(cols), figsize=(2.6 * len(cols), 2.5 * len(rows)), squeeze=False)
    for i, r in enumerate(rows):
        rgb = r["rgb"]
        panels = [overlay(rgb, None, outline(r["hand_mask"])), overlay(rgb, r["before"]), overlay(rgb, r["after"]),
                  renders[2 * i][0], renders[2 * i][1], renders[2 * i + 1][1]]
        notes = ["", f"IoU {r['iou_before']:.2f}", f"IoU {r['iou_after']:.2f}" + (" (doubtful)" if r["warning"] else ""),
                 f"{r['parts_auto']} part(s)", "", f"depth/width {r['ratio']:.2f} (true ~{r['true_ratio']:.2f})"]
        for j, (ax, img) in enumerate(zip(axes[i], panels)):
            ax.imshow(img)
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(cols[j], fontsize=9)
            ax.set_xlabel(notes[j], fontsize=8)
        axes[i, 0].set_ylabel(r["name"], fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80)
    plt.close(fig)
    from PIL import Image

    buf.seek(0)
    with Image.open(buf) as im:  # 256 colours, dithered: half the bytes
        small = io.BytesIO()
        rgb = im.convert("RGB")
        rgb.quantize(palette=rgb.quantize(256, method=Image.Quantize.MEDIANCUT), dither=Image.Dither.FLOYDSTEINBERG).save(small, format="PNG", optimize=True)
    write_bytes_atomic(path, small.getvalue())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="GenRe on real photos with hand masks: mask IoU before/after refinement, side ratios, tilt, parts.")
    parser.add_argument("--photos", type=Path, default=ROOT / "examples" / "photos", help="folder of NAME.jpg + NAME_mask.png (+ truth.json)")
    add_weights(parser, type=resolve_weights, default="default",
                        help="shipped weights by name (default: the product model, 'default'; 'protocol') or a file")
    add_out(parser, type=Path, default=ROOT / "results" / "photos", help="where table.md, photos.csv and gallery.png go")
    parser.add_argument("--only", nargs="+", metavar="NAME", help="only these photos")
    parser.add_argument("--seedings", action="store_true", help="also the mask IoU of each GrabCut seeding (border, network, auto)")
    parser.add_argument("--no-gallery", action="store_true", help="skip the Blender renders")
    parser.add_argument("--visible-fusion", action=argparse.BooleanOptionalAction, default=None,
                        help="fill the holes in the visible side from the depth (default: the weights' config)")
    parser.add_argument("--plain-backdrop", action=argparse.BooleanOptionalAction, default=None,
                        help="paint the photo outside the mask grey before the nets (default: the weights' config)")
    parser.add_argument("--size", type=int, default=200, help="gallery render size in pixels")
    parser.add_argument("--samples", type=int, default=16, help="Cycles samples of the gallery renders")
    args = parser.parse_args(argv)

    photos = find_photos(args.photos)
    if args.only:
        photos = [p for p in photos if p[0] in args.only]
    if not photos:
        parser.error(f"{args.photos}: no photo with a NAME_mask.png beside it")
    truth_path = args.photos / "truth.json"
    truth = json.loads(truth_path.read_text()) if truth_path.is_file() else {}
    rec = Reconstructor(args.weights)
    rows = []
    for name, photo, hand_path in photos:
        t0 = time.perf_counter()
        image = load_image(photo)
        hand_mask = load_mask(hand_path, image)
        try:
            before = rec.run(photo, MaskGuidance(refine=False), visible_fusion=args.visible_fusion, plain_backdrop=args.plain_backdrop)
            before_mask, before_warning = before.photo_mask, before.mask_warning
        except ImageError as exc:  # the depth net sees nothing here: its silhouette is empty (IoU 0, cover 0)
            if exc.code != "no_object":
                raise
            before_mask, before_warning = np.zeros_like(hand_mask), "the depth net's silhouette is empty"
        auto = rec.run(photo, visible_fusion=args.visible_fusion, plain_backdrop=args.plain_backdrop)
        hand = rec.run(photo, MaskGuidance(mask=hand_path), visible_fusion=args.visible_fusion, plain_backdrop=args.plain_backdrop)
        tilt_deg, roll_deg, defined = tilt(hand.vertices, hand.faces)
        row = {
            "name": name,
            "rgb": image.rgb,
            "hand_mask": hand_mask,
            "before": before_mask,
            "after": auto.photo_mask,
            "auto": auto,
            "hand": hand,
            "iou_before": iou(before_mask, hand_mask),
            "iou_after": iou(auto.photo_mask, hand_mask),
            "cover_before": cover(before_mask),
            "cover_after": cover(auto.photo_mask),
            "touch_after": border_touch(auto.photo_mask),
            "warning": auto.mask_warning,
            "warning_before": before_warning,
            "ratio": side_ratio(hand.vertices),
            "seen_ratio": seen_ratio(hand, rec.config.camera),
            "true_ratio": float(truth.get(name, {}).get("depth_over_width", float("nan"))),
            "flat": flatness(hand.vertices, hand.faces),
            "true_flat": float(truth.get(name, {}).get("thinnest_depth_over_width", float("nan"))),
            "tilt": tilt_deg,
            "roll": roll_deg,
            "tilt_defined": defined,
            "parts_hand": hand.clean.parts,
            "parts_hand_before": hand.clean.parts_before,
            "parts_auto": auto.clean.parts,
            "parts_auto_before": auto.clean.parts_before,
            "hand_doubtful": doubt(hand_mask),
        }
        if args.seedings:
            for s, m in auto_masks(rec, photo, SEEDINGS).items():
                row[f"iou_{s}"] = iou(m, hand_mask)
            row["iou_auto*"] = row["iou_border"] if before_warning else row["iou_network"]
        rows.append(row)
        print(f"{name:10s} IoU before {row['iou_before']:.3f} after {row['iou_after']:.3f}"
              + "".join(f" {s} {row[f'iou_{s}']:.3f}" for s in (*SEEDINGS, "auto*") if f"iou_{s}" in row)
              + f" | cover {row['cover_before']:.2f}→{row['cover_after']:.2f}{' DOUBTFUL' if row['warning'] else ''}"
              + f" | depth/width {row['ratio']:.2f} (seen side {row['seen_ratio']:.2f}; true ~{row['true_ratio']:.2f})"
              + f" | flat {row['flat']:.2f} (true ~{row['true_flat']:.2f})"
              + f" | tilt {row['tilt']:+.0f}° roll {row['roll']:+.0f}°{'' if defined else ' ~'}"
              + f" | parts hand {row['parts_hand']} ({row['parts_hand_before']}) auto {row['parts_auto']} ({row['parts_auto_before']})"
              + f" ({time.perf_counter() - t0:.1f} s)", flush=True)

    mean = {k: float(np.mean([r[k] for r in rows])) for k in ("iou_before", "iou_after", *(f"iou_{s}" for s in (*SEEDINGS, "auto*"))) if k in rows[0]}
    print("mean IoU " + ", ".join(f"{k.removeprefix('iou_')} {v:.3f}" for k, v in mean.items()))
    defined_tilts = [abs(r["tilt"]) for r in rows if r["tilt_defined"]]
    tilt_line = (f"mean |tilt| {np.mean([abs(r['tilt']) for r in rows]):.1f}° over all {len(rows)} photos, "
                 + (f"{np.mean(defined_tilts):.1f}° over the {len(defined_tilts)} whose upright axis is well-defined"
                    if defined_tilts else "no photo with a well-defined upright axis"))
    print(tilt_line)
    print(f"doubtful automatic masks: before {sum(bool(r['warning_before']) for r in rows)}, after {sum(bool(r['warning']) for r in rows)} of {len(rows)}; "
          f"masks covering > 85 % without a warning: {sum(r['cover_after'] > 0.85 and not r['warning'] for r in rows)}")

    from genre_backend.atomic import atomic_write_bytes as write_bytes_atomic

    args.out.mkdir(parents=True, exist_ok=True)
    seed_cols = [s for s in (*SEEDINGS, "auto*") if f"iou_{s}" in rows[0]]
    header = ["photo", "IoU before (depth net)", "IoU after (automatic)", *(f"IoU {s}" for s in seed_cols), "cover before", "cover after", "doubtful after",
              "depth/width (hand mask)", "seen side's depth/width", "judged true", "thinnest depth/width", "judged true", "tilt°", "roll°", "parts (hand mask)", "parts (auto mask)"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    table = []
    for r in rows:
        cells = [r["name"], f"{r['iou_before']:.3f}", f"{r['iou_after']:.3f}", *(f"{r[f'iou_{s}']:.3f}" for s in seed_cols),
                 f"{r['cover_before']:.2f}", f"{r['cover_after']:.2f}", "yes" if r["warning"] else "no",
                 f"{r['ratio']:.2f}", f"{r['seen_ratio']:.2f}", f"{r['true_ratio']:.2f}", f"{r['flat']:.2f}", f"{r['true_flat']:.2f}", f"{r['tilt']:+.0f}{'' if r['tilt_defined'] else ' ~'}", f"{r['roll']:+.0f}",
                 f"{r['parts_hand']} ({r['parts_hand_before']})", f"{r['parts_auto']} ({r['parts_auto_before']})"]
        table.append(cells)
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("| **mean** | " + " | ".join(f"**{mean[k]:.3f}**" for k in ("iou_before", "iou_after", *(f"iou_{s}" for s in seed_cols))) + " |" + " |" * (len(header) - 3 - len(seed_cols)))
    text = "\n".join([
        f"# GenRe on {len(rows)} real photos (`scripts/eval_photos.py`, weights `{args.weights.name}`)",
        "",
        "IoU of the automatic mask (no user mask) against the hand mask at the photo's pixels, before = the depth net's own silhouette, after = the mask `genre reconstruct` uses (docs/masks.md); cover = fraction of the photo the automatic mask covers; "
        "depth/width = the side-view ratio of the mesh made with the hand mask; seen side's = its masked depth map alone, back-projected: the spread along the view over the widest spread across it (the surface the depth net made; the rest of the mesh's depth is the hidden side's); thinnest depth/width = its depth over width along its thinnest principal axis (a plate: ~0.1); tilt / roll = angle of its principal axis nearest the view's up from +y, "
        "seen from the side (+ = top toward the camera) / from the camera (+ = top to the right), ~ = ill-defined (round object); parts after clean-up (before it).",
        "",
        *lines,
        "",
        tilt_line[0].upper() + tilt_line[1:] + ".",
        "",
    ])
    write_bytes_atomic(args.out / "table.md", text.encode())
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    w.writerows(table)
    write_bytes_atomic(args.out / "photos.csv", buf.getvalue().encode())
    if not args.no_gallery:
        gallery(rows, args.out / "gallery.png", args.size, args.samples)
    print(f"wrote {args.out / 'table.md'}, {args.out / 'photos.csv'}" + ("" if args.no_gallery else f", {args.out / 'gallery.png'}"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
