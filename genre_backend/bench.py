"""``genre bench``: speed figures, printed (benchmarks are scripts, not timed tests).

``genre bench geometry`` times each geometry op at the ``default`` and
``paper`` resolutions on an analytic sphere (radius 0.45, seen from the
default camera), reports the median of several runs and the ratio to the
op's plain reference implementation.  References that would take minutes at
full size are timed on a slice of the work and scaled up; the table says so.
"""

from __future__ import annotations

import argparse
import statistics
import time
from typing import Callable

import torch

from .analytic import sphere_depth
from .config import PRESETS, get_preset

__all__ = ["main", "geometry_benchmark"]


def _median_time(fn: Callable[[], object], repeats: int) -> float:
    fn()  # warm-up (caches, allocator)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def geometry_benchmark(preset: str, repeats: int = 5) -> list[dict]:
    """Time the geometry ops of one preset; returns one row per op."""
    import trimesh

    from .mesh_voxels import mesh_to_shell, voxels_to_mesh
    from .metrics import chamfer_distance, chamfer_distance_reference, sample_surface
    from .spherical import depth_to_sph, depth_to_triangles, mesh_to_sph, raycast_triangles_reference, sph_to_points, sph_to_voxels
    from .voxels import points_to_voxels_reference

    cfg = get_preset(preset)
    g, cam = cfg.geometry, cfg.camera
    r = 0.45
    depth = sphere_depth(cam, g.image_size, r, dtype=torch.float32)
    rows = []

    def add(op, fast, ref=None, ref_scale=1.0, note=""):
        t = _median_time(fast, repeats)
        row = {"preset": preset, "op": op, "ms": 1e3 * t, "ref_ms": None, "note": note}
        if ref is not None:
            row["ref_ms"] = 1e3 * _median_time(ref, 1) * ref_scale
        rows.append(row)

    # depth → partial spherical map; the reference ray-casts a few map rows against all triangles
    tris, _ = depth_to_triangles(depth, cam, g.depth_edge_max_ratio)
    ref_rows = 2
    tri_np = tris.double().numpy()
    add(
        f"depth {g.image_size}² → partial sph {g.sph_size}²",
        lambda: depth_to_sph(depth, cam, g.sph_size, g.depth_edge_max_ratio),
        lambda: raycast_triangles_reference(tri_np, ref_rows, g.sph_size),
        g.sph_size / ref_rows,
        f"reference timed on {ref_rows} of {g.sph_size} rows, scaled",
    )
    # spherical map → voxels
    full = torch.full((1, g.sph_size, g.sph_size), 1.0 - r)
    pts, mask = sph_to_points(full, g.sph_nohit_min, g.sph_supersample)
    sub = max(1, pts.shape[1] // 4096)
    add(
        f"sph {g.sph_size}² → voxels {g.voxel_size}³",
        lambda: sph_to_voxels(full, g.voxel_size, g.sph_nohit_min, g.sph_supersample),
        lambda: points_to_voxels_reference(pts[:, ::sub], g.voxel_size, mask[:, ::sub]),
        sub,
        f"reference timed on 1/{sub} of the points, scaled" if sub > 1 else "",
    )
    # marching cubes of a voxelised sphere
    vox = sph_to_voxels(full, g.voxel_size, g.sph_nohit_min, g.sph_supersample)[0, 0]
    add(f"marching cubes {g.voxel_size}³ → mesh", lambda: voxels_to_mesh(vox, g.default_threshold), note="scikit-image (no reference)")
    # ground truth from a mesh (offline data preparation)
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=r)
    v, f = torch.tensor(sphere.vertices, dtype=torch.float32), torch.tensor(sphere.faces)
    add(f"mesh (20k faces) → full sph {g.sph_size}²", lambda: mesh_to_sph(v, f, g.sph_size), note="ground truth, offline")
    add(f"mesh (20k faces) → shell {g.voxel_size}³", lambda: mesh_to_shell(v, f, g.voxel_size, g.shell_dilation), note="ground truth, offline")
    # Chamfer distance
    for n in (g.chamfer_points, 10_000):
        a = sample_surface(v, f, n, seed=0)
        b = sample_surface(v, f, n, seed=1)
        sub = max(1, n // 1000)
        ref_note = f"reference: loop over points, timed on 1/{sub}² of the pairs, scaled" if sub > 1 else "reference: loop over points"
        add(f"chamfer {n} pts (k-d tree)", lambda: chamfer_distance(a, b), lambda: chamfer_distance_reference(a[::sub].numpy(), b[::sub].numpy()), sub * sub, ref_note)
        add(f"chamfer {n} pts (brute, differentiable)", lambda: chamfer_distance(a, b, method="brute"), lambda: chamfer_distance_reference(a[::sub].numpy(), b[::sub].numpy()), sub * sub, ref_note)
    return rows


def _print_rows(rows: list[dict]) -> None:
    print(f"{'preset':<8} {'op':<42} {'median ms':>10} {'ref ms':>10} {'ref/fast':>9}  note")
    for row in rows:
        ref = f"{row['ref_ms']:.1f}" if row["ref_ms"] is not None else "—"
        ratio = f"{row['ref_ms'] / row['ms']:.1f}×" if row["ref_ms"] is not None else "—"
        print(f"{row['preset']:<8} {row['op']:<42} {row['ms']:>10.1f} {ref:>10} {ratio:>9}  {row['note']}")


def main(argv: list[str], prog: str = "genre bench") -> int:
    parser = argparse.ArgumentParser(prog=prog, description="Print speed figures of the project's operations.")
    sub = parser.add_subparsers(dest="what", required=True)
    geo = sub.add_parser("geometry", help="time the geometry core at the default and paper resolutions")
    geo.add_argument("--preset", choices=[*PRESETS, "all"], default="all")
    geo.add_argument("--repeats", type=int, default=5, help="timed runs per op (median reported)")
    geo.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, device cpu")
    presets = list(PRESETS) if args.preset == "all" else [args.preset]
    rows = []
    for preset in presets:
        rows += geometry_benchmark(preset, args.repeats)
    _print_rows(rows)
    return 0
