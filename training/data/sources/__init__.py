"""Shape sources: one module per origin of 3D models.

Every source module exposes ``PACKAGES`` (the Debian packages it needs; empty
for user folders) and ``enumerate_shapes(root) -> list[ShapeRecord]`` where
``root`` is the folder the packages were unpacked into (``root / PKG`` holds
the tree of package ``PKG``).  A :class:`ShapeRecord` says where a model is,
what it is called, who made it, under which licence, and how to rotate it
into the project's canonical frame; its ``load`` callable returns the model's
parts in the *source's own* coordinates.  The corpus builder
(:mod:`training.data.corpus`) does the rest (rotation, centring, scaling,
classification, filtering, splitting).

Canonical frame (see :mod:`genre_backend.frame`): right-handed, +Z up, the
object's front faces −Y.  The constant rotations below convert the common
source conventions; each source module says which it uses and how it was
checked on the real files.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import trimesh

__all__ = [
    "ShapeRecord",
    "Y_UP_FRONT_POS_Z",
    "Z_UP_FRONT_NEG_Y",
    "slug",
    "rotation_to_list",
    "scene_parts",
    "rotation_from_axes",
]

# (x, y, z) -> (x, -z, y): Y-up models whose front faces +Z (Sweet Home 3D,
# crrcsim).  A +90 degree rotation about X.
Y_UP_FRONT_POS_Z = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
# Already canonical.
Z_UP_FRONT_NEG_Y = np.eye(3)


@dataclass
class ShapeRecord:
    """One model found in a source, not yet loaded.

    Attributes:
        shape_id: stable unique id, ``"<source>-<slug>"`` (file-name safe).
        source: source module name (``"sweethome3d"``, ``"flightgear"``, ...).
        package: Debian package holding it, or ``None`` for user folders.
        path: original location; for a member of an archive,
            ``"<archive path>!<member path>"``.
        name: human-readable name (catalogue name or file stem).
        creator: author for attribution (``""`` when unknown).
        licence: short licence id (``"CC0"``, ``"CC-BY-3.0"``, ``"GPL-2+"``...).
        category: the source's own grouping (catalogue category, folder).
        class_hint: class decided by the source itself (e.g. every FlightGear
            AI aircraft is an ``"airplane"``), or ``None`` to classify by name.
        rotation: ``(3, 3) float`` rotation from the source's coordinates to
            the canonical frame (includes any per-model rotation).
        load: returns the model's parts, ``list[trimesh.Trimesh]``, in source
            coordinates; raises ``ValueError``/``OSError`` on bad input.
        align_long_axis: if True, after ``rotation`` the longer horizontal
            extent is turned onto the Y axis (for sources whose heading is
            not consistent between models, e.g. FlightGear ships).
        family: near-duplicate group key; shapes of one source with equal
            family are variants of one design (see ``training.data.corpus``).
        extra: source-specific facts kept in the manifest (e.g. Sweet Home
            3D's catalogue size ``(width, depth, height)`` in cm).
    """

    shape_id: str
    source: str
    package: str | None
    path: str
    name: str
    creator: str
    licence: str
    category: str
    class_hint: str | None
    rotation: np.ndarray
    load: Callable[[], list[trimesh.Trimesh]] = field(repr=False)
    align_long_axis: bool = False
    family: str = ""
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        r = np.asarray(self.rotation, dtype=np.float64)
        if r.shape != (3, 3):
            raise ValueError(f"{self.shape_id}: rotation must be (3, 3), got {r.shape}")
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-3) or np.linalg.det(r) < 0:
            raise ValueError(f"{self.shape_id}: rotation is not a proper rotation: {r.tolist()}")
        self.rotation = r
        if not self.family:
            self.family = self.shape_id


def slug(text: str) -> str:
    """Lower-case file-name-safe form of ``text`` (``[a-z0-9_.-]``, no leading dot)."""
    out = re.sub(r"[^a-z0-9_.-]+", "_", text.lower()).strip("_.")
    return out or "unnamed"


def rotation_to_list(r: np.ndarray) -> list[list[float]]:
    """``(3, 3)`` rotation as nested lists rounded to 9 decimals (for JSON)."""
    return [[round(float(v), 9) for v in row] for row in np.asarray(r)]


def scene_parts(loaded: trimesh.Trimesh | trimesh.Scene) -> list[trimesh.Trimesh]:
    """Flatten what :func:`trimesh.load` returned into meshes in world coordinates.

    Scene graph transforms are applied; non-mesh geometry (paths, points) is
    dropped.  Materials and UVs stay attached to each part.
    """
    if isinstance(loaded, trimesh.Trimesh):
        return [loaded]
    if isinstance(loaded, trimesh.Scene):
        return [g for g in loaded.dump(concatenate=False) if isinstance(g, trimesh.Trimesh)]
    raise ValueError(f"not a mesh: {type(loaded).__name__}")


_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def rotation_from_axes(up: str, front: str) -> np.ndarray:
    """Rotation taking a source's ``up`` axis to +Z and its ``front`` axis to −Y.

    Args:
        up, front: signed axis names such as ``"y"``, ``"+z"``, ``"-x"``;
            they must be perpendicular.

    Returns:
        ``(3, 3) float`` proper rotation ``R`` (apply as ``R @ v``).
    """

    def axis(name: str) -> np.ndarray:
        text = name.strip().lower()
        sign = -1.0 if text.startswith("-") else 1.0
        key = text.lstrip("+-")
        if key not in _AXES:
            raise ValueError(f"axis must be one of x, y, z with an optional sign, got {name!r}")
        return sign * np.array(_AXES[key])

    u, f = axis(up), axis(front)
    if abs(float(u @ f)) > 1e-9:
        raise ValueError(f"up {up!r} and front {front!r} must be perpendicular")
    row_z = u
    row_y = -f
    row_x = np.cross(row_y, row_z)
    return np.stack([row_x, row_y, row_z])
