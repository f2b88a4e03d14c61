"""``genre train average``: one weights file whose tensors are the (weighted) mean of several files' tensors.

Weight averaging of one model's snapshots — along a low-learning-rate run
(stochastic weight averaging, Izmailov et al., UAI 2018) or of two runs that
share a start (a "model soup", Wortsman et al., ICML 2022) — often lands
lower on held-out data than any of the snapshots, at no cost at inference.
It only makes sense for files that are one fine-tuning apart (one basin);
that is the caller's judgement, the arithmetic is checked here:

* every file must hold the same nets (tensor names and shapes); the mesh
  settings of the first file's config are the result's;
* floating-point tensors, batch-norm statistics included, are averaged in
  float64 and stored as float32 (a float16 file is read as float32);
* integer tensors (batch-norm step counters) take the largest value.

The batch-norm statistics are averaged rather than re-estimated: for
snapshots a few thousand low-lr steps apart they barely differ, and a
re-estimate would need the training views.

    genre train average RUN/snap/step_*.safetensors --out W.safetensors
    genre train average A.safetensors B.safetensors --mix 0.7 0.3 --out W.safetensors
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from genre_backend.arguments import add_out, add_storage
from genre_backend.nets.model import GenRe, load_model, save_model
from genre_backend.weights_file import WeightsError

__all__ = ["average_models", "main"]


def average_models(models: list[GenRe], weights: list[float] | None = None) -> GenRe:
    """A new model whose state is the weighted mean of ``models``' states, with the first one's config (its mesh settings).

    ``weights`` (default: equal) are normalised to sum to 1; they must be
    non-negative with a positive sum.  Raises :class:`ValueError` when the
    models' nets differ (tensor names or shapes) or the weights do not fit.
    """
    if not models:
        raise ValueError("nothing to average")
    weights = [1.0] * len(models) if weights is None else [float(w) for w in weights]
    if len(weights) != len(models):
        raise ValueError(f"{len(weights)} weights for {len(models)} files")
    if any(not w >= 0 for w in weights) or sum(weights) <= 0:
        raise ValueError(f"weights must be non-negative with a positive sum, got {weights}")
    total = sum(weights)
    weights = [w / total for w in weights]
    states = [m.state_dict() for m in models]
    shapes = {k: tuple(v.shape) for k, v in states[0].items()}
    for k, s in enumerate(states[1:], 1):
        if {n: tuple(v.shape) for n, v in s.items()} != shapes:
            raise ValueError(f"file {k + 1} holds other nets than file 1 (tensor names or shapes differ)")
    merged = {}
    for name, ref in states[0].items():
        if ref.is_floating_point():
            acc = torch.zeros(ref.shape, dtype=torch.float64)
            for w, s in zip(weights, states):
                acc += w * s[name].to(torch.float64)
            merged[name] = acc.to(ref.dtype)
        else:
            merged[name] = torch.stack([s[name] for s in states]).amax(dim=0)
    out = GenRe(models[0].config)
    out.load_state_dict(merged, strict=True)
    return out.eval()


def main(argv: list[str] | None = None, prog: str = "genre train average") -> int:
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="+", help="GenRe weights files of one model (same nets; the first one's config is kept)")
    ap.add_argument("--mix", type=float, nargs="+", default=None, help="each file's share, one number per file (default: equal)")
    add_out(ap, required=True, help="the averaged weights file (.safetensors; a .json beside it)")
    add_storage(ap)
    args = ap.parse_args(argv)
    if Path(args.out).resolve() in {Path(f).resolve() for f in args.files}:
        ap.error("--out is one of the input files")
    try:
        models = [load_model(f) for f in args.files]
        model = average_models(models, args.mix)
    except (WeightsError, ValueError) as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    extra = {"averaged": [str(f) for f in args.files], "mix": args.mix or [1.0] * len(args.files)}
    save_model(model, args.out, extra, storage=args.storage)
    print(f"{len(models)} files averaged -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
