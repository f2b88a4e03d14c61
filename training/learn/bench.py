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

``--processes 1,2`` also times each stage as ``genre train`` runs it under
``torchrun --nproc_per_node=2``: the batch split over that many processes,
the threads too, the gradients summed over gloo after each backward (as DDP
does, without its overlap of the sum with the backward), each step's time the
slowest process's.  The batch is then the global batch.

    genre bench train --weights default --batch 4 --rounds 5
    genre bench train --stages joint --ways fp32,channels-last --batch 4,16   # larger batches beside the plain one
    genre bench train --stages joint --ways fp32,channels-last+bf16 --batch 4,16 --processes 1,2

The header names the processor and what torch's CPU kernels use on it (its
vector extension, and whether oneDNN has native bf16): the bf16 and
channels-last figures depend on both, and the machines lent differ.
"""

from __future__ import annotations

import argparse
import os
import queue
import statistics
import sys
import tempfile
import time
from collections.abc import Callable

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
        self.trained = [p for n in _trained(self.model, stage) for p in n.parameters()]
        self.opt = speed.optimiser(self.trained, lr=1e-5)
        self.model.train()
        self.x = _inputs(self.model, batch, torch.Generator().manual_seed(seed))

    def seconds(self, steps: int, warmup: int = 0, sync: Callable[[list], None] | None = None) -> list[float]:
        """Seconds of each of ``steps`` training steps after ``warmup`` untimed ones; ``sync`` (the data-parallel
        gradient sum) is given the trained parameters between the backward and the optimiser's step."""
        times = []
        for k in range(warmup + steps):
            t = time.perf_counter()
            loss = _forward(self.model, self.stage, self.x, self.channels_last, self.bf16)
            self.opt.zero_grad(set_to_none=True)
            loss.backward()
            if sync is not None:
                sync(self.trained)
            self.opt.step()
            if k >= warmup:
                times.append(time.perf_counter() - t)
        return times


Key = tuple[str, int, str, int]  # stage, global batch, way, processes


def _gradient_sum(world: int) -> Callable[[list], None]:
    """The data-parallel step's gradient exchange: every gradient summed over the processes in one flat buffer
    and divided by their number (DDP's all-reduce, in one bucket and after the backward)."""
    import torch.distributed as dist

    def sync(params: list) -> None:
        grads = [p.grad for p in params if p.grad is not None]
        flat = torch.cat([g.reshape(-1) for g in grads])
        dist.all_reduce(flat)
        flat /= world
        offset = 0
        for g in grads:
            g.copy_(flat[offset:offset + g.numel()].view_as(g))
            offset += g.numel()
    return sync


def _rank(rank: int, world: int, init: str, weights: str, keys: list, threads: int, inbox, outbox) -> None:
    """One process of a data-parallel bench: its share of each key's batch, timed when the parent asks."""
    import torch.distributed as dist

    try:
        torch.set_num_threads(threads)
        dist.init_process_group("gloo", init_method=init, rank=rank, world_size=world)
        sync = _gradient_sum(world)
        timers, warm = {}, {}
        for key in keys:
            stage, batch, way, _ = key
            t = time.perf_counter()
            timers[key] = timer = StepTimer(weights, stage, way, batch // world, seed=rank)
            timer.seconds(0, warmup=2, sync=sync)
            warm[key] = time.perf_counter() - t
        if rank == 0:
            outbox.put(("ready", warm))
        while (steps := inbox.get()) is not None:
            times = {key: timer.seconds(steps, sync=sync) for key, timer in timers.items()}
            if rank == 0:
                outbox.put(("times", times))
        dist.destroy_process_group()
    except BaseException as exc:  # the parent reports it and stops the others
        outbox.put(("error", f"process {rank}: {type(exc).__name__}: {exc}"))
        raise


class ParallelTimers:
    """The keys of one process count > 1, each timed in ``world`` spawned processes that stay up between rounds
    and wait idle while the parent's own keys are timed, so that every way is measured on a quiet machine."""

    def __init__(self, weights: str, keys: list[Key], world: int, threads: int):
        import torch.multiprocessing as mp

        ctx = mp.get_context("spawn")
        self.dir = tempfile.TemporaryDirectory(prefix="genre-bench-")
        init = f"file://{os.path.join(self.dir.name, 'rendezvous')}"
        self.inboxes = [ctx.Queue() for _ in range(world)]
        self.outbox = ctx.Queue()
        self.procs = [ctx.Process(target=_rank, args=(r, world, init, weights, keys, max(1, threads // world),
                                                       self.inboxes[r], self.outbox), daemon=True)
                      for r in range(world)]
        for p in self.procs:
            p.start()
        self.warm = self._reply("ready")

    def _reply(self, kind: str):
        while True:
            try:
                got, value = self.outbox.get(timeout=1.0)
            except queue.Empty:
                if any(not p.is_alive() for p in self.procs):
                    self.close()
                    raise RuntimeError("a bench process ended before it answered") from None
                continue
            if got == "error":
                self.close()
                raise RuntimeError(value)
            if got == kind:
                return value

    def seconds(self, steps: int) -> dict:
        for box in self.inboxes:
            box.put(steps)
        return self._reply("times")

    def close(self) -> None:
        for p, box in zip(self.procs, self.inboxes):
            if p.is_alive():
                box.put(None)
        for p in self.procs:
            p.join(timeout=30)
            if p.is_alive():
                p.kill()
        self.dir.cleanup()


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


def _counts(ap: argparse.ArgumentParser, flag: str, text: str) -> list[int]:
    """Whole numbers of 1 or more separated by commas, in the order given."""
    try:
        counts = [int(b) for b in str(text).split(",") if b]
    except ValueError:
        ap.error(f"{flag}: whole numbers separated by commas, got {text!r}")
    if not counts or min(counts) < 1:
        ap.error(f"{flag}: at least one count of 1 or more")
    return counts


def main(argv: list[str] | None = None, prog: str = "genre bench train") -> int:
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    add_weights(ap, default="default")
    ap.add_argument("--batch", default="4", help="batch size, or several separated by commas (default 4)")
    ap.add_argument("--steps", type=int, default=3, help="timed steps per round (default 3)")
    ap.add_argument("--rounds", type=int, default=3, help="rounds, each running every way once (default 3)")
    ap.add_argument("--stages", default=",".join(STAGES))
    ap.add_argument("--ways", default=",".join(WAYS))
    add_threads(ap, help="torch threads (default: every core)")
    ap.add_argument("--processes", default="1",
                    help="processes the batch is split over, or several counts separated by commas (default 1; "
                         "2 = as torchrun --nproc_per_node=2 runs genre train)")
    ap.add_argument("--pack", default=None, help="also time the on-the-fly sample maker on this pack")
    ap.add_argument("--pack-shapes", type=int, default=40, help="shapes of the pack the maker times (default 40)")
    args = ap.parse_args(argv)
    threads = args.threads or os.cpu_count() or 1
    torch.set_num_threads(threads)
    batches, worlds = _counts(ap, "--batch", args.batch), _counts(ap, "--processes", args.processes)
    for world in worlds:
        for batch in batches:
            if batch % world:
                ap.error(f"--batch {batch} does not split over {world} processes")
    stages = [s for s in args.stages.split(",") if s]
    ways = [w for w in args.ways.split(",") if w]
    for name in stages + ways:
        if name not in STAGES and name not in WAYS:
            ap.error(f"unknown stage or way {name!r}")
    print(f"device: cpu ({cpu_description()}), {threads} threads, torch {torch.__version__}; "
          f"batch {','.join(map(str, batches))}"
          + (f" over {','.join(map(str, worlds))} processes" if worlds != [1] else "")
          + f"; median of {args.rounds} rounds × {args.steps} steps", flush=True)
    keys = [(stage, batch, way, world) for stage in stages for world in worlds for batch in batches for way in ways]
    timers, warm, groups = {}, {}, []
    for key in keys:
        if key[3] == 1:
            t = time.perf_counter()
            timers[key] = timer = StepTimer(args.weights, key[0], key[2], key[1])
            timer.seconds(0, warmup=2)  # (a compiled refiner compiles here)
            warm[key] = time.perf_counter() - t
    try:
        for world in sorted(set(worlds) - {1}):
            groups.append(group := ParallelTimers(args.weights, [k for k in keys if k[3] == world], world, threads))
            warm.update(group.warm)
        results: dict[Key, list[float]] = {}
        for _ in range(args.rounds):
            for key, timer in timers.items():
                results.setdefault(key, []).extend(timer.seconds(args.steps))
            for group in groups:
                for key, times in group.seconds(args.steps).items():
                    results.setdefault(key, []).extend(times)
    finally:
        for group in groups:
            group.close()
    # samples/s, and its ratio to the first way at the first batch size and process count (the plain path as
    # 'genre train' ran it)
    print(f"\n| stage, batch | {' | '.join(ways)} |\n| --- |{' --- |' * len(ways)}")
    for stage in stages:
        plain = batches[0] / statistics.median(results[(stage, batches[0], ways[0], worlds[0])])
        for world in worlds:
            for batch in batches:
                cells = []
                for way in ways:
                    rate = batch / statistics.median(results[(stage, batch, way, world)])
                    cells.append(f"{rate:.2f}/s ({rate / plain:.2f}×)")
                label = f"{stage}, {batch}" + (f" ({world} processes × {batch // world})" if world > 1 else "")
                print(f"| {label} | {' | '.join(cells)} |")
    print("set-up and two warm-up steps (s): "
          + "; ".join(f"{s}/{b}/{w}{f'/{n}p' if n > 1 else ''} {v:.0f}" for (s, b, w, n), v in warm.items()))
    if args.pack:
        for voxels in (False, True):
            t = _maker_seconds(args.pack, args.weights, batches[0], args.rounds * args.steps, voxels, args.pack_shapes)
            print(f"sample maker ({'with' if voxels else 'without'} voxel targets): {batches[0] / statistics.median(t):.1f} samples/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
