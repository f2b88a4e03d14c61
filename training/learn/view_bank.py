"""Rendered views as a session's inputs: the depth net's own predictions in place of the true depth plus noise.

``genre train session --views DIR`` draws a share of each step's fresh samples
(the recipe's ``bank_share``) from a folder of renders (``genre data render``).
Such a sample is the rendered view's pose and shape, the targets made from the
pack's mesh at that pose (:class:`~training.learn.burst.ViewMaker`, as for any
session sample), and, as the depth the partial map and the depth voxels come
from, the **depth net's prediction** on the render, masked by the render's own
silhouette (what ``genre eval`` does for the GenRe row).  The refiner and the
inpainting net then learn from the errors the depth net really makes, which the
smooth synthetic noise of the other samples does not imitate (issue 47: a
refiner trained on noise alone scored 21 % worse from predicted depth).

The depth net is frozen in a session, so its predictions are made once per
depth net and folder and cached beside the renders
(``DIR/depth_predictions-<hash of the depth net's weights>.npz``).
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from genre_backend.frame import camera_rotation
from genre_backend.nets.model import GenRe

from ..data.views import find_views, load_view

__all__ = ["ViewBank", "load_view_bank", "depth_net_digest"]


@dataclass(frozen=True)
class ViewBank:
    """Rendered views of a pack's shapes: pack index, pose and the depth net's masked depth of each."""

    shape: torch.Tensor  # (V,) int64, index into the pack
    azimuth: torch.Tensor  # (V,) degrees
    elevation: torch.Tensor  # (V,) degrees
    depth: torch.Tensor  # (V, S, S) float16: the depth net's depth where the render's mask is set, else 0
    keys: tuple[str, ...]  # "<shape id>/KKK" of each view

    def __len__(self) -> int:
        return int(self.shape.shape[0])

    def draw(self, gen: torch.Generator, n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``n`` views drawn uniformly (with replacement) from ``gen``: (shape, azimuth, elevation, depth (n, S, S) float)."""
        pick = torch.randint(len(self), (n,), generator=gen)
        return self.shape[pick], self.azimuth[pick], self.elevation[pick], self.depth[pick].float()


def depth_net_digest(model: GenRe) -> str:
    """A hash of the depth net's weights (and the image size): the key of a predictions cache."""
    h = hashlib.sha256(str(model.config.geometry.image_size).encode())
    for name, t in sorted(model.depth_net.state_dict().items()):
        h.update(name.encode())
        h.update(t.detach().cpu().float().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def _pose_check(camera: dict, key: str) -> tuple[float, float]:
    """The view's (azimuth, elevation), checked against its recorded camera-to-object rotation: a render whose
    rotation is not :func:`~genre_backend.frame.camera_rotation` of its angles would pair the targets with another pose."""
    az, el = float(camera["azimuth_deg"]), float(camera["elevation_deg"])
    recorded = torch.tensor(camera["rotation_cam_to_obj"], dtype=torch.float64)
    ours = camera_rotation(az, el, dtype=torch.float64)[0]
    if not torch.allclose(recorded, ours, atol=1e-5):
        raise ValueError(f"{key}: the recorded rotation is not the frame's camera_rotation({az:.3f}, {el:.3f})")
    return az, el


def load_view_bank(root: str | os.PathLike, pack_ids: list[str], model: GenRe, device: torch.device,
                   batch: int = 32, say=print) -> ViewBank:
    """The views under ``root`` whose shape is in the pack, with ``model``'s depth net's predictions
    (read from the cache when it holds them for this depth net, else made in batches of ``batch`` and cached)."""
    root = Path(root)
    index = {sid: i for i, sid in enumerate(pack_ids)}
    refs = [r for r in find_views(root, targets=False) if r.shape_id in index]
    if not refs:
        raise FileNotFoundError(f"{root}: no complete rendered view of a shape in the pack")
    s = model.config.geometry.image_size
    cache = root / f"depth_predictions-{depth_net_digest(model)}.npz"
    keys = tuple(r.key for r in refs)
    try:
        with np.load(cache) as z:
            if tuple(str(k) for k in z["keys"]) == keys:
                say(f"view bank: {len(keys)} views, depth predictions read from {cache.name}")
                return ViewBank(torch.from_numpy(z["shape"]), torch.from_numpy(z["azimuth"]),
                                torch.from_numpy(z["elevation"]), torch.from_numpy(z["depth"]), keys)
    except (OSError, ValueError, KeyError):
        pass
    shape, az, el, depth = [], [], [], []
    was_training = model.depth_net.training
    model.depth_net.eval()
    try:
        for start in range(0, len(refs), batch):
            views = [load_view(r.shape_dir, r.view) for r in refs[start:start + batch]]
            for r, v in zip(refs[start:start + batch], views):
                if v["rgb"].shape[:2] != (s, s):
                    raise ValueError(f"{r.key}: rendered at {v['rgb'].shape[1]} px, the weights take {s}")
                a, e = _pose_check(v["camera"], r.key)
                shape.append(index[r.shape_id])
                az.append(a)
                el.append(e)
            rgb = torch.from_numpy(np.stack([v["rgb"] for v in views])).permute(0, 3, 1, 2).float().div(255.0)
            mask = torch.from_numpy(np.stack([v["mask"] for v in views]) > 0.5)
            with torch.no_grad():
                pred = model.depth_net(rgb.to(device))["depth"].float().cpu()
            depth.append(torch.where(mask, pred, torch.zeros_like(pred)).half())
            if (start // batch) % 10 == 0:
                say(f"view bank: depth predictions {min(start + batch, len(refs))}/{len(refs)}")
    finally:
        model.depth_net.train(was_training)
    bank = ViewBank(torch.tensor(shape, dtype=torch.int64), torch.tensor(az, dtype=torch.float32),
                    torch.tensor(el, dtype=torch.float32), torch.cat(depth), keys)
    tmp = cache.with_name(f".{cache.name}.{os.getpid()}.tmp.npz")
    np.savez(tmp, keys=np.array(keys), shape=bank.shape.numpy(), azimuth=bank.azimuth.numpy(),
             elevation=bank.elevation.numpy(), depth=bank.depth.numpy())
    os.replace(tmp, cache)
    say(f"view bank: {len(keys)} views, depth predictions cached in {cache.name}")
    return bank
