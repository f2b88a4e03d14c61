"""Depth estimator ``f_2D→2.5D``: RGB → planar depth and silhouette.

A U-ResNet-18 (:mod:`genre_backend.nets.uresnet`) with one decoder per output
head: ``depth`` (planar depth in world units, ``distance + output / scale``)
and ``silhouette`` (logits of the object mask).  Trained from scratch.
"""

from __future__ import annotations

import torch
from torch import nn

from ..config import GenreConfig
from .uresnet import ResNetEncoder, UDecoder
from ..validation import check_tensor

__all__ = ["DepthNet", "IMAGENET_MEAN", "IMAGENET_STD", "normalize_rgb"]

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def normalize_rgb(rgb: torch.Tensor) -> torch.Tensor:
    """(B, 3, S, S) float in [0, 1] → ImageNet-normalised network input."""
    mean = torch.tensor(IMAGENET_MEAN, dtype=rgb.dtype, device=rgb.device).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, dtype=rgb.dtype, device=rgb.device).view(1, 3, 1, 1)
    return (rgb - mean) / std


class DepthNet(nn.Module):
    HEADS = ("depth", "silhouette")

    def __init__(self, config: GenreConfig):
        super().__init__()
        net = config.network
        self.size = config.geometry.image_size
        if self.size % 32:  # the encoder halves the image five times; the decoder's skips must line up
            raise ValueError(f"image side {self.size} must be a multiple of 32")
        self.distance = config.camera.distance
        self.scale = net.depth_output_scale
        self.encoder = ResNetEncoder(3, net.depth_widths)
        self.decoders = nn.ModuleDict({h: UDecoder(net.depth_widths, 1, net.depth_decoder_blocks) for h in self.HEADS})

    def forward(self, rgb: torch.Tensor) -> dict[str, torch.Tensor]:
        """rgb: (B, 3, S, S) float in [0, 1].

        Returns ``depth`` (B, S, S) planar depth over the whole image and
        ``silhouette_logits`` (B, S, S).
        """
        return self.decode(*self.encode(rgb))

    def encode(self, rgb: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor]:
        """The encoder's skips and deepest features for rgb (B, 3, S, S) in [0, 1]: what every head reads
        (and what a training-only head, :mod:`training.learn.normals`, reads beside them)."""
        check_tensor("rgb", rgb, ("B", 3, self.size, self.size))
        return self.encoder(normalize_rgb(rgb))

    def decode(self, skips: list[torch.Tensor], deep: torch.Tensor) -> dict[str, torch.Tensor]:
        """The heads' outputs (:meth:`forward`'s) from :meth:`encode`'s features."""
        depth = self.distance + self.decoders["depth"](skips, deep)[:, 0] / self.scale
        return {"depth": depth, "silhouette_logits": self.decoders["silhouette"](skips, deep)[:, 0]}
