"""Colour from the photo: which vertices the photo sees, their UVs into it, and colour for the rest.

The mesh is posed in the view frame of :mod:`genre_backend.frame`, so the
camera that took the (framed) photo is known exactly: a vertex's texture
coordinate is its own projection into the square crop the networks saw.

* :func:`zbuffer` rasterises the mesh's planar depth at the network's image
  size (:func:`zbuffer_reference` is the slow per-face loop beside it);
* :func:`seen_vertices` keeps the vertices that face the camera, are not
  hidden behind other faces, and land inside the object mask;
* :func:`photo_texture` gives every vertex a UV: its projection when seen,
  else the UV of the nearest seen vertex (in 3D) — so the back and the sides
  take the colour of the closest surface the photo shows, never black, and
  never a streak smeared across a face seen edge-on.

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

__all__ = ["MAX_TEXTURE_SIDE", "PhotoTexture", "project", "zbuffer", "zbuffer_reference", "seen_vertices", "photo_texture", "sample_bilinear"]

# The texture is the photo's crop at its own resolution, capped at this many pixels a side.
MAX_TEXTURE_SIDE = 2048


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


@dataclass
class PhotoTexture:
    """A mesh's colour from its photo.

    ``image``: (T, T, 3) uint8, the square of the photo the camera saw (the
    reconstruction's ``crop_box``) at up to :data:`MAX_TEXTURE_SIDE` pixels.
    ``uv``: (V, 2) float32 texture coordinates into ``image`` (v up).
    ``seen``: (V,) bool, the vertices whose UV is their own projection; the
    others carry the UV of the nearest seen vertex.
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

    vertices (V, 3) view frame, faces (F, 3), mask (S, S) bool at the
    network's image size, ``tolerance``: the z-buffer tolerance of
    :func:`seen_vertices` (about a voxel and a half).
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"image: expected (T, T, 3) uint8, got {img.shape} {img.dtype}")
    v = np.asarray(vertices, np.float64)
    size = np.asarray(mask).shape[0]
    seen = seen_vertices(v, faces, camera, mask, tolerance)
    pix, _ = project(v, camera, size)
    uv = np.stack([pix[:, 0] / size, 1.0 - pix[:, 1] / size], axis=1)
    if seen.any() and not seen.all():
        from scipy.spatial import cKDTree

        idx = np.flatnonzero(seen)
        _, nearest = cKDTree(v[idx]).query(v[~seen])
        uv[~seen] = uv[idx[nearest]]
    return PhotoTexture(img, uv.astype(np.float32), seen)
