"""Wider nets that compute exactly what the narrower ones did (function-preserving widening).

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

:func:`widen_refiner` does the same for the 3-D refiner's base width ``refiner_nf`` (issue 47: "widen it if the
fit diagnostic says capacity is the limit"); its concatenations are the decoder's ``[up, skip]`` too, and its
fully-connected bottleneck keeps its size as long as the deepest level's width does (``refiner_max_width``).

``python -m training.learn.widen --weights W --refiner-nf 12 --out WIDE.safetensors`` writes a widened file.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import nn

from genre_backend.nets.model import GenRe
from genre_backend.nets.refiner import VoxelRefiner
from genre_backend.nets.uresnet import _UpStage

__all__ = ["widen_depth_net", "widen_refiner", "main"]

_CONVS = (nn.Conv2d, nn.ConvTranspose2d, nn.Conv3d, nn.ConvTranspose3d)
_NORMS = (nn.BatchNorm2d, nn.BatchNorm3d)


def _index(n_old: int, n_new: int) -> torch.Tensor:
    if n_new < n_old:
        raise ValueError(f"cannot narrow a layer from {n_old} to {n_new} channels")
    return torch.arange(n_old)


def _concat_inputs(up_old: int, up_new: int, skip_old: int) -> torch.Tensor:
    """Where the old input channels of a convolution over ``[up, skip]`` sit in the new one's."""
    return torch.cat([torch.arange(up_old), up_new + torch.arange(skip_old)])


def _fuse_inputs(old: _UpStage, new: _UpStage) -> torch.Tensor:
    """Where the old fusion's input channels ``[up, skip]`` sit in the new one's."""
    up_old, up_new = old.up[0].out_channels, new.up[0].out_channels
    return _concat_inputs(up_old, up_new, old.fuse[0].in_channels - up_old)


@torch.no_grad()
def _copy_conv(old: nn.Module, new: nn.Module, in_idx: torch.Tensor) -> None:
    transposed = isinstance(old, (nn.ConvTranspose2d, nn.ConvTranspose3d))  # its weight is (in, out, k…)
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
def _copy_norm(old: nn.Module, new: nn.Module) -> None:
    idx = _index(old.num_features, new.num_features)
    for name in ("weight", "bias", "running_mean", "running_var"):
        getattr(new, name)[idx] = getattr(old, name)
    new.num_batches_tracked.copy_(old.num_batches_tracked)


def _widen_module(old: nn.Module, new: nn.Module, concat_inputs: dict[str, torch.Tensor] | None = None) -> None:
    """Copy ``old`` into the wider ``new`` (same structure), layer by layer in forward order of channels.
    ``concat_inputs``: for a convolution over a concatenation, where its old input channels sit in the new one's
    (the U-ResNet's fusions are found here)."""
    fuse_inputs = dict(concat_inputs or {})
    for name, module in old.named_modules():
        if isinstance(module, _UpStage):
            fuse_inputs[f"{name}.fuse.0" if name else "fuse.0"] = _fuse_inputs(module, new.get_submodule(name))
    olds = dict(old.named_modules())
    for name, n in new.named_modules():
        o = olds.get(name)
        if o is None or type(o) is not type(n):
            raise ValueError(f"the two nets differ at {name!r}")
        if isinstance(n, _CONVS):
            in_old = o.in_channels
            in_idx = fuse_inputs.get(name, _index(in_old, n.in_channels))
            _copy_conv(o, n, in_idx)
        elif isinstance(n, _NORMS):
            _copy_norm(o, n)
        elif isinstance(n, nn.Linear) and n.weight.shape == o.weight.shape:
            n.load_state_dict(o.state_dict())  # a layer the widening leaves as it was
        elif isinstance(n, nn.Linear) or any(True for _ in n.parameters(recurse=False)):
            raise ValueError(f"no widening rule for {name!r} ({type(n).__name__})")


def _rebuilt(model: GenRe, network, net_name: str, seed: int) -> GenRe:
    """A new model of ``network``'s sizes with every net but ``net_name`` copied from ``model`` (that one is left
    initialised from ``seed``, for the caller to widen into)."""
    torch.manual_seed(seed)
    wide = GenRe(dataclasses.replace(model.config, network=network))
    prefix = f"{net_name}."
    missing, unexpected = wide.load_state_dict(
        {k: v for k, v in model.state_dict().items() if not k.startswith(prefix)}, strict=False)
    if unexpected or any(not k.startswith(prefix) for k in missing):
        raise ValueError(f"the nets besides the {net_name} do not fit: {unexpected or missing}")
    return wide


def widen_depth_net(model: GenRe, widths: tuple[int, int, int, int], seed: int = 0) -> GenRe:
    """A copy of ``model`` whose depth net has ``widths`` (each ≥ the old one) and predicts what the old one did;
    the inpainting net and refiner are copied unchanged.  ``seed``: the new channels' initialisation."""
    widths = tuple(int(w) for w in widths)
    old_widths = model.config.network.depth_widths
    if len(widths) != 4 or any(w < o for w, o in zip(widths, old_widths)):
        raise ValueError(f"depth widths {widths}: expected four widths, each at least the old {old_widths}")
    wide = _rebuilt(model, dataclasses.replace(model.config.network, depth_widths=widths), "depth_net", seed)
    _widen_module(model.depth_net, wide.depth_net)
    return wide.train(model.training)


def widen_refiner(model: GenRe, nf: int, seed: int = 0) -> GenRe:
    """A copy of ``model`` whose refiner has base width ``nf`` (at least the old one) and refines as the old one
    did; the depth and inpainting nets are copied unchanged.  The deepest level keeps its width (the widths are
    capped there by ``refiner_max_width``), so that the fully-connected bottleneck keeps its size and weights."""
    net = model.config.network
    old: VoxelRefiner = model.refiner
    deep = old.deep
    if int(nf) < net.refiner_nf:
        raise ValueError(f"refiner width {nf}: expected at least the old {net.refiner_nf}")
    network = dataclasses.replace(net, refiner_nf=int(nf), refiner_max_width=min(deep, net.refiner_max_width or deep))
    wide = _rebuilt(model, network, "refiner", seed)
    concat = {}
    for i, (up_old, up_new) in enumerate(zip(old.up, wide.refiner.up)):
        w_old, w_new = up_old[0].out_channels, up_new[0].out_channels
        concat[f"fuse.{i}.0"] = _concat_inputs(w_old, w_new, w_old)
    _widen_module(old, wide.refiner, concat)
    return wide.train(model.training)


def main(argv: list[str] | None = None) -> int:
    import argparse

    from genre_backend.arguments import add_out, add_seed, add_weights
    from genre_backend.nets.model import load_model, save_model
    from genre_backend.weights_file import resolve_weights, weights_extra

    parser = argparse.ArgumentParser(prog="python -m training.learn.widen", description=(
        "Write a copy of a weights file with wider nets that compute what the old ones did (Net2WiderNet-style, "
        "zero weights from the new channels to the old ones)."))
    add_weights(parser, required=True, help="the weights to widen: a shipped name ('default') or a .safetensors file")
    parser.add_argument("--depth-widths", type=int, nargs=4, metavar="W", help="the depth net's four new widths")
    parser.add_argument("--refiner-nf", type=int, help="the refiner's new base width (network.refiner_nf)")
    add_seed(parser, default=0, help="the new channels' initialisation (default 0)")
    add_out(parser, required=True, help="the widened weights file to write")
    args = parser.parse_args(argv)
    if not (args.depth_widths or args.refiner_nf):
        parser.error("nothing to widen: give --depth-widths and/or --refiner-nf")
    source = resolve_weights(args.weights)
    model = load_model(source)
    if args.depth_widths:
        model = widen_depth_net(model, tuple(args.depth_widths), seed=args.seed)
    if args.refiner_nf:
        model = widen_refiner(model, args.refiner_nf, seed=args.seed)
    save_model(model, args.out, extra={**weights_extra(source), "widened_from": str(args.weights)})
    print(f"wrote {args.out}: " + ", ".join(
        f"{name} {sum(p.numel() for p in getattr(model, name).parameters()) / 1e6:.2f} M parameters"
        for name in ("depth_net", "inpaint_net", "refiner")))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
