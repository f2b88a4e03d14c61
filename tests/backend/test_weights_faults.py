"""Damaged or hostile weights files are refused whole at load, as one WeightsError line (issue 43, part 1).

Every file is generated here from a tiny random model written by
:func:`genre_backend.nets.model.save_model`: its stored config, its tensors or
its bytes are damaged one way each.  Loading each must raise
:class:`WeightsError` (never RecursionError, a torch RuntimeError, a file that
loads and then fails every job, or one that silently makes a wrong mesh);
``genre reconstruct`` must print one error line and exit 1, and ``genre
serve`` must write the error as its first and only protocol line.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from genre_backend.weights_file import WeightsError
from genre_backend.nets.model import GenRe, load_model, save_model
from support.server import ServerProcess
from support.tiny_data import TINY

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Path:
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("weights") / "tiny.safetensors"
    save_model(GenRe(TINY), path)
    return path


def _parts(path: Path) -> tuple[dict, dict]:
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as f:
        return dict(f.metadata()), {k: f.get_tensor(k) for k in f.keys()}


def _write(out: Path, meta: dict, state: dict) -> Path:
    from safetensors.torch import save_file

    save_file(state, str(out), metadata=meta)
    return out


def _config(part: str, key: str, value):
    """A damage: the stored config's ``part.key`` set to ``value`` (``part`` None: a top-level key)."""
    def damage(good: Path, out: Path) -> Path:
        meta, state = _parts(good)
        config = json.loads(meta["config"])
        (config if part is None else config[part])[key] = value
        meta["config"] = json.dumps(config)
        return _write(out, meta, state)
    return damage


def _meta(key: str, text: str | None):
    """A damage: the metadata's ``key`` replaced by ``text`` (None: removed)."""
    def damage(good: Path, out: Path) -> Path:
        meta, state = _parts(good)
        if text is None:
            del meta[key]
        else:
            meta[key] = text
        return _write(out, meta, state)
    return damage


def _first(state: dict, pred) -> str:
    return sorted(k for k, v in state.items() if pred(k, v))[0]


def _is_weight(k, v) -> bool:
    return v.is_floating_point() and v.ndim == 4


def _tensor(change):
    """A damage: ``change(state)`` applied to the file's tensors."""
    def damage(good: Path, out: Path) -> Path:
        meta, state = _parts(good)
        change(state)
        return _write(out, meta, state)
    return damage


def _set(pred, make):
    def change(state):
        name = _first(state, pred)
        state[name] = make(state[name])
    return _tensor(change)


def _with_nan(t):
    t = t.clone()
    t.view(-1)[0] = float("nan")
    return t


def _with_inf(t):
    t = t.clone()
    t.view(-1)[-1] = float("inf")
    return t


def _missing(state):
    del state[_first(state, _is_weight)]


def _extra(state):
    state["refiner.planted"] = torch.zeros(3)


def _bytes(make):
    """A damage: the file's bytes replaced by ``make(bytes)``."""
    def damage(good: Path, out: Path) -> Path:
        out.write_bytes(make(good.read_bytes()))
        return out
    return damage


NESTED = "[" * 100_000 + "]" * 100_000  # (200,000 characters: refused by its length)
NESTED_SHORT = "[" * 30_000 + "]" * 30_000  # (within the length bound: refused by its depth)

# (id, damage, a fragment the message must hold)
CASES = [
    # the list: tracebacks before
    ("config_nested_100000", _meta("config", NESTED), "characters of JSON"),
    ("refiner_fc_1e9", _config("network", "refiner_fc", 10**9), "network.refiner_fc"),
    ("refiner_full_nf_1e6", _config("network", "refiner_full_nf", 10**6), "network.refiner_full_nf"),
    ("voxel_size_4096", _config("geometry", "voxel_size", 4096), "geometry.voxel_size"),
    # the list: loaded, then failed every job or wrote a wrong mesh
    ("lens_mm_0", _config("camera", "lens_mm", 0), "camera.lens_mm"),
    ("distance_1e308", _config("camera", "distance", 1e308), "camera.distance"),
    ("distance_negative", _config("camera", "distance", -2.2), "camera.distance"),
    ("sensor_mm_negative", _config("camera", "sensor_mm", -30), "camera.sensor_mm"),
    ("image_size_1e5", _config("geometry", "image_size", 10**5), "geometry.image_size"),
    ("sph_size_1e5", _config("geometry", "sph_size", 10**5), "geometry.sph_size"),
    ("sph_supersample_1e6", _config("geometry", "sph_supersample", 10**6), "geometry.sph_supersample"),
    ("object_fraction_1e-300", _config("geometry", "object_fraction", 1e-300), "geometry.object_fraction"),
    ("nan_tensor", _set(_is_weight, _with_nan), "not finite"),
    ("int32_tensor", _set(_is_weight, lambda t: t.to(torch.int32)), "int32"),
    ("missing_tensor", _tensor(_missing), "missing"),
    ("wrong_shape_tensor", _set(_is_weight, lambda t: torch.zeros(*[d + 1 for d in t.shape])), "shape"),
    ("truncated_file", _bytes(lambda b: b[: len(b) // 2]), "not a readable safetensors"),
    ("random_bytes", _bytes(lambda b: os.urandom(len(b))), "not a readable safetensors"),
    # more of the same kinds
    ("empty_file", _bytes(lambda b: b""), "not a readable safetensors"),
    ("header_only", _bytes(lambda b: b[: 8 + int.from_bytes(b[:8], "little")]), "not a readable safetensors"),
    ("inf_tensor", _set(_is_weight, _with_inf), "not finite"),
    ("nan_batchnorm_variance", _set(lambda k, v: k.endswith("running_var"), _with_nan), "not finite"),
    ("float_step_counter", _set(lambda k, v: k.endswith("num_batches_tracked"), lambda t: t.to(torch.float32)), "int64"),
    ("bool_tensor", _set(_is_weight, lambda t: t > 0), "bool"),
    ("unexpected_tensor", _tensor(_extra), "unexpected tensor"),
    ("config_not_json", _meta("config", "{"), "not valid JSON"),
    ("config_missing", _meta("config", None), "no 'config'"),
    ("config_1mb", _meta("config", json.dumps({"preset": "x" * 1_000_000})), "characters of JSON"),
    ("config_nested_30000", _meta("config", NESTED_SHORT), "nested 30,000 deep"),
    ("config_deep_objects", _meta("config", '{"a":' * 50 + "1" + "}" * 50), "nested"),
    ("config_huge_integer", _meta("config", '{"preset": ' + "9" * 5000 + "}"), "not valid JSON"),
    ("config_a_list", _meta("config", "[]"), "expected an object"),
    ("format_foreign", _meta("format", "other/1"), "format"),
    ("refiner_nf_1e6", _config("network", "refiner_nf", 10**6), "network.refiner_nf"),
    ("depth_widths_huge", _config("network", "depth_widths", [10**6] * 4), "network.depth_widths"),
    ("widths_too_many_parameters", _config("network", "inpaint_widths", [2048] * 4), "parameters"),
    ("decoder_blocks_1e6", _config("network", "depth_decoder_blocks", 10**6), "network.depth_decoder_blocks"),
    ("depth_output_scale_0", _config("network", "depth_output_scale", 0), "network.depth_output_scale"),
    ("voxel_size_not_power_of_two", _config("geometry", "voxel_size", 48), "power of two"),
    ("image_size_not_multiple_of_32", _config("geometry", "image_size", 48), "multiple of 32"),
    ("sph_pad_not_multiple_of_32", _config("geometry", "sph_pad", 15), "multiple of 32"),
    ("sph_pad_1e6", _config("geometry", "sph_pad", 10**6), "geometry.sph_pad"),
    ("shell_dilation_1e6", _config("geometry", "shell_dilation", 10**6), "geometry.shell_dilation"),
    ("chamfer_points_1e9", _config("geometry", "chamfer_points", 10**9), "geometry.chamfer_points"),
    ("threshold_step_tiny", _config("geometry", "threshold_step", 1e-300), "geometry.threshold_step"),
    ("sph_nohit_min_0", _config("geometry", "sph_nohit_min", 0), "geometry.sph_nohit_min"),
    ("object_fraction_2", _config("geometry", "object_fraction", 2), "geometry.object_fraction"),
    ("fov_too_narrow", _config("camera", "sensor_mm", 0.5), "field of view"),
    ("distance_inside_the_object", _config("camera", "distance", 0.5), "camera.distance"),
    ("elevation_reversed", _config("camera", "elevation_min_deg", 80), "elevation_min_deg"),
    ("preset_not_printable", _config(None, "preset", "a\nb"), "preset"),
]


def test_the_undamaged_file_and_the_shipped_weights_load(good, tmp_path):
    assert load_model(good).config == TINY
    half = save_model(load_model(good), tmp_path / "half.safetensors", storage="float16")
    assert load_model(half).config == TINY
    for name in ("default", "protocol"):
        load_model(REPO / "genre_backend" / "weights" / f"{name}.safetensors")


@pytest.mark.parametrize("name, damage, text", CASES, ids=[c[0] for c in CASES])
def test_each_damaged_file_is_refused_whole_at_load(good, tmp_path, name, damage, text):
    path = damage(good, tmp_path / f"{name}.safetensors")
    with pytest.raises(WeightsError) as exc:
        load_model(path)
    msg = str(exc.value)
    assert msg.startswith(f"{path}: ") and "\n" not in msg and len(msg) < 1000, msg
    assert text in msg[len(f"{path}: "):], msg


def test_reading_the_damaged_config_is_quick(good, tmp_path):
    """The depth check runs before the parser: 100,000 brackets are refused at once, not recursed into."""
    import time

    path = _meta("config", NESTED_SHORT)(good, tmp_path / "nested.safetensors")
    start = time.perf_counter()
    with pytest.raises(WeightsError, match="nested 30,000 deep"):
        load_model(path)
    assert time.perf_counter() - start < 5.0


def _photo(tmp_path: Path) -> Path:
    from PIL import Image

    path = tmp_path / "photo.png"
    Image.new("RGB", (64, 64), (200, 100, 50)).save(path)
    return path


@pytest.mark.parametrize("name", ["config_nested_100000", "refiner_fc_1e9"])
def test_reconstruct_prints_one_line_and_exits_1(good, tmp_path, name):
    damage = dict((c[0], c[1]) for c in CASES)[name]
    path = damage(good, tmp_path / f"{name}.safetensors")
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-m", "genre_backend.cli", "reconstruct", str(_photo(tmp_path)), "-o",
                           str(tmp_path / "m.obj"), "--weights", str(path)],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    lines = proc.stderr.splitlines()
    assert proc.returncode == 1, proc.stderr
    assert len(lines) == 1 and lines[0].startswith("genre reconstruct: error: ") and lines[0].endswith("[bad_weights]"), proc.stderr
    assert proc.stdout == "" and not (tmp_path / "m.obj").exists()


@pytest.mark.slow
@pytest.mark.parametrize("name", ["config_nested_100000", "refiner_fc_1e9", "nan_tensor"])
def test_serve_writes_the_error_as_its_first_and_only_line(good, tmp_path, name):
    damage = dict((c[0], c[1]) for c in CASES)[name]
    path = damage(good, tmp_path / f"{name}.safetensors")
    s = ServerProcess("--weights", str(path))
    ev = s.next(timeout=300)
    assert ev["type"] == "error" and ev["code"] == "bad_weights" and ev["id"] is None, ev
    assert s.next(timeout=60) is None  # nothing after it: no `ready`
    assert s.close() == 1
    assert len(s.raw) == 1
    assert "Traceback" not in s.proc.stderr.read()


def test_anything_else_raised_while_the_model_is_built_is_weights_error(good, monkeypatch):
    from genre_backend.nets import model as model_module

    def fail(self, *args, **kwargs):
        raise RuntimeError("[enforce fail at alloc_cpu.cpp:117] data. DefaultCPUAllocator: not enough memory\nsecond line")

    monkeypatch.setattr(model_module.GenRe, "load_state_dict", fail)
    with pytest.raises(WeightsError, match=r"could not be built from the file \(RuntimeError: .*not enough memory\)$"):
        load_model(good)


def test_an_unexpected_error_at_load_is_still_one_line(good, tmp_path, monkeypatch, capsys):
    from genre_backend.inference import reconstruct
    from genre_backend.frontends import reconstruct_cli

    def fail(*args, **kwargs):
        raise OSError("disk on fire\nmore")

    monkeypatch.setattr(reconstruct, "Reconstructor", fail)
    code = reconstruct_cli.main([str(_photo(tmp_path)), "-o", str(tmp_path / "m.obj"), "--weights", str(good)])
    out, err = capsys.readouterr()
    assert code == 1 and out == "" and err.count("\n") == 1 and err.rstrip().endswith("[internal]") and "disk on fire" in err


def _int8_damages():
    """Damages of an int8-stored file (``storage: int8``): its scales and its rows."""
    from genre_backend.weights_file import INT8_SCALE_SUFFIX as S

    def first_scale(state):
        return sorted(k for k in state if k.endswith(S))[0]

    def negative(state):
        state[first_scale(state)][0] = -1.0

    def short(state):
        k = first_scale(state)
        state[k] = state[k][:-1].clone()

    def orphan(state):
        del state[first_scale(state)[: -len(S)]]

    def not_int8(state):
        k = first_scale(state)[: -len(S)]
        state[k] = state[k].float()

    def nan(state):
        state[first_scale(state)][0] = float("nan")

    return [("scale_negative", negative, "finite positive"), ("scale_short", short, "finite positive"),
            ("scale_orphan", orphan, "has no tensor"), ("rows_not_int8", not_int8, "not int8 rows"),
            ("scale_nan", nan, "finite positive")]


@pytest.mark.parametrize("name, change, text", _int8_damages(), ids=[d[0] for d in _int8_damages()])
def test_a_damaged_int8_file_is_refused_whole_at_load(good, tmp_path, name, change, text):
    packed = save_model(load_model(good), tmp_path / "int8.safetensors", storage="int8")
    assert load_model(packed).config == TINY
    meta, state = _parts(packed)
    assert meta["storage"] == "int8"
    change(state)
    path = _write(tmp_path / f"{name}.safetensors", meta, state)
    with pytest.raises(WeightsError, match=text) as exc:
        load_model(path)
    assert str(exc.value).startswith(f"{path}: ") and "\n" not in str(exc.value)


def test_an_unknown_storage_is_refused(good, tmp_path):
    meta, state = _parts(good)
    path = _write(tmp_path / "int4.safetensors", {**meta, "storage": "int4"}, state)
    with pytest.raises(WeightsError, match="storage 'int4'"):
        load_model(path)
