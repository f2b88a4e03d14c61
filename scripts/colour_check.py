#!/usr/bin/env python3
"""Print how well colour from the photo reproduces each photo (issue 17's check).

    .venv/bin/python scripts/colour_check.py [--weights W] [--[no-]visible-fusion]

For ``examples/sofa.png`` (automatic mask) and the real photos
``examples/photos/apple.jpg`` and ``orange.jpg`` (hand masks): the
reconstruction's textured mesh rendered unlit through the matching camera
(Blender Workbench), against the photo inside the mask; mean absolute error
(0–255) and the share of the mask the mesh covers.  ``tests/backend/output/test_colour.py``
holds the error to ≤ 8.
"""

import argparse
import sys
from pathlib import Path
from genre_backend.arguments import add_weights

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

CASES = [("examples/sofa.png", None), ("examples/photos/apple.jpg", "examples/photos/apple_mask.png"),
         ("examples/photos/orange.jpg", "examples/photos/orange_mask.png")]


def main() -> int:
    from genre_backend.output.colour_check import photo_colour_error
    from genre_backend.inference.reconstruct import MaskGuidance, Reconstructor
    from genre_backend.weights_file import resolve_weights

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_weights(p, type=resolve_weights, default="default")
    p.add_argument("--visible-fusion", action=argparse.BooleanOptionalAction, default=None,
                   help="fill the holes in the visible side from the depth (default: the weights' config)")
    args = p.parse_args()
    rec = Reconstructor(args.weights)
    for photo, mask in CASES:
        result = rec.run(REPO / photo, MaskGuidance(mask=None if mask is None else REPO / mask), visible_fusion=args.visible_fusion)
        mae, coverage = photo_colour_error(result)
        print(f"{photo:<28} mask {result.mask_source:<8} MAE {mae:4.2f}/255  mask covered {coverage:.0%}  "
              f"parts {result.clean.parts} (before clean-up {result.clean.parts_before})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
