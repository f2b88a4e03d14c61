"""``genre bench``, registered with the backend's CLI like the training commands.

Named in pyproject.toml under the ``genre.commands`` entry-point group: the benchmarks live outside the package
whose operations they time (:mod:`benchmarks.bench`), and the backend never imports them.  Importing this module
is cheap: the loader imports the command when it runs.
"""

from __future__ import annotations

from genre_backend.cli import Command

__all__ = ["COMMANDS"]


def _bench():
    from . import bench

    return bench.main


COMMANDS = [Command("bench", "print speed figures (geometry, inference)", _bench)]
