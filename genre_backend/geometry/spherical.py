"""Spherical maps: GenRe's 2D representation of a 3D surface.

A spherical map is an (H, W) image over directions from the origin of the
view frame (:mod:`genre_backend.frame`).  Row ``i`` has polar angle
``θ_i = (i + 0.5)·π/H`` measured from view +y (up); column ``j`` has azimuth
``φ_j = j·2π/W``; the direction is::

    d(θ, φ) = (−sin θ sin φ,  cos θ,  −sin θ cos φ)

so row 0 is the top, column 0 (the azimuth seam) points away from the camera
(−z), column W/4 points left (−x), column W/2 points at the camera (+z): the
visible hemisphere sits in the middle of the map, and the map reads like the
photo (up is up, left is left).

The value ``s`` of a pixel is the distance travelled inward from the unit
sphere along ``−d`` until the first surface hit, i.e. ``s = 1 − r`` with ``r``
the largest radius at which the ray ``t·d`` (0 ≤ t ≤ 1) meets the surface;
``s = 1`` means no hit.

The one core operation is :func:`raycast_triangles`, an exact origin-ray ×
triangle test vectorised over (triangle, candidate pixel) pairs.  It serves
both the partial map of a depth image (the depth map's own triangulated
surface) and the full ground-truth map of a mesh (open meshes welcome), and it
is differentiable with respect to the triangle vertices.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import torch

from ..config import CameraConfig
from ..frame import depth_to_points, depth_valid_mask
from ..validation import check_positive_int, check_tensor
from .voxels import points_to_voxels, voxel_centres

__all__ = [
    "ray_triangles_reference",
    "NO_HIT",
    "sph_directions",
    "directions_to_pixels",
    "raycast_triangles",
    "raycast_triangles_reference",
    "depth_to_triangles",
    "depth_to_sph",
    "mesh_to_sph",
    "resample_sph",
    "sph_to_points",
    "sph_to_voxels",
    "pad_sph",
    "crop_sph",
    "mirror_sph",
    "sph_hull_ramp",
    "hull_ramp",
    "sph_hull_ramp_reference",
]

NO_HIT = 1.0


@lru_cache(maxsize=16)
def _directions(height: int, width: int, dtype: torch.dtype, device: str) -> torch.Tensor:
    # Cached across calls, so never an inference tensor: one made under torch.inference_mode() (a
    # reconstruction) could not be used later by autograd (training in the same process).
    with torch.inference_mode(False):
        return _make_directions(height, width, dtype, device)


def _make_directions(height: int, width: int, dtype: torch.dtype, device: str) -> torch.Tensor:
    theta = (torch.arange(height, dtype=torch.float64) + 0.5) * math.pi / height
    phi = torch.arange(width, dtype=torch.float64) * 2.0 * math.pi / width
    st, ct = torch.sin(theta)[:, None], torch.cos(theta)[:, None]
    sp, cp = torch.sin(phi)[None, :], torch.cos(phi)[None, :]
    d = torch.stack(torch.broadcast_tensors(-st * sp, ct, -st * cp), dim=-1)
    return d.to(dtype=dtype, device=device)


def sph_directions(height: int, width: int | None = None, *, dtype=torch.float32, device=None) -> torch.Tensor:
    """Unit directions (H, W, 3) of a spherical map's pixels (see module doc)."""
    width = height if width is None else width
    check_positive_int("height", height)
    check_positive_int("width", width)
    return _directions(height, width, dtype, str(torch.device(device or "cpu")))


def directions_to_pixels(dirs: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Continuous (row, col) map coordinates (..., 2) of unit directions (..., 3).

    Pixel ``(i, j)``'s centre is at ``(i, j)``; columns lie in ``[0, W)``.
    """
    check_tensor("dirs", dirs, ("...", 3))
    theta = torch.acos(dirs[..., 1].clamp(-1.0, 1.0))
    phi = torch.remainder(torch.atan2(-dirs[..., 0], -dirs[..., 2]), 2.0 * math.pi)
    return torch.stack([theta * height / math.pi - 0.5, phi * width / (2.0 * math.pi)], dim=-1)


def _candidates(tri: torch.Tensor, height: int, width: int, chunk_pairs: int):
    """Yield (triangle index, row, col) candidate pairs covering each triangle's projection.

    Each triangle's projection onto the sphere lies in the spherical cap around
    its centroid direction whose radius is the largest angle to a vertex; the
    candidate pixels are that cap's (θ, φ) bounding box, or every pixel when the
    cap is a hemisphere or more, or every column when it contains a pole.
    """
    unit = tri / torch.linalg.vector_norm(tri, dim=-1, keepdim=True).clamp(min=1e-12)
    centre = unit.sum(dim=1)
    centre = centre / torch.linalg.vector_norm(centre, dim=-1, keepdim=True).clamp(min=1e-12)
    cos_alpha = (unit * centre[:, None, :]).sum(-1).min(dim=1).values.clamp(-1.0, 1.0)
    alpha = torch.acos(cos_alpha) * 1.001 + 1e-6
    rc = directions_to_pixels(centre, height, width)
    theta_c = (rc[:, 0] + 0.5) * math.pi / height
    phi_c = rc[:, 1] * 2.0 * math.pi / width
    row_step, col_step = math.pi / height, 2.0 * math.pi / width
    row0 = torch.ceil((theta_c - alpha) / row_step - 0.5).clamp(0, height - 1)
    row1 = torch.floor((theta_c + alpha) / row_step - 0.5).clamp(0, height - 1)
    polar = (theta_c - alpha <= 0) | (theta_c + alpha >= math.pi) | (alpha >= math.pi / 2)
    sin_ratio = (torch.sin(alpha.clamp(max=math.pi / 2)) / torch.sin(theta_c).clamp(min=1e-12)).clamp(max=1.0)
    beta = torch.asin(sin_ratio)
    col0 = torch.ceil((phi_c - beta) / col_step)
    col1 = torch.floor((phi_c + beta) / col_step)
    full = polar | (sin_ratio >= 1.0) | (col1 - col0 + 1 >= width)
    col0 = torch.where(full, torch.zeros_like(col0), col0)
    col1 = torch.where(full, torch.full_like(col1, width - 1), col1)
    row0, row1 = torch.where(alpha >= math.pi / 2, 0, row0), torch.where(alpha >= math.pi / 2, height - 1, row1)
    nrow = (row1 - row0 + 1).clamp(min=0).long()
    ncol = (col1 - col0 + 1).clamp(min=0).long()
    count = nrow * ncol
    row0, col0 = row0.long(), col0.long()
    # Process triangles in chunks so that at most ~chunk_pairs pairs exist at once
    # (a single triangle with more candidates than that forms a chunk of its own).
    ends = torch.cumsum(count, 0)
    start = 0
    while start < tri.shape[0]:
        base = int(ends[start - 1]) if start > 0 else 0
        stop = max(int(torch.searchsorted(ends, base + chunk_pairs, right=True)), start + 1)
        cnt = count[start:stop]
        idx = torch.repeat_interleave(torch.arange(start, stop, device=tri.device), cnt)
        first = torch.cumsum(cnt, 0) - cnt
        offsets = torch.arange(idx.shape[0], device=tri.device) - torch.repeat_interleave(first, cnt)
        nc = ncol[idx]
        rows = row0[idx] + torch.div(offsets, nc, rounding_mode="floor")
        cols = torch.remainder(col0[idx] + torch.remainder(offsets, nc), width)
        yield idx, rows, cols
        start = stop


def raycast_triangles(
    triangles: torch.Tensor,
    batch_index: torch.Tensor,
    batch_size: int,
    height: int,
    width: int | None = None,
    *,
    chunk_pairs: int = 4_000_000,
) -> torch.Tensor:
    """Spherical maps (B, H, W) of triangle soups: ``1 − (largest hit radius ≤ 1)``.

    triangles:   (T, 3, 3) float view-frame vertices of each triangle.
    batch_index: (T,) int64, which map (0 ≤ b < batch_size) each triangle belongs to.
    For every pixel direction ``d`` the ray ``t·d`` from the origin is tested
    against every candidate triangle exactly (``d`` inside the cone spanned by
    the vertices, ``t = v0·(v1×v2) / (n·d)``); hits with 0 < t ≤ 1 count.
    Differentiable with respect to ``triangles`` (gradient flows to the hit
    that wins each pixel).
    """
    width = height if width is None else width
    check_tensor("triangles", triangles, (None, 3, 3))
    if not isinstance(batch_index, torch.Tensor) or batch_index.dtype != torch.int64 or batch_index.shape != triangles.shape[:1]:
        raise ValueError(f"batch_index: expected an int64 tensor of shape ({triangles.shape[0]},)")
    check_positive_int("batch_size", batch_size)
    if triangles.shape[0] and (int(batch_index.min()) < 0 or int(batch_index.max()) >= batch_size):
        raise ValueError(f"batch_index: values must lie in [0, {batch_size})")
    dirs = sph_directions(height, width, dtype=triangles.dtype, device=triangles.device).reshape(-1, 3)
    radius = triangles.new_zeros(batch_size * height * width)
    if triangles.shape[0] == 0:
        return (1.0 - radius).view(batch_size, height, width)
    v0, v1, v2 = triangles.unbind(dim=1)
    e01, e12, e20 = torch.cross(v0, v1, dim=-1), torch.cross(v1, v2, dim=-1), torch.cross(v2, v0, dim=-1)
    volume = (v0 * e12).sum(-1)  # v0 · (v1 × v2): orientation of the cone, and the plane offset
    normal = e01 + e12 + e20  # (v1 − v0) × (v2 − v0)
    sign = torch.sign(volume).detach()
    keep = sign != 0
    hit_parts, pix_parts = [], []
    with torch.no_grad():
        for tri_idx, rows, cols in _candidates(triangles.detach(), height, width, chunk_pairs):
            pix = rows * width + cols
            d = dirs[pix]
            s = sign[tri_idx]
            inside = (
                keep[tri_idx]
                & ((d * e01[tri_idx]).sum(-1) * s >= 0)
                & ((d * e12[tri_idx]).sum(-1) * s >= 0)
                & ((d * e20[tri_idx]).sum(-1) * s >= 0)
            )
            hit_parts.append(tri_idx[inside])
            pix_parts.append(pix[inside])
    tri_idx, pix = torch.cat(hit_parts), torch.cat(pix_parts)
    t = volume[tri_idx] / (normal[tri_idx] * dirs[pix]).sum(-1)
    valid = (t > 0) & (t <= 1.0)
    target = batch_index[tri_idx[valid]] * (height * width) + pix[valid]
    radius = radius.scatter_reduce(0, target, t[valid], reduce="amax", include_self=True)
    return (1.0 - radius).view(batch_size, height, width)


def raycast_triangles_reference(triangles: np.ndarray, height: int, width: int | None = None) -> np.ndarray:
    """Plain reference of :func:`raycast_triangles` for one map: a loop over rays.

    triangles: (T, 3, 3) float.  Each ray is tested against every triangle with
    the Möller–Trumbore algorithm in float64.  Returns (H, W) float64.
    """
    width = height if width is None else width
    tri = np.asarray(triangles, dtype=np.float64)
    dirs = sph_directions(height, width, dtype=torch.float64).numpy()
    out = np.ones((height, width))
    for i in range(height):
        for j in range(width):
            hit, t = ray_triangles_reference(np.zeros(3), dirs[i, j], tri)
            hit &= t <= 1
            if hit.any():
                out[i, j] = 1.0 - t[hit].max()
    return out


def ray_triangles_reference(origin: np.ndarray, direction: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Möller–Trumbore in float64: which triangles (T, 3, 3) the ray ``origin + t·direction`` (t > 0) meets, and t.

    Returns ``(hit (T,) bool, t (T,) float64)``; the references of the ray casters
    (here and :func:`genre_backend.geometry.raster.mesh_depth_reference`) loop over rays with it.
    """
    tri = np.asarray(triangles, dtype=np.float64)
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = np.cross(direction, e2)
    det = (e1 * p).sum(-1)
    ok = np.abs(det) > 1e-15
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tvec = origin - v0
    u = (tvec * p).sum(-1) * inv
    q = np.cross(tvec, e1)
    v = (direction * q).sum(-1) * inv
    t = (e2 * q).sum(-1) * inv
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0), t


def depth_to_triangles(
    depth: torch.Tensor,
    camera: CameraConfig,
    max_edge_ratio: float,
    mask: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Triangulate depth maps into view-frame triangle soups.

    depth: (B, S, S) float planar depth (background 0); mask: (B, S, S) bool,
    optional (defaults to depth > 0).  Each 2×2 block of valid pixels yields
    two triangles, dropped if their longest edge exceeds ``max_edge_ratio``
    times the pixel footprint ``depth / focal`` (a depth discontinuity or a
    surface seen edge-on, not a sampled surface).  Returns ``(triangles (T, 3, 3), batch_index (T,))``.
    """
    check_tensor("depth", depth, ("B", "S", "S"))
    valid = depth_valid_mask(depth)
    if mask is not None:
        if mask.shape != depth.shape or mask.dtype != torch.bool:
            raise ValueError(f"mask: expected a bool tensor of shape {tuple(depth.shape)}")
        valid = valid & mask
    pts = depth_to_points(depth, camera)
    a, b = pts[:, :-1, :-1], pts[:, :-1, 1:]
    c, d = pts[:, 1:, :-1], pts[:, 1:, 1:]
    va, vb, vc, vd = valid[:, :-1, :-1], valid[:, :-1, 1:], valid[:, 1:, :-1], valid[:, 1:, 1:]
    tris = torch.stack([torch.stack([a, c, b], dim=-2), torch.stack([b, c, d], dim=-2)], dim=3)  # (B,S-1,S-1,2,3,3)
    ok = torch.stack([va & vc & vb, vb & vc & vd], dim=-1)
    edges = tris - tris.roll(1, dims=-2)
    longest = torch.linalg.vector_norm(edges.detach(), dim=-1).max(dim=-1).values
    footprint = (camera.distance - tris[..., 2].detach()).max(dim=-1).values / camera.focal_px(depth.shape[-1])
    ok = ok & (longest <= max_edge_ratio * footprint)
    batch = torch.arange(depth.shape[0], device=depth.device).view(-1, 1, 1, 1).expand_as(ok)
    return tris[ok], batch[ok]


def depth_to_sph(
    depth: torch.Tensor,
    camera: CameraConfig,
    sph_size: int,
    max_edge_ratio: float,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Partial spherical maps (B, H, H) of the surface visible in depth maps (B, S, S).

    The visible surface is triangulated (:func:`depth_to_triangles`) and ray
    cast exactly; directions that do not meet it hold 1.  Differentiable in depth.
    """
    tris, batch = depth_to_triangles(depth, camera, max_edge_ratio, mask)
    return raycast_triangles(tris, batch, depth.shape[0], sph_size)


def mesh_to_sph(vertices: torch.Tensor, faces: torch.Tensor, sph_size: int) -> torch.Tensor:
    """Full spherical map (H, H) of a view-frame mesh (ground truth; open meshes are fine).

    vertices: (V, 3) float; faces: (F, 3) int64 indices into vertices.
    """
    check_tensor("vertices", vertices, (None, 3))
    if not isinstance(faces, torch.Tensor) or faces.dtype not in (torch.int32, torch.int64) or faces.dim() != 2 or faces.shape[1] != 3:
        raise ValueError("faces: expected an integer tensor of shape (F, 3)")
    if faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= vertices.shape[0]):
        raise ValueError("faces: indices out of range of vertices")
    tris = vertices[faces.long()]
    batch = torch.zeros(tris.shape[0], dtype=torch.int64, device=vertices.device)
    return raycast_triangles(tris, batch, 1, sph_size)[0]


def resample_sph(sph: torch.Tensor, factor: int) -> torch.Tensor:
    """Bilinearly resample maps (B, H, W) to (B, k·H, k·W) on the finer spherical grid.

    The finer grid's pixel directions follow the module's convention at the
    new size; values are interpolated periodically in azimuth and clamped at
    the poles.  ``factor`` 1 returns the input.
    """
    check_tensor("sph", sph, ("B", None, None))
    check_positive_int("factor", factor)
    if factor == 1:
        return sph
    batch, height, width = sph.shape
    padded = pad_sph(sph[:, None], 1)[:, 0]  # (B, H+2, W+2)
    rows = (torch.arange(factor * height, dtype=sph.dtype, device=sph.device) + 0.5) / factor - 0.5 + 1.0
    cols = torch.arange(factor * width, dtype=sph.dtype, device=sph.device) / factor + 1.0
    r0 = rows.floor().clamp(0, height).long()
    c0 = cols.floor().long()
    wr, wc = (rows - r0).view(-1, 1), (cols - c0).view(1, -1)
    top = padded[:, r0][:, :, c0] * (1 - wc) + padded[:, r0][:, :, c0 + 1] * wc
    bottom = padded[:, r0 + 1][:, :, c0] * (1 - wc) + padded[:, r0 + 1][:, :, c0 + 1] * wc
    return top * (1 - wr) + bottom * wr


def sph_to_points(sph: torch.Tensor, nohit_min: float = 1.0 - 1e-4, supersample: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Back-project spherical maps (B, H, W) to points.

    Returns ``(points (B, P, 3), mask (B, P) bool)`` with ``P = k²·H·W`` for
    ``supersample`` = k: the map is resampled ``k`` times finer
    (:func:`resample_sph`) and the point of direction ``d`` is ``(1 − s)·d``.
    Pixels with ``s ≥ nohit_min`` (no hit) are masked out, and so is every fine
    pixel that interpolates between a hit and a no-hit pixel.
    """
    check_tensor("sph", sph, ("B", None, None))
    hit = resample_sph((sph < nohit_min).to(sph.dtype), supersample) >= 1.0 - 1e-6
    fine = resample_sph(sph, supersample)
    batch, height, width = fine.shape
    dirs = sph_directions(height, width, dtype=sph.dtype, device=sph.device).reshape(1, -1, 3)
    radius = (1.0 - fine).reshape(batch, -1, 1)
    return radius * dirs, hit.reshape(batch, -1)


def sph_to_voxels(sph: torch.Tensor, resolution: int, nohit_min: float = 1.0 - 1e-4, supersample: int = 1) -> torch.Tensor:
    """Spherical maps (B, H, W) → voxel grids (B, 1, N, N, N): :func:`sph_to_points` then the paper rule."""
    points, mask = sph_to_points(sph, nohit_min, supersample)
    return points_to_voxels(points, resolution, mask)


def pad_sph(sph: torch.Tensor, pad: int) -> torch.Tensor:
    """Pad maps (B, C, H, W) by ``pad`` pixels: periodic in azimuth, edge-replicated at the poles.

    Returns (B, C, H + 2·pad, W + 2·pad).
    """
    check_tensor("sph", sph, ("B", "C", None, None), finite=False)
    if isinstance(pad, bool) or not isinstance(pad, int) or pad < 0 or pad > sph.shape[-1]:
        raise ValueError(f"pad: expected an int in [0, {sph.shape[-1]}], got {pad!r}")
    if pad == 0:
        return sph
    wrapped = torch.cat([sph[..., -pad:], sph, sph[..., :pad]], dim=-1)
    return torch.cat([wrapped[..., :1, :].expand(-1, -1, pad, -1), wrapped, wrapped[..., -1:, :].expand(-1, -1, pad, -1)], dim=-2)


def crop_sph(padded: torch.Tensor, pad: int) -> torch.Tensor:
    """Inverse of :func:`pad_sph`: (B, C, H + 2·pad, W + 2·pad) → (B, C, H, W)."""
    check_tensor("padded", padded, ("B", "C", None, None), finite=False)
    if isinstance(pad, bool) or not isinstance(pad, int) or pad < 0 or 2 * pad >= min(padded.shape[-2:]):
        raise ValueError(f"pad: expected an int in [0, {min(padded.shape[-2:]) // 2}), got {pad!r}")
    if pad == 0:
        return padded
    return padded[..., pad:-pad, pad:-pad]


def mirror_sph(sph: torch.Tensor) -> torch.Tensor:
    """The maps (…, H, W) of the scene reflected in the view frame's x = 0 plane (x → −x).

    The reflection maps the direction of azimuth φ to that of −φ, so column
    ``j`` takes column ``(W − j) mod W``: the seam (column 0, away from the
    camera) and column W/2 (towards it) stay, left and right swap.  Its own
    inverse.
    """
    check_tensor("sph", sph, ("...", None, None), finite=False)
    return torch.roll(torch.flip(sph, dims=(-1,)), 1, dims=-1)


def _hull_radius(sph: torch.Tensor, nohit_min: float, spread: int) -> torch.Tensor:
    """The outermost radius (B, H, W) a map allows per pixel: ``1 − s`` at hits, 0 at no-hit pixels, the maximum over
    the pixel's (2·spread + 1)² neighbourhood (periodic in azimuth, edge-replicated at the poles)."""
    radius = torch.where(sph < nohit_min, 1.0 - sph, torch.zeros_like(sph))
    if spread:
        radius = torch.nn.functional.max_pool2d(pad_sph(radius[:, None], spread), 2 * spread + 1, stride=1)[:, 0]
    return radius


@lru_cache(maxsize=8)
def _hull_lookup(resolution: int, height: int, wide: int, device: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each voxel centre reads an (H + 2, W + 2) padded map (:func:`pad_sph` by 1) — ``grid_sample``'s (x, y)
    in [-1, 1] over its pixel centres, (1, N³, 1, 2) — and the centres' radii (N³,); cached, never an inference tensor
    (see :func:`_directions`)."""
    with torch.inference_mode(False):
        c = voxel_centres(resolution, device=device)
        centres = torch.stack(torch.meshgrid(c, c, c, indexing="ij"), dim=-1).reshape(-1, 3)
        rho = torch.linalg.vector_norm(centres, dim=-1)
        toward = torch.tensor([0.0, 0.0, 1.0], device=device).expand_as(centres)  # the centre (odd N): the camera's
        rc = directions_to_pixels(torch.where(rho[:, None] > 0, centres / rho.clamp(min=1e-12)[:, None], toward), height, wide)
        x = (rc[:, 1] + 1.0) / (wide + 1) * 2.0 - 1.0  # padded column j + 1 at x = -1 + 2 (j + 1) / (W + 1)
        y = (rc[:, 0] + 1.0) / (height + 1) * 2.0 - 1.0
        return torch.stack([x, y], dim=-1).view(1, -1, 1, 2), rho


def sph_hull_ramp(sph: torch.Tensor, resolution: int, nohit_min: float = 1.0 - 1e-4, spread: int = 1,
                  width: float = 1.0, offset: float = 0.0) -> torch.Tensor:
    """How far inside the radial hull of full spherical maps each voxel centre lies, as a ramp in [0, 1].

    A full map's pixel of direction ``d`` holds ``s = 1 − r`` with ``r`` the *largest* radius at which the ray
    ``t·d`` meets the surface (module doc), so no surface point lies beyond radius ``r`` in that direction: the
    region ``|p| ≤ r(p / |p|)`` (the radial hull, star-shaped about the view frame's origin) holds the whole
    object.  sph: (B, H, W) full maps; ``resolution``: N.  ``r`` is the pixel's hull radius, the largest of its
    (2·spread + 1)² neighbours' (no-hit pixels: 0), read bilinearly at the centre's direction; returns (B, 1, N, N,
    N) float32 ``clip(0.5 + ((r − |c|)·N + offset) / width, 0, 1)``: 1 well inside, 0 beyond the hull (moved
    ``offset`` voxels outward) by more than half a ramp.  Differentiable with respect to ``sph``.  ``min(probability, ramp)`` empties what the refiner puts outside the map's own surface
    (``GeometryConfig.sph_hull_carve``).  A voxel centred on the origin (odd N) reads the direction to the camera.
    """
    check_tensor("sph", sph, ("B", None, None))
    check_positive_int("resolution", resolution)
    if isinstance(spread, bool) or not isinstance(spread, int) or not 0 <= spread <= min(sph.shape[-2:]) // 2:
        raise ValueError(f"spread: expected an int in [0, {min(sph.shape[-2:]) // 2}], got {spread!r}")
    if not (math.isfinite(width) and width > 0):
        raise ValueError(f"width: expected a positive number of voxels, got {width!r}")
    if not (math.isfinite(offset) and offset >= 0):
        raise ValueError(f"offset: expected voxels >= 0, got {offset!r}")
    batch, height, wide = sph.shape
    radius = _hull_radius(sph.float(), nohit_min, spread)
    grid, rho = _hull_lookup(resolution, height, wide, str(sph.device))
    padded = pad_sph(radius[:, None], 1)  # (B, 1, H + 2, W + 2): row i ↦ i + 1, column j ↦ j + 1
    r = torch.nn.functional.grid_sample(padded, grid.expand(batch, -1, -1, -1), mode="bilinear", padding_mode="border",
                                        align_corners=True)
    ramp = (0.5 + ((r.view(batch, -1) - rho) * resolution + offset) / width).clamp(0.0, 1.0)
    return ramp.view(batch, 1, resolution, resolution, resolution)


def hull_ramp(sph: torch.Tensor, geometry, width: float = 1.0) -> torch.Tensor:
    """:func:`sph_hull_ramp` of full maps (B, H, H) as a model's ``GeometryConfig`` sets it: its grid, its no-hit
    level, its ``sph_hull_spread`` and ``sph_hull_offset``; the one call inference (the mesh option
    ``sph_hull_carve``) and training (a refiner trained with the trim; ``width`` > 1 for its gradient) share."""
    return sph_hull_ramp(sph, geometry.voxel_size, geometry.sph_nohit_min, geometry.sph_hull_spread, width=width,
                         offset=geometry.sph_hull_offset)


def sph_hull_ramp_reference(sph: torch.Tensor, resolution: int, nohit_min: float = 1.0 - 1e-4, spread: int = 1,
                            width: float = 1.0, offset: float = 0.0) -> torch.Tensor:
    """Plain-loop reference of :func:`sph_hull_ramp`: the neighbourhood maximum, the direction's map coordinates and
    the bilinear read written out per voxel (periodic columns, rows clamped to the poles' pixels)."""
    check_tensor("sph", sph, ("B", None, None))
    batch, height, wide = sph.shape
    n = resolution
    out = torch.zeros(batch, 1, n, n, n, dtype=torch.float64)
    for b in range(batch):
        s = sph[b].double().tolist()
        hull = [[1.0 - s[i][j] if s[i][j] < nohit_min else 0.0 for j in range(wide)] for i in range(height)]
        big = [[max(hull[min(max(i + di, 0), height - 1)][(j + dj) % wide]
                    for di in range(-spread, spread + 1) for dj in range(-spread, spread + 1))
                for j in range(wide)] for i in range(height)]
        for ix in range(n):
            for iy in range(n):
                for iz in range(n):
                    x, y, z = ((ix + 0.5) / n - 0.5, (iy + 0.5) / n - 0.5, (iz + 0.5) / n - 0.5)
                    rho = math.sqrt(x * x + y * y + z * z)
                    dx, dy, dz = (x / rho, y / rho, z / rho) if rho > 0 else (0.0, 0.0, 1.0)
                    theta = math.acos(max(-1.0, min(1.0, dy)))
                    phi = math.atan2(-dx, -dz) % (2.0 * math.pi)
                    row = min(max(theta * height / math.pi - 0.5, 0.0), height - 1.0)
                    col = phi * wide / (2.0 * math.pi)
                    r0, c0 = min(int(math.floor(row)), height - 2), int(math.floor(col))
                    a, bb = col - c0, row - r0
                    r = ((1 - a) * (1 - bb) * big[r0][c0 % wide] + a * (1 - bb) * big[r0][(c0 + 1) % wide]
                         + (1 - a) * bb * big[r0 + 1][c0 % wide] + a * bb * big[r0 + 1][(c0 + 1) % wide])
                    out[b, 0, ix, iy, iz] = min(max(0.5 + ((r - rho) * n + offset) / width, 0.0), 1.0)
    return out.float()
