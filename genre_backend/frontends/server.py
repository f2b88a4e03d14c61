"""``genre serve``: the long-lived JSON-lines reconstruction server (protocol: ``docs/protocol.md``).

The main thread reads stdin line by line and answers ``ping``, ``version``,
``cancel`` and ``shutdown`` at once; ``reconstruct`` requests go to a queue
that one worker thread runs in arrival order with the model loaded once.
Every event is one JSON object on one stdout line, written under a lock and
flushed; logs go to stderr only (``sys.stdout`` is pointed at stderr while
serving, so a stray print cannot corrupt the stream).

Shutdown: a ``shutdown`` request cancels the running job (at its next stage
boundary) and drops the queued ones (each gets ``cancelled``), then answers
``bye`` and exits 0.  End of stdin lets the queued jobs finish (nobody is left
to cancel them), then writes ``bye`` (id null) and exits 0.
"""

from __future__ import annotations

import argparse
import json
import logging
import queue
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from .. import __version__
from ..arguments import DEVICES, add_device, add_weights
from ..protocol import (PROTOCOL_VERSION, REQUESTS, Bye, Cancelled, Error, Pong, Progress, Ready, RequestError, Result,
                        Version, cap, message, path_field, request_id, show_json)
from ..process import Stop, install_stop_handlers, stops_quiet, take_stops, uninstall_stop_handlers
from .serve_stop import stopped_lines

__all__ = ["PROTOCOL_VERSION", "Server", "main"]

# the option keys of a request: every mesh option of the record (genre_backend/inference/options.py), the named set
# `quality`, and the intermediates folder (a path, like `mask`, not a mesh option)
_PATH_OPTIONS = ("save_intermediates",)


def _option_keys() -> tuple[str, ...]:
    from ..inference.options import BY_NAME

    return (*BY_NAME, "quality", *_PATH_OPTIONS)


_OPTION_KEYS = _option_keys()
log = logging.getLogger("genre.serve")


@dataclass
class Job:
    id: Any
    image: str
    output: str
    mask: str | None
    options: Any  # options.MeshOptions: the request's, over its quality's set (None fields: the weights')
    save_intermediates: str | None
    box: tuple[float, float, float, float] | None = None  # a person's box and strokes file for GrabCut (mask inputs)
    strokes: str | None = None
    guidance_frame: str = "upright"  # the pixels box and strokes are over: "upright" (EXIF applied) or "stored"
    cancel: threading.Event = field(default_factory=threading.Event)
    answered: bool = False  # `cancelled` already sent (a job cancelled while still queued)


def _key(req_id: Any) -> str:
    """Jobs are keyed by their id's JSON text, so 1 and "1" are different jobs."""
    return json.dumps(req_id)


def _one_line(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return cap(lines[0] if lines else exc.__class__.__name__)


_cap, _show = cap, show_json


class Server:
    """The protocol over a pair of text streams; ``reconstructor`` is a loaded :class:`Reconstructor`."""

    def __init__(self, reconstructor, out: TextIO, device: str):
        self.rec = reconstructor
        self.out = out
        self.device = device
        self.lock = threading.Lock()
        self.jobs: queue.Queue[Job | None] = queue.Queue()
        self.pending: dict[str, Job] = {}  # queued or running, by id
        self.pending_lock = threading.Lock()
        self.running: Job | None = None
        self.broken = threading.Event()  # stdout closed: nobody listens any more
        self.said_bye = False
        self.worker = threading.Thread(target=self._work, name="genre-serve-worker", daemon=True)

    # ---- output -------------------------------------------------------------------------
    def emit(self, event) -> None:
        """Write ``event`` (a :mod:`~genre_backend.protocol` event) as one line."""
        # ASCII-only JSON: a lone surrogate (a non-UTF-8 file name, or "\ud800" sent by a client)
        # goes out as its \u escape, never as text the UTF-8 stream cannot encode.
        line = json.dumps(message(event), ensure_ascii=True, allow_nan=False)
        with self.lock:
            if self.broken.is_set():
                return
            try:
                self.out.write(line + "\n")
                self.out.flush()
            except (BrokenPipeError, OSError, ValueError):
                self.broken.set()

    def error(self, req_id: Any, code: str, message: str) -> None:
        log.info("error %s %s: %s", _cap(json.dumps(req_id), 300), code, _cap(message, 300))
        self.emit(Error(req_id, code, _cap(message)))

    def info(self) -> dict:
        from ..inference.options import schema

        return {
            "protocol": PROTOCOL_VERSION,
            "version": __version__,
            "weights": str(self.rec.weights_path),
            "preset": self.rec.preset,
            "device": self.device,
            "threshold": self.rec.config.geometry.default_threshold,
            **schema(self.rec.config.geometry),  # "options" and "qualities": the mesh options' record (options.py)
        }

    # ---- requests -----------------------------------------------------------------------
    def _guidance(self, msg: dict, rid: Any, mask: str | None) -> tuple[tuple[float, float, float, float] | None, str | None]:
        """The request's ``box`` ([x0, y0, x1, y1], the photo's pixels) and ``strokes`` (a path), checked; (None, None) when absent."""
        strokes = path_field(msg, "strokes", rid, False)
        box = msg.get("box")
        if box is not None:
            from ..validation import check_box

            if not isinstance(box, list):  # (check_box also reads the command line's "x0,y0,x1,y1" text)
                raise RequestError("bad_field", f"field box: expected four numbers [x0, y0, x1, y1] in an array, got {_show(box, 60)}", rid)
            try:
                box = check_box("box", box)
            except ValueError as exc:
                raise RequestError("bad_field", f"field {_one_line(exc)}", rid) from None
        if mask is not None and (box is not None or strokes is not None):
            given = " and ".join(f"'{n}'" for n, v in (("box", box), ("strokes", strokes)) if v is not None)
            raise RequestError("bad_field", f"give either 'mask' or {given}, not both", rid)
        return box, strokes

    @staticmethod
    def _guidance_frame(msg: dict, rid: Any) -> str:
        """The request's ``guidance_frame`` (the pixels its box and strokes are over), checked; "upright" when absent."""
        from ..photo.decode import GUIDANCE_FRAMES

        frame = msg.get("guidance_frame")
        if frame is None:
            return "upright"
        if not isinstance(frame, str) or frame not in GUIDANCE_FRAMES:
            raise RequestError("bad_field", f"field 'guidance_frame': expected one of {', '.join(map(repr, GUIDANCE_FRAMES))}, "
                                            f"got {_show(frame, 60)}", rid)
        return frame

    def _parse_job(self, msg: dict) -> Job:
        rid = request_id(msg, required=True)
        image = path_field(msg, "image", rid, True)
        output = path_field(msg, "output", rid, True)
        mask = path_field(msg, "mask", rid, False)
        box, strokes = self._guidance(msg, rid, mask)
        options = msg.get("options")
        if options is None:  # (absent or null)
            options = {}
        elif not isinstance(options, dict):  # false, 0, "" and [] included
            raise RequestError("bad_field", f"field 'options' must be an object, got {_show(options, 60)}", rid)
        from ..output.mesh_export import resolve_format
        from ..inference.options import OptionError, parse_request_options

        try:
            record = parse_request_options(options, show=_show, extra=_PATH_OPTIONS)
        except OptionError as exc:
            raise RequestError("bad_field", _cap(str(exc)), rid) from None
        fmt = record.format
        if fmt is not None:
            ext = Path(output).suffix.lower().lstrip(".")
            if ext in ("obj", "ply", "glb") and ext != fmt:  # as the CLI: format and extension agree
                raise RequestError("bad_field", f"option 'format' {fmt} does not match the output's extension .{ext}", rid)
        written = resolve_format(output, fmt)
        if record.up == "z" and written != "ply":
            raise RequestError("bad_field", f"option 'up' 'z' is for ply only; {written} is always written +y up, as its importers expect", rid)
        inter = path_field(options, "save_intermediates", rid, False, "option")
        return Job(rid, image, output, mask, record, inter, box=box, strokes=strokes,
                   guidance_frame=self._guidance_frame(msg, rid))

    def handle(self, line: str) -> bool:
        """Answer one input line; returns False when the server should stop reading."""
        try:
            msg = json.loads(line)
        except (ValueError, RecursionError) as exc:  # (ValueError: also integers past Python's digit limit)
            self.error(None, "bad_json", f"not valid JSON: {_one_line(exc)}")
            return True
        if not isinstance(msg, dict):
            self.error(None, "bad_json", f"expected a JSON object, got {type(msg).__name__}")
            return True
        rid = None
        try:
            rid = request_id(msg, required=False)
            if "type" not in msg:
                raise RequestError("missing_field", "missing field 'type'", rid)
            kind = msg["type"]
            if kind == "ping":
                self.emit(Pong(rid))
            elif kind == "version":
                self.emit(Version(id=rid, **self.info()))
            elif kind == "reconstruct":
                job = self._parse_job(msg)
                with self.pending_lock:
                    if _key(job.id) in self.pending:
                        raise RequestError("bad_field", f"a job with id {_show(job.id)} is already queued or running", job.id)
                    self.pending[_key(job.id)] = job
                log.info("queued job %s: %s", _cap(_key(job.id), 300), _cap(job.image, 300))
                self.jobs.put(job)
            elif kind == "cancel":
                target = request_id(msg, required=True)
                self.cancel(target)
            elif kind == "shutdown":
                self.shutdown(rid, cancel=True)
                return False
            else:
                raise RequestError("unknown_type", f"unknown request type {_show(kind)}; known: {', '.join(REQUESTS)}", rid)
        except RequestError as exc:
            self.error(exc.req_id if exc.req_id is not None else rid, exc.code, str(exc))
        except Exception as exc:  # a bug, not the client's doing: said so, and the server keeps reading
            log.exception("request %s: internal error", _cap(json.dumps(rid), 300))
            self.error(rid, "internal", f"internal error: {exc.__class__.__name__}: {_one_line(exc)}")
        return True

    def cancel(self, rid: Any) -> None:
        with self.pending_lock:
            job = self.pending.get(_key(rid))
            if job is None:
                raise RequestError("unknown_job", f"no queued or running job with id {_show(rid)}", rid)
            self._cancel_locked(job)
        log.info("cancel requested for job %s", _cap(json.dumps(rid), 300))

    def _cancel_locked(self, job: Job) -> None:
        """Flag ``job``; a queued job is answered now, the running one at its next stage boundary."""
        job.cancel.set()
        if job is not self.running and not job.answered:
            job.answered = True
            self.pending.pop(_key(job.id), None)
            self.emit(Cancelled(job.id))

    def shutdown(self, rid: Any, cancel: bool, reason: str | None = None) -> None:
        """Stop the worker (cancelling everything when ``cancel``), then say ``bye`` (with ``reason`` after a signal)."""
        if cancel:
            with self.pending_lock:
                for job in list(self.pending.values()):
                    self._cancel_locked(job)
        self.jobs.put(None)
        if self.worker.is_alive():
            self.worker.join()  # (the running job stops at its next stage boundary; a write in progress is finished)
        if not self.said_bye:
            self.said_bye = True
            stops_quiet()  # (a signal from here on is logged, never a second bye)
            self.emit(Bye(rid, reason))

    # ---- the worker ---------------------------------------------------------------------
    def _work(self) -> None:
        while True:
            job = self.jobs.get()
            if job is None:
                return
            with self.pending_lock:
                if job.answered:
                    continue
                self.running = job
            try:
                self._run(job)
            finally:
                with self.pending_lock:
                    self.running = None
                    self.pending.pop(_key(job.id), None)

    def _end(self, job: Job, event) -> None:
        """Free the job's id, then send its last event (so the client may reuse the id at once)."""
        with self.pending_lock:
            self.pending.pop(_key(job.id), None)
            self.running = None
        if isinstance(event, Error):
            log.info("error %s %s: %s", _cap(_key(job.id), 300), event.code, _cap(event.message, 300))
        self.emit(event)

    def _run(self, job: Job) -> None:
        from ..config import SETTINGS
        from ..inference.options import OPTIONS
        from ..inference.reconstruct import STAGE_START, Hooks, MaskGuidance, error_code
        from ..inference.reconstruct import Cancelled as JobCancelled  # (the exception; protocol.Cancelled is the event)
        from ..output.mesh_export import check_outputs

        if job.cancel.is_set():
            self._end(job, Cancelled(job.id))
            return
        log.info("job %s: %s -> %s", _cap(_key(job.id), 300), _cap(job.image, 300), _cap(job.output, 300))
        try:
            # every output (mesh, .mtl, texture, intermediates folder) before any network runs
            opts = job.options
            check_outputs(job.output, opts.format, bool(opts.texture), (job.image, job.mask, job.strokes), job.save_intermediates)
            result = self.rec.run(
                job.image,
                MaskGuidance(mask=job.mask, box=job.box, strokes=job.strokes, frame=job.guidance_frame),
                opts,
                Hooks(progress=lambda stage, fraction: self.emit(Progress(job.id, stage, fraction)),
                      should_cancel=job.cancel.is_set),
            )
            if job.cancel.is_set():
                raise JobCancelled("cancelled before stage write")
            self.emit(Progress(job.id, "write", STAGE_START["write"]))
            path, fmt = result.save_mesh(job.output, opts.format, texture=bool(opts.texture), up=opts.up)
            if job.save_intermediates:
                result.save_intermediates(job.save_intermediates)
        except JobCancelled:
            log.info("job %s cancelled", _cap(_key(job.id), 300))
            self._end(job, Cancelled(job.id))
            return
        except RequestError as exc:
            self._end(job, Error(job.id, exc.code, _cap(str(exc))))
            return
        except Exception as exc:  # every failure is reported; the server keeps serving
            code = error_code(exc)
            if code == "internal":
                log.exception("job %s: internal error", _cap(_key(job.id), 300))
                message = f"internal error: {exc.__class__.__name__}: {_one_line(exc)}"
            else:
                message = _one_line(exc)
            self._end(job, Error(job.id, code, message))
            return
        self._end(job, Result(
            id=job.id, mesh=str(path), format=fmt, up=result.up, vertices=int(len(result.vertices)), faces=int(len(result.faces)),
            parts=result.clean.parts, parts_dropped=result.clean.parts_before - result.clean.parts,
            watertight=result.clean.watertight, files=[str(p) for p in result.files], mask_source=result.mask_source,
            mask_warning=result.mask_warning, primitive=result.primitive,
            timings={k: round(v, 4) for k, v in result.timings.items()}, camera=result.camera(),
            options={spec.name: getattr(result.options, spec.name) for spec in OPTIONS},  # the whole record as used
            settings={spec.name: getattr(result.options, spec.name) for spec in SETTINGS}))  # the weights' settings as used
        log.info("job %s done: %d faces in %.2f s", _cap(_key(job.id), 300), len(result.faces), sum(result.timings.values()))

    # ---- the loop -----------------------------------------------------------------------
    def serve(self, stdin: TextIO) -> int:
        """Answer ``stdin`` until ``shutdown`` or its end (exit status 0), or until SIGINT/SIGTERM (:class:`Stop`).

        A signal cancels the queued jobs and the running one (at its next
        stage boundary; a mesh being written is finished, so no temporary file
        is left), says ``bye`` with ``reason`` ``SIGINT``/``SIGTERM``, and
        returns 128 + the signal's number (130, 143).
        """
        # The worker starts before `ready`, while a signal still ends the process at once: a Stop raised inside
        # Thread.start (waiting for the new thread to run) would leave a thread half started, which a second start
        # or a join then breaks (the process died of SIGABRT at exit, 1 in ~30 SIGTERMs sent right after `ready`).
        self.worker.start()
        try:
            take_stops()  # (from here a signal raises Stop: the jobs to cancel, a write to finish, then `bye`)
            self.emit(Ready(**self.info()))
            if self.broken.is_set():  # a stdout whose reader has gone (a closed pipe): nobody to answer
                stops_quiet()
                log.error("stdout is closed: nobody to answer; stopping")
                self.jobs.put(None)
                self.worker.join()
                return 1
            for raw in stdin if stdin is not None else ():  # (None: started with stdin closed, an empty input)
                line = raw.strip()
                if not line:
                    continue
                if not self.handle(line):
                    return 0
                if self.broken.is_set():
                    break
            log.info("end of input: finishing queued jobs")
            self.shutdown(None, cancel=self.broken.is_set())
            return 0
        except Stop as stop:
            log.info("%s: cancelling the jobs; a write in progress is finished first", stop.reason)
            self.shutdown(None, cancel=True, reason=stop.reason)
            return stop.status


def main(argv: list[str] | None = None, prog: str = "genre serve") -> int:
    """``genre serve``: the exit status (0 after ``shutdown`` or the end of input; 130 or 143 after SIGINT or
    SIGTERM; 1 when the weights cannot be loaded or stdout is closed).

    A signal before ``ready`` (while the arguments are read, the modules imported or the weights loaded) writes
    ``bye`` with its name as the only line; after ``ready``, :meth:`Server.serve` stops as ``shutdown`` does."""
    # (done already when started by `genre serve`, before this module was imported): until `ready`, a signal
    # writes `bye` and ends the process at once, wherever it is (an import, the weights' load); from `ready` on,
    # it raises Stop, and the server stops as `shutdown` does (Server.serve)
    installed = install_stop_handlers(at_once=stopped_lines)
    out = sys.stdout
    try:
        return _main(argv, prog, out)
    finally:
        sys.stdout = out
        if installed:  # (called in a process that goes on, a test's: its own handlers back)
            uninstall_stop_handlers()


def _main(argv: list[str] | None, prog: str, out: TextIO | None) -> int:
    parser = argparse.ArgumentParser(prog=prog, description="JSON-lines reconstruction server on stdin/stdout (protocol: docs/protocol.md).")
    add_weights(parser)
    add_device(parser, choices=list(DEVICES))
    parser.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    args = parser.parse_args(argv)
    logging.basicConfig(stream=sys.stderr, level=args.log_level, format="genre serve: %(levelname)s %(message)s")
    if out is None:  # started with stdout closed: one line on stderr (when that is open), no traceback
        stops_quiet()
        log.error("stdout is closed: nobody to answer; stopping")
        return 1
    sys.stdout = sys.stderr  # nothing but protocol lines reaches the real stdout
    stdin = sys.stdin
    try:
        out.reconfigure(encoding="utf-8", newline="\n")
        if stdin is not None:
            stdin.reconfigure(encoding="utf-8", errors="replace")
    except (AttributeError, ValueError):
        pass

    def fatal(code: str, text: str) -> int:
        stops_quiet()
        log.error(text)
        try:
            out.write(json.dumps(message(Error(None, code, text))) + "\n")
            out.flush()
        except (OSError, ValueError):
            pass
        return 1

    return _load_and_serve(args, out, stdin, fatal)


def _load_and_serve(args, out: TextIO, stdin: TextIO, fatal) -> int:
    from ..weights_file import DEFAULT_WEIGHTS_NAME, WEIGHTS_NAMES, WeightsError, resolve_weights

    try:
        weights = resolve_weights(args.weights)
    except WeightsError as exc:
        return fatal("bad_weights", f"--weights: {exc}")
    name = args.weights or DEFAULT_WEIGHTS_NAME
    if name in WEIGHTS_NAMES and not weights.is_file():
        return fatal("bad_weights", f"no {name} weights at {weights}: the trained weights are not installed yet; train them with 'genre train' and pass --weights")
    from ..inference.reconstruct import Reconstructor

    try:
        rec = Reconstructor(weights, args.device)
    except WeightsError as exc:
        return fatal("bad_weights", _one_line(exc))
    except ValueError as exc:
        return fatal("bad_field", _one_line(exc))
    except Exception as exc:  # noqa: BLE001  (load_model turns a bad file into WeightsError; anything else is one line too)
        return fatal("internal", f"internal error while loading {weights}: {exc.__class__.__name__}: {_one_line(exc)}")
    log.info("loaded %s (preset %s) on %s", weights, rec.preset, rec.device)
    return Server(rec, out, str(rec.device)).serve(stdin)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
