"""The ``genre`` console entry point.

Subcommands are :class:`Command` records: a name, a one-line summary and a
loader that imports the command's module only when it runs, so that
``genre --version`` and ``genre --help`` stay instant (torch and bpy load only
when a command needs them).  The backend registers its own commands here
(``reconstruct``, ``serve``); other packages add theirs through the
``genre.commands`` entry-point group (the training side registers ``data``,
``train``, ``eval`` and ``chain`` in ``training/commands.py``, the benchmarks
``bench`` in ``benchmarks/commands.py``; both named in pyproject.toml).
The backend never imports the training side or the benchmarks.
"""

from __future__ import annotations

import sys

if sys.argv[1:2] == ["serve"]:  # genre serve: SIGINT and SIGTERM taken over first, before even this module's imports
    from .frontends.serve_stop import stopped_lines
    from .process import install_stop_handlers

    install_stop_handlers(at_once=stopped_lines)

from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from typing import NoReturn  # noqa: E402

from . import __version__  # noqa: E402
from .process import exit_process, open_missing_streams, say  # noqa: E402

__all__ = ["Command", "ENTRY_POINT_GROUP", "backend_commands", "commands", "main", "run"]

ENTRY_POINT_GROUP = "genre.commands"
MainFn = Callable[..., int]


@dataclass(frozen=True)
class Command:
    """One ``genre`` subcommand: ``load()`` imports its module and returns its ``main(argv, prog) -> int``.

    ``quick_exit``: a command whose process, once it has returned, ends without the interpreter's tear-down of
    every module (:func:`run`).
    (``genre serve`` takes SIGINT and SIGTERM over in this module's first lines, before its other imports.)"""

    name: str
    summary: str
    load: Callable[[], MainFn]
    quick_exit: bool = False


def _reconstruct() -> MainFn:
    from .frontends import reconstruct_cli

    return reconstruct_cli.main


def _serve() -> MainFn:
    from .frontends import server

    return server.main


def backend_commands() -> list[Command]:
    return [
        Command("reconstruct", "turn photos into meshes", _reconstruct, quick_exit=True),
        Command("serve", "run the JSON-over-stdio reconstruction server", _serve, quick_exit=True),
    ]


def _plugin_commands() -> list[Command]:
    """Commands registered by installed packages under the ``genre.commands`` entry-point group."""
    from importlib.metadata import entry_points

    found: list[Command] = []
    for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        try:
            registered = ep.load()
        except ImportError:  # a package that is listed but no longer importable
            continue
        found.extend(c for c in registered if isinstance(c, Command))
    return found


def commands() -> dict[str, Command]:
    """Every available subcommand by name: the registered ones (bench, data, train, eval, chain), then the backend's.  A
    registered command never replaces one of the backend's (which :func:`main` runs without looking up the
    registered ones)."""
    backend = backend_commands()
    reserved = {cmd.name for cmd in backend}
    out: dict[str, Command] = {}
    for cmd in _plugin_commands():
        if cmd.name not in reserved:
            out.setdefault(cmd.name, cmd)
    for cmd in backend:
        out[cmd.name] = cmd
    return out


def _usage(available: dict[str, Command]) -> str:
    lines = [
        "usage: genre [--version] [--help] COMMAND [ARGS...]",
        "",
        "GenRe: single-image 3D reconstruction of seen and unseen object classes.",
        "",
        "commands:",
    ]
    for name, cmd in available.items():
        lines.append(f"  {name:<12} {cmd.summary}")
    lines += ["", "Run 'genre COMMAND --help' for a command's options."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    name = argv[0] if argv else None
    if argv[:2] == ["bench", "train"]:  # the training side's throughput: 'genre train bench' (training/learn/bench.py)
        name, argv = "train", ["train", "bench", *argv[2:]]
    command = {cmd.name: cmd for cmd in backend_commands()}.get(name)
    try:
        return _dispatch(argv, name, command)
    except KeyboardInterrupt:  # Ctrl-C: one line, no traceback, the shell's 128 + SIGINT (each write is atomic: no half file)
        say(f"genre {name}: interrupted")
        return 130


def _dispatch(argv: list[str], name: str | None, command: Command | None) -> int:
    """Run the command ``argv`` names (``command``: the backend's, when it is one), or print the usage."""
    if argv[:1] in (["-V"], ["--version"]):
        print(f"genre {__version__}")
        return 0
    if command is None:  # (the backend's own commands start without the entry-point look-up and the training package)
        available = commands()
        if not argv or name in ("-h", "--help", "help"):
            print(_usage(available))
            return 0 if argv else 2
        if name not in available:
            hint = ""
            if name in ("data", "train", "eval", "chain"):
                hint = " (the training commands come with the 'training' package: install the project with 'pip install -e .')"
            print(f"genre: unknown command {name!r}{hint}\n\n{_usage(available)}", file=sys.stderr)
            return 2
        command = available[name]
    return int(command.load()(argv[1:], prog=f"genre {name}") or 0)


def run() -> NoReturn:
    """The ``genre`` console script and ``python -m genre_backend.cli``: :func:`main`, then the process's end, at
    once after a ``quick_exit`` command (:func:`genre_backend.process.exit_process`).  A standard stream that was
    closed when the process started gets the null device first (:func:`genre_backend.process.open_missing_streams`)."""
    open_missing_streams()
    code = main()
    name = sys.argv[1] if len(sys.argv) > 1 else None
    exit_process(code, quick=any(c.name == name and c.quick_exit for c in backend_commands()))


if __name__ == "__main__":  # pragma: no cover
    # `python -m genre_backend.cli` (genre chain runs its steps so): run the imported module's run(), whose Command
    # class is the one the registered commands were made with (this file's __main__ copy would not match them)
    from genre_backend.cli import run as _run

    _run()
