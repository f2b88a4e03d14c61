"""Colour from the photo: which faces the photo shows, their UVs into it, and a smooth colour for the rest.

The mesh is posed in the view frame of :mod:`genre_backend.frame`, so the
camera that took the (framed) photo is known exactly: a point's texture
coordinate is its own projection into the square crop the networks saw.

* :func:`zbuffer` rasterises the mesh's planar depth (:func:`zbuffer_reference`
  is the slow per-face loop beside it);
* :func:`front_faces` keeps the faces the photo shows: the nearest to the
  camera at a pixel centre inside the object mask, at 1, 2, 4 and 8 times
  the network's image size;
* :func:`photo_texture` makes the texture an atlas [photo | smooth photo] and
  gives every face corner a UV.  A face the photo shows reads the photo at
  its corners' projections: from the photo's viewpoint the mesh is the photo,
  up to the outline.  Every other face reads the smooth copy
  (:func:`smooth_photo`: a Gaussian blur of the photo's pixels inside the
  object mask shrunk by :data:`SOURCE_MARGIN_PX`, normalised by the blurred
  mask, so neither the backdrop nor the outline's blend with it takes part),
  at UVs filled from the seen vertices by a **harmonic fill** over the mesh
  (:func:`harmonic_fill`; a filled UV outside the shrunk mask, as a concave
  outline gives, moves to the nearest pixel inside).  The hidden side so
  shows the photo's object, mirrored through the outline and spread over
  the back without seams, but blurred: its colours change smoothly from one
  vertex to the next instead of repeating the photo's detail.

A seen vertex on the boundary has two UVs: its projection into the photo on
the faces the photo shows, into the smooth copy on the others.  OBJ keeps UVs
per face corner (``f v/vt``); glTF splits such a vertex in two; PLY has one
colour per vertex, the texture at each vertex's own UV (:class:`PhotoTexture`).

Before (issue 42), hidden vertices read the sharp photo at the harmonic UVs:
the back showed the photo's detail, and the colour jump between hidden
neighbours rose on busy photos; faces at the outline with a hidden corner
smeared the photo across the front (the bus's front error 9.64/255).  Before
that (each hidden vertex took the UV of the nearest seen vertex in 3D),
78–91 % of the hidden vertices read the outline's blend with the backdrop.
The figures are in docs/lab/hidden-colour.md (``scripts/hidden_colour.py``).

UVs follow the glTF/OBJ convention used by Blender: ``u`` left → right,
``v`` bottom → top of the texture image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..config import CameraConfig
from ..frame import view_to_pixels

__all__ = ["MAX_TEXTURE_SIDE", "SOURCE_MARGIN_PX", "SMOOTH_SIGMA_PX", "FRONT_RASTER_SCALES", "PhotoTexture", "project",
           "zbuffer", "zbuffer_reference", "front_faces", "mesh_edges", "harmonic_fill", "shrink_mask", "fill_outside_mask",
           "smooth_photo", "hidden_edge_jumps", "photo_texture", "sample_bilinear"]

# The texture is the photo's crop at its own resolution, capped at this many pixels a side.
MAX_TEXTURE_SIDE = 2048
# Only the object mask shrunk by this many pixels (at the network's image size) colours the hidden side: the outline's
# pixels blend the object with the backdrop.
SOURCE_MARGIN_PX = 2
# The smooth copy of the photo the hidden side reads: a Gaussian of this many pixels at the network's image size.
SMOOTH_SIGMA_PX = 4.0
# The rasters (times the network's image size) at whose pixel centres a face the photo shows must be the nearest.
FRONT_RASTER_SCALES = (1, 2, 4, 8)


def project(vertices: np.ndarray, camera: CameraConfig, size: int) -> tuple[np.ndarray, np.ndarray]:
    """View-frame points (V, 3) → (pixel coordinates (V, 2) float64 (u along columns, v along rows), planar depth (V,))."""
    uv, depth = view_to_pixels(torch.as_tensor(np.asarray(vertices, np.float64)), camera, size)
    return uv.numpy(), depth.numpy()


def _raster(vertices: np.ndarray, faces: np.ndarray, camera: CameraConfig, size: int, max_face_px: int):
    """Yield, per offset in the faces' pixel boxes, ``(face indices, flat pixel indices, planar depths)`` of the
    pixel centres (``size`` × ``size`` image) that faces (F, 3) cover; see :func:`zbuffer`."""
    uv, depth = project(vertices, camera, size)
    f = np.asarray(faces, np.int64)
    if len(f) == 0:
        return
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
        tall = np.flatnonzero(ok & (h > dy))  # (only the faces whose box reaches this offset: the work follows their area)
        for dx in range(int(w.max())):
            i = tall[w[tall] > dx]
            px, py = x0[i] + dx, y0[i] + dy
            qx, qy = px + 0.5, py + 0.5
            l0 = ((by[i] - cy[i]) * (qx - cx[i]) + (cx[i] - bx[i]) * (qy - cy[i])) / den[i]
            l1 = ((cy[i] - ay[i]) * (qx - cx[i]) + (ax[i] - cx[i]) * (qy - cy[i])) / den[i]
            l2 = 1.0 - l0 - l1
            sel = (px >= 0) & (px < size) & (py >= 0) & (py < size) & (l0 >= -1e-9) & (l1 >= -1e-9) & (l2 >= -1e-9)
            if not sel.any():
                continue
            # planar depth is affine in the view frame but not in the image: interpolate 1/depth
            j = i[sel]
            inv = l0[sel] / d[j, 0] + l1[sel] / d[j, 1] + l2[sel] / d[j, 2]
            yield j, py[sel] * size + px[sel], 1.0 / inv


def zbuffer(vertices: np.ndarray, faces: np.ndarray, camera: CameraConfig, size: int, max_face_px: int = 16) -> np.ndarray:
    """Nearest planar depth (size, size) of the mesh at each pixel centre; ``inf`` where no face covers it.

    vertices (V, 3) view frame, faces (F, 3) int.  Faces are rasterised with
    barycentric tests over their pixel bounding boxes, all faces at once per
    offset in the box; a face wider than ``max_face_px`` pixels is tested only
    on its first ``max_face_px``² pixels (marching-cubes faces are ~1–2 px).
    """
    zb = np.full(size * size, np.inf)
    for _, pixel, depth in _raster(np.asarray(vertices, np.float64), faces, camera, size, max_face_px):
        np.minimum.at(zb, pixel, depth)
    return zb.reshape(size, size)


def front_faces(vertices: np.ndarray, faces: np.ndarray, camera: CameraConfig, mask: np.ndarray,
                scales: tuple[int, ...] = FRONT_RASTER_SCALES) -> np.ndarray:
    """(F,) bool: the faces the photo shows, those nearest the camera at a pixel centre inside ``mask``.

    ``mask`` (S, S) bool, the object mask at the network's image size; the
    faces are rasterised (:func:`zbuffer`) at S times each of ``scales`` (the
    mask scaled by nearest pixel), and a face counts when it is the nearest at
    any pixel centre of any of them: a face of a pixel or less, seen edge-on
    at the outline, holds a pixel centre of one raster but not another's.
    """
    m = np.asarray(mask, bool)
    v = np.asarray(vertices, np.float64)
    shown = np.zeros(len(faces), bool)
    for scale in scales:
        side = m.shape[0] * scale
        inside = _upsample_mask(m, side).ravel()
        hits = list(_raster(v, faces, camera, side, 16 * scale))
        if not hits:
            continue
        face, pixel, depth = (np.concatenate(a) for a in zip(*hits))
        zb = np.full(side * side, np.inf)
        np.minimum.at(zb, pixel, depth)
        shown[face[(depth <= zb[pixel]) & inside[pixel]]] = True
    return shown


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


def hidden_edge_jumps(texture: PhotoTexture, faces: np.ndarray) -> np.ndarray:
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

    ``image``: (T, 2T, 3) uint8, an atlas of two squares: on the left the
    square of the photo the camera saw (the reconstruction's ``crop_box``) at
    up to :data:`MAX_TEXTURE_SIDE` pixels, its pixels outside the object mask
    filled from inside it; on the right the same square smoothed
    (:func:`smooth_photo`), for the hidden side.
    ``face_uv``: (F, 3, 2) float32 texture coordinates of each face's corners
    into ``image`` (v up): a face the photo shows (:func:`front_faces`) has its
    corners' projections into the photo, any other face UVs into the smooth
    square.  ``uv``: (V, 2) float32, each vertex's own UV: its projection into
    the photo when ``seen`` (a corner of a face the photo shows), else its UV
    into the smooth square; a seen vertex's corners on hidden faces read the
    smooth square at its projection (:meth:`corners`).
    """

    image: np.ndarray
    uv: np.ndarray
    seen: np.ndarray
    face_uv: np.ndarray

    @property
    def photo(self) -> np.ndarray:
        """(T, T, 3) uint8: the photo's square of ``image`` (its left half)."""
        return self.image[:, : self.image.shape[0]]

    def vertex_colours(self) -> np.ndarray:
        """(V, 4) uint8 RGBA: the texture sampled at each vertex's UV (for formats without textures)."""
        rgb = sample_bilinear(self.image, self.uv.astype(np.float64))
        return np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], axis=1)

    def corners(self, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The corner UVs as a list of distinct (vertex, UV) pairs: ``(uv (N, 2) float32, vertex (N,) int64,
        face_uv_index (F, 3) int64)``; the first V entries are the vertices' own ``uv`` (entry i belongs to vertex
        i), the rest the seen vertices' second UVs.  An OBJ writes them as ``vt`` lines; a glTF file, which has one
        UV per vertex, splits each vertex with two."""
        f = np.asarray(faces, np.int64)
        n = len(self.uv)
        index = f.copy()
        other = np.any(self.face_uv != self.uv[f], axis=-1)
        if not other.any():
            return self.uv, np.arange(n), index
        keys = np.column_stack([f[other].astype(np.float64), self.face_uv[other].astype(np.float64)])
        extra, inverse = np.unique(keys, axis=0, return_inverse=True)
        index[other] = n + inverse.ravel()
        uv = np.concatenate([self.uv, extra[:, 1:].astype(np.float32)])
        return uv, np.concatenate([np.arange(n), extra[:, 0].astype(np.int64)]), index


def smooth_photo(image: np.ndarray, source: np.ndarray, sigma_px: float) -> np.ndarray:
    """(T, T, 3) uint8: ``image`` (T, T, 3) uint8 blurred with only the pixels of ``source`` (S, S) bool (scaled to
    T by nearest pixel) taking part: blur(image·m) / blur(m), a Gaussian of ``sigma_px`` texture pixels; a pixel
    with no ``source`` pixel within reach takes the nearest one's value."""
    from scipy.ndimage import distance_transform_edt, gaussian_filter

    m = _upsample_mask(np.asarray(source, bool), image.shape[0])
    if not m.any():
        return image.copy()
    w = m.astype(np.float64)
    den = gaussian_filter(w, sigma_px, mode="nearest")
    out = np.stack([gaussian_filter(image[..., k] * w, sigma_px, mode="nearest") for k in range(3)], axis=-1)
    reach = den > 1e-6
    out = np.clip(np.rint(out / np.where(reach, den, 1.0)[..., None]), 0, 255).astype(np.uint8)
    if not reach.all():
        _, (rows, cols) = distance_transform_edt(~reach, return_indices=True)
        out = out[rows, cols]
    return out


def _snap_inside(uv: np.ndarray, sel: np.ndarray, shrunk: np.ndarray) -> None:
    """Move the UVs (V, 2) (into a square, v up) of ``sel`` (V,) bool that land outside ``shrunk`` (S, S) bool
    to its nearest pixel centre, in place."""
    from scipy.ndimage import distance_transform_edt

    size = shrunk.shape[0]
    _, (near_rows, near_cols) = distance_transform_edt(~shrunk, return_indices=True)
    c = np.clip(np.floor(uv[:, 0] * size).astype(np.int64), 0, size - 1)
    r = np.clip(np.floor((1.0 - uv[:, 1]) * size).astype(np.int64), 0, size - 1)
    off = sel & ~shrunk[r, c]
    uv[off, 0] = (near_cols[r[off], c[off]] + 0.5) / size
    uv[off, 1] = 1.0 - (near_rows[r[off], c[off]] + 0.5) / size


def _to_atlas(uv: np.ndarray, half: int, side: int) -> np.ndarray:
    """UVs (N, 2) into a square → into the atlas's left (``half`` 0) or right (1) square of ``side`` pixels,
    ``u`` kept between the square's outer pixel centres (bilinear sampling never reads the other square)."""
    u = np.clip(uv[:, 0], 0.5 / side, 1.0 - 0.5 / side)
    return np.stack([(half + u) / 2.0, uv[:, 1]], axis=1)


def photo_texture(vertices: np.ndarray, faces: np.ndarray, camera: CameraConfig, mask: np.ndarray, image: np.ndarray) -> PhotoTexture:
    """Every face's corner UVs into an atlas of ``image`` (T, T, 3) uint8, the photo's crop seen by ``camera``,
    and its smoothed copy; see the module docstring.

    vertices (V, 3) view frame, faces (F, 3), mask (S, S) bool: the object
    mask at the network's image size (shrunk here by :data:`SOURCE_MARGIN_PX`
    (:func:`shrink_mask`) for what colours the hidden side; pixels beyond the
    image's border count as inside).  The atlas's photo is ``image`` with the
    pixels outside ``mask`` filled from inside the shrunk mask
    (:func:`fill_outside_mask`), its smooth copy :func:`smooth_photo` of the
    shrunk mask's pixels (:data:`SMOOTH_SIGMA_PX`).
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"image: expected (T, T, 3) uint8, got {img.shape} {img.dtype}")
    m = np.asarray(mask, bool)
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    size, side = m.shape[0], img.shape[0]
    shown = front_faces(v, f, camera, m)
    seen = np.zeros(len(v), bool)
    seen[f[shown].ravel()] = True
    shrunk = shrink_mask(m, SOURCE_MARGIN_PX)
    pix, _ = project(v, camera, size)
    own = np.stack([pix[:, 0] / size, 1.0 - pix[:, 1] / size], axis=1)
    col = np.clip(np.floor(pix[:, 0]).astype(np.int64), 0, size - 1)
    row = np.clip(np.floor(pix[:, 1]).astype(np.int64), 0, size - 1)
    source = seen & shrunk[row, col]
    if not source.any():  # a mask too thin to shrink (or nothing seen): every seen vertex lends its UV
        source = seen
    hidden_uv = harmonic_fill(own, source, f, v)
    hidden_uv[seen] = own[seen]
    if shrunk.any():
        _snap_inside(hidden_uv, ~seen, shrunk)  # a filled UV outside the shrunk mask (a concave outline)
        photo = fill_outside_mask(img, m, shrunk)
    else:
        photo = img
    smooth = smooth_photo(img, shrunk if shrunk.any() else m, SMOOTH_SIGMA_PX * side / size)
    left, right = _to_atlas(own, 0, side), _to_atlas(hidden_uv, 1, side)
    face_uv = np.where(shown[:, None, None], left[f], right[f])
    uv = np.where(seen[:, None], left, right)
    return PhotoTexture(np.concatenate([photo, smooth], axis=1), uv.astype(np.float32), seen, face_uv.astype(np.float32))
