"""The baselines of the paper's Table 1, trained and stored beside GenRe.

* :class:`CompletionBaseline` -- **3D Completion**: the depth net → depth
  voxels (the paper's projection rule) → a 3D completion net of the refiner's
  architecture and size (:class:`genre_backend.nets.refiner.VoxelRefiner`, fed
  ``[zeros, depth voxels]`` on its two input channels), no spherical maps.
  Trained by ``genre train completion`` (depth net frozen, taken from
  ``--init``; the refiner's loss).
* :class:`OneStepNet` -- **GenRe-1step**: RGB → full spherical map directly
  with a U-ResNet like the depth net's (same widths and decoder blocks);
  trained by ``genre train onestep`` (MSE against the true full map over the
  periodically padded map, like the inpainting net).  At evaluation its map
  goes through GenRe's own projection and trained refiner.
* :class:`NearestIndex` -- **Nearest training shape**: for every training
  view, a small thumbnail of its true masked depth; a query's predicted
  masked depth is matched (L2 over thumbnails) and the retrieved training
  shape is returned posed as it appears in the retrieved view (its
  view-frame points).

Files: safetensors with JSON metadata (format ``genre-baseline/1``, the
baseline's ``kind`` and the model config), never pickle; GenRe's own weights
format (:mod:`genre_backend.nets.model`) is untouched.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from genre_backend import frame
from genre_backend.config import GenreConfig
from genre_backend.nets.depth_net import DepthNet, normalize_rgb
from genre_backend.nets.refiner import VoxelRefiner
from genre_backend.nets.uresnet import ResNetEncoder, UDecoder
from genre_backend.validation import check_tensor
from genre_backend.geometry.voxels import points_to_voxels
from genre_backend.atomic import atomic_write_bytes
from genre_backend.weights_file import WeightsError, load_state_strict, read_weights, save_weights, stored_config
from genre_backend.arguments import add_out, add_weights

from ..data.views import find_views, load_view_meta, surface_points_path, view_paths

__all__ = [
    "BASELINE_FORMAT",
    "CompletionBaseline",
    "OneStepNet",
    "NearestIndex",
    "save_baseline",
    "load_baseline",
    "depth_thumbnail",
    "build_nearest_index",
    "share_depth_net",
]

BASELINE_FORMAT = "genre-baseline/1"
THUMB = 32  # side of the nearest-neighbour depth thumbnails


class CompletionBaseline(nn.Module):
    """Depth net + a 3D completion net of the refiner's size; ``forward(rgb, mask)`` → shell logits (B, 1, N³)."""

    kind = "completion"

    def __init__(self, config: GenreConfig):
        super().__init__()
        self.config = config
        self.depth_net = DepthNet(config)
        self.completion = VoxelRefiner(config.geometry.voxel_size, config.network.refiner_nf, config.network.refiner_fc,
                                       config.network.refiner_full_nf)

    def depth_voxels(self, masked_depth: torch.Tensor) -> torch.Tensor:
        pts = frame.depth_to_points(masked_depth, self.config.camera).flatten(1, 2)
        return points_to_voxels(pts, self.config.geometry.voxel_size, (masked_depth > 0).flatten(1))

    def complete(self, vox_depth: torch.Tensor) -> torch.Tensor:
        """Depth voxels (B, 1, N³) → logits (B, 1, N³); the spherical channel is zeros."""
        return self.completion(torch.cat([torch.zeros_like(vox_depth), vox_depth], dim=1))

    def forward(self, rgb: torch.Tensor, mask: torch.Tensor | None = None, depth: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        out = self.depth_net(rgb)
        if mask is None:
            mask = out["silhouette_logits"] > 0
        d = out["depth"] if depth is None else depth
        out["masked_depth"] = torch.where(mask, d, torch.zeros_like(d))
        out["vox_depth"] = self.depth_voxels(out["masked_depth"])
        out["logits"] = self.complete(out["vox_depth"])
        return out


class OneStepNet(nn.Module):
    """RGB (B, 3, S, S) in [0, 1] → full spherical map (B, H, H) with a depth-net-like U-ResNet.

    The U-ResNet runs at the image resolution; its output is area-resampled
    to the spherical map's size and predicted as ``0.5 + output``.
    """

    kind = "onestep"

    def __init__(self, config: GenreConfig):
        super().__init__()
        self.config = config
        net = config.network
        self.size, self.sph = config.geometry.image_size, config.geometry.sph_size
        self.encoder = ResNetEncoder(3, net.depth_widths)
        self.decoder = UDecoder(net.depth_widths, 1, net.depth_decoder_blocks)

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        check_tensor("rgb", rgb, ("B", 3, self.size, self.size))
        skips, deep = self.encoder(normalize_rgb(rgb))
        out = self.decoder(skips, deep)
        if out.shape[-1] != self.sph:
            out = F.interpolate(out, size=(self.sph, self.sph), mode="area" if out.shape[-1] > self.sph else "bilinear")
        return 0.5 + out[:, 0]


_KINDS = {"completion": CompletionBaseline, "onestep": OneStepNet}


def save_baseline(net: nn.Module, path: str | os.PathLike, extra: dict | None = None) -> Path:
    """Write a baseline net (``kind``, config and tensors) atomically as safetensors, plus a JSON sidecar."""
    config = net.config.to_dict()
    meta = {"format": BASELINE_FORMAT, "kind": net.kind, "config": json.dumps(config), "extra": json.dumps(extra or {})}
    sidecar = {"format": BASELINE_FORMAT, "kind": net.kind, "config": config, "extra": extra or {}}
    return save_weights(path, net.state_dict(), meta, sidecar)


def share_depth_net(completion_path: str | os.PathLike, genre_weights: str | os.PathLike, out: str | os.PathLike) -> Path:
    """Write the 3D Completion baseline of ``completion_path`` with GenRe's depth net of ``genre_weights``.

    The completion net is trained on a frozen copy of GenRe's depth net
    (``genre train completion``), so the depth net is a stage the two rows
    share.  When GenRe's depth net is trained on (``genre train depth
    --init``) this gives the baseline the same one, its completion net
    untouched, so that Table 1 compares the two with equal depth nets.
    The two must be of one preset.  Returns the path written (``out``).
    """
    from genre_backend.nets.model import load_model

    baseline = load_baseline(completion_path, "completion")
    genre = load_model(genre_weights)
    g, b = genre.config.geometry, baseline.config.geometry
    if (g.image_size, g.sph_size, g.voxel_size) != (b.image_size, b.sph_size, b.voxel_size):
        raise WeightsError(f"{genre_weights}: made for another preset than the baseline's ({genre.config.preset} vs {baseline.config.preset})")
    baseline.depth_net.load_state_dict(genre.depth_net.state_dict())
    extra = {"depth_net_from": str(Path(genre_weights).resolve()), "completion_from": str(Path(completion_path).resolve())}
    return save_baseline(baseline, out, extra)


def load_baseline(path: str | os.PathLike, kind: str | None = None, device: str | torch.device = "cpu") -> nn.Module:
    """Load a net saved by :func:`save_baseline`; ``kind`` (optional) must match.  Raises WeightsError."""
    state, meta = read_weights(path, BASELINE_FORMAT, what="baseline weights")
    if meta.get("kind") not in _KINDS or (kind is not None and meta["kind"] != kind):
        raise WeightsError(f"{path}: holds a {meta.get('kind')!r} baseline, expected {kind!r}")
    net = _KINDS[meta["kind"]](stored_config(path, meta))
    load_state_strict(net, state, path)
    return net.to(device).eval()


# ---- nearest training shape ---------------------------------------------------------------
def depth_thumbnail(masked_depth: torch.Tensor, size: int = THUMB) -> torch.Tensor:
    """Masked depth (B, S, S) (background 0) → (B, size, size) area-averaged thumbnails.

    Background stays 0, so thumbnails compare silhouettes as well as depth.
    """
    check_tensor("masked_depth", masked_depth, ("B", "S", "S"))
    return F.adaptive_avg_pool2d(masked_depth[:, None].float(), size)[:, 0]


class NearestIndex:
    """Depth thumbnails of training views and what to retrieve for each.

    ``thumbs`` (V, T, T) float; ``rotations`` (V, 3, 3) camera-to-object;
    ``shape_dirs`` (V,) folders holding ``surface_points.npz``.
    """

    kind = "nearest"

    def __init__(self, thumbs: torch.Tensor, rotations: torch.Tensor, shape_dirs: list[str], views: list[int]):
        if not (len(thumbs) == len(rotations) == len(shape_dirs) == len(views)) or len(thumbs) == 0:
            raise ValueError("NearestIndex: needs one thumbnail, rotation, shape folder and view per training view (≥ 1)")
        self.thumbs, self.rotations, self.shape_dirs, self.views = thumbs.float(), rotations.double(), list(shape_dirs), list(views)
        self._points: dict[str, np.ndarray] = {}

    def query(self, masked_depth: torch.Tensor) -> list[int]:
        """Index of the closest training view for each predicted masked depth (B, S, S)."""
        q = depth_thumbnail(masked_depth.detach().cpu(), self.thumbs.shape[-1]).flatten(1)
        return torch.cdist(q, self.thumbs.flatten(1)).argmin(dim=1).tolist()

    def object_points(self, i: int) -> np.ndarray:
        d = self.shape_dirs[i]
        if d not in self._points:
            with np.load(surface_points_path(d)) as z:
                self._points[d] = z["points"].astype(np.float32)
        return self._points[d]

    def view_points(self, i: int) -> torch.Tensor:
        """The retrieved shape's surface points (10k, 3) posed as it appears in training view ``i`` (view frame)."""
        pts = torch.from_numpy(self.object_points(i)).double()[None]
        return frame.object_to_view(pts, self.rotations[i][None])[0].float()

    def shape_id(self, i: int) -> str:
        return Path(self.shape_dirs[i]).name

    def save(self, path: str | os.PathLike, config: GenreConfig) -> Path:
        from safetensors.torch import save

        path = Path(path)
        meta = {"format": BASELINE_FORMAT, "kind": self.kind, "config": json.dumps(config.to_dict()),
                "shape_dirs": json.dumps(self.shape_dirs), "views": json.dumps(self.views)}
        return atomic_write_bytes(path, save({"thumbs": self.thumbs.contiguous(), "rotations": self.rotations.contiguous()}, metadata=meta))

    @classmethod
    def load(cls, path: str | os.PathLike) -> NearestIndex:
        from safetensors import safe_open

        path = Path(path)
        if not path.is_file():
            raise WeightsError(f"nearest-shape index not found: {path}")
        with safe_open(str(path), framework="pt", device="cpu") as f:
            meta = f.metadata() or {}
            if meta.get("format") != BASELINE_FORMAT or meta.get("kind") != cls.kind:
                raise WeightsError(f"{path}: not a nearest-shape index")
            return cls(f.get_tensor("thumbs"), f.get_tensor("rotations"), json.loads(meta["shape_dirs"]), json.loads(meta["views"]))


def build_nearest_index(views_root: str | os.PathLike, config: GenreConfig, shape_ids: set[str] | None = None, progress: bool = False) -> NearestIndex:
    """Thumbnails of the true masked depth of every training view under ``views_root`` (with surface points)."""
    from tqdm import tqdm

    refs = find_views(Path(views_root), shape_ids, surface_points=True)
    if not refs:
        raise FileNotFoundError(f"{views_root}: no training views with targets and surface points to index")
    thumbs, rots, dirs, views = [], [], [], []
    for r in tqdm(refs, desc="nearest index", unit="view", disable=not progress):
        meta = load_view_meta(r.shape_dir, r.view)
        with np.load(view_paths(r.shape_dir, r.view)["npz"]) as z:
            depth = torch.from_numpy(np.where(z["mask"] > 0.5, z["depth"], 0.0).astype(np.float32))
        thumbs.append(depth_thumbnail(depth[None])[0])
        rots.append(torch.tensor(meta["rotation_cam_to_obj"], dtype=torch.float64))
        dirs.append(str(r.shape_dir.resolve()))
        views.append(r.view)
    return NearestIndex(torch.stack(thumbs), torch.stack(rots), dirs, views)


def main(argv: list[str] | None = None) -> int:
    """``python -m training.learn.baselines share-depth --completion IN --weights W --out OUT``."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m training.learn.baselines",
                                     description="Give a 3D Completion baseline GenRe's depth net (share_depth_net).")
    sub = parser.add_subparsers(dest="command", required=True)
    share = sub.add_parser("share-depth", help="write the baseline with the depth net of GenRe's weights")
    share.add_argument("--completion", required=True, help="3D Completion weights (RUN/completion/best.safetensors)")
    add_weights(share, required=True, help="GenRe weights whose depth net the baseline takes")
    add_out(share, required=True, help="the baseline file to write")
    args = parser.parse_args(argv)
    try:
        print(share_depth_net(args.completion, args.weights, args.out))
    except (WeightsError, FileNotFoundError) as exc:
        print(f"{parser.prog}: error: {exc}")
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
