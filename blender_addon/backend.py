"""Talking to one long-lived ``genre serve`` process, without ``bpy``.

Nothing here imports ``bpy``: the add-on's operators call these classes from
Blender's main thread, and the tests drive them directly.

* :func:`build_command` turns the add-on preferences (backend command,
  weights, device) into the argument list of ``genre serve``;
  :func:`weights_argument` turns the Model choice (the shipped ``default`` or
  ``protocol`` weights, or a custom file) into its ``--weights`` value.
* :class:`BackendClient` owns the subprocess.  A reader thread parses its
  stdout (one JSON object per line, see ``docs/protocol.md``) into the
  event dataclasses of :mod:`.protocol` (a copy of the backend's), queued;
  a second thread keeps the last lines of stderr for error messages.  The
  main thread only ever calls the non-blocking :meth:`BackendClient.poll`.
* :class:`Request` is one request (``version`` or ``reconstruct``) followed
  to its answer by :meth:`Request.tick`, called once per timer tick.  It
  starts the backend if needed, waits for ``ready``, sends the request,
  follows the progress, handles cancel, time-outs and a dying backend, and
  ends in exactly one of ``done``, ``failed`` or ``cancelled``.
"""

from __future__ import annotations

import collections
import itertools
import json
import os
import queue
import shlex
import shutil
import stat
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from .protocol import REQUESTS, Cancel, Error, Progress, Ready, message, read_event

__all__ = [
    "BackendError",
    "BackendClient",
    "BackendManager",
    "Request",
    "build_command",
    "weights_argument",
    "MODELS",
    "STAGE_LABELS",
    "private_temp_root",
]

# The add-on preferences' Model choices (identifier, label, description): the backend's two shipped
# weights by name (genre_backend/weights/NAME.safetensors, see the README's "Which weights") and a file.
MODELS = (
    ("default", "Product", "The product model (the backend's 'default' weights): the one for everyday use"),
    ("protocol", "Research protocol", "The research weights ('protocol'): trained on the seen classes only, behind every published table"),
    ("custom", "Custom file", "A weights file (.safetensors) of your own"),
)
SHIPPED_WEIGHTS = ("default", "protocol")

# Human names of the server's progress stages (docs/protocol.md).
STAGE_LABELS = {
    "starting": "Starting backend",
    "queued": "Waiting for backend",
    "load": "Loading photo",
    "preprocess": "Preparing photo",
    "depth": "Estimating depth",
    "partial_sph": "Projecting to sphere",
    "inpaint": "Completing sphere",
    "voxels": "Building voxels",
    "refine": "Refining shape",
    "mesh": "Extracting mesh",
    "write": "Writing mesh",
    "cancelling": "Cancelling",
}

_EOF = object()  # the reader thread's last item: stdout closed


class BackendError(RuntimeError):
    """A one-line, user-facing reason why the backend could not do its job."""


def weights_argument(model: str, path: str = "") -> str:
    """``--weights``' value for the Model preference: ``default``/``protocol`` by name, ``custom`` the file ``path``.

    Raises :class:`BackendError` for a custom model without a file, or an unknown model.
    """
    if model in SHIPPED_WEIGHTS:
        return model
    if model == "custom":
        if not (path or "").strip():
            raise BackendError("Model is 'Custom file' but no weights file is set: choose one in the add-on preferences")
        return path
    raise BackendError(f"unknown model {model!r}: choose {', '.join(m[0] for m in MODELS)}")


def build_command(command: str, weights: str = "", device: str = "auto", *, which: Callable[[str], str | None] = shutil.which) -> list[str]:
    """The argument list that starts ``genre serve`` from the add-on preferences.

    ``command`` is either a Python interpreter that has the backend installed
    (run as ``python -m genre_backend.cli serve``) or the ``genre`` executable;
    empty means ``genre`` found on ``PATH``.  A value that is not an existing
    file is split like a shell command line, so ``/opt/py/bin/python3 -X utf8``
    works too.  ``weights`` is a shipped weights name (``default``,
    ``protocol``: passed as it is), a file (passed as an absolute path), or
    empty (no ``--weights``: the backend's default).  ``device`` is ``auto``
    (the server's choice), ``cpu`` or ``cuda``.
    Raises :class:`BackendError` when the program cannot be found.
    """
    command = (command or "").strip()
    if not command:
        found = which("genre")
        if not found:
            raise BackendError("no backend command set: choose a Python with the GenRe backend installed, "
                               "or the 'genre' program, in the add-on preferences")
        argv = [found]
    elif os.path.isfile(os.path.expanduser(command)):
        argv = [os.path.expanduser(command)]
    else:
        try:
            argv = shlex.split(command)
        except ValueError as exc:
            raise BackendError(f"cannot parse the backend command {command!r}: {exc}") from None
        if not argv:
            raise BackendError("the backend command is empty")
    program = os.path.expanduser(argv[0])
    if os.sep in program or (os.altsep and os.altsep in program):
        if not os.path.isfile(program):
            raise BackendError(f"backend command not found: {program}")
        if not os.access(program, os.X_OK):
            raise BackendError(f"backend command is not executable: {program}")
    else:
        found = which(program)
        if not found:
            raise BackendError(f"backend command not found on PATH: {program}")
        program = found
    argv[0] = program
    name = os.path.basename(program).lower()
    if name.startswith("python") or name.startswith("pypy"):
        argv += ["-m", "genre_backend.cli", "serve"]
    else:
        argv += ["serve"]
    if weights in SHIPPED_WEIGHTS:
        argv += ["--weights", weights]
    elif weights:
        argv += ["--weights", os.path.abspath(os.path.expanduser(weights))]
    if device and device != "auto":
        argv += ["--device", device]
    return argv


class BackendClient:
    """One ``genre serve`` subprocess with a reader thread; all methods are non-blocking except :meth:`stop`."""

    STDERR_LINES = 40

    def __init__(self, argv: list[str], *, env: dict[str, str] | None = None, cwd: str | None = None):
        self.argv = list(argv)
        self.ready: Ready | None = None  # the server's ready event, once seen
        self.started_at = 0.0
        self._env = env
        self._cwd = cwd
        self._proc: subprocess.Popen | None = None
        self._events: queue.Queue = queue.Queue()
        self._stderr: collections.deque[str] = collections.deque(maxlen=self.STDERR_LINES)
        self._closed = False  # stdout reached end of file
        self._write_lock = threading.Lock()
        self._threads: list[threading.Thread] = []

    # -- life cycle ---------------------------------------------------------
    def start(self) -> None:
        """Spawn the process (does not wait for ``ready``); :class:`BackendError` when it cannot start."""
        if self._proc is not None:
            raise RuntimeError("BackendClient.start() called twice")
        env = dict(os.environ if self._env is None else self._env)
        env.setdefault("PYTHONUNBUFFERED", "1")
        env["PYTHONIOENCODING"] = "utf-8"
        # `python -m` would put the working folder first on sys.path: a genre_backend folder there (Blender started in
        # a checkout) would shadow the installed backend. Python 3.11+ leaves it out with this set.
        env["PYTHONSAFEPATH"] = "1"
        # Blender's own Python settings must not leak into the backend's interpreter.
        if self._env is None:
            for key in ("PYTHONHOME", "PYTHONPATH", "PYTHONSTARTUP"):
                env.pop(key, None)
        kwargs: dict[str, Any] = {}
        if sys.platform == "win32":  # no console window per backend
            kwargs["creationflags"] = getattr(subprocess, "CREATE_NO_WINDOW", 0)
        else:
            kwargs["start_new_session"] = True  # Ctrl-C in Blender's terminal is Blender's, not the backend's
        try:
            self._proc = subprocess.Popen(
                self.argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                env=env, cwd=self._cwd, bufsize=0, **kwargs,
            )
        except FileNotFoundError:
            raise BackendError(f"backend command not found: {self.argv[0]}") from None
        except PermissionError:
            raise BackendError(f"backend command is not executable: {self.argv[0]}") from None
        except OSError as exc:
            raise BackendError(f"cannot start the backend ({self.argv[0]}): {exc.strerror or exc}") from None
        self.started_at = time.monotonic()
        for target, name in ((self._read_stdout, "genre-stdout"), (self._read_stderr, "genre-stderr")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def returncode(self) -> int | None:
        return None if self._proc is None else self._proc.poll()

    def alive(self) -> bool:
        """The process runs and its stdout is still open."""
        return self._proc is not None and self._proc.poll() is None and not self._closed

    def stop(self, timeout: float = 3.0) -> None:
        """Ask the server to shut down, then terminate and kill it if it lingers (blocks up to ~2·timeout)."""
        proc = self._proc
        if proc is None or proc.poll() is not None:
            self._close_pipes()
            return
        try:
            self.send({"type": "shutdown", "id": "addon-shutdown"})
        except BackendError:
            pass
        try:
            if proc.stdin:
                proc.stdin.close()  # end of stdin acts as shutdown too
        except OSError:
            pass
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.terminate()
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout)
        self._close_pipes()

    def kill(self) -> None:
        """Kill the process at once (a hung or timed-out backend)."""
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.kill()
            try:
                proc.wait(5.0)
            except subprocess.TimeoutExpired:
                pass
        self._close_pipes()

    def _close_pipes(self) -> None:
        proc = self._proc
        if proc is None:
            return
        for pipe in (proc.stdin,):
            try:
                if pipe:
                    pipe.close()
            except OSError:
                pass

    # -- I/O ----------------------------------------------------------------
    def send(self, message: dict[str, Any]) -> None:
        """Write one JSON line; :class:`BackendError` when the backend is gone."""
        proc = self._proc
        if proc is None or proc.stdin is None:
            raise BackendError("the backend is not running")
        data = (json.dumps(message) + "\n").encode("utf-8")
        with self._write_lock:
            try:
                proc.stdin.write(data)
                proc.stdin.flush()
            except (BrokenPipeError, ValueError, OSError):
                raise BackendError(self.death_reason()) from None

    def poll(self) -> list[Any]:
        """Every event the reader thread has parsed so far (never waits): :mod:`.protocol` events."""
        out = []
        while True:
            try:
                item = self._events.get_nowait()
            except queue.Empty:
                return out
            if item is _EOF:
                self._closed = True
                continue
            if isinstance(item, Ready) and item.type == "ready" and self.ready is None:
                self.ready = item
            out.append(item)

    def stderr_tail(self, lines: int = 1) -> str:
        """The last non-empty stderr lines, joined by ' | '."""
        kept = [s for s in list(self._stderr) if s.strip()]
        return " | ".join(kept[-lines:])

    def death_reason(self) -> str:
        """Why the backend is not answering, in one line (exit code and the last thing it wrote to stderr)."""
        proc = self._proc
        code = None
        if proc is not None:
            try:
                code = proc.wait(0.5)
            except subprocess.TimeoutExpired:
                code = None
        tail = self.stderr_tail(1)
        if code is None:
            what = "the backend closed its output"
        elif code < 0:
            what = f"the backend was killed by signal {-code}"
        else:
            what = f"the backend exited with code {code}"
        return f"{what}: {tail}" if tail else what

    def _read_stdout(self) -> None:
        assert self._proc is not None and self._proc.stdout is not None
        stream = self._proc.stdout
        try:
            for raw in iter(stream.readline, b""):
                line = raw.decode("utf-8", errors="replace").strip()
                if not line:
                    continue
                try:
                    event = read_event(json.loads(line))
                except ValueError:
                    self._stderr.append(f"(stdout, not JSON) {line[:200]}")
                    continue
                except TypeError:  # a known type with a field it does not have
                    event = None
                if event is not None:
                    self._events.put(event)
                else:
                    self._stderr.append(f"(stdout, not an event) {line[:200]}")
        except (OSError, ValueError):
            pass
        finally:
            self._events.put(_EOF)

    def _read_stderr(self) -> None:
        assert self._proc is not None and self._proc.stderr is not None
        try:
            for raw in iter(self._proc.stderr.readline, b""):
                self._stderr.append(raw.decode("utf-8", errors="replace").rstrip())
        except (OSError, ValueError):
            pass


_ids = itertools.count(1)


@dataclass
class Request:
    """One request to the shared backend, followed to its end by :meth:`tick`.

    ``get_client`` returns the running :class:`BackendClient` (starting it
    when needed; it may raise :class:`BackendError`), ``discard_client``
    throws the current one away (after a crash or a time-out) so that the next
    request starts a fresh backend.  ``kind`` is ``"reconstruct"`` or
    ``"version"``; ``payload`` holds the request's fields besides ``type``
    and ``id``.

    After each :meth:`tick`, ``state`` is one of ``starting``, ``running``,
    ``cancelling`` (still going) or ``done``, ``failed``, ``cancelled``
    (finished); ``stage``/``fraction`` describe the progress, ``result`` is
    the answering event, ``ready`` the backend's ``ready`` event (with the mesh options' schema) once seen, and
    ``error`` the one-line reason of a failure.
    """

    get_client: Callable[[], BackendClient]
    discard_client: Callable[[], None]
    kind: str
    payload: dict[str, Any] = field(default_factory=dict)
    startup_timeout: float = 120.0  # from spawning to the ready event
    timeout: float = 600.0  # from sending the request to its answer
    cancel_grace: float = 20.0  # from sending cancel to the server's answer
    id: str = ""
    state: str = "new"
    stage: str = "starting"
    fraction: float = 0.0
    result: Any = None  # the answering event (protocol.Result or protocol.Version)
    ready: Ready | None = None  # the backend's ready event (its option schema, docs/protocol.md), once seen
    error: str = ""
    started_at: float = 0.0
    finished_at: float = 0.0
    _sent_at: float | None = None
    _cancel_requested: bool = False
    _cancel_sent_at: float | None = None
    _client: BackendClient | None = None

    FINISHED = ("done", "failed", "cancelled")

    def __post_init__(self):
        if self.kind not in ("reconstruct", "version"):
            raise ValueError(f"unknown request kind {self.kind!r}")
        if not self.id:
            self.id = f"blender-{os.getpid()}-{next(_ids)}"

    @property
    def finished(self) -> bool:
        return self.state in self.FINISHED

    @property
    def elapsed(self) -> float:
        end = self.finished_at or time.monotonic()
        return max(0.0, end - self.started_at) if self.started_at else 0.0

    def cancel(self) -> None:
        """Ask for the request to stop; the next :meth:`tick` acts on it."""
        if not self.finished:
            self._cancel_requested = True

    # -- the per-tick step --------------------------------------------------
    def tick(self, now: float | None = None) -> str:
        """Advance by whatever the backend has said since the last tick; returns ``state``."""
        if self.finished:
            return self.state
        now = time.monotonic() if now is None else now
        if self.state == "new":
            self.started_at = now
            self.state = "starting"
        try:
            self._step(now)
        except BackendError as exc:
            self._fail(now, str(exc), discard=True)
        return self.state

    def _step(self, now: float) -> None:
        if self._client is None:
            if self._cancel_requested:
                return self._finish(now, "cancelled")
            self._client = self.get_client()  # may raise BackendError
        client = self._client
        for event in client.poll():
            self._on_event(now, event)
            if self.finished:
                break
        self.ready = client.ready if client.ready is not None else self.ready
        if self.finished:
            return
        if self._sent_at is None:
            if client.ready is not None:
                if self._cancel_requested:
                    return self._finish(now, "cancelled")
                client.send(message(REQUESTS[self.kind](id=self.id, **self.payload)))
                self._sent_at = now
                self.state = "running"
                self.stage = "queued"
            elif self._cancel_requested:
                return self._finish(now, "cancelled")  # nothing was asked yet; the backend keeps loading for next time
            elif not client.alive():
                raise BackendError(client.death_reason())
            elif now - client.started_at > self.startup_timeout:
                self._fail(now, f"the backend did not become ready within {self.startup_timeout:.0f} s", discard=True, kill=True)
            return
        if self._cancel_requested and self._cancel_sent_at is None:
            client.send(message(Cancel(self.id)))
            self._cancel_sent_at = now
            self.state = "cancelling"
            self.stage = "cancelling"
        if not client.alive():
            if self._cancel_sent_at is not None:
                self.discard_client()
                return self._finish(now, "cancelled")
            raise BackendError(client.death_reason())
        if self._cancel_sent_at is not None:
            if now - self._cancel_sent_at > self.cancel_grace:
                # The server did not stop in time: kill it; the next request starts a fresh one.
                client.kill()
                self.discard_client()
                self._finish(now, "cancelled")
        elif now - self._sent_at > self.timeout:
            what = "reconstruction" if self.kind == "reconstruct" else "backend"
            self._fail(now, f"the {what} timed out after {self.timeout:g} s (stage: {STAGE_LABELS.get(self.stage, self.stage)})",
                       discard=True, kill=True)

    def _on_event(self, now: float, event: Any) -> None:
        """Follow one :mod:`.protocol` event (a parsed line's dict is read as one first)."""
        if isinstance(event, dict):
            event = read_event(event)
        if event is None:
            return
        if isinstance(event, Error) and event.id is None:
            # Before ready: the server cannot start (bad weights, unusable device) and exits.
            # After: a line of ours it could not read.  Either way this request cannot succeed.
            where = "backend could not start" if self._sent_at is None else "backend error"
            return self._fail(now, f"{where}: {event.message or 'unknown error'} ({event.code or 'error'})",
                              discard=self._sent_at is None)
        if getattr(event, "id", None) != self.id:
            return  # ready, or the answer to an earlier, abandoned request
        if isinstance(event, Progress):
            if self._cancel_sent_at is None:
                self.stage = str(event.stage or self.stage)
                try:
                    self.fraction = min(1.0, max(self.fraction, float(event.fraction)))
                except (TypeError, ValueError):
                    pass
        elif isinstance(event, Error):
            if self._cancel_sent_at is not None:
                return self._finish(now, "cancelled")
            self._fail(now, f"{event.message or 'unknown error'} ({event.code or 'error'})")
        elif event.type == "cancelled":
            self._finish(now, "cancelled")
        elif self._cancel_sent_at is not None and event.type in ("result", "version"):
            self.result = event  # finished before it could stop; the caller cleans up the file
            self._finish(now, "cancelled")
        elif event.type == self._answer_type():
            self.result = event
            self.fraction = 1.0
            self._finish(now, "done")

    def _answer_type(self) -> str:
        return "result" if self.kind == "reconstruct" else "version"

    def _finish(self, now: float, state: str) -> None:
        self.state = state
        self.finished_at = now

    def _fail(self, now: float, reason: str, *, discard: bool = False, kill: bool = False) -> None:
        if kill and self._client is not None:
            self._client.kill()
        if discard:
            self.discard_client()
        self.error = reason
        self._finish(now, "failed")


class BackendManager:
    """The one shared backend process: started on first use, reused, restarted when its command changes or it dies."""

    def __init__(self, client_factory: Callable[[list[str]], BackendClient] = BackendClient):
        self._factory = client_factory
        self.client: BackendClient | None = None

    def get(self, argv: list[str]) -> BackendClient:
        client = self.client
        if client is not None and (client.argv != list(argv) or not client.alive()):
            self.discard()
            client = None
        if client is None:
            client = self._factory(list(argv))
            client.start()  # BackendError when it cannot start
            self.client = client
        return client

    def discard(self) -> None:
        """Stop and forget the current backend (it is started afresh on next use)."""
        client, self.client = self.client, None
        if client is not None:
            client.stop(timeout=2.0)

    def request(self, argv: list[str], kind: str, payload: dict[str, Any] | None = None, **limits: float) -> Request:
        """A :class:`Request` bound to this manager's backend started with ``argv``."""
        return Request(get_client=lambda: self.get(argv), discard_client=self.discard, kind=kind, payload=dict(payload or {}), **limits)


def private_temp_root(name: str) -> str:
    """``<tmp>/name`` when it is (or is now made) a real folder of this user's that only they can enter; else a
    fresh folder from :func:`tempfile.mkdtemp`.

    The system temp folder is shared: another user may have made a folder of
    that predictable name, or a link of that name to somewhere else, first.
    """
    path = os.path.join(tempfile.gettempdir(), name)
    try:
        os.mkdir(path, 0o700)
    except FileExistsError:
        pass
    except OSError:
        return tempfile.mkdtemp(prefix=name + "-")
    try:
        st = os.lstat(path)
        trusted = stat.S_ISDIR(st.st_mode) and (not hasattr(os, "getuid") or st.st_uid == os.getuid())
        if trusted and hasattr(os, "getuid") and stat.S_IMODE(st.st_mode) & 0o077:
            os.chmod(path, 0o700)
    except OSError:
        trusted = False
    return path if trusted else tempfile.mkdtemp(prefix=name + "-")

