"""``genre serve``'s lines when a signal stops it before its ``ready`` line (docs/protocol.md, *Signals*).

Imported by :mod:`genre_backend.cli` as the first thing ``genre serve`` does, before any other import, so it
imports nothing: from then on SIGINT and SIGTERM end the server with these lines
(:func:`genre_backend.process.install_stop_handlers`).
"""

from __future__ import annotations

__all__ = ["stopped_lines"]


def stopped_lines(reason: str) -> tuple[str, str]:
    """(the stderr line, the one stdout line) of a server stopped by the signal ``reason`` (``"SIGINT"``,
    ``"SIGTERM"``) before ``ready``: ``bye`` with the signal's name, exactly as ``json.dumps`` writes it."""
    return f"genre serve: INFO {reason} while starting: stopping", f'{{"type": "bye", "id": null, "reason": "{reason}"}}'
