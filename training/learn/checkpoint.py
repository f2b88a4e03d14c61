"""A stage's checkpoint: its trained weights, the optimiser's state, the step, the best validation loss and the
processor time so far, written atomically (``OUT/STAGE/checkpoint/``: ``state.safetensors`` + ``state.json``)."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from genre_backend.config import GenreConfig
from genre_backend.io import _UMASK

if TYPE_CHECKING:
    from .stage import StageModule
    from .train_config import TrainConfig

__all__ = ["CheckpointMismatch", "cpu_seconds", "save_checkpoint", "load_checkpoint", "checkpoint_model_config", "same_nets"]


class CheckpointMismatch(ValueError):
    """A stage's checkpoint does not fit the model being trained (architecture or stage changed)."""


def cpu_seconds() -> float:
    """Processor time (user + system, all threads) of this process so far."""
    import resource

    use = resource.getrusage(resource.RUSAGE_SELF)
    return use.ru_utime + use.ru_stime


def save_checkpoint(stage_dir: Path, module: StageModule, opt: torch.optim.Optimizer, step: int, best: float, tcfg: TrainConfig,
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


def checkpoint_model_config(stage_dir: Path) -> GenreConfig | None:
    """The model config a stage's checkpoint was written with (None without a readable one)."""
    for ck in [stage_dir / "checkpoint", *sorted(stage_dir.glob("checkpoint.old-*"))]:
        try:
            return GenreConfig.from_dict(json.loads((ck / "state.json").read_text())["model_config"])
        except (OSError, ValueError, KeyError, TypeError):
            continue
    return None


def same_nets(a: GenreConfig, b: GenreConfig) -> bool:
    """Whether two configs build networks with the same tensors (widths and resolutions)."""
    ga, gb = a.geometry, b.geometry
    return a.network == b.network and (ga.image_size, ga.sph_size, ga.sph_pad, ga.voxel_size) == (gb.image_size, gb.sph_size, gb.sph_pad, gb.voxel_size)


def load_checkpoint(stage_dir: Path, module: StageModule, opt: torch.optim.Optimizer) -> tuple[int, float, float]:
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
