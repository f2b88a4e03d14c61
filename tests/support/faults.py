"""Fault injection helpers shared by the fault suite (``tests/backend/frontends/test_refuse_and_stop.py`` and
``test_stop_edges.py`` beside it): ``genre`` run as a subprocess with hooks that slow its writes, and folder
listings to compare before and after."""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from genre_backend.atomic import is_temporary_name
from support.server import ServerProcess

REPO = Path(__file__).resolve().parents[2]

# The CLI with every atomic write slowed: the bytes are written and flushed into the temporary, the target is
# appended to $GENRE_TEST_MARK, then it sleeps $GENRE_TEST_SLEEP seconds (before the file is closed and renamed).
SLOW_WRITES = """
import os, sys, time
import genre_backend.atomic as gio
_orig = gio._write_temporary
def _slow(path, writer):
    def w(fh):
        writer(fh)
        fh.flush()
        with open(os.environ["GENRE_TEST_MARK"], "a") as m:
            m.write(os.fspath(path) + "\\n")
        time.sleep(float(os.environ.get("GENRE_TEST_SLEEP", "3")))
    return _orig(path, w)
gio._write_temporary = _slow
from genre_backend.cli import main
sys.exit(main(sys.argv[1:]))
"""


# The same, ended as the `genre` console script ends (genre_backend.cli.run: the process's end included, a quick exit
# after `genre reconstruct` and after genre serve's `bye`), where SLOW_WRITES returns through sys.exit
SLOW_WRITES_RUN = SLOW_WRITES.replace("from genre_backend.cli import main\nsys.exit(main(sys.argv[1:]))",
                                      "from genre_backend.cli import run\nrun()")
assert SLOW_WRITES_RUN != SLOW_WRITES


def listing(root: Path) -> set[str]:
    """Every path under ``root``, relative to it."""
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def temporaries(root: Path) -> list[str]:
    """The project's temporary files under ``root`` (``.NAME.~genrePID-XXXXXXXX``)."""
    return sorted(n for n in listing(root) if is_temporary_name(Path(n).name))


def env(**extra) -> dict:
    return {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1", **extra}


def default_sigint() -> None:
    """(a child's preexec_fn) SIGINT back to its default: a suite started in the background of a non-interactive
    shell hands its children SIGINT ignored, and Python then, rightly, leaves Ctrl-C ignored."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def server_with_env(weights, cwd, environ, script: str | None = None, prefix: list[str] | None = None,
                    preexec=default_sigint) -> ServerProcess:
    """``genre serve --weights WEIGHTS`` (or ``script`` run as ``python -c script serve``) in ``cwd`` with the
    environment ``environ``, its stdout read into events on a thread."""
    s = ServerProcess.__new__(ServerProcess)
    cmd = [sys.executable, "-c", script, "serve"] if script else [sys.executable, "-m", "genre_backend.cli", "serve"]
    s.proc = subprocess.Popen([*(prefix or []), *cmd, "--weights", str(weights)], cwd=cwd, env=environ, text=True,
                              encoding="utf-8", errors="replace", stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, bufsize=1, preexec_fn=preexec)
    s.events = queue.Queue()
    s.raw = []
    threading.Thread(target=s._read, daemon=True).start()
    return s


def all_lines(s: ServerProcess) -> list[dict]:
    """Every event the (exited) server wrote."""
    while s.events.get(timeout=60) is not None:
        pass
    return [json.loads(line) for line in s.raw]


def wait_for_mark(mark: Path, proc, timeout: float = 300.0, writes: int = 1) -> list[str]:
    """Wait until the ``writes``-th temporary of the run holds its bytes (the slowed writer sleeps in it)."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        if mark.exists() and len(mark.read_text().splitlines()) >= writes:
            return mark.read_text().splitlines()
        assert proc.poll() is None, proc.stderr.read()
        time.sleep(0.05)
    raise AssertionError("no write began")


def job(rid, photo, output, **options) -> dict:
    return {"type": "reconstruct", "id": rid, "image": str(photo), "output": output, "options": options}
