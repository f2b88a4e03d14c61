"""Stopping a training run cleanly on SIGINT / SIGTERM (:class:`StopSignals`).

A trainer runs its steps inside ``with StopSignals() as stop:`` and reads :meth:`StopSignals.caught` (one
process) or :meth:`StopSignals.agreed` (every process of a ``torchrun`` group, so that all of them leave after
the same step and none is left waiting in the next step's all-reduce) between steps; when it is set, the trainer
writes its checkpoint and returns.  A second signal while the first is being handled stops the process at once
(the handler that was there before, e.g. Python's ``KeyboardInterrupt`` for Ctrl-C).  Outside the main thread,
where Python cannot install handlers, the context does nothing and a signal acts as it would without it.
"""

from __future__ import annotations

import signal
import threading

import torch

__all__ = ["StopSignals", "SIGNALS"]

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopSignals:
    """SIGINT and SIGTERM turned into a flag for the duration of a ``with`` block; the old handlers come back after it."""

    def __init__(self):
        self.signum: int | None = None
        self._old: dict[int, object] = {}

    def install(self) -> StopSignals:
        """Catch SIGINT and SIGTERM from now on (in the main thread; elsewhere nothing changes)."""
        if threading.current_thread() is threading.main_thread():
            self._old = {s: signal.signal(s, self._catch) for s in SIGNALS}
        return self

    def restore(self) -> None:
        """Put back the handlers :meth:`install` replaced."""
        for s, handler in self._old.items():
            signal.signal(s, handler)
        self._old = {}

    def __enter__(self) -> StopSignals:
        return self.install()

    def __exit__(self, *exc) -> None:
        self.restore()

    def _catch(self, signum: int, _frame) -> None:
        if self.signum is None:
            self.signum = signum
            return
        self.restore()  # a second signal: the old handler takes it now
        signal.raise_signal(signum)

    def caught(self) -> int:
        """The signal caught so far in this process (0: none)."""
        return self.signum or 0

    def agreed(self, world: int, device: torch.device | str = "cpu") -> int:
        """The largest signal number any of ``world`` processes caught (0: none); a collective when ``world`` > 1
        (on ``device``, the one the process group communicates on), so every rank must call it at the same point of
        every step."""
        if world <= 1:
            return self.caught()
        import torch.distributed as dist

        flag = torch.tensor([self.caught()], dtype=torch.int64, device=device)
        dist.all_reduce(flag, op=dist.ReduceOp.MAX)
        return int(flag.item())
