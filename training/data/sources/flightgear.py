"""FlightGear: AI aircraft (``flightgear-data-ai``) and ships, a few aircraft
and vehicles (``flightgear-data-models``), all AC3D ``.ac`` files, GPL-2+.

Which files are shapes (rules, applied in this order):

* AI aircraft (``AI/Aircraft/<type>/``): every ``.ac`` below the type's folder
  is a candidate unless its folder is a ``lights``/``light``/``refueling``
  folder, its file name says it is an accessory (:data:`ACCESSORY_FILE`:
  lights, flares, drop tanks, wheels, exhausts, banners, refuelling probes,
  booms and drogues, shuttle engine pods, pilots, tow ropes) or it is smaller
  than :data:`MIN_MAIN_BYTES`.  Of the remaining candidates the *largest file*
  is the type's main model (a type folder holds one aircraft, sometimes in
  several liveries or sub-variants, which are near-duplicates anyway).  The
  ``balloon`` type holds hot-air balloons, not airplanes: kept, class
  ``balloon`` (unassigned); the ``Ferry`` type is a ferry boat (vessel, the
  same file as ``Models/Maritime/Civilian/FerryBoat1.ac``, so one is kept).
* Models (``Models/``): ``Maritime/Civilian`` and ``Maritime/Military``
  (also one folder deeper) are vessels; ``Maritime/Misc`` (buoys, piers,
  rafts), ``Aircraft``, ``Military`` and ``Transport`` are kept; ``Aircraft`` files are
  airplanes except the ``H-60`` and ``dauphin`` helicopters (unassigned), the
  others are classified by name (a Humvee pickup is a car, trains and a bus
  stay unassigned).  Other folders (buildings, airport furniture, scenery)
  are not enumerated.
* Inside every file, objects whose name matches :data:`JUNK_OBJECT` are
  dropped with their children: shadows, light cones/flares/halos, transparent
  propeller discs, refuelling drogues and hoses, and the flat ``Wake`` planes
  several ships carry (they made ContainerShip 872 m long instead of 240 m);
  in vessels also parts of at most 8 triangles with no height
  (:func:`is_water_plane`: the ``rect`` wake planes of CG47 and LPD17, which
  doubled their length).  Objects named ``GROUND`` that merely group a whole
  model are not dropped (see :func:`training.data.readers.ac3d.read_ac3d_parts`).

Frame, checked on the real files: AC3D is Y-up and FlightGear models point
their nose/bow to −X (FlightGear's body frame has X aft).  Over
A320/744/f16/Spitfire, the highest 15% of the vertices (the fin) lie at
+0.4…+1.0 of the half-length along +X, i.e. aft.  So ``(x, y, z) ->
(z, x, y)`` puts the nose at −Y and the fin up (+Z).  Ship models are not
consistent about which horizontal axis is the hull's (``LargeFerry`` is
88 m along Z, 19 m along X), so vessels also get ``align_long_axis``.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..readers.ac3d import AC3DPart, merge_parts, read_ac3d_parts
from . import ShapeRecord, slug

__all__ = ["PACKAGES", "enumerate_shapes", "JUNK_OBJECT", "ACCESSORY_FILE", "FLIGHTGEAR_TO_CANONICAL"]

PACKAGES = ("flightgear-data-ai", "flightgear-data-models")
LICENCE = "GPL-2+"

_FG = "usr/share/games/flightgear"
MIN_MAIN_BYTES = 20_000

# (x aft, y up, z) -> canonical (x right, y aft so the nose is at -Y, z up)
FLIGHTGEAR_TO_CANONICAL = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])

JUNK_OBJECT = re.compile(
    r"shadow|light|flare|flame|glow|halo|cone-texture|propdisc|prop_?blur|drogue|hose|smoke|contrail"
    r"|^wake|ground|^sea$|water",
    re.IGNORECASE,
)
ACCESSORY_FILE = re.compile(
    r"light|flash|flare|strobe|beacon|^nav|toggle|taxi|cone|tank|wheel|exhaust|banner|probe|refuel"
    r"|boom|drogue|ssme|omspod|pilot|rope|lights",
    re.IGNORECASE,
)
_AI_NON_AIRPLANES = {"balloon": "balloon", "ferry": "vessel"}
_HELICOPTER = re.compile(r"^h-60|dauphin|heli", re.IGNORECASE)
_ACCESSORY_DIRS = {"lights", "light", "refueling"}


def _skip_object(name: str) -> bool:
    return bool(JUNK_OBJECT.search(name))


def is_water_plane(part: AC3DPart) -> bool:
    """A part with at most 8 triangles and no height (a wake or sea plane, "rect" in CG47/LPD17)."""
    extent = np.ptp(part.vertices, axis=0)
    return len(part.faces) <= 8 and extent[1] <= 1e-3 * max(extent[0], extent[2], 1e-12)


def _load(path: Path, vessel: bool = False):
    parts = read_ac3d_parts(path, skip_object=_skip_object)
    if vessel:
        parts = [p for p in parts if not is_water_plane(p)]
    if not parts:
        raise ValueError(f"{path}: no polygons left after removing junk objects")
    return [merge_parts(parts)]


def main_model(type_dir: Path) -> Path | None:
    """The main ``.ac`` of one AI aircraft folder, or None (rules in the module docstring)."""
    candidates = []
    for path in sorted(type_dir.rglob("*.ac")):
        rel_dirs = {p.lower() for p in path.relative_to(type_dir).parts[:-1]}
        if rel_dirs & _ACCESSORY_DIRS or ACCESSORY_FILE.search(path.stem):
            continue
        size = path.stat().st_size
        if size < MIN_MAIN_BYTES:
            continue
        candidates.append((size, str(path), path))
    if not candidates:
        return None
    return max(candidates)[2]


def _record(path: Path, package: str, name: str, category: str, class_hint: str | None, family: str,
            align: bool = False) -> ShapeRecord:
    return ShapeRecord(
        shape_id=f"fg-{slug(family)}",
        source="flightgear",
        package=package,
        path=str(path),
        name=name,
        creator="FlightGear contributors",
        licence=LICENCE,
        category=category,
        class_hint=class_hint,
        rotation=FLIGHTGEAR_TO_CANONICAL,
        load=lambda p=path, v=class_hint == "vessel": _load(p, v),
        align_long_axis=align,
        family=family,
    )


def enumerate_shapes(root: Path) -> list[ShapeRecord]:
    """AI aircraft and selected models under ``root/<package>/``; missing packages are skipped."""
    root = Path(root)
    records: list[ShapeRecord] = []
    ai = root / "flightgear-data-ai" / _FG / "AI" / "Aircraft"
    if ai.is_dir():
        for type_dir in sorted(p for p in ai.iterdir() if p.is_dir()):
            main = main_model(type_dir)
            if main is None:
                continue
            hint = _AI_NON_AIRPLANES.get(type_dir.name.lower(), "airplane")
            family = f"ai-{type_dir.name}" if hint != "vessel" else "ship-" + re.sub(r"[^a-z0-9]", "", main.stem.lower())
            records.append(
                _record(main, "flightgear-data-ai", type_dir.name, "AI/Aircraft", hint, family, align=hint == "vessel")
            )
    models = root / "flightgear-data-models" / _FG / "Models"
    if models.is_dir():
        for sub in ("Maritime/Civilian", "Maritime/Military"):
            for path in sorted((models / sub).rglob("*.ac")):
                if ACCESSORY_FILE.search(path.stem):
                    continue
                family = "ship-" + re.sub(r"[^a-z0-9]", "", path.stem.lower())
                rel = path.relative_to(models)
                records.append(
                    _record(path, "flightgear-data-models", path.stem, str(rel.parent), "vessel", family, align=True)
                )
        for sub in ("Maritime/Misc", "Aircraft", "Military", "Transport"):
            for path in sorted((models / sub).glob("*.ac")):
                if ACCESSORY_FILE.search(path.stem) or path.stat().st_size < 5_000:
                    continue
                rel = path.relative_to(models)
                hint = None
                if sub == "Aircraft":
                    hint = "helicopter" if _HELICOPTER.search(path.stem) else "airplane"
                records.append(
                    _record(path, "flightgear-data-models", path.stem, str(rel.parent), hint,
                            "model-" + slug(str(rel.with_suffix(""))))
                )
    # two ship files of one design (CG-57 and CG-57-high-detail) share a family:
    # keep the smaller file (the high-detail one is 13 MB of the same hull)
    by_family: dict[str, ShapeRecord] = {}
    for r in records:
        old = by_family.get(r.family)
        if old is None or Path(r.path).stat().st_size < Path(old.path).stat().st_size:
            by_family[r.family] = r
    return sorted(by_family.values(), key=lambda r: r.shape_id)
