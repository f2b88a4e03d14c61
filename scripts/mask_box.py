#!/usr/bin/env python3
"""The automatic mask, a box alone and the doubt test on the real photos with hand masks (or another folder).

For every photo ``NAME.jpg``/``.png`` in ``--photos`` (``examples/photos``)
with a hand mask ``NAME_mask.png`` beside it: the IoU against the hand mask
of

* the **automatic** mask (the salient-object net's, what ``genre
  reconstruct`` does without a mask; with ``--grabcut``, GrabCut seeded by
  the photo's border, its fallback), and whether it is warned as doubtful
  (:func:`genre_backend.photo.mask_doubt.doubt`,
  :func:`~genre_backend.photo.mask_doubt.salient_doubt` or
  :func:`~genre_backend.photo.mask_doubt.cut_doubt`, as ``genre
  reconstruct`` warns);
* the mask from a **box** alone (``--box``): the hand mask's bounding box,
  its width and height grown by ``--grow`` (5 %, half on each side),
  clipped to the photo; and whether that is warned.

Only the salient net runs (none with ``--grabcut``; about 20 s for the 9 photos on
2 cores).  Prints a Markdown table
(``docs/masks.md`` holds it) and the counts of the doubt test: a mask is
*wrong* at IoU < ``--wrong`` (0.8).

    .venv/bin/python scripts/mask_box.py
    .venv/bin/python scripts/mask_box.py --photos examples/holdout   # the six photos set aside
    .venv/bin/python scripts/mask_box.py --grabcut                   # GrabCut's figures (the fallback)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from genre_backend.photo.decode import load_image, load_mask  # noqa: E402
from genre_backend.photo.preprocess import composite, mask_bbox  # noqa: E402
from genre_backend.photo.mask_doubt import doubt  # noqa: E402
from genre_backend.photo.segment import segment  # noqa: E402

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two (H, W) bool masks (1 when both are empty)."""
    union = int((a | b).sum())
    return float((a & b).sum()) / union if union else 1.0


def grown_box(mask: np.ndarray, grow: float) -> tuple[float, float, float, float]:
    """The (H, W) bool mask's bounding box (x0, y0, x1, y1), width and height grown by ``grow``, clipped to the mask."""
    x0, y0, x1, y1 = mask_bbox(mask)
    dx, dy = (x1 - x0) * grow / 2.0, (y1 - y0) * grow / 2.0
    h, w = mask.shape
    return max(0.0, x0 - dx), max(0.0, y0 - dy), min(float(w), x1 + dx), min(float(h), y1 + dy)


def measure(folder: Path, grow: float = 0.05, seeding: str = "salient") -> list[dict]:
    """One row per photo with a hand mask: name, IoU and warning of the automatic and of the box mask.

    ``seeding``: ``"salient"`` (the net's masks) or ``"border"`` (GrabCut's, as without the net)."""
    rows = []
    for photo in sorted(folder.iterdir()):
        hand_path = folder / f"{photo.stem}_mask.png"
        if photo.suffix.lower() not in PHOTO_SUFFIXES or photo.stem.endswith("_mask") or not hand_path.is_file():
            continue
        image = load_image(photo)
        hand = load_mask(hand_path, image)
        rgb = composite(image)
        auto = segment(rgb, seeding=seeding)
        box = grown_box(hand, grow)
        boxed = segment(rgb, seeding=seeding, box=box)
        rows.append({
            "name": photo.stem,
            "auto_iou": iou(auto.mask, hand),
            "auto_warning": doubt(auto.mask) or auto.doubt,
            "box": box,
            "box_iou": iou(boxed.mask, hand),
            "box_warning": doubt(boxed.mask) or boxed.doubt,
        })
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--photos", type=Path, default=ROOT / "examples" / "photos")
    parser.add_argument("--grow", type=float, default=0.05, help="the box's growth in width and height (default 0.05)")
    parser.add_argument("--wrong", type=float, default=0.8, help="a mask below this IoU is wrong (default 0.8)")
    parser.add_argument("--grabcut", action="store_true", help="GrabCut's masks (the fallback), not the salient net's")
    args = parser.parse_args(argv)
    rows = measure(args.photos, args.grow, "border" if args.grabcut else "salient")
    print("| photo | automatic IoU | warned | box IoU | warned |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['name']} | {r['auto_iou']:.3f} | {'yes' if r['auto_warning'] else 'no'} | {r['box_iou']:.3f} | "
              f"{'yes' if r['box_warning'] else 'no'} |")
    print(f"| **mean** | **{np.mean([r['auto_iou'] for r in rows]):.3f}** | | **{np.mean([r['box_iou'] for r in rows]):.3f}** | |")
    print()
    for kind in ("auto", "box"):
        wrong = [r for r in rows if r[f"{kind}_iou"] < args.wrong]
        right = [r for r in rows if r[f"{kind}_iou"] >= args.wrong]
        print(f"{kind}: wrong masks (IoU < {args.wrong:g}) warned {sum(bool(r[f'{kind}_warning']) for r in wrong)} of {len(wrong)}; "
              f"right masks warned falsely {sum(bool(r[f'{kind}_warning']) for r in right)} of {len(right)}")
    for r in rows:
        for kind in ("auto", "box"):
            if r[f"{kind}_warning"]:
                print(f"  {r['name']} ({kind}): {r[f'{kind}_warning']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
