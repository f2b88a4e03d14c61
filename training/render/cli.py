"""``genre data render``: render every shape's views into a views folder (resumable, shardable).

Shapes come from a corpus manifest or a folder of meshes
(:func:`training.data.views.read_shapes`); the folder's settings, failures
and views are files of :mod:`training.data.views`.

What stops a shape, and what the next run does about it:

* its rendering raised an error (a broken mesh...): recorded as failed and
  skipped by later runs (``--retry-failed`` tries again);
* Blender crashed on it (a fatal signal: faulthandler writes into the
  shard's crash log): counted, and retried until it has crashed
  ``MAX_CRASHES`` times, then recorded as failed;
* the process was killed (``kill -9``, out of memory, power loss: nothing is
  written) or stopped with Ctrl-C: an interruption, never a failure; the
  next run renders the missing views.

Ctrl-C (SIGINT) or SIGTERM lets the view being rendered finish, then stops the
run with exit code 130 (SIGINT) or 143 (SIGTERM); a second signal stops at
once, with the same code.  Either way the process's temp folders (the
renderer's ``genre-render-<pid>-XXXXXXXX`` and Blender's session folder) are
removed; after a kill, the next run removes them.

Exit codes: 0 when every view of every selected shape is on disk, 1 when
views are missing because shapes failed (in this run or an earlier one; the
count is printed), 2 on a usage error or when Blender cannot render with the
chosen engine, 130 or 143 when interrupted (SIGINT, SIGTERM).
"""

from __future__ import annotations

import argparse
import dataclasses
import faulthandler
import json
import os
import signal
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from genre_backend.atomic import atomic_write_json
from genre_backend.arguments import add_out, add_seed, add_threads

from ..data.views import (FAILURES_GLOB, crash_log_path, read_render_attempts, read_render_settings, read_shapes,
                          render_failures_path, view_is_complete, write_render_attempts, write_render_settings)
from .randomness import sample_views
from .scene import ENGINES, LIGHTINGS, BlenderRenderer, RenderSettings, engine_problem, render_shape

__all__ = ["MAX_CRASHES", "EXIT_INTERRUPTED", "main"]

# A shape on which Blender crashed this many times is recorded as failed.
MAX_CRASHES = 2
# Interruptions never fail a shape; from this many on, each run warns about it.
WARN_INTERRUPTIONS = 3
# The shell's code for a process stopped by SIGINT.
EXIT_INTERRUPTED = 130


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
        description="Render RGB, planar depth, mask and camera JSON for every shape (Blender on the CPU).",
    )
    p.add_argument("--shapes", required=True, help="a manifest JSON ($GENRE_HOME/corpus/manifest.json) or a folder of meshes")
    add_out(p, required=True, help="output folder (one sub-folder per shape)")
    p.add_argument("--views", type=_positive, default=20, help="random views per shape (default 20)")
    p.add_argument("--preset", choices=["default", "paper"], default="default", help="image size preset")
    add_seed(p, help="seed of views, lighting and backgrounds")
    p.add_argument("--engine", choices=ENGINES, default="cycles",
                   help="render engine (default cycles; recorded in the folder's render_settings.json). Depth, mask "
                        "and camera mean the same for all; eevee and workbench need EGL (libegl1)")
    p.add_argument("--lighting", choices=LIGHTINGS, default=RenderSettings.lighting,
                   help="random (default): HDRI and suns from anywhere; camera-side: a key light from the camera's "
                        "side, as product photos are lit (recorded in render_settings.json)")
    p.add_argument("--limit", type=_positive, default=None, help="render only the first K shapes")
    p.add_argument("--shard", type=_parse_shard, default=(0, 1), metavar="I/N", help="render every N-th shape from I")
    p.add_argument("--split", default=None, help="only manifest shapes of this split or group (e.g. train, unseen)")
    p.add_argument("--elevation", type=float, nargs=2, default=None, metavar=("MIN", "MAX"),
                   help="camera elevations in degrees, in place of the preset's (e.g. 60 88: views from above); "
                        "recorded in render_settings.json")
    p.add_argument("--classes", nargs="+", default=None, metavar="CLASS",
                   help="only manifest shapes of these classes (e.g. primitive: more views of some shapes)")
    p.add_argument("--samples", type=_positive, default=RenderSettings.samples,
                   help="samples per pixel (Cycles, EEVEE); anti-aliasing samples for Workbench (1: none)")
    add_threads(p, type=_positive, default=RenderSettings.threads, help="Cycles CPU threads")
    p.add_argument("--no-denoise", dest="denoise", action="store_false", help="turn off Cycles' fast OIDN denoiser")
    p.add_argument("--retry-failed", action="store_true", help="try again shapes recorded as failed")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def _read_json(path: Path, default):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return default


class _StopOnSigint:
    """While active (main thread only), SIGINT or SIGTERM asks the run to stop after the current view.

    Python's own handler would raise KeyboardInterrupt wherever Python code
    runs next, which is often inside Cycles' Python callbacks, where Blender
    prints and swallows it and rendering goes on.  A second signal exits at
    once with 128 plus the first one's number (the files on disk stay
    consistent: every file is written atomically and a view is complete only
    once its JSON exists), after removing this process's temp folders (its
    scratch folder and Blender's session folder,
    :func:`genre_backend.process.remove_own_folders`).
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self, prog: str):
        self.prog = prog
        self.requested = False
        self.signum = signal.SIGINT  # the signal that asked (its exit status: 128 plus its number)
        self._previous: dict = {}

    @property
    def status(self) -> int:
        return 128 + int(self.signum)

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._previous = {sig: signal.signal(sig, self._handle) for sig in self.SIGNALS}
        return self

    def __exit__(self, *exc):
        for sig, previous in self._previous.items():  # (None: a handler installed outside Python, such as a stock Blender's own)
            signal.signal(sig, signal.SIG_DFL if previous is None else previous)
        return False

    def _handle(self, signum, frame):
        if self.requested:
            from genre_backend.process import remove_own_folders  # noqa: PLC0415

            os.write(2, f"\n{self.prog}: stopped at once\n".encode())
            remove_own_folders()
            os._exit(self.status)
        self.requested = True
        self.signum = signum
        again = "Ctrl-C" if signum == signal.SIGINT else "a second signal"
        os.write(2, f"\n{self.prog}: {signal.Signals(signum).name}: stopping after the current view ({again} to stop at once)\n".encode())

    def check(self) -> None:
        """Raise KeyboardInterrupt if a stop was asked for."""
        if self.requested:
            raise KeyboardInterrupt


def _settings_difference(previous: dict, wanted: dict) -> str:
    keys = sorted(set(previous) | set(wanted))
    return ", ".join(f"{k}={previous.get(k)!r} (asked: {wanted.get(k)!r})" for k in keys if previous.get(k) != wanted.get(k))


class _Refused(Exception):
    """A reason ``genre data render`` stops before rendering anything (one line, exit status 2)."""


def _shapes_to_render(args: argparse.Namespace):
    """(the preset's config, the shapes of ``--shapes`` this invocation renders: split, classes, shard, limit)."""
    from genre_backend.config import get_preset  # noqa: PLC0415

    try:
        config = get_preset(args.preset)
        if args.elevation is not None:
            lo, hi = args.elevation
            config = dataclasses.replace(config, camera=dataclasses.replace(config.camera, elevation_min_deg=lo,
                                                                             elevation_max_deg=hi))
        shapes = read_shapes(args.shapes)
    except ValueError as exc:
        raise _Refused(str(exc)) from None
    problem = engine_problem(args.engine)
    if problem:
        raise _Refused(problem)
    if args.split is not None:
        shapes = [s for s in shapes if s.split == args.split or args.split in s.groups]
    if args.classes is not None:
        wanted = set(args.classes)
        shapes = [s for s in shapes if s.cls in wanted]
        if not shapes:
            raise _Refused(f"no shape of the classes {sorted(wanted)} to render")
    shapes = shapes[args.shard[0]::args.shard[1]]
    if args.limit is not None:
        shapes = shapes[: args.limit]
    return config, shapes


@dataclass
class _RenderRun:
    """One invocation's rendering in progress: its settings, the shard's failures and attempts, the counters."""

    prog: str
    args: argparse.Namespace
    config: object  # GenreConfig
    out: Path
    settings: RenderSettings
    run_settings: dict
    previous: dict | None  # the settings the folder was rendered with (None: nothing rendered yet)
    failures: dict[str, str] = field(default_factory=dict)
    attempts: object = None  # data.views.RenderAttempts of this shard
    bar: object = None
    renderer: BlenderRenderer | None = None
    stop: _StopOnSigint | None = None
    rendered: int = 0

    @property
    def failures_file(self) -> Path:
        return render_failures_path(self.out, self.args.shard)

    @property
    def crash_log(self) -> Path:
        return crash_log_path(self.out, self.args.shard)

    def note(self, text: str) -> None:
        from tqdm import tqdm  # noqa: PLC0415

        tqdm.write(f"{self.prog}: {text}", file=sys.stderr)

    def save_attempts(self) -> None:
        write_render_attempts(self.out, self.args.shard, self.attempts)

    def fail(self, shape_id: str, why: str) -> None:
        """Record a shape as failed (later runs skip it) and say so."""
        self.failures[shape_id] = why
        atomic_write_json(self.failures_file, self.failures)
        self.note(f"skipped {shape_id}: {why}")


def _load_attempts(run: _RenderRun) -> None:
    """The shard's failures and attempts (all cleared by ``--retry-failed``); the shape an earlier run died on is
    counted as a crash when it left a crash log, else as an interruption."""
    for path in sorted(run.out.glob(FAILURES_GLOB)):
        run.failures.update(_read_json(path, {}))
    run.attempts = attempts = read_render_attempts(run.out, run.args.shard)
    if run.args.retry_failed:
        for path in run.out.glob(FAILURES_GLOB):
            path.unlink(missing_ok=True)
        run.failures = {}
        attempts.crashes = {}
    # The previous run of this shard died while rendering attempts.in_flight: a crash if it left a crash log.
    if attempts.in_flight is not None:
        sid = attempts.in_flight
        try:
            crash_text = run.crash_log.read_text(encoding="utf-8", errors="replace").strip()
        except OSError:
            crash_text = ""
        counts = attempts.crashes if crash_text else attempts.interruptions
        counts[sid] = counts.get(sid, 0) + 1
        if crash_text:
            first = crash_text.splitlines()[0]
            run.note(f"Blender crashed on {sid} in an earlier run ({first}); crash {counts[sid]} of at most {MAX_CRASHES}")
        attempts.in_flight = None
    run.save_attempts()


def _start_renderer(run: _RenderRun) -> int | None:
    """Blender, started when there is work (a failure here is fatal, not the shape's: returns 2); the folder's
    settings written with the first render."""
    try:
        run.renderer = BlenderRenderer(run.config, run.settings)
    except ValueError as exc:
        run.note(f"error: {exc}")
        return 2
    except Exception as exc:  # noqa: BLE001
        run.note(f"error: could not set up Blender: {type(exc).__name__}: {exc}")
        return 2
    for line in run.renderer.notes:
        run.note(line)
    if run.previous is None:
        write_render_settings(run.out, run.run_settings)
        run.previous = run.run_settings
    run.stop.check()
    return None


def _render_one(run: _RenderRun, shape) -> int | None:
    """Render the missing views of ``shape`` (skipped when failed, complete or crashed too often); a shape that
    raises is recorded as failed.  Returns 2 when Blender cannot start, else None."""
    args, attempts = run.args, run.attempts
    views = sample_views(shape.id, args.views, args.seed, run.config.camera)
    shape_dir = run.out / shape.id
    if shape.id in run.failures or all(view_is_complete(shape_dir, k) for k in range(args.views)):
        run.bar.update(args.views)
        return None
    crashes = attempts.crashes.get(shape.id, 0)
    if crashes >= MAX_CRASHES:
        run.fail(shape.id, f"Blender crashed {crashes} times while rendering it")
        run.bar.update(args.views)
        return None
    interruptions = attempts.interruptions.get(shape.id, 0)
    if interruptions >= WARN_INTERRUPTIONS:
        run.note(f"warning: rendering {shape.id} was interrupted {interruptions} times before "
                 f"(killed, perhaps for lack of memory?); trying again")
    if run.renderer is None and _start_renderer(run) is not None:
        return 2
    attempts.in_flight = shape.id
    run.save_attempts()
    todo = {k for k in range(args.views) if not view_is_complete(shape_dir, k)}
    reported = [0]

    def on_view(k, reported=reported, todo=todo):
        reported[0] += 1
        run.rendered += k in todo
        run.bar.update(1)
        run.stop.check()

    try:
        render_shape(run.renderer, shape, views, run.out, args.seed, on_view=on_view)
    except Exception as exc:  # noqa: BLE001  (one bad shape must not stop the corpus)
        run.fail(shape.id, f"{type(exc).__name__}: {exc}")
        run.bar.update(args.views - reported[0])
    attempts.in_flight = None
    attempts.crashes.pop(shape.id, None)
    attempts.interruptions.pop(shape.id, None)
    run.save_attempts()
    return None


def _render_all(run: _RenderRun, shapes: list) -> tuple[int | None, bool]:
    """Every shape in turn, with a crash log for faulthandler and Ctrl-C turned into a clean stop.
    Returns (2 when Blender could not start else None, whether it was interrupted)."""
    from tqdm import tqdm  # noqa: PLC0415

    run.bar = tqdm(total=len(shapes) * run.args.views, unit="view", desc="render", disable=run.args.no_progress,
                   dynamic_ncols=True)
    crash_fh = open(run.crash_log, "w", encoding="utf-8")  # noqa: SIM115  (open while faulthandler may write to it)
    faulthandler_was_enabled = faulthandler.is_enabled()
    faulthandler.enable(file=crash_fh, all_threads=True)
    run.stop = _StopOnSigint(run.prog)
    try:
        with run.stop:
            for shape in shapes:
                run.stop.check()
                if _render_one(run, shape) is not None:
                    return 2, False
    except KeyboardInterrupt:  # asked for by _StopOnSigint (or SIGINT outside the main thread's handler)
        if run.attempts.in_flight is not None:
            sid = run.attempts.in_flight
            run.attempts.interruptions[sid] = run.attempts.interruptions.get(sid, 0) + 1
            run.attempts.in_flight = None
            run.save_attempts()
        return None, True
    finally:
        run.bar.close()
        if run.renderer is not None:
            run.renderer.close()
        faulthandler.disable()
        if faulthandler_was_enabled:
            faulthandler.enable(file=sys.__stderr__, all_threads=True)
        crash_fh.close()
    return None, False


def _outcome(run: _RenderRun, shapes: list, seconds: float, interrupted: bool) -> int:
    """Print what was rendered and what is missing; the exit status (0, 1 with views missing, 130 interrupted)."""
    rate = f", {seconds / run.rendered:.3f} s/view including start-up" if run.rendered else ""
    print(f"rendered {run.rendered} views of {len(shapes)} shapes in {seconds:.1f} s{rate}", flush=True)
    views = run.args.views
    missing = {s.id: n for s in shapes if (n := sum(not view_is_complete(run.out / s.id, k) for k in range(views)))}
    if interrupted:
        print(f"{run.prog}: interrupted: {sum(missing.values())} views of {len(missing)} shapes are missing; "
              f"run the same command again to render them", file=sys.stderr)
        return run.stop.status if run.stop is not None else EXIT_INTERRUPTED
    if missing:
        failed = [sid for sid in missing if sid in run.failures]
        print(f"{run.prog}: {sum(missing.values())} views of {len(missing)} shapes are missing: {len(failed)} shapes "
              f"failed (listed with the reason in {run.out / 'render_failures*.json'}; --retry-failed renders them again)",
              file=sys.stderr)
        return 1
    return 0


def main(argv: Sequence[str] | None = None, prog: str = "genre data render") -> int:
    """``genre data render``: render every shape's views; returns the exit code (see the module's docstring)."""
    args = _build_parser(prog).parse_args(list(sys.argv[1:] if argv is None else argv))
    try:
        config, shapes = _shapes_to_render(args)
    except _Refused as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    settings = RenderSettings(samples=args.samples, threads=args.threads, denoise=args.denoise, engine=args.engine,
                              lighting=args.lighting)
    run_settings = {"preset": args.preset, "seed": args.seed, "image_size": config.geometry.image_size,
                    "camera": config.to_dict()["camera"], "engine": args.engine, "lighting": args.lighting}
    previous = read_render_settings(out)
    if previous is not None and previous != run_settings:
        print(f"{prog}: error: {out} was rendered with other settings: {_settings_difference(previous, run_settings)}; "
              f"use another --out", file=sys.stderr)
        return 2
    run = _RenderRun(prog, args, config, out, settings, run_settings, previous)
    _load_attempts(run)
    t0 = time.perf_counter()
    code, interrupted = _render_all(run, shapes)
    if code is not None:
        return code
    return _outcome(run, shapes, time.perf_counter() - t0, interrupted)


if __name__ == "__main__":
    sys.exit(main())
