"""The colour-from-photo check: how closely a textured mesh, rendered through the photo's camera, shows the photo.

``scripts/colour_check.py`` and ``scripts/hidden_colour.py`` report it; ``tests/backend/inference/test_colour.py``
holds it under a bound.
"""

from __future__ import annotations

import numpy as np

from ..photo.preprocess import crop_resize
from .blender import render_textured

__all__ = ["photo_colour_error"]


def photo_colour_error(result, size: int = 256) -> tuple[float, float]:
    """How well a reconstruction's colour from the photo reproduces it: ``(mean absolute error in 0–255,
    coverage)``.

    ``result``: a :class:`~genre_backend.inference.result.Reconstruction`.  Its textured mesh is
    rendered unlit through the matching camera (:func:`render_textured`) and
    compared with the photo's crop inside the object mask, where the mesh
    covers it; ``coverage`` is the share of the mask the mesh covers.
    """
    from PIL import Image

    tex = result.texture()
    rgb, covered = render_textured(result.vertices, result.faces, tex.face_uv, tex.image, size, result.config.camera)
    side = tex.photo.shape[0]
    photo = crop_resize(tex.photo, (0, 0, side, side), size, (0, 0, 0))
    mask = np.asarray(Image.fromarray(result.intermediates["mask"].numpy().astype(np.uint8) * 255).resize((size, size), Image.NEAREST)) > 0
    inside = mask & covered
    if not inside.any():
        return float("nan"), 0.0
    return float(np.abs(rgb[inside].astype(np.float64) - photo[inside]).mean()), float(inside.sum() / max(mask.sum(), 1))
