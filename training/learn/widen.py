"""A wider depth net that computes exactly what the narrower one did (function-preserving widening).

The installed depth net is the small preset (``depth_widths`` 16–128) and underfits its own training views
(``results/stage_errors/depth.md``).  Training a wider one from scratch would throw away every CPU-hour the small
one has had, so :func:`widen_depth_net` builds the wider net *around* it, in the manner of Net2WiderNet (Chen,
Goodfellow and Shlens, ICLR 2016), with zero-initialised outgoing weights in place of their copied units:

* every old channel keeps its old weights, batch-norm parameters and statistics;
* every new channel gets fresh weights (PyTorch's default initialisation) *from* every input;
* every weight *from* a new channel *to* an old one is zero.

So the old channels see exactly the old inputs, the outputs (depth, silhouette) are the old ones to rounding,
in eval and in train mode, and the first gradient step already moves the zero weights (their gradient is the new
channels' activations times the old outputs' error).  The only concatenation in the U-ResNet, ``[up, skip]`` in
each decoder stage's fusion, is mapped part by part.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import nn

from genre_backend.nets.model import GenRe
from genre_backend.nets.uresnet import _UpStage

__all__ = ["widen_depth_net"]


def _index(n_old: int, n_new: int) -> torch.Tensor:
    if n_new < n_old:
        raise ValueError(f"cannot narrow a layer from {n_old} to {n_new} channels")
    return torch.arange(n_old)


def _fuse_inputs(old: _UpStage, new: _UpStage) -> torch.Tensor:
    """Where the old fusion's input channels ``[up, skip]`` sit in the new one's."""
    up_old, up_new = old.up[0].out_channels, new.up[0].out_channels
    skip_old = old.fuse[0].in_channels - up_old
    return torch.cat([torch.arange(up_old), up_new + torch.arange(skip_old)])


@torch.no_grad()
def _copy_conv(old: nn.Module, new: nn.Module, in_idx: torch.Tensor) -> None:
    transposed = isinstance(old, nn.ConvTranspose2d)  # its weight is (in, out, k, k)
    w_old, w_new = old.weight, new.weight
    out_idx = _index(old.out_channels, new.out_channels)
    new_inputs = torch.ones(new.in_channels, dtype=torch.bool)
    new_inputs[in_idx] = False
    new_idx = new_inputs.nonzero()[:, 0]

    def at(outs: torch.Tensor, ins: torch.Tensor):
        return (ins[:, None], outs[None, :]) if transposed else (outs[:, None], ins[None, :])

    w_new[at(out_idx, new_idx)] = 0  # the old outputs see only the old inputs
    w_new[at(out_idx, in_idx)] = w_old
    if old.bias is not None:
        new.bias[out_idx] = old.bias


@torch.no_grad()
def _copy_norm(old: nn.BatchNorm2d, new: nn.BatchNorm2d) -> None:
    idx = _index(old.num_features, new.num_features)
    for name in ("weight", "bias", "running_mean", "running_var"):
        getattr(new, name)[idx] = getattr(old, name)
    new.num_batches_tracked.copy_(old.num_batches_tracked)


def _widen_module(old: nn.Module, new: nn.Module) -> None:
    """Copy ``old`` into the wider ``new`` (same structure), layer by layer in forward order of channels."""
    fuse_inputs = {}
    for name, module in old.named_modules():
        if isinstance(module, _UpStage):
            fuse_inputs[f"{name}.fuse.0" if name else "fuse.0"] = _fuse_inputs(module, new.get_submodule(name))
    olds = dict(old.named_modules())
    for name, n in new.named_modules():
        o = olds.get(name)
        if o is None or type(o) is not type(n):
            raise ValueError(f"the two nets differ at {name!r}")
        if isinstance(n, (nn.Conv2d, nn.ConvTranspose2d)):
            in_old = o.in_channels
            in_idx = fuse_inputs.get(name, _index(in_old, n.in_channels))
            _copy_conv(o, n, in_idx)
        elif isinstance(n, nn.BatchNorm2d):
            _copy_norm(o, n)
        elif isinstance(n, nn.Linear) or any(True for _ in n.parameters(recurse=False)):
            raise ValueError(f"no widening rule for {name!r} ({type(n).__name__})")


def widen_depth_net(model: GenRe, widths: tuple[int, int, int, int], seed: int = 0) -> GenRe:
    """A copy of ``model`` whose depth net has ``widths`` (each ≥ the old one) and predicts what the old one did;
    the inpainting net and refiner are copied unchanged.  ``seed``: the new channels' initialisation."""
    widths = tuple(int(w) for w in widths)
    old_widths = model.config.network.depth_widths
    if len(widths) != 4 or any(w < o for w, o in zip(widths, old_widths)):
        raise ValueError(f"depth widths {widths}: expected four widths, each at least the old {old_widths}")
    config = dataclasses.replace(model.config, network=dataclasses.replace(model.config.network, depth_widths=widths))
    torch.manual_seed(seed)
    wide = GenRe(config)
    state = {k: v for k, v in model.state_dict().items() if not k.startswith("depth_net.")}
    missing, unexpected = wide.load_state_dict(state, strict=False)
    if unexpected or any(not k.startswith("depth_net.") for k in missing):
        raise ValueError(f"the nets besides the depth net do not fit: {unexpected or missing}")
    _widen_module(model.depth_net, wide.depth_net)
    return wide.train(model.training)
