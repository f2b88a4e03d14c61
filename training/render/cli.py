"""``genre data render``: render every shape's views into a views folder (resumable, shardable).

Shapes come from a corpus manifest or a folder of meshes
(:func:`training.data.views.read_shapes`); the folder's settings, failures
and views are files of :mod:`training.data.views`.  A shape that fails is
recorded and skipped by later runs; one whose rendering was interrupted
``MAX_ATTEMPTS`` times (Blender crashed or was killed on it) is given up.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Sequence

from genre_backend.io import atomic_write_json

from ..data.views import (FAILURES_GLOB, inflight_path, read_render_settings, read_shapes, render_failures_path,
                          view_is_complete, write_render_settings)
from .randomness import sample_views
from .scene import BlenderRenderer, RenderSettings, render_shape

__all__ = ["MAX_ATTEMPTS", "main"]

# A shape whose render was interrupted this many times (e.g. Blender crashed) is given up.
MAX_ATTEMPTS = 2


def _parse_shard(text: str) -> tuple[int, int]:
    try:
        i, n = (int(t) for t in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--shard expects I/N, got {text!r}") from None
    if n < 1 or not 0 <= i < n:
        raise argparse.ArgumentTypeError(f"--shard I/N needs 0 <= I < N, got {text!r}")
    return i, n


def _positive(text: str) -> int:
    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text}")
    return v


def _build_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog,
        description="Render RGB, planar depth, mask and camera JSON for every shape (Blender Cycles, CPU).",
    )
    p.add_argument("--shapes", required=True, help="a manifest JSON (data/corpus/manifest.json) or a folder of meshes")
    p.add_argument("--out", required=True, help="output folder (one sub-folder per shape)")
    p.add_argument("--views", type=_positive, default=20, help="random views per shape (default 20)")
    p.add_argument("--preset", choices=["default", "paper"], default="default", help="image size preset")
    p.add_argument("--seed", type=int, default=0, help="seed of views, lighting and backgrounds")
    p.add_argument("--limit", type=_positive, default=None, help="render only the first K shapes")
    p.add_argument("--shard", type=_parse_shard, default=(0, 1), metavar="I/N", help="render every N-th shape from I")
    p.add_argument("--split", default=None, help="only manifest shapes of this split or group (e.g. train, unseen)")
    p.add_argument("--samples", type=_positive, default=RenderSettings.samples, help="Cycles samples per pixel")
    p.add_argument("--threads", type=_positive, default=RenderSettings.threads, help="Cycles CPU threads")
    p.add_argument("--no-denoise", dest="denoise", action="store_false", help="turn off the fast OIDN denoiser")
    p.add_argument("--retry-failed", action="store_true", help="try again shapes recorded as failed")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def _read_json(path: Path, default):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return default


def main(argv: Sequence[str] | None = None, prog: str = "genre data render") -> int:
    """``genre data render``: render every shape's views.

    Returns 0 when every shape is complete or was already recorded as failed,
    1 when a shape failed in this run (recorded in ``render_failures*.json``
    and skipped by later runs unless ``--retry-failed``), 2 on a usage error.
    A shape whose rendering was interrupted ``MAX_ATTEMPTS`` times (Blender
    crashed or the process was killed while on it) is recorded as failed.
    """
    args = _build_parser(prog).parse_args(list(sys.argv[1:] if argv is None else argv))
    from genre_backend.config import get_preset  # noqa: PLC0415

    try:
        config = get_preset(args.preset)
        shapes = read_shapes(args.shapes)
    except ValueError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    if args.split is not None:
        shapes = [s for s in shapes if s.split == args.split or args.split in s.groups]
    shapes = shapes[args.shard[0]::args.shard[1]]
    if args.limit is not None:
        shapes = shapes[: args.limit]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    settings = RenderSettings(samples=args.samples, threads=args.threads, denoise=args.denoise)
    run_settings = {"preset": args.preset, "seed": args.seed, "image_size": config.geometry.image_size,
                    "camera": config.to_dict()["camera"]}
    previous = read_render_settings(out)
    if previous is not None and previous != run_settings:
        print(f"{prog}: error: {out} was rendered with other settings {previous}; use another --out", file=sys.stderr)
        return 2
    if previous is None:
        write_render_settings(out, run_settings)

    failures_file = render_failures_path(out, args.shard)
    inflight_file = inflight_path(out, args.shard)
    failures: dict[str, str] = {}
    for path in sorted(out.glob(FAILURES_GLOB)):
        failures.update(_read_json(path, {}))
    inflight: dict[str, int] = _read_json(inflight_file, {})
    if args.retry_failed:
        for path in out.glob(FAILURES_GLOB):
            path.unlink(missing_ok=True)
        failures, inflight = {}, {}
    total_views = len(shapes) * args.views
    from tqdm import tqdm  # noqa: PLC0415

    bar = tqdm(total=total_views, unit="view", desc="render", disable=args.no_progress, dynamic_ncols=True)
    renderer = None
    rendered = 0
    new_failures = 0
    t0 = time.perf_counter()
    try:
        for shape in shapes:
            views = sample_views(shape.id, args.views, args.seed, config.camera)
            if shape.id in failures:
                bar.update(args.views)
                continue
            attempts = int(inflight.get(shape.id, 0))
            if attempts >= MAX_ATTEMPTS:
                failures[shape.id] = f"rendering was interrupted {attempts} times (Blender crashed or was killed)"
                atomic_write_json(failures_file, failures)
                new_failures += 1
                bar.update(args.views)
                continue
            shape_dir = out / shape.id
            if all(view_is_complete(shape_dir, k) for k in range(args.views)):
                bar.update(args.views)
                continue
            inflight[shape.id] = attempts + 1
            atomic_write_json(inflight_file, inflight)
            reported = [0]

            def on_view(k, reported=reported):
                reported[0] += 1
                bar.update(1)

            if renderer is None:  # started only when there is work; a failure here is fatal, not the shape's
                try:
                    renderer = BlenderRenderer(config, settings)
                except Exception as exc:  # noqa: BLE001
                    tqdm.write(f"{prog}: error: could not set up Blender: {type(exc).__name__}: {exc}", file=sys.stderr)
                    return 2
            try:
                rendered += render_shape(renderer, shape, views, out, args.seed, on_view=on_view)
            except Exception as exc:  # noqa: BLE001  (one bad shape must not stop the corpus)
                failures[shape.id] = f"{type(exc).__name__}: {exc}"
                atomic_write_json(failures_file, failures)
                new_failures += 1
                tqdm.write(f"{prog}: skipped {shape.id}: {failures[shape.id]}", file=sys.stderr)
                bar.update(args.views - reported[0])
            inflight.pop(shape.id, None)
            atomic_write_json(inflight_file, inflight)
    finally:
        bar.close()
        if renderer is not None:
            renderer.close()
    dt = time.perf_counter() - t0
    rate = f", {dt / rendered:.3f} s/view including start-up" if rendered else ""
    summary = f"rendered {rendered} views of {len(shapes)} shapes in {dt:.1f} s{rate}"
    if failures:
        summary += f"; {len(failures)} failed shapes are listed in {out / 'render_failures*.json'}"
    print(summary)
    return 1 if new_failures else 0


if __name__ == "__main__":
    sys.exit(main())
