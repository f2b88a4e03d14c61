"""``genre train STAGE``: staged and joint training of GenRe, resumable and data-parallel.

Stages (``method.md``):

``depth``    the depth net alone: MSE on planar depth inside the silhouette (×
             ``depth_output_scale``) + BCE on the silhouette.  Adam lr 1e-3.
``inpaint``  the inpainting net; its input is the partial spherical map of the
             *predicted* depth (depth net frozen) inside the true mask; MSE
             against the true full map over the periodically padded map.  lr 1e-4.
``refine``   the refiner; both nets frozen; BCE-with-logits against the voxel
             target (the surface shell or the truncated distance,
             ``GeometryConfig.target``; ``--target``/the recipe may change it)
             + ``surface_weight`` × the BCE weighted by the target, each less
             the target's entropy.  lr 1e-4.
``joint``    everything, through the differentiable projections: the refiner's
             loss + the spherical MSE.  lr 1e-5.

Baseline stages (:mod:`training.learn.baselines`; their weights are baseline files,
``genre-baseline/1``, never GenRe's format):

``completion``  the 3D Completion baseline: the depth net (frozen, from
             ``--init``) → depth voxels → a completion net of the refiner's
             architecture and size, starting from ``--init``'s refiner; the
             refiner's loss.  lr 1e-4.
``onestep``  GenRe-1step's RGB → full spherical map U-ResNet (the depth net's
             widths); MSE against the true full map over the padded map.  lr 1e-3.

The modules, by concern: :mod:`.train_config` (:class:`TrainConfig`, a recipe's
values and the overrides), :mod:`.stage` (:class:`StageModule`: a stage's
trainable nets and loss; the losses themselves in :mod:`.losses`),
:mod:`.batches` (deterministic batches), :mod:`.checkpoint`, :mod:`.logs`
(``log.csv``, TensorBoard, ``loss.png``), :mod:`.loop` (:func:`train`: the
steps and the files a stage leaves, data-parallel) and this one, the command
line: its arguments become a :class:`TrainSpec`, and :func:`run` trains it.

Data-parallel: ``torchrun --nproc_per_node=N -m training.learn.train …``
(gloo on the CPU, NCCL on CUDA); each process takes its share of every
global batch, rank 0 writes the files.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path

from genre_backend.config import PRESETS, GenreConfig
from genre_backend.arguments import add_out
from genre_backend.weights_file import WeightsError, resolve_weights

from .batches import StepBatches
from .checkpoint import CheckpointMismatch
from .losses import DEPTH_GRADIENT_STRIDES, depth_gradient_loss
from .loop import dist_info, train, weights_digest
from .recipe import RECIPES, STAGES, StageRecipe
from .stage import BASELINE_STAGES, StageModule
from .train_config import TrainConfig

__all__ = ["STAGES", "BASELINE_STAGES", "TrainConfig", "TrainSpec", "StageModule", "StepBatches", "CheckpointMismatch",
           "train", "weights_digest", "parse_args", "run", "main", "depth_gradient_loss", "DEPTH_GRADIENT_STRIDES"]

_RECIPE_FIELDS = {f.name: f for f in dataclasses.fields(StageRecipe)}  # (their help texts)
# TrainConfig's fields that are not plain --OPTION VALUE options of their own name
_SPECIAL = ("stage", "data", "out", "recipe", "init", "preset", "shapes", "augment", "progress")


@dataclass(frozen=True)
class TrainSpec:
    """What one ``genre train`` command line asks for: the stage's settings, and what to do with them."""

    config: TrainConfig
    model_config: GenreConfig | None = None  # --model-config's model, instead of the preset's (None: the preset's)
    dry_run: bool = False  # print the resolved settings as one JSON line; read and write nothing


def _parser(prog: str) -> argparse.ArgumentParser:
    """``genre train``'s options: the fixed ones, then one per :class:`TrainConfig` field (default: the recipe's)."""
    parser = argparse.ArgumentParser(prog=prog, description="Train one GenRe stage (resumes automatically; "
                                     "'genre train burst --help': a GPU burst from a training pack; 'genre train average --help': "
                                     "the mean of several weights files; 'genre train batch-norm --help': a weights file's batch-norm statistics "
                                     "re-estimated; 'genre train graft --help': a weights file with another's depth or inpainting net).")
    parser.add_argument("stage", choices=STAGES)
    parser.add_argument("--data", required=True, nargs="+",
                        help="folder(s) of rendered views with targets ('genre data render' + 'genre data targets'); a folder "
                             "named twice is drawn twice as often (the mix of a run)")
    add_out(parser, required=True, help="run folder; this stage writes OUT/STAGE/")
    parser.add_argument("--init", help="weights to start from: a file (e.g. OUT/depth/best.safetensors) or a shipped name (default, protocol); "
                             "default: fresh weights of --preset")
    parser.add_argument("--recipe", choices=sorted(RECIPES), default="paper",
                        help="named training recipe (training/learn/recipe.py); the options below override its values")
    parser.add_argument("--preset", choices=sorted(PRESETS), default=None, help="model preset (default: the recipe's)")
    parser.add_argument("--model-config", help="JSON file of a model config (GenreConfig.to_dict) instead of --preset")
    parser.add_argument("--shapes", help="file listing the shape ids to train on (default: every shape in --data)")
    for f in dataclasses.fields(TrainConfig):
        if f.name in _SPECIAL:
            continue
        kind = float if f.type in ("float", "float | None") else (int if f.type in ("int", "int | None") else str)
        from_recipe = f.default is None and f.name in StageRecipe.keys()
        what = _RECIPE_FIELDS[f.name].metadata["help"] if f.name in StageRecipe.keys() else f.metadata["help"]
        if from_recipe or f.default is not None:  # (a None default's help says what none means)
            what += " (default: the recipe's)" if from_recipe else f" (default: {f.default})"
        parser.add_argument("--" + f.name.replace("_", "-"), type=kind, default=f.default, help=what)
    parser.add_argument("--no-augment", action="store_true")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--dry-run", action="store_true", help="print the resolved settings as JSON and exit (nothing is read or written)")
    return parser


def parse_args(argv: list[str], prog: str = "genre train") -> TrainSpec:
    """``genre train``'s arguments as a :class:`TrainSpec`; a wrong value exits with argparse's usage error (2).
    A real run (not ``--dry-run``) also needs the weights it names to exist."""
    parser = _parser(prog)
    args = parser.parse_args(argv)
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(TrainConfig) if f.name not in ("augment", "progress")}
    try:
        config = TrainConfig(**values, augment=not args.no_augment, progress=not args.no_progress)
    except ValueError as exc:
        parser.error(str(exc))
    for name in ("init", "inpaint_from"):  # a shipped name (default, protocol) is its file, as --weights takes it
        given = getattr(config, name)
        if not given:
            continue
        try:
            config = dataclasses.replace(config, **{name: str(resolve_weights(given))})
        except WeightsError as exc:
            parser.error(f"--{name.replace('_', '-')}: {exc}")
        if not args.dry_run and not Path(getattr(config, name)).is_file():
            parser.error(f"--{name.replace('_', '-')}: no such weights file: {given}")
    model_config = None
    if args.model_config and not args.dry_run:
        try:
            model_config = GenreConfig.from_dict(json.loads(Path(args.model_config).read_text()))
        except (OSError, ValueError) as exc:
            parser.error(f"--model-config: {exc}")
    return TrainSpec(config=config, model_config=model_config, dry_run=args.dry_run)


def run(spec: TrainSpec, prog: str = "genre train") -> int:
    """Train (or resume) the stage ``spec`` names and print its summary as JSON (rank 0); with ``dry_run``, print
    the resolved settings instead.  Returns the exit status: 0, 2 for a checkpoint that does not fit the model (one
    line on stderr), or 128 + N when signal N (SIGINT, SIGTERM) stopped the run after a checkpoint."""
    if spec.dry_run:
        print(json.dumps(dataclasses.asdict(spec.config), sort_keys=True))
        return 0
    try:
        summary = train(spec.config, spec.model_config)
    except CheckpointMismatch as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    if dist_info()[0] == 0:
        print(json.dumps(summary, indent=2))
    if summary.get("stopped"):
        if dist_info()[0] == 0:
            print(f"{prog}: stopped by {summary['stopped']} after step {summary['checkpoint_step']} (checkpointed); "
                  "the same command resumes", file=sys.stderr)
        return 128 + summary["signal"]  # (the shell's status for a process its signal ended)
    return 0


def main(argv: list[str] | None = None, prog: str = "genre train") -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["burst"]:  # the GPU burst (training/learn/burst.py): its own options
        from . import burst

        return burst.main(argv[1:], prog=f"{prog} burst")
    if argv[:1] == ["bench"]:  # genre bench train: training throughput per stage (training/learn/bench.py)
        from . import bench

        return bench.main(argv[1:], prog="genre bench train")
    if argv[:1] == ["average"]:  # one weights file, the mean of several snapshots (training/learn/average.py)
        from . import average

        return average.main(argv[1:], prog=f"{prog} average")
    if argv[:1] == ["graft"]:  # one weights file made of another's nets, net by net (training/learn/graft.py)
        from . import graft

        return graft.main(argv[1:], prog=f"{prog} graft")
    if argv[:1] == ["batch-norm"]:  # a weights file's batch-norm statistics re-estimated (training/learn/batchnorm.py)
        from . import batchnorm

        return batchnorm.main(argv[1:], prog=f"{prog} batch-norm")
    if argv[:1] == ["session"]:  # the background training of every session (training/learn/session.py)
        from . import session

        return session.main(argv[1:], prog=f"{prog} session")
    return run(parse_args(argv, prog), prog)


if __name__ == "__main__":
    status = main()
    if dist_info()[1] > 1:
        # under torchrun: leave without the interpreter's teardown, where gloo's threads, though the group was
        # destroyed, can still abort the process ("terminate called without an active exception", SIGABRT) after
        # its work and files are done
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
    sys.exit(status)
