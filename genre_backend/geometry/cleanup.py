"""Clean marching-cubes meshes: parts, cavities, floaters, watertightness.

Marching cubes of a padded probability grid (:func:`.mesh_voxels.voxels_to_mesh`)
gives closed surfaces, oriented outward, but often several of them: small
floaters around the object, and *cavity* surfaces — the inner wall of a hollow
region, a closed surface whose normals point into the hole, so its signed
volume is negative.  An artist wants one clean piece:

* :func:`mesh_parts` labels the connected parts (faces sharing vertices);
* :func:`part_measures` gives each part's area and signed volume;
* :func:`clean_mesh` drops cavity surfaces (never visible from outside) and,
  unless asked to keep everything, parts whose area is below a fraction of the
  largest part's;
* :func:`is_watertight` checks that every edge is shared by exactly two faces
  that traverse it in opposite directions (closed and consistently oriented).

trimesh's ``split``, ``volume``, ``is_watertight`` and
``is_winding_consistent`` are the references the tests hold these to.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["DEFAULT_KEEP_FRACTION", "CleanReport", "mesh_parts", "part_measures", "is_watertight", "clean_mesh"]

# Parts whose area is below this fraction of the largest part's are dropped by default.
# (Floaters of the voxel refiner are a few voxels; a separated chair leg is ~8 % of its chair.)
DEFAULT_KEEP_FRACTION = 0.05


def _check(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices: expected shape (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces: expected shape (F, 3), got {f.shape}")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"faces: indices must lie in [0, {len(v)}), got [{f.min()}, {f.max()}]")
    return v.astype(np.float64, copy=False), f.astype(np.int64, copy=False)


def mesh_parts(faces: np.ndarray, n_vertices: int) -> tuple[int, np.ndarray]:
    """Connected parts of a triangle mesh.

    faces: (F, 3) int; n_vertices: V.  Two faces are in one part when they
    share a vertex.  Returns ``(count, labels)`` with labels (F,) int64 in
    ``[0, count)``; vertices used by no face belong to no part.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, np.int64)
    if len(f) == 0:
        return 0, np.zeros(0, np.int64)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(n_vertices, n_vertices))
    _, vertex_label = connected_components(graph, directed=False)
    # renumber the labels of vertices that are in faces to 0..count-1
    used, face_label = np.unique(vertex_label[f[:, 0]], return_inverse=True)
    return len(used), face_label.astype(np.int64)


def part_measures(vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(area (count,), signed volume (count,)) of each labelled part.

    The signed volume (divergence theorem, ``det(v0, v1, v2) / 6`` summed over
    faces) is positive for a closed part whose normals point outward, negative
    for one whose normals point inward (a cavity's wall).
    """
    v, f = _check(vertices, faces)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cross = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    return np.bincount(labels, area, minlength=count), np.bincount(labels, volume, minlength=count)


def is_watertight(faces: np.ndarray) -> bool:
    """True when every edge is used by exactly two faces, once in each direction (closed, consistently wound)."""
    f = np.asarray(faces, np.int64)
    if len(f) == 0:
        return False
    directed = np.stack([f, np.roll(f, -1, axis=1)], axis=-1).reshape(-1, 2)
    if len(np.unique(directed, axis=0)) != len(directed):
        return False  # an edge traversed twice in the same direction: inconsistent winding or non-manifold
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected, axis=0, return_counts=True)
    return bool((counts == 2).all())


@dataclass
class CleanReport:
    """What :func:`clean_mesh` did: parts before and after, cavities and floaters dropped, watertightness after."""

    parts_before: int
    parts: int
    cavities_dropped: int
    small_dropped: int
    watertight: bool


def clean_mesh(vertices: np.ndarray, faces: np.ndarray, keep_fraction: float = DEFAULT_KEEP_FRACTION) -> tuple[np.ndarray, np.ndarray, CleanReport]:
    """Drop cavity walls and small parts of a mesh; renumber the vertices.

    vertices (V, 3) float, faces (F, 3) int.  A part with negative signed
    volume (a closed surface facing inward: the wall of a hollow inside
    another part) is always dropped.  Of the others, parts whose area is below
    ``keep_fraction`` × the largest part's area are dropped; ``keep_fraction``
    0 keeps them all.  Returns ``(vertices (V', 3) float32, faces (F', 3)
    int64, CleanReport)``.
    """
    if not 0.0 <= keep_fraction <= 1.0:
        raise ValueError(f"keep_fraction: expected a value in [0, 1], got {keep_fraction}")
    v, f = _check(vertices, faces)
    count, labels = mesh_parts(f, len(v))
    if count == 0:
        return v.astype(np.float32), f, CleanReport(0, 0, 0, 0, False)
    area, volume = part_measures(v, f, labels, count)
    outward = volume > 0
    if not outward.any():  # nothing faces outward (a mesh from elsewhere, wound inward): keep it as it is
        outward[:] = True
    keep = outward & (area >= keep_fraction * area[outward].max())
    kept_faces = f[keep[labels]]
    used = np.unique(kept_faces)
    remap = np.full(len(v), -1, np.int64)
    remap[used] = np.arange(len(used))
    new_faces = remap[kept_faces]
    report = CleanReport(
        parts_before=count,
        parts=int(keep.sum()),
        cavities_dropped=int((~outward).sum()),
        small_dropped=int((outward & ~keep).sum()),
        watertight=is_watertight(new_faces),
    )
    return v[used].astype(np.float32), new_faces, report
