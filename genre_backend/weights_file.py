"""The weights file format: the one reader and writer of GenRe's (and the baselines') weights, and the shipped
weights found by name.

Weights are safetensors files with a format tag and the model config in their metadata, plus a JSON sidecar for
people; :func:`save_weights` and :func:`read_weights` are the only code that writes and reads them (through
:mod:`genre_backend.atomic`).  No pickle anywhere.  The shipped weights are found by name (``default``,
``protocol``) through :func:`resolve_weights`, the one place that knows where they lie.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from .atomic import atomic_write_bytes, atomic_write_text

__all__ = [
    "WeightsError",
    "WEIGHTS_DIR",
    "WEIGHTS_NAMES",
    "DEFAULT_WEIGHTS_NAME",
    "PROTOCOL_WEIGHTS_NAME",
    "named_weights",
    "resolve_weights",
    "weights_extra",
    "save_weights",
    "read_weights",
    "load_state_strict",
    "check_state",
    "stored_config",
    "parse_json_bounded",
    "STORAGES",
    "INT8_SCALE_SUFFIX",
    "pack_int8",
]


class WeightsError(ValueError):
    """A weights file that cannot be used: missing, corrupt, foreign, or not matching its config."""


WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
DEFAULT_WEIGHTS_NAME = "default"
PROTOCOL_WEIGHTS_NAME = "protocol"
# The shipped weights, by name (genre_backend/weights/NAME.safetensors + NAME.json; MODEL_CARD.md):
WEIGHTS_NAMES = {
    DEFAULT_WEIGHTS_NAME: "the product model for users (make demo, the add-on): trained on every class",
    PROTOCOL_WEIGHTS_NAME: "the research model: trained on the seen classes only; every Table-1 number comes from it",
}


def named_weights(name: str) -> Path:
    """The shipped file of the weights called ``name`` (``default`` or ``protocol``); ValueError for another name."""
    if name not in WEIGHTS_NAMES:
        raise ValueError(f"unknown weights name {name!r}: choose {' or '.join(WEIGHTS_NAMES)}")
    return WEIGHTS_DIR / f"{name}.safetensors"


def resolve_weights(spec: str | os.PathLike | None = None) -> Path:
    """What ``--weights`` names: a shipped weights name, or a weights file path.

    ``None`` or ``""``: the ``default`` weights.  ``default`` / ``protocol``:
    the shipped file of that name (a file of that bare name in the current
    folder is reached as ``./default``).  Anything else that looks like a path
    (it exists, contains a folder separator, or has a suffix) is that file;
    whether it loads is :func:`read_weights`' business.  A bare word that is
    none of these is a :class:`WeightsError` naming the choices.
    """
    if spec is None or (isinstance(spec, str) and spec == ""):
        return named_weights(DEFAULT_WEIGHTS_NAME)
    if isinstance(spec, str) and spec in WEIGHTS_NAMES:
        return named_weights(spec)
    path = Path(spec)
    text = os.fspath(spec)
    if path.exists() or os.sep in text or (os.altsep and os.altsep in text) or path.suffix:
        return path
    raise WeightsError(f"unknown weights {text!r}: give a name ({', '.join(WEIGHTS_NAMES)}) or a weights file path")



def save_weights(path: str | os.PathLike, state: dict, meta: dict[str, str], sidecar: dict) -> Path:
    """Write ``state`` (name → tensor) as safetensors with string ``meta``, plus ``path.json`` = ``sidecar``.

    Both files are written atomically; tensors are made contiguous and moved
    to the CPU first.  ``meta`` must hold a ``format`` tag (read back by
    :func:`read_weights`).
    """
    from safetensors.torch import save

    if "format" not in meta:
        raise ValueError("save_weights: meta needs a 'format' tag")
    path = Path(path)
    tensors = {k: v.detach().contiguous().cpu() for k, v in state.items()}
    atomic_write_bytes(path, save(tensors, metadata=meta))
    atomic_write_text(path.with_suffix(".json"), json.dumps(sidecar, indent=2))
    return path


def _not_a_file(path: Path, what: str) -> str | None:
    """Why ``path`` is no regular file to read (None when it is one), as one line: missing, a directory, or another
    kind (a FIFO, a socket, a device), which is never opened (opening a FIFO would wait for a writer)."""
    import stat

    try:
        mode = path.stat().st_mode
    except (FileNotFoundError, NotADirectoryError):
        return f"{what} file not found: {path}"
    except (OSError, ValueError) as exc:  # a name too long, a loop of links; a NUL in the name
        return f"{path}: {what} file cannot be opened ({getattr(exc, 'strerror', None) or exc})"
    if stat.S_ISREG(mode):
        return None
    kind = ("a directory" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode)
            else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "not a regular file")
    return f"{path}: is {kind}, not a {what} file" if kind != "not a regular file" else f"{path}: not a regular file"


# How a file stores its floating-point weights (the metadata's ``storage``; none means float32):
# float16 halves the file; int8 quarters the large weights (see :func:`pack_int8`), the rest float16.
STORAGES = ("float32", "float16", "int8")
INT8_SCALE_SUFFIX = ".int8_scale"
INT8_MIN_ELEMENTS = 1024  # smaller tensors (biases, batch-norm scales) are not worth a scale per row


def pack_int8(state: dict) -> dict:
    """``state`` with every floating-point tensor of two or more dimensions and at least 1,024 elements stored as
    int8 rows: symmetric, one float32 scale per output channel (``NAME`` + :data:`INT8_SCALE_SUFFIX`, the row's
    largest magnitude ÷ 127), so each value is within half a scale step of the original.  The rest is returned
    as it is.  :func:`read_weights` undoes it for a file whose metadata says ``storage: int8``."""
    import torch

    out = {}
    for name, tensor in state.items():
        if not tensor.is_floating_point() or tensor.dim() < 2 or tensor.numel() < INT8_MIN_ELEMENTS:
            out[name] = tensor
            continue
        rows = tensor.detach().float().reshape(tensor.shape[0], -1)
        scale = rows.abs().amax(dim=1) / 127.0
        scale = torch.where(scale > 0, scale, torch.ones_like(scale))  # an all-zero row stores zeros
        out[name] = torch.round(rows / scale[:, None]).clamp(-127, 127).to(torch.int8).reshape(tensor.shape)
        out[name + INT8_SCALE_SUFFIX] = scale
    return out


def _unpack_int8(state: dict, path: Path) -> dict:
    """The float32 tensors a :func:`pack_int8` state stands for; a scale without its rows, rows that are not
    int8, or a scale of the wrong shape or not finite and positive is a :class:`WeightsError`."""
    import torch

    out = {}
    for name, tensor in state.items():
        if name.endswith(INT8_SCALE_SUFFIX):
            if name[: -len(INT8_SCALE_SUFFIX)] not in state:
                raise WeightsError(f"{path}: int8 storage: scale {name} has no tensor")
            continue
        scale = state.get(name + INT8_SCALE_SUFFIX)
        if scale is None:
            out[name] = tensor
            continue
        if tensor.dtype != torch.int8 or tensor.dim() < 2:
            raise WeightsError(f"{path}: int8 storage: tensor {name} has a scale but is not int8 rows")
        if (not scale.is_floating_point() or tuple(scale.shape) != (tensor.shape[0],)
                or not bool(torch.isfinite(scale).all()) or not bool((scale > 0).all())):
            raise WeightsError(f"{path}: int8 storage: scale of {name} is not {tensor.shape[0]} finite positive values")
        out[name] = (tensor.float().reshape(tensor.shape[0], -1) * scale.float()[:, None]).reshape(tensor.shape)
    return out


def read_weights(path: str | os.PathLike, expect_format: str, what: str = "weights") -> tuple[dict, dict[str, str]]:
    """Read a file written by :func:`save_weights`: ``(state, meta)`` on the CPU.

    Raises :class:`WeightsError` with a one-line reason when the file is
    missing, unreadable, or carries another format tag than ``expect_format``.
    """
    from safetensors import safe_open

    path = Path(path)
    problem = _not_a_file(path, what)
    if problem:
        raise WeightsError(problem)
    try:  # (safetensors reports an unreadable file as "No such file or directory")
        with open(path, "rb"):
            pass
    except OSError as exc:
        raise WeightsError(f"{path}: {what} file not readable ({exc.strerror or exc})") from None
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            meta = f.metadata() or {}
            state = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as exc:  # noqa: BLE001  (safetensors raises several types for damaged files)
        raise WeightsError(f"{path}: not a readable safetensors {what} file ({exc.__class__.__name__}: {exc})") from None
    if meta.get("format") != expect_format:
        raise WeightsError(f"{path}: {what} format {meta.get('format')!r}, this version reads {expect_format!r}")
    storage = meta.get("storage", "float32")
    if storage not in STORAGES:
        raise WeightsError(f"{path}: {what} storage {storage!r}, this version reads {', '.join(STORAGES)}")
    if storage == "int8":
        state = _unpack_int8(state, path)
    return state, meta


# The JSON a weights file's metadata carries is parsed only within these bounds (a hostile file could
# otherwise nest 100,000 brackets, beyond the parser's recursion limit, or hold megabytes of config):
MAX_CONFIG_CHARS = 64 * 1024  # a stored config is about 2 KB
MAX_EXTRA_CHARS = 1024 * 1024
MAX_JSON_DEPTH = 16  # a config nests 3 deep


def _json_depth(text: str) -> int:
    """The deepest nesting of ``[`` / ``{`` in JSON ``text`` (brackets inside strings do not count)."""
    import re

    depth = deepest = 0
    for m in re.finditer(r'"(?:[^"\\]|\\.)*"|[\[{]|[\]}]', text):
        c = m.group()
        if c in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif c in "]}":
            depth -= 1
    return deepest


def parse_json_bounded(text: Any, where: str, max_chars: int, max_depth: int = MAX_JSON_DEPTH) -> Any:
    """``json.loads(text)``, refused (:class:`WeightsError` naming ``where``) when ``text`` is not a string,
    is longer than ``max_chars``, nests deeper than ``max_depth`` or is not JSON."""
    if not isinstance(text, str):
        raise WeightsError(f"{where}: expected JSON text, got {type(text).__name__}")
    if len(text) > max_chars:
        raise WeightsError(f"{where}: {len(text):,} characters of JSON, at most {max_chars:,}")
    depth = _json_depth(text)
    if depth > max_depth:
        raise WeightsError(f"{where}: JSON nested {depth:,} deep, at most {max_depth}")
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise WeightsError(f"{where}: not valid JSON ({_first_line(exc)})") from None


def _first_line(exc: BaseException, limit: int = 300) -> str:
    lines = str(exc).strip().splitlines()
    line = lines[0] if lines else exc.__class__.__name__
    return line if len(line) <= limit else line[:limit] + "…"


def weights_extra(path: str | os.PathLike) -> dict:
    """The ``extra`` a weights file carries in its metadata (``{}`` if none or unreadable): e.g. ``model``, ``source``."""
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            extra = parse_json_bounded((f.metadata() or {}).get("extra") or "{}", "extra", MAX_EXTRA_CHARS)
    except Exception:  # noqa: BLE001  (a missing or damaged file has no extra; loading it says why)
        return {}
    return extra if isinstance(extra, dict) else {}


def stored_config(path: str | os.PathLike, meta: dict[str, str]):
    """The :class:`~genre_backend.config.GenreConfig` stored in a weights file's metadata (or WeightsError).

    The JSON is parsed within bounds (:func:`parse_json_bounded`) and every
    field is range-checked by the config's classes.
    """
    from .config import GenreConfig

    if "config" not in meta:
        raise WeightsError(f"{path}: the stored config is invalid (the metadata has no 'config')")
    data = parse_json_bounded(meta["config"], f"{path}: the stored config", MAX_CONFIG_CHARS)
    try:
        return GenreConfig.from_dict(data)
    except (KeyError, ValueError, TypeError, OverflowError) as exc:
        raise WeightsError(f"{path}: the stored config is invalid ({_first_line(exc)})") from None


def check_state(wanted: dict, state: dict, path: str | os.PathLike) -> None:
    """Refuse (:class:`WeightsError`, one line) a file's tensors ``state`` that do not fit a model's ``wanted`` state dict.

    ``wanted``: name → tensor (any device, the meta device included: only
    shapes and dtypes are read).  Every tensor must be present, none extra,
    each of the model's shape; where the model's tensor is floating-point the
    file's must be floating-point (float16, bfloat16, float32 or float64) and
    finite (no NaN, no ±inf); where it is an integer (batch-norm step
    counters) the file's must have the same dtype.
    """
    import torch

    for name, tensor in wanted.items():
        if name not in state:
            raise WeightsError(f"{path}: weights do not match the stored config (tensor {name} is missing from the file)")
        got = state[name]
        if tuple(got.shape) != tuple(tensor.shape):
            raise WeightsError(f"{path}: weights do not match the stored config (tensor {name} has shape "
                               f"{tuple(got.shape)} in the file, the model wants {tuple(tensor.shape)})")
        if tensor.is_floating_point():
            if not got.is_floating_point():
                raise WeightsError(f"{path}: tensor {name} is {str(got.dtype).replace('torch.', '')} in the file; "
                                   f"the model's weights are floating-point")
            if not bool(torch.isfinite(got).all()):
                bad = int((~torch.isfinite(got)).sum())
                raise WeightsError(f"{path}: tensor {name} holds {bad:,} values that are not finite (NaN or ±inf)")
        elif got.dtype != tensor.dtype:
            raise WeightsError(f"{path}: tensor {name} is {str(got.dtype).replace('torch.', '')} in the file, "
                               f"the model wants {str(tensor.dtype).replace('torch.', '')}")
    extra = sorted(set(state) - set(wanted))
    if extra:
        raise WeightsError(f"{path}: weights do not match the stored config (unexpected tensor {extra[0]} in the file)")


def load_state_strict(module, state: dict, path: str | os.PathLike) -> None:
    """``module.load_state_dict(state, strict=True)`` after :func:`check_state`; a mismatch becomes a one-line
    :class:`WeightsError`.

    The message names the first tensor that is missing, unexpected, of
    another shape (with both shapes), of a dtype that does not fit, or not
    finite.
    """
    check_state(module.state_dict(), state, path)
    try:
        module.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()[0]
        raise WeightsError(f"{path}: weights do not match the stored config ({first})") from None
