"""The add-on tests' model and photo, made by the project's own training code (also for the GUI run, tests/addon/e2e)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def make_weights(root: Path, steps: tuple[int, int, int] = (3, 3, 3), lr: float | None = None) -> Path:
    """Weights from the project's own training code: tiny rendered views, a few steps of each stage (for the GUI
    end-to-end run, tests/addon/e2e/run_gui_e2e.py; the tests here use the session's model, conftest.py).

    ``steps``: (depth, inpaint, refine) training steps; ``lr``: one learning rate for all (None: the stage defaults).
    """
    code = f"""
import sys
from pathlib import Path
sys.path[:0] = [{str(REPO / 'tests')!r}, {str(REPO)!r}]
from support.tiny_data import TINY, make_tiny_views
from training.learn.train import TrainConfig, train
root = Path({str(root)!r})
views = make_tiny_views(root)
prev = None
for stage, steps in zip(("depth", "inpaint", "refine"), {tuple(steps)!r}):
    cfg = TrainConfig(stage=stage, data=str(views), out=str(root / "train"), steps=steps, batch_size=2, lr={lr!r},
                      val_fraction=0.0, augment=False, progress=False, log_every=10, init=prev)
    train(cfg, TINY if prev is None else None)
    prev = str(root / "train" / stage / "final.safetensors")
"""
    env = {**os.environ, "BLENDER_USER_RESOURCES": str(root / "blender-user"), "XDG_CACHE_HOME": str(root / "cache")}
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, timeout=900)
    if proc.returncode != 0:
        raise AssertionError(f"making the test weights failed:\n{proc.stderr[-4000:]}")
    return root / "train" / "refine" / "final.safetensors"


def make_photo(root: Path) -> Path:
    """The photo: a rendered view of the tiny views under ``root`` (``root/views``) with its object mask as alpha
    (a cut-out product shot), so that the few training steps need not have taught the depth net a silhouette yet."""
    photo = root / "box.png"
    if not photo.is_file():
        import numpy as np
        from PIL import Image

        rgb = np.asarray(Image.open(root / "views" / "box" / "view_000.png").convert("RGB"))
        mask = np.load(root / "views" / "box" / "view_000.npz")["mask"] > 0
        Image.fromarray(np.dstack([rgb, mask.astype(np.uint8) * 255]), "RGBA").save(photo)
    return photo


def load_addon_module(stem: str):
    """A bpy-free module of blender_addon/ (``backend``, ``schema``, ``geometry``) imported by file, inside a stand-in
    for its package (whose ``__init__`` needs bpy), so that its relative imports (``.protocol``) resolve."""
    import importlib
    import types

    package = "genre_addon_bpy_free"
    if package not in sys.modules:
        stand_in = types.ModuleType(package)
        stand_in.__path__ = [str(REPO / "blender_addon")]
        sys.modules[package] = stand_in
    return importlib.import_module(f"{package}.{stem}")
