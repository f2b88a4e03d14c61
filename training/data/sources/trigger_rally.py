"""Trigger Rally cars (``trigger-rally-data``, GPL-2+): ``vehicles/<car>/<car>.obj``
inside ``data.zip``.

Nine vehicle folders: three bodies (Cordo, Evo, Fox) in three racing classes
(kitcar, super500, wrc).  Several classes reuse one body geometry with a
different texture; the corpus's near-duplicate rule collapses those.  The
wheels are separate ``*_wheel.obj`` files and are not included.

Frame, checked on the real files: Z-up, length along Y; the steering wheels
in ``fox_wrc.vehicle`` (``steer="0.85"``) sit at y = +1.24 and the driven
rear ones at y = −0.99, so the front is +Y.  ``(x, y, z) -> (−x, −y, z)``
(180 degrees about Z) puts the front at −Y.
"""

from __future__ import annotations

import re
import zipfile
from pathlib import Path

import numpy as np

from . import ShapeRecord, slug
from .sweethome3d import load_obj_from_zip

__all__ = ["PACKAGES", "enumerate_shapes", "TRIGGER_TO_CANONICAL"]

PACKAGES = ("trigger-rally-data",)
TRIGGER_TO_CANONICAL = np.diag([-1.0, -1.0, 1.0])
_ZIP = "usr/share/games/trigger-rally/data.zip"
_NAME = re.compile(r'\bname\s*=\s*"([^"]+)"')


def enumerate_shapes(root: Path) -> list[ShapeRecord]:
    """One record per ``vehicles/<car>/<car>.obj`` in the game's ``data.zip``."""
    archive = Path(root) / "trigger-rally-data" / _ZIP
    if not archive.is_file():
        return []
    with zipfile.ZipFile(archive) as zf:
        names = set(zf.namelist())
        records = []
        for member in sorted(names):
            m = re.fullmatch(r"vehicles/([^/]+)/\1\.obj", member)
            if not m:
                continue
            car = m.group(1)
            vehicle_file = f"vehicles/{car}/{car}.vehicle"
            display = car
            if vehicle_file in names:
                found = _NAME.search(zf.read(vehicle_file).decode("latin-1"))
                if found:
                    display = f"{found.group(1)} ({car})"
            records.append(
                ShapeRecord(
                    shape_id=f"trigger-{slug(car)}",
                    source="trigger_rally",
                    package="trigger-rally-data",
                    path=f"{archive}!{member}",
                    name=display,
                    creator="Trigger Rally contributors",
                    licence="GPL-2+",
                    category="car body (wheels not included)",
                    class_hint="car",
                    rotation=TRIGGER_TO_CANONICAL,
                    load=lambda a=archive, mem=member: load_obj_from_zip(a, mem),
                    family=f"trigger-{car.split('_')[0]}",
                )
            )
    return records
