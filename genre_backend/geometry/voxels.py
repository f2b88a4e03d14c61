"""Points → voxels with GenRe's "average distance, negate, add 1" rule, and the silhouette's voxels.

The grid covers the cube ``[-0.5, 0.5]^3`` of the view frame (see
:mod:`genre_backend.frame`) with ``N`` voxels per side, indexed
``grid[b, 0, ix, iy, iz]`` along view x, y, z.  Voxel ``(ix, iy, iz)`` has its
centre at ``((ix, iy, iz) + 0.5) / N − 0.5``.

For every voxel hit by at least one point the value is ``1 − mean_k |p_k − c|/h``
(``c`` the voxel centre, ``h = 1/N`` the pitch, so values lie in
``(1 − √3/2, 1] ≈ (0.134, 1]``); empty voxels hold 0.  Points outside the cube
or masked out are ignored.  The result is differentiable with respect to the
point coordinates (scatter-add of distances and counts).
"""

from __future__ import annotations

import math

import torch

from ..validation import check_mask, check_positive_int, check_tensor

__all__ = ["points_to_voxels", "points_to_voxels_reference", "silhouette_voxels", "silhouette_voxels_reference",
           "voxel_centres"]


def voxel_centres(resolution: int, *, dtype=torch.float32, device=None) -> torch.Tensor:
    """Coordinates (N,) of voxel centres along one axis of an N-voxel grid over [-0.5, 0.5]."""
    check_positive_int("resolution", resolution)
    return (torch.arange(resolution, dtype=dtype, device=device) + 0.5) / resolution - 0.5


def points_to_voxels(points: torch.Tensor, resolution: int, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Voxelise batched point sets with the paper's rule.

    points: (B, P, 3) float view-frame points.
    mask:   (B, P) bool, optional; False entries are ignored.
    Returns (B, 1, N, N, N) float with N = ``resolution``.
    """
    check_tensor("points", points, ("B", "P", 3))
    check_positive_int("resolution", resolution)
    if mask is not None:
        check_mask("mask", mask, points[..., 0])
    batch, count = points.shape[:2]
    n = resolution
    scaled = (points + 0.5) * n  # voxel units; voxel k spans [k, k+1)
    index = torch.floor(scaled.detach())
    inside = ((index >= 0) & (index < n)).all(dim=-1)
    if mask is not None:
        inside = inside & mask
    index = index.clamp(0, n - 1).long()
    dist = torch.linalg.vector_norm(scaled - (index.to(points.dtype) + 0.5), dim=-1)
    flat = ((torch.arange(batch, device=points.device).view(batch, 1) * n + index[..., 0]) * n + index[..., 1]) * n + index[..., 2]
    flat, dist = flat[inside], dist[inside]
    total = points.new_zeros(batch * n**3).index_add(0, flat, dist)
    hits = points.new_zeros(batch * n**3).index_add(0, flat, torch.ones_like(dist))
    occupied = hits > 0
    values = torch.where(occupied, 1.0 - total / hits.clamp(min=1.0), torch.zeros_like(total))
    return values.view(batch, 1, n, n, n)


def points_to_voxels_reference(points: torch.Tensor, resolution: int, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Plain-loop reference of :func:`points_to_voxels` (slow; for tests and benchmarks)."""
    check_tensor("points", points, ("B", "P", 3))
    n = resolution
    out = torch.zeros(points.shape[0], 1, n, n, n, dtype=torch.float64)
    for b in range(points.shape[0]):
        sums: dict[tuple[int, int, int], list[float]] = {}
        for k in range(points.shape[1]):
            if mask is not None and not bool(mask[b, k]):
                continue
            p = [float(v) for v in points[b, k]]
            idx = tuple(int((c + 0.5) * n // 1) for c in p)
            if not all(0 <= i < n for i in idx):
                continue
            centre = [(i + 0.5) / n - 0.5 for i in idx]
            d = sum((pc - cc) ** 2 for pc, cc in zip(p, centre)) ** 0.5 * n
            sums.setdefault(idx, []).append(d)
        for idx, ds in sums.items():
            out[(b, 0) + idx] = 1.0 - sum(ds) / len(ds)
    return out.to(points.dtype)


def silhouette_voxels(mask: torch.Tensor, camera, resolution: int) -> torch.Tensor:
    """The voxels whose centre the camera sees inside the object's mask (a one-view visual hull).

    mask:   (B, S, S) bool, the object's pixels in the model's square input image.
    camera: :class:`genre_backend.config.CameraConfig` (the view frame of :mod:`genre_backend.frame`).
    Returns (B, 1, N, N, N) bool with N = ``resolution``: voxel ``(ix, iy, iz)`` is True when its centre
    projects (:func:`genre_backend.frame.view_to_pixels`) into a pixel of ``mask`` that is True.  Centres
    that project outside the image, or lie at or behind the camera, are False.  No object point can lie
    in a False voxel's centre, so the surface is carved there (``GeometryConfig.silhouette_carve``).
    """
    from ..frame import view_to_pixels

    check_tensor("mask", mask, ("B", "S", "S"), floating=False)
    check_positive_int("resolution", resolution)
    size = mask.shape[-1]
    c = voxel_centres(resolution, device=mask.device)
    centres = torch.stack(torch.meshgrid(c, c, c, indexing="ij"), dim=-1)  # (N, N, N, 3): view x, y, z
    uv, depth = view_to_pixels(centres, camera, size)
    cell = torch.floor(uv).long()
    seen = ((cell >= 0) & (cell < size)).all(dim=-1) & (depth > 0)
    cell = cell.clamp(0, size - 1)
    inside = mask.bool()[:, cell[..., 1], cell[..., 0]]  # rows are v, columns u
    return (inside & seen)[:, None]


def silhouette_voxels_reference(mask: torch.Tensor, camera, resolution: int) -> torch.Tensor:
    """Plain-loop reference of :func:`silhouette_voxels`: the pinhole projection written out per voxel."""
    check_tensor("mask", mask, ("B", "S", "S"), floating=False)
    n, size = resolution, mask.shape[-1]
    f = camera.lens_mm / camera.sensor_mm * size
    out = torch.zeros(mask.shape[0], 1, n, n, n, dtype=torch.bool)
    for ix in range(n):
        for iy in range(n):
            for iz in range(n):
                x, y, z = ((ix + 0.5) / n - 0.5, (iy + 0.5) / n - 0.5, (iz + 0.5) / n - 0.5)
                d = camera.distance - z  # planar depth: the camera looks down −z from (0, 0, distance)
                if d <= 0:
                    continue
                col, row = math.floor(x * f / d + size / 2.0), math.floor(-y * f / d + size / 2.0)
                if 0 <= col < size and 0 <= row < size:
                    for b in range(mask.shape[0]):
                        out[b, 0, ix, iy, iz] = bool(mask[b, row, col])
    return out
