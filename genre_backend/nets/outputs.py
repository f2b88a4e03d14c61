"""What the networks make of a framed photo, and the view the steps after them read.

:class:`NetOutputs` is every intermediate of the pipeline (:meth:`.model.GenRe.forward`; ``genre reconstruct``'s stages
``depth`` to ``refine``); :class:`View` is the framed view the steps after the networks need
(:meth:`genre_backend.inference.options.MeshOptions.shape_grid`, ``snap_mesh``): the mask, the masked depth and the
camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..config import CameraConfig

__all__ = ["NetOutputs", "View"]


@dataclass(frozen=True)
class View:
    """One framed view (S = image size, H = spherical map size): ``mask`` (S, S) bool, ``depth`` (S, S) the masked
    depth (0 off the object), ``camera`` the camera they are seen through, ``sph`` (H, H) the full spherical map the
    refiner read (``None``: a row without one)."""

    mask: torch.Tensor
    depth: torch.Tensor
    camera: CameraConfig
    sph: torch.Tensor | None = None


@dataclass(frozen=True)
class NetOutputs:
    """The networks on a batch of B framed photos (S = image size, H = spherical map size, N = voxel grid size):
    ``depth`` (B, S, S), ``silhouette_logits`` (B, S, S), ``mask`` (B, S, S) bool, ``masked_depth`` (B, S, S),
    ``partial_sph`` and ``full_sph`` (B, H, H), ``vox_sph``, ``vox_depth`` and ``logits`` (B, 1, N, N, N).
    :meth:`view` and :meth:`images` read the first photo of the batch."""

    depth: torch.Tensor
    silhouette_logits: torch.Tensor
    mask: torch.Tensor
    masked_depth: torch.Tensor
    partial_sph: torch.Tensor
    full_sph: torch.Tensor
    vox_sph: torch.Tensor
    vox_depth: torch.Tensor
    logits: torch.Tensor

    def view(self, camera: CameraConfig) -> View:
        """The first photo's mask, masked depth (S, S) and full spherical map (H, H), seen through ``camera``."""
        return View(self.mask[0], self.masked_depth[0], camera, self.full_sph[0])

    def images(self) -> dict[str, torch.Tensor]:
        """Name → the first photo's output without its batch axis (and a grid's channel axis): (S, S), (H, H) or
        (N, N, N), as ``Reconstruction.intermediates`` keeps them."""
        maps = ("depth", "silhouette_logits", "mask", "masked_depth", "partial_sph", "full_sph")
        return {**{k: getattr(self, k)[0] for k in maps}, **{k: getattr(self, k)[0, 0] for k in ("vox_sph", "vox_depth", "logits")}}
