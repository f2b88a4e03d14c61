"""Spherical inpainting net ``c_S→S``: partial spherical map → full spherical map.

A U-ResNet-18 (:mod:`genre_backend.nets.uresnet`) run on maps padded
periodically in azimuth (:func:`genre_backend.geometry.spherical.pad_sph`);
the loss covers the padded map.  Two heads, chosen by
``config.network.inpaint_head``:

``"value"`` (the paper's)
    one input channel, the partial map ``s`` (``s = 1``: no hit), and one
    output, the full map, regressed as a value (mean squared error).

``"hit"``
    two input channels, the seen pixels' radius ``r = 1 − s`` (0 elsewhere,
    scaled by :data:`RADIUS_SCALE`) and the seen mask; two outputs, the logit
    that a ray meets the surface at all and the radius where it does.  The full
    map is ``1 − r`` where the hit probability is above
    ``geometry.sph_hit_probability`` and ``1`` (no hit) elsewhere.

Measured on 16 seen-test views (``scripts/stage_errors.py``): a third of a
true full map is "no hit", which the value head must place on the same scale
as radii a few voxels apart; fed the true depth's partial map, the value
head's map projects to CD 0.121 and the hit head's to 0.111 (the partial map
alone: 0.116).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ..config import GenreConfig
from ..geometry.spherical import NO_HIT, crop_sph, pad_sph
from .uresnet import ResNetEncoder, UDecoder
from ..validation import check_tensor

__all__ = ["InpaintNet", "RADIUS_SCALE", "MAX_HIT_VALUE"]

# The hit head's radii are predicted as r · RADIUS_SCALE: radii of hits lie in ~[0, 0.3]
# (95 % of the true maps' hits on seen-test views have s ≥ 0.71), so this puts them in ~[0, 1].
RADIUS_SCALE = 4.0
# a hit's map value stays below geometry.sph_nohit_min (0.9999) so that it projects to a point
MAX_HIT_VALUE = 0.9998


class InpaintNet(nn.Module):
    def __init__(self, config: GenreConfig):
        super().__init__()
        net, g = config.network, config.geometry
        self.size, self.pad, self.head = g.sph_size, g.sph_pad, net.inpaint_head
        self.hit_logit_min = math.log(g.sph_hit_probability / (1.0 - g.sph_hit_probability))
        if g.sph_padded_size % 32:
            raise ValueError(f"padded spherical map side {g.sph_padded_size} must be a multiple of 32")
        channels = 1 if self.head == "value" else 2
        self.encoder = ResNetEncoder(channels, net.inpaint_widths)
        self.decoder = UDecoder(net.inpaint_widths, channels, net.inpaint_decoder_blocks)

    def forward_parts(self, padded: torch.Tensor) -> dict[str, torch.Tensor]:
        """The raw outputs for (B, 1, P, P) padded partial maps (P = size + 2·pad).

        ``"value"`` head: ``{"map"}``, the padded full map (B, 1, P, P).
        ``"hit"`` head: ``{"map", "hit_logits", "radius"}``, each (B, 1, P, P);
        ``radius`` is in map units (not scaled) and ``map`` is composed from
        the two as described in the module docstring.
        """
        p = self.size + 2 * self.pad
        check_tensor("padded partial map", padded, ("B", 1, p, p))
        if self.head == "value":
            skips, deep = self.encoder(padded * 2.0 - 1.0)  # maps live in [0, 1]; centre them
            return {"map": padded + self.decoder(skips, deep)}  # predict the change from the input
        seen = (padded < NO_HIT).to(padded.dtype)
        radius_in = (1.0 - padded) * seen
        skips, deep = self.encoder(torch.cat([radius_in * RADIUS_SCALE, seen], dim=1))
        out = self.decoder(skips, deep)
        radius = radius_in + out[:, 1:2] / RADIUS_SCALE  # the change from the seen radius
        hit_logits = out[:, :1]
        return {"map": self.compose(hit_logits, radius), "hit_logits": hit_logits, "radius": radius}

    def compose(self, hit_logits: torch.Tensor, radius: torch.Tensor, hit_probability: float | None = None) -> torch.Tensor:
        """The hit head's map from its outputs (any equal shapes): ``1 − radius`` (kept below
        ``geometry.sph_nohit_min``) where the hit probability exceeds ``hit_probability``
        (default ``geometry.sph_hit_probability``), ``1`` (no hit) elsewhere."""
        logit_min = self.hit_logit_min if hit_probability is None else math.log(hit_probability / (1.0 - hit_probability))
        value = (1.0 - radius).clamp(0.0, MAX_HIT_VALUE)
        return torch.where(hit_logits > logit_min, value, torch.full_like(value, NO_HIT))

    def forward_padded(self, padded: torch.Tensor) -> torch.Tensor:
        """(B, 1, P, P) padded partial maps → (B, 1, P, P) padded full maps (P = size + 2·pad)."""
        return self.forward_parts(padded)["map"]

    def forward(self, partial: torch.Tensor) -> torch.Tensor:
        """(B, H, W) partial maps → (B, H, W) full maps."""
        check_tensor("partial map", partial, ("B", self.size, self.size))
        return crop_sph(self.forward_padded(pad_sph(partial[:, None], self.pad)), self.pad)[:, 0]
