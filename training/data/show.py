"""``genre data show``: a contact sheet of training samples for a person to look at.

One row per sample: RGB, depth, mask, partial and full spherical maps, and
the middle slice of the voxel target (view x–y plane at z = 0).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from genre_backend.config import PRESETS, get_preset
from genre_backend.arguments import add_out, add_seed

from .dataset import ViewDataset
from .views import find_views, recorded_preset

__all__ = ["contact_sheet", "main"]


def contact_sheet(views_root: Path, out_png: Path, preset: str | None = None, count: int = 6, seed: int = 0) -> int:
    """Write a contact sheet of ``count`` samples picked evenly (seeded) from ``views_root``; returns the number shown."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    config = get_preset(recorded_preset(views_root, preset))
    refs = find_views(Path(views_root))
    if not refs:
        raise ValueError(f"{views_root}: no views with targets (run 'genre data render' and 'genre data targets')")
    pick = np.random.default_rng(seed).choice(len(refs), size=min(count, len(refs)), replace=False)
    data = ViewDataset([refs[i] for i in sorted(pick)], config)
    cols = ["RGB", "depth", "mask", "partial sph", "full sph", "voxel target (z = 0 slice)"]
    fig, axes = plt.subplots(len(data), len(cols), figsize=(2.2 * len(cols), 2.3 * len(data)), squeeze=False)
    for r in range(len(data)):
        s = data[r]
        depth = s["depth"].numpy()
        n = s["voxels"].shape[0]
        panels = [
            s["rgb"].permute(1, 2, 0).numpy(),
            np.where(depth > 0, depth, np.nan),
            s["mask"].numpy(),
            s["partial_sph"].numpy(),
            s["full_sph"].numpy(),
            s["voxels"][:, :, n // 2].T.flip(0).numpy(),  # x to the right, y up
        ]
        for c, img in enumerate(panels):
            ax = axes[r, c]
            ax.imshow(img, cmap=None if c == 0 else ("gray" if c in (2, 5) else "viridis"), vmin=0 if c in (3, 4) else None, vmax=1 if c in (3, 4) else None)
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(cols[c], fontsize=9)
        ref = data.refs[r]
        axes[r, 0].set_ylabel(f"{ref.shape_id[:18]}\nview {ref.view}", fontsize=7)
    fig.tight_layout()
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=80)
    plt.close(fig)
    return len(data)


def main(argv: list[str] | None = None, prog: str = "genre data show") -> int:
    parser = argparse.ArgumentParser(prog=prog, description="Write a contact sheet PNG of rendered samples and their targets.")
    parser.add_argument("--views", type=Path, required=True, help="folder written by 'genre data render' (+ targets)")
    add_out(parser, type=Path, default=Path("contact_sheet.png"))
    parser.add_argument("--preset", choices=sorted(PRESETS), default=None,
                        help="check against the preset recorded by 'genre data render' (default: the recorded one)")
    parser.add_argument("--count", type=int, default=6)
    add_seed(parser)
    args = parser.parse_args(argv)
    try:
        shown = contact_sheet(args.views, args.out, args.preset, args.count, args.seed)
    except ValueError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {args.out} ({shown} samples)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
