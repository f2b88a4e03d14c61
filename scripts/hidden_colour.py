#!/usr/bin/env python3
"""How the hidden side is coloured: colour jumps across hidden edges and background taken onto it.

    .venv/bin/python scripts/hidden_colour.py [--weights W] [--json OUT]

For ``examples/sofa.png`` (automatic mask, as ``make demo``) and real photos
of ``examples/photos`` (hand masks), reconstructs the mesh and its
:class:`~genre_backend.output.colour.PhotoTexture`, and prints:

* ``jump``: mean |ΔRGB| (0-255, mean of the three channels) over the mesh
  edges whose two ends are both hidden (not seen by the photo), the vertex
  colours being the texture sampled at each vertex's UV, and ``p99`` its
  99th percentile;
* ``off-mask``: the share of hidden vertices whose UV lands outside the
  object mask shrunk by 2 px (where the photo shows the background or its
  blend with the object) — colour taken from the background (a texture
  that is an atlas of squares side by side: the place in its square);
* ``front MAE``: the textured mesh rendered unlit through the photo's camera
  against the photo inside the mask (``photo_colour_error``, the check of
  ``scripts/colour_check.py``, held to ≤ 8 by ``tests/backend/output/test_colour.py``).

Self-contained (it reads only the texture's ``uv``, ``image`` and ``seen``),
so the same script scores an older commit's colouring.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from genre_backend.arguments import add_weights

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

CASES = [("examples/sofa.png", None)] + [
    (f"examples/photos/{name}", f"examples/photos/{name.rsplit('.', 1)[0]}_mask.png")
    for name in ("apple.jpg", "orange.jpg", "bus.jpg", "quokka.jpg", "lighter.png")]
SHRINK_PX = 2


def figures(texture, faces: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """``jump``, ``p99`` and ``off_mask`` (see the module docstring) of ``texture`` on ``faces`` (F, 3);
    ``mask`` (S, S) bool, the object mask at the network's image size."""
    from scipy.ndimage import distance_transform_edt

    from genre_backend.output.colour import sample_bilinear

    uv = np.asarray(texture.uv, np.float64)
    rgb = sample_bilinear(texture.image, uv).astype(np.float64)
    hidden = ~np.asarray(texture.seen, bool)
    f = np.asarray(faces, np.int64)
    edges = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1), axis=0)
    both = edges[hidden[edges[:, 0]] & hidden[edges[:, 1]]]
    jumps = np.abs(rgb[both[:, 0]] - rgb[both[:, 1]]).mean(axis=1)
    size = mask.shape[0]
    shrunk = distance_transform_edt(np.pad(mask, 1, constant_values=True))[1:-1, 1:-1] > SHRINK_PX
    squares = texture.image.shape[1] // texture.image.shape[0]  # an atlas of squares side by side (1: the photo alone)
    col = np.clip((uv[:, 0] * squares % 1.0 * size).astype(np.int64), 0, size - 1)
    row = np.clip(((1.0 - uv[:, 1]) * size).astype(np.int64), 0, size - 1)
    off = ~shrunk[row, col]
    return {"jump": float(jumps.mean()) if len(jumps) else 0.0,
            "p99": float(np.percentile(jumps, 99)) if len(jumps) else 0.0,
            "off_mask": float(off[hidden].mean()) if hidden.any() else 0.0,
            "hidden_edges": int(len(both))}


def main() -> int:
    from genre_backend.output.colour_check import photo_colour_error
    from genre_backend.inference.reconstruct import MaskGuidance, Reconstructor
    from genre_backend.weights_file import resolve_weights

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_weights(p, type=resolve_weights, default="default")
    p.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = p.parse_args()
    rec = Reconstructor(args.weights)
    rows = {}
    for photo, mask in CASES:
        result = rec.run(REPO / photo, MaskGuidance(mask=None if mask is None else REPO / mask))
        tex = result.texture()
        row = figures(tex, result.faces, result.intermediates["mask"].numpy().astype(bool))
        row["front_mae"], _ = photo_colour_error(result)
        rows[photo] = row
        print(f"{photo:<28} jump {row['jump']:5.2f}  p99 {row['p99']:6.2f}  off-mask {row['off_mask']:6.1%}  "
              f"front MAE {row['front_mae']:4.2f}/255  ({row['hidden_edges']} hidden edges)", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
