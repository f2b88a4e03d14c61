"""How a ``genre`` process ends: at once after a one-shot command, without the interpreter's tear-down."""

from __future__ import annotations

import os
import sys
import threading
from typing import NoReturn


def exit_process(code: int, quick: bool) -> NoReturn:
    """End this process with status ``code``.

    ``quick`` (a one-shot command such as ``genre reconstruct``, once it has returned), with no other thread left:
    the exit functions (``atexit``) run and the standard streams are flushed, then the process ends at once
    (``os._exit``), without the interpreter's tear-down of every module: torch's alone takes about 0.5 s of a cold
    ``genre reconstruct`` (docs/benchmarks.md).  Every file a command writes is closed by then (the one atomic
    write, :mod:`genre_backend.io`).  Otherwise, or with a thread still running: ``sys.exit(code)``.
    """
    if not quick or threading.active_count() > 1:
        sys.exit(code)
    import atexit

    atexit._run_exitfuncs()  # CPython's own runner of the exit functions (what a normal exit calls)
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe or stream: nothing more can be said on it
            pass
    os._exit(code)
