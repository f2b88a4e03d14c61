"""The depth net's surface normals: a training-only head, its target from the true depth, and its loss.

The original's depth estimator also predicts surface normals (``shared/method.md``: MSE on depth *and
normals* inside the silhouette).  Shading is a function of the normal, not of the depth, so a head that must
give the normal at each pixel asks the shared encoder for what the picture's shading says, which the depth's
loss alone (a relief that follows the outline) has not taught it here (``results/stage_errors/depth.md``).

The head is a second :class:`~genre_backend.nets.uresnet.UDecoder` on the depth net's encoder
(:meth:`~genre_backend.nets.depth_net.DepthNet.encode`); it lives in the training stage
(:class:`training.learn.stage.StageModule`, recipe field ``normals_weight``), is kept in the stage's
checkpoint, and never reaches a weights file: inference does not use it.

Normals are in the view frame (:mod:`genre_backend.frame`: x right, y up, z toward the camera) and face the
camera (z > 0 on a surface it sees).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from genre_backend.config import CameraConfig
from genre_backend.frame import depth_to_points
from genre_backend.nets.uresnet import UDecoder
from genre_backend.validation import check_tensor

__all__ = ["MAX_DEPTH_STEP", "NormalsHead", "depth_normals", "normals_loss"]

# the largest depth difference (scene units; the shape's diagonal is 1) between a pixel and either neighbour
# that still counts as one surface: a pixel at 128² and 2.2 away is ~0.011 wide, so this keeps slopes to ~78°
# and drops the steps where one part hides another
MAX_DEPTH_STEP = 0.05


def depth_normals(depth: torch.Tensor, camera: CameraConfig, max_step: float = MAX_DEPTH_STEP
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit normals of planar depth maps by central differences of their back-projected points.

    depth: (B, S, S) planar depth, background 0 (:func:`genre_backend.frame.depth_to_points`'s encoding).
    Returns ``(normals, valid)``: normals (B, 3, S, S) facing the camera, zero where not valid; valid
    (B, S, S) bool: the pixel and its four neighbours on the object, each neighbour within ``max_step``
    of it in depth (no image border pixel is valid).
    """
    check_tensor("depth", depth, ("B", "S", "S"))
    if not max_step > 0:
        raise ValueError(f"max_step: expected a positive number, got {max_step!r}")
    points = depth_to_points(depth, camera)  # (B, S, S, 3)
    du = points[:, 1:-1, 2:] - points[:, 1:-1, :-2]  # along the columns (image right)
    dv = points[:, 2:, 1:-1] - points[:, :-2, 1:-1]  # along the rows (image down)
    n = torch.cross(dv, du, dim=-1)  # right × down would face away; down × right faces the camera
    centre = depth[:, 1:-1, 1:-1]
    near = [depth[:, 1:-1, 2:], depth[:, 1:-1, :-2], depth[:, 2:, 1:-1], depth[:, :-2, 1:-1]]
    ok = centre > 0
    for d in near:
        ok = ok & (d > 0) & ((d - centre).abs() <= max_step)
    length = n.norm(dim=-1)
    ok = ok & (length > 0)
    n = torch.where(ok[..., None], n / length.clamp(min=1e-12)[..., None], torch.zeros_like(n))
    normals = F.pad(n.permute(0, 3, 1, 2), (1, 1, 1, 1))
    valid = F.pad(ok, (1, 1, 1, 1), value=False)
    return normals, valid


def normals_loss(pred: torch.Tensor, true: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean of 1 − cos(angle) between the predicted (B, 3, S, S; any length, normalised here) and the true
    unit normals over the valid pixels (B, S, S bool); 0 where none is valid.  Returns a scalar tensor."""
    check_tensor("pred", pred, ("B", 3, "S", "S"))
    check_tensor("true", true, tuple(pred.shape))
    check_tensor("valid", valid, (pred.shape[0], pred.shape[2], pred.shape[3]), floating=False, finite=False)
    cos = (F.normalize(pred, dim=1, eps=1e-6) * true).sum(dim=1)
    return ((1.0 - cos) * valid).sum() / valid.sum().clamp(min=1)


class NormalsHead(nn.Module):
    """A decoder of the depth net's widths from its encoder's features to three channels (the normal, any length)."""

    def __init__(self, widths: tuple[int, int, int, int], blocks: int):
        super().__init__()
        self.decoder = UDecoder(tuple(widths), 3, blocks)

    def forward(self, skips: list[torch.Tensor], deep: torch.Tensor) -> torch.Tensor:
        return self.decoder(skips, deep)
