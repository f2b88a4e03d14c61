"""What the networks make of one framed photo, and the view the steps after them read.

:class:`NetOutputs` is the networks' outputs of one photo (:meth:`.reconstruct.Reconstructor.run`'s stages ``depth`` to
``refine``), batches of one on the run's device; :class:`View` is the framed view the steps after the networks need
(:meth:`.options.MeshOptions.shape_grid`, :meth:`~.options.MeshOptions.snap_mesh`): the mask, the masked depth and the
camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..config import CameraConfig

__all__ = ["NetOutputs", "View"]


@dataclass(frozen=True)
class View:
    """One framed view (S = image size): ``mask`` (S, S) bool, ``depth`` (S, S) the masked depth (0 off the object),
    ``camera`` the camera they are seen through."""

    mask: torch.Tensor
    depth: torch.Tensor
    camera: CameraConfig


@dataclass(frozen=True)
class NetOutputs:
    """The networks on one framed photo (S = image size, H = spherical map size, N = voxel grid size), batches of one:
    ``depth`` (1, S, S), ``silhouette_logits`` (1, S, S), ``mask`` (1, S, S) bool, ``masked_depth`` (1, S, S),
    ``partial_sph`` and ``full_sph`` (1, H, H), ``vox_sph``, ``vox_depth`` and ``logits`` (1, 1, N, N, N)."""

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
        """The mask and the masked depth (S, S), seen through ``camera``."""
        return View(self.mask[0], self.masked_depth[0], camera)

    def images(self) -> dict[str, torch.Tensor]:
        """Name → the output without its batch axis (and a grid's channel axis): (S, S), (H, H) or (N, N, N), as
        :attr:`.result.Reconstruction.intermediates` keeps them."""
        maps = ("depth", "silhouette_logits", "mask", "masked_depth", "partial_sph", "full_sph")
        return {**{k: getattr(self, k)[0] for k in maps}, **{k: getattr(self, k)[0, 0] for k in ("vox_sph", "vox_depth", "logits")}}
