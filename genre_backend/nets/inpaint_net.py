"""Spherical inpainting net ``c_S→S``: partial spherical map → full spherical map.

A U-ResNet-18 (:mod:`genre_backend.nets.uresnet`) with one input channel and one
decoder, run on maps padded periodically in azimuth
(:func:`genre_backend.geometry.spherical.pad_sph`); the loss covers the padded map.
"""

from __future__ import annotations

import torch
from torch import nn

from ..config import GenreConfig
from ..geometry.spherical import crop_sph, pad_sph
from .uresnet import ResNetEncoder, UDecoder
from ..validation import check_tensor

__all__ = ["InpaintNet"]


class InpaintNet(nn.Module):
    def __init__(self, config: GenreConfig):
        super().__init__()
        net, g = config.network, config.geometry
        self.size, self.pad = g.sph_size, g.sph_pad
        if g.sph_padded_size % 32:
            raise ValueError(f"padded spherical map side {g.sph_padded_size} must be a multiple of 32")
        self.encoder = ResNetEncoder(1, net.inpaint_widths)
        self.decoder = UDecoder(net.inpaint_widths, 1, net.inpaint_decoder_blocks)

    def forward_padded(self, padded: torch.Tensor) -> torch.Tensor:
        """(B, 1, P, P) padded partial maps → (B, 1, P, P) padded full maps (P = size + 2·pad)."""
        p = self.size + 2 * self.pad
        check_tensor("padded partial map", padded, ("B", 1, p, p))
        skips, deep = self.encoder(padded * 2.0 - 1.0)  # maps live in [0, 1]; centre them
        return padded + self.decoder(skips, deep)  # predict the change from the input

    def forward(self, partial: torch.Tensor) -> torch.Tensor:
        """(B, H, W) partial maps → (B, H, W) full maps."""
        check_tensor("partial map", partial, ("B", self.size, self.size))
        return crop_sph(self.forward_padded(pad_sph(partial[:, None], self.pad)), self.pad)[:, 0]
