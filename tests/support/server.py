"""``genre serve`` as a subprocess for the tests: its stdout read into events on a thread."""

from __future__ import annotations

import json
import os
import queue
import subprocess
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


class NotAnEvent(str):
    """A stdout line that is not one JSON object (the reader hands it on, so the test fails at once)."""


class ServerProcess:
    """A ``genre serve`` subprocess (in ``cwd``) with a reader thread collecting its stdout events."""

    def __init__(self, *args: str, cwd: Path = REPO):
        env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}  # tiny model: one thread is fastest
        self.proc = subprocess.Popen([sys.executable, "-m", "genre_backend.cli", "serve", *args], cwd=cwd, env=env, text=True,
                                     encoding="utf-8", errors="replace",  # a non-UTF-8 byte shows as U+FFFD (the line is then not ASCII)
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, bufsize=1)
        self.events: queue.Queue[dict | NotAnEvent | None] = queue.Queue()
        self.raw: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        for line in self.proc.stdout:
            self.raw.append(line)
            try:
                event = json.loads(line)  # every stdout line must be one JSON object
            except ValueError:
                event = None
            self.events.put(event if isinstance(event, dict) else NotAnEvent(line))
        self.events.put(None)

    def send(self, obj) -> None:
        self.proc.stdin.write((obj if isinstance(obj, str) else json.dumps(obj)) + "\n")
        self.proc.stdin.flush()

    def send_bytes(self, line: bytes) -> None:
        """One raw line (any bytes but a newline): what a client with its own encoder may send."""
        self.proc.stdin.flush()
        self.proc.stdin.buffer.write(line + b"\n")
        self.proc.stdin.buffer.flush()

    @staticmethod
    def _checked(ev):
        assert not isinstance(ev, NotAnEvent), f"server wrote a stdout line that is not one JSON object: {ev[:300]!r}"
        return ev

    def next(self, timeout: float = 120.0) -> dict | None:
        return self._checked(self.events.get(timeout=timeout))

    def until(self, pred, timeout: float = 120.0) -> list[dict]:
        """Events up to and including the first for which ``pred`` holds."""
        seen = []
        deadline = time.time() + timeout
        while True:
            ev = self._checked(self.events.get(timeout=max(0.1, deadline - time.time())))
            assert ev is not None, f"server exited; events so far {seen}; stderr: {self.proc.stderr.read()}"
            seen.append(ev)
            if pred(ev):
                return seen

    def close(self) -> int:
        if self.proc.poll() is None:
            try:
                self.proc.stdin.close()
            except OSError:
                pass
        try:
            return self.proc.wait(timeout=60)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
