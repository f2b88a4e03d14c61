"""The ``genre`` console entry point.

Each subcommand lives in its own module with a ``main(argv, prog) -> int``
function; this file only dispatches, importing the module on demand so that
``genre --version`` and ``genre --help`` stay instant (torch and bpy load only
when a command needs them).
"""

from __future__ import annotations

import importlib
import sys

from . import __version__

# name -> (module, one-line summary)
COMMANDS: dict[str, tuple[str | None, str]] = {
    "data": ("training.data.cli", "fetch, build, render and inspect the training corpus"),
    "train": ("training.learn.train", "train the networks stage by stage"),
    "eval": ("training.eval.runner", "evaluate a trained model over a split"),
    "reconstruct": ("genre_backend.inference.reconstruct_cli", "turn photos into meshes"),
    "serve": ("genre_backend.inference.server", "run the JSON-over-stdio reconstruction server"),
    "bench": ("genre_backend.inference.bench", "print speed figures (geometry, inference)"),
}


def _usage() -> str:
    lines = [
        "usage: genre [--version] [--help] COMMAND [ARGS...]",
        "",
        "GenRe: single-image 3D reconstruction of seen and unseen object classes.",
        "",
        "commands:",
    ]
    for name, (module, summary) in COMMANDS.items():
        lines.append(f"  {name:<12} {summary}{'' if module else '  (not available in this version)'}")
    lines += ["", "Run 'genre COMMAND --help' for a command's options."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0 if argv else 2
    if argv[0] in ("-V", "--version"):
        print(f"genre {__version__}")
        return 0
    name = argv[0]
    if name not in COMMANDS:
        print(f"genre: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    module_name = COMMANDS[name][0]
    if module_name is None:
        print(f"genre {name}: not available in genre {__version__} yet", file=sys.stderr)
        return 2
    module = importlib.import_module(module_name)
    return int(module.main(argv[1:], prog=f"genre {name}") or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
