"""Tiny real training data made in the tests: meshes rendered with Blender, with targets."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import trimesh

from genre_backend.config import GenreConfig, GeometryConfig, NetworkConfig

TINY = GenreConfig(
    preset="tiny",
    geometry=GeometryConfig(image_size=64, sph_size=32, sph_pad=16, voxel_size=32, target="distance"),
    network=NetworkConfig(depth_widths=(8, 16, 32, 64), depth_decoder_blocks=0, inpaint_widths=(8, 16, 32, 64), refiner_nf=4, refiner_fc=32),
)


def _normalised(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    lo, hi = mesh.bounds
    mesh.apply_translation(-(lo + hi) / 2)
    mesh.apply_scale(1.0 / np.linalg.norm(hi - lo))
    return mesh


def make_tiny_views(root: Path, config: GenreConfig = TINY, views_per_shape: int = 2) -> Path:
    """Render a box and a table-like shape (views_per_shape views each) and build their targets under root/views."""
    from training.data.views import ShapeEntry
    from training.render.scene import BlenderRenderer, render_shape
    from training.data.targets import build_targets

    meshes = root / "meshes"
    meshes.mkdir(parents=True, exist_ok=True)
    box = _normalised(trimesh.creation.box(extents=(0.6, 0.3, 0.4)))
    top = trimesh.creation.box(extents=(0.8, 0.5, 0.06))
    top.apply_translation((0, 0, 0.3))
    legs = [trimesh.creation.box(extents=(0.06, 0.06, 0.6)) for _ in range(4)]
    for leg, (x, y) in zip(legs, [(-0.35, -0.2), (0.35, -0.2), (-0.35, 0.2), (0.35, 0.2)]):
        leg.apply_translation((x, y, 0.0))
    table = _normalised(trimesh.util.concatenate([top, *legs]))
    shapes = []
    for name, mesh in (("box", box), ("table", table)):
        path = meshes / f"{name}.ply"
        mesh.export(path)
        shapes.append(ShapeEntry(name, path))
    renderer = BlenderRenderer(config, scratch_dir=root / "scratch")
    views = root / "views"
    for i, shape in enumerate(shapes):
        poses = [(30.0 + 100.0 * k + 45.0 * i, 15.0 + 10.0 * k) for k in range(views_per_shape)]
        render_shape(renderer, shape, poses, views, seed=0)
    build_targets(views, config, progress=False)
    return views


def copy_tiny_views(views: Path, root: Path) -> Path:
    """A copy of :func:`make_tiny_views`' output (``views`` and the meshes beside it) under ``root``, as if rendered
    there (the views' records name the copied meshes); returns ``root/views``.  Rendering takes seconds of
    Blender, copying milliseconds: the tests render once per session and copy (conftest.py)."""
    import shutil

    root.mkdir(parents=True, exist_ok=True)
    shutil.copytree(views.parent / "meshes", root / "meshes")
    shutil.copytree(views, root / "views")
    old, new = str(views.parent / "meshes"), str(root / "meshes")
    for record in (root / "views").rglob("*.json"):
        text = record.read_text()
        if old in text:
            record.write_text(text.replace(old, new))
    return root / "views"


# The tiny renders' masks span a median 0.66 of the image (measured over make_tiny_views), so
# the test model frames photos that way; the shipped presets use the config default (0.5).
TINY_FRAMED = dataclasses.replace(TINY, geometry=dataclasses.replace(TINY.geometry, object_fraction=0.66))


def train_tiny_weights(views: Path, run: Path) -> Path:
    """The tiny model trained stage by stage on ``views`` (depth 60 steps, inpaint 30, refine 60) into ``run``, on
    one thread (tiny nets: one thread is faster, and 25× faster on a busy 2-core machine, measured); returns the
    final refine weights.  The tests' shared model (conftest.py's ``trained``, made once per session).  Its nets
    run channels-last in fp32 whatever the processor (``speed``), so that every machine kind trains the same
    weights: ``--speed auto`` would train under bf16 where oneDNN has it natively, and an inference test's 1e-6
    agreement between two paths held for the fp32 weights only (1e-5 apart on 18 of 1,024 values under bf16)."""
    import torch

    from training.learn.train import TrainConfig, train

    common = dict(data=str(views), out=str(run), batch_size=4, val_fraction=0.0, augment=False, progress=False, log_every=50,
                  speed="channels-last")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        train(TrainConfig(stage="depth", steps=60, lr=3e-3, **common), TINY_FRAMED)
        prev = run / "depth" / "final.safetensors"
        for stage, steps, lr in (("inpaint", 30, 1e-3), ("refine", 60, 3e-3)):
            train(TrainConfig(stage=stage, steps=steps, lr=lr, init=str(prev), **common))
            prev = run / stage / "final.safetensors"
    finally:
        torch.set_num_threads(threads)
    return prev


def tiny_train_config(stage: str, views: Path, out: Path, **overrides):
    """A :class:`training.learn.train.TrainConfig` for the tiny views: batch 4, no validation, no augmentation, quiet."""
    from training.learn.train import TrainConfig

    base = dict(stage=stage, data=str(views), out=str(out), batch_size=4, val_fraction=0.0, augment=False, progress=False, log_every=5)
    base.update(overrides)
    return TrainConfig(**base)


def two_colour_backgrounds(folder: Path) -> Path:
    """A 'genre data backgrounds' folder of two plain photos (red, green; 64×48 JPEG) at ``folder``; returns it."""
    import json

    from PIL import Image

    (folder / "images").mkdir(parents=True)
    rows = []
    for i, colour in enumerate([(250, 10, 10), (10, 250, 10)]):
        Image.new("RGB", (64, 48), colour).save(folder / "images" / f"p{i}.jpg", quality=100)
        rows.append({"file": f"images/p{i}.jpg", "package": "p", "version": "1", "source": f"s{i}", "licence": "CC0-1.0",
                     "width": 64, "height": 48})
    (folder / "index.json").write_text(json.dumps({"format": "genre-backgrounds/1", "images": rows}))
    return folder


def write_manifest(tmp: Path, meshes: dict) -> Path:
    """A corpus manifest in ``tmp`` of ``meshes`` (id → (trimesh, group), written as ``shapes/<id>.glb``), class
    ``primitive``, split ``unassigned``, the group given (``product-train`` / ``product-test``)."""
    import json

    (tmp / "shapes").mkdir(parents=True, exist_ok=True)
    shapes = []
    for sid, (mesh, group) in meshes.items():
        mesh.export(tmp / "shapes" / f"{sid}.glb")
        shapes.append({"id": sid, "class": "primitive", "split": "unassigned", "groups": [group], "source": "test",
                       "licence": "CC0"})
    path = tmp / "manifest.json"
    path.write_text(json.dumps({"shapes": shapes}))
    return path
