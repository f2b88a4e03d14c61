"""One outline, three depths: does a depth net tell a ball from a plate when both are seen from straight above?

Seen from above (elevation 88°), a ball, an ellipsoid of the same footprint flattened to 0.35 of its depth, and a
thin disc (3 % of its width) have the same round outline; only their shading differs. Each is rendered in Blender
(Cycles, the training renders' settings) from three azimuths in each of the renderer's lightings
(:data:`training.render.scene.LIGHTINGS`), composited over a plain light grey backdrop as a product shot, and each
weights file's depth net predicts its depth. Printed per render: the true depth range inside the silhouette
(eroded by 2 px, as ``scripts/depth_errors.py`` does) and each net's, each followed in brackets by how far the
middle stands above the outline (:func:`centre_height`, which a few wrong pixels at the outline do not move);
then, per net, in how many of the render pairs the disc's predicted range is below half the ball's (a net that reads shading: all; one that reads the outline: none).

Usage::

    python scripts/outline_probe.py --weights default --weights $GENRE_HOME/runs/X/depth/final.safetensors
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.ndimage import binary_erosion, distance_transform_edt

from genre_backend import frame
from genre_backend.arguments import add_weights
from genre_backend.config import get_preset
from genre_backend.nets.model import load_model
from genre_backend.weights_file import resolve_weights
from training.render import scene as render

RADIUS = 0.3
ELEVATION = 88.0
AZIMUTHS = (20.0, 90.0, 160.0)
BACKDROP = 0.8  # the grey of the plain backdrop, in [0, 1]


def probe_shapes() -> dict[str, trimesh.Trimesh]:
    """The ball, the flattened ellipsoid (0.35 as deep) and the disc (3 % as deep as wide), one footprint."""
    ball = trimesh.creation.icosphere(subdivisions=5, radius=RADIUS)
    dome = trimesh.creation.icosphere(subdivisions=5, radius=RADIUS)
    dome.vertices[:, 2] *= 0.35
    disc = trimesh.creation.cylinder(radius=RADIUS, height=0.03 * 2 * RADIUS, sections=96)
    return {"ball": ball, "dome": dome, "disc": disc}


def depth_range(depth: np.ndarray, inner: np.ndarray) -> float:
    """The range (max − min) of ``depth`` over the ``inner`` pixels."""
    return float(np.ptp(depth[inner]))


def centre_height(depth: np.ndarray, inside: np.ndarray) -> float:
    """How far the middle of the silhouette stands nearer the camera than a ring just inside its outline.

    ``inside``: the silhouette (bool).  The middle: the pixels farthest from the outline (the top tenth of the
    distance to it); the ring: the pixels 4–6 px inside it.  Mean depth of the ring minus mean depth of the
    middle, so a dome facing the camera is positive and a flat face square to it is 0; unlike
    :func:`depth_range` it does not see a few wrong pixels at the outline.
    """
    dist = distance_transform_edt(inside)
    ring = (dist > 4) & (dist <= 6)
    if not ring.any():
        raise ValueError("the silhouette is too small for a ring 4-6 px inside its outline")
    middle = dist >= np.percentile(dist[dist > 2], 90)
    return float(depth[ring].mean() - depth[middle].mean())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_weights(parser, action="append", required=True, help="weights (name or file); repeat to compare")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    config = get_preset("default")
    nets = [load_model(resolve_weights(w)).eval() for w in args.weights]
    ranges: dict[tuple[str, str, float], list[float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        paths = {}
        for name, mesh in probe_shapes().items():
            paths[name] = Path(tmp) / f"{name}.ply"
            mesh.export(paths[name])
        render.prepare_blender_environment(Path(tmp) / "blender-cache")
        for lighting in render.LIGHTINGS:
            renderer = render.BlenderRenderer(config, render.RenderSettings(samples=16, lighting=lighting))
            try:
                for name, path in paths.items():
                    renderer.load_shape(path)
                    for k, azimuth in enumerate(AZIMUTHS):
                        out = renderer.render_view(azimuth, ELEVATION, np.random.default_rng(k))
                        alpha = out["rgba"][..., 3].astype(np.float32) / 255.0
                        inside = alpha > 0.5
                        inner = binary_erosion(inside, iterations=2)
                        true = frame.encode_raw_depth(torch.from_numpy(out["raw_depth"])).numpy()
                        rgb = out["rgba"][..., :3].astype(np.float32) / 255.0
                        rgb = rgb * alpha[..., None] + BACKDROP * (1.0 - alpha[..., None])
                        x = torch.from_numpy(rgb).permute(2, 0, 1)[None]
                        got, heights = [depth_range(true, inner)], [centre_height(true, inside)]
                        for net in nets:
                            with torch.no_grad():
                                pred = net.depth_net(x)["depth"][0].numpy()
                            got.append(depth_range(pred, inner))
                            heights.append(centre_height(pred, inside))
                        ranges[(lighting, name, azimuth)] = got
                        print(f"{lighting:11s} {name} azimuth {azimuth:5.1f}: true {got[0]:.3f} (centre {heights[0]:+.3f}) | "
                              + " | ".join(f"{w}: {g:.3f} ({h:+.3f})" for w, g, h in zip(args.weights, got[1:], heights[1:])),
                              flush=True)
            finally:
                renderer.close()
    pairs = [(lighting, a) for lighting in render.LIGHTINGS for a in AZIMUTHS]
    for i, w in enumerate(args.weights, start=1):
        told = sum(ranges[(lt, "disc", a)][i] < 0.5 * ranges[(lt, "ball", a)][i] for lt, a in pairs)
        print(f"{w}: the disc below half the ball's range in {told} of {len(pairs)} render pairs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
