"""The backend's mesh options as the add-on shows them, without ``bpy``.

``genre serve``'s ``ready`` (and ``version``) event carries ``"options"``: one
entry per mesh option of the backend's record (``genre_backend/inference/options.py``),
``{name, type, min, max, min_open, max_open, choices, default, label, help, weights}``
with ``default`` the loaded weights' value, and ``"qualities"``: the named
sets behind the Quality choice (``docs/protocol.md``).  The Advanced panel
has one row per entry (:func:`rows`), except the options the add-on sets
itself (:data:`ADDON_OWNED`); a new backend option appears there without a
change here.
"""

from __future__ import annotations

import json
import math
import os
from typing import Any

__all__ = ["ADDON_OWNED", "QUALITIES", "rows", "check_value", "shown", "VALUE_KINDS", "cached"]

# the schema of the shipped default weights, kept beside this file (``python build_addon.py --schema`` writes it; the
# build refuses a stale one): the Advanced rows exist before the backend has started
CACHE_FILE = "options_schema.json"

# set by the add-on itself: the file it reads back (OBJ, +y up) and Colour from Photo on the main panel
ADDON_OWNED = ("format", "up", "texture")
# the Quality choice (identifier, label, description, the backend's name); the option values are the backend's (its
# "qualities"), sent by name
QUALITIES = (
    ("FAST", "Fast", "One pass through the networks (no mirror average): about half the time", "fast"),
    ("BEST", "Best", "The model's own settings, chosen on evaluation views", "best"),
)
VALUE_KINDS = ("float", "int", "bool", "choice")


def rows(event: dict[str, Any] | None) -> list[dict[str, Any]]:
    """The schema entries of a ``ready``/``version`` event that get a row: well-formed, of a known kind, not the add-on's."""
    entries = (event or {}).get("options")
    if not isinstance(entries, list):
        return []
    out = []
    for e in entries:
        if not (isinstance(e, dict) and isinstance(e.get("name"), str) and e.get("type") in VALUE_KINDS):
            continue
        if e["name"] in ADDON_OWNED:
            continue
        if e["type"] in ("float", "int") and not all(isinstance(e.get(k), (int, float)) and not isinstance(e.get(k), bool)
                                                     for k in ("min", "max")):
            continue
        if e["type"] == "choice" and not (isinstance(e.get("choices"), list) and e["choices"]):
            continue
        out.append(e)
    return out


def check_value(entry: dict[str, Any], value: Any) -> str | None:
    """Why ``value`` is outside the option's kind or range (one line, naming the row's label), else None."""
    kind, label = entry.get("type"), entry.get("label") or entry.get("name")
    if kind == "bool":
        return None if isinstance(value, bool) else f"{label}: expected on or off"
    if kind == "choice":
        return None if value in (entry.get("choices") or ()) else f"{label}: expected one of {', '.join(entry.get('choices') or ())}"
    lo, hi = entry["min"], entry["max"]
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (lo < value if entry.get("min_open") else lo <= value) and (value < hi if entry.get("max_open") else value <= hi)
    if ok:
        return None
    span = f"{'(' if entry.get('min_open') else '['}{lo:g}, {hi:g}{')' if entry.get('max_open') else ']'}"
    return f"{label}: expected a{'n integer' if kind == 'int' else ' number'} in {span}, got {value:g}" if isinstance(value, (int, float)) \
        else f"{label}: expected a number in {span}"


def shown(entry: dict[str, Any], value: Any) -> str:
    """A value as a row shows it: ``0.45``, ``4``, ``On``/``Off``, a choice's name; ``?`` when unknown."""
    if value is None:
        return "?"
    if entry.get("type") == "bool":
        return "On" if value else "Off"
    if entry.get("type") == "float":
        return f"{value:.3g}"
    return str(value)


def dumps(value: Any) -> str:
    """The schema's default as kept in a row's string property (JSON)."""
    return json.dumps(value)


def cached(folder: str = os.path.dirname(os.path.abspath(__file__))) -> dict[str, Any] | None:
    """The schema kept with the add-on (:data:`CACHE_FILE`), shaped like a ``ready`` event; None when unreadable."""
    try:
        with open(os.path.join(folder, CACHE_FILE), encoding="utf-8") as fh:
            event = json.load(fh)
    except (OSError, ValueError):
        return None
    return event if isinstance(event, dict) and rows(event) else None
