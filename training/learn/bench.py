"""``genre bench train``: training throughput per stage, the plain path beside the fast one, in one run.

For each stage (depth, inpaint, refine, joint) and each way of running the
nets — fp32 contiguous (the plain path, what ``genre train`` runs), channels-last,
bf16 autocast, both, channels-last with the refiner compiled (``torch.compile``) — it
times forward plus backward plus an Adam step on
inputs of the model's shapes, after warm-up steps, and prints the median
samples/s and its ratio to the plain path.  The ways are interleaved round by
round so that a busy machine slows them alike.  ``--pack`` also times the
on-the-fly sample maker (:class:`training.learn.burst.ViewMaker`, no voxel
target and with it), the data side of ``genre train session``.

    genre bench train --weights default --batch 4 --rounds 5
    genre bench train --stages joint --ways fp32,channels-last --batch 4,16   # larger batches beside the plain one

The header names the processor and what torch's CPU kernels use on it (its
vector extension, and whether oneDNN has native bf16): the bf16 and
channels-last figures depend on both, and the machines lent differ.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import torch
import torch.nn.functional as F

from genre_backend.weights_file import resolve_weights
from genre_backend.nets.model import GenRe, load_model
from genre_backend.arguments import add_threads, add_weights

from .burst import WAYS, Speed, apply_speed

__all__ = ["WAYS", "STAGES", "StepTimer", "cpu_description", "main"]

STAGES = ("depth", "inpaint", "refine", "joint")


def _inputs(model: GenRe, batch: int, gen: torch.Generator) -> dict[str, torch.Tensor]:
    g = model.config.geometry
    p, n = g.sph_size + 2 * g.sph_pad, g.voxel_size
    partial = torch.rand(batch, 1, p, p, generator=gen)
    partial = torch.where(partial > 0.6, torch.ones_like(partial), partial * 0.4 + 0.5)
    return {"rgb": torch.rand(batch, 3, g.image_size, g.image_size, generator=gen),
            "depth": torch.rand(batch, g.image_size, g.image_size, generator=gen) + 1.5,
            "partial": partial, "full": torch.rand(batch, 1, p, p, generator=gen),
            "vox": (torch.rand(batch, 2, n, n, n, generator=gen) > 0.97).float(),
            "target": torch.rand(batch, 1, n, n, n, generator=gen)}


def cpu_description() -> str:
    """The processor's model name, torch's CPU capability and whether oneDNN runs bf16 natively here."""
    name = "unknown processor"
    try:
        with open("/proc/cpuinfo") as fh:
            name = next((ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name")), name)
    except OSError:
        pass
    cap = torch.backends.cpu.get_cpu_capability()
    bf16 = torch.ops.mkldnn._is_mkldnn_bf16_supported()
    return f"{name}, torch CPU capability {cap}, oneDNN bf16 {'native' if bf16 else 'emulated (slow)'}"


def _forward(model: GenRe, stage: str, x: dict, channels_last: bool, bf16: bool) -> torch.Tensor:
    """The stage's loss on ``x`` (the nets that stage trains, losses of the same kind as its own)."""
    total = x["rgb"].new_zeros(())
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        if stage in ("depth", "joint"):
            rgb = x["rgb"].contiguous(memory_format=torch.channels_last) if channels_last else x["rgb"]
            out = model.depth_net(rgb)
            total = total + F.mse_loss(out["depth"].float(), x["depth"])
        if stage in ("inpaint", "joint"):
            padded = x["partial"].contiguous(memory_format=torch.channels_last) if channels_last else x["partial"]
            parts = model.inpaint_net.forward_parts(padded)
            total = total + F.mse_loss(parts["map"].float(), x["full"])
        if stage in ("refine", "joint"):
            vox = x["vox"].contiguous(memory_format=torch.channels_last_3d) if channels_last else x["vox"]
            logits = model.refiner(vox)
            total = total + F.binary_cross_entropy_with_logits(logits.float(), x["target"])
    return total


def _trained(model: GenRe, stage: str) -> list[torch.nn.Module]:
    return {"depth": [model.depth_net], "inpaint": [model.inpaint_net], "refine": [model.refiner],
            "joint": [model.depth_net, model.inpaint_net, model.refiner]}[stage]


class StepTimer:
    """One stage run one way: a model and its optimiser, built once (a compiled refiner compiles once), timed step by step."""

    def __init__(self, weights: str, stage: str, way: str, batch: int, seed: int = 0):
        self.stage, (self.channels_last, self.bf16, _) = stage, WAYS[way]
        speed = Speed.from_way(way)
        self.model = apply_speed(load_model(resolve_weights(weights)), speed)
        self.opt = speed.optimiser([p for n in _trained(self.model, stage) for p in n.parameters()], lr=1e-5)
        self.model.train()
        self.x = _inputs(self.model, batch, torch.Generator().manual_seed(seed))

    def seconds(self, steps: int, warmup: int = 0) -> list[float]:
        """Seconds of each of ``steps`` training steps after ``warmup`` untimed ones."""
        times = []
        for k in range(warmup + steps):
            t = time.perf_counter()
            loss = _forward(self.model, self.stage, self.x, self.channels_last, self.bf16)
            self.opt.zero_grad(set_to_none=True)
            loss.backward()
            self.opt.step()
            if k >= warmup:
                times.append(time.perf_counter() - t)
        return times


def _maker_seconds(pack: str, weights: str, batch: int, steps: int, voxels: bool, shapes: int) -> list[float]:
    from training.data.pack import read_pack

    from .burst import ViewMaker
    from .recipe import get_burst_recipe

    model = load_model(resolve_weights(weights))
    recipe = get_burst_recipe("session")
    maker = ViewMaker(read_pack(pack), model.config, torch.device("cpu"), recipe.grid_factor, shapes, voxels=voxels)
    gen = torch.Generator().manual_seed(0)
    times = []
    for _ in range(steps):
        t = time.perf_counter()
        shape, az, el = maker.draw(gen, batch, recipe)
        maker.make(shape, az, el, recipe.depth_noise, gen)
        times.append(time.perf_counter() - t)
    return times


def main(argv: list[str] | None = None, prog: str = "genre bench train") -> int:
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    add_weights(ap, default="default")
    ap.add_argument("--batch", default="4", help="batch size, or several separated by commas (default 4)")
    ap.add_argument("--steps", type=int, default=3, help="timed steps per round (default 3)")
    ap.add_argument("--rounds", type=int, default=3, help="rounds, each running every way once (default 3)")
    ap.add_argument("--stages", default=",".join(STAGES))
    ap.add_argument("--ways", default=",".join(WAYS))
    add_threads(ap, help="torch threads (default: every core)")
    ap.add_argument("--pack", default=None, help="also time the on-the-fly sample maker on this pack")
    ap.add_argument("--pack-shapes", type=int, default=40, help="shapes of the pack the maker times (default 40)")
    args = ap.parse_args(argv)
    import os

    torch.set_num_threads(args.threads or os.cpu_count() or 1)
    try:
        batches = [int(b) for b in str(args.batch).split(",") if b]
    except ValueError:
        ap.error(f"--batch: whole numbers separated by commas, got {args.batch!r}")
    if not batches or min(batches) < 1:
        ap.error("--batch: at least one batch size of 1 or more")
    stages = [s for s in args.stages.split(",") if s]
    ways = [w for w in args.ways.split(",") if w]
    for name in stages + ways:
        if name not in STAGES and name not in WAYS:
            ap.error(f"unknown stage or way {name!r}")
    print(f"device: cpu ({cpu_description()}), {torch.get_num_threads()} threads, torch {torch.__version__}; "
          f"batch {','.join(map(str, batches))}; median of {args.rounds} rounds × {args.steps} steps", flush=True)
    timers, warm = {}, {}
    for stage in stages:
        for batch in batches:
            for way in ways:
                t = time.perf_counter()
                timers[(stage, batch, way)] = timer = StepTimer(args.weights, stage, way, batch)
                timer.seconds(0, warmup=2)  # (a compiled refiner compiles here)
                warm[(stage, batch, way)] = time.perf_counter() - t
    results: dict[tuple[str, int, str], list[float]] = {}
    for _ in range(args.rounds):
        for key, timer in timers.items():
            results.setdefault(key, []).extend(timer.seconds(args.steps))
    # samples/s, and its ratio to the first way at the first batch size (the plain path as 'genre train' ran it)
    print(f"\n| stage, batch | {' | '.join(ways)} |\n| --- |{' --- |' * len(ways)}")
    for stage in stages:
        plain = batches[0] / statistics.median(results[(stage, batches[0], ways[0])])
        for batch in batches:
            cells = []
            for way in ways:
                rate = batch / statistics.median(results[(stage, batch, way)])
                cells.append(f"{rate:.2f}/s ({rate / plain:.2f}×)")
            print(f"| {stage}, {batch} | {' | '.join(cells)} |")
    print("set-up and two warm-up steps (s): " + "; ".join(f"{s}/{b}/{w} {v:.0f}" for (s, b, w), v in warm.items()))
    if args.pack:
        for voxels in (False, True):
            t = _maker_seconds(args.pack, args.weights, batches[0], args.rounds * args.steps, voxels, args.pack_shapes)
            print(f"sample maker ({'with' if voxels else 'without'} voxel targets): {batches[0] / statistics.median(t):.1f} samples/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
