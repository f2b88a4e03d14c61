#!/usr/bin/env python3
"""What each voxel representation loses by itself: the truth through it, on seen-test views.

For a seeded sample of seen-test views it turns each view's posed true mesh
into a 64³ grid of each representation, back into a mesh, and scores it
against the truth with ``genre eval``'s metric (CD at 1,024 points, both
clouds normalised); the resampling floor is printed beside:

* ``shell``                   the paper's surface shell, marching cubes (``GeometryConfig.target = "shell"``)
* ``distance, plain``         the truncated distance, marching cubes only
* ``distance, moved``         … sheets moved all the way back onto the surface (``surface_margin`` 0)
* ``distance, shipped``       … ``grid_to_surface`` as shipped (filled, moved, margin 0.25 voxel)
* ``solid (winding number)``  inside/outside by libigl's fast winding number, a ramp of the
                              signed distance, marching cubes at 0.5 (a road not taken: it
                              loses open and thin shapes)

    .venv/bin/python scripts/representation_floor.py --views ~/.cache/genre/views/eval --views-count 10
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from genre_backend.arguments import add_seed  # noqa: E402
from genre_backend import frame  # noqa: E402
from genre_backend.config import get_preset  # noqa: E402
from genre_backend.geometry.metrics import CloudScorer  # noqa: E402
from genre_backend.geometry.mesh_voxels import grid_index_to_view, grid_to_surface, mesh_to_target, voxels_to_mesh  # noqa: E402
from training.eval.protocol import POINTS_SMALL, resolve_mesh, sample_seen_test_views  # noqa: E402
from training.eval.runner import Truth, mesh_metrics  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    import igl
    import trimesh

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--views", required=True, help="evaluation views (genre data render + targets of the test split)")
    p.add_argument("--manifest", default=None, help="the corpus manifest (default: $GENRE_HOME/corpus/manifest.json)")
    p.add_argument("--views-count", type=int, default=10)
    p.add_argument("--thresholds", default="0.5,0.75", help="levels of the distance rows")
    add_seed(p)
    args = p.parse_args(argv)
    geometry = get_preset("default").geometry
    n = geometry.voxel_size
    levels = [float(t) for t in args.thresholds.split(",")]
    try:
        views = sample_seen_test_views(Path(args.views), Path(args.manifest) if args.manifest else None,
                                       args.views_count, args.seed)
    except FileNotFoundError as exc:
        p.error(str(exc))
    centres = grid_index_to_view(np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3).astype(np.float64), n)
    truth, scores = Truth(), {}

    def add(name: str, verts, faces, target) -> None:
        scores.setdefault(name, []).append(mesh_metrics(verts, faces, target)["cd1k"])

    for view in views:
        mesh = trimesh.load(resolve_mesh(view.meta["mesh"]), force="mesh", process=False)
        rot = torch.tensor(view.meta["rotation_cam_to_obj"], dtype=torch.float64)[None]
        verts = frame.object_to_view(torch.tensor(np.asarray(mesh.vertices))[None], rot)[0]
        faces = torch.tensor(np.asarray(mesh.faces))
        gt, again = truth.posed(view)
        target = CloudScorer(gt[:POINTS_SMALL], gt)
        scores.setdefault("noise floor (truth resampled)", []).append(target.metrics(again[:POINTS_SMALL], again)["cd1k"])
        add("shell, t=0.50", *voxels_to_mesh(mesh_to_target(verts, faces, dataclasses.replace(geometry, target="shell")), 0.5), target)
        dist = mesh_to_target(verts, faces, geometry)
        for t in levels:
            add(f"distance, plain, t={t:.2f}", *voxels_to_mesh(dist, t), target)
            add(f"distance, moved, t={t:.2f}", *grid_to_surface(dist, t, dataclasses.replace(geometry, surface_margin=0.0)), target)
            add(f"distance, shipped, t={t:.2f}", *grid_to_surface(dist, t, geometry), target)
        sd, _, _ = igl.signed_distance(centres, verts.numpy(), faces.numpy(), igl.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER)
        solid = np.clip(0.5 - sd.reshape(n, n, n) * n, 0.0, 1.0).astype(np.float32)
        add("solid (winding number), t=0.50", *voxels_to_mesh(solid, 0.5), target)
    print(f"{len(views)} seen-test views; mean CD (1,024 points) of the truth through each representation")
    for name, values in scores.items():
        print(f"{name:36s} {np.mean(values):.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
