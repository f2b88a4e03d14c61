"""Reader for AC3D ``.ac`` files and TORCS ``.acc`` files.

AC3D is a line-oriented text format::

    AC3Db
    MATERIAL "name" rgb r g b amb ... emis ... spec ... shi s trans t
    OBJECT world
    kids 1
    OBJECT poly
    name "body"
    rot  r0 r1 r2 r3 r4 r5 r6 r7 r8     (optional, 3x3)
    loc  x y z                          (optional)
    numvert n
    x y z [nx ny nz]                    (n lines; .acc files add normals)
    numsurf m
    SURF 0xFF                           (flags: low nibble = surface type)
    mat k
    refs r
    index u v [u2 v2 ...]               (r lines)
    kids 0

Surface types (low nibble of the ``SURF`` flags): 0 polygon, 1 closed line,
2 open line, 4 triangle strip (TORCS ``.acc`` only).  Polygons become
triangles (fans for triangles/quads, ear clipping for larger polygons);
strips are unrolled with alternating winding; lines have no area and are
skipped.

Transforms: every object has a rotation ``M`` (the nine numbers of ``rot``
read row by row) and a translation ``loc``, both relative to its parent.
A vertex ``v`` (row vector) of an object moves to ``v @ M + loc`` in its
parent's frame, and so on up the tree.  This row-vector reading is the one
of the OpenSceneGraph/plib loaders used by FlightGear, TORCS and crrcsim; in
the real packages ``rot`` is almost always the identity, so the convention
only matters for the few files that use it.

The coordinates are returned exactly as stored (AC3D is Y-up by convention;
the source modules convert to the project's Z-up frame).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from .source_bytes import source_bytes

__all__ = ["AC3DPart", "read_ac3d", "read_ac3d_parts", "merge_parts", "triangulate_polygon"]

_TOKEN = re.compile(r'"[^"]*"|\S+')
_RGB = re.compile(r"\brgb\s+(\S+)\s+(\S+)\s+(\S+)")
_TRANS = re.compile(r"\btrans\s+(\S+)")
_DEFAULT_RGBA = np.array([200, 200, 200, 255], dtype=np.uint8)


@dataclass
class AC3DPart:
    """One ``OBJECT`` of an AC3D file with geometry, in the file's root frame.

    Attributes:
        name: the object's ``name`` (``""`` when it has none).
        path: names of the object's ancestors and itself, root first.
        vertices: ``(n, 3) float64`` positions after all parent transforms.
        faces: ``(m, 3) int64`` triangles indexing ``vertices``.
        face_rgba: ``(m, 4) uint8`` colour of each triangle's material.
        texture: the object's texture file name, or ``None``.
    """

    name: str
    path: tuple[str, ...]
    vertices: np.ndarray
    faces: np.ndarray
    face_rgba: np.ndarray
    texture: str | None = None


@dataclass
class _Cursor:
    lines: list[str]
    source: str
    pos: int = 0
    materials: list[np.ndarray] = field(default_factory=list)

    def next_tokens(self) -> list[str]:
        """Tokens of the next non-blank line; ValueError at end of file."""
        while self.pos < len(self.lines):
            line = self.lines[self.pos]
            self.pos += 1
            tokens = _TOKEN.findall(line)
            if tokens:
                return tokens
        raise ValueError(f"{self.source}: unexpected end of file")

    def at_end(self) -> bool:
        """True when only blank lines remain."""
        while self.pos < len(self.lines) and not self.lines[self.pos].strip():
            self.pos += 1
        return self.pos >= len(self.lines)

    def fail(self, message: str) -> ValueError:
        return ValueError(f"{self.source}, line {self.pos}: {message}")


def _floats(cursor: _Cursor, tokens: list[str], count: int) -> np.ndarray:
    if len(tokens) < count:
        raise cursor.fail(f"expected {count} numbers, got {len(tokens)}")
    try:
        return np.array([float(t) for t in tokens[:count]], dtype=np.float64)
    except ValueError as exc:
        raise cursor.fail(f"not a number in {tokens[:count]}") from exc


def _int(cursor: _Cursor, token: str) -> int:
    try:
        value = int(token, 0) if token.lower().startswith("0x") else int(token)
    except ValueError as exc:
        raise cursor.fail(f"not an integer: {token!r}") from exc
    if value < 0:
        raise cursor.fail(f"negative count {value}")
    return value


def triangulate_polygon(points: np.ndarray) -> np.ndarray:
    """Triangulate one simple planar-ish polygon.

    Args:
        points: ``(n, 3) float`` corner positions in order, ``n >= 3``.

    Returns:
        ``(n - 2, 3) int64`` corner indices (into ``points``) of triangles
        with the polygon's winding.  Triangles and quads are fanned; larger
        polygons are ear-clipped in the plane of their Newell normal, falling
        back to a fan if the polygon is self-intersecting.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 3:
        raise ValueError(f"points must be (n>=3, 3), got {points.shape}")
    n = len(points)
    fan = np.array([[0, k, k + 1] for k in range(1, n - 1)], dtype=np.int64)
    if n <= 4:
        return fan
    # Newell normal, then project onto the two axes most orthogonal to it.
    nxt = np.roll(points, -1, axis=0)
    normal = np.array([
        np.sum((points[:, 1] - nxt[:, 1]) * (points[:, 2] + nxt[:, 2])),
        np.sum((points[:, 2] - nxt[:, 2]) * (points[:, 0] + nxt[:, 0])),
        np.sum((points[:, 0] - nxt[:, 0]) * (points[:, 1] + nxt[:, 1])),
    ])
    if not np.any(normal):
        return fan
    drop = int(np.argmax(np.abs(normal)))
    keep = [a for a in range(3) if a != drop]
    p2 = points[:, keep]
    if normal[drop] < 0:  # keep the projected polygon counter-clockwise
        p2 = p2[:, ::-1]
    remaining = list(range(n))
    triangles: list[tuple[int, int, int]] = []

    def cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
        return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))

    while len(remaining) > 3:
        m = len(remaining)
        for k in range(m):
            ia, ib, ic = remaining[k - 1], remaining[k], remaining[(k + 1) % m]
            a, b, c = p2[ia], p2[ib], p2[ic]
            if cross(a, b, c) <= 0.0:
                continue  # reflex or degenerate corner
            inside = False
            for j in remaining:
                if j in (ia, ib, ic):
                    continue
                q = p2[j]
                if cross(a, b, q) >= 0 and cross(b, c, q) >= 0 and cross(c, a, q) >= 0:
                    inside = True
                    break
            if not inside:
                triangles.append((ia, ib, ic))
                remaining.pop(k)
                break
        else:
            return fan  # no ear found: self-intersecting outline
    triangles.append((remaining[0], remaining[1], remaining[2]))
    return np.array(triangles, dtype=np.int64)


def _strip_triangles(refs: list[int]) -> list[tuple[int, int, int]]:
    out = []
    for k in range(len(refs) - 2):
        a, b, c = refs[k], refs[k + 1], refs[k + 2]
        if a == b or b == c or a == c:
            continue
        out.append((a, b, c) if k % 2 == 0 else (b, a, c))
    return out


def _parse_material(cursor: _Cursor, line: str) -> np.ndarray:
    rgb = _RGB.search(line)
    if rgb is None:
        return _DEFAULT_RGBA.copy()
    values = [float(v) for v in rgb.groups()]
    trans = _TRANS.search(line)
    alpha = 1.0 - float(trans.group(1)) if trans else 1.0
    rgba = np.clip(np.array(values + [alpha]), 0.0, 1.0)
    return np.round(rgba * 255).astype(np.uint8)


def _parse_surface(cursor: _Cursor, vertices: np.ndarray, triangles: list[tuple[int, int, int]],
                   tri_material: list[int]) -> None:
    """One ``SURF`` block of an object whose (V, 3) ``vertices`` are read: its triangles (vertex indices) and
    their material index appended to ``triangles`` and ``tri_material``; lines add nothing."""
    surf = cursor.next_tokens()
    if surf[0] != "SURF" or len(surf) < 2:
        raise cursor.fail(f"expected SURF, got {surf[0]!r}")
    kind = _int(cursor, surf[1]) & 0x0F
    material = 0
    while True:
        t = cursor.next_tokens()
        if t[0] == "mat":
            material = _int(cursor, t[1])
        elif t[0] == "refs":
            break
        else:
            raise cursor.fail(f"unexpected {t[0]!r} in SURF block")
    refs = [_int(cursor, cursor.next_tokens()[0]) for _ in range(_int(cursor, t[1]))]
    if refs and max(refs) >= len(vertices):
        raise cursor.fail(f"surface refers to vertex {max(refs)}, object has {len(vertices)}")
    if kind == 0:
        # drop repeated consecutive corners before triangulating
        clean = [r for k, r in enumerate(refs) if r != refs[k - 1]] if len(refs) > 1 else refs
        if len(clean) >= 3:
            local = triangulate_polygon(vertices[clean])
            new = [(clean[a], clean[b], clean[c]) for a, b, c in local]
            triangles.extend(new)
            tri_material.extend([material] * len(new))
    elif kind == 4:
        new = _strip_triangles(refs)
        triangles.extend(new)
        tri_material.extend([material] * len(new))
    # kinds 1 and 2 are lines: no surface


def _parse_object(
    cursor: _Cursor,
    first: list[str],
    parent_matrix: np.ndarray,
    parent_path: tuple[str, ...],
    skip_object: Callable[[str], bool] | None,
    skipped: bool,
    parts: list[AC3DPart],
) -> None:
    if first[0] != "OBJECT":
        raise cursor.fail(f"expected OBJECT, got {first[0]!r}")
    name = ""
    rotation = np.eye(3)
    location = np.zeros(3)
    texture: str | None = None
    vertices = np.zeros((0, 3))
    triangles: list[tuple[int, int, int]] = []
    tri_material: list[int] = []
    while True:
        tokens = cursor.next_tokens()
        key = tokens[0]
        if key == "name":
            name = " ".join(tokens[1:]).strip('"')
        elif key == "data":
            remaining = _int(cursor, tokens[1]) if len(tokens) > 1 else 0
            while remaining > 0 and cursor.pos < len(cursor.lines):
                remaining -= len(cursor.lines[cursor.pos]) + 1
                cursor.pos += 1
        elif key == "texture" and texture is None and len(tokens) > 1:
            texture = tokens[1].strip('"')
        elif key == "rot":
            rotation = _floats(cursor, tokens[1:], 9).reshape(3, 3)
        elif key == "loc":
            location = _floats(cursor, tokens[1:], 3)
        elif key == "numvert":
            count = _int(cursor, tokens[1])
            vertices = np.empty((count, 3))
            for i in range(count):
                vertices[i] = _floats(cursor, cursor.next_tokens(), 3)
        elif key == "numsurf":
            for _ in range(_int(cursor, tokens[1])):
                _parse_surface(cursor, vertices, triangles, tri_material)
        elif key == "kids":
            kids = _int(cursor, tokens[1])
            local = np.eye(4)
            local[:3, :3] = rotation.T  # row-vector v @ M  ==  column-vector M.T @ v
            local[:3, 3] = location
            matrix = parent_matrix @ local
            path = parent_path + (name,)
            # only objects with geometry of their own are dropped by name: pure
            # group nodes (e.g. the "dad_GROUND" roots of VRML exports) are not
            hide = skipped or (
                skip_object is not None and bool(name) and bool(triangles) and skip_object(name)
            )
            if triangles and not hide:
                faces = np.asarray(triangles, dtype=np.int64)
                world = vertices @ matrix[:3, :3].T + matrix[:3, 3]
                palette = cursor.materials
                rgba = np.array(
                    [palette[m] if m < len(palette) else _DEFAULT_RGBA for m in tri_material], dtype=np.uint8
                )
                parts.append(AC3DPart(name, path, world, faces, rgba, texture))
            for _ in range(kids):
                if cursor.at_end():
                    break  # a few real files declare more kids than they hold; the viewers accept that
                _parse_object(cursor, cursor.next_tokens(), matrix, path, skip_object, hide, parts)
            return
        # everything else (texrep, texoff, crease, url, subdiv, hidden, locked, folded) is irrelevant here


def read_ac3d_parts(
    source: str | Path | bytes, *, skip_object: Callable[[str], bool] | None = None
) -> list[AC3DPart]:
    """Parse an AC3D/``.acc`` file into its parts (objects with triangles).

    Args:
        source: a file path, or the file's bytes.
        skip_object: optional predicate on an object's name; an object with
            surfaces of its own for which it returns True is dropped together
            with all its children.  Group objects without surfaces are never
            dropped by name (exporters name whole-model roots "GROUND").

    Returns:
        The parts in file order, vertices in the file's root frame.

    Raises:
        ValueError: not an AC3D file, or a malformed/truncated one.
    """
    raw, label = source_bytes(source)
    text = raw.decode("latin-1")
    lines = text.splitlines()
    if not lines or not lines[0].startswith("AC3D"):
        raise ValueError(f"{label}: not an AC3D file (no 'AC3D' header)")
    cursor = _Cursor(lines, label, pos=1)
    parts: list[AC3DPart] = []
    while cursor.pos < len(lines):
        line = lines[cursor.pos]
        tokens = _TOKEN.findall(line)
        if not tokens:
            cursor.pos += 1
            continue
        if tokens[0] == "MATERIAL":
            cursor.materials.append(_parse_material(cursor, line))
            cursor.pos += 1
        elif tokens[0] == "OBJECT":
            cursor.pos += 1
            _parse_object(cursor, tokens, np.eye(4), (), skip_object, False, parts)
        else:
            raise cursor.fail(f"unexpected {tokens[0]!r} at top level")
    return parts


def read_ac3d(
    source: str | Path | bytes, *, skip_object: Callable[[str], bool] | None = None
) -> trimesh.Trimesh:
    """Read an AC3D ``.ac``/``.acc`` file as one merged mesh.

    Args:
        source: a file path, or the file's bytes.
        skip_object: see :func:`read_ac3d_parts`.

    Returns:
        A :class:`trimesh.Trimesh` (not processed: vertices are exactly the
        file's, per part, after transforms) with ``(m, 4) uint8`` face colours
        from the materials; ``metadata["parts"]`` lists the part names.

    Raises:
        ValueError: unreadable input, or a file with no triangles at all.
    """
    parts = read_ac3d_parts(source, skip_object=skip_object)
    if not parts:
        raise ValueError(f"{source if not isinstance(source, (bytes, bytearray)) else '<bytes>'}: no polygons")
    return merge_parts(parts)


def merge_parts(parts: list[AC3DPart]) -> trimesh.Trimesh:
    """Concatenate parts into one unprocessed mesh with face colours (see :func:`read_ac3d`)."""
    if not parts:
        raise ValueError("no parts to merge")
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts])
    vertices = np.concatenate([p.vertices for p in parts])
    faces = np.concatenate([p.faces + o for p, o in zip(parts, offsets)])
    colours = np.concatenate([p.face_rgba for p in parts])
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, face_colors=colours, process=False)
    mesh.metadata["parts"] = [p.name for p in parts]
    return mesh
