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

Each stage writes ``OUT/STAGE/``: ``best.safetensors`` (lowest validation
loss) and ``final.safetensors`` (weights + config, no pickle), ``config.json``
(the resolved training config), ``log.csv``, ``tb/`` (TensorBoard),
``loss.png`` and ``checkpoint/`` (weights, optimiser state, step: written
atomically every ``checkpoint_minutes``).  Running the same command again
resumes from the checkpoint with the same step count and, on the CPU, the
same numbers: the batch of step k and its augmentation depend only on
(seed, k).  The steps a killed run did after its last checkpoint run again;
their rows are first dropped from ``log.csv`` (one row per step and split).

Data-parallel: ``torchrun --nproc_per_node=N -m genre_backend.cli train …``
(gloo on the CPU, NCCL on CUDA); each process takes its share of every
global batch, rank 0 writes the files.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import hashlib
import json
import math
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from genre_backend.config import INPAINT_HEADS, PRESETS, TARGETS, GenreConfig, get_preset
from genre_backend.nets.model import GenRe, grow_refiner, load_model, save_model, with_inpaint_net, with_inpaint_net_of
from genre_backend.geometry.spherical import crop_sph, pad_sph
from genre_backend.io import _UMASK, atomic_write, atomic_write_bytes

from ..data.dataset import ViewDataset, split_views
from ..data.views import gather_views
from .losses import DEPTH_GRADIENT_STRIDES, depth_gradient_loss, sph_loss, voxel_loss
from .recipe import RECIPES, STAGES, StageRecipe, get_recipe

__all__ = ["STAGES", "TrainConfig", "StageModule", "train", "weights_digest", "main", "depth_gradient_loss",
           "DEPTH_GRADIENT_STRIDES"]

BASELINE_STAGES = ("completion", "onestep")


@dataclass
class TrainConfig:
    """Everything one training stage needs; saved beside every checkpoint."""

    stage: str
    data: str | list[str]  # folder(s) of rendered views with targets
    out: str  # run folder; the stage writes OUT/STAGE/
    recipe: str = "paper"  # training/learn/recipe.py: every None below comes from it
    preset: str | None = None  # used only when not starting from --init weights
    init: str | None = None  # weights to start from (the previous stage's best)
    steps: int | None = None
    batch_size: int | None = None  # per process
    lr: float | None = None
    beta1: float | None = None
    beta2: float | None = None
    surface_weight: float | None = None
    photo_fraction: float | None = None
    sph_loss: str | None = None
    depth_weight: float | None = None
    depth_gradient_weight: float | None = None  # depth, joint: the depth error's gradient matching term's weight
    lr_halflife: int | None = None
    sph_teacher: float | None = None  # refine: the share of samples fed the true full map (teacher forcing)
    depth_dropout: float | None = None  # refine, joint: the share of samples whose depth voxels are emptied
    mirror: float | None = None  # every stage: the share of training samples reflected left to right
    target: str | None = None  # the voxel representation to train (GeometryConfig.target); None: the recipe's, else the model's
    refiner_full_nf: int | None = None  # the refiner's full-resolution branch (NetworkConfig.refiner_full_nf); None: the recipe's, else the model's
    # the inpainting net's head (NetworkConfig.inpaint_head) and its four widths ("32,64,128,256";
    # NetworkConfig.inpaint_widths); None: the model's.  Another head or other widths than the model's give a
    # fresh inpainting net at the inpaint stage (nets.model.with_inpaint_net); other stages refuse them.
    inpaint_head: str | None = None
    inpaint_widths: str | tuple[int, ...] | None = None
    # weights whose trained inpainting net replaces --init's (nets.model.with_inpaint_net_of), e.g. a wider net
    # trained in another run put under later weights' depth net and refiner (a resumed stage: the checkpoint wins, as for --init)
    inpaint_from: str | None = None
    backgrounds: str | None = None  # a 'genre data backgrounds' folder (needed when photo_fraction > 0)
    val_fraction: float = 0.05
    val_every: int = 200
    val_samples: int = 48
    checkpoint_minutes: float = 3.0
    checkpoint_every: int = 0  # also every this many steps (0: off)
    log_every: int = 10
    seed: int = 0
    workers: int = 0
    device: str = "cpu"
    shapes: str | None = None  # optional file with one shape id per line (e.g. the seen-train split)
    augment: bool = True
    progress: bool = True

    def __post_init__(self):
        if self.stage not in STAGES:
            raise ValueError(f"stage must be one of {STAGES}, got {self.stage!r}")
        recipe = get_recipe(self.recipe)
        if self.preset is None:
            self.preset = recipe.preset
        given = {k: getattr(self, k) for k in StageRecipe.keys() if getattr(self, k) is not None}
        resolved = dataclasses.replace(recipe.stage(self.stage), **given)  # (validates the values)
        for k in StageRecipe.keys():
            setattr(self, k, getattr(resolved, k))
        if self.sph_teacher > 0 and self.stage != "refine":
            raise ValueError(f"sph_teacher: only the refine stage feeds the true map, not {self.stage!r}")
        if self.depth_dropout > 0 and self.stage not in ("refine", "joint"):
            raise ValueError(f"depth_dropout: only the refine and joint stages have depth voxels to empty, not {self.stage!r}")
        if isinstance(self.data, (list, tuple)):
            if not self.data:
                raise ValueError("data: expected at least one views folder")
            self.data = [str(d) for d in self.data]
        if self.target is None:
            self.target = recipe.target
        if self.target is not None and self.target not in TARGETS:
            raise ValueError(f"target: expected one of {TARGETS}, got {self.target!r}")
        if self.refiner_full_nf is None:
            self.refiner_full_nf = recipe.refiner_full_nf
        if self.refiner_full_nf is not None and (isinstance(self.refiner_full_nf, bool) or not isinstance(self.refiner_full_nf, int)
                                                 or self.refiner_full_nf < 0):
            raise ValueError(f"refiner_full_nf: expected an int >= 0, got {self.refiner_full_nf!r}")
        if self.inpaint_head is not None and self.inpaint_head not in INPAINT_HEADS:
            raise ValueError(f"inpaint_head: expected one of {INPAINT_HEADS}, got {self.inpaint_head!r}")
        if self.inpaint_widths is not None:
            given = self.inpaint_widths
            try:
                widths = tuple(int(w) for w in (given.split(",") if isinstance(given, str) else given))
            except (TypeError, ValueError):
                widths = ()
            if len(widths) != 4 or min(widths) < 1:
                raise ValueError(f"inpaint_widths: expected four positive ints (e.g. 32,64,128,256), got {given!r}")
            self.inpaint_widths = widths

    @property
    def learning_rate(self) -> float:
        return self.lr

    def lr_at(self, step: int) -> float:
        """The learning rate of step ``step`` (0-based): ``lr``, halved every ``lr_halflife`` steps when that is set."""
        return self.lr * 0.5 ** (step / self.lr_halflife) if self.lr_halflife else self.lr


class StageModule(nn.Module):
    """The model with one stage's trainable parts; ``forward(batch)`` returns (loss, logged terms)."""

    def __init__(self, model: GenRe, stage: str, surface_weight: float, sph_loss: str = "mse", depth_weight: float = 0.0,
                 sph_teacher: float = 0.0, depth_dropout: float = 0.0, depth_gradient_weight: float = 0.0):
        super().__init__()
        self.model, self.stage, self.surface_weight, self.sph_loss_kind = model, stage, surface_weight, sph_loss
        self.depth_weight = depth_weight  # the joint stage: the depth net's own loss, added with this weight
        self.depth_gradient_weight = depth_gradient_weight  # the depth loss's gradient matching term
        if sph_teacher > 0 and stage != "refine":
            raise ValueError(f"sph_teacher: only the refine stage feeds the true map (stage {stage!r})")
        if depth_dropout > 0 and stage not in ("refine", "joint"):
            raise ValueError(f"depth_dropout: only the refine and joint stages have depth voxels to empty (stage {stage!r})")
        # training batches only (StepBatches' per-sample "coin"): validation and inference see every input as it is
        self.sph_teacher, self.depth_dropout = sph_teacher, depth_dropout
        self.baseline = None
        if stage in BASELINE_STAGES:
            from .baselines import CompletionBaseline, OneStepNet

            self.baseline = (CompletionBaseline if stage == "completion" else OneStepNet)(model.config)
            if stage == "completion":  # the depth net it completes from: GenRe's (from --init), frozen
                self.baseline.depth_net.load_state_dict(model.depth_net.state_dict())
                # the completion net has the refiner's architecture and starts where GenRe's refiner
                # is: freshly initialised after the depth stage, or trained when continuing from full
                # weights, so that the two voxel nets always start level
                self.baseline.completion.load_state_dict(model.refiner.state_dict())
        trainable = {"depth": [model.depth_net], "inpaint": [model.inpaint_net], "refine": [model.refiner], "joint": [model],
                     "completion": [], "onestep": []}[stage]
        for p in model.parameters():
            p.requires_grad_(False)
        for part in trainable:
            for p in part.parameters():
                p.requires_grad_(True)
        self.frozen = [m for m in (model.depth_net, model.inpaint_net, model.refiner) if not any(p.requires_grad for p in m.parameters())]
        if stage == "completion":
            for p in self.baseline.depth_net.parameters():
                p.requires_grad_(False)
            self.frozen.append(self.baseline.depth_net)

    def checkpointed(self) -> tuple[str, nn.Module]:
        """The key prefix and module a checkpoint keeps: GenRe's nets, or for a baseline stage the
        baseline alone (so its checkpoint does not depend on GenRe's architecture)."""
        return ("model", self.model) if self.baseline is None else ("baseline", self.baseline)

    def save_weights(self, path: Path, extra: dict) -> None:
        """The stage's weights file: GenRe's format, or the baseline's for a baseline stage."""
        if self.baseline is None:
            save_model(self.model, path, extra)
        else:
            from .baselines import save_baseline

            save_baseline(self.baseline, path, extra)

    def train(self, mode: bool = True):
        super().train(mode)
        for m in self.frozen:
            m.eval()  # frozen nets keep their batch-norm statistics
        return self

    # ---- losses -------------------------------------------------------------------------
    def depth_loss(self, out, batch):
        valid = batch["depth"] > 0
        scale = self.model.config.network.depth_output_scale
        err = ((out["depth"] - batch["depth"]) * scale) ** 2
        l_depth = (err * valid).sum() / valid.sum().clamp(min=1)
        l_sil = F.binary_cross_entropy_with_logits(out["silhouette_logits"], batch["mask"].float())
        terms = {"depth_mse": l_depth, "silhouette_bce": l_sil}
        loss = l_depth + l_sil
        if self.depth_gradient_weight > 0:
            l_grad = depth_gradient_loss(out["depth"] * scale, batch["depth"] * scale, valid)
            terms["depth_gradient_l1"] = l_grad
            loss = loss + self.depth_gradient_weight * l_grad
        return loss, terms

    def sph_loss(self, parts: dict[str, torch.Tensor], batch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """:func:`training.learn.losses.sph_loss` of the inpainting net's ``parts`` against ``batch["full_sph"]``."""
        return sph_loss(parts, batch["full_sph"], self.model.config.geometry, self.sph_loss_kind)

    def voxel_loss(self, logits, batch):
        """:func:`training.learn.losses.voxel_loss` of the refiner's logits against ``batch["voxels"]``."""
        return voxel_loss(logits, batch["voxels"], self.surface_weight)

    def forward(self, batch: dict[str, torch.Tensor]):
        m = self.model
        if self.stage == "depth":
            return self.depth_loss(m.depth_net(batch["rgb"]), batch)
        if self.stage == "onestep":
            pad = m.config.geometry.sph_pad
            return self.sph_loss({"map": pad_sph(self.baseline(batch["rgb"])[:, None], pad)}, batch)
        if self.stage == "completion":
            b = self.baseline
            with torch.no_grad():
                depth = m.masked_depth(b.depth_net(batch["rgb"])["depth"], batch["mask"])
                vox_depth = b.depth_voxels(depth)
            return self.voxel_loss(b.complete(vox_depth), batch)
        with torch.set_grad_enabled(self.stage == "joint" and torch.is_grad_enabled()):
            depth_out = m.depth_net(batch["rgb"])
            depth = m.masked_depth(depth_out["depth"], batch["mask"])
            partial = m.partial_sph(depth)
        pad = m.config.geometry.sph_pad
        if self.stage == "inpaint":
            return self.sph_loss(m.inpaint_net.forward_parts(pad_sph(partial[:, None], pad)), batch)
        with torch.set_grad_enabled(self.stage == "joint" and torch.is_grad_enabled()):
            sph_parts = m.inpaint_net.forward_parts(pad_sph(partial[:, None], pad))
            full = crop_sph(sph_parts["map"], pad)[:, 0]
            if self.training and "coin" in batch and self.sph_teacher > 0:
                full = torch.where((batch["coin"][:, 0] < self.sph_teacher)[:, None, None], batch["full_sph"], full)
            vox_sph, vox_depth = m.sph_voxels(full), m.depth_voxels(depth)
        if self.training and "coin" in batch and self.depth_dropout > 0:
            keep = (batch["coin"][:, 1] >= self.depth_dropout).to(vox_depth.dtype)
            vox_depth = vox_depth * keep.view(-1, *([1] * (vox_depth.dim() - 1)))
        logits = m.refine(vox_sph, vox_depth)
        loss, terms = self.voxel_loss(logits, batch)
        if self.stage == "joint":
            l_sph, sph_terms = self.sph_loss(sph_parts, batch)
            terms.update(sph_terms)
            loss = loss + l_sph
            if self.depth_weight > 0:
                l_depth, depth_terms = self.depth_loss(depth_out, batch)
                terms.update(depth_terms)
                loss = loss + self.depth_weight * l_depth
        return loss, terms


# ---- deterministic batches ---------------------------------------------------------------
def _mix(*parts: int) -> int:
    return int.from_bytes(hashlib.sha256(repr(parts).encode()).digest()[:8], "big") & ((1 << 63) - 1)


class StepBatches(torch.utils.data.Dataset):
    """Item k is this process's share of the global batch of step k (so workers may prefetch)."""

    def __init__(self, data: ViewDataset, batch: int, rank: int, world: int, seed: int):
        self.data, self.batch, self.rank, self.world, self.seed = data, batch, rank, world, seed
        self._perms: dict[int, torch.Tensor] = {}

    def __len__(self) -> int:
        return 1 << 40

    def _index(self, g: int) -> int:
        n = len(self.data)
        epoch, pos = divmod(g, n)
        if epoch not in self._perms:
            self._perms = {epoch: torch.randperm(n, generator=torch.Generator().manual_seed(_mix(self.seed, epoch)))}
        return int(self._perms[epoch][pos])

    def __getitem__(self, step: int) -> dict[str, torch.Tensor]:
        first = (step * self.world + self.rank) * self.batch
        samples = [self.data.sample(self._index(g), _mix(self.seed, g, 1)) for g in range(first, first + self.batch)]
        out = {k: torch.stack([s[k] for s in samples]) for k in samples[0]}
        # two uniform numbers per sample for the stage's per-sample choices (StageModule: sph_teacher, depth_dropout)
        out["coin"] = torch.stack([torch.rand(2, generator=torch.Generator().manual_seed(_mix(self.seed, g, 2)))
                                   for g in range(first, first + self.batch)])
        return out


def _to(batch, device):
    return {k: v.to(device, non_blocking=True) for k, v in batch.items()}


# ---- checkpoints -------------------------------------------------------------------------
class CheckpointMismatch(ValueError):
    """A stage's checkpoint does not fit the model being trained (architecture or stage changed)."""


def _cpu_seconds() -> float:
    """Processor time (user + system, all threads) of this process so far."""
    import resource

    use = resource.getrusage(resource.RUSAGE_SELF)
    return use.ru_utime + use.ru_stime


def _save_checkpoint(stage_dir: Path, module: StageModule, opt: torch.optim.Optimizer, step: int, best: float, tcfg: TrainConfig,
                     cpu_s: float = 0.0) -> None:
    from safetensors.torch import save_file

    prefix, trained = module.checkpointed()
    tensors = {f"{prefix}.{k}": v.detach().cpu().contiguous() for k, v in trained.state_dict().items()}
    opt_state = opt.state_dict()
    scalars = {}
    for idx, st in opt_state["state"].items():
        for name, val in st.items():
            if torch.is_tensor(val):
                tensors[f"opt.{idx}.{name}"] = val.detach().cpu().contiguous()
            else:
                scalars[f"{idx}.{name}"] = val
    meta = {
        "step": step,
        "best_val": best,
        "cpu_s": cpu_s,  # the stage's processor seconds over every run so far
        "param_groups": opt_state["param_groups"],
        "opt_scalars": scalars,
        "model_config": module.model.config.to_dict(),
        "train_config": dataclasses.asdict(tcfg),
    }
    stage_dir.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f"checkpoint.tmp-{os.getpid()}-", dir=stage_dir))  # a fresh name, never a planted one
    os.chmod(tmp, 0o777 & ~_UMASK)  # mkdtemp makes 0700; the checkpoint gets the usual permissions
    save_file(tensors, str(tmp / "state.safetensors"))
    (tmp / "state.json").write_text(json.dumps(meta))
    final = stage_dir / "checkpoint"
    old = stage_dir / f"checkpoint.old-{os.getpid()}"
    if final.exists():
        os.replace(final, old)
    os.replace(tmp, final)  # the checkpoint is either the old or the new one, never half
    shutil.rmtree(old, ignore_errors=True)


def _checkpoint_model_config(stage_dir: Path) -> GenreConfig | None:
    """The model config a stage's checkpoint was written with (None without a readable one)."""
    for ck in [stage_dir / "checkpoint", *sorted(stage_dir.glob("checkpoint.old-*"))]:
        try:
            return GenreConfig.from_dict(json.loads((ck / "state.json").read_text())["model_config"])
        except (OSError, ValueError, KeyError, TypeError):
            continue
    return None


def _same_nets(a: GenreConfig, b: GenreConfig) -> bool:
    """Whether two configs build networks with the same tensors (widths and resolutions)."""
    ga, gb = a.geometry, b.geometry
    return a.network == b.network and (ga.image_size, ga.sph_size, ga.sph_pad, ga.voxel_size) == (gb.image_size, gb.sph_size, gb.sph_pad, gb.voxel_size)


def _load_checkpoint(stage_dir: Path, module: StageModule, opt: torch.optim.Optimizer) -> tuple[int, float, float]:
    from safetensors.torch import load_file

    ck = stage_dir / "checkpoint"
    if not (ck / "state.json").is_file():
        old = sorted(stage_dir.glob("checkpoint.old-*"))  # killed between the two renames
        if not old:
            return 0, math.inf, 0.0
        ck = old[-1]
    meta = json.loads((ck / "state.json").read_text())
    tensors = load_file(str(ck / "state.safetensors"))
    prefix, trained = module.checkpointed()  # older baseline checkpoints also hold "model." tensors: ignored
    try:
        trained.load_state_dict({k[len(prefix) + 1:]: v for k, v in tensors.items() if k.startswith(prefix + ".")})
        _load_optimizer(opt, tensors, meta)
    except (RuntimeError, ValueError, KeyError) as exc:
        why = " ".join(str(exc).split())[:300] or type(exc).__name__
        raise CheckpointMismatch(
            f"{ck} was written for a different model or optimiser than this run's ({why}); "
            f"to train the {module.stage} stage afresh, delete {ck} (or pass another --out)"
        ) from exc
    return int(meta["step"]), float(meta["best_val"]), float(meta.get("cpu_s", 0.0))


def _load_optimizer(opt: torch.optim.Optimizer, tensors: dict[str, torch.Tensor], meta: dict) -> None:
    state: dict[int, dict] = {}
    for k, v in tensors.items():
        if k.startswith("opt."):
            _, idx, name = k.split(".", 2)
            state.setdefault(int(idx), {})[name] = v
    for k, v in meta["opt_scalars"].items():
        idx, name = k.split(".", 1)
        state.setdefault(int(idx), {})[name] = v
    groups = meta["param_groups"]
    for saved, current in zip(groups, opt.param_groups):
        # this run's settings win over the checkpoint's: a stage continued with another --lr (or betas)
        # trains with it, as log.csv says (the Adam moments carry on)
        saved["lr"], saved["betas"] = current["lr"], current["betas"]
    opt.load_state_dict({"state": state, "param_groups": groups})


LOG_FIELDS = ["step", "split", "loss", "terms", "lr", "s_per_step", "samples_per_s"]  # log.csv's columns


def _trim_log(csv_path: Path, step: int) -> bool:
    """Keep only ``log.csv``'s rows up to ``step`` (the checkpoint a run resumes from); atomically.

    A run killed between two checkpoints has logged steps past the last one;
    the resumed run logs them again, so without this they would appear twice.
    Rows up to ``step`` were all written (and flushed) before that checkpoint
    was saved.  A last line without its newline (a kill mid-write) is dropped
    too.  Returns False when there is no usable log (no file, or another
    header): the caller then starts a new one.
    """
    try:
        text = csv_path.read_bytes().decode("utf-8", "surrogateescape")
    except FileNotFoundError:
        return False
    parts = text.split("\n")  # the csv module ends rows with \r\n: kept as they are
    lines = [p + "\n" for p in parts[:-1]] + ([parts[-1]] if parts[-1] else [])
    header = ",".join(LOG_FIELDS) + "\n"
    if not lines or lines[0].replace("\r\n", "\n") != header:
        return False
    kept = [lines[0]]
    for line in lines[1:]:
        if not line.endswith("\n"):
            break  # cut off by the kill: nothing after it was written
        row = next(csv.reader([line]), [])
        if len(row) == len(LOG_FIELDS) and row[0].isdigit() and int(row[0]) <= step:
            kept.append(line)
    if len(kept) < len(lines):
        atomic_write_bytes(csv_path, "".join(kept).encode("utf-8", "surrogateescape"))
    return True


def _plot_losses(csv_path: Path, png_path: Path, stage: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = list(csv.DictReader(csv_path.open()))
    if not rows:
        return
    fig, ax = plt.subplots(figsize=(7, 4))
    for split, style in (("train", "-"), ("val", "o-")):
        pts = [(int(r["step"]), float(r["loss"])) for r in rows if r["split"] == split]
        if pts:
            ax.plot(*zip(*pts), style, label=split, markersize=3)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_title(f"GenRe training: {stage} stage")
    ax.legend()
    fig.tight_layout()
    atomic_write(png_path, lambda fh: fig.savefig(fh, format="png", dpi=90))
    plt.close(fig)


# ---- the loop ----------------------------------------------------------------------------
def _dist_info() -> tuple[int, int]:
    return int(os.environ.get("RANK", "0")), int(os.environ.get("WORLD_SIZE", "1"))


def train(tcfg: TrainConfig, model_config: GenreConfig | None = None) -> dict:
    """Run (or resume) one stage; returns a summary with timings and losses."""
    rank, world = _dist_info()
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
    torch.manual_seed(tcfg.seed)
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
    resumed = _checkpoint_model_config(Path(tcfg.out) / tcfg.stage)
    if resumed is not None and _same_nets(resumed, model.config):
        # a resumed stage keeps the config it was trained with (threshold, target...), whatever --init says
        # now (the chain names --init only for a stage's first run); other nets: the checkpoint load says so
        model.config = resumed
    if tcfg.target is not None and model.config.geometry.target != tcfg.target:
        # a change of representation: the nets are the same, the refiner learns the new target
        model.config = dataclasses.replace(model.config, geometry=dataclasses.replace(model.config.geometry, target=tcfg.target))
    config = model.config
    module = StageModule(model, tcfg.stage, tcfg.surface_weight, tcfg.sph_loss, tcfg.depth_weight,
                         tcfg.sph_teacher, tcfg.depth_dropout, tcfg.depth_gradient_weight).to(device)
    params = [p for p in module.parameters() if p.requires_grad]
    opt = torch.optim.Adam(params, lr=tcfg.learning_rate, betas=(tcfg.beta1, tcfg.beta2))

    stage_dir = Path(tcfg.out) / tcfg.stage
    if rank == 0:
        stage_dir.mkdir(parents=True, exist_ok=True)
        (stage_dir / "config.json").write_text(json.dumps({"train": dataclasses.asdict(tcfg), "model": config.to_dict()}, indent=2))
    start, best, cpu_before = (_load_checkpoint(stage_dir, module, opt) if (stage_dir / "checkpoint").exists()
                               or list(stage_dir.glob("checkpoint.old-*")) else (0, math.inf, 0.0))
    cpu_start = _cpu_seconds()

    def cpu_total() -> float:
        """This stage's processor seconds so far, over every run that resumed it (rank 0's process)."""
        return cpu_before + _cpu_seconds() - cpu_start

    shape_ids = None
    if tcfg.shapes:
        shape_ids = {line.strip() for line in Path(tcfg.shapes).read_text().splitlines() if line.strip()}
    need_targets = tcfg.stage != "depth"  # the depth stage needs only the renders
    folders = tcfg.data if isinstance(tcfg.data, list) else [tcfg.data]
    refs = gather_views(folders, shape_ids, targets=need_targets)
    train_refs, val_refs = split_views(refs, tcfg.val_fraction)
    # photo compositing: every stage feeds the RGB image to a net (the depth net, or the 1-step baseline), so a stage
    # whose photo_fraction is set composites that share over photographs (the recipes set it for depth and joint;
    # --photo-fraction on refine shows the frozen depth net photo-like images, as on a user's photo)
    photo = tcfg.photo_fraction if tcfg.augment else 0.0
    bank = None
    if photo > 0:
        from ..data.photo_backgrounds import BackgroundBank

        if not tcfg.backgrounds:
            raise ValueError(f"photo_fraction {photo} needs --backgrounds DIR (a 'genre data backgrounds' folder, e.g. $GENRE_HOME/backgrounds)")
        bank = BackgroundBank(tcfg.backgrounds)
    train_set = ViewDataset(train_refs, config, augment=tcfg.augment and (tcfg.stage == "depth" or photo > 0), targets=need_targets,
                            backgrounds=bank, photo_fraction=photo, mirror=tcfg.mirror if tcfg.augment else 0.0)
    val_set = ViewDataset(val_refs, config, targets=need_targets) if val_refs else None

    net = module
    if world > 1:
        net = nn.parallel.DistributedDataParallel(module, device_ids=[device.index] if device.type == "cuda" else None)
    loader = torch.utils.data.DataLoader(
        StepBatches(train_set, tcfg.batch_size, rank, world, tcfg.seed),
        batch_size=None,
        sampler=range(start, tcfg.steps),
        num_workers=tcfg.workers,
    )
    writer = None
    log = None
    if rank == 0:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(stage_dir / "tb"), purge_step=start)
        # resuming: the rows of the steps after the checkpoint are run (and logged) again, so they go
        new_log = start == 0 or not _trim_log(stage_dir / "log.csv", start)
        log = (stage_dir / "log.csv").open("w" if new_log else "a", newline="", encoding="utf-8")
        log_writer = csv.DictWriter(log, fieldnames=LOG_FIELDS)
        if new_log:
            log_writer.writeheader()
    from tqdm import tqdm

    bar = tqdm(total=tcfg.steps, initial=start, desc=f"train {tcfg.stage}", unit="step", disable=rank != 0 or not tcfg.progress, dynamic_ncols=True)
    last_ckpt = time.monotonic()
    window_t, window_n = time.perf_counter(), 0
    step_times = []
    first_loss = last_loss = None

    def validate() -> float:
        module.eval()
        total, count = 0.0, 0
        with torch.no_grad():
            for i in range(min(len(val_set), tcfg.val_samples)):
                b = {k: v[None].to(device) for k, v in val_set.sample(i, None).items()}
                total += float(module(b)[0])
                count += 1
        module.train()
        return total / max(count, 1)

    module.train()
    step = start
    for step, batch in zip(range(start, tcfg.steps), loader):
        t0 = time.perf_counter()
        lr_now = tcfg.lr_at(step)
        for group in opt.param_groups:
            group["lr"] = lr_now
        batch = _to(batch, device)
        loss, terms = net(batch)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        lv = float(loss.detach())
        if not math.isfinite(lv):
            raise FloatingPointError(f"loss became {lv} at step {step}; lower the learning rate")
        first_loss = lv if first_loss is None else first_loss
        last_loss = lv
        step_times.append(time.perf_counter() - t0)
        window_n += 1
        done = step + 1
        if rank == 0:
            bar.update(1)
            bar.set_postfix(loss=f"{lv:.4g}")
            if done % tcfg.log_every == 0 or done == tcfg.steps:
                dt = (time.perf_counter() - window_t) / window_n
                log_writer.writerow(
                    {"step": done, "split": "train", "loss": f"{lv:.6g}", "terms": json.dumps({k: round(float(v.detach()), 6) for k, v in terms.items()}),
                     "lr": f"{lr_now:.6g}", "s_per_step": f"{dt:.4f}", "samples_per_s": f"{tcfg.batch_size * world / dt:.3f}"}
                )
                log.flush()
                writer.add_scalar(f"{tcfg.stage}/train_loss", lv, done)
                for k, v in terms.items():
                    writer.add_scalar(f"{tcfg.stage}/{k}", float(v.detach()), done)
                window_t, window_n = time.perf_counter(), 0
            if val_set is not None and (done % tcfg.val_every == 0 or done == tcfg.steps):
                v = validate()
                log_writer.writerow({"step": done, "split": "val", "loss": f"{v:.6g}", "terms": "{}", "lr": f"{lr_now:.6g}", "s_per_step": "", "samples_per_s": ""})
                log.flush()
                writer.add_scalar(f"{tcfg.stage}/val_loss", v, done)
                if v < best:
                    best = v
                    module.save_weights(stage_dir / "best.safetensors", {"stage": tcfg.stage, "step": done, "val_loss": v,
                                                                         "cpu_s": round(cpu_total(), 1)})
            due = time.monotonic() - last_ckpt > 60 * tcfg.checkpoint_minutes
            if due or (tcfg.checkpoint_every and done % tcfg.checkpoint_every == 0) or done == tcfg.steps:
                _save_checkpoint(stage_dir, module, opt, done, best, tcfg, cpu_total())
                _plot_losses(stage_dir / "log.csv", stage_dir / "loss.png", tcfg.stage)
                last_ckpt = time.monotonic()
    bar.close()
    summary = {"stage": tcfg.stage, "steps": tcfg.steps, "resumed_from": start, "world_size": world, "cpu_s": round(cpu_total(), 1),
               "photo_fraction": photo}
    if rank == 0:
        module.save_weights(stage_dir / "final.safetensors", {"stage": tcfg.stage, "step": tcfg.steps, "cpu_s": round(cpu_total(), 1)})
        if val_set is None:  # no held-out shapes: the final weights are the best we know
            shutil.copyfile(stage_dir / "final.safetensors", stage_dir / "best.safetensors")
            shutil.copyfile(stage_dir / "final.json", stage_dir / "best.json")
        writer.close()
        log.close()
        _plot_losses(stage_dir / "log.csv", stage_dir / "loss.png", tcfg.stage)
        if step_times:
            med = sorted(step_times)[len(step_times) // 2]
            summary.update(
                s_per_step=round(med, 4),
                samples_per_s=round(tcfg.batch_size * world / med, 2),
                first_loss=first_loss,
                last_loss=last_loss,
                best_val=None if math.isinf(best) else best,
                train_views=len(train_set),
                val_views=len(val_set) if val_set else 0,
            )
        (stage_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    if world > 1:
        import torch.distributed as dist

        # parameters agree by construction (all-reduced gradients); batch-norm running
        # statistics are per process, so every rank takes rank 0's (the saved ones)
        net_saved = model if module.baseline is None else module.baseline
        param_digests = [None] * world
        dist.all_gather_object(param_digests, weights_digest(net_saved, buffers=False))
        summary["rank_param_digests"] = param_digests
        for buf in net_saved.buffers():
            dist.broadcast(buf, 0)
        digests = [None] * world
        dist.all_gather_object(digests, weights_digest(net_saved))
        summary["rank_digests"] = digests
        if rank == 0:
            (stage_dir / "summary.json").write_text(json.dumps(summary, indent=2))
        dist.barrier()
    return summary


def weights_digest(model: nn.Module, buffers: bool = True) -> str:
    """SHA-256 of every parameter (and buffer), to compare the weights of processes."""
    h = hashlib.sha256()
    items = model.state_dict().items() if buffers else model.named_parameters()
    for name, t in sorted(items):
        h.update(name.encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def main(argv: list[str] | None = None, prog: str = "genre train") -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["burst"]:  # the GPU burst (training/learn/burst.py): its own options
        from . import burst

        return burst.main(argv[1:], prog=f"{prog} burst")
    parser = argparse.ArgumentParser(prog=prog, description="Train one GenRe stage (resumes automatically; "
                                     "'genre train burst --help': a GPU burst from a training pack).")
    parser.add_argument("stage", choices=STAGES)
    parser.add_argument("--data", required=True, nargs="+",
                        help="folder(s) of rendered views with targets ('genre data render' + 'genre data targets'); a folder "
                             "named twice is drawn twice as often (the mix of a run)")
    parser.add_argument("--out", required=True, help="run folder; this stage writes OUT/STAGE/")
    parser.add_argument("--init", help="weights to start from (e.g. OUT/depth/best.safetensors); default: fresh weights of --preset")
    parser.add_argument("--recipe", choices=sorted(RECIPES), default="paper",
                        help="named training recipe (training/learn/recipe.py); the options below override its values")
    parser.add_argument("--preset", choices=sorted(PRESETS), default=None, help="model preset (default: the recipe's)")
    parser.add_argument("--model-config", help="JSON file of a model config (GenreConfig.to_dict) instead of --preset")
    parser.add_argument("--shapes", help="file listing the shape ids to train on (default: every shape in --data)")
    for f in dataclasses.fields(TrainConfig):
        if f.name in ("stage", "data", "out", "recipe", "init", "preset", "shapes", "augment", "progress"):
            continue
        kind = float if f.type in ("float", "float | None") else (int if f.type in ("int", "int | None") else str)
        default = "the recipe's" if f.default is None and f.name in StageRecipe.keys() else f.default
        parser.add_argument("--" + f.name.replace("_", "-"), type=kind, default=f.default, help=f"default: {default}")
    parser.add_argument("--no-augment", action="store_true")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--dry-run", action="store_true", help="print the resolved settings as JSON and exit (nothing is read or written)")
    args = parser.parse_args(argv)
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(TrainConfig) if f.name not in ("augment", "progress")}
    try:
        tcfg = TrainConfig(**values, augment=not args.no_augment, progress=not args.no_progress)
    except ValueError as exc:
        parser.error(str(exc))
    if args.dry_run:
        print(json.dumps(dataclasses.asdict(tcfg), sort_keys=True))
        return 0
    for name in ("init", "inpaint_from"):
        if getattr(tcfg, name) and not Path(getattr(tcfg, name)).is_file():
            parser.error(f"--{name.replace('_', '-')}: no such weights file: {getattr(tcfg, name)}")
    model_config = None
    if args.model_config:
        try:
            model_config = GenreConfig.from_dict(json.loads(Path(args.model_config).read_text()))
        except (OSError, ValueError) as exc:
            parser.error(f"--model-config: {exc}")
    try:
        summary = train(tcfg, model_config)
    except CheckpointMismatch as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    if _dist_info()[0] == 0:
        print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
