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
import os
from typing import Any

from .protocol import OPTION_KINDS, Option

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
VALUE_KINDS = OPTION_KINDS


def rows(event: Any) -> list[dict[str, Any]]:
    """The schema entries of a ``ready``/``version`` event (a :mod:`.protocol` event, or its dict) that get a row:
    well-formed (:meth:`.protocol.Option.from_entry`), not the add-on's."""
    entries = event.get("options") if isinstance(event, dict) else getattr(event, "options", None)
    if not isinstance(entries, list):
        return []
    return [e for e in entries if Option.from_entry(e) is not None and e["name"] not in ADDON_OWNED]


def check_value(entry: dict[str, Any], value: Any) -> str | None:
    """Why ``value`` is outside the option's kind or range (one line, naming the row's label), else None: the
    backend's own check (:meth:`.protocol.Option.accepts`), worded for the panel."""
    option = Option.from_entry(entry)
    if option is None or option.accepts(value):
        return None
    if option.kind == "bool":
        return f"{option.label}: expected on or off"
    if option.kind == "choice":
        return f"{option.label}: expected one of {', '.join(option.choices)}"
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    what = "an integer" if option.kind == "int" else "a number"
    return f"{option.label}: expected {what} in {option.span()}" + (f", got {value:g}" if number else "")


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
