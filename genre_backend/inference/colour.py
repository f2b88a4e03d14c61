"""Colour from the photo: which vertices the photo sees, their UVs into it, and colour for the rest.

The mesh is posed in the view frame of :mod:`genre_backend.frame`, so the
camera that took the (framed) photo is known exactly: a vertex's texture
coordinate is its own projection into the square crop the networks saw.

* :func:`zbuffer` rasterises the mesh's planar depth at the network's image
  size (:func:`zbuffer_reference` is the slow per-face loop beside it);
* :func:`seen_vertices` keeps the vertices that face the camera, are not
  hidden behind other faces, and land inside the object mask;
* :func:`photo_texture` gives every vertex a UV: its projection when seen;
  for the rest a **harmonic fill** of the UVs over the mesh graph
  (:func:`harmonic_fill`), with the seen vertices that land inside the
  object mask shrunk by :data:`SOURCE_MARGIN_PX` pixels as fixed values.
  The hidden side so shows the photo's object, mirrored through the
  outline and spread smoothly over the back (a harmonic map of a disc onto a
  convex outline is one-to-one), with no seams between patches, and never
  the background: a filled UV that still lands outside the shrunk mask (a
  concave outline) moves to its nearest pixel inside, and the texture's
  pixels outside the mask take the colour of the nearest pixel inside the
  shrunk mask, so not even a face's interior shows the backdrop.

Why UVs and not colours are diffused: every format keeps one UV per vertex
(OBJ ``f v/v``, glTF attributes), so a hidden vertex's colour must be a
place in the texture that its seen neighbours' faces can blend towards.

Before (each hidden vertex took the UV of the nearest seen vertex in 3D):
on ``make demo``'s sofa and five real photos, 78–91 % of the hidden
vertices read the photo outside the shrunk mask (the outline's blend with the
backdrop: the sofa's back had a green patch), and the colour jumps between
hidden neighbours had a 99th percentile of 41–123 / 255
(``scripts/hidden_colour.py``; the figures after are in the README's
*What to expect*).

UVs follow the glTF/OBJ convention used by Blender: ``u`` left → right,
``v`` bottom → top of the texture image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..config import CameraConfig
from ..frame import view_to_pixels
from ..geometry.mesh_voxels import vertex_normals

__all__ = ["MAX_TEXTURE_SIDE", "SEEN_MARGIN_PX", "SOURCE_MARGIN_PX", "PhotoTexture", "project", "zbuffer", "zbuffer_reference",
           "seen_vertices", "mesh_edges", "harmonic_fill", "shrink_mask", "fill_outside_mask", "hidden_edge_jumps", "photo_texture",
           "sample_bilinear"]

# The texture is the photo's crop at its own resolution, capped at this many pixels a side.
MAX_TEXTURE_SIDE = 2048
# A vertex is seen only inside the object mask shrunk by this many pixels (at the network's image size) ...
SEEN_MARGIN_PX = 1
# ... and lends its UV to the hidden side only inside the mask shrunk by this many: the outline's pixels
# blend the object with the backdrop.
SOURCE_MARGIN_PX = 2


def project(vertices: np.ndarray, camera: CameraConfig, size: int) -> tuple[np.ndarray, np.ndarray]:
    """View-frame points (V, 3) → (pixel coordinates (V, 2) float64 (u along columns, v along rows), planar depth (V,))."""
    uv, depth = view_to_pixels(torch.as_tensor(np.asarray(vertices, np.float64)), camera, size)
    return uv.numpy(), depth.numpy()


def zbuffer(vertices: np.ndarray, faces: np.ndarray, camera: CameraConfig, size: int, max_face_px: int = 16) -> np.ndarray:
    """Nearest planar depth (size, size) of the mesh at each pixel centre; ``inf`` where no face covers it.

    vertices (V, 3) view frame, faces (F, 3) int.  Faces are rasterised with
    barycentric tests over their pixel bounding boxes, all faces at once per
    offset in the box; a face wider than ``max_face_px`` pixels is tested only
    on its first ``max_face_px``² pixels (marching-cubes faces are ~1–2 px).
    """
    uv, depth = project(vertices, camera, size)
    f = np.asarray(faces, np.int64)
    zb = np.full(size * size, np.inf)
    if len(f) == 0:
        return zb.reshape(size, size)
    p = uv[f]  # (F, 3, 2)
    d = depth[f]  # (F, 3)
    x0 = np.floor(p[..., 0].min(axis=1) - 0.5).astype(np.int64)
    y0 = np.floor(p[..., 1].min(axis=1) - 0.5).astype(np.int64)
    w = np.minimum(np.ceil(p[..., 0].max(axis=1) - 0.5).astype(np.int64) - x0 + 1, max_face_px)
    h = np.minimum(np.ceil(p[..., 1].max(axis=1) - 0.5).astype(np.int64) - y0 + 1, max_face_px)
    ax, bx, cx = p[:, 0, 0], p[:, 1, 0], p[:, 2, 0]
    ay, by, cy = p[:, 0, 1], p[:, 1, 1], p[:, 2, 1]
    den = (by - cy) * (ax - cx) + (cx - bx) * (ay - cy)
    ok = np.abs(den) > 1e-12
    den = np.where(ok, den, 1.0)
    for dy in range(int(h.max())):
        for dx in range(int(w.max())):
            px, py = x0 + dx, y0 + dy
            sel = ok & (dx < w) & (dy < h) & (px >= 0) & (px < size) & (py >= 0) & (py < size)
            qx, qy = px + 0.5, py + 0.5
            l0 = ((by - cy) * (qx - cx) + (cx - bx) * (qy - cy)) / den
            l1 = ((cy - ay) * (qx - cx) + (ax - cx) * (qy - cy)) / den
            l2 = 1.0 - l0 - l1
            sel &= (l0 >= -1e-9) & (l1 >= -1e-9) & (l2 >= -1e-9)
            if not sel.any():
                continue
            # planar depth is affine in the view frame but not in the image: interpolate 1/depth
            inv = l0[sel] / d[sel, 0] + l1[sel] / d[sel, 1] + l2[sel] / d[sel, 2]
            np.minimum.at(zb, py[sel] * size + px[sel], 1.0 / inv)
    return zb.reshape(size, size)


def zbuffer_reference(vertices: np.ndarray, faces: np.ndarray, camera: CameraConfig, size: int) -> np.ndarray:
    """:func:`zbuffer` one face and one pixel at a time (slow; for tests)."""
    uv, depth = project(vertices, camera, size)
    zb = np.full((size, size), np.inf)
    for tri in np.asarray(faces, np.int64):
        (ax, ay), (bx, by), (cx, cy) = uv[tri]
        den = (by - cy) * (ax - cx) + (cx - bx) * (ay - cy)
        if abs(den) <= 1e-12:
            continue
        for py in range(max(0, int(np.floor(min(ay, by, cy) - 0.5))), min(size, int(np.ceil(max(ay, by, cy) - 0.5)) + 1)):
            for px in range(max(0, int(np.floor(min(ax, bx, cx) - 0.5))), min(size, int(np.ceil(max(ax, bx, cx) - 0.5)) + 1)):
                qx, qy = px + 0.5, py + 0.5
                l0 = ((by - cy) * (qx - cx) + (cx - bx) * (qy - cy)) / den
                l1 = ((cy - ay) * (qx - cx) + (ax - cx) * (qy - cy)) / den
                l2 = 1.0 - l0 - l1
                if min(l0, l1, l2) >= -1e-9:
                    z = 1.0 / (l0 / depth[tri[0]] + l1 / depth[tri[1]] + l2 / depth[tri[2]])
                    zb[py, px] = min(zb[py, px], z)
    return zb


def seen_vertices(vertices: np.ndarray, faces: np.ndarray, camera: CameraConfig, mask: np.ndarray, tolerance: float) -> np.ndarray:
    """(V,) bool: the vertices the photo shows.

    A vertex is seen when its normal faces the camera, its planar depth is
    within ``tolerance`` (view-frame units) of the z-buffer around its pixel
    (the farthest of the 3×3 pixels), and
    that pixel lies inside ``mask`` ((S, S) bool, the object mask at the
    network's image size S).
    """
    m = np.asarray(mask, bool)
    if m.ndim != 2 or m.shape[0] != m.shape[1]:
        raise ValueError(f"mask: expected a square (S, S) array, got shape {m.shape}")
    size = m.shape[0]
    v = np.asarray(vertices, np.float64)
    uv, depth = project(v, camera, size)
    col = np.clip(np.floor(uv[:, 0]).astype(np.int64), 0, size - 1)
    row = np.clip(np.floor(uv[:, 1]).astype(np.int64), 0, size - 1)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < size) & (uv[:, 1] >= 0) & (uv[:, 1] < size)
    from scipy.ndimage import maximum_filter

    # the farthest of the 3×3 pixels around the vertex: a surface seen at a grazing angle changes depth a
    # lot within one pixel, while a real occluder covers the whole neighbourhood
    zb = maximum_filter(zbuffer(v, faces, camera, size), size=3, mode="nearest")
    unhidden = depth <= zb[row, col] + tolerance
    to_camera = np.array([0.0, 0.0, camera.distance]) - v
    facing = np.einsum("ij,ij->i", vertex_normals(v, faces), to_camera) > 0
    return inside & m[row, col] & unhidden & facing


def sample_bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Colours (N, C) uint8 of ``image`` (H, W, C) uint8 at texture coordinates ``uv`` (N, 2) (v up), clamped at the edges."""
    img = np.asarray(image, np.float64)
    h, w = img.shape[:2]
    x = np.clip(uv[:, 0] * w - 0.5, 0, w - 1)
    y = np.clip((1.0 - uv[:, 1]) * h - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return np.clip(np.rint(top * (1 - fy) + bottom * fy), 0, 255).astype(np.uint8)


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """The unique undirected edges (E, 2) int64 of triangles ``faces`` (F, 3), each as (low, high) index."""
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    e = np.sort(e, axis=1)
    e = e[e[:, 0] != e[:, 1]]
    return np.unique(e, axis=0) if len(e) else np.zeros((0, 2), np.int64)


def harmonic_fill(values: np.ndarray, known: np.ndarray, faces: np.ndarray, vertices: np.ndarray | None = None) -> np.ndarray:
    """Values (V, C) float64 equal to ``values`` (V, C) where ``known`` (V,) bool, harmonic on the mesh graph elsewhere.

    Each unknown vertex's value is the mean of its neighbours' (the graph
    Laplacian with unit edge weights, solved exactly with the known values
    as Dirichlet conditions).  A connected part with no known vertex takes,
    whole, the value of the known vertex nearest in 3D to any of its vertices
    (``vertices`` (V, 3) needed then; without any known vertex the values
    are returned unchanged).
    """
    from scipy import sparse
    from scipy.sparse.csgraph import connected_components
    from scipy.sparse.linalg import splu

    x = np.array(values, np.float64, copy=True)
    if x.ndim == 1:
        return harmonic_fill(x[:, None], known, faces, vertices)[:, 0]
    known = np.asarray(known, bool)
    n = len(x)
    if known.all() or not known.any():
        return x
    e = mesh_edges(faces)
    adj = sparse.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()
    _, part = connected_components(adj, directed=False)
    anchored = np.zeros(part.max() + 1, bool)
    anchored[part[known]] = True
    free = ~known & anchored[part]
    if free.any():
        lap = (sparse.diags(np.asarray(adj.sum(axis=1)).ravel()) - adj).tocsr()
        fi, ki = np.flatnonzero(free), np.flatnonzero(known)
        a = lap[fi][:, fi].tocsc()
        b = -(lap[fi][:, ki] @ x[ki])
        x[fi] = splu(a).solve(np.ascontiguousarray(b))
    lone = ~known & ~anchored[part]
    if lone.any() and vertices is not None:
        from scipy.spatial import cKDTree

        v = np.asarray(vertices, np.float64)
        ki, li = np.flatnonzero(known), np.flatnonzero(lone)
        dist, nearest = cKDTree(v[ki]).query(v[li])
        order = np.lexsort((dist, part[li]))  # by part, then distance: each part's closest vertex first
        first = np.unique(part[li][order], return_index=True)[1]
        best = dict(zip(part[li][order][first], ki[nearest[order][first]]))
        x[li] = x[[best[p] for p in part[li]]]
    return x


def shrink_mask(mask: np.ndarray, margin_px: float) -> np.ndarray:
    """(S, S) bool: the pixels of ``mask`` (S, S) bool farther than ``margin_px`` (Euclidean, between pixel
    centres) from every pixel outside it; pixels beyond the image's border count as inside."""
    from scipy.ndimage import distance_transform_edt

    m = np.pad(np.asarray(mask, bool), 1, constant_values=True)
    return distance_transform_edt(m)[1:-1, 1:-1] > margin_px


def _upsample_mask(mask: np.ndarray, side: int) -> np.ndarray:
    """``mask`` (S, S) bool at ``side`` (side, side) by nearest pixel centre."""
    s = mask.shape[0]
    idx = np.minimum(((np.arange(side) + 0.5) * s / side).astype(np.int64), s - 1)
    return mask[np.ix_(idx, idx)]


def fill_outside_mask(image: np.ndarray, mask: np.ndarray, source: np.ndarray) -> np.ndarray:
    """``image`` (T, T, 3) uint8 with every pixel outside ``mask`` (S, S) bool given the colour of the nearest
    pixel inside ``source`` (S, S) bool (the masks scaled to T by nearest pixel); unchanged if ``source`` is empty."""
    from scipy.ndimage import distance_transform_edt

    side = image.shape[0]
    src = _upsample_mask(np.asarray(source, bool), side)
    out = ~_upsample_mask(np.asarray(mask, bool), side)
    if not src.any() or not out.any():
        return image
    _, (rows, cols) = distance_transform_edt(~src, return_indices=True)
    filled = image.copy()
    filled[out] = image[rows[out], cols[out]]
    return filled


def hidden_edge_jumps(texture: "PhotoTexture", faces: np.ndarray) -> np.ndarray:
    """Colour jumps (E_h,) float64: mean |ΔRGB| (0-255) of the vertex colours across each edge of ``faces``
    (F, 3) whose two ends are hidden (not ``texture.seen``)."""
    rgb = texture.vertex_colours()[:, :3].astype(np.float64)
    e = mesh_edges(faces)
    hidden = ~np.asarray(texture.seen, bool)
    e = e[hidden[e[:, 0]] & hidden[e[:, 1]]]
    return np.abs(rgb[e[:, 0]] - rgb[e[:, 1]]).mean(axis=1)


@dataclass
class PhotoTexture:
    """A mesh's colour from its photo.

    ``image``: (T, T, 3) uint8, the square of the photo the camera saw (the
    reconstruction's ``crop_box``) at up to :data:`MAX_TEXTURE_SIDE` pixels,
    its pixels outside the object mask filled from inside it.
    ``uv``: (V, 2) float32 texture coordinates into ``image`` (v up).
    ``seen``: (V,) bool, the vertices whose UV is their own projection; the
    others carry UVs filled from the seen ones (:func:`photo_texture`).
    """

    image: np.ndarray
    uv: np.ndarray
    seen: np.ndarray

    def vertex_colours(self) -> np.ndarray:
        """(V, 4) uint8 RGBA: the texture sampled at each vertex's UV (for formats without textures)."""
        rgb = sample_bilinear(self.image, self.uv.astype(np.float64))
        return np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], axis=1)


def photo_texture(vertices: np.ndarray, faces: np.ndarray, camera: CameraConfig, mask: np.ndarray, image: np.ndarray, tolerance: float) -> PhotoTexture:
    """UVs of every vertex into ``image`` (T, T, 3) uint8, the photo's crop seen by ``camera``; see the module docstring.

    vertices (V, 3) view frame, faces (F, 3), mask (S, S) bool: the object
    mask at the network's image size (shrunk here: by :data:`SEEN_MARGIN_PX`
    for what is seen, by :data:`SOURCE_MARGIN_PX` (:func:`shrink_mask`) for
    what colours the hidden side; pixels beyond the image's border count as
    inside), ``tolerance``:
    the z-buffer tolerance of :func:`seen_vertices` (about a voxel and a half).
    The returned ``image`` is ``image`` with the pixels outside ``mask``
    filled from inside the shrunk mask (:func:`fill_outside_mask`).
    """
    from scipy.ndimage import binary_erosion, distance_transform_edt

    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"image: expected (T, T, 3) uint8, got {img.shape} {img.dtype}")
    m = np.asarray(mask, bool)
    v = np.asarray(vertices, np.float64)
    size = m.shape[0]
    seen = seen_vertices(v, faces, camera, binary_erosion(m, iterations=SEEN_MARGIN_PX, border_value=1), tolerance)
    shrunk = shrink_mask(m, SOURCE_MARGIN_PX)
    pix, _ = project(v, camera, size)
    col = np.clip(np.floor(pix[:, 0]).astype(np.int64), 0, size - 1)
    row = np.clip(np.floor(pix[:, 1]).astype(np.int64), 0, size - 1)
    uv = np.stack([pix[:, 0] / size, 1.0 - pix[:, 1] / size], axis=1)
    if not shrunk.any() or seen.all():
        return PhotoTexture(img, uv.astype(np.float32), seen)
    _, (near_rows, near_cols) = distance_transform_edt(~shrunk, return_indices=True)

    def snap(sel: np.ndarray) -> None:
        """Move the UVs of ``sel`` (V,) bool that land outside the shrunk mask to its nearest pixel centre."""
        c = np.clip(np.floor(uv[:, 0] * size).astype(np.int64), 0, size - 1)
        r = np.clip(np.floor((1.0 - uv[:, 1]) * size).astype(np.int64), 0, size - 1)
        off = sel & ~shrunk[r, c]
        uv[off, 0] = (near_cols[r[off], c[off]] + 0.5) / size
        uv[off, 1] = 1.0 - (near_rows[r[off], c[off]] + 0.5) / size

    source = seen & shrunk[row, col]
    if not source.any():  # a mask too thin to shrink: every seen vertex lends its UV
        source = seen
    filled = harmonic_fill(uv, source, faces, v)
    uv[~seen] = filled[~seen]
    snap(~seen)  # a filled UV outside the shrunk mask (a concave outline)
    img = fill_outside_mask(img, m, shrunk)
    return PhotoTexture(img, uv.astype(np.float32), seen)
