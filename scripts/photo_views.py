#!/usr/bin/env python3
"""A folder of rendered views made photo-like, as training makes them: for evaluating what real backgrounds do.

Each view's picture is composited through its film alpha over a crop of the background bank ('genre data
backgrounds'), then given a camera's faults (exposure, white balance, blur, noise, JPEG), exactly as a training
sample with photo compositing is (:func:`training.data.dataset.composite_alpha`, :func:`~training.data.dataset.photometric`)
but without the colour augmentation; the draws are seeded by ``--seed`` and the view's key, so the folder is made
the same every time. Every other file of a view (depth, mask, targets, surface points, its JSON) is linked, not
copied, so ``genre eval`` reads the folder as the original with other pictures. Used by results/decisions.md
(2026-12-03, the plain backdrop):

    python scripts/photo_views.py $GENRE_HOME/views/product_eval $GENRE_HOME/views/product_eval_photo \\
        --backgrounds $GENRE_HOME/backgrounds --seed 81
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from genre_backend.arguments import add_seed
from training.data.dataset import composite_alpha, photometric
from training.data.photo_backgrounds import BackgroundBank


def view_seed(seed: int, key: str) -> int:
    """A 63-bit seed from ``seed`` and a view's key (``shape/view_KKK``), the same on every machine."""
    return int.from_bytes(hashlib.sha256(f"{seed}:{key}".encode()).digest()[:8], "little") >> 1


def photo_like(rgb: np.ndarray, alpha: np.ndarray, bank: BackgroundBank, seed: int) -> np.ndarray:
    """(S, S, 3) uint8 render and (S, S) film alpha → (S, S, 3) uint8 over a bank photo with a camera's faults."""
    gen = torch.Generator().manual_seed(seed)
    size = rgb.shape[0]
    x = torch.from_numpy(rgb.astype(np.float32) / 255.0).permute(2, 0, 1).contiguous()
    x = composite_alpha(x, torch.from_numpy(alpha.astype(np.float32)), bank.sample(gen, size))
    x = photometric(x, gen)
    return (x.clamp(0, 1).permute(1, 2, 0).numpy() * 255.0 + 0.5).astype(np.uint8)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("src", type=Path, help="a folder of rendered views with targets")
    p.add_argument("out", type=Path, help="the new folder (made; views already in it are left as they are)")
    p.add_argument("--backgrounds", type=Path, required=True, help="the background bank ('genre data backgrounds')")
    add_seed(p, default=81, help="seed of the backgrounds and faults (default 81)")
    args = p.parse_args(argv)
    if not args.src.is_dir():
        print(f"photo_views: {args.src} is not a folder", file=sys.stderr)
        return 2
    bank = BackgroundBank(args.backgrounds)
    made = 0
    for shape in sorted(d for d in args.src.iterdir() if d.is_dir()):
        dest = args.out / shape.name
        dest.mkdir(parents=True, exist_ok=True)
        for f in sorted(shape.iterdir()):
            target = dest / f.name
            if target.exists() or target.is_symlink():
                continue
            if f.suffix == ".png" and f.with_suffix(".npz").exists():
                with Image.open(f) as im:
                    rgb = np.asarray(im.convert("RGB"))
                with np.load(f.with_suffix(".npz")) as z:
                    alpha = z["mask"]
                out = photo_like(rgb, alpha, bank, view_seed(args.seed, f"{shape.name}/{f.stem}"))
                tmp = target.with_name(target.name + ".tmp")
                Image.fromarray(out, "RGB").save(tmp, format="PNG")
                os.replace(tmp, target)
                made += 1
            else:
                target.symlink_to(f.resolve())
    for f in args.src.iterdir():  # the folder's own files (an index), linked alike
        if f.is_file() and not (args.out / f.name).exists():
            (args.out / f.name).symlink_to(f.resolve())
    print(f"photo_views: {made} pictures made photo-like in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
