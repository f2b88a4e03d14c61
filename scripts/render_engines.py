#!/usr/bin/env python3
"""Speed and agreement of the render engines on the same views (``genre data render --engine``).

Renders the same shapes and views with each engine, each in its own process
(so start-up and EEVEE's shader compilation are counted where they happen),
and prints per engine:

* start-up seconds (Blender scene set-up), the first view's seconds and the
  steady seconds per view (views after the first; written to disk as
  ``genre data render`` writes them);
* against Cycles on the same views: pixels hit by one engine only (and how
  many of those lie off the silhouette's 1-pixel band), the planar-depth
  difference where both hit (median, 99th percentile, the maximum off the
  silhouette band and overall, and that maximum expressed as how far the
  sampling point would have to move along the local depth slope, in pixels),
  mask (alpha ≥ 0.5) pixels that differ, and the mean absolute RGB
  difference (0-255) over pixels inside both masks.

Shapes: an icosphere, an off-centre cube and a table (legs and top), unless
``--shapes`` names a folder of meshes or a manifest.

    .venv/bin/python scripts/render_engines.py                      # 3 shapes x 4 views, all engines
    .venv/bin/python scripts/render_engines.py --engines cycles workbench --views 10
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from genre_backend.arguments import add_out, add_seed  # noqa: E402
from training.data import views as view_files  # noqa: E402
from training.render.scene import ENGINES, RenderSettings  # noqa: E402


def _make_shapes(folder: Path) -> Path:
    import trimesh  # noqa: PLC0415

    folder.mkdir(parents=True, exist_ok=True)
    trimesh.creation.icosphere(subdivisions=5, radius=0.3).export(folder / "sphere.ply")
    cube = trimesh.creation.box(extents=[0.35] * 3)
    cube.apply_translation([0.12, -0.05, 0.08])
    cube.export(folder / "cube.obj")
    top = trimesh.creation.box(extents=(0.8, 0.5, 0.06))
    top.apply_translation((0, 0, 0.3))
    parts = [top]
    for x, y in [(-0.35, -0.2), (0.35, -0.2), (-0.35, 0.2), (0.35, 0.2)]:
        leg = trimesh.creation.box(extents=(0.06, 0.06, 0.6))
        leg.apply_translation((x, y, 0.0))
        parts.append(leg)
    table = trimesh.util.concatenate(parts)
    table.apply_scale(1.0 / np.linalg.norm(table.bounds[1] - table.bounds[0]))
    table.export(folder / "table.ply")
    return folder


def _worker(args) -> None:
    """Render every shape's views with one engine into args.out; print the timings as one JSON line."""
    from genre_backend.config import get_preset  # noqa: PLC0415
    from training.render.randomness import sample_views  # noqa: PLC0415
    from training.render.scene import BlenderRenderer, render_shape  # noqa: PLC0415

    config = get_preset(args.preset)
    settings = RenderSettings(samples=args.samples, denoise=not args.no_denoise, engine=args.worker)
    t0 = time.perf_counter()
    renderer = BlenderRenderer(config, settings)
    setup = time.perf_counter() - t0
    times = []
    last = [time.perf_counter()]

    def on_view(k):
        now = time.perf_counter()
        times.append(now - last[0])
        last[0] = now

    for shape in view_files.read_shapes(args.shapes):
        last[0] = time.perf_counter()
        render_shape(renderer, shape, sample_views(shape.id, args.views, args.seed, config.camera), args.out,
                     args.seed, on_view=on_view)
    renderer.close()
    print(json.dumps({"setup_s": setup, "view_s": times, "notes": renderer.notes, "samples": settings.samples,
                      "denoise": renderer.denoise}))


def _band(hit: np.ndarray) -> np.ndarray:
    """Pixels with a 3x3 neighbour on the other side of the hit/background edge."""
    padded = np.pad(hit, 1, mode="edge")
    h, w = hit.shape
    return np.any([padded[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] != hit for dy in (-1, 0, 1) for dx in (-1, 0, 1)],
                  axis=0)


def _slope(depth: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """Largest depth change to a 4-neighbour that is also hit (scene units per pixel; 0 where none is)."""
    padded, hits = np.pad(depth, 1, mode="edge"), np.pad(hit, 1)
    h, w = depth.shape
    out = np.zeros_like(depth)
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        nb = padded[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
        ok = hits[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] & hit
        out = np.maximum(out, np.where(ok, np.abs(nb - depth), 0.0))
    return out


def _agreement(reference: Path, other: Path) -> dict:
    diffs, interior_max, overall_max, shift_max = [], 0.0, 0.0, 0.0
    xor = xor_off_band = mask_xor = hits = 0
    rgb_sum, rgb_n = 0.0, 0
    for shape_dir in sorted(p for p in reference.iterdir() if p.is_dir()):
        for k in view_files.view_indices(shape_dir):
            a, b = view_files.load_view(shape_dir, k), view_files.load_view(other / shape_dir.name, k)
            ha, hb = a["depth"] > 0, b["depth"] > 0
            band = _band(ha)
            both = ha & hb
            d = np.abs(a["depth"] - b["depth"])
            diffs.append(d[both])
            interior_max = max(interior_max, float(d[both & ~band].max(initial=0.0)))
            overall_max = max(overall_max, float(d[both].max(initial=0.0)))
            # The difference as a sideways shift of the sampling point, in pixels (where it is above 1e-5).
            slope = _slope(a["depth"], ha)
            big = both & ~band & (d > 1e-5) & (slope > 0)
            shift_max = max(shift_max, float((d[big] / slope[big]).max(initial=0.0)))
            hits += int(ha.sum())
            xor += int((ha ^ hb).sum())
            xor_off_band += int(((ha ^ hb) & ~band).sum())
            ma, mb = a["mask"] >= 0.5, b["mask"] >= 0.5
            mask_xor += int((ma ^ mb).sum())
            inside = ma & mb
            rgb_sum += float(np.abs(a["rgb"].astype(int) - b["rgb"].astype(int))[inside].sum())
            rgb_n += int(inside.sum()) * 3
    d = np.concatenate(diffs)
    return {"hits": hits, "hit_xor": xor, "hit_xor_off_band": xor_off_band, "depth_median": float(np.median(d)),
            "depth_p99": float(np.quantile(d, 0.99)), "depth_max_off_band": interior_max, "depth_max": overall_max,
            "shift_px_max": shift_max,
            "mask_xor": mask_xor, "rgb_mean_abs": rgb_sum / max(rgb_n, 1)}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--shapes", default=None, help="folder of meshes or manifest (default: sphere, cube, table)")
    p.add_argument("--engines", nargs="+", choices=ENGINES, default=list(ENGINES), help="engines to compare")
    p.add_argument("--views", type=int, default=4, help="views per shape (default 4)")
    p.add_argument("--samples", type=int, default=RenderSettings.samples, help="samples (as genre data render)")
    p.add_argument("--no-denoise", action="store_true", help="Cycles without its denoiser")
    p.add_argument("--preset", default="default")
    add_seed(p)
    p.add_argument("--worker", choices=ENGINES, help=argparse.SUPPRESS)
    add_out(p, type=Path, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.worker:
        _worker(args)
        return 0
    engines = ["cycles"] + [e for e in args.engines if e != "cycles"]
    with tempfile.TemporaryDirectory(prefix="genre-engines-") as tmp:
        tmp = Path(tmp)
        shapes = args.shapes or str(_make_shapes(tmp / "shapes"))
        n_shapes = len(view_files.read_shapes(shapes))
        print(f"{n_shapes} shapes x {args.views} views, preset {args.preset}, --samples {args.samples}"
              f"{', no denoiser' if args.no_denoise else ''}")
        rows = {}
        for engine in engines:
            cmd = [sys.executable, __file__, "--worker", engine, "--out", str(tmp / engine), "--shapes", shapes,
                   "--views", str(args.views), "--samples", str(args.samples), "--preset", args.preset,
                   "--seed", str(args.seed)] + (["--no-denoise"] if args.no_denoise else [])
            done = subprocess.run(cmd, capture_output=True, text=True)
            if done.returncode != 0:
                print(f"{engine}: failed (exit {done.returncode}): {done.stderr.strip().splitlines()[-1:]}")
                continue
            rows[engine] = json.loads(done.stdout.strip().splitlines()[-1])
            for note in rows[engine]["notes"]:
                print(f"{engine}: {note}")
        print(f"{'engine':10} {'start-up s':>10} {'first view s':>12} {'s/view':>7}")
        for engine, row in rows.items():
            steady = row["view_s"][1:] or row["view_s"]
            print(f"{engine:10} {row['setup_s']:10.2f} {row['view_s'][0]:12.2f} {float(np.mean(steady)):7.3f}")
        if "cycles" not in rows:
            return 1
        print("\nagainst cycles, same views (depth in scene units; camera 2.2 from the origin):")
        for engine in rows:
            if engine == "cycles":
                continue
            a = _agreement(tmp / "cycles", tmp / engine)
            print(f"{engine}: hit pixels {a['hits']}, hit by one engine only {a['hit_xor']} "
                  f"({a['hit_xor_off_band']} off the silhouette band); depth |diff| median {a['depth_median']:.1e}, "
                  f"p99 {a['depth_p99']:.1e}, max off the band {a['depth_max_off_band']:.1e}, "
                  f"max {a['depth_max']:.1e} (off the band at most a {a['shift_px_max']:.4f} px shift along the "
                  f"depth slope); mask pixels differing {a['mask_xor']}; "
                  f"RGB mean |diff| inside both masks {a['rgb_mean_abs']:.1f} / 255")
    return 0


if __name__ == "__main__":
    sys.exit(main())
