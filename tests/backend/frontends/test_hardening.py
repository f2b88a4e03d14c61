"""Inputs and faults that once stopped the server, overwrote the wrong file or left debris (issue 18)."""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from genre_backend.config import GenreConfig
from genre_backend.frontends import reconstruct_cli
from genre_backend.inference.reconstruct import OutputError, check_output_path
from genre_backend.atomic import TMP_MARK, atomic_write_bytes, remove_dead_temporaries, tmp_prefix
from genre_backend.weights_file import WeightsError
from genre_backend.nets.model import WEIGHTS_FORMAT, load_model
from support.server import ServerProcess

REPO = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def photo(trained):
    return trained[1] / "box" / "view_000.png"


def _cli(capsys, *args):
    code = reconstruct_cli.main([str(a) for a in args], prog="genre reconstruct")
    out, err = capsys.readouterr()
    return code, out, err


# ---- R1, R2, R5: the server keeps serving ------------------------------------------------------------
@pytest.fixture(scope="module")
def server(trained):
    s = ServerProcess("--weights", str(trained[0]))
    assert s.next(timeout=300)["type"] == "ready"
    yield s
    s.send({"type": "shutdown", "id": "end"})
    assert s.until(lambda e: e["type"] == "bye")[-1]["id"] == "end"
    assert s.close() == 0


def _pong(server, rid="alive"):
    server.send({"type": "ping", "id": rid})
    return server.until(lambda e: e["type"] == "pong")[-1]


def test_huge_integer_is_bad_json_not_a_crash(server):
    server.send('{"type": "ping", "id": ' + "9" * 5000 + "}")
    ev = server.next()
    assert ev["type"] == "error" and ev["code"] == "bad_json" and ev["id"] is None
    assert "digit" in ev["message"]
    assert _pong(server) == {"type": "pong", "id": "alive"}


def test_lone_surrogates_are_echoed_as_escapes(server, photo, tmp_path):
    server.send('{"type": "ping", "id": "\\ud800x"}')
    assert server.next() == {"type": "pong", "id": "\ud800x"}
    assert server.raw[-1].isascii() and "\\ud800" in server.raw[-1]
    # a real non-UTF-8 file name (as the OS hands it to Python): the mesh is written and its result sent
    out = tmp_path / os.fsdecode(b"caf\xe9.obj")
    server.send(json.dumps({"type": "reconstruct", "id": "latin1", "image": str(photo), "output": str(out)}))
    ev = server.until(lambda e: e["type"] in ("result", "error"))[-1]
    assert ev["type"] == "result", ev
    assert ev["mesh"] == str(out) and os.path.isfile(os.fsencode(tmp_path) + b"/caf\xe9.obj")
    assert _pong(server)["id"] == "alive"


def test_long_values_are_not_echoed_whole(server, photo, tmp_path):
    huge = "x" * 1_000_000
    server.send({"type": "reconstruct", "id": 1, "image": str(photo), "output": str(tmp_path / huge)})
    ev = server.until(lambda e: e["type"] in ("result", "error"))[-1]
    assert ev["type"] == "error" and ev["code"] == "output_unwritable", ev
    assert len(ev["message"]) < 3000 and "characters" in ev["message"]
    server.send({"type": "reconstruct", "id": 2, "image": str(photo), "output": "o.obj", "options": {huge: 1}})
    ev = server.next()
    assert ev["code"] == "bad_field" and len(ev["message"]) < 3000
    assert _pong(server)["id"] == "alive"


@pytest.mark.parametrize(
    "fields, code, text",
    [
        ({"options": {"threshold": 10**400}}, "bad_field", "(0, 1)"),  # float() overflowed and stopped the reader
        ({"options": ""}, "bad_field", "must be an object"),  # false, 0, "" and [] were taken for {}
        ({"options": False}, "bad_field", "must be an object"),
        ({"image": "a\x00b.png"}, "bad_field", "NUL"),  # each path field: one answer, before any work
        ({"output": "m\ud800.obj"}, "bad_field", "lone surrogate"),
        ({"mask": "m\x00.png"}, "bad_field", "NUL"),
        ({"options": {"save_intermediates": "\udfff"}}, "bad_field", "lone surrogate"),
        ({"image": "x" * 300 + ".png"}, "bad_image", "name too long"),  # an OSError in a job was 'internal'
        ({"mask": "m" * 300 + ".png"}, "bad_mask", "name too long"),
        ({"options": {"save_intermediates": "i" * 300}}, "output_unwritable", "name too long"),  # (was after the mesh's write)
    ],
)
def test_odd_fields_get_their_code_in_one_line(server, photo, tmp_path, fields, code, text):
    out = tmp_path / "odd.obj"
    req = {"type": "reconstruct", "id": "odd", "image": str(photo), "output": str(out), **fields}
    server.send(req)
    ev = server.until(lambda e: e["type"] in ("result", "error") and e["id"] == "odd")[-1]
    assert ev["type"] == "error" and ev["code"] == code and text in ev["message"] and "\n" not in ev["message"], ev
    assert not out.exists()
    assert _pong(server)["id"] == "alive"


# ---- R3, R7: the wrong file is never overwritten -----------------------------------------------------
def test_outputs_that_are_not_regular_files_or_are_inputs_are_refused(trained, photo, tmp_path, capsys):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    for out in (fifo, Path("/dev/null")):
        with pytest.raises(OutputError, match="not a regular file"):
            check_output_path(out)
        code, _, err = _cli(capsys, photo, "-o", out, "--weights", trained[0], "--format", "obj")
        assert code == 1 and "[output_unwritable]" in err and len(err.strip().splitlines()) == 1, err
    assert fifo.exists() and not fifo.is_file() and Path("/dev/null").is_char_device()
    copy_ = tmp_path / "photo.png"
    copy_.write_bytes(photo.read_bytes())
    before = copy_.read_bytes()
    code, _, err = _cli(capsys, copy_, "-o", copy_, "--weights", trained[0], "--format", "obj")
    assert code == 1 and "input" in err and "[output_unwritable]" in err
    assert copy_.read_bytes() == before


def test_intermediates_never_replace_the_users_mask(trained, photo, tmp_path, capsys):
    import numpy as np
    from PIL import Image

    inter = tmp_path / "inter"
    inter.mkdir()
    mask = inter / "mask.png"
    alpha = np.load(photo.with_suffix(".npz"))["mask"] > 0.5
    Image.fromarray(alpha.astype(np.uint8) * 255, "L").save(mask)
    before = mask.read_bytes()
    code, _, err = _cli(capsys, photo, "--mask", mask, "-o", tmp_path / "m.obj", "--weights", trained[0], "--save-intermediates", inter)
    assert code == 1 and "input" in err and "[output_unwritable]" in err, err
    assert mask.read_bytes() == before


def test_over_long_output_name_is_one_line(trained, photo, tmp_path, capsys):
    code, _, err = _cli(capsys, photo, "-o", tmp_path / ("n" * 300 + ".obj"), "--weights", trained[0])
    assert code == 1 and "[output_unwritable]" in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err


# ---- R4 and dead temporaries ------------------------------------------------------------------------
def test_planted_symlink_at_a_temporary_name_is_not_followed(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    target = tmp_path / "mesh.obj"
    for suffix in ("", "x" * 8):  # the old fixed name and a guess at the new one
        os.symlink(victim, tmp_path / (tmp_prefix(target) + suffix))
    atomic_write_bytes(target, b"mesh")
    assert victim.read_text() == "keep me" and target.read_bytes() == b"mesh"


def test_temporaries_of_dead_processes_are_removed_on_the_next_write(tmp_path):
    target = tmp_path / "big.obj"
    proc = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True, check=True)
    dead = int(proc.stdout)
    stale = tmp_path / f".big.obj{TMP_MARK}{dead}-abcd1234"
    stale.write_bytes(b"half a mesh")
    live = tmp_path / f".big.obj{TMP_MARK}{os.getppid()}-abcd1234"  # a process that is running
    live.write_bytes(b"being written")
    other = tmp_path / f".other.obj{TMP_MARK}{dead}-abcd1234"  # another target's: left for its own next write
    other.write_bytes(b"x")
    users = [tmp_path / f".big.obj.tmp-{dead}-abcd1234", tmp_path / f".big.obj{TMP_MARK}{dead}-mine"]  # a user's own files
    for u in users:
        u.write_bytes(b"the user's")
    atomic_write_bytes(target, b"mesh")
    assert not stale.exists() and live.exists() and other.exists() and target.read_bytes() == b"mesh"
    assert all(u.read_bytes() == b"the user's" for u in users)
    assert remove_dead_temporaries(tmp_path / "other.obj") == 1 and not other.exists()


def test_temporary_names_fit_the_name_limit(tmp_path):
    for n in (200, 233, 240, 250, 255):
        for ch in ("a", "é", "\u6f22"):  # 1, 2 and 3 bytes a character
            name = (ch * n)
            while len(os.fsencode(name + ".obj")) > 255:
                name = name[:-1]
            target = tmp_path / (name + ".obj")
            assert len(os.fsencode(tmp_prefix(target))) + 8 <= 255
            atomic_write_bytes(target, b"mesh")
            assert target.read_bytes() == b"mesh"
            target.unlink()
    assert os.listdir(tmp_path) == []


# ---- bad weights files ------------------------------------------------------------------------------
def _rewrite_config(trained, tmp_path, mutate) -> Path:
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(trained[0]), framework="pt") as f:
        meta = dict(f.metadata())
        state = {k: f.get_tensor(k) for k in f.keys()}
    config = json.loads(meta["config"])
    mutate(config)
    meta["config"] = json.dumps(config)
    out = tmp_path / "mutated.safetensors"
    save_file(state, str(out), metadata=meta)
    return out


@pytest.mark.parametrize(
    "part, key, value, text",
    [("geometry", "voxel_size", "64", "expected int"), ("network", "depth_widths", None, "expected tuple"),
     ("geometry", "default_threshold", float("nan"), "expected float"), ("geometry", "default_threshold", 2, "(0, 1)"),
     ("geometry", "object_fraction", 0, "object_fraction")],
)
def test_wrongly_typed_stored_config_is_bad_weights(trained, tmp_path, capsys, photo, part, key, value, text):
    path = _rewrite_config(trained, tmp_path, lambda c: c[part].__setitem__(key, value))
    with pytest.raises(WeightsError, match=text.replace("(", r"\(").replace(")", r"\)")):
        load_model(path)
    code, _, err = _cli(capsys, photo, "-o", tmp_path / "m.obj", "--weights", path)
    assert code == 1 and "[bad_weights]" in err and "Traceback" not in err


def test_nan_threshold_weights_fail_serve_with_an_error_event(trained, tmp_path):
    path = _rewrite_config(trained, tmp_path, lambda c: c["geometry"].__setitem__("default_threshold", float("nan")))
    s = ServerProcess("--weights", str(path))
    ev = s.next(timeout=300)
    assert ev["type"] == "error" and ev["code"] == "bad_weights"
    assert s.close() == 1


def test_wrong_shape_weights_name_the_tensor_and_both_shapes(trained, tmp_path):
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(trained[0]), framework="pt") as f:
        meta = dict(f.metadata())
        state = {k: f.get_tensor(k) for k in f.keys()}
    name = sorted(k for k in state if state[k].ndim == 4)[0]
    state[name] = torch.zeros(*[d + 1 for d in state[name].shape])
    bad = tmp_path / "shape.safetensors"
    save_file(state, str(bad), metadata=meta)
    with pytest.raises(WeightsError) as exc:
        load_model(bad)
    msg = str(exc.value)
    assert name in msg and "in the file" in msg and "the model wants" in msg and "\n" not in msg
    assert meta["format"] == WEIGHTS_FORMAT


def test_config_round_trip_and_checks():
    from genre_backend.config import PRESETS

    for preset in PRESETS.values():
        assert GenreConfig.from_dict(copy.deepcopy(preset.to_dict())) == preset
    d = PRESETS["default"].to_dict()
    d["geometry"]["voxel_size"] = True  # a bool is not an int here
    with pytest.raises(ValueError, match="expected int"):
        GenreConfig.from_dict(d)


def test_a_new_output_name_without_an_extension_gets_the_formats(tmp_path):
    photo = [Path("photo.png")]
    assert reconstruct_cli.output_paths(photo, str(tmp_path / "plate"), "obj") == [tmp_path / "plate.obj"]
    assert reconstruct_cli.output_paths(photo, str(tmp_path / "plate"), "glb") == [tmp_path / "plate.glb"]
    assert reconstruct_cli.output_paths(photo, str(tmp_path / "plate.v2"), "obj") == [tmp_path / "plate.v2"]  # named
    (tmp_path / "there").write_text("a user's file")
    assert reconstruct_cli.output_paths(photo, str(tmp_path / "there"), "obj") == [tmp_path / "there"]  # judged as named
    (tmp_path / "folder").mkdir()
    assert reconstruct_cli.output_paths(photo, str(tmp_path / "folder"), "ply") == [tmp_path / "folder" / "photo.ply"]
