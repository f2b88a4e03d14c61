"""GL-117 flight-game models (``gl-117-data``, GPL-2+): ``models/*.3ds``.

Classes come from the file names, which follow the game's own naming
(:data:`CLASS_BY_STEM`): ``gl-NN*`` are the game's jet fighters and
``transp*`` its transport aircraft (airplane), ``ship*`` are ships (vessel),
``pickup*`` pickup trucks (car).  ``gl-117.3ds`` is the game's flat title
logo, not an aircraft: it is left to the junk rules (and to ``other``).
Everything else (missiles, tanks, buildings, flares, chaff) is classified by
name, usually ``other``; flat billboards (flares, chaff, cannon muzzle
flashes) are removed by the corpus junk rules.

Frame, checked on the real files: Z-up (gl-14: 2.68 x 1.88 x 0.56 with Z the
thinnest, like every jet), fuselage along X with the nose toward −X: the
highest 15% of the vertices (the fins) sit at +0.54 (gl-14), +0.66 (gl-16),
+0.93 (gl-29) of the half-length along +X, and the pickups' cabs (their
highest part) lie toward −X.  So ``(x, y, z) -> (−y, x, z)`` puts the nose at
−Y, up stays +Z.  3DS vertices are stored in world coordinates, so parts need
no per-object transform (they assemble correctly as loaded).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..readers.threeds import read_3ds
from . import ShapeRecord, slug

__all__ = ["PACKAGES", "enumerate_shapes", "GL117_TO_CANONICAL", "CLASS_BY_STEM"]

PACKAGES = ("gl-117-data",)
GL117_TO_CANONICAL = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
_MODELS = "usr/share/games/gl-117/models"
CLASS_BY_STEM: list[tuple[re.Pattern, str | None]] = [
    (re.compile(r"^gl-117$"), None),  # the title logo
    (re.compile(r"^gl-\d+"), "airplane"),
    (re.compile(r"^transp\d"), "airplane"),
    (re.compile(r"^ship\d"), "vessel"),
    (re.compile(r"^pickup\d"), "car"),
]


def _hint(stem: str) -> str | None:
    for pattern, cls in CLASS_BY_STEM:
        if pattern.search(stem):
            return cls
    return None


def enumerate_shapes(root: Path) -> list[ShapeRecord]:
    """All ``.3ds`` files under ``root/gl-117-data``."""
    models = Path(root) / "gl-117-data" / _MODELS
    if not models.is_dir():
        return []
    return [
        ShapeRecord(
            shape_id=f"gl117-{slug(path.stem)}",
            source="gl117",
            package="gl-117-data",
            path=str(path),
            name=path.stem,
            creator="Thomas A. Drexl (GL-117)",
            licence="GPL-2+",
            category="models",
            class_hint=_hint(path.stem),
            rotation=GL117_TO_CANONICAL,
            load=lambda p=path: [read_3ds(p)],
        )
        for path in sorted(models.glob("*.3ds"))
    ]
