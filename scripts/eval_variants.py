#!/usr/bin/env python3
"""``genre eval`` with one change to the pipeline made in-process: probes that need no new weights format.

* ``--refiner-from W2``: the refiner's probability averaged with the refiner of the weights file W2 (the same depth
  and inpainting nets; an ensemble of refiners).
* ``--pipeline-from W2``: two whole pipelines, ``--weights`` and W2, averaged as probabilities (an ensemble of, say,
  depth nets when W2 differs only there).
* ``--back-level DELTA,MARGIN,RAMP``: the grid's hidden back at a higher level. In each column of the grid along the
  view, a voxel more than MARGIN voxels behind the grid's own front (its voxel nearest the camera above the level)
  has DELTA subtracted, ramped in over RAMP voxels; applied after the weights' own mesh steps.

Everything after these options goes to ``genre eval`` unchanged; it runs with ``--jobs 1``, since the change lives
in this process. Used by ``results/decisions.md`` (2026-12-01, the twenty-seventh session):

    H=$GENRE_HOME
    .venv/bin/python scripts/eval_variants.py --refiner-from $H/cand/F46.safetensors -- \\
        --data $H/views/product_eval --groups product-test --weights genre_backend/weights/default.safetensors --rows GenRe --levels 0.45 \\
        --no-figures --out OUT
    .venv/bin/python scripts/eval_variants.py --back-level 0.05,2,2 -- --data $H/views/fresh88_s300 \\
        --groups product-train --max-views 1 --weights genre_backend/weights/default.safetensors --rows GenRe --levels 0.45 --no-figures --out OUT
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import torch

import genre_backend.inference.options as options
import genre_backend.nets.model as model_module


class RefinerMean(torch.nn.Module):
    """Two refiners whose probabilities are averaged (:func:`genre_backend.nets.model.mean_probability_logits`)."""

    def __init__(self, a, b):
        super().__init__()
        self.a, self.b = a, b

    def forward(self, x):
        return model_module.mean_probability_logits(self.a(x), self.b(x))


class PipelineMean(torch.nn.Module):
    """Two pipelines run on the same input; the first one's outputs with the two logits averaged as probabilities."""

    def __init__(self, a, b):
        super().__init__()
        self.a, self.b = a, b
        self.config = a.config

    def forward(self, *args, **kwargs):
        oa, ob = self.a(*args, **kwargs), self.b(*args, **kwargs)
        return dataclasses.replace(oa, logits=model_module.mean_probability_logits(oa.logits, ob.logits))


def back_lowered(prob: torch.Tensor, level: float, delta: float, margin: float, ramp: float) -> torch.Tensor:
    """``prob`` (N, N, N), indexed [ix, iy, iz] with +z toward the camera, lowered by up to ``delta`` behind its
    own front at ``level`` (see the module's docstring)."""
    n = prob.shape[-1]
    iz = torch.arange(n).view(1, 1, n).expand_as(prob)
    front = torch.where(prob >= level, iz, torch.full_like(iz, -1)).amax(dim=2, keepdim=True)
    weight = ((front - iz).float() - margin).div(max(ramp, 1e-6)).clamp(0, 1) * (front >= 0)
    return prob - delta * weight


def main(argv: list[str]) -> int:
    if "--" not in argv:
        argv = [*argv, "--"]
    cut = argv.index("--")
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--refiner-from", metavar="W2", help="a weights file whose refiner joins --weights' refiner")
    which.add_argument("--pipeline-from", metavar="W2", help="a weights file whose whole pipeline joins --weights'")
    which.add_argument("--back-level", metavar="DELTA,MARGIN,RAMP", help="the hidden back's level raised by DELTA")
    args = p.parse_args(argv[:cut])
    rest = list(argv[cut + 1:])
    if "--jobs" in rest:
        del rest[rest.index("--jobs"):rest.index("--jobs") + 2]
    load = model_module.load_model

    if args.refiner_from:
        def patched(path, device="cpu"):
            m = load(path, device)
            m.refiner = RefinerMean(m.refiner, load(args.refiner_from, device).refiner).eval()
            return m
        model_module.load_model = patched
    elif args.pipeline_from:
        model_module.load_model = lambda path, device="cpu": PipelineMean(load(path, device),
                                                                           load(args.pipeline_from, device)).eval()
    else:
        delta, margin, ramp = (float(x) for x in args.back_level.split(","))
        shape_grid = options.MeshOptions.shape_grid

        def lowered(self, prob, view, geometry):
            return back_lowered(shape_grid(self, prob, view, geometry), self.threshold, delta, margin, ramp)
        options.MeshOptions.shape_grid = lowered

    from genre_backend.cli import main as genre
    return genre(["eval", *rest, "--jobs", "1"])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
