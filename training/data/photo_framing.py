"""Rendered views brought to the framing a photo gets: ``genre data photo-frame``.

A render shows its object as the canonical frame puts it (:mod:`genre_backend.frame`: the bounding box's centre at
the origin, its diagonal 1, the camera 2.2 away), so the image's centre is where the object's centre projects and
the object's size in the image says how much of the unit diagonal lies across the view, and so how deep the object
is. A photo carries neither: :func:`genre_backend.photo.preprocess.preprocess` crops it to a square centred on the
mask's bounding box whose longest side spans ``GeometryConfig.object_fraction`` of the image. Nets trained only on
renders read a photo's framing as a render's (results/photo_framing.md measures what that costs).

This module frames a render as the photo path frames a photo, with the same two functions
(:func:`~genre_backend.photo.preprocess.square_crop_box`, :func:`~genre_backend.photo.preprocess.crop_resize`), and
makes the rest of the view agree with the new picture. Cropping the square box ``B`` (centre ``(cx, cy)``, side
``s`` pixels) and resizing it to ``S`` pixels magnifies by ``k = S / s`` about the box's centre. Seen at the
camera's distance ``D``, that is the object moved across the view by ``-b`` and scaled by ``k``::

    p' = k (p - b),   b = ((cx - S/2) D / f, -(cy - S/2) D / f, 0)     (f: the focal length in pixels)

exact for points at the origin's depth and off by a share ``|z| / D`` of ``k - 1`` for the others (the picture is
magnified, not seen from nearer), as a photo's unknown lens is. So the framed view's planar depth is
``D - k (D - d)`` (``d`` the render's), and its targets (``genre data targets`` on the framed folder) are those of the
mesh posed and then mapped by :func:`framed_points`. Views whose framed object would leave the voxel grid are left
out (counted).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from genre_backend import frame
from genre_backend.arguments import add_out
from genre_backend.config import CameraConfig, get_preset
from genre_backend.photo.preprocess import NEUTRAL_BACKGROUND, crop_resize, mask_bbox, square_crop_box

from .views import (SETTINGS_FILE, load_view, surface_points_path, view_indices, view_is_complete, view_paths,
                    write_view, recorded_preset)

__all__ = ["Framing", "photo_framing", "frame_view", "framed_points", "framing_of", "main"]

# the framed object must stay inside the voxel grid's cube [-0.5, 0.5]^3 with this margin (in the cube's units)
GRID_MARGIN = 0.02


@dataclass(frozen=True)
class Framing:
    """The photo path's crop of one view: ``box`` (x0, y0, x1, y1) in the render's pixels, the magnification ``scale``
    (k) and the ``offset`` b (x, y) in view-frame units at the camera's distance (the module docstring)."""

    fraction: float
    box: tuple[float, float, float, float]
    scale: float
    offset: tuple[float, float]
    part: str = "both"

    def to_meta(self) -> dict:
        return {"fraction": self.fraction, "box": list(self.box), "scale": self.scale, "offset": list(self.offset),
                "part": self.part}


PARTS = ("both", "centre", "size")  # what of the photo's framing a view gets (the rest stays the render's)


def photo_framing(mask: np.ndarray, fraction: float, camera: CameraConfig, part: str = "both") -> Framing:
    """The framing :func:`genre_backend.photo.preprocess.preprocess` gives a photo whose mask is ``mask`` (S, S) (True
    or > 0.5 on the object) when ``object_fraction`` is ``fraction``. ``part``: ``"both"``, that framing;
    ``"centre"``, its centre at the render's own size; ``"size"``, its size about the render's own centre (the two
    halves of what a photo's framing changes, to measure each)."""
    if part not in PARTS:
        raise ValueError(f"part: expected one of {PARTS}, got {part!r}")
    size = mask.shape[-1]
    bbox = mask_bbox(np.asarray(mask) > 0.5)
    if bbox is None:
        raise ValueError("the view's mask is empty: nothing to frame")
    box = square_crop_box(bbox, fraction)
    if part == "centre":  # the photo's centre, the render's size
        box = square_crop_box(bbox, max(bbox[2] - bbox[0], bbox[3] - bbox[1]) / size)
    elif part == "size":  # the render's centre, the photo's size
        half = (box[2] - box[0]) / 2.0
        box = (size / 2.0 - half, size / 2.0 - half, size / 2.0 + half, size / 2.0 + half)
    side = box[2] - box[0]
    k = size / side
    f = camera.focal_px(size)
    cx, cy = (box[0] + box[2]) / 2.0, (box[1] + box[3]) / 2.0
    b = ((cx - size / 2.0) * camera.distance / f, -(cy - size / 2.0) * camera.distance / f)
    return Framing(float(fraction), tuple(float(v) for v in box), float(k), (float(b[0]), float(b[1])), part)


def framing_of(meta: dict) -> Framing | None:
    """The :class:`Framing` a framed view's JSON records (None for a render as it was made)."""
    m = meta.get("photo_framing")
    if m is None:
        return None
    return Framing(float(m["fraction"]), tuple(float(v) for v in m["box"]), float(m["scale"]),
                   (float(m["offset"][0]), float(m["offset"][1])), str(m.get("part", "both")))


def framed_points(points: torch.Tensor, framing: Framing) -> torch.Tensor:
    """View-frame points (..., 3) of the render → the same points in the framed view's frame: ``k (p - b)``."""
    b = torch.tensor([framing.offset[0], framing.offset[1], 0.0], dtype=points.dtype, device=points.device)
    return framing.scale * (points - b)


def frame_view(rgb: np.ndarray, depth: np.ndarray, alpha: np.ndarray, framing: Framing, camera: CameraConfig
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A render's picture (S, S, 3) uint8, planar depth (S, S) (0: background) and film alpha (S, S) in [0, 1], framed.

    The picture and the alpha are cropped and resized as the photo path crops a photo (outside the render: the
    neutral grey, alpha 0). The depth is each framed pixel's nearest render pixel's, mapped to ``D - k (D - d)``; a
    pixel is object where that nearest pixel is (alpha > 0.5 and depth > 0), and its alpha is put on that side of 0.5,
    so that the mask and the depth agree (as :func:`training.data.dataset.stretch_sample` does)."""
    size = rgb.shape[0]
    grey = tuple(int(round(255 * c)) for c in NEUTRAL_BACKGROUND)
    rgb_f = crop_resize(rgb, framing.box, size, grey)
    alpha_f = crop_resize(np.round(np.clip(alpha, 0.0, 1.0) * 255.0).astype(np.uint8), framing.box, size, 0)
    alpha_f = alpha_f.astype(np.float32) / 255.0
    # the nearest render pixel of each framed pixel centre
    x0, y0, x1, _ = framing.box
    step = (x1 - x0) / size
    centres = (np.arange(size) + 0.5) * step
    cols = np.floor(x0 + centres).astype(np.int64)
    rows = np.floor(y0 + centres).astype(np.int64)
    inside = ((rows >= 0) & (rows < size))[:, None] & ((cols >= 0) & (cols < size))[None, :]
    r, c = np.clip(rows, 0, size - 1), np.clip(cols, 0, size - 1)
    d = depth[r[:, None], c[None, :]]
    obj = inside & (alpha[r[:, None], c[None, :]] > 0.5) & (d > 0)
    dist = camera.distance
    depth_f = np.where(obj, dist - framing.scale * (dist - d), 0.0).astype(np.float32)
    eps = 1e-3
    alpha_f = np.where(obj, np.maximum(alpha_f, 0.5 + eps), np.minimum(alpha_f, 0.5)).astype(np.float32)
    return rgb_f, depth_f, alpha_f


def fits_grid(points: torch.Tensor, margin: float = GRID_MARGIN) -> bool:
    """Whether view-frame points (P, 3) lie inside the voxel grid's cube [-0.5, 0.5]^3 less ``margin``."""
    return bool((points.abs() <= 0.5 - margin).all())


def frame_folder(src: Path, out: Path, fraction: float, camera: CameraConfig, progress: bool = True, part: str = "both"
                 ) -> dict[str, int]:
    """Write every complete view of ``src`` framed into ``out`` (a views folder); views already there are kept.
    Returns counts: views framed, kept, left out (the framed object would leave the grid)."""
    from tqdm import tqdm

    out.mkdir(parents=True, exist_ok=True)
    counts = {"framed": 0, "kept": 0, "left_out": 0}
    settings = src / SETTINGS_FILE
    if settings.is_file() and not (out / SETTINGS_FILE).exists():
        (out / SETTINGS_FILE).write_text(settings.read_text())
    shapes = sorted(p for p in src.iterdir() if p.is_dir())
    for shape_dir in tqdm(shapes, desc="photo-frame", unit="shape", disable=not progress):
        dest = out / shape_dir.name
        points = None
        for k in view_indices(shape_dir):
            if not view_is_complete(shape_dir, k):
                continue
            if view_is_complete(dest, k):
                counts["kept"] += 1
                continue
            view = load_view(shape_dir, k)
            meta = view["camera"]
            framing = photo_framing(view["mask"], fraction, camera, part)
            if points is None:
                if not surface_points_path(shape_dir).is_file():
                    raise FileNotFoundError(f"{shape_dir}: no surface_points.npz: run 'genre data targets --views "
                                            f"{src}' first")
                with np.load(surface_points_path(shape_dir)) as z:
                    points = torch.from_numpy(z["points"].astype(np.float64))
            rot = torch.tensor(meta["rotation_cam_to_obj"], dtype=torch.float64)
            posed = framed_points(frame.object_to_view(points[None], rot[None])[0], framing)
            if not fits_grid(posed):
                counts["left_out"] += 1
                continue
            rgb, depth, alpha = frame_view(view["rgb"], view["depth"], view["mask"], framing, camera)
            dest.mkdir(parents=True, exist_ok=True)
            link = surface_points_path(dest)
            if not link.exists():
                os.symlink(surface_points_path(shape_dir).resolve(), link)
            meta = {**meta, "photo_framing": {**framing.to_meta(), "source": str(view_paths(shape_dir, k)["json"])}}
            write_view(dest, k, rgb, depth, alpha, meta)
            counts["framed"] += 1
    return counts


def main(argv: list[str] | None = None, prog: str = "genre data photo-frame") -> int:
    parser = argparse.ArgumentParser(prog=prog, description="Rendered views framed as the photo path frames a photo "
                                     "(training/data/photo_framing.py); then run 'genre data targets' on the new folder.")
    parser.add_argument("--views", type=Path, required=True, help="a folder written by 'genre data render' (with targets)")
    add_out(parser, type=Path, required=True, help="the framed views folder")
    parser.add_argument("--fraction", type=float, default=None,
                        help="the share of the image the mask's longest side spans (default: the preset's object_fraction)")
    parser.add_argument("--part", choices=PARTS, default="both",
                        help="both (default): the photo's framing; centre: its centre at the render's own size; size: its "
                        "size about the render's centre (to measure each half of what the framing costs)")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if not args.views.is_dir():
        parser.error(f"--views: not a folder: {args.views}")
    if args.out.resolve() == args.views.resolve():
        parser.error("--out: must not be the --views folder")
    try:
        config = get_preset(recorded_preset(args.views))
    except ValueError as exc:
        parser.error(str(exc))
    fraction = config.geometry.object_fraction if args.fraction is None else args.fraction
    if not 0.05 <= fraction <= 1.0:
        parser.error(f"--fraction: expected a value in [0.05, 1], got {fraction}")
    start = time.perf_counter()
    try:
        counts = frame_folder(args.views, args.out, fraction, config.camera, progress=not args.no_progress, part=args.part)
    except (OSError, ValueError) as exc:  # the views written so far are complete; the same command resumes
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 1
    counts["seconds"] = round(time.perf_counter() - start, 1)
    print(json.dumps(counts))
    return 0


if __name__ == "__main__":
    sys.exit(main())
