"""Ground-truth targets of rendered views, in the view frame of each view.

For every view ``OUT/<shape>/view_KKK`` written by :mod:`training.render.scene`
this writes ``view_KKK_targets.npz`` with

* ``full_sph``    (H, H) float32 — the posed mesh's full spherical map (ray cast),
* ``partial_sph`` (H, H) float32 — the partial map of the true depth,
* the refiner's voxel target, one key per representation
  (``GeometryConfig.target``, :func:`~genre_backend.geometry.mesh_voxels.mesh_to_target`):
  ``shell`` (N³ bits, ``np.packbits``) — the paper's surface shell — and/or
  ``distance`` (N³ uint8, value × 255) — the truncated unsigned distance;
* ``sph_size`` / ``voxel_size`` — what the arrays were made for;

and once per shape ``surface_points.npz``: 10,000 area-uniform points
(object frame) for evaluation.  Files are written atomically (temporary name,
then rename); complete targets are skipped on re-runs, and a file that lacks
the wanted representation gets it added (its spherical maps are kept).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from genre_backend import frame
from genre_backend.config import TARGETS, GenreConfig, get_preset, PRESETS
from genre_backend.geometry.metrics import sample_surface
from genre_backend.geometry.spherical import depth_to_sph, mesh_to_sph
from genre_backend.atomic import atomic_savez, atomic_write_text

from .photo_framing import Framing, framed_points, framing_of
from .views import TARGETS_FAILURES_FILE, load_view_meta, recorded_preset, surface_points_path, targets_path, view_indices, view_paths

__all__ = ["ShapeTargets", "targets_path", "load_targets", "has_target", "build_targets", "main"]

SURFACE_POINTS = 10_000


def _encode(kind: str, grid: torch.Tensor) -> np.ndarray:
    if kind == "shell":
        return np.packbits(grid.numpy().reshape(-1) > 0.5)
    return np.round(grid.numpy().reshape(-1) * 255.0).astype(np.uint8)


def _decode(kind: str, stored: np.ndarray, n: int) -> np.ndarray:
    if kind == "shell":
        return np.unpackbits(stored, count=n**3).reshape(n, n, n).astype(np.float32)
    return (stored.reshape(n, n, n).astype(np.float32) / 255.0)


def has_target(path: Path, kind: str) -> bool:
    """Whether a targets file exists and holds the ``kind`` voxel target."""
    if not path.is_file():
        return False
    try:
        with np.load(path) as z:
            return kind in z.files
    except (OSError, ValueError, EOFError):  # a cut file: written again
        return False


def load_targets(shape_dir: Path, view: int, geometry) -> dict[str, np.ndarray]:
    """Read a view's targets for ``geometry`` (a GeometryConfig).

    Returns ``full_sph``, ``partial_sph`` (H, H) float32 and ``voxels``
    (N, N, N) float32 in [0, 1]: the refiner's target in the representation
    ``geometry.target`` names.
    """
    kind = geometry.target
    with np.load(targets_path(shape_dir, view)) as z:
        n = int(z["voxel_size"])
        if n != geometry.voxel_size:
            raise ValueError(f"{shape_dir}: targets were made for {n}³ voxels, the config wants {geometry.voxel_size}³")
        if kind not in z.files:
            raise ValueError(f"{shape_dir}: view {view} has no '{kind}' voxel target: run "
                             f"'genre data targets --views {shape_dir.parent} --target {kind}'")
        return {"full_sph": z["full_sph"], "partial_sph": z["partial_sph"], "voxels": _decode(kind, z[kind], n)}


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

    def posed(self, rotation: torch.Tensor, framing: Framing | None = None) -> torch.Tensor:
        """The mesh's vertices in a view's frame (and mapped to its photo framing, when the view has one)."""
        verts = frame.object_to_view(self.vertices[None], rotation.to(torch.float64)[None])[0]
        return verts if framing is None else framed_points(verts, framing)

    def voxel_target(self, rotation: torch.Tensor, kind: str, framing: Framing | None = None) -> np.ndarray:
        """The ``kind`` voxel target of the posed mesh, encoded for the targets file."""
        from genre_backend.geometry.mesh_voxels import dilate, mesh_to_distance, mesh_to_surface_voxels, points_to_occupancy

        g = self.config.geometry
        rot = rotation.to(torch.float64)[None]
        verts = self.posed(rotation, framing)
        if framing is None:
            surface = points_to_occupancy(frame.object_to_view(self.lattice[None], rot)[0], g.voxel_size)
        else:  # the lattice is half a voxel apart before the framing's magnification, not after
            surface = mesh_to_surface_voxels(verts, self.faces, g.voxel_size)
        if kind == "shell":
            return _encode(kind, dilate(surface, g.shell_dilation).float())
        return _encode(kind, mesh_to_distance(verts, self.faces, g.voxel_size, g.distance_band, surface=surface))

    def view_targets(self, rotation: torch.Tensor, depth: torch.Tensor, kind: str, framing: Framing | None = None
                     ) -> dict[str, np.ndarray]:
        """A view's targets; ``framing``: the view is a render framed as a photo (:mod:`.photo_framing`)."""
        g, cam = self.config.geometry, self.config.camera
        verts = self.posed(rotation, framing)
        full = mesh_to_sph(verts.float(), self.faces, g.sph_size)  # float32: 2× faster, error ~1e-7
        partial = depth_to_sph(depth[None].float(), cam, g.sph_size, g.depth_edge_max_ratio)[0]
        return {
            "full_sph": full.numpy().astype(np.float32),
            "partial_sph": partial.numpy().astype(np.float32),
            kind: self.voxel_target(rotation, kind, framing),
            "voxel_size": np.int64(g.voxel_size),
            "sph_size": np.int64(g.sph_size),
        }


def build_targets(views_root: Path, config: GenreConfig, *, progress: bool = True, shard: tuple[int, int] = (0, 1)) -> dict[str, int]:
    """Write missing targets (with ``config.geometry.target``'s voxels) for every rendered view; returns counts."""
    from tqdm import tqdm

    kind = config.geometry.target
    k_shard, n_shards = shard
    shape_dirs = sorted(p for p in Path(views_root).iterdir() if p.is_dir())[k_shard::n_shards]
    counts = {"views": 0, "written": 0, "added_target": 0, "skipped_complete": 0, "failed_shapes": 0}
    failures = {}
    bar = tqdm(shape_dirs, desc="targets", unit="shape", disable=not progress)
    for shape_dir in bar:
        views = view_indices(shape_dir)
        todo = [k for k in views if not has_target(targets_path(shape_dir, k), kind)]
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
                path = targets_path(shape_dir, k)
                old = None
                if path.is_file():
                    try:
                        with np.load(path) as z:
                            old = {name: z[name] for name in z.files}
                    except (OSError, ValueError, EOFError):
                        old = None
                if old is not None and int(old.get("voxel_size", -1)) == config.geometry.voxel_size \
                        and int(old.get("sph_size", -1)) == config.geometry.sph_size:
                    atomic_savez(path, **old, **{kind: shape.voxel_target(rot, kind, framing_of(meta))})  # the maps are kept
                    counts["added_target"] += 1
                else:
                    atomic_savez(path, **shape.view_targets(rot, depth, kind, framing_of(meta)))
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
    parser.add_argument("--target", choices=TARGETS, default=None,
                        help="the voxel representation to add (default: the preset's, geometry.target)")
    parser.add_argument("--shard", default="0/1", metavar="K/N",
                        help="build only every N-th shape starting at K (run N processes side by side)")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    try:
        shard = tuple(int(x) for x in args.shard.split("/"))
        if len(shard) != 2 or not 0 <= shard[0] < shard[1]:
            raise ValueError
    except ValueError:
        parser.error(f"--shard: expected K/N with 0 <= K < N, got {args.shard!r}")
    if not args.views.is_dir():
        parser.error(f"--views: not a folder: {args.views}")
    try:
        preset = recorded_preset(args.views, args.preset)
    except ValueError as exc:
        parser.error(str(exc))
    start = time.perf_counter()
    config = get_preset(preset)
    if args.target:
        config = dataclasses.replace(config, geometry=dataclasses.replace(config.geometry, target=args.target))
    counts = build_targets(args.views, config, progress=not args.no_progress, shard=shard)
    counts["seconds"] = round(time.perf_counter() - start, 1)
    print(json.dumps(counts))
    return 1 if counts["failed_shapes"] else 0


if __name__ == "__main__":
    sys.exit(main())
