"""CRRCSim radio-controlled model aircraft (``crrcsim-data``, GPL-2).

Shapes: every ``objects/*.ac``.  A file is an aircraft when a flight model
in ``models/*.xml`` names it in ``<graphics ... model="X.ac">``; those are
airplanes and gliders (class ``airplane``) except the helicopters and
quadcopters (``heli``, ``copter*``, class ``helicopter``, unassigned).  The
other files (trees, a table, a trash can, huts, terrain) are scenery and are
classified by name like any other shape.

Frame, checked on the real files: Y-up with the wings along X and the
fuselage along Z (PilatusB4: 15.0 m span along X, 6.8 m length along Z,
2.0 m height along Y), nose toward +Z: the highest 15% of the vertices (the
fin) sit at −0.86 (PilatusB4), −1.13 (sport), −1.2 (zagi) of the half-length
along Z, i.e. aft.  So ``(x, y, z) -> (x, −z, y)`` (the Sweet Home 3D
rotation) puts the nose at −Y and the fin up.
"""

from __future__ import annotations

import re
from pathlib import Path

from ..readers.ac3d import read_ac3d
from . import Y_UP_FRONT_POS_Z, ShapeRecord, slug

__all__ = ["PACKAGES", "enumerate_shapes", "aircraft_files"]

PACKAGES = ("crrcsim-data",)
_BASE = "usr/share/games/crrcsim"
_GRAPHICS = re.compile(r"<graphics[^>]*\bmodel\s*=\s*\"([^\"]+\.ac)\"", re.IGNORECASE)
_ROTORCRAFT = re.compile(r"^(heli|copter)", re.IGNORECASE)
_JUNK_OBJECT = re.compile(r"shadow|ground", re.IGNORECASE)


def aircraft_files(models_dir: Path) -> set[str]:
    """File names of ``.ac`` models used by the flight models in ``models_dir``."""
    names: set[str] = set()
    for xml in sorted(Path(models_dir).glob("*.xml")):
        names.update(Path(m).name for m in _GRAPHICS.findall(xml.read_text(encoding="latin-1")))
    return names


def _load(path: Path):
    return [read_ac3d(path, skip_object=lambda name: bool(_JUNK_OBJECT.search(name)))]


def enumerate_shapes(root: Path) -> list[ShapeRecord]:
    """All ``objects/*.ac`` under ``root/crrcsim-data``."""
    base = Path(root) / "crrcsim-data" / _BASE
    objects = base / "objects"
    if not objects.is_dir():
        return []
    aircraft = aircraft_files(base / "models")
    records = []
    for path in sorted(objects.glob("*.ac")):
        if path.name in aircraft:
            hint = "helicopter" if _ROTORCRAFT.match(path.stem) else "airplane"
            category = "aircraft"
        else:
            hint, category = None, "scenery"
        records.append(
            ShapeRecord(
                shape_id=f"crrcsim-{slug(path.stem)}",
                source="crrcsim",
                package="crrcsim-data",
                path=str(path),
                name=path.stem,
                creator="CRRCSim contributors",
                licence="GPL-2",
                category=category,
                class_hint=hint,
                rotation=Y_UP_FRONT_POS_Z,
                load=lambda p=path: _load(p),
            )
        )
    return records
