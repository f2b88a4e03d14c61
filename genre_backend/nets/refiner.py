"""Voxel refiner: a 3D encoder–decoder with skips and a fully-connected bottleneck.

Input (B, 2, N, N, N): channel 0 from the (inpainted) spherical map, channel
1 from the depth map (both :func:`genre_backend.geometry.voxels.points_to_voxels`
grids).  Output (B, 1, N, N, N): logits of the object's surface shell
(:func:`genre_backend.geometry.mesh_voxels.mesh_to_shell`).

With ``L = log2(N) − 1`` levels and base width ``nf`` the encoder has, per
level ``k`` (width ``nf·2^k``), a 3×3×3 convolution at the incoming
resolution (all but the first level) and a 4×4×4 stride-2 convolution down
to N/2^(k+1), ending at 2³.  The bottleneck flattens the 2³ features through
a ``fc``-wide fully-connected layer and back.  The decoder mirrors the
encoder: a 4×4×4 stride-2 transposed convolution up, the encoder's features
at that resolution concatenated, a 3×3×3 convolution fusing them.  A last
transposed convolution returns to N³ and one channel of logits, to which a
3×3×3 convolution of the two input grids themselves is added.  That
full-resolution skip is ours, not the original's: without it the finest
features the output sees are N/2³, so even a perfect spherical map came out
as a blob (the first default weights, commit 5aa4676, on 8 seen-test views:
CD 0.18 from the true spherical and depth maps, against 0.065 for the
projected true map alone).  It is linear and one channel wide to keep the
cost at N³ small on the CPU.

``max_width > 0`` caps every level's width (a wide base, ``nf``, without the
parameters of the deepest levels, which a GPU burst's bf16 time does not need
and a weights file that must travel cannot carry).

``full_nf > 0`` adds a second, non-linear full-resolution branch (ours too):
three 3×3×3 convolutions (``full_nf`` channels, then one) over the two input
grids and the logits above, whose output is added to those logits.  It sees
a 7³ neighbourhood at N³, enough to put a flat face or a sharp edge where the
projected surface voxels say it is, which the coarse path (finest features at
N/2, eight channels in the default preset) blurs: given the true depth and
spherical maps, the product weights without it score 1.6× the CD of the
projected true map alone (0.097 against 0.061 on 16 seen-test views,
``scripts/stage_errors.py``).  Its last convolution starts at zero, so a
refiner grown from weights without the branch (:meth:`VoxelRefiner.load_grown`)
starts with their output unchanged.  Trained so on the product model
(recipe ``product_full``) it did not sharpen the output: the refiner's
inputs from the depth and inpainting nets are off by more than the blur
(docs/lab/product-model.md, *The product model*).
At N = 128, nf = 20, fc = 640 (the ``paper`` preset) this has 52.5 M
parameters (the original: 53.5 M).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ..validation import check_tensor
from .phase_conv import PhaseConvTranspose3d

__all__ = ["VoxelRefiner"]

SKIP_INIT = 0.5  # initial weight of every tap of the full-resolution skip
OUT_BIAS_INIT = -3.0  # initial logit bias: about the prior of a shell voxel (scripts/stage_errors.py prints the fraction)


def _block(conv: nn.Module, channels: int) -> nn.Sequential:
    return nn.Sequential(conv, nn.BatchNorm3d(channels), nn.LeakyReLU(0.2, inplace=True))


class VoxelRefiner(nn.Module):
    def __init__(self, resolution: int, nf: int, fc: int, full_nf: int = 0, max_width: int = 0):
        super().__init__()
        levels = int(round(math.log2(resolution))) - 1
        if 2 ** (levels + 1) != resolution or levels < 2:
            raise ValueError(f"refiner resolution must be a power of two ≥ 8, got {resolution}")
        self.resolution = resolution
        widths = [nf * 2**k if not max_width else min(nf * 2**k, max_width) for k in range(levels)]
        self.pre = nn.ModuleList()
        self.down = nn.ModuleList()
        cin = 2
        for k, w in enumerate(widths):
            self.pre.append(nn.Identity() if k == 0 else _block(nn.Conv3d(cin, cin, 3, 1, 1, bias=False), cin))
            self.down.append(_block(nn.Conv3d(cin, w, 4, 2, 1, bias=False), w))
            cin = w
        deep = widths[-1]
        self.fc = nn.Sequential(
            nn.Flatten(),
            nn.Linear(deep * 8, fc),
            nn.ReLU(inplace=True),
            nn.Linear(fc, deep * 8),
            nn.ReLU(inplace=True),
        )
        self.deep = deep
        self.up = nn.ModuleList()
        self.fuse = nn.ModuleList()
        # decoder: from 2³ (width widths[-1]) up to N/2 (width widths[0]), fusing encoder outputs
        for k in range(levels - 1, 0, -1):
            w_out = widths[k - 1]
            self.up.append(_block(nn.ConvTranspose3d(widths[k], w_out, 4, 2, 1, bias=False), w_out))
            self.fuse.append(_block(nn.Conv3d(2 * w_out, w_out, 3, 1, 1, bias=False), w_out))
        self.out = PhaseConvTranspose3d(widths[0], 1)  # nn.ConvTranspose3d(widths[0], 1, 4, 2, 1), its forward ~5× faster on the CPU
        self.skip = nn.Conv3d(2, 1, 3, 1, 1, bias=False)  # the input grids at full resolution
        # Start it as a dilation of the input hits (a voxel next to projected surface is likely
        # shell): with Adam at lr 1e-4 a randomly initialised tap would take ~10⁴ steps to get there.
        nn.init.constant_(self.skip.weight, SKIP_INIT)
        nn.init.constant_(self.out.bias, OUT_BIAS_INIT)
        if full_nf < 0:
            raise ValueError(f"refiner full-resolution width must be >= 0, got {full_nf}")
        self.full = None
        if full_nf:
            self.full = nn.Sequential(
                nn.Conv3d(3, full_nf, 3, 1, 1),
                nn.LeakyReLU(0.2, inplace=True),
                nn.Conv3d(full_nf, full_nf, 3, 1, 1),
                nn.LeakyReLU(0.2, inplace=True),
                nn.Conv3d(full_nf, 1, 3, 1, 1),
            )
            nn.init.zeros_(self.full[-1].weight)
            nn.init.zeros_(self.full[-1].bias)

    def load_grown(self, state: dict[str, torch.Tensor]) -> list[str]:
        """Load a state dict of the same refiner without the full-resolution branch.

        Every tensor of ``state`` must match this refiner's; only the branch's own
        tensors may be missing (they keep their initialisation, under which the
        output equals the smaller refiner's).  Returns the names left as initialised.
        """
        own = self.state_dict()
        missing = sorted(set(own) - set(state))
        unknown = sorted(set(state) - set(own))
        foreign = [k for k in missing if not k.startswith("full.")]
        if unknown or foreign:
            raise ValueError(f"cannot grow the refiner: unexpected tensors {unknown[:4]}, missing {foreign[:4]}")
        self.load_state_dict(state, strict=False)
        return missing

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 2, N, N, N) float → (B, 1, N, N, N) logits."""
        n = self.resolution
        check_tensor("refiner input", x, ("B", 2, n, n, n), finite=False)
        inputs = x
        feats = []
        for pre, down in zip(self.pre, self.down):
            x = down(pre(x))
            feats.append(x)
        x = self.fc(x).view(-1, self.deep, 2, 2, 2)
        for up, fuse, skip in zip(self.up, self.fuse, reversed(feats[:-1])):
            x = fuse(torch.cat([up(x), skip], dim=1))
        logits = self.out(x) + self.skip(inputs)
        if self.full is not None:
            logits = logits + self.full(torch.cat([inputs, logits], dim=1))
        return logits
