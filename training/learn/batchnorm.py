"""``genre train batch-norm``: a weights file whose batch-norm statistics are re-estimated on training batches.

In evaluation mode every batch-norm layer normalises with the running statistics that training kept: an
exponential mean (momentum 0.1) over the last few dozen batches, each of one process's few samples, taken while
the weights kept moving.  A mean of weights (``genre train average``: SWA, soups) carries the mean of its files'
statistics, which are not those of the mean's own activations.  Stochastic weight averaging (Izmailov et al., UAI
2018) therefore re-estimates them with one pass over training data in training mode; this command does that for a
GenRe weights file.

The nets' inputs are made exactly as the joint stage makes them (:class:`~training.learn.stage.StageModule`: the
training set's photo compositing and camera faults, the predicted depth inside the true mask, its partial map, the
inpainted map, both voxel grids), so each net's statistics are those of what the net before it now gives it.  Each
layer's new statistics are the equal-weight mean over the batches of the batch's mean and (unbiased) variance, as
``torch.optim.swa_utils.update_bn`` makes them; the nets run in fp32, as at inference.  Nothing else changes.

    genre train batch-norm W.safetensors --data VIEWS [VIEWS ...] --backgrounds B --out W_bn.safetensors
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable
from pathlib import Path

import torch
from torch import nn

from genre_backend.arguments import add_out, add_seed, add_storage
from genre_backend.nets.model import GenRe, load_model, save_model
from genre_backend.weights_file import WeightsError

from .batches import StepBatches
from .stage import StageModule
from .train_config import TrainConfig

__all__ = ["batch_norms", "refresh_batch_norm", "training_batches", "main"]


def batch_norms(model: nn.Module) -> list[nn.modules.batchnorm._BatchNorm]:
    """Every batch-norm layer of ``model`` (2D and 3D), in module order."""
    return [m for m in model.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]


@torch.no_grad()
def refresh_batch_norm(model: GenRe, batches: Iterable[dict[str, torch.Tensor]]) -> int:
    """Replace every batch-norm layer's running statistics of ``model`` by their mean over ``batches``.

    Each batch is a joint-stage training batch (``rgb``, ``mask``, ``full_sph``, ``voxels``, as
    :class:`~training.learn.batches.StepBatches` gives them), run through the joint stage in training mode
    without gradients.  Returns the number of batches; the model is left in evaluation mode with each layer's
    momentum as it was.  Raises :class:`ValueError` when ``model`` has no batch-norm layer or ``batches`` is empty.
    """
    norms = batch_norms(model)
    if not norms:
        raise ValueError("the model has no batch-norm layer")
    momenta = [m.momentum for m in norms]
    grads = [p.requires_grad for p in model.parameters()]
    saved = [(m.running_mean.clone(), m.running_var.clone(), m.num_batches_tracked.clone()) for m in norms]
    for m in norms:
        m.reset_running_stats()
        m.momentum = None  # a cumulative mean: every batch counts the same
    stage = StageModule(model, "joint", surface_weight=0.0)
    stage.train()
    count = 0
    try:
        for batch in batches:
            stage(batch)
            count += 1
    finally:
        for m, momentum in zip(norms, momenta):
            m.momentum = momentum
        for p, g in zip(model.parameters(), grads):
            p.requires_grad_(g)
        model.eval()
    if count == 0:
        for m, (mean, var, n) in zip(norms, saved):  # as it was
            m.running_mean.copy_(mean)
            m.running_var.copy_(var)
            m.num_batches_tracked.copy_(n)
        raise ValueError("no batches to estimate the batch-norm statistics from")
    return count


def training_batches(data: list[str], *, recipe: str, backgrounds: str | None, samples: int, batch_size: int,
                     seed: int, model: GenRe) -> Iterable[dict[str, torch.Tensor]]:
    """``ceil(samples / batch_size)`` joint-stage training batches of ``data`` as ``genre train joint --recipe
    RECIPE`` draws them (the same training share of the views, compositing and faults), for ``seed``."""
    from .loop import _datasets

    tcfg = TrainConfig(stage="joint", data=data, out="", recipe=recipe, backgrounds=backgrounds, seed=seed,
                       batch_size=batch_size)
    train_set, _, _ = _datasets(tcfg, model.config)
    steps = -(-samples // batch_size)
    source = StepBatches(train_set, batch_size, 0, 1, seed)
    return (source[k] for k in range(steps))


def main(argv: list[str] | None = None, prog: str = "genre train batch-norm") -> int:
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    ap.add_argument("weights", help="a GenRe weights file (e.g. 'genre train average''s)")
    ap.add_argument("--data", nargs="+", required=True, help="views folders with targets, as 'genre train joint --data'")
    ap.add_argument("--backgrounds", default=None, help="a 'genre data backgrounds' folder (the recipe's photo compositing)")
    ap.add_argument("--recipe", default="product", help="the recipe whose joint stage draws the batches (default: product)")
    ap.add_argument("--samples", type=int, default=1024, help="training samples to estimate from (default: 1024)")
    ap.add_argument("--batch-size", type=int, default=8, help="samples a batch, as one training process's (default: 8)")
    add_seed(ap, help="which batches (default: 0)")
    add_out(ap, required=True, help="the weights file with the new statistics (.safetensors; a .json beside it)")
    add_storage(ap)
    args = ap.parse_args(argv)
    if Path(args.out).resolve() == Path(args.weights).resolve():
        ap.error("--out is the input file")
    if args.samples < 1 or args.batch_size < 2:
        ap.error("--samples must be at least 1 and --batch-size at least 2 (a batch's variance needs two samples)")
    try:
        model = load_model(args.weights)
        batches = training_batches(args.data, recipe=args.recipe, backgrounds=args.backgrounds, samples=args.samples,
                                   batch_size=args.batch_size, seed=args.seed, model=model)
        count = refresh_batch_norm(model, batches)
    except (OSError, ValueError, WeightsError) as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    extra = {"batch_norm": {"from": Path(args.weights).name, "data": args.data, "recipe": args.recipe,
                            "batches": count, "batch_size": args.batch_size, "seed": args.seed}}
    path = save_model(model, args.out, extra, storage=args.storage)
    print(f"{path}: {len(batch_norms(model))} batch-norm layers re-estimated on {count} batches of {args.batch_size}")
    return 0
