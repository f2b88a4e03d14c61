#!/usr/bin/env python3
"""Render noise of views folders: against a many-sample reference and as high-frequency energy.

Each views folder (``genre data render --out``) holds the same shapes and
views (same ``--seed``).  For every view present in all folders, over the
pixels inside the object (mask ≥ 0.999 in the view and the reference,
eroded by 1 px so the anti-aliased outline is left out), it prints per folder:

* ``mad_ref``: the mean absolute RGB difference (0-255) from the reference
  folder's view (``--reference``, e.g. the same Blender at 512 samples
  without a denoiser): noise plus the denoiser's bias;
* ``hf``: the mean absolute difference between the RGB and its 3×3 median
  (0-255): speckle, comparable across Blenders without a reference;
* ``p99``: the 99th percentile of ``|rgb - reference|`` over those pixels
  (the fireflies).

The numbers in ``training/render/scene.py`` and docs/data.md (adaptive
sampling for Blenders without OpenImageDenoise) come from, with SHAPES a
folder of corpus meshes (``sh3d-blendswap-cc-0-stove-169``,
``sh3d-blendswap-cc-by-coffeetable-22``, ``sh3d-blendswap-cc-0-antiquechair-101``,
``sh3d-blendswap-cc-0-armchair-1``)::

    R="blender -b --factory-startup --python training/render/blender_script.py --"
    $R --shapes SHAPES --views 2 --no-progress --samples 16 --no-denoise --out n34_s16_raw
    $R --shapes SHAPES --views 2 --no-progress --samples 16 --out n34_final
    $R --shapes SHAPES --views 2 --no-progress --samples 512 --no-denoise --out n34_ref
    .venv/bin/genre data render --shapes SHAPES --views 2 --no-progress --samples 16 --out n50_oidn
    .venv/bin/genre data render --shapes SHAPES --views 2 --no-progress --samples 512 --no-denoise --out n50_ref
    .venv/bin/python scripts/render_noise.py --reference n34_ref n34_s16_raw n34_final
    .venv/bin/python scripts/render_noise.py --reference n50_ref n50_oidn
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from PIL import Image
from scipy import ndimage


def _view(folder: Path, rel: Path) -> tuple[np.ndarray, np.ndarray]:
    """(rgb (H, W, 3) float64 0-255, mask (H, W) float32) of one view."""
    rgb = np.asarray(Image.open(folder / rel.with_suffix(".png")).convert("RGB"), dtype=np.float64)
    mask = np.load(folder / rel.with_suffix(".npz"))["mask"].astype(np.float32)
    return rgb, mask


def noise_figures(rgb: np.ndarray, ref: np.ndarray, inside: np.ndarray) -> dict[str, float]:
    """``mad_ref``, ``hf`` and ``p99`` (0-255) of ``rgb`` (H, W, 3) against ``ref`` (H, W, 3) over ``inside`` (H, W) bool."""
    diff = np.abs(rgb - ref).mean(axis=2)[inside]
    med = np.stack([ndimage.median_filter(rgb[..., c], size=3) for c in range(3)], axis=2)
    hf = np.abs(rgb - med).mean(axis=2)[inside]
    return {"mad_ref": float(diff.mean()), "hf": float(hf.mean()), "p99": float(np.percentile(diff, 99))}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--reference", required=True, type=Path, help="views folder of the many-sample reference")
    p.add_argument("folders", nargs="+", type=Path, help="views folders to score")
    args = p.parse_args(argv)
    rels = sorted(f.relative_to(args.reference).with_suffix("") for f in args.reference.glob("*/view_*.json"))
    rels = [r for r in rels if all((f / r).with_suffix(".json").is_file() for f in args.folders)]
    if not rels:
        print("no view is in every folder", file=sys.stderr)
        return 1
    totals = {f: [] for f in args.folders}
    for rel in rels:
        ref, ref_mask = _view(args.reference, rel)
        for folder in args.folders:
            rgb, mask = _view(folder, rel)
            inside = ndimage.binary_erosion((mask >= 0.999) & (ref_mask >= 0.999), iterations=1)
            figs = noise_figures(rgb, ref, inside)
            totals[folder].append(figs)
            print(f"{rel}  {folder.name:14s} " + "  ".join(f"{k} {v:6.2f}" for k, v in figs.items()))
    print(f"mean over {len(rels)} views:")
    for folder, rows in totals.items():
        print(f"  {folder.name:14s} " + "  ".join(f"{k} {np.mean([r[k] for r in rows]):6.2f}" for k in rows[0]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
