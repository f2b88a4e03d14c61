"""The training losses, shared by ``genre train`` (:mod:`training.learn.stage`) and the GPU burst
(:mod:`training.learn.burst`).  Each takes tensors and the config it needs, nothing else.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from genre_backend.geometry.spherical import pad_sph
from genre_backend.nets.inpaint_net import RADIUS_SCALE
from genre_backend.validation import check_tensor

__all__ = ["DEPTH_GRADIENT_STRIDES", "OUTLINE_STEP", "depth_gradient_loss", "depth_mse", "outline_loss", "sph_loss", "voxel_loss"]


DEPTH_GRADIENT_STRIDES = (1, 2, 4, 8)


def depth_mse(pred: torch.Tensor, true: torch.Tensor, valid: torch.Tensor, offset_weight: float = 1.0) -> torch.Tensor:
    """The depth's squared error over the valid pixels, its per-view offset weighed ``offset_weight`` times.

    pred, true: (B, H, W) depth; valid: (B, H, W) bool.  Each view's error
    ``e = pred - true`` over its valid pixels splits exactly into its mean
    ``m`` (the offset along the view) and the rest (the relief):
    ``sum e² = sum (e - m)² + n m²``.  The loss is
    ``(sum over views of sum (e - m)² + offset_weight · n m²) / (valid pixels)``:
    at 1 the plain MSE over the batch's valid pixels; at 0 a constant error
    costs nothing (scale-invariant losses weigh the offset down likewise: Eigen
    et al., NeurIPS 2014).  Returns a scalar tensor.
    """
    check_tensor("pred", pred, ("B", "H", "W"))
    check_tensor("true", true, tuple(pred.shape))
    check_tensor("valid", valid, tuple(pred.shape), floating=False, finite=False)
    if not (isinstance(offset_weight, (int, float)) and not isinstance(offset_weight, bool)
            and math.isfinite(offset_weight) and offset_weight >= 0):
        raise ValueError(f"offset_weight: expected a finite number >= 0, got {offset_weight!r}")
    v = valid.to(pred.dtype)
    err = (pred - true) * v
    n = v.sum(dim=(1, 2))
    mean = err.sum(dim=(1, 2)) / n.clamp(min=1)
    relief = (((err - mean[:, None, None]) * v) ** 2).sum()
    return (relief + offset_weight * (n * mean ** 2).sum()) / n.sum().clamp(min=1)


def depth_gradient_loss(pred: torch.Tensor, true: torch.Tensor, valid: torch.Tensor,
                        strides: tuple[int, ...] = DEPTH_GRADIENT_STRIDES) -> torch.Tensor:
    """Multi-scale gradient matching of a depth map (after Li & Snavely, MegaDepth, 2018).

    pred, true: (B, H, W) depth; valid: (B, H, W) bool, the pixels whose true
    depth counts.  For each stride s the error map ``pred - true`` is sampled
    every s pixels and its differences between horizontally and vertically
    neighbouring samples, both valid, are taken; the term is the mean absolute
    difference over those pairs, averaged over the strides (a stride without a
    pair counts 0).  It is 0 for an error that is the same at every valid
    pixel (an offset) and grows with a wrong slope or wrong relief, which the
    MSE of the depth weighs only by their share of the error.
    Returns a scalar tensor.
    """
    check_tensor("pred", pred, ("B", "H", "W"))
    check_tensor("true", true, tuple(pred.shape))
    check_tensor("valid", valid, tuple(pred.shape), floating=False, finite=False)
    if valid.dtype != torch.bool:
        raise ValueError(f"valid: expected a bool tensor, got {valid.dtype}")
    if not strides or any(isinstance(s, bool) or not isinstance(s, int) or s < 1 for s in strides):
        raise ValueError(f"strides: expected positive ints, got {strides!r}")
    err = pred - true
    total = err.new_zeros(())
    for s in strides:
        e, v = err[:, ::s, ::s], valid[:, ::s, ::s]
        pairs_x, pairs_y = v[:, :, 1:] & v[:, :, :-1], v[:, 1:, :] & v[:, :-1, :]
        diff_x = (e[:, :, 1:] - e[:, :, :-1]).abs() * pairs_x
        diff_y = (e[:, 1:, :] - e[:, :-1, :]).abs() * pairs_y
        count = pairs_x.sum() + pairs_y.sum()
        total = total + (diff_x.sum() + diff_y.sum()) / count.clamp(min=1)
    return total / len(strides)


def sph_loss(parts: dict[str, torch.Tensor], full_sph: torch.Tensor, geometry, kind: str = "mse"
             ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The spherical maps' loss on padded maps.

    parts: the inpainting net's :meth:`~genre_backend.nets.inpaint_net.InpaintNet.forward_parts`
    output; full_sph: (B, H, H) the true full maps; geometry: the model's GeometryConfig;
    kind: ``"mse"`` or ``"l1"``.  The ``"value"`` head: the map's MSE (or L1) against
    the true map.  The ``"hit"`` head: the hit logits' BCE against the true map's
    hits, plus the radius's MSE (or L1, ×RADIUS_SCALE) on the true hits.
    Returns (loss, {term name: value}).
    """
    target = pad_sph(full_sph[:, None], geometry.sph_pad)
    err = F.l1_loss if kind == "l1" else F.mse_loss
    if "hit_logits" not in parts:
        loss = err(parts["map"], target)
        return loss, {f"sph_{kind}": loss}
    hit = target < geometry.sph_nohit_min
    l_hit = F.binary_cross_entropy_with_logits(parts["hit_logits"], hit.to(target.dtype))
    per_pixel = err(parts["radius"] * RADIUS_SCALE, (1.0 - target) * RADIUS_SCALE, reduction="none")
    l_radius = (per_pixel * hit).sum() / hit.sum().clamp(min=1)
    return l_hit + l_radius, {"sph_hit_bce": l_hit, f"sph_radius_{kind}": l_radius}


def voxel_loss(logits: torch.Tensor, voxels: torch.Tensor, surface_weight: float
               ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """BCE over the grid + ``surface_weight`` × the BCE weighted by the target (the shell's voxels, or the distance's ramp).

    logits: (B, 1, N, N, N); voxels: (B, N, N, N) the target in [0, 1].  The
    target's own entropy is subtracted per voxel (a constant: the gradients
    are the BCE's), so that the loss is the KL divergence, 0 at a perfect fit
    for the soft distance target as for the binary shell.
    """
    target = voxels[:, None]
    entropy = -(torch.xlogy(target, target) + torch.xlogy(1 - target, 1 - target))
    bce = F.binary_cross_entropy_with_logits(logits, target, reduction="none") - entropy
    l_all = bce.mean()
    l_surf = (bce * target).sum() / target.sum().clamp(min=1)
    return l_all + surface_weight * l_surf, {"voxel_bce": l_all, "surface_bce": l_surf}


OUTLINE_STEP = 1.0  # outline_loss samples each ray every voxel of depth


def outline_loss(logits: torch.Tensor, voxels: torch.Tensor, camera) -> torch.Tensor:
    """The BCE between what the predicted grid and the true one show the camera, less the truth's own entropy.

    logits: (B, 1, N, N, N) the refiner's; voxels: (B, N, N, N) the target in [0, 1].  Each grid's
    silhouette is the largest value along each pixel's ray, an N × N image through the view's camera
    (:func:`genre_backend.geometry.voxels.ray_max`); the term is their per-pixel BCE with the true one as
    target, 0 at a perfect fit.  The grid's BCE spreads a part left out (a thin leg, the rim along the
    outline) over a few voxels among N³; here it costs a whole pixel of the outline: this is the mesh
    covering the object's mask, which the real-photo check asks for and *Fill Visible Holes* otherwise
    buys at test time.  Returns a scalar tensor.
    """
    from genre_backend.geometry.voxels import ray_max

    check_tensor("logits", logits, ("B", 1, "N", "N", "N"))
    check_tensor("voxels", voxels, (logits.shape[0], *logits.shape[2:]))
    n = logits.shape[-1]
    with torch.no_grad():
        target = ray_max(voxels[:, None].float(), camera, n, OUTLINE_STEP).clamp(0.0, 1.0)
    eps = 1e-6
    pred = ray_max(torch.sigmoid(logits.float()), camera, n, OUTLINE_STEP).clamp(eps, 1.0 - eps)
    # written out: F.binary_cross_entropy refuses to run under autocast
    bce = -(target * torch.log(pred) + (1 - target) * torch.log1p(-pred))
    entropy = -(torch.xlogy(target, target) + torch.xlogy(1 - target, 1 - target))
    return (bce - entropy).mean()
