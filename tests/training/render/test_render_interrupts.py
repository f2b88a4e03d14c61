"""Interrupted rendering (issue 18): kills and Ctrl-C are resumable interruptions, crashes and errors fail a shape.

Each case runs ``genre data render`` in a child process (real Blender,
real signals) and checks the folder against an uninterrupted run of the
same command.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("bpy")
trimesh = pytest.importorskip("trimesh")

from training.data import views as view_files  # noqa: E402
from training.render.cli import EXIT_INTERRUPTED, MAX_CRASHES  # noqa: E402

ROOT = Path(__file__).resolve().parents[3]
VIEWS = 5


@pytest.fixture(scope="module")
def shapes(tmp_path_factory):
    folder = tmp_path_factory.mktemp("shapes")
    trimesh.creation.icosphere(subdivisions=4, radius=0.3).export(folder / "ball.ply")
    box = trimesh.creation.box(extents=[0.3, 0.2, 0.4])
    box.apply_translation([0.1, 0.05, 0.0])
    box.export(folder / "box.obj")
    return folder


def _argv(shapes: Path, out: Path) -> list[str]:
    return ["--shapes", str(shapes), "--out", str(out), "--views", str(VIEWS), "--samples", "8", "--no-progress"]


def _command(argv: list[str], prelude: str = "") -> list[str]:
    code = f"import sys\n{prelude}\nfrom training.render.cli import main\nsys.exit(main({argv!r}, 'r'))\n"
    return [sys.executable, "-c", code]


def _env(tmp: Path) -> dict:
    return dict(os.environ, GENRE_BLENDER_CACHE=str(tmp / "cache"))


def _start(argv, tmp: Path, prelude: str = "") -> subprocess.Popen:
    return subprocess.Popen(_command(argv, prelude), cwd=ROOT, env=_env(tmp), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _wait_for(path: Path, proc: subprocess.Popen, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        assert proc.poll() is None, f"the renderer ended before {path.name}: {proc.communicate()}"
        assert time.monotonic() < deadline, f"no {path} after {timeout} s"
        time.sleep(0.01)


def _run(argv, tmp: Path, prelude: str = "") -> subprocess.CompletedProcess:
    return subprocess.run(_command(argv, prelude), cwd=ROOT, env=_env(tmp), capture_output=True, text=True,
                          timeout=600)


@pytest.fixture(scope="module")
def reference(shapes, tmp_path_factory):
    """The same command run once without interruption."""
    tmp = tmp_path_factory.mktemp("reference")
    out = tmp / "out"
    done = _run(_argv(shapes, out), tmp)
    assert done.returncode == 0, done.stderr
    return out


def _assert_same_as(reference: Path, out: Path) -> None:
    """Every view of ``out`` is complete, no temporaries are left, and each equals the reference's."""
    for shape in ("ball", "box"):
        names = sorted(p.name for p in (out / shape).iterdir())
        assert names == [f"view_{k:03d}.{ext}" for k in range(VIEWS) for ext in ("json", "npz", "png")]
        for k in range(VIEWS):
            a, b = view_files.load_view(reference / shape, k), view_files.load_view(out / shape, k)
            np.testing.assert_array_equal(a["depth"], b["depth"])
            np.testing.assert_array_equal(a["mask"], b["mask"])
            np.testing.assert_array_equal(a["rgb"], b["rgb"], err_msg=f"{shape} view {k}")
            assert a["camera"] == b["camera"]
    assert not list(out.glob("render_failures*.json"))


@pytest.mark.slow
def test_killed_twice_on_one_shape_then_resumed(shapes, reference, tmp_path):
    """kill -9 twice while the same shape renders: neither kill fails it, and a third run completes the folder."""
    out = tmp_path / "out"
    argv = _argv(shapes, out)
    for k in (0, 2):  # the first run is killed after view 0 of 'ball', the second after view 2 of it
        proc = _start(argv, tmp_path)
        try:
            _wait_for(out / "ball" / f"view_{k:03d}.json", proc)
            os.kill(proc.pid, signal.SIGKILL)
        finally:
            proc.communicate()
        assert proc.returncode == -signal.SIGKILL
        assert not view_files.view_is_complete(out / "ball", VIEWS - 1)
    attempts = view_files.read_render_attempts(out)
    assert attempts.in_flight == "ball" and attempts.crashes == {}
    done = _run(argv, tmp_path)
    assert done.returncode == 0, done.stderr
    attempts = view_files.read_render_attempts(out)
    assert attempts == view_files.RenderAttempts()  # counted as interruptions, then cleared once 'ball' was done
    _assert_same_as(reference, out)


def _interrupt_after_first_views(proc: subprocess.Popen, out) -> tuple[str, float]:
    """Ctrl-C once the first shape has two views on disk; (stderr, seconds from the signal to the exit)."""
    try:
        _wait_for(out / "ball" / "view_001.json", proc)
        sent = time.monotonic()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
        return err, time.monotonic() - sent
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


@pytest.mark.slow
def test_ctrl_c_stops_promptly_with_130_and_resumes(shapes, reference, tmp_path):
    out = tmp_path / "out"
    argv = _argv(shapes, out)
    proc = _start(argv, tmp_path)
    err, waited = _interrupt_after_first_views(proc, out)
    assert proc.returncode == EXIT_INTERRUPTED, err
    # At most the view being rendered (~0.3 s here) is finished first, then Blender is closed.
    assert waited < 10.0, f"the run took {waited:.1f} s to stop"
    assert "Traceback" not in err and "KeyboardInterrupt" not in err
    complete = sum(view_files.view_is_complete(out / s, k) for s in ("ball", "box") for k in range(VIEWS))
    assert 2 <= complete < 2 * VIEWS
    assert f"interrupted: {2 * VIEWS - complete} views of" in err
    assert view_files.read_render_attempts(out).in_flight is None
    done = _run(argv, tmp_path)
    assert done.returncode == 0, done.stderr
    _assert_same_as(reference, out)


# ---- issue 51: SIGTERM as Ctrl-C, and no temp folder left ($TMPDIR a fresh folder; Blender's cache outside it)
def _start_in(argv, tmp: Path, tmpdir: Path) -> subprocess.Popen:
    return subprocess.Popen(_command(argv), cwd=ROOT, env=dict(_env(tmp), TMPDIR=str(tmpdir)), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _fresh_tmpdir(tmp_path: Path) -> Path:
    tmpdir = tmp_path / "tmpdir"
    tmpdir.mkdir()
    return tmpdir


def _listing(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


@pytest.mark.slow
@pytest.mark.parametrize("signals", [1, 2], ids=["once", "twice"])
def test_sigterm_stops_like_ctrl_c_with_143_and_leaves_no_temp_folder(shapes, reference, tmp_path, signals):
    """SIGTERM lets the view being rendered finish (once) or stops at once (twice); either way the renderer's
    scratch folder (genre-render-<pid>-…, where the partial view_depth.exr and view_rgba.png lie) and Blender's
    session folder (blender_XXXXXX, in genre-bpy-<pid>-…) are removed, and the next run completes the folder."""
    out = tmp_path / "out"
    argv = _argv(shapes, out)
    tmpdir = _fresh_tmpdir(tmp_path)
    proc = _start_in(argv, tmp_path, tmpdir)
    try:
        _wait_for(out / "ball" / "view_001.json", proc)
        during = _listing(tmpdir)
        assert any(n.startswith("genre-render-") for n in during) and any("/blender_" in n for n in during), during
        for _ in range(signals):
            proc.send_signal(signal.SIGTERM)
            time.sleep(0.02)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 143, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err
    assert "SIGTERM: stopping after the current view" in err
    if signals == 1:
        assert "interrupted:" in err and "views of" in err
    else:  # (on a loaded machine the current view may end before the second signal lands: then it is the first's stop)
        assert "stopped at once" in err or ("interrupted:" in err and "views of" in err), err
    assert _listing(tmpdir) == set()
    done = subprocess.run(_command(argv), cwd=ROOT, env=dict(_env(tmp_path), TMPDIR=str(tmpdir)), capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    _assert_same_as(reference, out)
    assert _listing(tmpdir) == set()


@pytest.mark.slow
def test_after_a_kill_the_next_run_removes_the_temp_folders(shapes, tmp_path):
    out = tmp_path / "out"
    argv = _argv(shapes, out)
    tmpdir = _fresh_tmpdir(tmp_path)
    proc = _start_in(argv, tmp_path, tmpdir)
    try:
        _wait_for(out / "ball" / "view_000.json", proc)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.communicate()
    left = {n for n in _listing(tmpdir) if "/" not in n}
    assert {n.split(f"{proc.pid}-")[0] for n in left} == {"genre-render-", "genre-bpy-"}, left
    done = subprocess.run(_command(argv), cwd=ROOT, env=dict(_env(tmp_path), TMPDIR=str(tmpdir)), capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert _listing(tmpdir) == set()


# Makes rendering the box crash the process with a real SIGSEGV (as a Blender crash would).
_CRASH_ON_BOX = """
import faulthandler
import training.render.cli as cli
_render_shape = cli.render_shape
def render_shape(renderer, shape, *args, **kwargs):
    if shape.id == "box":
        faulthandler._sigsegv()
    return _render_shape(renderer, shape, *args, **kwargs)
cli.render_shape = render_shape
"""


@pytest.mark.slow
def test_repeated_crashes_fail_the_shape_and_the_run_says_what_is_missing(shapes, tmp_path):
    out = tmp_path / "out"
    argv = _argv(shapes, out)
    for _crash in range(1, MAX_CRASHES + 1):
        done = _run(argv, tmp_path, _CRASH_ON_BOX)
        assert done.returncode == -signal.SIGSEGV, done.stderr
        assert "Segmentation fault" in view_files.crash_log_path(out).read_text()
        assert not (out / "render_failures.json").exists()  # a crash is retried until the MAX_CRASHES-th
    assert all(view_files.view_is_complete(out / "ball", k) for k in range(VIEWS))
    done = _run(argv, tmp_path, _CRASH_ON_BOX)
    assert done.returncode == 1
    assert f"Blender crashed on box in an earlier run (Fatal Python error: Segmentation fault); crash {MAX_CRASHES}" \
        in done.stderr
    assert f"{VIEWS} views of 1 shapes are missing: 1 shapes failed" in done.stderr
    failures = json.loads((out / "render_failures.json").read_text())
    assert failures == {"box": f"Blender crashed {MAX_CRASHES} times while rendering it"}
    # Later runs skip it and still say that views are missing; --retry-failed renders it.
    again = _run(argv, tmp_path)
    assert again.returncode == 1 and f"{VIEWS} views of 1 shapes are missing" in again.stderr
    retried = _run(argv + ["--retry-failed"], tmp_path)
    assert retried.returncode == 0, retried.stderr
    assert all(view_files.view_is_complete(out / "box", k) for k in range(VIEWS))
    assert view_files.read_render_attempts(out) == view_files.RenderAttempts()


def test_attempts_file_of_older_versions_reads_as_interruptions(tmp_path):
    view_files.inflight_path(tmp_path).write_text(json.dumps({"a": 2, "b": 1}))
    assert view_files.read_render_attempts(tmp_path) == view_files.RenderAttempts(interruptions={"a": 2, "b": 1})
    view_files.inflight_path(tmp_path).write_text("{broken")
    assert view_files.read_render_attempts(tmp_path) == view_files.RenderAttempts()
    attempts = view_files.RenderAttempts("a", {"a": 1}, {"b": 3})
    view_files.write_render_attempts(tmp_path, (0, 1), attempts)
    assert view_files.read_render_attempts(tmp_path) == attempts


@pytest.mark.slow
@pytest.mark.blender
def test_ctrl_c_in_a_stock_blender_stops_with_130(shapes, tmp_path):
    """A stock Blender installs a SIGINT handler of its own (not Python's); the run still stops with 130 and resumes."""
    out = tmp_path / "out"
    env = dict(_env(tmp_path), BLENDER_USER_RESOURCES=str(tmp_path / "user"), XDG_CACHE_HOME=str(tmp_path / "xdg"))
    script = ROOT / "training" / "render" / "blender_script.py"
    cmd = [shutil.which("blender"), "--background", "--factory-startup", "--python", str(script), "--",
           *_argv(shapes, out), "--no-denoise"]
    proc = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    err, waited = _interrupt_after_first_views(proc, out)
    assert proc.returncode == EXIT_INTERRUPTED, err
    assert waited < 10.0
    assert "interrupted:" in err and "views of" in err
    done = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert all(view_files.view_is_complete(out / s, k) for s in ("ball", "box") for k in range(VIEWS))
