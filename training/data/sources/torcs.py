"""TORCS car bodies (``torcs-data``, GPL-2+): ``cars/<car>/<car>.acc``.

Each car folder holds the full-detail body ``<car>.acc`` and lower levels of
detail ``<car>-lodN.acc``; only the full-detail file is used.  Wheels are
separate files in TORCS (drawn by the game at run time), so the shapes are
bodies without wheels: this is stated in each entry's ``category``.

Frame, checked on the real files: ``.acc`` files are AC3D, Y-up (155-DTM:
y from 0 to 1.2 m, x ±2.4 m, z ±0.95 m), and the car points to +X (its
``REAR_s_0`` part sits at x = −2.27).  So ``(x, y, z) -> (−z, −x, y)`` puts
the front at −Y and the roof up (+Z).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..readers.ac3d import read_ac3d
from . import ShapeRecord, slug

__all__ = ["PACKAGES", "enumerate_shapes", "TORCS_TO_CANONICAL"]

PACKAGES = ("torcs-data",)
TORCS_TO_CANONICAL = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
_CARS = "usr/share/games/torcs/cars"
_JUNK_OBJECT = re.compile(r"shadow|ground", re.IGNORECASE)


def car_licences(copyright_file: Path) -> dict[str, str]:
    """Per-car licences from the package's DEP-5 ``copyright`` file.

    Returns ``{car folder: licence}`` for ``Files: data/cars/models/<car>/*``
    stanzas; cars without one fall under the package's ``GPL-2+``.
    """
    out: dict[str, str] = {}
    if not copyright_file.is_file():
        return out
    cars: list[str] = []
    for line in copyright_file.read_text(encoding="utf-8", errors="replace").splitlines():
        if line.startswith("Files:"):
            cars = re.findall(r"data/cars/models/([^/\s]+)/", line)
        elif line.startswith("License:") and cars:
            for car in cars:
                out[car] = line.split(":", 1)[1].strip()
            cars = []
    return out


def _load(path: Path):
    return [read_ac3d(path, skip_object=lambda name: bool(_JUNK_OBJECT.search(name)))]


def enumerate_shapes(root: Path) -> list[ShapeRecord]:
    """One record per car folder with a ``<car>.acc`` under ``root/torcs-data``."""
    cars = Path(root) / "torcs-data" / _CARS
    records = []
    if not cars.is_dir():
        return records
    licences = car_licences(Path(root) / "torcs-data" / "usr/share/doc/torcs-data/copyright")
    for car_dir in sorted(p for p in cars.iterdir() if p.is_dir()):
        body = car_dir / f"{car_dir.name}.acc"
        if not body.is_file():
            continue
        records.append(
            ShapeRecord(
                shape_id=f"torcs-{slug(car_dir.name)}",
                source="torcs",
                package="torcs-data",
                path=str(body),
                name=car_dir.name,
                creator="TORCS contributors",
                licence=licences.get(car_dir.name, "GPL-2+"),
                category="car body (wheels not included)",
                class_hint="car",
                rotation=TORCS_TO_CANONICAL,
                load=lambda p=body: _load(p),
            )
        )
    return records
