"""U-ResNet: a ResNet-18 encoder with mirrored transposed-convolution decoders.

The shared body of the depth estimator (:mod:`genre_backend.nets.depth_net`) and
the spherical inpainting net (:mod:`genre_backend.nets.inpaint_net`).

Encoder (ResNet-18 layout, widths ``w = (w1, w2, w3, w4)``)::

    stem   7×7 conv, stride 2 → w1           (H/2)   skip s0
    pool   3×3 max-pool, stride 2             (H/4)
    layer1 2 basic blocks, w1                 (H/4)   skip s1
    layer2 2 basic blocks, w2, stride 2       (H/8)   skip s2
    layer3 2 basic blocks, w3, stride 2       (H/16)  skip s3
    layer4 2 basic blocks, w4, stride 2       (H/32)

Each decoder mirrors it: at every scale a 4×4 transposed convolution doubles
the resolution, the encoder's skip at that scale is concatenated, a 3×3
convolution fuses them, and ``blocks`` basic blocks follow; a last transposed
convolution returns to full resolution and a 3×3 convolution gives the
output channels (linear).  Image sides must be multiples of 32.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["BasicBlock", "ResNetEncoder", "UDecoder", "count_parameters"]


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


class BasicBlock(nn.Module):
    """ResNet basic block: two 3×3 convs with batch norm and an identity (or 1×1) shortcut."""

    def __init__(self, cin: int, cout: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.short = None
        if stride != 1 or cin != cout:
            self.short = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = torch.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return torch.relu(y + (x if self.short is None else self.short(x)))


class ResNetEncoder(nn.Module):
    """ResNet-18 encoder; returns the skips ``[s0, s1, s2, s3]`` and the deepest features."""

    def __init__(self, in_channels: int, widths: tuple[int, int, int, int]):
        super().__init__()
        w1, w2, w3, w4 = widths
        self.stem = nn.Sequential(nn.Conv2d(in_channels, w1, 7, 2, 3, bias=False), nn.BatchNorm2d(w1), nn.ReLU(inplace=True))
        self.pool = nn.MaxPool2d(3, 2, 1)
        self.layer1 = nn.Sequential(BasicBlock(w1, w1), BasicBlock(w1, w1))
        self.layer2 = nn.Sequential(BasicBlock(w1, w2, 2), BasicBlock(w2, w2))
        self.layer3 = nn.Sequential(BasicBlock(w2, w3, 2), BasicBlock(w3, w3))
        self.layer4 = nn.Sequential(BasicBlock(w3, w4, 2), BasicBlock(w4, w4))

    def forward(self, x: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor]:
        s0 = self.stem(x)
        s1 = self.layer1(self.pool(s0))
        s2 = self.layer2(s1)
        s3 = self.layer3(s2)
        return [s0, s1, s2, s3], self.layer4(s3)


class _UpStage(nn.Module):
    def __init__(self, cin: int, cskip: int, cout: int, blocks: int):
        super().__init__()
        self.up = nn.Sequential(nn.ConvTranspose2d(cin, cout, 4, 2, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))
        self.fuse = nn.Sequential(nn.Conv2d(cout + cskip, cout, 3, 1, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))
        self.blocks = nn.Sequential(*[BasicBlock(cout, cout) for _ in range(blocks)])

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        return self.blocks(self.fuse(torch.cat([self.up(x), skip], dim=1)))


class UDecoder(nn.Module):
    """Mirrored decoder from the encoder's deepest features and skips to (out_channels, H, W)."""

    def __init__(self, widths: tuple[int, int, int, int], out_channels: int, blocks: int):
        super().__init__()
        w1, w2, w3, w4 = widths
        self.stages = nn.ModuleList(
            [
                _UpStage(w4, w3, w3, blocks),  # H/32 → H/16, skip s3
                _UpStage(w3, w2, w2, blocks),  # → H/8, skip s2
                _UpStage(w2, w1, w1, blocks),  # → H/4, skip s1
                _UpStage(w1, w1, w1, blocks),  # → H/2, skip s0
            ]
        )
        half = max(w1 // 2, 1)
        self.head = nn.Sequential(
            nn.ConvTranspose2d(w1, half, 4, 2, 1, bias=False),
            nn.BatchNorm2d(half),
            nn.ReLU(inplace=True),
            nn.Conv2d(half, out_channels, 3, 1, 1),
        )

    def forward(self, skips: list[torch.Tensor], deep: torch.Tensor) -> torch.Tensor:
        x = deep
        for stage, skip in zip(self.stages, reversed(skips)):
            x = stage(x, skip)
        return self.head(x)
