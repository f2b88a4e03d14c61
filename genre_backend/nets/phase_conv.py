"""A 3-D transposed convolution (kernel 4, stride 2, padding 1) computed by phases.

A stride-2 transposed convolution writes each output voxel from at most 2 input
voxels per axis, and which kernel taps it uses depends only on the voxel's
*phase* (its index mod 2 on each axis).  So the same map is a plain 3×3×3
convolution at the input's resolution with ``8 · out_channels`` outputs (one per
phase and channel) followed by a 3-D pixel shuffle.  On the CPU, torch's
transposed 3-D convolution takes a slow path for thin outputs (the refiner's
last layer, 8 → 1 channel at 64³); the phase form runs it through the fast
convolution kernels instead (``genre bench layers`` prints both).

Derivation (one axis; the others are the same).  With stride 2 and padding 1,
input ``x[i]`` reaches output ``o = 2i − 1 + k`` through tap ``k`` ∈ 0..3.  For
``o = 2m + r`` (phase ``r`` ∈ {0, 1}) and ``i = m + d``, the tap is
``k = r + 1 − 2d``; a 3-tap correlation with padding 1 reads ``d = t − 1`` at its
tap ``t`` ∈ 0..2, so its weight there is the transposed kernel's tap
``k = r + 3 − 2t`` where that lies in 0..3, and zero elsewhere.

The module keeps :class:`torch.nn.ConvTranspose3d`'s parameters (``weight`` of
shape ``(in, out, 4, 4, 4)``, ``bias``), so state dicts, weight files and code
that inspects the layer are unchanged; only ``forward`` differs.  The reference
is ``torch.nn.functional.conv_transpose3d`` itself (tests/backend/nets/test_phase_conv.py).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["PhaseConvTranspose3d", "phase_kernel", "pixel_shuffle_3d"]

# Tap of the zero-padded transposed kernel (taps −1..4 stored at 0..5) that
# phase r reads at correlation tap t: (r + 3 − 2t) + 1.
_TAPS = torch.tensor([[4, 2, 0], [5, 3, 1]])


def phase_kernel(weight: torch.Tensor) -> torch.Tensor:
    """(in, out, 4, 4, 4) transposed-convolution kernel → (out·8, in, 3, 3, 3) convolution kernel.

    Output channel ``c·8 + rz·4 + ry·2 + rx`` is channel ``c`` at phase ``(rz, ry, rx)``.
    (A zero pad and three gathers; the module's backward is torch's own, so it is not differentiated.)
    """
    cin, cout = weight.shape[:2]
    taps = _TAPS.flatten().to(weight.device)
    w = F.pad(weight, (1, 1, 1, 1, 1, 1))
    w = w.index_select(2, taps).index_select(3, taps).index_select(4, taps)  # (in, out, 6, 6, 6)
    w = w.reshape(cin, cout, 2, 3, 2, 3, 2, 3).permute(1, 2, 4, 6, 0, 3, 5, 7)
    return w.reshape(cout * 8, cin, 3, 3, 3)


def pixel_shuffle_3d(x: torch.Tensor) -> torch.Tensor:
    """(B, C·8, D, H, W) → (B, C, 2D, 2H, 2W), channel ``c·8 + rz·4 + ry·2 + rx`` to phase (rz, ry, rx)."""
    b, c8, d, h, w = x.shape
    c = c8 // 8
    x = x.reshape(b, c, 2, 2, 2, d, h, w).permute(0, 1, 5, 2, 6, 3, 7, 4)
    return x.reshape(b, c, 2 * d, 2 * h, 2 * w)


class _ByPhases(torch.autograd.Function):
    """Forward by phases; backward by torch's own transposed-convolution gradients (fast on the CPU)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
        ctx.save_for_backward(x, weight)
        ctx.has_bias = bias is not None
        fmt = _format_of(x)
        phase_bias = None if bias is None else bias.repeat_interleave(8)
        y = F.conv3d(x, phase_kernel(weight).contiguous(memory_format=fmt), phase_bias, padding=1)
        return pixel_shuffle_3d(y).contiguous(memory_format=fmt)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        x, weight = ctx.saved_tensors
        mask = [ctx.needs_input_grad[0], ctx.needs_input_grad[1], ctx.has_bias and ctx.needs_input_grad[2]]
        gx, gw, gb = torch.ops.aten.convolution_backward(
            grad.contiguous(memory_format=_format_of(x)), x, weight, [weight.shape[1]] if ctx.has_bias else None,
            [2, 2, 2], [1, 1, 1], [1, 1, 1], True, [0, 0, 0], 1, mask)
        return gx, gw, gb


class PhaseConvTranspose3d(nn.ConvTranspose3d):
    """``nn.ConvTranspose3d(in, out, 4, 2, 1)`` whose forward runs by phases on the CPU (same parameters, same map).

    Worth it where the output is thin: for 8 → 1 channel at 32³ → 64³ (the refiner's
    last layer) torch's own forward is ~5× slower than the phase form, while its
    backward is faster than the phase form's, so the backward stays torch's.  For
    wider outputs torch's forward is as fast or faster (``genre bench layers``), so
    only that layer uses this class.  Under autocast, on other devices, in half
    precision or with an ``output_size``, the parent's forward runs.  (No double
    backward by phases: nothing here needs it.)
    """

    def __init__(self, in_channels: int, out_channels: int, bias: bool = True, device=None, dtype=None):
        super().__init__(in_channels, out_channels, 4, 2, 1, bias=bias, device=device, dtype=dtype)

    def forward(self, x: torch.Tensor, output_size=None) -> torch.Tensor:
        if (output_size is not None or x.device.type != "cpu" or x.dtype not in (torch.float32, torch.float64)
                or torch.is_autocast_enabled("cpu") or x.dim() != 5):
            return super().forward(x, output_size)
        return _ByPhases.apply(x, self.weight, self.bias)


def _format_of(x: torch.Tensor) -> torch.memory_format:
    if x.is_contiguous(memory_format=torch.channels_last_3d) and not x.is_contiguous():
        return torch.channels_last_3d
    return torch.contiguous_format
