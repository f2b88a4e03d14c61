"""Reader for Autodesk 3D Studio ``.3ds`` files (binary chunks).

A 3DS file is a tree of chunks; each chunk is ``uint16 id, uint32 length``
(little-endian, the length counting the 6-byte header) followed by data and
sub-chunks.  The chunks used here:

==========  =========================================================
``0x4D4D``  main chunk
``0x3D3D``  editor (mesh data)
``0x4000``  named object: zero-terminated name, then sub-chunks
``0x4100``  triangle mesh
``0x4110``  vertex list: ``uint16 n`` then ``n x 3 float32``
``0x4120``  face list: ``uint16 m`` then ``m x (3 uint16 corners, uint16 flags)``,
            then sub-chunk ``0x4130`` (material name + the faces using it)
``0x4160``  the object's local axes and origin (``4 x 3 float32``)
``0xAFFF``  material: ``0xA000`` name, ``0xA020`` diffuse colour
            (``0x0010`` float RGB or ``0x0011`` byte RGB)
==========  =========================================================

The vertex list of a 3DS mesh is stored *already in world coordinates*: the
``0x4160`` matrix only records the frame the modeller used, and the
keyframer section (``0xB000``) holds animation pivots.  Applying ``0x4160``
would therefore move parts twice; the reader keeps vertices as stored.  (The
gl-117 models were checked this way: their parts assemble with no transform.)
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from .source_bytes import source_bytes

__all__ = ["read_3ds"]

_MAIN, _EDITOR, _OBJECT, _TRIMESH = 0x4D4D, 0x3D3D, 0x4000, 0x4100
_VERTICES, _FACES, _FACE_MATERIAL = 0x4110, 0x4120, 0x4130
_MATERIAL, _MAT_NAME, _MAT_DIFFUSE = 0xAFFF, 0xA000, 0xA020
_COLOR_F, _COLOR_B, _COLOR_B_GAMMA, _COLOR_F_GAMMA = 0x0010, 0x0011, 0x0012, 0x0013
_DEFAULT_RGBA = (200, 200, 200, 255)


@dataclass
class _Mesh:
    name: str
    vertices: np.ndarray  # (n, 3) float64
    faces: np.ndarray  # (m, 3) int64
    face_material: list[str | None]


def _chunks(data: bytes, start: int, end: int, label: str):
    """Yield ``(id, data_start, chunk_end)`` for the chunks in ``data[start:end]``."""
    pos = start
    while pos + 6 <= end:
        cid, length = struct.unpack_from("<HI", data, pos)
        if length < 6 or pos + length > end:
            raise ValueError(f"{label}: chunk 0x{cid:04X} at byte {pos} has bad length {length}")
        yield cid, pos + 6, pos + length
        pos += length


def _cstring(data: bytes, pos: int, end: int) -> tuple[str, int]:
    stop = data.find(b"\0", pos, end)
    if stop < 0:
        raise ValueError(f"unterminated name at byte {pos}")
    return data[pos:stop].decode("latin-1"), stop + 1


def _read_trimesh(data: bytes, start: int, end: int, name: str, label: str) -> _Mesh:
    vertices = np.zeros((0, 3))
    faces = np.zeros((0, 3), dtype=np.int64)
    face_material: list[str | None] = []
    for cid, s, e in _chunks(data, start, end, label):
        if cid == _VERTICES:
            (n,) = struct.unpack_from("<H", data, s)
            if s + 2 + 12 * n > e:
                raise ValueError(f"{label}: vertex list of {name!r} is truncated")
            vertices = np.frombuffer(data, dtype="<f4", count=3 * n, offset=s + 2).reshape(n, 3).astype(np.float64)
        elif cid == _FACES:
            (m,) = struct.unpack_from("<H", data, s)
            if s + 2 + 8 * m > e:
                raise ValueError(f"{label}: face list of {name!r} is truncated")
            raw = np.frombuffer(data, dtype="<u2", count=4 * m, offset=s + 2).reshape(m, 4)
            faces = raw[:, :3].astype(np.int64)
            face_material = [None] * m
            for sid, ss, se in _chunks(data, s + 2 + 8 * m, e, label):
                if sid == _FACE_MATERIAL:
                    mat_name, p = _cstring(data, ss, se)
                    (k,) = struct.unpack_from("<H", data, p)
                    ids = np.frombuffer(data, dtype="<u2", count=k, offset=p + 2)
                    for f in ids:
                        if f < m:
                            face_material[int(f)] = mat_name
    if len(faces) and (faces.max() >= len(vertices)):
        raise ValueError(f"{label}: object {name!r} refers to vertex {faces.max()} of {len(vertices)}")
    return _Mesh(name, vertices, faces, face_material)


def _read_colour(data: bytes, start: int, end: int, label: str) -> tuple[int, int, int, int] | None:
    for cid, s, _e in _chunks(data, start, end, label):
        if cid in (_COLOR_B, _COLOR_B_GAMMA):
            r, g, b = data[s : s + 3]
            return (r, g, b, 255)
        if cid in (_COLOR_F, _COLOR_F_GAMMA):
            rgb = np.clip(np.array(struct.unpack_from("<3f", data, s)), 0, 1)
            r, g, b = (int(round(v * 255)) for v in rgb)
            return (r, g, b, 255)
    return None


def read_3ds(source: str | Path | bytes) -> trimesh.Trimesh:
    """Read a ``.3ds`` file as one merged mesh.

    Args:
        source: a file path, or the file's bytes.

    Returns:
        A :class:`trimesh.Trimesh` (unprocessed) of all triangle-mesh objects,
        ``(m, 4) uint8`` face colours from the materials' diffuse colours;
        ``metadata["parts"]`` lists the object names.

    Raises:
        ValueError: not a 3DS file, a truncated/malformed one, or no triangles.
    """
    data, label = source_bytes(source)
    if len(data) < 6 or struct.unpack_from("<H", data, 0)[0] != _MAIN:
        raise ValueError(f"{label}: not a 3DS file (no 0x4D4D main chunk)")
    try:
        _cid, main_len = struct.unpack_from("<HI", data, 0)
        main_end = min(main_len, len(data))
        meshes: list[_Mesh] = []
        colours: dict[str, tuple[int, int, int, int]] = {}
        for cid, s, e in _chunks(data, 6, main_end, label):
            if cid != _EDITOR:
                continue
            for sub, ss, se in _chunks(data, s, e, label):
                if sub == _OBJECT:
                    name, p = _cstring(data, ss, se)
                    for kind, ks, ke in _chunks(data, p, se, label):
                        if kind == _TRIMESH:
                            meshes.append(_read_trimesh(data, ks, ke, name, label))
                elif sub == _MATERIAL:
                    mat_name, rgba = None, None
                    for kind, ks, ke in _chunks(data, ss, se, label):
                        if kind == _MAT_NAME:
                            mat_name, _ = _cstring(data, ks, ke)
                        elif kind == _MAT_DIFFUSE:
                            rgba = _read_colour(data, ks, ke, label)
                    if mat_name is not None and rgba is not None:
                        colours[mat_name] = rgba
    except struct.error as exc:
        raise ValueError(f"{label}: truncated 3DS data ({exc})") from exc
    meshes = [m for m in meshes if len(m.faces)]
    if not meshes:
        raise ValueError(f"{label}: no triangle meshes")
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes])
    vertices = np.concatenate([m.vertices for m in meshes])
    faces = np.concatenate([m.faces + o for m, o in zip(meshes, offsets)])
    rgba = np.array(
        [colours.get(n, _DEFAULT_RGBA) if n else _DEFAULT_RGBA for m in meshes for n in m.face_material],
        dtype=np.uint8,
    )
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, face_colors=rgba, process=False)
    mesh.metadata["parts"] = [m.name for m in meshes]
    return mesh
