"""Exact distances from points to triangles, in torch on any device (the GPU burst's distance targets).

:func:`point_triangles_distance` measures every point against every triangle, in chunks; :func:`near_surface_distance`
only against the triangles near it (a grid of blocks), for points within ``reach`` of the surface;
:func:`closest_on_triangles` is their closest-point step.  :func:`point_mesh_distance_reference`
is the plain NumPy loop they are checked against.  (The CPU's targets use libigl's AABB tree,
:func:`.mesh_voxels.mesh_to_distance`.)
"""

from __future__ import annotations

import numpy as np
import torch

from ..validation import check_tensor

__all__ = [
    "closest_on_triangles",
    "point_triangles_distance",
    "near_surface_distance",
    "point_mesh_distance_reference",
]

def _closest_on_triangle(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The point of triangle abc nearest to p (all (3,) float64), by its Voronoi regions."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = ab @ ap, ac @ ap
    if d1 <= 0 and d2 <= 0:
        return a
    bp = p - b
    d3, d4 = ab @ bp, ac @ bp
    if d3 >= 0 and d4 <= d3:
        return b
    vc = d1 * d4 - d3 * d2
    if vc <= 0 and d1 >= 0 and d3 <= 0:
        return a + d1 / (d1 - d3) * ab
    cp = p - c
    d5, d6 = ab @ cp, ac @ cp
    if d6 >= 0 and d5 <= d6:
        return c
    vb = d5 * d2 - d1 * d6
    if vb <= 0 and d2 >= 0 and d6 <= 0:
        return a + d2 / (d2 - d6) * ac
    va = d3 * d6 - d5 * d4
    if va <= 0 and (d4 - d3) >= 0 and (d5 - d6) >= 0:
        return b + (d4 - d3) / ((d4 - d3) + (d5 - d6)) * (c - b)
    denom = 1.0 / (va + vb + vc)
    return a + ab * (vb * denom) + ac * (vc * denom)


def closest_on_triangles(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """The point of triangle abc nearest to p, elementwise over broadcast (..., 3) tensors.

    Voronoi regions as in Ericson, *Real-Time Collision Detection*, 5.1.5
    (``_closest_on_triangle`` is the scalar reference); degenerate triangles
    fall on a vertex or an edge.
    """
    ab, ac = b - a, c - a
    ap, bp, cp = p - a, p - b, p - c
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    tiny = torch.finfo(p.dtype).tiny

    def safe(x):
        return torch.where(x.abs() > tiny, x, torch.full_like(x, tiny))

    denom = safe(va + vb + vc)
    q = a + ab * (vb / denom)[..., None] + ac * (vc / denom)[..., None]  # inside the face
    # the regions in the reverse of the reference's order, so that a later (= earlier there) one wins
    w_bc = ((d4 - d3) / safe((d4 - d3) + (d5 - d6)))[..., None]
    q = torch.where(((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0))[..., None], b + w_bc * (c - b), q)
    w_ac = (d2 / safe(d2 - d6))[..., None]
    q = torch.where(((vb <= 0) & (d2 >= 0) & (d6 <= 0))[..., None], a + w_ac * ac, q)
    q = torch.where(((d6 >= 0) & (d5 <= d6))[..., None], c.expand_as(q), q)
    w_ab = (d1 / safe(d1 - d3))[..., None]
    q = torch.where(((vc <= 0) & (d1 >= 0) & (d3 <= 0))[..., None], a + w_ab * ab, q)
    q = torch.where(((d3 >= 0) & (d4 <= d3))[..., None], b.expand_as(q), q)
    q = torch.where(((d1 <= 0) & (d2 <= 0))[..., None], a.expand_as(q), q)
    return q


def point_triangles_distance(points: torch.Tensor, triangles: torch.Tensor, *, chunk_pairs: int = 16_000_000) -> torch.Tensor:
    """Distance (P,) from each point (P, 3) to the nearest of the triangles (T, 3, 3); torch, any device.

    :func:`closest_on_triangles` over every (point, triangle) pair, in chunks
    of about ``chunk_pairs``; :func:`point_mesh_distance_reference` is the
    plain loop it is tested against.  inf for every point when there is no triangle.
    """
    check_tensor("points", points, (None, 3))
    check_tensor("triangles", triangles, (None, 3, 3))
    out = points.new_full((points.shape[0],), float("inf"))
    if triangles.shape[0] == 0 or points.shape[0] == 0:
        return out
    a, b, c = (t[None] for t in triangles.unbind(dim=1))  # (1, T, 3)
    step = max(1, chunk_pairs // triangles.shape[0])
    for start in range(0, points.shape[0], step):
        p = points[start:start + step, None, :]  # (p, 1, 3)
        out[start:start + step] = torch.linalg.vector_norm(p - closest_on_triangles(p, a, b, c), dim=-1).min(dim=1).values
    return out


def near_surface_distance(points: torch.Tensor, triangles: torch.Tensor, reach: float, *, block: float = 0.0625,
                          chunk_pairs: int = 16_000_000) -> torch.Tensor:
    """Distance (P,) from each point to the nearest triangle, exact where it is at most ``reach``; inf elsewhere
    when no triangle comes within ``reach`` of the point's block.

    The points are binned in cubes of edge ``block``; a point is measured only
    against the triangles whose bounding box comes within ``reach`` of its
    cube's, as (point, triangle) pairs in chunks of about ``chunk_pairs``.
    Above ``reach`` a value may be larger than the true distance (a nearer
    triangle was culled), never smaller.  For the truncated distance target,
    whose band is ``reach``, this is exact and far cheaper than
    :func:`point_triangles_distance` over every pair.
    """
    check_tensor("points", points, (None, 3))
    check_tensor("triangles", triangles, (None, 3, 3))
    out = points.new_full((points.shape[0],), float("inf"))
    if triangles.shape[0] == 0 or points.shape[0] == 0:
        return out
    cell = torch.floor(points / block).long()
    cell = cell - cell.min(dim=0).values
    span = int(cell.max()) + 1
    key = (cell[:, 0] * span + cell[:, 1]) * span + cell[:, 2]
    keys, inverse, counts = torch.unique(key, return_inverse=True, return_counts=True)
    order = torch.argsort(inverse, stable=True)
    first = torch.cumsum(counts, 0) - counts  # the blocks' first positions in ``order``
    bmin = torch.full((len(keys), 3), float("inf"), dtype=points.dtype, device=points.device)
    bmin = bmin.scatter_reduce(0, inverse[:, None].expand(-1, 3), points, reduce="amin")
    bmax = torch.full_like(bmin, -float("inf")).scatter_reduce(0, inverse[:, None].expand(-1, 3), points, reduce="amax")
    lo, hi = triangles.min(dim=1).values, triangles.max(dim=1).values
    near = ((lo[None] <= bmax[:, None] + reach) & (hi[None] >= bmin[:, None] - reach)).all(dim=-1)  # (blocks, T)
    blk, tri = torch.nonzero(near, as_tuple=True)
    if blk.numel() == 0:
        return out
    per = counts[blk]  # each (block, triangle) entry pairs the triangle with every point of the block
    ends = torch.cumsum(per, 0)
    start = 0
    while start < blk.numel():
        base = int(ends[start - 1]) if start > 0 else 0
        stop = max(int(torch.searchsorted(ends, base + chunk_pairs, right=True)), start + 1)
        cnt = per[start:stop]
        e = torch.repeat_interleave(torch.arange(start, stop, device=points.device), cnt)
        k = torch.arange(e.numel(), device=points.device) - torch.repeat_interleave(torch.cumsum(cnt, 0) - cnt, cnt)
        pidx = order[first[blk[e]] + k]
        t = triangles[tri[e]]
        d = torch.linalg.vector_norm(points[pidx] - closest_on_triangles(points[pidx], t[:, 0], t[:, 1], t[:, 2]), dim=-1)
        out.scatter_reduce_(0, pidx, d, reduce="amin", include_self=True)
        start = stop
    return out


def point_mesh_distance_reference(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Plain-loop reference: distance (P,) from each point (P, 3) to the nearest triangle (slow; tests)."""
    v = np.asarray(vertices, np.float64)
    out = []
    for p in np.asarray(points, np.float64):
        out.append(min(np.linalg.norm(p - _closest_on_triangle(p, *v[list(f)])) for f in np.asarray(faces)))
    return np.asarray(out)
