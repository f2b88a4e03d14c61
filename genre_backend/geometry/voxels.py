"""Points → voxels with GenRe's "average distance, negate, add 1" rule, and the silhouette's ramp.

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

import numpy as np
import torch

from ..validation import check_mask, check_positive_int, check_tensor

__all__ = ["points_to_voxels", "points_to_voxels_reference", "silhouette_ramp", "silhouette_ramp_reference",
           "voxel_centres", "mirror_voxels", "ray_first_hit", "ray_last_hit",
           "ray_first_hit_reference", "ray_max", "ray_max_reference"]


def voxel_centres(resolution: int, *, dtype=torch.float32, device=None) -> torch.Tensor:
    """Coordinates (N,) of voxel centres along one axis of an N-voxel grid over [-0.5, 0.5]."""
    check_positive_int("resolution", resolution)
    return (torch.arange(resolution, dtype=dtype, device=device) + 0.5) / resolution - 0.5


def mirror_voxels(grid: torch.Tensor) -> torch.Tensor:
    """Grids (…, N, N, N) indexed (x, y, z), as :func:`points_to_voxels` writes them, of the scene
    reflected in the view frame's x = 0 plane: voxel ``i`` along x takes voxel ``N − 1 − i``
    (the grid spans [−0.5, 0.5], so the reflection maps voxel centres onto voxel centres)."""
    if grid.dim() < 3 or not (grid.shape[-1] == grid.shape[-2] == grid.shape[-3]):
        raise ValueError(f"grid: expected (..., N, N, N), got {tuple(grid.shape)}")
    return torch.flip(grid, dims=(-3,))


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



def _signed_pixel_distance(mask: np.ndarray) -> np.ndarray:
    """(S, S) bool → (S, S) float32: each pixel centre's distance to the mask's outline, in pixels, + inside.

    The outline runs along pixel edges: a pixel next to one of the other side is 0.5 from it.
    """
    from scipy import ndimage

    inside = ndimage.distance_transform_edt(mask) if mask.any() else np.zeros(mask.shape)
    outside = ndimage.distance_transform_edt(~mask) if (~mask).any() else np.zeros(mask.shape)
    return np.where(mask, inside - 0.5, 0.5 - outside).astype(np.float32)


def silhouette_ramp(mask: torch.Tensor, camera, resolution: int, width: float = 1.0) -> torch.Tensor:
    """How far inside the object's outline the camera sees each voxel centre, as a ramp in [0, 1].

    mask:   (B, S, S) bool, the object's pixels in the model's square input image.
    camera: :class:`genre_backend.config.CameraConfig` (the view frame of :mod:`genre_backend.frame`).
    width:  voxels over which the ramp rises from 0 to 1, centred on the outline.
    Returns (B, 1, N, N, N) float32 with N = ``resolution``: ``clip(0.5 + d / width, 0, 1)``, with ``d`` the
    signed distance (in voxels at the centre's depth, + inside) from the centre's projection
    (:func:`genre_backend.frame.view_to_pixels`) to the mask's outline: the pixel centres' exact Euclidean
    distances to the outline (which runs along pixel edges), interpolated bilinearly.  No object point can lie
    where the ramp is 0 (a one-view visual hull); ``min(probability, ramp)`` carves the refiner's output to
    the outline with a surface that follows it smoothly instead of in voxel steps
    (``GeometryConfig.silhouette_carve``).  Centres beyond the image's edge take its border's value;
    centres at or behind the camera are 0.
    """
    from ..frame import view_to_pixels

    check_tensor("mask", mask, ("B", "S", "S"), floating=False)
    check_positive_int("resolution", resolution)
    if not (math.isfinite(width) and width > 0):
        raise ValueError(f"width: expected a positive number of voxels, got {width!r}")
    size = mask.shape[-1]
    sd = torch.from_numpy(np.stack([_signed_pixel_distance(m) for m in mask.bool().cpu().numpy()]))[:, None]
    c = voxel_centres(resolution)
    centres = torch.stack(torch.meshgrid(c, c, c, indexing="ij"), dim=-1)  # (N, N, N, 3): view x, y, z
    uv, depth = view_to_pixels(centres, camera, size)
    grid = (uv / size * 2.0 - 1.0).reshape(1, -1, 1, 2).expand(mask.shape[0], -1, -1, -1)
    d_px = torch.nn.functional.grid_sample(sd, grid, mode="bilinear", padding_mode="border", align_corners=False)
    d_px = d_px.view(mask.shape[0], 1, resolution, resolution, resolution)
    d_vox = d_px * (depth / camera.focal_px(size) * resolution)  # a pixel spans depth/f world units, a voxel 1/N
    ramp = (0.5 + d_vox / width).clamp(0.0, 1.0)
    return torch.where(depth > 0, ramp, torch.zeros_like(ramp)).to(mask.device)


def silhouette_ramp_reference(mask: torch.Tensor, camera, resolution: int, width: float = 1.0) -> torch.Tensor:
    """Plain-loop reference of :func:`silhouette_ramp`: brute-force distances, the pinhole and the bilinear
    interpolation written out per voxel."""
    check_tensor("mask", mask, ("B", "S", "S"), floating=False)
    n, size = resolution, mask.shape[-1]
    f = camera.lens_mm / camera.sensor_mm * size
    out = torch.zeros(mask.shape[0], 1, n, n, n, dtype=torch.float64)
    for b in range(mask.shape[0]):
        m = mask[b].bool().tolist()
        cells = [(r, c) for r in range(size) for c in range(size)]
        sd = [[0.0] * size for _ in range(size)]
        for r, c in cells:  # the nearest pixel centre on the other side, less half a pixel
            other = [math.hypot(r - r2, c - c2) for r2, c2 in cells if m[r2][c2] != m[r][c]]
            d = (min(other) - 0.5) if other else 0.0
            sd[r][c] = d if m[r][c] else -d
        for ix in range(n):
            for iy in range(n):
                for iz in range(n):
                    x, y, z = ((ix + 0.5) / n - 0.5, (iy + 0.5) / n - 0.5, (iz + 0.5) / n - 0.5)
                    depth = camera.distance - z  # planar depth: the camera looks down −z from (0, 0, distance)
                    if depth <= 0:
                        continue
                    # pixel-centre coordinates of the projection (centres at integer + 0.5), clamped to the border
                    u = min(max(x * f / depth + size / 2.0 - 0.5, 0.0), size - 1.0)
                    v = min(max(-y * f / depth + size / 2.0 - 0.5, 0.0), size - 1.0)
                    c0, r0 = min(int(u), size - 2), min(int(v), size - 2)
                    a, bb = u - c0, v - r0
                    d_px = ((1 - a) * (1 - bb) * sd[r0][c0] + a * (1 - bb) * sd[r0][c0 + 1]
                            + (1 - a) * bb * sd[r0 + 1][c0] + a * bb * sd[r0 + 1][c0 + 1])
                    d_vox = d_px * depth / f * n
                    out[b, 0, ix, iy, iz] = min(max(0.5 + d_vox / width, 0.0), 1.0)
    return out.float()


def _ray_samples(camera, n: int, image_size: int, step: float, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """The samples along every pixel's ray through an N-voxel grid: ``(depths (K,), coords (K, S, S, 3))``.

    Planar depths every ``step`` voxels across the cube's reach from the camera, and their points
    (:func:`genre_backend.frame.depth_to_points`) as ``grid_sample``'s coordinates (x, y, z) = (iz, iy, ix),
    float32 on ``device``.
    """
    from ..frame import depth_to_points

    check_positive_int("image_size", image_size)
    if not (math.isfinite(step) and step > 0):
        raise ValueError(f"step: expected a positive number of voxels, got {step!r}")
    half = math.sqrt(3.0) / 2.0
    k = int(math.ceil(2.0 * half * n / step)) + 1
    depths = torch.linspace(camera.distance - half, camera.distance + half, k, device=device)
    pts = depth_to_points(depths.view(k, 1, 1).expand(k, image_size, image_size).contiguous(), camera)  # (K, S, S, 3)
    return depths, (2.0 * pts)[..., [2, 1, 0]].float()


def ray_max(grid: torch.Tensor, camera, image_size: int, step: float = 1.0) -> torch.Tensor:
    """The largest value along each pixel's ray: (B, S, S), differentiable (the grid's soft silhouette).

    grid: (B, 1, N, N, N) float (a probability grid), indexed and interpolated as for :func:`ray_first_hit`;
    each ray is sampled every ``step`` voxels of planar depth across the cube.  The gradient reaches the
    voxels around each ray's largest sample.  Of a binary grid it is the mask of the pixels whose ray meets
    the solid (to within the sampling); of a refiner's probabilities, how surely some part stands on that
    pixel's ray: the mesh at level ``t`` covers the pixel where it exceeds ``t``.
    """
    check_tensor("grid", grid, ("B", 1, "N", "N", "N"))
    _, coords = _ray_samples(camera, grid.shape[-1], image_size, step, device=grid.device)
    b, k = grid.shape[0], coords.shape[0]
    coords = coords.reshape(1, k, image_size * image_size, 3).expand(b, -1, -1, -1)
    grid = grid.float()
    with torch.no_grad():  # which sample is each ray's largest: the maximum's gradient reaches that sample only
        vals = torch.nn.functional.grid_sample(grid.detach(), coords[:, :, :, None], mode="bilinear", padding_mode="zeros",
                                               align_corners=False)
        first = vals.view(b, k, -1).argmax(dim=1)  # (B, S·S)
    chosen = torch.gather(coords, 1, first[:, None, :, None].expand(-1, -1, -1, 3))  # (B, 1, S·S, 3)
    vals = torch.nn.functional.grid_sample(grid, chosen[:, :, :, None], mode="bilinear", padding_mode="zeros",
                                           align_corners=False)  # (B, 1, 1, S·S, 1): the same values, with their gradient
    return vals.view(b, image_size, image_size)


def _trilinear_reference(g: np.ndarray, p) -> float:
    """The grid ``g`` (N, N, N) at the view-frame point ``p`` (x, y, z), interpolated trilinearly as
    ``grid_sample`` does (voxel centres at ``(i + 0.5)/N − 0.5``, 0 outside the grid), written out (references)."""
    n = g.shape[0]
    u = [(c + 0.5) * n - 0.5 for c in p]  # continuous voxel index
    i0 = [math.floor(c) for c in u]
    total = 0.0
    for corner in range(8):
        idx = [i0[a] + ((corner >> a) & 1) for a in range(3)]
        if all(0 <= i < n for i in idx):
            w = 1.0
            for a in range(3):
                w *= (u[a] - i0[a]) if (corner >> a) & 1 else (1.0 - u[a] + i0[a])
            total += w * g[idx[0], idx[1], idx[2]]
    return total


def ray_max_reference(grid: torch.Tensor, camera, image_size: int, step: float = 1.0) -> np.ndarray:
    """Plain-loop reference of :func:`ray_max` for one grid (N, N, N) (slow; tests): (S, S) float64, each pixel's
    planar depths sampled as :func:`ray_max` samples them, the pinhole and the trilinear interpolation written out."""
    g = grid.detach().double().cpu().numpy()
    n = g.shape[0]
    f = camera.lens_mm / camera.sensor_mm * image_size
    half = math.sqrt(3.0) / 2.0
    k = int(math.ceil(2.0 * half * n / step)) + 1
    depths = np.linspace(camera.distance - half, camera.distance + half, k)
    out = np.zeros((image_size, image_size))
    for r in range(image_size):
        for c in range(image_size):
            best = 0.0
            for d in depths:
                p = ((c + 0.5 - image_size / 2.0) / f * d, -(r + 0.5 - image_size / 2.0) / f * d, camera.distance - d)
                best = max(best, _trilinear_reference(g, p))
            out[r, c] = best
    return out


def ray_first_hit(grid: torch.Tensor, level: float, camera, image_size: int, step: float = 0.5) -> torch.Tensor:
    """Where each pixel's ray first meets the grid: (S, S) float32 planar depth, ``inf`` where it meets nothing.

    grid: (N, N, N) float, indexed ``[ix, iy, iz]`` over the view-frame cube ``[-0.5, 0.5]^3``
    (voxel centre ``(i + 0.5)/N − 0.5``), interpolated trilinearly and 0 outside the cube.
    camera: :class:`genre_backend.config.CameraConfig`; S = ``image_size``.  Each ray is sampled
    every ``step`` voxels of planar depth across the cube (:func:`genre_backend.frame.depth_to_points`);
    the result is the first sample above ``level`` (so within ``step`` voxels behind the crossing),
    and a region above ``level`` thicker than ``step`` voxels along the ray is never missed.
    """
    return _ray_hit(grid, level, camera, image_size, step, last=False)


def ray_last_hit(grid: torch.Tensor, level: float, camera, image_size: int, step: float = 0.5) -> torch.Tensor:
    """Where each pixel's ray last leaves the grid: (S, S) float32 planar depth of its farthest sample above ``level``
    (the back the camera cannot see, within ``step`` voxels in front of the crossing), ``inf`` where it meets nothing;
    as :func:`ray_first_hit` otherwise."""
    return _ray_hit(grid, level, camera, image_size, step, last=True)


def _ray_hit(grid: torch.Tensor, level: float, camera, image_size: int, step: float, last: bool) -> torch.Tensor:
    from ..validation import check_threshold

    check_tensor("grid", grid, ("N", "N", "N"))
    check_threshold("level", level)
    depths, coords = _ray_samples(camera, grid.shape[0], image_size, step, device=torch.device("cpu"))
    vals = torch.nn.functional.grid_sample(grid.detach().float().cpu()[None, None], coords[None], mode="bilinear",
                                           padding_mode="zeros", align_corners=False)[0, 0]  # (K, S, S)
    above = vals > level
    if last:  # the last sample above the level: the first one counted from the far end
        index = above.shape[0] - 1 - above.flip(0).float().argmax(dim=0)
    else:  # the first sample above the level (0 where none: masked below)
        index = above.float().argmax(dim=0)
    return torch.where(above.any(dim=0), depths[index], torch.tensor(float("inf")))


def ray_first_hit_reference(grid: torch.Tensor, level: float, camera, image_size: int, step: float = 0.125,
                            rows: int | None = None, last: bool = False) -> np.ndarray:
    """Plain-loop reference of :func:`ray_first_hit` (slow; tests): (S, S) float64 planar depth, ``inf`` where
    nothing is met; each pixel's ray marched in steps of ``step`` voxels along the ray itself, the trilinear
    interpolation written out.  ``rows``: only the first this many pixel rows are marched (the others stay
    ``inf``; for timing).  ``last``: marched from the far side toward the camera, the reference of
    :func:`ray_last_hit`."""
    g = grid.detach().double().cpu().numpy()
    n = g.shape[0]
    f = camera.lens_mm / camera.sensor_mm * image_size
    out = np.full((image_size, image_size), np.inf)

    for r in range(image_size if rows is None else min(rows, image_size)):
        for c in range(image_size):
            # the ray from the camera at (0, 0, distance) through the pixel centre, unit length
            dx, dy = (c + 0.5 - image_size / 2.0) / f, -(r + 0.5 - image_size / 2.0) / f
            norm = math.sqrt(dx * dx + dy * dy + 1.0)
            d = (dx / norm, dy / norm, -1.0 / norm)
            t = camera.distance + (1.0 if last else -1.0)
            while abs(t - camera.distance) <= 1.0:
                x, y, z = d[0] * t, d[1] * t, camera.distance + d[2] * t
                if max(abs(x), abs(y), abs(z)) < 0.5 and _trilinear_reference(g, (x, y, z)) > level:
                    out[r, c] = camera.distance - z  # planar depth
                    break
                t += -step / n if last else step / n
    return out
