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
from genre_backend.atomic import _UMASK

if TYPE_CHECKING:
    from .stage import StageModule
    from .train_config import TrainConfig

__all__ = ["CheckpointMismatch", "cpu_seconds", "save_checkpoint", "load_checkpoint", "checkpoint_model_config", "same_nets",
           "optimizer_tensors", "optimizer_state", "write_state", "read_state"]


class CheckpointMismatch(ValueError):
    """A stage's checkpoint does not fit the model being trained (architecture or stage changed)."""


def cpu_seconds() -> float:
    """Processor time (user + system, all threads) of this process so far."""
    import resource

    use = resource.getrusage(resource.RUSAGE_SELF)
    return use.ru_utime + use.ru_stime


def optimizer_tensors(opt: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], dict]:
    """The optimiser's state as tensors (``opt.IDX.NAME``) and the JSON part (``param_groups``, ``opt_scalars``)."""
    opt_state = opt.state_dict()
    tensors, scalars = {}, {}
    for idx, st in opt_state["state"].items():
        for name, val in st.items():
            if torch.is_tensor(val):
                tensors[f"opt.{idx}.{name}"] = val.detach().cpu().contiguous()
            else:
                scalars[f"{idx}.{name}"] = val
    return tensors, {"param_groups": opt_state["param_groups"], "opt_scalars": scalars}


def write_state(folder: Path, tensors: dict[str, torch.Tensor], meta: dict) -> None:
    """``folder/checkpoint/`` (``state.safetensors`` + ``state.json``) replaced as a whole: it is either the old
    state or the new one, never half (a fresh temporary folder, two renames)."""
    from safetensors.torch import save_file

    folder.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f"checkpoint.tmp-{os.getpid()}-", dir=folder))  # a fresh name, never a planted one
    os.chmod(tmp, 0o777 & ~_UMASK)  # mkdtemp makes 0700; the checkpoint gets the usual permissions
    save_file(tensors, str(tmp / "state.safetensors"))
    (tmp / "state.json").write_text(json.dumps(meta))
    final = folder / "checkpoint"
    old = folder / f"checkpoint.old-{os.getpid()}"
    if final.exists():
        os.replace(final, old)
    os.replace(tmp, final)
    shutil.rmtree(old, ignore_errors=True)


def read_state(folder: Path) -> tuple[dict[str, torch.Tensor], dict] | None:
    """What :func:`write_state` wrote (or, after a kill between its two renames, the old state); None without one."""
    from safetensors.torch import load_file

    ck = folder / "checkpoint"
    if not (ck / "state.json").is_file():
        old = sorted(folder.glob("checkpoint.old-*"))
        if not old:
            return None
        ck = old[-1]
    return load_file(str(ck / "state.safetensors")), json.loads((ck / "state.json").read_text())


def save_checkpoint(stage_dir: Path, module: StageModule, opt: torch.optim.Optimizer, step: int, best: float, tcfg: TrainConfig,
                     cpu_s: float = 0.0) -> None:
    prefix, trained = module.checkpointed()
    tensors = {f"{prefix}.{k}": v.detach().cpu().contiguous() for k, v in trained.state_dict().items()}
    # training-only heads (StageModule.aux: the depth stage's normals head), which no weights file keeps
    tensors.update({f"aux.{k}": v.detach().cpu().contiguous() for k, v in module.aux.state_dict().items()})
    opt_tensors, opt_meta = optimizer_tensors(opt)
    meta = {
        "step": step,
        "best_val": best,
        "cpu_s": cpu_s,  # the stage's processor seconds over every run so far
        **opt_meta,
        "model_config": module.model.config.to_dict(),
        "train_config": dataclasses.asdict(tcfg),
    }
    write_state(stage_dir, {**tensors, **opt_tensors}, meta)


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
    state = read_state(stage_dir)
    if state is None:
        return 0, math.inf, 0.0
    tensors, meta = state
    ck = stage_dir / "checkpoint"
    prefix, trained = module.checkpointed()  # older baseline checkpoints also hold "model." tensors: ignored
    try:
        trained.load_state_dict({k[len(prefix) + 1:]: v for k, v in tensors.items() if k.startswith(prefix + ".")})
        module.aux.load_state_dict({k[4:]: v for k, v in tensors.items() if k.startswith("aux.")})
        _load_optimizer(opt, tensors, meta)
    except (RuntimeError, ValueError, KeyError) as exc:
        why = " ".join(str(exc).split())[:300] or type(exc).__name__
        raise CheckpointMismatch(
            f"{ck} was written for a different model or optimiser than this run's ({why}); "
            f"to train the {module.stage} stage afresh, delete {ck} (or pass another --out)"
        ) from exc
    return int(meta["step"]), float(meta["best_val"]), float(meta.get("cpu_s", 0.0))


def optimizer_state(tensors: dict[str, torch.Tensor], meta: dict) -> dict[int, dict]:
    """The optimiser's per-parameter state from :func:`optimizer_tensors`' two parts."""
    state: dict[int, dict] = {}
    for k, v in tensors.items():
        if k.startswith("opt."):
            _, idx, name = k.split(".", 2)
            state.setdefault(int(idx), {})[name] = v
    for k, v in meta["opt_scalars"].items():
        idx, name = k.split(".", 1)
        state.setdefault(int(idx), {})[name] = v
    return state


# how the update runs (one fused kernel, a loop over tensors) is the running trainer's choice, never the checkpoint's:
# a state written by the single-tensor Adam resumes fused, and back (the state's tensors are the same)
IMPLEMENTATION = ("fused", "foreach")


def load_optimizer_state(opt: torch.optim.Optimizer, state: dict, keep: tuple[str, ...] = IMPLEMENTATION) -> None:
    """Load ``state`` (``{"state", "param_groups"}``) into ``opt``; for the settings named in ``keep`` this run's
    values win over the saved ones."""
    groups = [dict(saved) for saved in state["param_groups"]]
    for saved, current in zip(groups, opt.param_groups):
        saved.update({k: current[k] for k in keep if k in current})
    opt.load_state_dict({"state": state["state"], "param_groups": groups})


def _load_optimizer(opt: torch.optim.Optimizer, tensors: dict[str, torch.Tensor], meta: dict) -> None:
    # this run's settings win over the checkpoint's: a stage continued with another --lr (or betas) trains with it,
    # as log.csv says (the Adam moments carry on); so does a net's share of the rate (StageModule.param_groups)
    load_optimizer_state(opt, {"state": optimizer_state(tensors, meta), "param_groups": meta["param_groups"]},
                         keep=("lr", "betas", "lr_scale") + IMPLEMENTATION)
