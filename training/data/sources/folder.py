"""Any folder of meshes: ``<root>/<class>/<...>/<model>.<ext>``.

The class is the name of the first sub-folder (lower-cased; ``armchair`` and
``stool`` are folded into ``chair`` by the corpus class rules like every other
name).  Files directly in ``root`` get no class hint and are classified by
their file name.  Readable formats: whatever trimesh loads (OBJ, PLY, STL,
OFF, glTF/GLB) plus AC3D (``.ac``/``.acc``) and 3DS through the project's
readers.  The folder's up and front axes are parameters (default: already
canonical, +Z up, front −Y).  The licence is unknown (``unknown``) unless a
``LICENCE``/``LICENSE`` file's first line says otherwise.
"""

from __future__ import annotations

from pathlib import Path

import trimesh

from ..readers import read_3ds, read_ac3d
from . import ShapeRecord, rotation_from_axes, scene_parts, slug

__all__ = ["PACKAGES", "MESH_SUFFIXES", "enumerate_shapes", "load_mesh_file"]

PACKAGES: tuple[str, ...] = ()
MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf", ".ac", ".acc", ".3ds")


def load_mesh_file(path: Path) -> list[trimesh.Trimesh]:
    """Load one mesh file of any supported format as parts in file coordinates."""
    suffix = path.suffix.lower()
    if suffix in (".ac", ".acc"):
        return [read_ac3d(path)]
    if suffix == ".3ds":
        return [read_3ds(path)]
    if suffix not in MESH_SUFFIXES:
        raise ValueError(f"{path}: unsupported mesh format {suffix!r}")
    try:
        loaded = trimesh.load(str(path), force="scene")
    except Exception as exc:  # trimesh raises many types on bad files
        raise ValueError(f"{path}: {type(exc).__name__}: {exc}") from exc
    return scene_parts(loaded)


def _licence(root: Path) -> str:
    for name in ("LICENCE", "LICENSE", "LICENCE.txt", "LICENSE.txt"):
        f = root / name
        if f.is_file():
            first = f.read_text(encoding="utf-8", errors="replace").strip().splitlines()
            if first:
                return first[0].strip()[:60]
    return "unknown"


def enumerate_shapes(root: Path, *, up: str = "+z", front: str = "-y") -> list[ShapeRecord]:
    """Every mesh file below ``root``.

    Args:
        root: the folder.
        up, front: the files' up and front axes (signed axis names).
    """
    root = Path(root)
    if not root.is_dir():
        raise ValueError(f"mesh folder {root} does not exist")
    rotation = rotation_from_axes(up, front)
    licence = _licence(root)
    records = []
    for path in sorted(p for p in root.rglob("*") if p.is_file() and p.suffix.lower() in MESH_SUFFIXES):
        rel = path.relative_to(root)
        hint = rel.parts[0].lower() if len(rel.parts) > 1 else None
        records.append(
            ShapeRecord(
                shape_id=f"folder-{slug(root.name)}-{slug(str(rel.with_suffix('')))}",
                source="folder",
                package=None,
                path=str(path),
                name=path.stem,
                creator="",
                licence=licence,
                category=str(rel.parent) if len(rel.parts) > 1 else "",
                class_hint=hint,
                rotation=rotation,
                load=lambda p=path: load_mesh_file(p),
            )
        )
    return records
