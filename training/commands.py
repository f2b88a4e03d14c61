"""The training side's ``genre`` subcommands, registered with the backend's CLI.

Named in pyproject.toml under the ``genre.commands`` entry-point group, so
``genre data|train|eval|chain`` exist while the backend never imports ``training``.
Importing this module is cheap: each loader imports its command on demand.
"""

from __future__ import annotations

from genre_backend.cli import Command

__all__ = ["COMMANDS"]


def _render_main():
    from .render import cli

    return cli.main


def _data():
    from .data import cli

    def main(argv, prog="genre data"):
        return cli.main(argv, prog, delegated={"render": _render_main})

    return main


def _train():
    from .learn import train

    return train.main


def _chain():
    from . import chain

    return chain.main


def _eval():
    from .eval import cli

    return cli.main


COMMANDS = [
    Command("data", "fetch, build, render and inspect the training corpus", _data),
    Command("train", "train the networks stage by stage", _train),
    Command("eval", "evaluate a trained model over a split", _eval),
    Command("chain", "run a named training chain: data, stages, scores (training/chain.py)", _chain),
]
