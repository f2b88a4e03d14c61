"""ShapeNetCore v1 or v2, for users who have a copy (it cannot be downloaded
here: it needs an account).

Layout: ``<root>/<synset>/<model>/model.obj`` (v1) or
``<root>/<synset>/<model>/models/model_normalized.obj`` (v2).  Only the
synsets of the paper's classes (:data:`SYNSETS`) are enumerated; the class
comes from the synset.  ShapeNet's licence is its own terms of use (research
only), recorded as ``ShapeNet-ToU``.

Frame: ShapeNetCore models are aligned Y-up.  Which horizontal axis is the
front could not be checked on this machine (no ShapeNet copy); the default
assumes the front faces +Z (the Sweet Home 3D convention, ``(x, y, z) ->
(x, −z, y)``) and ``front`` can be changed by callers
(``genre data build --shapenet-front``).
"""

from __future__ import annotations

from pathlib import Path

import trimesh

from . import ShapeRecord, rotation_from_axes, scene_parts, slug

__all__ = ["PACKAGES", "SYNSETS", "enumerate_shapes"]

PACKAGES: tuple[str, ...] = ()

# WordNet synset id -> project class (the 13 classes of the GenRe paper plus
# the ShapeNet synsets of two Pix3D classes).
SYNSETS: dict[str, str] = {
    "02691156": "airplane",
    "02958343": "car",
    "03001627": "chair",
    "02828884": "bench",
    "04530566": "vessel",
    "04090263": "rifle",
    "04256520": "sofa",
    "04379243": "table",
    "04401088": "phone",
    "02933112": "cabinet",
    "03691459": "speaker",
    "03636649": "lamp",
    "03211117": "display",
    "02818832": "bed",
    "02871439": "bookcase",
}


def _model_file(model_dir: Path) -> Path | None:
    for rel in ("models/model_normalized.obj", "model.obj"):
        if (model_dir / rel).is_file():
            return model_dir / rel
    return None


def enumerate_shapes(root: Path, *, front: str = "+z") -> list[ShapeRecord]:
    """Models of :data:`SYNSETS` under a ShapeNetCore folder ``root``.

    Args:
        root: the folder holding the synset folders.
        front: ShapeNet's front axis (signed ``x``/``z``); up is +Y.
    """
    root = Path(root)
    if not root.is_dir():
        raise ValueError(f"ShapeNet folder {root} does not exist")
    rotation = rotation_from_axes("+y", front)
    records = []
    for synset, cls in SYNSETS.items():
        synset_dir = root / synset
        if not synset_dir.is_dir():
            continue
        for model_dir in sorted(p for p in synset_dir.iterdir() if p.is_dir()):
            path = _model_file(model_dir)
            if path is None:
                continue
            records.append(
                ShapeRecord(
                    shape_id=f"shapenet-{synset}-{slug(model_dir.name)}",
                    source="shapenet",
                    package=None,
                    path=str(path),
                    name=model_dir.name,
                    creator="",
                    licence="ShapeNet-ToU",
                    category=synset,
                    class_hint=cls,
                    rotation=rotation,
                    load=lambda p=path: scene_parts(trimesh.load(str(p), force="scene")),
                )
            )
    return records
