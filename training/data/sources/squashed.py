"""Procedural shapes whose outline does not tell their depth, for training the depth net only (CC0, written here).

Why: seen from straight above, a ball, a flattened ellipsoid and a plate have the same round outline; only their
shading tells them apart (``scripts/outline_probe.py``). The corpus has few such families, so a depth net can
score well by reading depth off the outline alone, and does (``results/stage_errors/depth.md``). Each shape here is
one of three solids, squashed along the vertical to a random thickness, so that for any footprint every depth
occurs:

``ellipsoid``
    an icosphere (642 vertices) scaled to axes 1 × U[0.5, 1] × t;
``cylinder``
    a 64-sided cylinder, its footprint an ellipse 1 × U[0.5, 1], height t (from a coin to a drum);
``box``
    a box 1 × U[0.5, 1] × t (from a card to a cube).

``t``, the vertical extent over the largest, is log-uniform on [0.04, 1]. Every shape lies with its squashed axis
vertical (object +Z), centred on its bounding box and scaled to a bounding-box diagonal of 1, as the corpus and
:mod:`training.data.sources.thin` normalise. Shape ``k`` of a kind comes from
``numpy.random.default_rng([seed, KINDS.index(kind), k])``. Like the thin shapes, these are never a corpus source
or a test shape (``genre data squashed`` writes them for ``genre data render``).
"""

from __future__ import annotations

import numpy as np
import trimesh

from .thin import _normalised

__all__ = ["KINDS", "THICKNESS", "squashed_shape"]

KINDS: tuple[str, ...] = ("ellipsoid", "cylinder", "box")
THICKNESS: tuple[float, float] = (0.04, 1.0)  # the vertical extent over the largest, drawn log-uniformly


def _unit_solid(kind: str) -> trimesh.Trimesh:
    """The kind's solid spanning [-1, 1] on every axis."""
    if kind == "ellipsoid":
        return trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    if kind == "cylinder":
        return trimesh.creation.cylinder(radius=1.0, height=2.0, sections=64)
    return trimesh.creation.box(extents=(2.0, 2.0, 2.0))


def squashed_shape(kind: str, k: int, seed: int = 0) -> tuple[str, str, trimesh.Trimesh]:
    """Shape ``k`` of ``kind`` as ``(id, class, mesh)``: id ``squashed-<kind>-<k>``, class ``squashed-<kind>``."""
    if kind not in KINDS:
        raise ValueError(f"unknown squashed kind {kind!r}; known: {', '.join(KINDS)}")
    rng = np.random.default_rng([int(seed), KINDS.index(kind), int(k)])
    width = float(rng.uniform(0.5, 1.0))
    lo, hi = THICKNESS
    thickness = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    mesh = _unit_solid(kind)
    mesh.vertices = np.asarray(mesh.vertices) * [1.0, width, thickness]
    return f"squashed-{kind}-{k:03d}", f"squashed-{kind}", _normalised(mesh, np.eye(3))
