"""Regular shapes fitted to a reconstruction: the mesh replaced by a box, cylinder, cone, torus or ellipsoid.

Why: the voxel nets blur a plain cube into a lumpy box and a cylinder into a
rounded loaf (issue 16: the product model's regular primitives sat at 2.8×
the Chamfer noise floor).  When the surface the camera sees is explained by
one regular shape, that shape is the better mesh.  :func:`snap` fits each
family of :data:`FAMILIES` in any pose to

* the **outline**: the rays of the pixels along the mask's edge must meet the
  shape inside the mask and miss it outside.  The mask is sharp where the
  depth net's surface is rounded: it tells a cube from an ellipsoid;
* the **mesh points** (Q, 3): samples of the refiner's mesh, which carries
  the hidden side;
* the **visible points** (P, 3): the masked depth map unprojected
  (:func:`genre_backend.frame.depth_to_points`), weighted least: on
  primitives the depth net is off by 3-13 % of the object's size;

takes the family whose silhouette has the highest IoU with the mask
(:func:`outline_disagreement` = 1 − IoU), and replaces the mesh by it when
both that and twice the mesh points' mean distance to it (over its
bounding-box diagonal) are at most ``tolerance``
(``GeometryConfig.primitive_snap``; 0 turns the stage off).

The families, their parameters and signed distances: :mod:`.primitive_shapes`.  Fitting is batched gradient
descent (Adam) over many starting poses at once, seeded, so a given input always gives the same fit.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch

from .primitive_shapes import FAMILIES, family_mesh, signed_distance

__all__ = ["PrimitiveFit", "fit_primitive", "outline_disagreement", "snap", "trace_depth", "visible_points"]

# Fitting budget: starting poses per family, each COARSE_STEPS Adam steps on half the points; the KEEP best of each
# family then STEPS more on all POINTS of each cloud.
STARTS = 12
COARSE_STEPS = 80
KEEP = 3
STEPS = 60
# A family whose best start is this far off after the coarse steps (its objective, over the shape's diagonal) is not
# refined: no tolerance that makes sense (at most a few per cent) would take it.
GIVE_UP = 0.3
# The outline: rays of up to OUTLINE_RAYS pixels within OUTLINE_BAND pixels of the mask's edge, RAY_SAMPLES points
# each; a ray inside the mask must meet the shape and one outside must miss it (weight OUTLINE_WEIGHT).  The mask is
# sharp where the depth net's surface is rounded: it is what tells a cube from an ellipsoid.
OUTLINE_RAYS = 160
OUTLINE_BAND = 2
RAY_SAMPLES = 32
OUTLINE_WEIGHT = 10.0
# The visible points' weight: the depth net's surface of a primitive is rounded and off by a few per cent of its size.
VISIBLE_WEIGHT = 0.1
LEARNING_RATE = 0.03
POINTS = 512
# The mesh points' weight in the fit: the refiner's mesh carries the hidden side, blurred.
MESH_WEIGHT = 0.3
# The snap decision's weight on the mesh points' mean distance to the fit (chosen on the calibration views among 1,
# 2 and 4: results/decisions.md).
MESH_FACTOR = 2.0


@dataclass(frozen=True)
class PrimitiveFit:
    """One fitted shape: ``family``, ``params`` (family parameters, the table of :mod:`.primitive_shapes`), ``rotation`` (3, 3) own →
    view frame, ``centre`` (3,), ``residual`` (1 − the IoU of its silhouette and the mask:
    :func:`outline_disagreement`; inf before it is measured),
    ``mesh_residual`` (the mesh points' mean distance to the shape over the diagonal) and ``loss`` (the fit's
    weighted objective)."""

    family: str
    params: tuple[float, ...]
    rotation: np.ndarray
    centre: np.ndarray
    residual: float
    mesh_residual: float
    loss: float

    @property
    def disagreement(self) -> float:
        """What the tolerance is compared with: ``max(residual, MESH_FACTOR · mesh_residual)``: the fit must match
        the mask's outline and stay on the refiner's mesh (a shape that fits the outline but not the mesh has
        guessed the depth the outline cannot tell)."""
        return max(self.residual, MESH_FACTOR * self.mesh_residual)

    def accepted(self, tolerance: float) -> bool:
        """Whether :func:`snap` with this ``tolerance`` replaces the mesh by this fit (0: never)."""
        return tolerance > 0 and self.disagreement <= tolerance

    def sdf(self, points: torch.Tensor) -> torch.Tensor:
        """Signed distance of view-frame points (N, 3) to the fitted shape (N,)."""
        rot = torch.from_numpy(self.rotation).to(points)
        local = (points - torch.from_numpy(self.centre).to(points)) @ rot
        return signed_distance(self.family, local, torch.tensor(self.params, dtype=points.dtype))

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """The fitted shape as a closed triangle mesh in the view frame: ``(vertices (V, 3) float32, faces (F, 3) int64)``."""
        v, f = family_mesh(self.family, self.params)
        v = v @ self.rotation.T + self.centre
        return v.astype(np.float32), f.astype(np.int64)

    def describe(self) -> str:
        return f"{self.family} (its silhouette covers the mask with IoU {1 - self.residual:.3f})"


# ----------------------------------------------------------------------------- fitting


def _rotation_6d(x: torch.Tensor) -> torch.Tensor:
    """(B, 6) → (B, 3, 3) rotations (Gram–Schmidt of two vectors; columns are the own frame's axes in the view frame)."""
    a = torch.nn.functional.normalize(x[:, :3], dim=-1)
    b = x[:, 3:] - (a * x[:, 3:]).sum(-1, keepdim=True) * a
    b = torch.nn.functional.normalize(b, dim=-1)
    return torch.stack([a, b, torch.cross(a, b, dim=-1)], dim=-1)


def _start_rotations(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """(count, 3, 3): the cloud's principal axes (each axis taken as the shape's own z in turn) and seeded random poses."""
    centred = points - points.mean(0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    axes = vt.T  # columns: principal directions
    if np.linalg.det(axes) < 0:
        axes[:, 2] = -axes[:, 2]
    starts = [axes[:, [(k + 1) % 3, (k + 2) % 3, k]] for k in range(3)]
    starts += [s * np.array([1.0, -1.0, -1.0]) for s in starts]  # the same axes, own z flipped (a cone's apex)
    while len(starts) < count:
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        w, x, y, z = q
        starts.append(np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]))
    return np.stack(starts[:count])


def _start_params(family: str, local: torch.Tensor) -> torch.Tensor:
    """(B, k) starting parameters from the cloud in each start's own frame (B, N, 3): its half-extents."""
    half = (local.amax(1) - local.amin(1)).clamp(min=1e-3) / 2  # (B, 3)
    if family in ("box", "ellipsoid"):
        return half
    radial = torch.maximum(half[:, 0], half[:, 1])
    if family in ("cylinder", "cone"):
        return torch.stack([radial, half[:, 2]], -1)
    tube = (half[:, 2]).clamp(max=0.9 * radial)
    return torch.stack([(radial - tube).clamp(min=1e-3), tube], -1)


def _params_of(family: str, raw: torch.Tensor) -> torch.Tensor:
    """Free variables → positive parameters (a torus's tube stays below its ring radius)."""
    if family == "torus":
        ring = torch.exp(raw[:, 0])
        return torch.stack([ring, ring * 0.98 * torch.sigmoid(raw[:, 1])], -1)
    return torch.exp(raw)


def _raw_of(family: str, params: torch.Tensor) -> torch.Tensor:
    if family == "torus":
        share = (params[:, 1] / (0.98 * params[:, 0])).clamp(0.05, 0.95)
        return torch.stack([params[:, 0].log(), torch.log(share / (1 - share))], -1)
    return params.log()


def _diag(family: str, params: torch.Tensor) -> torch.Tensor:
    """The bounding-box diagonal of the shape (B,)."""
    if family in ("box", "ellipsoid"):
        half = params
    elif family in ("cylinder", "cone"):
        half = torch.stack([params[:, 0], params[:, 0], params[:, 1]], -1)
    else:
        half = torch.stack([params[:, 0] + params[:, 1], params[:, 0] + params[:, 1], params[:, 1]], -1)
    return 2 * half.norm(dim=-1)


@dataclass
class _Evidence:
    """What a fit is made to explain (view frame, float32): ``visible`` (P, 3) points, ``surface`` (Q, 3) mesh
    points, and optionally the outline: ``rays`` (R, T, 3) points along the rays of pixels near the mask's
    outline, ``inside`` (R,) bool whether each pixel is in the mask."""

    visible: torch.Tensor
    surface: torch.Tensor
    rays: torch.Tensor | None = None
    inside: torch.Tensor | None = None

    def half(self) -> _Evidence:
        """Every other point and ray (they are in random order): the coarse steps' evidence."""
        cut = lambda x: None if x is None else x[: max(1, len(x) // 2)]  # noqa: E731
        return _Evidence(cut(self.visible), cut(self.surface), cut(self.rays), cut(self.inside))

    @property
    def scale(self) -> float:
        both = torch.cat([self.visible, self.surface])
        return float((both.amax(0) - both.amin(0)).norm())


def _outline_rays(depth: torch.Tensor, camera, count: int, rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays of up to ``count`` pixels within :data:`OUTLINE_BAND` pixels of the mask's outline (mask = depth > 0),
    each sampled at :data:`RAY_SAMPLES` planar depths across the object's depth range: ((R, T, 3), (R,) inside)."""
    from scipy import ndimage

    mask = (depth > 0).cpu().numpy()
    band = ndimage.binary_dilation(mask, iterations=OUTLINE_BAND) & ~ndimage.binary_erosion(mask, iterations=OUTLINE_BAND)
    ii, jj = np.nonzero(band)
    if len(ii) > count:
        pick = rng.choice(len(ii), count, replace=False)
        ii, jj = ii[pick], jj[pick]
    size = depth.shape[-1]
    f = camera.focal_px(size)
    seen = depth[depth > 0].double()
    lo, hi = float(seen.min()) - 0.6, float(seen.max()) + 0.6
    t = torch.linspace(max(lo, 1e-3), hi, RAY_SAMPLES, dtype=torch.float64)
    per_t = torch.stack([torch.from_numpy((jj + 0.5 - size / 2.0) / f), torch.from_numpy(-(ii + 0.5 - size / 2.0) / f),
                         -torch.ones(len(ii), dtype=torch.float64)], -1)  # (R, 3)
    pts = torch.tensor([0.0, 0.0, camera.distance], dtype=torch.float64) + t[None, :, None] * per_t[:, None, :]
    return pts.float(), torch.from_numpy(mask[ii, jj])


class _Poses:
    """A batch of candidate shapes of one family being fitted: free variables (B, k), (B, 6), (B, 3)."""

    def __init__(self, family: str, raw: torch.Tensor, six: torch.Tensor, centre: torch.Tensor):
        self.family, self.raw, self.six, self.centre = family, raw, six, centre

    @classmethod
    def start(cls, family: str, points: torch.Tensor, starts: np.ndarray) -> _Poses:
        centre = (points.amax(0) + points.amin(0)) / 2
        rot = torch.from_numpy(starts).to(points)
        local = (points - centre) @ rot  # (B, N, 3): own coordinates (the columns of rot are the own axes)
        return cls(family, _raw_of(family, _start_params(family, local)), torch.cat([rot[:, :, 0], rot[:, :, 1]], -1),
                   centre.expand(len(starts), 3).clone())

    def take(self, index: torch.Tensor) -> _Poses:
        return _Poses(self.family, self.raw[index], self.six[index], self.centre[index])

    def terms(self, ev: _Evidence):
        """The objective's terms (B,) each — the visible points' mean |distance|, the mesh points', the outline's
        mean violation (a ray inside the mask that misses the shape, or one outside that meets it, by how much) —
        and the parameters (B, k) and rotations (B, 3, 3)."""
        rot = _rotation_6d(self.six)
        params = _params_of(self.family, self.raw)
        sd = lambda pts: signed_distance(self.family, (pts[None] - self.centre[:, None]) @ rot, params)  # noqa: E731
        dv = sd(ev.visible).abs().mean(1)
        ds = sd(ev.surface).abs().mean(1)
        if ev.rays is None:
            do = torch.zeros_like(dv)
        else:
            r, t = ev.rays.shape[:2]
            nearest = sd(ev.rays.reshape(-1, 3)).reshape(-1, r, t).amin(-1)  # (B, R): < 0 where the ray meets the shape
            do = torch.where(ev.inside[None], nearest.clamp(min=0), (-nearest).clamp(min=0)).mean(1)
        return dv, ds, do, params, rot

    def objective(self, ev: _Evidence, grad: bool = False) -> torch.Tensor:
        """(B,) the weighted objective over each candidate's bounding-box diagonal."""
        with torch.set_grad_enabled(grad):
            dv, ds, do, params, _ = self.terms(ev)
            return (VISIBLE_WEIGHT * dv + MESH_WEIGHT * ds + OUTLINE_WEIGHT * do) / _diag(self.family, params)

    def descend(self, ev: _Evidence, steps: int) -> None:
        """``steps`` Adam steps on every candidate at once (the objective is scaled by the cloud's size)."""
        scale = ev.scale
        variables = [v.detach().clone().requires_grad_(True) for v in (self.raw, self.six, self.centre)]
        self.raw, self.six, self.centre = variables
        opt = torch.optim.Adam(variables, lr=LEARNING_RATE)
        for _ in range(steps):
            dv, ds, do, _, _ = self.terms(ev)
            loss = (VISIBLE_WEIGHT * dv + MESH_WEIGHT * ds + OUTLINE_WEIGHT * do).sum() / scale
            opt.zero_grad()
            loss.backward()
            opt.step()
        self.raw, self.six, self.centre = (v.detach() for v in variables)

    def best(self, ev: _Evidence) -> PrimitiveFit:
        with torch.no_grad():
            dv, ds, do, params, rot = self.terms(ev)
            diag = _diag(self.family, params)
            total = (VISIBLE_WEIGHT * dv + MESH_WEIGHT * ds + OUTLINE_WEIGHT * do) / diag
            i = int(torch.argmin(total))
            return PrimitiveFit(family=self.family, params=tuple(float(x) for x in params[i]), rotation=rot[i].double().numpy(),
                                centre=self.centre[i].double().numpy(), residual=math.inf,
                                mesh_residual=float(ds[i] / diag[i]), loss=float(total[i]))


def _subsample(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    if len(points) <= count:
        return points
    return points[rng.choice(len(points), count, replace=False)]


def fit_primitive(visible: np.ndarray, surface: np.ndarray, families=FAMILIES, *, depth: torch.Tensor | None = None,
                  camera=None, seed: int = 0) -> PrimitiveFit:
    """The regular shape that best explains the visible points (P, 3) and the mesh points (Q, 3) (view frame).

    Every family is fitted from :data:`STARTS` starting poses, by the weighted objective (the visible points'
    mean distance plus :data:`MESH_WEIGHT` times the mesh points', over the shape's bounding-box diagonal).
    With the masked depth map ``depth`` (S, S) the points came from and its ``camera``, each family's fit is
    judged by :func:`outline_disagreement` (its ``residual``) and the lowest wins; without, the lowest objective
    wins and ``residual`` is inf.  Raises ``ValueError`` for fewer than 16 points of either kind or non-finite points.
    """
    visible = np.asarray(visible, dtype=np.float64).reshape(-1, 3)
    surface = np.asarray(surface, dtype=np.float64).reshape(-1, 3)
    if len(visible) < 16 or len(surface) < 16:
        raise ValueError(f"fit_primitive: need at least 16 visible and 16 mesh points, got {len(visible)} and {len(surface)}")
    if not (np.isfinite(visible).all() and np.isfinite(surface).all()):
        raise ValueError("fit_primitive: points must be finite")
    unknown = [f for f in families if f not in FAMILIES]
    if unknown or not families:
        raise ValueError(f"fit_primitive: families must be among {FAMILIES}, got {families}")
    rng = np.random.default_rng(seed)
    fits = []
    # (fitting needs autograd, also when called from reconstruction, which runs in inference mode)
    with torch.inference_mode(False), torch.enable_grad():
        if depth is not None:
            depth = depth.detach().float().cpu().clone()  # (a normal tensor, not an inference one)
        ev = _Evidence(torch.from_numpy(_subsample(visible, POINTS, rng)).float(), torch.from_numpy(_subsample(surface, POINTS, rng)).float())
        if depth is not None:
            ev.rays, ev.inside = _outline_rays(depth, camera, OUTLINE_RAYS, rng)
        coarse = ev.half()
        starts = _start_rotations(torch.cat([ev.visible, ev.surface]).double().numpy(), STARTS, rng)
        for family in families:  # every start a few steps on half the evidence; the best few on to the end
            poses = _Poses.start(family, torch.cat([ev.visible, ev.surface]), starts)
            poses.descend(coarse, COARSE_STEPS)
            objective = poses.objective(coarse)
            poses = poses.take(torch.argsort(objective)[:KEEP])
            if float(objective.min()) <= GIVE_UP:
                poses.descend(ev, STEPS)
            fits.append(poses.best(ev))
    if depth is None:
        return min(fits, key=lambda fit: fit.loss)
    fits = [dataclasses.replace(fit, residual=outline_disagreement(fit, depth, camera)) for fit in fits]
    return min(fits, key=lambda fit: (fit.residual, fit.loss))


def snap(vertices: np.ndarray, faces: np.ndarray, depth: torch.Tensor, camera, tolerance: float, *, seed: int = 0):
    """The mesh, or the regular shape that explains it: ``(vertices, faces, fit)``.

    ``vertices`` (V, 3) / ``faces`` (F, 3): the reconstruction's mesh (view frame); ``depth`` (S, S): the masked
    depth map it was made from (background 0) and ``camera`` its camera.  ``fit`` is the best
    :class:`PrimitiveFit` (None when the stage is off or there are too few points); the mesh is replaced by it
    only when ``fit.accepted(tolerance)``: its :attr:`~PrimitiveFit.disagreement` (1 − silhouette IoU, or twice
    the mesh's mean distance to it over its diagonal, whichever is larger) is at most ``tolerance``.
    ``tolerance`` 0 turns the stage off.
    """
    from .metrics import sample_surface

    if isinstance(tolerance, bool) or not (math.isfinite(tolerance) and 0.0 <= tolerance < 1.0):
        raise ValueError(f"tolerance: expected a number in [0, 1), got {tolerance!r}")
    visible = visible_points(depth, camera)
    if tolerance == 0.0 or len(faces) == 0 or len(visible) < 16:
        return vertices, faces, None
    surface = sample_surface(vertices, faces, POINTS, seed=seed).numpy()
    fit = fit_primitive(visible, surface, depth=depth, camera=camera, seed=seed)
    if fit.accepted(tolerance):
        v, f = fit.mesh()
        return v, f, fit
    return vertices, faces, fit


def visible_points(depth: torch.Tensor, camera) -> np.ndarray:
    """The surface the camera sees: a masked depth map (S, S) (background 0) unprojected to view-frame points (P, 3)."""
    from ..frame import depth_to_points

    depth = depth.detach().float().cpu()
    pts = depth_to_points(depth[None], camera)[0]
    return pts[depth > 0].double().numpy()


def trace_depth(fit: PrimitiveFit, camera, size: int, steps: int = 64) -> torch.Tensor:
    """The planar depth map (size, size) of the fitted shape seen by ``camera`` (background 0), by sphere tracing
    its signed distance along each pixel's ray (:func:`genre_backend.frame.depth_to_points`' convention).  A ray
    counts as a hit when it comes within a fiftieth of a pixel's footprint of the surface (a grazing ray at the rim,
    which sphere tracing approaches only slowly, still counts; on the analytic sphere the mask is exact)."""
    f = camera.focal_px(size)
    c = (torch.arange(size, dtype=torch.float64) + 0.5 - size / 2.0) / f
    per_t = torch.stack(torch.broadcast_tensors(c.view(1, size), -c.view(size, 1), torch.tensor(-1.0, dtype=torch.float64)), -1)
    origin = torch.tensor([0.0, 0.0, camera.distance], dtype=torch.float64)
    stretch = per_t.norm(dim=-1)  # Euclidean length of one unit of planar depth
    t = torch.zeros(size, size, dtype=torch.float64)
    closest = torch.full((size, size), math.inf, dtype=torch.float64)
    at = torch.zeros_like(t)
    diag = float(_diag(fit.family, torch.tensor([fit.params], dtype=torch.float64))[0])
    for _ in range(steps + 1):
        d = fit.sdf((origin + t[..., None] * per_t).reshape(-1, 3)).reshape(size, size)
        nearer = d < closest
        closest, at = torch.where(nearer, d, closest), torch.where(nearer, t, at)
        t = (t + 0.9 * d.clamp(min=-diag) / stretch).clamp(0.0, 2 * camera.distance)  # (0.9: the ellipsoid's estimate)
    hit = closest < 0.02 * at * stretch / f
    return torch.where(hit, at, torch.zeros_like(at)).float()


def outline_disagreement(fit: PrimitiveFit, depth: torch.Tensor, camera) -> float:
    """1 − the IoU of the fitted shape's silhouette (:func:`trace_depth`) and the mask (``depth`` (S, S) > 0):
    0 when the shape covers exactly the object's pixels.  1 when nothing is seen."""
    mask = depth.detach().cpu() > 0
    mine = trace_depth(fit, camera, depth.shape[-1]) > 0
    union = int((mask | mine).sum())
    return 1.0 - int((mask & mine).sum()) / union if union else 1.0
