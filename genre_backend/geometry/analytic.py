"""Exact depth maps of analytic shapes, for tests and benchmarks."""

from __future__ import annotations

import math

import torch

from ..config import CameraConfig

__all__ = ["sphere_depth", "sphere_silhouette_radius_px"]


def sphere_depth(camera: CameraConfig, size: int, radius: float, *, dtype=torch.float64) -> torch.Tensor:
    """Exact planar depth (1, S, S) of a sphere of ``radius`` at the view-frame origin (background 0)."""
    if not 0.0 < radius < camera.distance:
        raise ValueError(f"radius must lie in (0, {camera.distance}), got {radius}")
    f = camera.focal_px(size)
    c = torch.arange(size, dtype=torch.float64) + 0.5 - size / 2.0
    qx, qy = c.view(1, size) / f, -c.view(size, 1) / f
    q2 = qx**2 + qy**2 + 1.0  # squared length of the ray direction with unit planar depth
    d = camera.distance
    disc = d * d - q2 * (d * d - radius * radius)
    depth = torch.where(disc > 0, (d - torch.sqrt(disc.clamp(min=0))) / q2, torch.zeros(()))
    return depth[None].to(dtype)


def sphere_silhouette_radius_px(camera: CameraConfig, size: int, radius: float) -> float:
    """Radius in pixels of the sphere's silhouette disc around the image centre."""
    return camera.focal_px(size) * math.tan(math.asin(radius / camera.distance))
