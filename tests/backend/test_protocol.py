"""genre_backend/protocol.py: the messages of genre serve as dataclasses, their lines, and the one check of a setting."""

from __future__ import annotations

import json
import math

import pytest

from genre_backend import protocol as p
from genre_backend.config import GeometryConfig
from genre_backend.inference.options import OPTIONS, schema


def test_an_event_is_its_line_and_back():
    result = p.Result(id="j", mesh="m.obj", format="obj", faces=3, camera={"distance": 2.2}, options={"texture": False},
                      settings={"threshold": 0.45, "pit_sealing": 4})
    line = p.message(result)
    assert list(line)[0] == "type" and line["type"] == "result"
    assert line["threshold"] == 0.45 and line["pit_sealing"] == 4 and "settings" not in line  # (flat on the line)
    assert p.read_event(json.loads(json.dumps(line))) == result
    assert p.message(p.Bye(None)) == {"type": "bye", "id": None}  # reason only after a signal
    assert p.message(p.Bye(None, "SIGTERM")) == {"type": "bye", "id": None, "reason": "SIGTERM"}
    assert p.message(p.Version(id=1, protocol=1)) | {} == {**p.message(p.Ready(protocol=1)), "type": "version", "id": 1}


def test_a_client_reads_what_it_knows():
    assert p.read_event({"type": "progress", "id": 1, "stage": "depth"}) == p.Progress(1, "depth", 0.0)  # missing: default
    assert p.read_event({"type": "pong", "id": 2, "later": "field"}) == p.Pong(2)  # a field added later: ignored
    for line in ({"type": "unheard_of"}, {"type": ["x"]}, {"id": 1}, [], "ready"):
        assert p.read_event(line) is None
    assert {c.type for c in p.EVENTS.values()} == {"ready", "version", "pong", "progress", "result", "error", "cancelled", "bye"}
    assert set(p.REQUESTS) == {"ping", "version", "reconstruct", "cancel", "shutdown"}
    assert p.message(p.Reconstruct(7, "a.png", "b.obj", options={"quality": "fast"})) == {
        "type": "reconstruct", "id": 7, "image": "a.png", "output": "b.obj", "options": {"quality": "fast"}}


def test_request_fields_are_checked_with_their_codes():
    assert p.request_id({"id": "x"}, True) == "x" and p.request_id({}, False) is None
    for msg, code in (({}, "missing_field"), ({"id": True}, "bad_field"), ({"id": math.nan}, "bad_field"), ({"id": []}, "bad_field")):
        with pytest.raises(p.RequestError) as exc:
            p.request_id(msg, True)
        assert exc.value.code == code
    assert p.path_field({"image": "a.png"}, "image", 1, True) == "a.png"
    for value in ("", 3, "a\x00b", "\ud800"):
        with pytest.raises(p.RequestError, match="field 'image'"):
            p.path_field({"image": value}, "image", 1, True)
    assert p.path_field({"image": "caf\udce9.png"}, "image", 1, True) == "caf\udce9.png"  # an escaped byte is a name


def test_a_schema_entry_is_the_option_it_describes():
    entries = schema(GeometryConfig(target="distance", pit_sealing=4))["options"]
    for entry, option in zip(entries, OPTIONS):
        read = p.Option.from_entry(entry)
        assert (read.name, read.kind, read.lo, read.hi, read.choices, read.label) == (
            option.name, option.kind, option.lo, option.hi, option.choices, option.label)
        assert read.expected() == option.expected().removesuffix(f" ({option.unit})")  # (the unit is not in the schema)
    assert p.Option.from_entry({"name": "x", "type": "float", "min": 0, "max": math.inf}) is None
    assert p.Option.from_entry({"name": "x", "type": "choice", "choices": []}) is None
    threshold = p.Option.from_entry(entries[0])
    assert threshold.accepts(0.5) and not any(threshold.accepts(v) for v in (0, 1, True, "0.5", math.nan, 10 ** 400))
