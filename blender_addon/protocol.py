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

import dataclasses
import json
import math
import os
import numbers
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

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


def _omitted() -> Any:
    """A field left off the line when None."""
    return field(default=None, metadata={"omit": True})


# ---- requests (client → server) ----------------------------------------------------------------------------------------
MAX_MESSAGE = 2000  # characters of an error message (never a client's 10 MB value echoed back)


class RequestError(ValueError):
    """A request that cannot be accepted; becomes an ``error`` event with ``code``."""

    def __init__(self, code: str, message: str, req_id: Any = None):
        super().__init__(message)
        self.code, self.req_id = code, req_id


def cap(text: str, limit: int = MAX_MESSAGE) -> str:
    """``text`` cut to ``limit`` characters, saying how long it was."""
    return text if len(text) <= limit else f"{text[:limit]}… ({len(text):,} characters)"


def show_json(value: Any, limit: int = 300) -> str:
    """A client's value quoted in a message: its JSON, cut to ``limit`` characters (any value, however deep)."""
    try:
        text = json.dumps(value)
    except (ValueError, RecursionError):  # nesting near the recursion limit; an integer past the digit limit
        text = f"<a JSON {type(value).__name__}>"
    return cap(text, limit)


def path_problem(value: str) -> str | None:
    """Why no file can have the name ``value`` (None if one can): a NUL, or a lone surrogate that is no escaped byte."""
    at = value.find("\x00")
    if at >= 0:
        return f"contains a NUL character (at character {at:,})"
    try:
        os.fsencode(value)
    except UnicodeEncodeError as exc:
        return (f"contains the lone surrogate {value[exc.start]!r} (at character {exc.start:,}); a name that is not UTF-8 "
                f"is sent with one \\udc80-\\udcff escape per byte")
    return None


def request_id(msg: dict, required: bool) -> Any:
    """A request's ``id`` (a string or a finite number; None when absent and not ``required``); :class:`RequestError`."""
    if "id" not in msg:
        if required:
            raise RequestError("missing_field", "missing field 'id'")
        return None
    rid = msg["id"]
    if isinstance(rid, bool) or not isinstance(rid, (str, int, float)) or (isinstance(rid, float) and not math.isfinite(rid)):
        raise RequestError("bad_field", "field 'id' must be a string or a number")
    return rid


def path_field(msg: dict, name: str, rid: Any, required: bool, where: str = "field") -> str | None:
    """The path ``msg[name]`` (None when absent or null and not ``required``), checked; :class:`RequestError`."""
    if name not in msg or msg[name] is None:
        if required:
            raise RequestError("missing_field", f"missing {where} '{name}'", rid)
        return None
    value = msg[name]
    if not isinstance(value, str) or not value:
        raise RequestError("bad_field", f"{where} '{name}' must be a non-empty string (a path)", rid)
    problem = path_problem(value)
    if problem:
        raise RequestError("bad_field", f"{where} '{name}' is not a usable path: it {problem}", rid)
    return value


@dataclass
class Ping:
    """Answered by ``pong``."""

    type: ClassVar[str] = "ping"
    id: Any = None


@dataclass
class VersionRequest:
    """Answered by ``version``."""

    type: ClassVar[str] = "version"
    id: Any = None


@dataclass
class Reconstruct:
    """A mesh of ``image`` written to ``output``; ``options``: the mesh options by name (``docs/protocol.md``)."""

    type: ClassVar[str] = "reconstruct"
    id: Any
    image: str
    output: str
    mask: str | None = _omitted()
    box: list | None = _omitted()
    strokes: str | None = _omitted()
    guidance_frame: str | None = _omitted()
    options: dict | None = _omitted()


@dataclass
class Cancel:
    """Cancel the job ``id``."""

    type: ClassVar[str] = "cancel"
    id: Any


@dataclass
class Shutdown:
    """Cancel everything, say ``bye`` and exit."""

    type: ClassVar[str] = "shutdown"
    id: Any = None


REQUESTS: dict[str, type] = {c.type: c for c in (Ping, VersionRequest, Reconstruct, Cancel, Shutdown)}


# ---- events (server → client) ------------------------------------------------------------------------------------------
@dataclass
class Ready:
    """The first line: the server, its weights and the mesh options' schema (``options``: :meth:`Option.describe`
    entries with their ``default``; ``qualities``: the named sets)."""

    type: ClassVar[str] = "ready"
    protocol: int = PROTOCOL_VERSION
    version: str = ""
    weights: str = ""
    preset: str = ""
    device: str = ""
    threshold: float | None = None
    options: list = field(default_factory=list)
    qualities: list = field(default_factory=list)


@dataclass
class Version(Ready):
    """The answer to ``version``: ``ready``'s fields and the request's ``id``."""

    type: ClassVar[str] = "version"
    id: Any = None


@dataclass
class Pong:
    type: ClassVar[str] = "pong"
    id: Any = None


@dataclass
class Progress:
    """A stage of job ``id`` starts; ``fraction`` of the whole job (never decreasing)."""

    type: ClassVar[str] = "progress"
    id: Any = None
    stage: str = ""
    fraction: float = 0.0


@dataclass
class Result:
    """Job ``id``'s mesh.  ``settings``: the options following the weights as used, one field each on the line;
    ``options``: the whole record as used; ``camera``: the view the mesh is posed for (``docs/protocol.md``)."""

    type: ClassVar[str] = "result"
    id: Any = None
    mesh: str = ""
    format: str = ""
    up: str = "y"
    vertices: int = 0
    faces: int = 0
    parts: int = 0
    parts_dropped: int = 0
    watertight: bool = False
    files: list = field(default_factory=list)
    mask_source: str | None = None
    mask_warning: str | None = None
    primitive: str | None = None
    timings: dict = field(default_factory=dict)
    camera: dict | None = None
    options: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict, metadata={"flat": True})


@dataclass
class Error:
    """``code`` and a one-line ``message``; ``id`` null when the request had none or could not be read."""

    type: ClassVar[str] = "error"
    id: Any = None
    code: str = "error"
    message: str = ""


@dataclass
class Cancelled:
    type: ClassVar[str] = "cancelled"
    id: Any = None


@dataclass
class Bye:
    """The last line; ``reason``: the signal that stopped the server (on the line only then)."""

    type: ClassVar[str] = "bye"
    id: Any = None
    reason: str | None = _omitted()


EVENTS: dict[str, type] = {c.type: c for c in (Ready, Version, Pong, Progress, Result, Error, Cancelled, Bye)}


def message(obj: Any) -> dict[str, Any]:
    """A request or event as its JSON object: ``type`` first; a ``flat`` field's keys on the object itself; an
    omitted-when-absent field left out when None."""
    out: dict[str, Any] = {"type": obj.type}
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if f.metadata.get("flat"):
            out.update(value)
        elif not (f.metadata.get("omit") and value is None):
            out[f.name] = value
    return out


def read_event(obj: Any) -> Any:
    """The event a parsed line holds (its dataclass from :data:`EVENTS`, a field missing from the line at its default,
    a ``flat`` field gathering the keys no other field names); None for a line that is no known event."""
    cls = EVENTS.get(obj.get("type")) if isinstance(obj, dict) and isinstance(obj.get("type"), str) else None
    if cls is None:
        return None
    fields = dataclasses.fields(cls)
    named = {f.name for f in fields}
    values = {f.name: obj[f.name] for f in fields if f.name in obj and not f.metadata.get("flat")}
    for f in fields:
        if f.metadata.get("flat"):
            values[f.name] = {k: v for k, v in obj.items() if k not in named and k != "type"}
    return cls(**values)
