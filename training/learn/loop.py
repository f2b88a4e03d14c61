"""The training loop of one stage (:func:`train`): the model, the data, the steps, the files a stage leaves.

Each stage writes ``OUT/STAGE/``: ``best.safetensors`` (lowest validation
loss) and ``final.safetensors`` (weights + config, no pickle), ``config.json``
(the resolved training config), ``log.csv``, ``tb/`` (TensorBoard),
``loss.png``, ``summary.json``, ``checkpoint/`` (:mod:`.checkpoint`) and, with
``snapshot_every``, ``snapshots/step_N.safetensors``.
Running the same stage again resumes from the checkpoint with the same step
count and, on the CPU, the same numbers: the batch of step k and its
augmentation depend only on (seed, k) (:mod:`.batches`).

Data-parallel under ``torchrun`` (``RANK``/``WORLD_SIZE`` set): gloo on the
CPU, NCCL on CUDA; each process takes ``batch_size`` samples of every step's
global batch (``batch_size`` × processes); rank 0 writes the files.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import json
import math
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import nn

from genre_backend.config import GenreConfig, get_preset
from genre_backend.nets.model import GenRe, grow_refiner, load_model, with_inpaint_net, with_inpaint_net_of

from ..data.dataset import ViewDataset, split_views
from ..data.views import gather_views
from .batches import StepBatches, to_device
from .burst import Speed, apply_speed
from .checkpoint import checkpoint_model_config, cpu_seconds, load_checkpoint, same_nets, save_checkpoint
from .logs import LOG_FIELDS, plot_losses, trim_log
from .stage import StageModule
from .stop import StopSignals
from .train_config import TrainConfig

__all__ = ["train", "build_model", "weights_digest", "dist_info"]


def dist_info() -> tuple[int, int]:
    """(rank, world size) of this process: torchrun's ``RANK`` and ``WORLD_SIZE``, else (0, 1)."""
    return int(os.environ.get("RANK", "0")), int(os.environ.get("WORLD_SIZE", "1"))


def _device_and_group(tcfg: TrainConfig, world: int) -> torch.device:
    """The device this process trains on; joins the process group when ``world`` > 1."""
    device = torch.device(tcfg.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda: no CUDA device is available")
    if world > 1:
        import torch.distributed as dist

        if not dist.is_initialized():
            dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        if device.type == "cpu":
            torch.set_num_threads(max(1, (os.cpu_count() or 1) // world))
        elif device.index is None:
            device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
    return device


def build_model(tcfg: TrainConfig, model_config: GenreConfig | None = None) -> GenRe:
    """The model a stage starts from: ``--init``'s weights (else fresh ones of ``model_config`` or the preset),
    with ``--inpaint-from``'s inpainting net, the recipe's refiner branch, a fresh inpainting net of another head
    or widths (inpaint stage only), the checkpoint's config when resuming and the recipe's voxel target."""
    if tcfg.init:
        model = load_model(tcfg.init).train()
    else:
        model = GenRe(model_config or get_preset(tcfg.preset))
    if tcfg.inpaint_from:
        model = with_inpaint_net_of(model, load_model(tcfg.inpaint_from))
    if tcfg.refiner_full_nf is not None:
        # a recipe with a full-resolution refiner branch grows one on weights without it (same output at step 0)
        model = grow_refiner(model, tcfg.refiner_full_nf)
    fresh = with_inpaint_net(model, head=tcfg.inpaint_head, widths=tcfg.inpaint_widths)  # the model itself when they match
    if fresh is not model:
        if tcfg.stage != "inpaint":
            want, have = fresh.config.network, model.config.network
            raise ValueError(f"the {tcfg.stage} stage needs an inpainting net with head {want.inpaint_head!r} and widths "
                             f"{want.inpaint_widths}; the model has {have.inpaint_head!r} and {have.inpaint_widths}: "
                             f"train the inpaint stage first")
        model = fresh  # a fresh inpainting net; the other nets kept
    resumed = checkpoint_model_config(Path(tcfg.out) / tcfg.stage)
    if resumed is not None and same_nets(resumed, model.config):
        # a resumed stage keeps the config it was trained with (threshold, target...), whatever --init says
        # now (the chain names --init only for a stage's first run); other nets: the checkpoint load says so
        model.config = resumed
    if tcfg.target is not None and model.config.geometry.target != tcfg.target:
        # a change of representation: the nets are the same, the refiner learns the new target
        geometry = dataclasses.replace(model.config.geometry, target=tcfg.target)
        model.config = dataclasses.replace(model.config, geometry=geometry)
    return model


def _datasets(tcfg: TrainConfig, config: GenreConfig) -> tuple[ViewDataset, ViewDataset | None, float]:
    """(training set, validation set or None, the photo share in force) of ``--data``'s views, split by shape."""
    shape_ids = None
    if tcfg.shapes:
        shape_ids = {line.strip() for line in Path(tcfg.shapes).read_text().splitlines() if line.strip()}
    need_targets = tcfg.stage != "depth"  # the depth stage needs only the renders
    folders = tcfg.data if isinstance(tcfg.data, list) else [tcfg.data]
    train_refs, val_refs = split_views(gather_views(folders, shape_ids, targets=need_targets), tcfg.val_fraction)
    # photo compositing: every stage feeds the RGB image to a net (the depth net, or the 1-step baseline), so a stage
    # whose photo_fraction is set composites that share over photographs (the recipes set it for depth and joint;
    # --photo-fraction on refine shows the frozen depth net photo-like images, as on a user's photo)
    photo = tcfg.photo_fraction if tcfg.augment else 0.0
    bank = None
    if photo > 0:
        from ..data.photo_backgrounds import BackgroundBank

        if not tcfg.backgrounds:
            raise ValueError(f"photo_fraction {photo} needs --backgrounds DIR (a 'genre data backgrounds' folder, "
                             f"e.g. $GENRE_HOME/backgrounds)")
        bank = BackgroundBank(tcfg.backgrounds)
    train_set = ViewDataset(train_refs, config, augment=tcfg.augment and (tcfg.stage == "depth" or photo > 0),
                            targets=need_targets, backgrounds=bank, photo_fraction=photo,
                            mirror=tcfg.mirror if tcfg.augment else 0.0, stretch=tcfg.stretch if tcfg.augment else 0.0,
                            backdrop=tcfg.backdrop if tcfg.augment else 0.0, depth_only=tcfg.depth_only,
                            true_map=tcfg.true_map)
    # validated on the picture the nets are shown in use (painted when the model paints: genre eval, reconstruct)
    val_set = ViewDataset(val_refs, config, targets=need_targets, depth_only=tcfg.depth_only,
                          plain_backdrop=config.geometry.plain_backdrop, true_map=tcfg.true_map) if val_refs else None
    for name in ("depth_only", "true_map"):
        if getattr(tcfg, name) is not None and not getattr(train_set, name):
            raise ValueError(f"{name}: no complete training views (render + targets) in {getattr(tcfg, name)}")
    return train_set, val_set, photo


class _StageLog:
    """Rank 0's ``log.csv`` and TensorBoard writer, opened at step ``start`` (rows after it dropped first)."""

    def __init__(self, stage_dir: Path, stage: str, start: int):
        from torch.utils.tensorboard import SummaryWriter

        self.stage = stage
        self.writer = SummaryWriter(str(stage_dir / "tb"), purge_step=start)
        # resuming: the rows of the steps after the checkpoint are run (and logged) again, so they go
        new_log = start == 0 or not trim_log(stage_dir / "log.csv", start)
        self.file = (stage_dir / "log.csv").open("w" if new_log else "a", newline="", encoding="utf-8")
        self.rows = csv.DictWriter(self.file, fieldnames=LOG_FIELDS)
        if new_log:
            self.rows.writeheader()

    def train_row(self, done: int, loss: float, terms: dict[str, torch.Tensor], lr: float, s_per_step: float,
                  samples_per_s: float) -> None:
        terms = {k: float(v.detach()) for k, v in terms.items()}
        self.rows.writerow({"step": done, "split": "train", "loss": f"{loss:.6g}",
                            "terms": json.dumps({k: round(v, 6) for k, v in terms.items()}), "lr": f"{lr:.6g}",
                            "s_per_step": f"{s_per_step:.4f}", "samples_per_s": f"{samples_per_s:.3f}"})
        self.file.flush()
        self.writer.add_scalar(f"{self.stage}/train_loss", loss, done)
        for k, v in terms.items():
            self.writer.add_scalar(f"{self.stage}/{k}", v, done)

    def val_row(self, done: int, loss: float, lr: float) -> None:
        self.rows.writerow({"step": done, "split": "val", "loss": f"{loss:.6g}", "terms": "{}", "lr": f"{lr:.6g}",
                            "s_per_step": "", "samples_per_s": ""})
        self.file.flush()
        self.writer.add_scalar(f"{self.stage}/val_loss", loss, done)

    def close(self) -> None:
        self.writer.close()
        self.file.close()


@dataclass
class _Run:
    """One stage's run in progress: what the steps read, and what they update (``best``, the losses, the timings)."""

    tcfg: TrainConfig
    rank: int
    world: int
    device: torch.device
    module: StageModule
    net: nn.Module  # the module, or its DistributedDataParallel wrapper
    opt: torch.optim.Optimizer
    stage_dir: Path
    train_set: ViewDataset
    val_set: ViewDataset | None
    photo: float
    start: int
    best: float
    cpu_before: float  # the processor seconds of the runs this one resumes
    cpu_start: float = field(default_factory=cpu_seconds)
    first_loss: float | None = None
    last_loss: float | None = None
    step_times: list[float] = field(default_factory=list)
    stopped: int = 0  # the signal that stopped the run before its last step (0: none)
    stopped_at: int = 0  # the step its checkpoint holds then

    def cpu_total(self) -> float:
        """This stage's processor seconds so far, over every run that resumed it (this process's)."""
        return self.cpu_before + cpu_seconds() - self.cpu_start

    def validate(self) -> float:
        """The mean loss over the first ``val_samples`` validation views, one at a time, in evaluation mode."""
        module, n = self.module, min(len(self.val_set), self.tcfg.val_samples)
        module.eval()
        total, count = 0.0, 0
        with torch.no_grad():
            for i in range(n):
                b = {k: v[None].to(self.device) for k, v in self.val_set.sample(i, None).items()}
                total += float(module(b)[0])
                count += 1
        module.train()
        return total / max(count, 1)


def _start(tcfg: TrainConfig, model_config: GenreConfig | None) -> _Run:
    """Everything a stage's steps need, in the order that fixes the random numbers (the seed, then the model)."""
    rank, world = dist_info()
    device = _device_and_group(tcfg, world)
    torch.manual_seed(tcfg.seed)
    model = build_model(tcfg, model_config)
    # the nets run as measured fastest on this device (genre bench train), or as --speed says
    speed = Speed.for_device(device) if tcfg.speed == "auto" else Speed.from_way(tcfg.speed)
    module = StageModule(model, tcfg.stage, tcfg.surface_weight, tcfg.sph_loss, tcfg.depth_weight,
                         tcfg.sph_teacher, tcfg.depth_dropout, tcfg.depth_gradient_weight, tcfg.outline_weight,
                         speed, tcfg.hull_grad_width, tcfg.depth_lr_scale, tcfg.normals_weight,
                         tcfg.depth_offset_weight).to(device)
    apply_speed(model, speed)
    if speed.depth_channels_last:  # a training-only head on the depth net's features runs as the depth net does
        module.aux.to(memory_format=torch.channels_last)
    opt = speed.optimiser(module.param_groups(tcfg.weight_decay), tcfg.learning_rate, (tcfg.beta1, tcfg.beta2),
                          tcfg.weight_decay)
    stage_dir = Path(tcfg.out) / tcfg.stage
    if rank == 0:
        stage_dir.mkdir(parents=True, exist_ok=True)
        resolved = {"train": dataclasses.asdict(tcfg), "speed": dataclasses.asdict(speed), "model": model.config.to_dict()}
        (stage_dir / "config.json").write_text(json.dumps(resolved, indent=2))
    start, best, cpu_before = load_checkpoint(stage_dir, module, opt)
    cpu_start = cpu_seconds()
    train_set, val_set, photo = _datasets(tcfg, model.config)
    net = module
    if world > 1:
        net = nn.parallel.DistributedDataParallel(module, device_ids=[device.index] if device.type == "cuda" else None)
    return _Run(tcfg, rank, world, device, module, net, opt, stage_dir, train_set, val_set, photo, start, best,
                cpu_before, cpu_start)


def _step(run: _Run, step: int, batch: dict[str, torch.Tensor]) -> tuple[float, dict[str, torch.Tensor], float]:
    """One optimiser step on ``batch`` (B samples); returns (loss, its logged terms, the learning rate used)."""
    lr_now = run.tcfg.lr_at(step)
    for group in run.opt.param_groups:
        group["lr"] = lr_now * group.get("lr_scale", 1.0)
    loss, terms = run.net(to_device(batch, run.device))
    run.opt.zero_grad(set_to_none=True)
    loss.backward()
    run.opt.step()
    lv = float(loss.detach())
    if not math.isfinite(lv):
        raise FloatingPointError(f"loss became {lv} at step {step}; lower the learning rate")
    run.first_loss = lv if run.first_loss is None else run.first_loss
    run.last_loss = lv
    return lv, terms, lr_now


def _validate_and_keep_best(run: _Run, log: _StageLog, done: int, lr_now: float) -> None:
    """Rank 0, every ``val_every`` steps and at the last: the validation loss, and ``best.safetensors`` when lower."""
    v = run.validate()
    log.val_row(done, v, lr_now)
    if v < run.best:
        run.best = v
        extra = {"stage": run.tcfg.stage, "step": done, "val_loss": v, "cpu_s": round(run.cpu_total(), 1)}
        run.module.save_weights(run.stage_dir / "best.safetensors", extra)


def _run_steps(run: _Run) -> None:
    """Steps ``start`` … ``steps`` − 1: train, and on rank 0 log, validate, keep the best and checkpoint."""
    tcfg = run.tcfg
    loader = torch.utils.data.DataLoader(StepBatches(run.train_set, tcfg.batch_size, run.rank, run.world, tcfg.seed),
                                         batch_size=None, sampler=range(run.start, tcfg.steps), num_workers=tcfg.workers)
    log = _StageLog(run.stage_dir, tcfg.stage, run.start) if run.rank == 0 else None
    from tqdm import tqdm

    bar = tqdm(total=tcfg.steps, initial=run.start, desc=f"train {tcfg.stage}", unit="step",
               disable=run.rank != 0 or not tcfg.progress, dynamic_ncols=True)
    last_ckpt = time.monotonic()
    window_t, window_n = time.perf_counter(), 0
    run.module.train()
    with StopSignals() as stop:
        for step, batch in zip(range(run.start, tcfg.steps), loader):
            t0 = time.perf_counter()
            lv, terms, lr_now = _step(run, step, batch)
            run.step_times.append(time.perf_counter() - t0)
            window_n += 1
            done = step + 1
            signum = stop.agreed(run.world, run.device) if done < tcfg.steps else 0  # (every rank leaves at one step)
            if signum:
                run.stopped, run.stopped_at = signum, done
            if run.rank == 0:
                window_t, window_n, last_ckpt = _after_step(run, log, bar, done, lv, terms, lr_now, window_t, window_n,
                                                            last_ckpt)
            if signum:
                break
    bar.close()
    if log is not None:
        log.close()


def _after_step(run: _Run, log: _StageLog, bar, done: int, lv: float, terms: dict, lr_now: float, window_t: float,
                window_n: int, last_ckpt: float) -> tuple[float, int, float]:
    """Rank 0 after step ``done``: the progress bar, log.csv, validation, snapshots and the checkpoint (also when
    a signal stops the run here).  Returns the new (window_t, window_n, last_ckpt)."""
    tcfg = run.tcfg
    bar.update(1)
    bar.set_postfix(loss=f"{lv:.4g}")
    if done % tcfg.log_every == 0 or done == tcfg.steps:
        dt = (time.perf_counter() - window_t) / window_n
        log.train_row(done, lv, terms, lr_now, dt, tcfg.batch_size * run.world / dt)
        window_t, window_n = time.perf_counter(), 0
    if run.val_set is not None and (done % tcfg.val_every == 0 or done == tcfg.steps):
        _validate_and_keep_best(run, log, done, lr_now)
    if tcfg.snapshot_every and done % tcfg.snapshot_every == 0:  # weights to average later (training/learn/average.py)
        extra = {"stage": tcfg.stage, "step": done, "cpu_s": round(run.cpu_total(), 1)}
        (run.stage_dir / "snapshots").mkdir(exist_ok=True)
        run.module.save_weights(run.stage_dir / "snapshots" / f"step_{done:07d}.safetensors", extra)
    due = time.monotonic() - last_ckpt > 60 * tcfg.checkpoint_minutes
    if due or (tcfg.checkpoint_every and done % tcfg.checkpoint_every == 0) or done == tcfg.steps or run.stopped:
        save_checkpoint(run.stage_dir, run.module, run.opt, done, run.best, tcfg, run.cpu_total())
        plot_losses(run.stage_dir / "log.csv", run.stage_dir / "loss.png", tcfg.stage)
        last_ckpt = time.monotonic()
    return window_t, window_n, last_ckpt


def _summary_head(run: _Run) -> dict:
    """What every stage summary starts with, finished or stopped."""
    tcfg = run.tcfg
    return {"stage": tcfg.stage, "steps": tcfg.steps, "resumed_from": run.start, "world_size": run.world,
            "cpu_s": round(run.cpu_total(), 1), "photo_fraction": run.photo}


def _finish(run: _Run) -> dict:
    """Rank 0: ``final.safetensors`` (and ``best`` when nothing was held out), ``loss.png`` and ``summary.json``.
    Returns the summary (every rank)."""
    tcfg, stage_dir = run.tcfg, run.stage_dir
    summary = _summary_head(run)
    if run.rank != 0:
        return summary
    run.module.save_weights(stage_dir / "final.safetensors",
                            {"stage": tcfg.stage, "step": tcfg.steps, "cpu_s": round(run.cpu_total(), 1)})
    if run.val_set is None:  # no held-out shapes: the final weights are the best we know
        shutil.copyfile(stage_dir / "final.safetensors", stage_dir / "best.safetensors")
        shutil.copyfile(stage_dir / "final.json", stage_dir / "best.json")
    plot_losses(stage_dir / "log.csv", stage_dir / "loss.png", tcfg.stage)
    if run.step_times:
        med = sorted(run.step_times)[len(run.step_times) // 2]
        summary.update(s_per_step=round(med, 4), samples_per_s=round(tcfg.batch_size * run.world / med, 2),
                       first_loss=run.first_loss, last_loss=run.last_loss,
                       best_val=None if math.isinf(run.best) else run.best, train_views=len(run.train_set),
                       val_views=len(run.val_set) if run.val_set else 0)
    (stage_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def _agree_across_ranks(run: _Run, summary: dict) -> None:
    """Several processes: every rank takes rank 0's batch-norm statistics; the parameter and weight digests of
    every rank go into the summary (rank 0 rewrites ``summary.json``)."""
    import torch.distributed as dist

    # parameters agree by construction (all-reduced gradients); batch-norm running
    # statistics are per process, so every rank takes rank 0's (the saved ones)
    net_saved = run.module.model if run.module.baseline is None else run.module.baseline
    param_digests = [None] * run.world
    dist.all_gather_object(param_digests, weights_digest(net_saved, buffers=False))
    summary["rank_param_digests"] = param_digests
    for buf in net_saved.buffers():
        dist.broadcast(buf, 0)
    digests = [None] * run.world
    dist.all_gather_object(digests, weights_digest(net_saved))
    summary["rank_digests"] = digests
    if run.rank == 0:
        (run.stage_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    dist.barrier()


def train(tcfg: TrainConfig, model_config: GenreConfig | None = None) -> dict:
    """Run (or resume) one stage; returns a summary with timings and losses.  SIGINT or SIGTERM stops it after the
    step in progress with a checkpoint of that step and no final weights; the summary then has ``stopped``."""
    import torch.distributed as dist

    # a process group this call joins, it leaves: one left to the interpreter's exit can abort the process
    # (gloo's threads outlive Python; "terminate called without an active exception", SIGABRT)
    joins_group = dist_info()[1] > 1 and not dist.is_initialized()
    try:
        run = _start(tcfg, model_config)
        _run_steps(run)
        if run.stopped:  # SIGINT/SIGTERM: the checkpoint holds the last step; the same command resumes from it
            return {**_summary_head(run), "stopped": f"signal {run.stopped}", "signal": run.stopped,
                    "checkpoint_step": run.stopped_at}
        summary = _finish(run)
        if run.world > 1:
            _agree_across_ranks(run, summary)
        return summary
    finally:
        if joins_group and dist.is_initialized():
            dist.destroy_process_group()


def weights_digest(model: nn.Module, buffers: bool = True) -> str:
    """SHA-256 of every parameter (and buffer), to compare the weights of processes."""
    h = hashlib.sha256()
    items = model.state_dict().items() if buffers else model.named_parameters()
    for name, t in sorted(items):
        h.update(name.encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()
