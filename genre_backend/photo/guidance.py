"""How a photo's mask is to be chosen: one record from the front ends to :func:`.preprocess.preprocess`.

:class:`MaskGuidance` carries a person's mask inputs (a mask file, a box, a strokes file and the pixels the box and
strokes are over) and the automatic mask's switches (``refine``, ``seeding``) as one value: ``genre reconstruct``'s
flags and ``genre serve``'s request fields make one, :meth:`~genre_backend.inference.reconstruct.Reconstructor.run`
takes it, and the preprocessing reads it (:func:`.preprocess.preprocess`; the order of choice is there).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from .segment import DEFAULT_SEEDING

__all__ = ["MaskGuidance"]


@dataclass(frozen=True)
class MaskGuidance:
    """A photo's mask inputs; the defaults: none given, the automatic mask.

    ``mask``: a mask file (white object on black, the photo's size).  ``box`` (x0, y0, x1, y1, the photo's pixels) and
    ``strokes`` (a file of white object and black background strokes on grey, the photo's size): a person's guidance
    for the found mask, over the photo's pixels as ``frame`` says (:data:`.decode.GUIDANCE_FRAMES`: ``"upright"``, EXIF
    orientation applied; ``"stored"``, as stored in the file); never with a mask file.  ``refine``: without a mask
    file or alpha, find the mask in the photo (off: the depth net's silhouette as it is); ``seeding``: how
    (:data:`.segment.SEEDINGS`).  Checked where it is used (:func:`.preprocess.preprocess`).
    """

    mask: str | os.PathLike | None = None
    box: tuple[float, float, float, float] | None = None
    strokes: str | os.PathLike | None = None
    frame: str = "upright"
    refine: bool = True
    seeding: str = DEFAULT_SEEDING

    @property
    def guided(self) -> bool:
        """Whether a person's box or strokes guide the found mask."""
        return self.box is not None or self.strokes is not None

    @property
    def files(self) -> tuple[Path, ...]:
        """The files given (mask, strokes): inputs a run never overwrites."""
        return tuple(Path(p) for p in (self.mask, self.strokes) if p is not None)
