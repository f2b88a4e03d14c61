"""How a ``genre`` process ends: its signals, its standard streams and its temp folders.

* **Signals** (:func:`install_stop_handlers`, :class:`Stop`): ``genre serve``
  takes SIGINT and SIGTERM over as the first thing it does, before any heavy
  import, so that from its first instant a signal ends it the documented way.
* **Streams** (:func:`open_missing_streams`, :func:`say`): a process started
  with a standard stream closed gets the null device there (so no file it
  opens lands on descriptor 1 or 2, where Blender's and torch's C-level
  prints would go into it), and a line goes to whichever of stdout and
  stderr still takes it.
* **Temp folders** (:func:`private_folder`): every folder a process makes in
  the shared temp folder carries its process id, is removed when it ends
  (exit functions; :func:`remove_own_folders` before an ``os._exit``), and,
  should it be killed, by the next process that makes one of the same kind.
* **The end** (:func:`exit_process`): after a one-shot command (``genre
  reconstruct``) or ``genre serve``, the exit functions run, the streams are
  flushed and the process ends without the interpreter's tear-down.

Only the standard library, imported lazily where it costs: ``genre serve``
imports this module before anything else.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from pathlib import Path  # (loaded already by the interpreter's start-up: the editable install's finder)

# (no `typing`: this module loads before genre serve's signal handlers, which should come as early as they can)

__all__ = ["Stop", "install_stop_handlers", "uninstall_stop_handlers", "take_stops", "stops_quiet", "open_missing_streams", "say", "private_folder",
           "remove_own_folders", "remove_dead_folders", "is_private_folder_name", "exit_process"]


# ---------------------------------------------------------------------------------------------- signals
class Stop(BaseException):
    """SIGINT or SIGTERM arrived (raised in the main thread by the handler :func:`install_stop_handlers` installs)."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum

    @property
    def reason(self) -> str:
        return signal.Signals(self.signum).name

    @property
    def status(self) -> int:
        """The exit status of a process this signal stopped: 128 plus its number (130, 143)."""
        return 128 + self.signum


# the stop's state: the signal stopping this process (None: none yet); ``at_once`` (while starting): a function of
# the signal's name giving the (stderr, stdout) lines to write before ending at once, else None (the handler raises
# :class:`Stop`); ``quiet``: the process has said its last line and is ending
_state = {"signum": None, "at_once": None, "quiet": False, "installed": False}
_previous: dict = {}  # the handlers replaced


def _on_stop_signal(signum, frame) -> None:
    name = signal.Signals(signum).name
    if _state["signum"] is not None or _state["quiet"]:
        import logging

        if _state["quiet"]:
            logging.getLogger("genre").warning("%s: ignored: already ending", name)
        else:
            logging.getLogger("genre").warning("%s: already stopping (on %s); finishing the write in progress", name,
                                               signal.Signals(_state["signum"]).name)
        return
    _state["signum"] = signum
    if _state["at_once"] is not None:  # still starting: nothing written, nothing to finish
        for fd, line in zip((2, 1), _state["at_once"](name)):
            try:
                os.write(fd, (line + "\n").encode())
            except OSError:  # a closed stream
                pass
        os._exit(128 + signum)
    raise Stop(signum)


def install_stop_handlers(at_once=None) -> bool:
    """SIGINT and SIGTERM stop this process, once; a later one is logged and otherwise ignored (the first is
    already stopping it).  Installed whatever the signals' disposition was, so a server started with SIGINT
    ignored (the background of a shell) still stops on it.  Main thread only; installed once.

    ``at_once`` (a process still starting, which has written nothing and has nothing to finish): a function of the
    signal's name returning the line for stderr and the line for stdout; the handler writes them and ends the
    process at once with 128 plus the signal's number, wherever it was (an import half done included), until
    :func:`take_stops`.  Without it (or after :func:`take_stops`) the handler raises :class:`Stop` in the main
    thread.  Returns whether this call installed them."""
    if threading.current_thread() is not threading.main_thread() or _state["installed"]:
        return False
    _state.update(signum=None, at_once=at_once, quiet=False)
    for sig in (signal.SIGINT, signal.SIGTERM):  # (SIGTERM last: once it is caught, both are this module's)
        _previous[sig] = signal.signal(sig, _on_stop_signal)
    _state["installed"] = True
    return True


def uninstall_stop_handlers() -> None:
    """Put back the handlers :func:`install_stop_handlers` replaced (a caller in a longer-lived process: a test)."""
    if _state["installed"] and threading.current_thread() is threading.main_thread():
        for sig, previous in _previous.items():
            signal.signal(sig, signal.SIG_DFL if previous is None else previous)
        _previous.clear()
        _state.update(signum=None, at_once=None, quiet=False, installed=False)


def take_stops() -> None:
    """From now on a signal raises :class:`Stop` (instead of ending the process at once): the process has begun
    what a stop must finish (``genre serve``: its ``ready`` line)."""
    _state["at_once"] = None


def stops_quiet() -> None:
    """From now on a signal raises nothing (it is logged): the process has said its last line and is ending."""
    _state["quiet"] = True


# ---------------------------------------------------------------------------------------------- streams
def open_missing_streams() -> None:
    """Give each of the standard descriptors 0, 1 and 2 that is closed the null device (the Python stream stays
    ``None``: nothing is written there).  Otherwise the next file opened would take descriptor 1 or 2, and
    anything a library prints at C level would go into it."""
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:
            try:
                got = os.open(os.devnull, os.O_RDWR)
            except OSError:
                return
            if got != fd:  # (another descriptor was free below it: cannot happen in order 0, 1, 2)
                os.dup2(got, fd)
                os.close(got)


def _write_line(stream, text: str) -> bool:  # (stream: a text stream or None)
    if stream is None:
        return False
    try:
        stream.write(text + "\n")
        stream.flush()
    except (OSError, ValueError, AttributeError):  # a closed pipe, a closed stream, a stream replaced by None
        return False
    return True


def say(text: str, err: bool = True) -> bool:
    """Write the line ``text`` on stderr (``err``) or stdout, else on the other one when that one is closed or
    broken; False when neither takes it.  Never raises."""
    first, second = (sys.stderr, sys.stdout) if err else (sys.stdout, sys.stderr)
    return _write_line(first, text) or _write_line(second, text)


# ---------------------------------------------------------------------------------------------- temp folders
_RANDOM_CHARS = 8  # mkdtemp's random part
_folders: list[tuple[int, Path]] = []  # (the process that made it, the folder)


def is_private_folder_name(name: str, prefix: str) -> int | None:
    """The process id in ``name`` when it is one :func:`private_folder` makes with ``prefix``
    (``PREFIX<pid>-XXXXXXXX``), else None."""
    if not name.startswith(prefix):
        return None
    pid, dash, rand = name[len(prefix):].partition("-")
    if not (pid.isdigit() and dash and len(rand) == _RANDOM_CHARS and rand.isascii() and rand.replace("_", "").isalnum()):
        return None
    return int(pid)


def remove_dead_folders(prefix: str, root: str | os.PathLike) -> int:
    """Remove the folders ``root/PREFIX<pid>-XXXXXXXX`` of this user whose process no longer runs (one killed
    before it could remove its own); returns how many.  A link, a file, another user's folder, a live process's
    or any other name is never touched."""
    import shutil
    import stat

    from .atomic import pid_alive

    removed = 0
    try:
        entries = list(os.scandir(root))
    except OSError:
        return 0
    for entry in entries:
        pid = is_private_folder_name(entry.name, prefix)
        if pid is None or pid == os.getpid():
            continue
        try:
            st = entry.stat(follow_symlinks=False)
        except OSError:
            continue
        if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.geteuid() or pid_alive(pid):
            continue
        shutil.rmtree(entry.path, ignore_errors=True)
        removed += not os.path.lexists(entry.path)
    return removed


def private_folder(prefix: str) -> Path:
    """A fresh folder ``PREFIX<pid>-XXXXXXXX`` in the temp folder (``tempfile.mkdtemp``: mode 0700, a name
    nobody can plant in advance), removed with everything in it when this process ends: by the exit functions,
    or by :func:`remove_own_folders` before an ``os._exit``.  The folders of this kind that killed processes
    left behind are removed first (:func:`remove_dead_folders`)."""
    import tempfile

    folder = Path(tempfile.mkdtemp(prefix=f"{prefix}{os.getpid()}-"))
    remove_dead_folders(prefix, folder.parent)
    if not _folders:
        import atexit

        atexit.register(remove_own_folders)
    _folders.append((os.getpid(), folder))
    return folder


def remove_own_folders() -> None:
    """Remove every folder :func:`private_folder` made in this process (a forked child leaves its parent's)."""
    import shutil

    while _folders:
        pid, folder = _folders.pop()
        if pid == os.getpid():
            shutil.rmtree(folder, ignore_errors=True)


# ---------------------------------------------------------------------------------------------- the end
def exit_process(code: int, quick: bool):  # -> NoReturn
    """End this process with status ``code``.

    ``quick`` (a one-shot command such as ``genre reconstruct``, once it has returned; ``genre serve`` once it
    has said ``bye``), with no other thread left: the exit functions (``atexit``) run and the standard streams
    are flushed, then the process ends at once (``os._exit``), without the interpreter's tear-down of every
    module: torch's alone takes about 0.5 s of a cold ``genre reconstruct`` (docs/lab/benchmarks.md), and the
    tear-down puts SIGINT and SIGTERM back to their defaults, so a second signal there would kill the process
    instead of being ignored.  Every file a command writes is closed by then (the one atomic write,
    :mod:`genre_backend.atomic`).  Otherwise, or with a thread still running: ``sys.exit(code)``.
    """
    if not quick or threading.active_count() > 1:
        sys.exit(code)
    import atexit

    atexit._run_exitfuncs()  # CPython's own runner of the exit functions (what a normal exit calls)
    for stream in (sys.stdout, sys.stderr):
        try:
            if stream is not None:
                stream.flush()
        except (OSError, ValueError):  # a closed pipe or stream: nothing more can be said on it
            pass
    os._exit(code)
