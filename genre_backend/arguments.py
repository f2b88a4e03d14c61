"""The command-line arguments every ``genre`` command spells alike, defined once.

``--weights``, ``--out``, ``--device``, ``--threads``, ``--seed``, ``--jobs`` and ``--storage``: each helper adds its flag to an
``argparse`` parser (or group) with the project's type, metavar and help; a command passes what is its own (a
default, ``required``, a help text that says more) as ``add_argument``'s keywords, which win.  Imports nothing from
the package but the weights file's storage names.
"""

from __future__ import annotations

from typing import Any

__all__ = ["WEIGHTS_HELP", "DEVICES", "add_weights", "add_out", "add_device", "add_threads", "add_seed", "add_jobs", "add_storage"]

WEIGHTS_HELP = ("weights: a shipped name, 'default' (the product model, the default) or 'protocol' (the research model, "
                "seen classes only), or a .safetensors file")
DEVICES = ("cpu", "cuda")  # the devices the front ends run on


def add_weights(parser, **kwargs: Any):
    """``--weights W``: a shipped weights name or a file (no default: the command's choice)."""
    return parser.add_argument("--weights", **{"metavar": "W", "help": WEIGHTS_HELP, **kwargs})


def add_out(parser, **kwargs: Any):
    """``--out``: where the command writes (a file or a folder, as its ``help`` says)."""
    return parser.add_argument("--out", **kwargs)


def add_device(parser, **kwargs: Any):
    """``--device``: the torch device (default ``cpu``)."""
    return parser.add_argument("--device", **{"default": "cpu", **kwargs})


def add_threads(parser, **kwargs: Any):
    """``--threads N``: the threads a command computes with (default: the library's choice)."""
    return parser.add_argument("--threads", **{"type": int, "default": None, "help": "torch threads (default: torch's choice)",
                                               **kwargs})


def add_seed(parser, **kwargs: Any):
    """``--seed N``: the seed of whatever the command draws at random (default 0)."""
    return parser.add_argument("--seed", **{"type": int, "default": 0, **kwargs})


def add_jobs(parser, **kwargs: Any):
    """``--jobs N``: worker processes side by side (default 1)."""
    return parser.add_argument("--jobs", **{"type": int, "default": 1, **kwargs})


def add_storage(parser) -> None:
    """``--storage float32|float16|int8`` (how a written weights file stores its weights:
    :func:`genre_backend.nets.model.save_model`), with ``--fp16`` as the short form of ``--storage float16``."""
    from .weights_file import STORAGES

    group = parser.add_mutually_exclusive_group()
    group.add_argument("--storage", choices=STORAGES, default="float32",
                       help="how to store the weights: float32, float16 (half the file) or int8 (the large weights as "
                            "int8 rows with a scale per output channel, the rest float16: about a quarter); inference "
                            "always computes in float32 (default: float32)")
    group.add_argument("--fp16", dest="storage", action="store_const", const="float16",
                       help="the same as --storage float16")
