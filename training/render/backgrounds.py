"""Random backgrounds behind the rendered object, and compositing over them.

The object is rendered over a transparent film and composited afterwards, so
the true mask (the film alpha) survives whatever the background is.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["make_background", "composite_over"]


def _smooth_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Value noise (size, size, 3) in [0, 1]: a random (cells+1)² colour grid, bilinearly upsampled."""
    grid = rng.random((cells + 1, cells + 1, 3))
    t = (np.arange(size) + 0.5) / size * cells
    i0 = np.minimum(t.astype(int), cells - 1)
    f = (t - i0)[:, None]
    rows = grid[i0] * (1 - f)[:, :, None] + grid[i0 + 1] * f[:, :, None]  # (size, cells+1, 3)
    out = rows[:, i0] * (1 - f.T)[:, :, None] + rows[:, i0 + 1] * f.T[:, :, None]
    return out


def make_background(rng: np.random.Generator, size: int) -> tuple[np.ndarray, dict[str, Any]]:
    """A random background image (size, size, 3) float32 in [0, 1] and a description.

    Kinds: ``solid`` (one colour), ``gradient`` (two colours along a random
    direction) and ``noise`` (two to three octaves of smooth value noise).
    """
    if size <= 0:
        raise ValueError(f"background size must be positive, got {size}")
    kind = str(rng.choice(["solid", "gradient", "noise"]))
    if kind == "solid":
        colour = rng.random(3)
        img = np.broadcast_to(colour, (size, size, 3)).copy()
        info = {"kind": kind, "colour": [round(float(c), 4) for c in colour]}
    elif kind == "gradient":
        a, b = rng.random(3), rng.random(3)
        angle = float(rng.uniform(0.0, 2.0 * math.pi))
        coords = (np.arange(size) + 0.5) / size - 0.5
        proj = coords[None, :] * math.cos(angle) - coords[:, None] * math.sin(angle)  # (H, W)
        t = np.clip(proj / math.sqrt(0.5) + 0.5, 0.0, 1.0)[:, :, None]
        img = a * (1 - t) + b * t
        info = {"kind": kind, "angle_deg": round(math.degrees(angle), 2)}
    else:
        octaves = int(rng.integers(2, 4))
        img = np.zeros((size, size, 3))
        weight_sum = 0.0
        for o in range(octaves):
            w = 0.5**o
            img += w * _smooth_noise(rng, size, int(rng.integers(2, 5)) * 2**o)
            weight_sum += w
        img /= weight_sum
        # Stretch the contrast so noise backgrounds are not all mid-grey.
        lo, hi = img.min(), img.max()
        img = (img - lo) / max(hi - lo, 1e-6)
        info = {"kind": kind, "octaves": octaves}
    return img.astype(np.float32), info


def composite_over(rgba: np.ndarray, background: np.ndarray) -> np.ndarray:
    """Straight-alpha ``rgba`` (H, W, 4) uint8 over ``background`` (H, W, 3) float in [0, 1] → (H, W, 3) uint8."""
    if rgba.ndim != 3 or rgba.shape[2] != 4 or rgba.dtype != np.uint8:
        raise ValueError(f"rgba: expected (H, W, 4) uint8, got {rgba.shape} {rgba.dtype}")
    if background.shape != rgba.shape[:2] + (3,):
        raise ValueError(f"background: expected {rgba.shape[:2] + (3,)}, got {background.shape}")
    fg = rgba[..., :3].astype(np.float32) / 255.0
    a = rgba[..., 3:].astype(np.float32) / 255.0
    out = fg * a + background.astype(np.float32) * (1.0 - a)
    return np.clip(np.rint(out * 255.0), 0, 255).astype(np.uint8)
