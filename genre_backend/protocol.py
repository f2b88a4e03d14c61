"""The messages of ``genre serve`` and the option entries they carry: standard library only.

This file is the protocol's one definition (``docs/protocol.md`` describes it):

* :class:`Option`, what one setting may hold and how it is shown: the metadata on the fields of the weights'
  ``GeometryConfig`` and of ``MeshOptions`` (``genre_backend/inference/options.py``), the entries of ``ready``'s
  ``options`` schema, and the one check of a value (:meth:`Option.accepts`);
* the requests a client sends (:data:`REQUESTS`) and the events the server writes (:data:`EVENTS`), as
  dataclasses: the server builds its lines with :func:`line`, a client reads them with :func:`read_event`.

``build_addon.py`` copies it into the Blender add-on unchanged (``blender_addon/protocol.py``; a test keeps the two
equal), so it imports nothing from the package and nothing outside the standard library.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

PROTOCOL_VERSION = 1
OPTION_KINDS = ("float", "int", "bool", "choice")


class OptionError(ValueError):
    """A setting's value outside its kind or range; ``str()`` is the one-line message."""

    def __init__(self, message: str, name: str):
        super().__init__(message)
        self.name = name


def shown(value: Any, limit: int = 300) -> str:
    """A value quoted in a message: its ``repr``, cut to ``limit`` characters."""
    try:
        text = repr(value)
    except ValueError:  # an integer past Python's 4,300-digit conversion limit
        text = "<an int of more than 4,300 digits>"
    return text if len(text) <= limit else f"{text[:limit]}… ({len(text):,} characters)"


@dataclass(frozen=True)
class Option:
    """What one setting may hold and how it is shown.

    ``kind``: ``"float"``, ``"int"``, ``"bool"`` or ``"choice"`` (one of ``choices``).  ``lo``/``hi``: the range of a
    number, open at an end where ``lo_open``/``hi_open``.  ``weights``: the ``GeometryConfig`` field that gives the
    default (the weights' own setting), else ``default`` is used.  ``distance_only``: a true or non-zero value needs
    weights of the distance target.  ``label``: a short title; ``help``: one line; ``chosen``: how the weights' value
    was chosen (stored beside it by ``training/eval/install.py``).  ``name``: the option's name (default: the field's).
    """

    kind: str
    label: str
    help: str
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple[str, ...] = ()
    weights: str | None = None
    default: Any = None
    distance_only: bool = False
    unit: str = ""
    metavar: str = "X"
    chosen: str = ""
    name: str = ""

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    def span(self) -> str:
        """A number's range as the messages write it: ``(0, 1)``, ``[0, 8]``."""
        return f"{'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"

    def expected(self) -> str:
        """What a value must be, as the error messages say it (``a number in (0, 1)``)."""
        unit = f" ({self.unit})" if self.unit else ""
        if self.kind in ("float", "int"):
            return f"{'a number' if self.kind == 'float' else 'an integer'} in {self.span()}{unit}"
        if self.kind == "bool":
            return "true or false"
        return "one of " + ", ".join(repr(c) for c in self.choices)

    def accepts(self, value: Any) -> bool:
        """Whether ``value`` is of the option's kind and in its range: the one check of a setting."""
        if self.kind == "bool":
            return isinstance(value, bool)
        if self.kind == "choice":
            return isinstance(value, str) and value in self.choices
        kind = numbers.Real if self.kind == "float" else numbers.Integral
        # compared as it is: float() of a 400-digit integer raises OverflowError
        return (not isinstance(value, bool) and isinstance(value, kind) and not (isinstance(value, float) and not math.isfinite(value))
                and (self.lo < value if self.lo_open else self.lo <= value) and (value < self.hi if self.hi_open else value <= self.hi))

    def check(self, value: Any, where: str | None = None, show: Callable[[Any], str] = shown) -> Any:
        """``value`` as the option holds it (an int made float for a float option); :class:`OptionError` otherwise.

        ``where`` names the value in the message (default: the option's name); ``show`` quotes the value.
        """
        if not self.accepts(value):
            raise OptionError(f"{where or self.name}: expected {self.expected()}, got {show(value)}", self.name)
        if self.kind in ("float", "int"):
            return float(value) if self.kind == "float" else int(value)
        return value

    def describe(self) -> dict[str, Any]:
        """The option's entry in the ``ready`` schema (without its default)."""
        return {"name": self.name, "type": self.kind, "min": self.lo, "max": self.hi, "min_open": self.lo_open,
                "max_open": self.hi_open, "choices": list(self.choices) or None, "label": self.label, "help": self.help,
                "weights": self.weights}

    @classmethod
    def from_entry(cls, entry: Any) -> Option | None:
        """The option a ``ready`` schema entry describes; None for an entry that is not well formed."""
        if not (isinstance(entry, dict) and isinstance(entry.get("name"), str) and entry.get("type") in OPTION_KINDS):
            return None
        number = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)  # noqa: E731
        if entry["type"] in ("float", "int") and not (number(entry.get("min")) and number(entry.get("max"))):
            return None
        choices = entry.get("choices")
        if entry["type"] == "choice" and not (isinstance(choices, list) and choices and all(isinstance(c, str) for c in choices)):
            return None
        return cls(kind=entry["type"], label=str(entry.get("label") or entry["name"]), help=str(entry.get("help") or ""),
                   lo=entry.get("min"), hi=entry.get("max"), lo_open=entry.get("min_open") is True,
                   hi_open=entry.get("max_open") is True, choices=tuple(choices or ()), default=entry.get("default"),
                   weights=entry.get("weights") if isinstance(entry.get("weights"), str) else None, name=entry["name"])
