"""The faces along the camera's rays, made whole in a predicted distance grid before the mesh is made.

* :func:`depth_to_distance` is the distance target of the surface a depth map shows (its pixels triangulated, jumps
  dropped, :func:`.mesh_voxels.mesh_to_distance` of that open sheet).
* :func:`fuse_visible_surface` adds it to a predicted grid where the grid leaves a hole (optionally: a deep pit) in
  what the camera sees, so that the mesh's front is whole (``GeometryConfig.visible_fusion``).
* :func:`seal_pits` fills the narrow wells in the grid's own visible front from the front around them
  (``GeometryConfig.pit_sealing``).
* :func:`seal_back` fills the dents in the grid's back, the side the camera cannot see, up to the rim around them
  (``GeometryConfig.back_sealing``).

Grids as in :mod:`.mesh_voxels`; only for the ``distance`` target.
"""

from __future__ import annotations

import numpy as np
import torch

from ..validation import check_hole_closing, check_tensor, check_threshold
from .mesh_voxels import mesh_to_distance

__all__ = ["depth_to_distance", "fuse_visible_surface", "seal_pits", "seal_back", "PIT_MIN_DEPTH_VOXELS"]

def depth_to_distance(depth: torch.Tensor, camera, geometry, mask: torch.Tensor | None = None) -> torch.Tensor:
    """The distance target (N, N, N) float32 of the surface one depth map shows, in the view frame.

    depth: (S, S) planar depth (background 0); mask: (S, S) bool, optional
    (default: depth > 0).  Neighbouring pixels are joined into triangles
    (:func:`..spherical.depth_to_triangles`: a triangle across a depth jump,
    longer than ``geometry.depth_edge_max_ratio`` pixel footprints, is
    dropped) and the grid is :func:`.mesh_voxels.mesh_to_distance` of that open sheet, the
    same truncated distance the refiner is trained to predict.  All zeros when
    no triangle is left.
    """
    from .spherical import depth_to_triangles

    check_tensor("depth", depth, ("S", "S"))
    tris, _ = depth_to_triangles(depth[None].float(), camera, geometry.depth_edge_max_ratio,
                                 None if mask is None else mask[None])
    n = geometry.voxel_size
    if len(tris) == 0:
        return torch.zeros((n, n, n), dtype=torch.float32)
    vertices = tris.reshape(-1, 3).double()
    faces = torch.arange(len(vertices), dtype=torch.int64).reshape(-1, 3)
    return mesh_to_distance(vertices, faces, n, geometry.distance_band, tree=False)  # the runtime's: no libigl


def fuse_visible_surface(prob: torch.Tensor, depth: torch.Tensor, camera, geometry, level: float,
                         grow_px: int = 2, pit_voxels: float | None = None) -> torch.Tensor:
    """A distance-target grid (N, N, N) with the holes in its visible face filled from the depth map.

    prob: (N, N, N) float in [0, 1] (the refiner's sigmoid, carved if the
    weights carve); depth: (S, S) the masked depth (background 0); ``level``:
    the iso-level the mesh is made at.  An object pixel whose ray meets no
    value above ``level`` (:func:`..voxels.ray_first_hit`: a hole through the
    front, a part the photo shows left out) is filled: those pixels are grown
    by ``grow_px`` so that the patch overlaps the grid's surface around them,
    and there the depth map's own surface is added, ``max(prob, visible)``
    (:func:`depth_to_distance`).  Where the grid covers a pixel nothing
    changes.  Returns ``prob`` (as float32, on the CPU) when nothing needs
    filling.  Only for ``geometry.target == "distance"``.

    ``pit_voxels``: also fill the pixels whose ray meets the grid more than
    this many voxels behind the depth map (a pit: the front face missing, the
    inside of the back seen).  The depth map is then first moved along the
    view axis onto the grid's front (by the median difference over the pixels
    that meet something, the tube's crossing lying ``(1 − level)·band`` voxels
    in front of its surface), and the moved map is what fills.  Measured on
    the seen-test views (``scripts/visible_fusion.py --pit-voxels 3``) it cost
    4.4–4.6 % CD against 0.1–1.9 % for the holes alone (the default weights
    with pits deeper than 6 or 10 voxels: 3.8 %, 2.9 %), so the setting
    (``GeometryConfig.visible_fusion``) fills holes only.
    """
    from scipy import ndimage

    from .voxels import ray_first_hit

    if geometry.target != "distance":
        raise ValueError("fuse_visible_surface: the visible surface is fused only into distance-target grids")
    n = geometry.voxel_size
    check_tensor("prob", prob, (n, n, n))
    check_tensor("depth", depth, ("S", "S"))
    if pit_voxels is not None and not (np.isfinite(pit_voxels) and pit_voxels > 0):
        raise ValueError(f"pit_voxels: expected a positive number of voxels, got {pit_voxels!r}")
    prob = prob.detach().cpu().float()
    depth = depth.detach().cpu().float()
    obj = depth > 0
    hit = ray_first_hit(prob, level, camera, depth.shape[-1])
    met = obj & torch.isfinite(hit)
    holes = obj & ~met
    moved = depth
    if pit_voxels is not None and met.any():
        h = 1.0 / n
        front = hit + (1.0 - level) * geometry.distance_band * h  # the surface behind the tube's crossing
        moved = torch.where(obj, depth + float((front - depth)[met].median()), depth)
        holes = holes | (met & (front - moved > pit_voxels * h))
    if not holes.any():
        return prob
    holes = holes.numpy()
    if grow_px > 0:
        holes = ndimage.binary_dilation(holes, np.ones((3, 3), bool), iterations=int(grow_px)) & obj.numpy()
    visible = depth_to_distance(moved.clamp(min=0.0) * obj, camera, geometry, torch.from_numpy(holes))
    return torch.maximum(prob, visible)


# A pit's floor must lie at least this many voxels behind its rim for seal_pits to fill it: the level
# crossing of a blurry front wanders by about a voxel, which is not a pit.
PIT_MIN_DEPTH_VOXELS = 2.0


def seal_pits(prob: torch.Tensor, mask: torch.Tensor, camera, geometry, level: float, width_voxels: int,
              grow_px: int = 2) -> torch.Tensor:
    """A distance-target grid (N, N, N) with the narrow pits in its visible face sealed by its own front.

    prob: (N, N, N) float in [0, 1] (the refiner's sigmoid, after any
    carving or fusion); mask: (S, S) bool, the object's pixels; ``level``:
    the iso-level the mesh is made at; ``width_voxels`` (int, 0-8; 0 returns
    ``prob``): the widest pit sealed is about ``2·width_voxels`` voxels across.

    The depth at which each object pixel's ray first meets the grid
    (:func:`..voxels.ray_first_hit`; a ray that meets nothing counts as far
    behind the object) is a height field seen from the camera.  A pit is a
    basin of it: pixels from which every path to the outside of the mask
    first climbs to a nearer depth, the well a blurry front wall leaves when
    its crossing falls through to the inside of the back.  The basins are
    filled to the depth of their rim (morphological reconstruction by
    erosion, scikit-image); those whose floor lies more than
    :data:`PIT_MIN_DEPTH_VOXELS` behind the filled surface and whose half-width
    (the largest distance from a pixel of the basin to its edge) is at most
    ``width_voxels`` voxels' worth of pixels are sealed: over the basin, grown
    by ``grow_px`` pixels so that the patch meets the front around it, the
    filled height field's own surface (moved behind the crossing to the
    surface the tube stands for) is added as a distance target,
    ``max(prob, patch)`` (:func:`depth_to_distance`).  A front that falls
    away toward the outline (a convex face) and a basin wider than the limit
    (a bowl seen from above) are left alone, and nothing is ever removed.
    Returns ``prob`` (float32, on the CPU) when nothing is sealed.  Only for
    ``geometry.target == "distance"``.
    """
    from scipy import ndimage

    from .voxels import ray_first_hit

    n, level = geometry.voxel_size, _checked_grid_and_mask("seal_pits: pits", prob, mask, geometry, level)
    width_voxels = check_hole_closing("width_voxels", width_voxels)  # (the same kind of width as hole_closing's)
    prob = prob.detach().cpu().float()
    if width_voxels == 0:
        return prob
    obj = mask.detach().cpu().numpy()
    size = obj.shape[-1]
    h = 1.0 / n
    far = float(camera.distance) + 1.0  # beyond the cube's far side: what a ray that meets nothing sees
    hit = ray_first_hit(prob, level, camera, size).numpy().astype(np.float64)
    front = np.where(obj & np.isfinite(hit), hit, far)
    filled = -_fill_basins(-front)  # nearer is higher; outside the mask the lowest, the sea every basin drains to
    rimmed = filled < far - h  # pixels with a nearer front to seal them with
    basins = obj & rimmed & (front - filled > PIT_MIN_DEPTH_VOXELS * h)
    if not basins.any():
        return prob
    labels, count = ndimage.label(basins)
    half_width = ndimage.distance_transform_edt(basins)
    widest = ndimage.maximum(half_width, labels, np.arange(1, count + 1))
    narrow = np.isin(labels, 1 + np.flatnonzero(np.asarray(widest) <= width_voxels * size / n))
    if not narrow.any():
        return prob
    if grow_px > 0:
        narrow = ndimage.binary_dilation(narrow, np.ones((3, 3), bool), iterations=int(grow_px)) & obj & rimmed
    surface = filled + (1.0 - level) * geometry.distance_band * h  # the crossing lies this far in front of the surface
    region = torch.from_numpy(narrow)
    patch = depth_to_distance(torch.from_numpy(np.where(narrow, surface, 0.0)).float(), camera, geometry, region)
    return torch.maximum(prob, patch)


def _checked_grid_and_mask(what: str, prob: torch.Tensor, mask: torch.Tensor, geometry, level: float) -> float:
    """The checks :func:`seal_pits` and :func:`seal_back` share (a distance grid of the geometry's size, a bool mask);
    returns the checked level."""
    if geometry.target != "distance":
        raise ValueError(f"{what} are sealed only in distance-target grids")
    n = geometry.voxel_size
    check_tensor("prob", prob, (n, n, n))
    check_tensor("mask", mask, ("S", "S"), floating=False)
    if mask.dtype != torch.bool:
        raise ValueError(f"mask: expected a bool tensor, got {mask.dtype}")
    return check_threshold("level", level)


def _fill_basins(height: np.ndarray) -> np.ndarray:
    """A height field (S, S) with every basin raised to its rim: morphological reconstruction by erosion from the
    image's border (scikit-image), so that water drains only over the border; the rest is unchanged."""
    from skimage.morphology import reconstruction

    seed = np.full_like(height, height.max())
    seed[0, :], seed[-1, :], seed[:, 0], seed[:, -1] = height[0, :], height[-1, :], height[:, 0], height[:, -1]
    return reconstruction(seed, height, method="erosion")


def seal_back(prob: torch.Tensor, mask: torch.Tensor, camera, geometry, level: float, grow_px: int = 2) -> torch.Tensor:
    """A distance-target grid (N, N, N) with the dents in its back, the side the camera cannot see, filled to their rim.

    prob: (N, N, N) float in [0, 1] (the refiner's sigmoid, after the other steps); mask: (S, S) bool, the object's
    pixels; ``level``: the iso-level the mesh is made at.

    The depth at which each object pixel's ray last leaves the grid (:func:`..voxels.ray_last_hit`) is the back seen
    from behind: a height field in which farther is higher.  Where the refiner's back is faint in its middle, its
    crossing falls forward onto the inside of the front and the mesh's back is a dish inside a rim (a real orange's,
    a hollow half as deep as the fruit).  A dent is a basin of that field: pixels from which every path to the outside
    of the mask (or to a ray that meets nothing, a hole through the object) first climbs to a farther depth.  The
    basins whose floor lies more than :data:`PIT_MIN_DEPTH_VOXELS` below their rim are filled to the depth of their
    rim, margins and all, whatever their width, and, over each basin grown by ``grow_px`` pixels, the filled field's
    surface (moved in front of the crossing to the surface the tube stands for) is added as a distance target,
    ``max(prob, patch)`` (:func:`depth_to_distance`): a lid that closes the dish, whose inside the mesh then fills.
    A back that is convex seen from behind, and one open to the outline or to a hole, are left alone; nothing is ever
    removed.  Returns ``prob`` (float32, on the CPU) when nothing is sealed.  Only for ``geometry.target ==
    "distance"``.
    """
    from scipy import ndimage

    from .voxels import ray_last_hit

    n, level = geometry.voxel_size, _checked_grid_and_mask("seal_back: dents", prob, mask, geometry, level)
    prob = prob.detach().cpu().float()
    obj = mask.detach().cpu().numpy()
    h = 1.0 / n
    near = float(camera.distance) - 1.0  # before the cube's near side: what a ray that meets nothing counts as
    hit = ray_last_hit(prob, level, camera, obj.shape[-1]).numpy().astype(np.float64)
    held = obj & np.isfinite(hit)
    back = np.where(held, hit, near)
    filled = _fill_basins(back)  # farther is higher: each dent raised to its rim, away from the camera
    raised = held & (filled > near + h) & (filled - back > 0.25 * h)  # a dent's whole floor, its shallow margin too
    labels, count = ndimage.label(raised)
    if count == 0:
        return prob
    deepest = ndimage.maximum(filled - back, labels, np.arange(1, count + 1))
    basins = np.isin(labels, 1 + np.flatnonzero(np.asarray(deepest) > PIT_MIN_DEPTH_VOXELS * h))
    if not basins.any():
        return prob
    if grow_px > 0:
        basins = ndimage.binary_dilation(basins, np.ones((3, 3), bool), iterations=int(grow_px)) & held
    surface = filled - (1.0 - level) * geometry.distance_band * h  # the back's crossing lies this far behind its surface
    region = torch.from_numpy(basins)
    patch = depth_to_distance(torch.from_numpy(np.where(basins, surface, 0.0)).float(), camera, geometry, region)
    return torch.maximum(prob, patch)
