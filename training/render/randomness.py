"""Seeded randomness of the training renders: one generator per (seed, shape, view, stream).

View k of a shape depends only on (seed, shape id, k), so asking for more
views later keeps the first ones, and a resumed or sharded run renders the
same pixels.  Streams: the view direction, the lighting, the background.
"""

from __future__ import annotations

import zlib

import numpy as np

__all__ = ["STREAM_VIEW", "STREAM_LIGHT", "STREAM_BACKGROUND", "view_rng", "sample_views"]

STREAM_VIEW, STREAM_LIGHT, STREAM_BACKGROUND = 0, 1, 2


def _shape_key(shape_id: str) -> int:
    return zlib.crc32(shape_id.encode("utf-8"))


def view_rng(seed: int, shape_id: str, view_index: int, stream: int) -> np.random.Generator:
    """The random generator of one (seed, shape, view, stream); deterministic across runs and machines."""
    if view_index < 0:
        raise ValueError(f"view_index must be >= 0, got {view_index}")
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, _shape_key(shape_id), int(view_index), int(stream)])


def sample_views(shape_id: str, n_views: int, seed: int, camera) -> list[tuple[float, float]]:
    """``n_views`` random (azimuth, elevation) pairs in degrees for one shape.

    Azimuth is uniform in [0, 360); elevation uniform in the camera config's
    ``[elevation_min_deg, elevation_max_deg]``.  View k depends only on
    (seed, shape_id, k), so asking for more views later keeps the first ones.
    """
    if n_views < 0:
        raise ValueError(f"n_views must be >= 0, got {n_views}")
    lo, hi = float(camera.elevation_min_deg), float(camera.elevation_max_deg)
    if not (-90.0 < lo <= hi < 90.0):
        raise ValueError(f"camera elevation range must lie in (-90, 90), got [{lo}, {hi}]")
    views = []
    for k in range(n_views):
        rng = view_rng(seed, shape_id, k, STREAM_VIEW)
        views.append((float(rng.uniform(0.0, 360.0)), float(rng.uniform(lo, hi))))
    return views
