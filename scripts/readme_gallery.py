#!/usr/bin/env python3
"""The README's picture grid: real photos and their textured meshes from the front, the side and behind.

    .venv/bin/python scripts/readme_gallery.py [--out docs/gallery.png] [--weights default] [--tile 150]

One row per photo of ``examples/photos`` with its automatic mask (the
salient-object net's, as ``genre reconstruct PHOTO --texture``; ``--hand-masks``:
the hand-drawn masks, ``--mask PHOTO_mask.png``): the photo with that mask
over it (:meth:`Reconstruction.mask_overlay`: background dimmed, outline yellow), then
the mesh with the photo's colour (:meth:`Reconstruction.texture`) rendered
by :func:`genre_backend.output.blender.render_views` (Workbench, the
``--preview`` sheet's renderer) from the photo's viewpoint, from the right
(90°) and from behind, at one scale per row.  Written as a 256-colour PNG
(kept under 400 KB); the sizes and timings are printed.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw
from genre_backend.arguments import add_out, add_weights

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

# (photo, caption): round and boxy objects, then the weak cases (flat or thin objects come out thick).
ROWS = [("apple.jpg", "apple"), ("bus.jpg", "bus"), ("quokka.jpg", "quokka"),
        ("lighter.png", "lighter (flat)"), ("butterfly.jpg", "butterfly (thin)")]
COLUMNS = ("photo and mask", "mesh: photo's view", "from the right", "from behind")
LABEL_H = 18


def _fit(image: np.ndarray, tile: int) -> Image.Image:
    """``image`` (H, W, 3) uint8 scaled to fit a white (tile, tile) square, centred."""
    im = Image.fromarray(image)
    im.thumbnail((tile, tile), Image.LANCZOS)
    out = Image.new("RGB", (tile, tile), "white")
    out.paste(im, ((tile - im.width) // 2, (tile - im.height) // 2))
    return out


def main() -> int:
    from genre_backend.output.blender import render_views
    from genre_backend.inference.reconstruct import MaskGuidance, Reconstructor
    from genre_backend.weights_file import resolve_weights

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_out(p, type=Path, default=REPO / "docs" / "gallery.png")
    add_weights(p, type=resolve_weights, default="default")
    p.add_argument("--tile", type=int, default=150, help="pixels a side of each picture")
    p.add_argument("--hand-masks", action="store_true", help="the hand-drawn masks, not the automatic (salient net's) ones")
    args = p.parse_args()
    tile = args.tile
    rec = Reconstructor(args.weights)
    sheet = Image.new("RGB", (tile * len(COLUMNS), LABEL_H + len(ROWS) * (tile + LABEL_H)), "white")
    draw = ImageDraw.Draw(sheet)
    for j, name in enumerate(COLUMNS):
        draw.text((j * tile + 4, 3), name, fill="black")
    for i, (photo, caption) in enumerate(ROWS):
        t0 = time.perf_counter()
        path = REPO / "examples" / "photos" / photo
        mask = path.with_name(path.stem + "_mask.png") if args.hand_masks else None
        result = rec.run(path, MaskGuidance(mask=mask))
        tex = result.texture()
        views = render_views(result.vertices, result.faces, tile * 2, camera=result.config.camera,
                             uv=tex.face_uv, texture=tex.image, views=("front", "side", "back"))
        pictures = [_fit(result.mask_overlay(), tile)]
        pictures += [Image.fromarray(v).resize((tile, tile), Image.LANCZOS) for v in views]
        y = LABEL_H + i * (tile + LABEL_H)
        draw.text((4, y + 3), f"{caption}: {len(result.faces):,} faces, mask: {result.mask_source}", fill="black")
        for j, pic in enumerate(pictures):
            sheet.paste(pic, (j * tile, y + LABEL_H))
        print(f"{photo:<14} {len(result.faces):>7,} faces  {time.perf_counter() - t0:5.1f} s", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    sheet.quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(args.out, optimize=True)
    print(f"wrote {args.out} ({sheet.width}×{sheet.height}, {args.out.stat().st_size / 1024:.0f} KB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
