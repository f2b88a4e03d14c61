"""Ground-truth targets of rendered views, in the view frame of each view.

For every view ``OUT/<shape>/view_KKK`` written by :mod:`training.render.scene`
this writes ``view_KKK_targets.npz`` with

* ``full_sph``    (H, H) float32 — the posed mesh's full spherical map (ray cast),
* ``partial_sph`` (H, H) float32 — the partial map of the true depth,
* ``shell``       (N³ bits, ``np.packbits``) — the surface shell (:func:`mesh_to_shell`),
* ``preset`` / ``sph_size`` / ``voxel_size`` — what the arrays were made for;

and once per shape ``surface_points.npz``: 10,000 area-uniform points
(object frame) for evaluation.  Files are written atomically (temporary name,
then rename); complete targets are skipped on re-runs.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from genre_backend import frame
from genre_backend.config import GenreConfig, get_preset, PRESETS
from genre_backend.geometry.metrics import sample_surface
from genre_backend.geometry.spherical import depth_to_sph, mesh_to_sph
from genre_backend.io import atomic_savez, atomic_write_text

from .views import TARGETS_FAILURES_FILE, load_view_meta, recorded_preset, surface_points_path, targets_path, view_indices, view_paths

__all__ = ["ShapeTargets", "targets_path", "load_targets", "build_targets", "main"]

SURFACE_POINTS = 10_000


def load_targets(shape_dir: Path, view: int, voxel_size: int) -> dict[str, np.ndarray]:
    """Read a view's targets: ``full_sph``, ``partial_sph`` (H, H) float32 and ``shell`` (N, N, N) bool."""
    with np.load(targets_path(shape_dir, view)) as z:
        n = int(z["voxel_size"])
        if n != voxel_size:
            raise ValueError(f"{shape_dir}: targets were made for {n}³ voxels, the config wants {voxel_size}³")
        shell = np.unpackbits(z["shell"], count=n**3).reshape(n, n, n).astype(bool)
        return {"full_sph": z["full_sph"], "partial_sph": z["partial_sph"], "shell": shell}


class ShapeTargets:
    """A mesh loaded once, with its surface lattice, posed for view after view."""

    def __init__(self, mesh_path: Path, config: GenreConfig):
        import trimesh

        from genre_backend.geometry.mesh_voxels import surface_lattice

        mesh = trimesh.load(mesh_path, force="mesh", process=False)
        if len(mesh.faces) == 0:
            raise ValueError(f"{mesh_path}: mesh has no faces")
        self.config = config
        self.vertices = torch.tensor(np.asarray(mesh.vertices), dtype=torch.float64)
        self.faces = torch.tensor(np.asarray(mesh.faces), dtype=torch.int64)
        # the lattice is rotation-invariant in spacing, so sample once in the object frame
        self.lattice = surface_lattice(self.vertices, self.faces, config.geometry.voxel_size)

    def view_targets(self, rotation: torch.Tensor, depth: torch.Tensor) -> dict[str, np.ndarray]:
        from genre_backend.geometry.mesh_voxels import lattice_to_shell

        g, cam = self.config.geometry, self.config.camera
        rot = rotation.to(torch.float64)[None]
        verts = frame.object_to_view(self.vertices[None], rot)[0]
        full = mesh_to_sph(verts.float(), self.faces, g.sph_size)  # float32: 2× faster, error ~1e-7
        partial = depth_to_sph(depth[None].float(), cam, g.sph_size, g.depth_edge_max_ratio)[0]
        pts = frame.object_to_view(self.lattice[None], rot)[0]
        shell = lattice_to_shell(pts, g.voxel_size, g.shell_dilation)
        return {
            "full_sph": full.numpy().astype(np.float32),
            "partial_sph": partial.numpy().astype(np.float32),
            "shell": np.packbits(shell.numpy().reshape(-1)),
            "voxel_size": np.int64(g.voxel_size),
            "sph_size": np.int64(g.sph_size),
        }


def build_targets(views_root: Path, config: GenreConfig, *, progress: bool = True) -> dict[str, int]:
    """Write missing targets for every rendered view under ``views_root``; returns counts."""
    from tqdm import tqdm

    shape_dirs = sorted(p for p in Path(views_root).iterdir() if p.is_dir())
    counts = {"views": 0, "written": 0, "skipped_complete": 0, "failed_shapes": 0}
    failures = {}
    bar = tqdm(shape_dirs, desc="targets", unit="shape", disable=not progress)
    for shape_dir in bar:
        views = view_indices(shape_dir)
        todo = [k for k in views if not targets_path(shape_dir, k).is_file()]
        counts["views"] += len(views)
        counts["skipped_complete"] += len(views) - len(todo)
        if not todo and surface_points_path(shape_dir).is_file():
            continue
        try:
            meta = load_view_meta(shape_dir, views[0])
            shape = ShapeTargets(Path(meta["mesh"]), config)
            if not surface_points_path(shape_dir).is_file():
                pts = sample_surface(shape.vertices, shape.faces, SURFACE_POINTS, seed=0).numpy()
                atomic_savez(surface_points_path(shape_dir), points=pts)
            for k in todo:
                meta = load_view_meta(shape_dir, k)
                if int(meta["image_size"]) != config.geometry.image_size:
                    raise ValueError(f"view {k} was rendered at {meta['image_size']}², the config wants {config.geometry.image_size}²")
                with np.load(view_paths(shape_dir, k)["npz"]) as z:
                    depth = torch.from_numpy(z["depth"])
                rot = torch.tensor(meta["rotation_cam_to_obj"])
                atomic_savez(targets_path(shape_dir, k), **shape.view_targets(rot, depth))
                counts["written"] += 1
        except Exception as exc:  # one bad shape must not stop the build
            counts["failed_shapes"] += 1
            failures[shape_dir.name] = f"{exc.__class__.__name__}: {exc}"
            print(f"targets: {shape_dir.name}: {failures[shape_dir.name]}", file=sys.stderr)
    if failures:
        atomic_write_text(Path(views_root) / TARGETS_FAILURES_FILE, json.dumps(failures, indent=2))
    return counts


def main(argv: list[str] | None = None, prog: str = "genre data targets") -> int:
    parser = argparse.ArgumentParser(prog=prog, description="Compute ground-truth targets for rendered views.")
    parser.add_argument("--views", type=Path, required=True, help="folder written by 'genre data render'")
    parser.add_argument("--preset", choices=sorted(PRESETS), default=None,
                        help="check against the preset recorded by 'genre data render' (default: the recorded one)")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if not args.views.is_dir():
        parser.error(f"--views: not a folder: {args.views}")
    try:
        preset = recorded_preset(args.views, args.preset)
    except ValueError as exc:
        parser.error(str(exc))
    start = time.perf_counter()
    counts = build_targets(args.views, get_preset(preset), progress=not args.no_progress)
    counts["seconds"] = round(time.perf_counter() - start, 1)
    print(json.dumps(counts))
    return 1 if counts["failed_shapes"] else 0


if __name__ == "__main__":
    sys.exit(main())
