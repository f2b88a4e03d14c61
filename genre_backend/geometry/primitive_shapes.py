"""The regular shapes a reconstruction may snap to (:mod:`.primitives`): box, cylinder, cone, torus and ellipsoid.

Families and their parameters (the shape's own frame; its pose is a rotation
(3, 3) taking own coordinates to the view frame, and a centre (3,)):

===========  ==========================================  ===============================
family       parameters                                  shape
===========  ==========================================  ===============================
box          half-sides (a, b, c)                        |x| ≤ a, |y| ≤ b, |z| ≤ c
cylinder     radius r, half-height h                     x² + y² ≤ r², |z| ≤ h
cone         base radius r, half-height h                base at z = −h, apex at z = +h
torus        ring radius R, tube radius t (t < R)        (√(x² + y²) − R)² + z² ≤ t²
ellipsoid    radii (a, b, c)                             (x/a)² + (y/b)² + (z/c)² ≤ 1
===========  ==========================================  ===============================

The signed distances (:func:`signed_distance`, negative inside) are exact
for the box, cylinder, cone and torus and the usual first-order estimate for
the ellipsoid (exact on its surface, where fitting needs it);
:func:`signed_distance_reference` measures the same against a fine
triangulation of the shape (:func:`family_mesh`) for the tests.
"""

from __future__ import annotations

import math

import numpy as np
import torch

__all__ = ["FAMILIES", "EDGE_SHARE", "family_mesh", "signed_distance", "signed_distance_reference"]

FAMILIES = ("box", "cylinder", "cone", "torus", "ellipsoid")
_N_PARAMS = {"box": 3, "cylinder": 2, "cone": 2, "torus": 2, "ellipsoid": 3}
# The snapped mesh's longest edge, as a share of its bounding-box diagonal (so the photo's colour maps onto it
# like onto the voxel mesh, whose edges are about a voxel).
EDGE_SHARE = 1.0 / 48.0
_SECTIONS = 96
_EPS2 = 1e-14  # added under square roots: distances exact to 1e-7, gradients finite everywhere


# ----------------------------------------------------------------------------- signed distances


def _combine(q: torch.Tensor) -> torch.Tensor:
    """Distance of a point to the box |q_i| ≤ 0 in the axes of q (..., k): outside length + inside max."""
    return _length(q.clamp(min=0)) + q.amax(dim=-1).clamp(max=0)


def _length(q: torch.Tensor) -> torch.Tensor:
    """|q| along the last axis, with a finite gradient at 0 (the fit's points can sit exactly on an edge or axis)."""
    return (q * q).sum(-1).add(_EPS2).sqrt()


def _sd_cone(p: torch.Tensor, r: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """Exact signed distance to the cone with base radius r at z = −h and apex at z = +h (axis z)."""
    rho = _length(p[..., :2])
    z = p[..., 2]
    # (rho, z) half-plane: the base segment (0..r at z = −h) and the side from (r, −h) to (0, h)
    ca_x = rho - torch.minimum(rho, torch.where(z < 0, r, torch.zeros_like(r)))
    ca_y = z.abs() - h
    k2x, k2y = -r, 2 * h
    t = (((0 - rho) * k2x + (h - z) * k2y) / (k2x * k2x + k2y * k2y)).clamp(0.0, 1.0)
    cb_x = rho + k2x * t
    cb_y = z - h + k2y * t
    inside = (cb_x < 0) & (ca_y < 0)
    d = torch.minimum(ca_x * ca_x + ca_y * ca_y, cb_x * cb_x + cb_y * cb_y).add(_EPS2).sqrt()
    return torch.where(inside, -d, d)


def signed_distance(family: str, p: torch.Tensor, params: torch.Tensor) -> torch.Tensor:
    """Signed distance (negative inside) of points ``p`` (..., N, 3) in the shape's own frame to ``family`` with
    ``params`` (..., k) (positive; see the module table).  Returns (..., N)."""
    if family not in FAMILIES:
        raise ValueError(f"family: expected one of {FAMILIES}, got {family!r}")
    if p.shape[-1] != 3 or params.shape[-1] != _N_PARAMS[family]:
        raise ValueError(f"{family}: expected points (..., N, 3) and params (..., {_N_PARAMS[family]}), got {tuple(p.shape)} and {tuple(params.shape)}")
    k = params.unsqueeze(-2)  # (..., 1, k)
    if family == "box":
        return _combine(p.abs() - k)
    if family == "cylinder":
        q = torch.stack([_length(p[..., :2]) - k[..., 0], p[..., 2].abs() - k[..., 1]], dim=-1)
        return _combine(q)
    if family == "cone":
        return _sd_cone(p, k[..., 0], k[..., 1])
    if family == "torus":
        ring = _length(p[..., :2]) - k[..., 0]
        return torch.sqrt(ring * ring + p[..., 2] ** 2 + _EPS2) - k[..., 1]
    # ellipsoid: k0 (k0 − 1) / k1 with k0 = |p / r|, k1 = |p / r²|
    k0 = _length(p / k)
    k1 = _length(p / (k * k))
    return k0 * (k0 - 1.0) / k1


def _polyline(corners, step: float) -> np.ndarray:
    """The 2-D polyline through ``corners`` with every segment cut into pieces at most ``step`` long."""
    out = [np.asarray(corners[0], dtype=np.float64)]
    for a, b in zip(corners[:-1], corners[1:]):
        a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        out += [a + (b - a) * k / n for k in range(1, n + 1)]
    return np.stack(out)


def _box_grid(half, step: float):
    """The box |x_i| ≤ half_i with each face a grid of squares-ish, at most ``step`` a side; the faces share the
    vertices on their common edges (so the mesh is closed)."""
    import trimesh

    counts = [max(1, int(np.ceil(2 * h / step))) if math.isfinite(step) else 1 for h in half]
    verts, faces = [], []
    for axis in range(3):
        u, w = (axis + 1) % 3, (axis + 2) % 3
        gu = np.linspace(-half[u], half[u], counts[u] + 1)
        gw = np.linspace(-half[w], half[w], counts[w] + 1)
        uu, ww = np.meshgrid(gu, gw, indexing="ij")
        for sign in (-1.0, 1.0):
            p = np.zeros(uu.shape + (3,))
            p[..., axis], p[..., u], p[..., w] = sign * half[axis], uu, ww
            base = sum(len(v) for v in verts)
            idx = base + np.arange(uu.size).reshape(uu.shape)
            a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
            tri = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
            faces.append(tri if sign > 0 else tri[:, ::-1])  # outward: (u, w, axis) is right-handed
            verts.append(p.reshape(-1, 3))
    mesh = trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=False)
    mesh.merge_vertices()
    return mesh


def family_mesh(family: str, params, edge: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A closed triangle mesh of ``family`` with ``params`` in its own frame.

    ``edge``: the longest edge wanted (default: :data:`EDGE_SHARE` of the bounding-box diagonal, so the photo's
    colour maps onto it as onto the voxel mesh; 0: as coarse as the shape allows).  Cylinders and cones are
    revolved profiles (:data:`_SECTIONS` sections), the torus a grid of 96 × 48, the ellipsoid a scaled icosphere,
    the box six subdivided faces: the edges stay sharp.  Returns (vertices (V, 3) float64, faces (F, 3) int64)."""
    import trimesh

    params = [float(x) for x in params]
    if family not in FAMILIES or len(params) != _N_PARAMS[family]:
        raise ValueError(f"family_mesh: unknown family {family!r} or wrong parameter count {len(params)}")
    if min(params) <= 0:
        raise ValueError(f"family_mesh: parameters must be positive, got {params}")
    if family == "torus" and params[1] >= params[0]:
        raise ValueError(f"family_mesh: a torus needs its tube radius below its ring radius, got {params}")
    half = {"box": params, "ellipsoid": params, "cylinder": [params[0], params[0], params[1]], "cone": [params[0], params[0], params[1]],
            "torus": [sum(params), sum(params), params[1]]}[family]
    step = 2 * float(np.linalg.norm(half)) * EDGE_SHARE if edge is None else (edge or math.inf)
    if family == "box":
        mesh = _box_grid(params, step)
    elif family in ("cylinder", "cone"):
        r, h = params
        top = [(r, h), (0.0, h)] if family == "cylinder" else [(0.0, h)]
        profile = _polyline([(0.0, -h), (r, -h), *top], step if math.isfinite(step) else 4 * (r + h))
        mesh = trimesh.creation.revolve(profile, sections=_SECTIONS)
    elif family == "torus":
        mesh = trimesh.creation.torus(major_radius=params[0], minor_radius=params[1], major_sections=_SECTIONS, minor_sections=_SECTIONS // 2)
    else:
        mesh = trimesh.creation.icosphere(subdivisions=5)
        mesh.apply_scale(params)
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def signed_distance_reference(family: str, points: np.ndarray, params) -> np.ndarray:
    """The signed distance measured on a fine mesh of the shape (trimesh's closest point and containment)."""
    import trimesh

    v, f = family_mesh(family, params, edge=0)
    mesh = trimesh.Trimesh(v, f, process=False)
    _, dist, _ = trimesh.proximity.closest_point(mesh, points)
    inside = mesh.contains(points)
    return np.where(inside, -dist, dist)
