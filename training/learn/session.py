"""``genre train session``: the training every session starts in its first minutes, in the background.

It trains the inpainting net (``--nets inpaint``) or the inpainting net and the
refiner together (``--nets both``) from samples made on the fly from a training
pack's meshes (:class:`training.learn.burst.ViewMaker`: random views from
−10° to 88°, the true depth plus a smooth error, the true full spherical map,
the refiner's distance target), on whatever device there is, with each net run
as :class:`~training.learn.burst.Speed` says for that device.  No rendering is
needed; the inpainting net needs no distance grid either, so it starts at once.
With ``--views DIR`` (a recipe with ``bank_share`` > 0, e.g. ``session-bank``)
that share of the samples are renders instead: their depth is the frozen depth
net's prediction on the picture (:mod:`training.learn.view_bank`), the errors
the refiner meets at inference.

It never ends by itself unless ``--hours`` or ``--max-steps`` says so.  Every
``--checkpoint-minutes`` (default 3), on SIGINT / SIGTERM and at the end it
writes, atomically, into ``OUT/NETS/``:

* ``checkpoint/`` (``state.safetensors`` + ``state.json``, replaced whole):
  the model, the optimiser, the step and the processor time; the next run of
  the same command resumes from it, on this machine or (copied) another;
* ``weights.safetensors`` (+ ``.json``): the model as a weights file that
  ``--weights`` and ``genre eval`` read (no pickle);
* ``log.csv``: one row every ``--log-every`` steps (rows past the checkpoint
  that a kill lost are dropped on resume).

Without a state it starts from ``--init`` (default: the installed
``default`` weights).  The learning rate follows the recipe's step schedule
(:class:`~training.learn.recipe.BurstRecipe` ``total_steps``): warm-up, a
cosine to ``lr_final`` × lr at ``total_steps``, then flat, so a run cut into
sessions follows the same curve as one run.  Each step's views are drawn from
a generator seeded by (seed, step): a resumed run draws what an unbroken one
would.  The next step's views are made in a second thread while the current
step trains (torch releases the GIL in its kernels).  Making a view costs about
as much as training on it (the spherical ray casts), so the recipe's ``reuse``
makes ``batch / reuse`` fresh views a step and fills the batch from the views of
the last ``buffer_steps`` steps, each mirrored at random when only the inpainting
net trains; a resumed run first remakes the buffer an unbroken run would hold.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import sys
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import torch

from genre_backend.config import GenreConfig
from genre_backend.geometry.spherical import mirror_sph
from genre_backend.weights_file import resolve_weights
from genre_backend.nets.model import GenRe, load_model, save_model
from genre_backend.arguments import add_device, add_out, add_seed, add_threads

from ..data.pack import read_pack
from .burst import Speed, ViewMaker, _step_loss, apply_speed, run_command
from .checkpoint import cpu_seconds, load_optimizer_state, optimizer_state, optimizer_tensors, read_state, write_state
from .recipe import BURST_RECIPES, BurstRecipe, get_burst_recipe
from .stop import StopSignals
from .view_bank import ViewBank, load_view_bank

__all__ = ["SessionSpec", "SampleStream", "lr_at", "run_session", "main"]

NETS = ("inpaint", "both")
WEIGHTS, LOG = "weights.safetensors", "log.csv"


@dataclass(frozen=True)
class SessionSpec:
    """One session's training: what it reads, where it writes, which nets, how long."""

    pack: str
    out: str
    nets: str = "inpaint"
    init: str = "default"
    recipe: str = "session"
    hours: float | None = None  # None: until stopped
    max_steps: int | None = None  # stop at this global step too
    batch_size: int | None = None  # None: the recipe's
    device: str = "auto"
    seed: int = 0
    threads: int | None = None  # None: every core
    checkpoint_minutes: float = 3.0
    log_every: int = 25
    shapes: int | None = None  # only the first K shapes of the pack (tests)
    grid_cache: str | None = None  # None: $GENRE_HOME/cache/distance_grids
    views: str | None = None  # a folder of renders: the recipe's bank_share of samples take the depth net's depth on them

    def __post_init__(self):
        if self.nets not in NETS:
            raise ValueError(f"nets: expected one of {', '.join(NETS)}, got {self.nets!r}")
        recipe = get_burst_recipe(self.recipe)
        if (self.views is None) != (recipe.bank_share == 0):
            raise ValueError(f"recipe {recipe.name!r} has bank_share {recipe.bank_share:g}: "
                             + ("--views names no renders to draw from" if self.views is None
                                else "--views needs a recipe with bank_share > 0 (e.g. session-bank)"))
        for name in ("hours", "checkpoint_minutes"):
            v = getattr(self, name)
            if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a positive number, got {v!r}")
        for name in ("max_steps", "batch_size", "threads", "shapes", "log_every"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
                raise ValueError(f"{name}: expected a positive int, got {v!r}")


def lr_at(recipe: BurstRecipe, step: int) -> float:
    """The learning rate of global step ``step`` (0-based) under ``recipe``'s step schedule."""
    total = max(recipe.total_steps, 1)
    warm = min(1.0, (step + 1) / recipe.warmup_steps) if recipe.warmup_steps > 0 else 1.0
    cosine = 0.5 * (1 + math.cos(math.pi * min(step / total, 1.0)))
    return recipe.lr * warm * (recipe.lr_final + (1 - recipe.lr_final) * cosine)


def _trained(model: GenRe, nets: str) -> list[torch.nn.Module]:
    return [model.inpaint_net] if nets == "inpaint" else [model.inpaint_net, model.refiner]


def _save_state(folder: Path, model: GenRe, opt: torch.optim.Optimizer, meta: dict) -> None:
    """The model and optimiser as one checkpoint folder, replaced whole (:func:`~training.learn.checkpoint.write_state`)."""
    tensors = {f"model.{k}": v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    opt_tensors, opt_meta = optimizer_tensors(opt)
    write_state(folder, {**tensors, **opt_tensors}, {**meta, "config": model.config.to_dict(), **opt_meta})


def _load_state(folder: Path) -> tuple[GenRe, dict, dict] | None:
    """(model, optimiser state dict, meta) from ``folder``'s checkpoint, or None when it has none."""
    state = read_state(folder)
    if state is None:
        return None
    tensors, doc = state
    model = GenRe(GenreConfig.from_dict(doc["config"]))
    model.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("model.")}, strict=True)
    return model, {"state": optimizer_state(tensors, doc), "param_groups": doc["param_groups"]}, doc


def _trim_log(path: Path, step: int) -> list[dict]:
    """log.csv's rows up to ``step`` (the rest were written after the state a resume starts from)."""
    if not path.is_file():
        return []
    with open(path, newline="") as fh:
        return [r for r in csv.DictReader(fh) if int(r["step"]) <= step]


def _write_log(path: Path, rows: list[dict]) -> None:
    if not rows:
        return
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]), extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    os.replace(tmp, path)


class SampleStream:
    """A session's batches: ``fresh`` views made a step (a function of (seed, step) alone, partial maps included),
    kept for the recipe's ``buffer_steps`` steps, and each step's batch its fresh views plus views drawn from the
    buffer, mirrored at random when only the inpainting net trains (a view's reflection is a view of the reflected
    shape).  :meth:`resume` remakes the buffer an unbroken run would hold at a step."""

    def __init__(self, maker: ViewMaker, model: GenRe, recipe: BurstRecipe, batch: int, seed: int, inpaint_only: bool,
                 bank: ViewBank | None = None):
        self.maker, self.model, self.recipe, self.batch, self.seed = maker, model, recipe, batch, seed
        self.bank = bank
        self.inpaint_only = inpaint_only
        self.fresh = max(1, batch // recipe.reuse)
        self.keep = ("partial", "full_sph", "teacher") if inpaint_only else None
        self.buffer: deque = deque(maxlen=max(1, recipe.buffer_steps))

    def make(self, k: int) -> dict:
        """Step ``k``'s fresh views."""
        gen = torch.Generator().manual_seed(self.seed * 1_000_003 + k)
        shape, az, el = self.maker.draw(gen, self.fresh, self.recipe)
        rendered = None
        if self.bank is not None:  # these samples are renders: their pose, and the depth net's depth on them
            rendered = torch.rand(self.fresh, generator=gen) < self.recipe.bank_share
            b_shape, b_az, b_el, b_depth = self.bank.draw(gen, self.fresh)
            shape, az, el = (torch.where(rendered, b, a) for a, b in ((shape, b_shape), (az, b_az), (el, b_el)))
        sample = self.maker.make(shape, az, el, self.recipe.depth_noise, gen)
        if rendered is not None:
            sample["depth"] = torch.where(rendered[:, None, None].to(sample["depth"].device),
                                          b_depth.to(sample["depth"].device), sample["depth"])
        with torch.no_grad():
            sample["partial"] = self.model.partial_sph(sample["depth"])  # (the projection only: no parameters)
        if self.recipe.sph_teacher > 0:
            sample["teacher"] = torch.rand(self.fresh, generator=gen) < self.recipe.sph_teacher
        return sample if self.keep is None else {name: v for name, v in sample.items() if name in self.keep}

    def resume(self, step: int) -> None:
        for k in range(max(0, step - self.buffer.maxlen + 1), step):
            self.buffer.append(self.make(k))

    def batch_of(self, k: int, fresh: dict) -> dict:
        """Step ``k``'s batch, ``fresh`` being :meth:`make`'s views of step ``k``."""
        self.buffer.append(fresh)
        gen = torch.Generator().manual_seed(self.seed * 1_000_003 + k + 2**40)
        sizes = [len(entry["full_sph"]) for entry in self.buffer]
        flat = torch.cat([torch.stack([torch.full((n,), e), torch.arange(n)], 1) for e, n in enumerate(sizes)])
        current = flat[-sizes[-1]:]
        more = self.batch - len(current)
        extra = flat[torch.randint(len(flat), (more,), generator=gen)] if more > 0 else flat[:0]
        pick = torch.cat([current, extra])[:self.batch]
        out = {name: torch.stack([self.buffer[int(e)][name][int(i)] for e, i in pick]) for name in fresh}
        if self.inpaint_only:
            flip = torch.rand(len(pick), generator=gen) < 0.5
            for name in ("partial", "full_sph"):
                out[name] = torch.where(flip[:, None, None], mirror_sph(out[name]), out[name])
        return out


def _set_up(spec: SessionSpec, recipe: BurstRecipe, device: torch.device, folder: Path, say):
    """The model (resumed or from ``--init``), its optimiser, the view maker and the state's meta."""
    from training.data.corpus import data_dir

    resumed = _load_state(folder)
    if resumed is None:
        init = resolve_weights(spec.init)
        model, opt_state, meta0 = load_model(init), None, {"step": 0, "samples": 0, "cpu_s": 0.0, "init": str(init)}
        say(f"session: starting from {init}")
    else:
        model, opt_state, meta0 = resumed
        say(f"session: resuming {folder} at step {meta0['step']} (from {meta0.get('init')})")
    model = apply_speed(model.to(device), Speed.for_device(device))
    pack = read_pack(spec.pack)
    bank = None if spec.views is None else load_view_bank(spec.views, list(pack.ids)[:spec.shapes], model, device, say=say)
    grid_cache = spec.grid_cache or str(data_dir() / "cache" / "distance_grids")
    maker = ViewMaker(pack, model.config, device, recipe.grid_factor, spec.shapes, progress=say,
                      voxels=spec.nets == "both", grid_cache=grid_cache, targets="exact" if device.type == "cpu" else "grid")
    for p in model.parameters():
        p.requires_grad_(False)
    trained = _trained(model, spec.nets)
    params = [p for net in trained for p in net.parameters()]
    for p in params:
        p.requires_grad_(True)
    opt = Speed.for_device(device).optimiser(params, recipe.lr, (recipe.beta1, recipe.beta2), recipe.weight_decay)
    if opt_state is not None:
        load_optimizer_state(opt, opt_state)
    model.eval()
    for net in trained:
        net.train()
    return model, opt, maker, bank, meta0


def run_session(spec: SessionSpec, say=print) -> dict:
    """Train until the budget ends or a signal comes; returns the summary (also in the checkpoint's state.json)."""
    t0 = time.time()
    torch.set_num_threads(spec.threads or os.cpu_count() or 1)
    recipe = get_burst_recipe(spec.recipe)
    device = torch.device("cuda" if spec.device == "auto" and torch.cuda.is_available() else
                          ("cpu" if spec.device == "auto" else spec.device))
    speed = Speed.for_device(device)
    folder = Path(spec.out) / spec.nets
    folder.mkdir(parents=True, exist_ok=True)
    model, opt, maker, bank, meta0 = _set_up(spec, recipe, device, folder, say)
    batch = spec.batch_size or recipe.batch_size
    step, samples, cpu_before = int(meta0["step"]), int(meta0["samples"]), float(meta0["cpu_s"])
    rows = _trim_log(folder / LOG, step)
    stop = StopSignals().install()  # (a signal while the buffer is remade ends the run at its first step, state unchanged)
    stream = SampleStream(maker, model, recipe, batch, spec.seed, spec.nets == "inpaint", bank)
    session_start, session_step0, last_ck = time.time(), step, time.time()
    deadline = None if spec.hours is None else session_start + spec.hours * 3600.0

    def checkpoint(final: bool) -> dict:
        elapsed, done = time.time() - session_start, step - session_step0
        m = {"step": step, "samples": samples, "cpu_s": cpu_before + cpu_seconds(), "init": meta0.get("init"),
             "recipe": recipe.name, "nets": spec.nets, "batch": batch, "device": str(device),
             "threads": torch.get_num_threads(), "speed": speed.__dict__, "final": final, "views": spec.views,
             "session_steps": done, "session_samples_per_s": done * batch / max(elapsed, 1e-9)}
        _save_state(folder, model, opt, m)
        save_model(model, folder / WEIGHTS, {"session": {k: m[k] for k in ("step", "samples", "recipe", "nets", "init")}},
                   storage="float16")
        _write_log(folder / LOG, rows)
        return m

    pool = ThreadPoolExecutor(1)
    try:
        stream.resume(step)
        say(f"session: {spec.nets} on {device} ({torch.get_num_threads()} threads), {speed}, batch {batch}, "
            f"{len(maker)} shapes, recipe {recipe.name}; set-up {time.time() - t0:.0f} s")
        session_start = last_ck = time.time()  # (the samples/s leave the set-up out)
        upcoming = pool.submit(stream.make, step)
        while not stop.caught() and (deadline is None or time.time() < deadline) and \
                (spec.max_steps is None or step < spec.max_steps):
            fresh = upcoming.result()
            upcoming = pool.submit(stream.make, step + 1)
            lr = lr_at(recipe, step)
            for group in opt.param_groups:
                group["lr"] = lr
            loss, terms = _step_loss(model, stream.batch_of(step, fresh), recipe, speed=speed, refiner=spec.nets == "both")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            step, samples = step + 1, samples + batch
            if step % spec.log_every == 0:
                elapsed = time.time() - session_start
                rows.append({"step": step, "seconds": round(elapsed, 1), "lr": lr, "batch": batch,
                             "loss": float(loss.detach()), **{k: float(v.detach()) for k, v in terms.items()}})
                say(f"step {step:7d}  loss {rows[-1]['loss']:.4f}  "
                    f"{(step - session_step0) * batch / max(elapsed, 1e-9):.1f} samples/s  lr {lr:.2e}")
            if time.time() - last_ck >= spec.checkpoint_minutes * 60.0:
                checkpoint(False)
                last_ck = time.time()
                say(f"checkpoint: step {step}, {folder}")
        upcoming.cancel()
    finally:
        pool.shutdown(wait=True)
        stop.restore()
    summary = checkpoint(True)
    why = f"signal {stop.caught()}" if stop.caught() else "budget"
    say(f"session: stopped ({why}) at step {step}; {summary['session_samples_per_s']:.1f} samples/s; state in {folder}")
    return summary


def main(argv: list[str] | None = None, prog: str = "genre train session") -> int:
    from training.data.corpus import data_dir

    home = data_dir()
    parser = argparse.ArgumentParser(prog=prog, description="Train the inpainting net (and the refiner) from a "
                                     "training pack, resuming, checkpointing every few minutes (training/learn/session.py).")
    parser.add_argument("--pack", default=str(home / "pack"), help="a training pack (genre data pack; default $GENRE_HOME/pack)")
    add_out(parser, default=str(home / "runs" / "session"), help="default $GENRE_HOME/runs/session")
    parser.add_argument("--nets", default="inpaint", choices=NETS, help="what trains (default inpaint)")
    parser.add_argument("--init", default="default", help="weights to start from when OUT/NETS holds no state")
    parser.add_argument("--recipe", default="session", choices=sorted(BURST_RECIPES))
    parser.add_argument("--hours", type=float, default=None, help="stop after this long (default: until stopped)")
    parser.add_argument("--max-steps", type=int, default=None)
    parser.add_argument("--batch-size", type=int, default=None)
    add_device(parser, default="auto")
    add_seed(parser)
    add_threads(parser)
    parser.add_argument("--checkpoint-minutes", type=float, default=3.0)
    parser.add_argument("--log-every", type=int, default=25)
    parser.add_argument("--shapes", type=int, default=None)
    parser.add_argument("--grid-cache", default=None)
    parser.add_argument("--views", default=None, help="a folder of renders (genre data render) of the pack's shapes: "
                        "the recipe's bank_share of the samples take the depth net's prediction on them as their depth "
                        "(training/learn/view_bank.py; e.g. --recipe session-bank)")
    args = parser.parse_args(argv)
    return run_command(prog, lambda: run_session(SessionSpec(**vars(args)), say=lambda m: print(m, flush=True)))


if __name__ == "__main__":
    sys.exit(main())
