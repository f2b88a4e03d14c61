"""Up-front input checks shared by the whole backend.

Every public geometry function validates its inputs with these helpers and
raises :class:`ValueError` with a message that names the argument, the shape
it expected and what it got.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

# torch is imported inside the tensor checks, so that the config (which uses the
# scalar checks) stays importable without it.


def check_tensor(
    name: str,
    x,
    shape: Sequence[int | str | None],
    *,
    floating: bool = True,
    finite: bool = True,
) -> torch.Tensor:
    """Validate ``x`` against a shape pattern and return it.

    ``shape`` entries are ints (must match), ``None`` (any size) or strings
    (a named size that must agree across all its occurrences in this call).
    A leading ``"..."`` entry accepts any number of leading dimensions.
    """
    import torch

    if not isinstance(x, torch.Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    pattern = list(shape)
    dims = list(x.shape)
    if pattern and pattern[0] == "...":
        pattern = pattern[1:]
        if len(dims) < len(pattern):
            raise ValueError(f"{name}: expected at least {len(pattern)} dims {_fmt(shape)}, got shape {tuple(dims)}")
        dims = dims[len(dims) - len(pattern):]
    elif len(dims) != len(pattern):
        raise ValueError(f"{name}: expected shape {_fmt(shape)}, got {tuple(x.shape)}")
    named: dict[str, int] = {}
    for want, got in zip(pattern, dims):
        if want is None:
            continue
        if isinstance(want, str):
            if named.setdefault(want, got) != got:
                raise ValueError(f"{name}: dimension {want} must be consistent, got shape {tuple(x.shape)}")
        elif want != got:
            raise ValueError(f"{name}: expected shape {_fmt(shape)}, got {tuple(x.shape)}")
    if floating and x.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"{name}: expected float32 or float64, got {x.dtype}")
    if finite and x.dtype.is_floating_point and not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name}: contains NaN or infinite values")
    return x


def check_mask(name: str, mask, like):
    """Validate a boolean mask (a torch.Tensor) with exactly the shape of ``like``."""
    import torch

    if not isinstance(mask, torch.Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(mask).__name__}")
    if mask.dtype != torch.bool:
        raise ValueError(f"{name}: expected a bool tensor, got {mask.dtype}")
    if mask.shape != like.shape:
        raise ValueError(f"{name}: expected shape {tuple(like.shape)}, got {tuple(mask.shape)}")
    return mask


def check_positive_int(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ValueError(f"{name}: expected a positive int, got {value!r}")
    return value


def check_threshold(name: str, value) -> float:
    """An isosurface level / probability threshold: a real number strictly inside (0, 1), returned as float.

    The one check of every threshold in the project (CLI options, server
    requests, weights metadata, marching cubes); bools, NaN and strings are refused.
    """
    # compared as it is: float() of a 400-digit integer raises OverflowError, not the ValueError callers catch
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not 0 < value < 1:
        raise ValueError(f"{name}: expected a number in (0, 1), got {_short_repr(value)}")
    return float(value)


MAX_HOLE_CLOSING = 8


def check_hole_closing(name: str, value) -> int:
    """A hole-closing size in voxels: an integer in [0, MAX_HOLE_CLOSING], returned as int (bools refused).

    The check of such a width given to a geometry function (a mesh option's range is its field's:
    ``genre_backend/config.py``, ``GeometryConfig``).
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not 0 <= value <= MAX_HOLE_CLOSING:
        raise ValueError(f"{name}: expected voxels, an integer in [0, {MAX_HOLE_CLOSING}], got {_short_repr(value)}")
    return int(value)


def _short_repr(value, limit: int = 300) -> str:
    try:
        text = repr(value)
    except ValueError:  # an integer past Python's 4,300-digit conversion limit
        return f"an integer of about {int(value.bit_length() * 0.30103):,} digits"
    return text if len(text) <= limit else f"{text[:limit]}… ({len(text):,} characters)"


def _fmt(shape: Sequence[int | str | None]) -> str:
    return "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"


def check_box(name: str, value) -> tuple[float, float, float, float]:
    """A box around the object in a photo's pixels: four finite numbers x0, y0, x1, y1 with x0 < x1 and y0 < y1.

    Accepts a sequence of four reals (bools refused) or the command line's text ``"x0,y0,x1,y1"``;
    returns floats.  Whether the box meets the photo is checked once the photo is decoded
    (:func:`genre_backend.photo.decode.photo_box`).
    """
    if isinstance(value, str):
        parts = [p.strip() for p in value.split(",")]
        try:
            value = [float(p) for p in parts]
        except ValueError:
            raise ValueError(f"{name}: expected four numbers x0,y0,x1,y1 (pixels of the photo), got {_short_repr(value)}") from None
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence) or len(value) != 4 or any(
            isinstance(v, bool) or not isinstance(v, numbers.Real) for v in value):
        raise ValueError(f"{name}: expected four numbers x0, y0, x1, y1 (pixels of the photo), got {_short_repr(value)}")
    try:
        x0, y0, x1, y1 = (float(v) for v in value)
    except OverflowError:  # an integer past the float range
        raise ValueError(f"{name}: expected four finite numbers, got {_short_repr(value)}") from None
    if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
        raise ValueError(f"{name}: expected four finite numbers, got {_short_repr(value)}")
    if not (x0 < x1 and y0 < y1):
        raise ValueError(f"{name}: expected x0 < x1 and y0 < y1 (left, top, right, bottom), got {x0:g},{y0:g},{x1:g},{y1:g}")
    return x0, y0, x1, y1
