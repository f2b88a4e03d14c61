"""Does a depth net's normals head know more of the surface than its depth says? Normals on rendered views.

For each view of a folder (``genre data render``), inside the render's silhouette eroded by 2 pixels and where
the true depth is one surface (:func:`training.learn.normals.depth_normals`), the angle between the true normal
and

* the normals head of a depth stage trained with ``--normals-weight`` (its checkpoint: ``--stage RUN/depth``);
* the normals of that stage's own predicted depth, and of the predicted depth of each ``--weights`` file
  (the same central differences, on the predicted depth inside the true silhouette).

Each row also runs on the picture with the object painted one colour (``depth_errors.flat_coloured``): a gap
between the two says the row reads the shading inside the outline.  Figures: the median over views of each
view's mean angle (degrees), and of its mean 1 − cos (the head's training loss).  Where the head is far below
its own depth's normals, the encoder knows the surface's orientation and the depth decoder does not pass it on.

Usage::

    python scripts/normals_probe.py --views $GENRE_HOME/views/product_eval --stage $GENRE_HOME/runs/depth53N/depth \\
        --weights $GENRE_HOME/runs/depth53C/depth/snapshots/step_0010000.safetensors
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import binary_erosion

sys.path.insert(0, str(Path(__file__).resolve().parent))

from depth_errors import flat_coloured  # noqa: E402

from genre_backend.arguments import add_weights  # noqa: E402
from genre_backend.config import GenreConfig  # noqa: E402
from genre_backend.nets.model import GenRe, load_model  # noqa: E402
from genre_backend.weights_file import resolve_weights  # noqa: E402
from training.data.views import find_views, load_view  # noqa: E402
from training.learn.checkpoint import read_state  # noqa: E402
from training.learn.normals import NormalsHead, depth_normals  # noqa: E402


def load_stage(stage_dir: Path) -> tuple[GenRe, NormalsHead]:
    """The GenRe nets and the normals head of a depth stage's resumable checkpoint."""
    state = read_state(stage_dir)
    if state is None:
        raise SystemExit(f"{stage_dir}: no readable checkpoint")
    tensors, meta = state
    config = GenreConfig.from_dict(meta["model_config"])
    model = GenRe(config)
    model.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("model.")})
    head = NormalsHead(config.network.depth_widths, config.network.depth_decoder_blocks)
    aux = {k[len("aux.normals."):]: v for k, v in tensors.items() if k.startswith("aux.normals.")}
    if not aux:
        raise SystemExit(f"{stage_dir}: the checkpoint has no normals head (trained without --normals-weight)")
    head.load_state_dict(aux)
    return model.eval(), head.eval()


def angles(pred: torch.Tensor, true: torch.Tensor, keep: torch.Tensor) -> tuple[float, float]:
    """(mean angle in degrees, mean 1 − cos) between (3, S, S) normals over the (S, S) pixels kept."""
    cos = (torch.nn.functional.normalize(pred, dim=0, eps=1e-6) * true).sum(0)[keep].clamp(-1, 1)
    return float(torch.rad2deg(torch.acos(cos)).mean()), float((1 - cos).mean())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", required=True, help="a folder of rendered views")
    ap.add_argument("--stage", required=True, help="a depth stage folder trained with --normals-weight (RUN/depth)")
    add_weights(ap, action="append", default=[], help="weights (name or file) whose depth's normals to compare; repeat")
    args = ap.parse_args(argv)
    model, head = load_stage(Path(args.stage))
    others = [load_model(resolve_weights(w)).eval() for w in args.weights]
    camera = model.config.camera
    names = ["normals head", "its own depth's normals"] + [f"{w}: its depth's normals" for w in args.weights]
    rows: dict[tuple[str, bool], list[tuple[float, float]]] = {(n, p): [] for n in names for p in (False, True)}
    for ref in find_views(args.views, targets=False):
        view = load_view(ref.shape_dir, ref.view)
        inner = binary_erosion(view["mask"] > 0.5, iterations=2)
        true_depth = torch.from_numpy(np.where(view["mask"] > 0.5, view["depth"], 0.0)).float()[None]
        true, valid = depth_normals(true_depth, camera)
        keep = valid[0] & torch.from_numpy(inner)
        if keep.sum() < 20:
            continue
        outside = torch.from_numpy(view["mask"] <= 0.5)
        for painted in (False, True):
            shown = flat_coloured(view) if painted else view
            rgb = torch.from_numpy(shown["rgb"]).permute(2, 0, 1)[None].float() / 255.0
            with torch.no_grad():
                skips, deep = model.depth_net.encode(rgb)
                depths = [model.depth_net.decode(skips, deep)["depth"]] + [net.depth_net(rgb)["depth"] for net in others]
                # a predicted depth's normals inside the true silhouette (every step counts: `keep` picks the pixels)
                normals = [head(skips, deep)[0]] + [
                    depth_normals(d.masked_fill(outside[None], 0.0), camera, max_step=1e9)[0][0] for d in depths]
            for name, pred in zip(names, normals):
                rows[(name, painted)].append(angles(pred, true[0], keep))
    print("| views | row | views scored | mean angle (°), median over views | 1 − cos | one colour: angle | gap (°) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for name in names:
        pic, flat = np.array(rows[(name, False)]), np.array(rows[(name, True)])
        a, c, fa = np.median(pic[:, 0]), np.median(pic[:, 1]), np.median(flat[:, 0])
        print(f"| {Path(args.views).name} | {name} | {len(pic)} | {a:.1f} | {c:.3f} | {fa:.1f} | {fa - a:+.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
