"""Reader for 0 A.D.'s compiled meshes, ``.pmd`` (``0ad-data``, CC-BY-SA-3.0).

A PMD file is little-endian binary: the magic ``PSMD``, ``uint32 version``
(1–4) and ``uint32 data_size`` (the file's length less these 12 bytes), then

* ``uint32 n_vertices``; from version 4, ``uint32 n_uv`` (UV pairs per vertex;
  1 before version 4);
* ``n_vertices`` vertices of ``float32 position[3], normal[3], uv[n_uv][2]``,
  then the skinning blend ``uint8 bones[4], float32 weights[4]``;
* ``uint32 n_faces`` triangles of ``uint16 corners[3]``;
* ``uint32 n_bones`` rest states of ``float32 translation[3], rotation[4]``;
* from version 2, prop points (where other meshes attach), not read here.

Positions are stored in the rest pose, in the game's frame (Y up). A mesh
with bones is a skinned part of a unit (a body, a horse); its rest pose is a
usable shape but the source module decides whether to take it.

The layout was checked on the 4,010 ``.pmd`` files of Debian's ``0ad-data``
0.0.26 (all of version 4; 279 with bones): every one reads with every face index inside
its vertex list and its declared size matching its length.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import trimesh

from .source_bytes import source_bytes

__all__ = ["read_pmd"]

_MAGIC = b"PSMD"
_HEADER = 12  # magic, version, data_size
_BLEND_BYTES = 4 + 16  # uint8 bones[4], float32 weights[4]


def read_pmd(source: str | Path | bytes) -> trimesh.Trimesh:
    """Read a ``.pmd`` file as one mesh.

    Args:
        source: a file path, or the file's bytes (as read from ``public.zip``).

    Returns:
        A :class:`trimesh.Trimesh` (unprocessed) in the file's own coordinates,
        with the first UV set in ``metadata["uv"]`` (``(n, 2) float32``, one
        per vertex), ``metadata["bones"]`` the number of bones (0: a rigid
        mesh) and ``metadata["pmd_version"]``.

    Raises:
        ValueError: not a PMD file, an unknown version, a truncated or
            inconsistent one, a face index outside the vertices, non-finite
            positions, or no triangles.
    """
    data, label = source_bytes(source)
    if len(data) < _HEADER + 4 or data[:4] != _MAGIC:
        raise ValueError(f"{label}: not a PMD file (no PSMD magic)")
    version, size = struct.unpack_from("<II", data, 4)
    if not 1 <= version <= 4:
        raise ValueError(f"{label}: PMD version {version} is not one of 1-4")
    if size != len(data) - _HEADER:
        raise ValueError(f"{label}: declares {size} bytes of data but holds {len(data) - _HEADER}")

    def take(offset: int, nbytes: int, what: str) -> int:
        if offset + nbytes > len(data):
            raise ValueError(f"{label}: truncated in the {what} (byte {offset} + {nbytes} > {len(data)})")
        return offset + nbytes

    n_vertices, = struct.unpack_from("<I", data, _HEADER)
    offset = _HEADER + 4
    n_uv = 1
    if version >= 4:
        take(offset, 4, "UV count")
        n_uv, = struct.unpack_from("<I", data, offset)
        offset += 4
        if n_uv > 16:
            raise ValueError(f"{label}: {n_uv} UV sets per vertex (at most 16 expected)")
    stride = 24 + 8 * n_uv + _BLEND_BYTES
    end = take(offset, n_vertices * stride, "vertices")
    rows = np.frombuffer(data, np.uint8, n_vertices * stride, offset).reshape(n_vertices, stride)
    positions = rows[:, :12].copy().view("<f4").reshape(n_vertices, 3)
    uv = rows[:, 24:32].copy().view("<f4").reshape(n_vertices, 2) if n_uv else np.zeros((n_vertices, 2), np.float32)
    offset = take(end, 4, "face count")
    n_faces, = struct.unpack_from("<I", data, end)
    end = take(offset, 6 * n_faces, "faces")
    faces = np.frombuffer(data, "<u2", 3 * n_faces, offset).reshape(n_faces, 3).astype(np.int64)
    take(end, 4, "bone count")
    n_bones, = struct.unpack_from("<I", data, end)
    take(end + 4, 28 * n_bones, "bones")

    if n_faces == 0:
        raise ValueError(f"{label}: no triangles")
    if faces.max() >= n_vertices:
        raise ValueError(f"{label}: a face uses vertex {int(faces.max())} of {n_vertices}")
    if not np.isfinite(positions).all():
        raise ValueError(f"{label}: non-finite vertex positions")
    mesh = trimesh.Trimesh(positions.astype(np.float64), faces, process=False)
    mesh.metadata.update({"uv": uv.astype(np.float32), "bones": int(n_bones), "pmd_version": int(version)})
    return mesh
