"""A mesh as the camera sees it: planar depth maps by exact ray–triangle tests (a z-buffer in torch).

:func:`mesh_depth` is what the GPU burst (``training/learn/burst.py``) renders
its training depth maps with, where no Blender exists: the same camera as
every render (:mod:`genre_backend.frame`: pixel centres at +0.5, principal
point at the image centre, planar depth along −z from the camera at
``(0, 0, d)``, background 0).  Each triangle is tested against the pixels of
its projected bounding box; a pixel's depth is the exact intersection of its
ray with the triangle's plane, and the nearest hit wins.
:func:`mesh_depth_reference` is a plain per-pixel loop (Möller–Trumbore in
float64) for the tests.
"""

from __future__ import annotations

import numpy as np
import torch

from .. import frame
from ..config import CameraConfig
from ..validation import check_positive_int, check_tensor
from .spherical import ray_triangles_reference

__all__ = ["mesh_depth", "mesh_depth_reference", "pixel_rays", "seen_from_camera"]


def pixel_rays(camera: CameraConfig, image_size: int, *, dtype=torch.float32, device=None) -> torch.Tensor:
    """Ray directions (S, S, 3) of the pixel centres in the view frame, scaled to planar depth 1 (z = −1)."""
    f = camera.focal_px(image_size)
    c = torch.arange(image_size, dtype=dtype, device=device) + 0.5 - image_size / 2.0
    x = (c / f).view(1, -1).expand(image_size, image_size)
    y = (-c / f).view(-1, 1).expand(image_size, image_size)
    return torch.stack([x, y, -torch.ones_like(x)], dim=-1)


def _pairs(count: torch.Tensor, chunk_pairs: int):
    """Yield (first, stop) triangle ranges whose candidate counts sum to about ``chunk_pairs`` at most."""
    ends = torch.cumsum(count, 0)
    start = 0
    while start < count.shape[0]:
        base = int(ends[start - 1]) if start > 0 else 0
        stop = max(int(torch.searchsorted(ends, base + chunk_pairs, right=True)), start + 1)
        yield start, stop
        start = stop


def mesh_depth(triangles: torch.Tensor, batch_index: torch.Tensor, batch_size: int, camera: CameraConfig,
               image_size: int, *, chunk_pairs: int = 8_000_000) -> torch.Tensor:
    """Planar depth maps (B, S, S) of view-frame triangle soups; 0 where no triangle is hit.

    triangles:   (T, 3, 3) float view-frame vertices (in front of the camera: z < distance).
    batch_index: (T,) int64, which map each triangle belongs to.
    A pixel counts as covered when its centre lies inside (or on an edge of)
    the triangle's projection; its depth ``t`` solves ``n·(c + t·r − v0) = 0``
    for the camera centre ``c`` and the pixel's ray ``r`` (:func:`pixel_rays`).
    Triangles seen exactly edge-on are skipped.  Not differentiable (targets).
    """
    check_tensor("triangles", triangles, (None, 3, 3))
    check_positive_int("batch_size", batch_size)
    check_positive_int("image_size", image_size)
    if not isinstance(batch_index, torch.Tensor) or batch_index.dtype != torch.int64 or batch_index.shape != triangles.shape[:1]:
        raise ValueError(f"batch_index: expected an int64 tensor of shape ({triangles.shape[0]},)")
    s = image_size
    dev, dt = triangles.device, triangles.dtype
    depth = torch.full((batch_size * s * s,), float("inf"), dtype=dt, device=dev)
    if triangles.shape[0] == 0:
        return torch.zeros((batch_size, s, s), dtype=dt, device=dev)
    with torch.no_grad():
        f = camera.focal_px(s)
        z = camera.distance - triangles[..., 2]  # planar depth of each vertex (T, 3)
        if bool((z <= 0).any()):
            raise ValueError("triangles: every vertex must lie in front of the camera (z < camera.distance)")
        u = triangles[..., 0] * f / z + s / 2.0
        v = -triangles[..., 1] * f / z + s / 2.0
        c0 = torch.ceil(u.min(dim=1).values - 0.5).clamp(0, s - 1).long()
        c1 = torch.floor(u.max(dim=1).values - 0.5).clamp(-1, s - 1).long()
        r0 = torch.ceil(v.min(dim=1).values - 0.5).clamp(0, s - 1).long()
        r1 = torch.floor(v.max(dim=1).values - 0.5).clamp(-1, s - 1).long()
        ncol, nrow = (c1 - c0 + 1).clamp(min=0), (r1 - r0 + 1).clamp(min=0)
        count = ncol * nrow
        v0, v1, v2 = triangles.unbind(dim=1)
        normal = torch.cross(v1 - v0, v2 - v0, dim=-1)
        centre = triangles.new_tensor([0.0, 0.0, camera.distance])
        offset = (normal * (v0 - centre)).sum(-1)  # n·(v0 − c)
        rays = pixel_rays(camera, s, dtype=dt, device=dev).reshape(-1, 3)
        # 2D edge functions of the projection, signed so that the inside is positive for either winding
        area = (u[:, 1] - u[:, 0]) * (v[:, 2] - v[:, 0]) - (u[:, 2] - u[:, 0]) * (v[:, 1] - v[:, 0])
        sign = torch.sign(area)
        for start, stop in _pairs(count, chunk_pairs):
            cnt = count[start:stop]
            idx = torch.repeat_interleave(torch.arange(start, stop, device=dev), cnt)
            if idx.numel() == 0:
                continue
            first = torch.cumsum(cnt, 0) - cnt
            k = torch.arange(idx.shape[0], device=dev) - torch.repeat_interleave(first, cnt)
            rows = r0[idx] + torch.div(k, ncol[idx], rounding_mode="floor")
            cols = c0[idx] + torch.remainder(k, ncol[idx])
            pu, pv = cols.to(dt) + 0.5, rows.to(dt) + 0.5
            ui, vi, sg = u[idx], v[idx], sign[idx]
            inside = sg != 0
            for a, b in ((0, 1), (1, 2), (2, 0)):
                edge = (ui[:, b] - ui[:, a]) * (pv - vi[:, a]) - (vi[:, b] - vi[:, a]) * (pu - ui[:, a])
                inside &= edge * sg >= 0
            pix = rows * s + cols
            denom = (normal[idx] * rays[pix]).sum(-1)
            t = offset[idx] / torch.where(denom == 0, torch.ones_like(denom), denom)
            ok = inside & (denom != 0) & (t > 0)
            target = batch_index[idx[ok]] * (s * s) + pix[ok]
            depth.scatter_reduce_(0, target, t[ok], reduce="amin", include_self=True)
    depth = torch.where(torch.isinf(depth), torch.zeros_like(depth), depth)
    return depth.view(batch_size, s, s)


def mesh_depth_reference(triangles: np.ndarray, camera: CameraConfig, image_size: int) -> np.ndarray:
    """Plain reference of :func:`mesh_depth` for one map: every pixel's ray against every triangle.

    triangles: (T, 3, 3) float view-frame vertices.  Möller–Trumbore in
    float64 from the camera centre along the pixel's ray (planar depth 1);
    returns (S, S) float64 planar depth, 0 where nothing is hit.
    """
    rays = pixel_rays(camera, image_size, dtype=torch.float64).numpy()
    origin = np.array([0.0, 0.0, camera.distance])
    out = np.zeros((image_size, image_size))
    for i in range(image_size):
        for j in range(image_size):
            hit, t = ray_triangles_reference(origin, rays[i, j], triangles)
            if hit.any():
                out[i, j] = t[hit].min()
    return out


def seen_from_camera(points: torch.Tensor, triangles: torch.Tensor, camera: CameraConfig, image_size: int = 256,
                     tolerance: float = 0.02) -> torch.Tensor:
    """Which view-frame points (P, 3) on a mesh's surface the camera sees → (P,) bool.

    triangles: (T, 3, 3) the mesh in the view frame.  A point is seen when its
    planar depth is within ``tolerance`` (scene units; the objects' bounding-box
    diagonal is 1) of the farthest surface the mesh shows at the point's pixel
    and the 8 around it (:func:`mesh_depth` at ``image_size``²).  The
    neighbours stand for the pixel's footprint: a point on a surface seen
    edge-on lies deeper than its pixel centre's hit, and one on the outline
    can fall in a pixel whose centre misses the mesh.  What that costs: hidden
    points within a pixel of an occluding edge count as seen.  Points outside
    the picture are hidden.
    """
    check_tensor("points", points, (None, 3))
    depth = mesh_depth(triangles.to(torch.float64), torch.zeros(triangles.shape[0], dtype=torch.int64), 1, camera, image_size)[0]
    farthest = torch.nn.functional.max_pool2d(depth[None, None], 3, stride=1, padding=1)[0, 0]  # (misses are 0)
    uv, d = frame.view_to_pixels(points.to(torch.float64), camera, image_size)
    inside = (uv >= 0).all(-1) & (uv < image_size).all(-1)
    cr = uv.floor().long().clamp(0, image_size - 1)
    return inside & (d <= farthest[cr[:, 1], cr[:, 0]] + tolerance)
