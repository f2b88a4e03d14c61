"""The samples a GPU burst makes (training/learn/burst.py: ViewMaker) against Blender's renders and `genre data targets`.

For the first COUNT shapes of a rendered, targeted views folder (view 000 of each) it packs the shape's mesh as
`genre data pack` would (decimated to MAX_FACES), makes the same view on the CPU and prints: mask IoU and depth
difference against the Blender render, the spherical map's difference and the voxel target's error and IoU at
0.45 against the view's targets file, and the time the shapes' distance grids took.

    .venv/bin/python scripts/check_burst_samples.py --views $GENRE_HOME/views/product_train_eval --count 4
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

from genre_backend.arguments import add_weights
from genre_backend.nets.model import load_model
from training.data.pack import Pack, _decimate, quantise
from training.data.targets import load_targets
from training.learn.burst import ViewMaker


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--views", required=True)
    p.add_argument("--count", type=int, default=4)
    p.add_argument("--max-faces", type=int, default=65535, help="decimate as the pack does (default: not at all)")
    p.add_argument("--grid-factor", type=int, default=2)
    add_weights(p, default="genre_backend/weights/default.safetensors", help="whose config (resolutions)")
    args = p.parse_args()
    cfg = load_model(args.weights).config
    dirs = sorted(d for d in Path(args.views).iterdir() if (d / "view_000.json").is_file())[: args.count]
    verts, faces, vo, fo, shapes = [], [], [0], [0], []
    for d in dirs:
        mesh = trimesh.load(json.loads((d / "view_000.json").read_text())["mesh"], force="mesh", process=False)
        v, f = _decimate(np.asarray(mesh.vertices), np.asarray(mesh.faces), args.max_faces)
        verts.append(quantise(v))
        faces.append(f.astype(np.uint16))
        vo.append(vo[-1] + len(v))
        fo.append(fo[-1] + len(f))
        shapes.append({"id": d.name})
    pack = Pack(Path(args.views), {"shapes": shapes}, np.concatenate(verts), np.concatenate(faces), np.array(vo), np.array(fo))
    start = time.time()
    maker = ViewMaker(pack, cfg, torch.device("cpu"), args.grid_factor)
    print(f"distance grids: {time.time() - start:.1f} s for {len(dirs)} shapes")
    for i, d in enumerate(dirs):
        cam = json.loads((d / "view_000.json").read_text())
        s = maker.make(torch.tensor([i]), torch.tensor([cam["azimuth_deg"]]), torch.tensor([cam["elevation_deg"]]))
        with np.load(d / "view_000.npz") as z:
            b_depth, b_mask = z["depth"], z["mask"] > 0.5
        depth = s["true_depth"][0].numpy()
        both = (depth > 0) & b_mask & (b_depth > 0)
        iou = ((depth > 0) & b_mask).sum() / max(((depth > 0) | b_mask).sum(), 1)
        t = load_targets(d, 0, cfg.geometry)
        vox, true = s["voxels"][0].numpy(), t["voxels"]
        band = (vox > 0) | (true > 0)
        hit = ((vox > 0.45) & (true > 0.45)).sum() / max(((vox > 0.45) | (true > 0.45)).sum(), 1)
        print(f"{d.name[:40]:40s} faces {fo[i + 1] - fo[i]:6d}  mask IoU {iou:.4f}  depth median {np.median(np.abs(depth - b_depth)[both]):.1e}  "
              f"sph mean {np.abs(s['full_sph'][0].numpy() - t['full_sph']).mean():.4f}  voxel error (band) "
              f"{np.abs(vox - true)[band].mean():.3f}  IoU@0.45 {hit:.3f}")


if __name__ == "__main__":
    main()
