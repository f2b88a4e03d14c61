"""``genre train burst``: train the inpainting net and the refiner on a lent GPU for a wall-clock budget.

A burst is what runs on the device machine (``scripts/gpu_burst.sh``, its
Python: torch, numpy, safetensors; no Blender, no trimesh).  It reads a
training pack (:mod:`training.data.pack`: the training shapes' meshes) and
makes every sample itself, on the GPU (:class:`ViewMaker`):

* a random view (azimuth uniform, elevation in the recipe's range, up to
  near-vertical: photos are often taken from above),
* the true planar depth map and mask of the posed mesh (:func:`genre_backend.geometry.raster.mesh_depth`),
  with a smooth random error added (``depth_noise``: the depth net's output is
  not exact),
* the true full spherical map (:func:`genre_backend.geometry.spherical.raycast_triangles`),
* the refiner's truncated-distance target, resampled from the shape's
  object-frame distance grid (made once per shape at start-up, ``grid_factor``
  times finer than the voxel grid, exact point–triangle distances).

The inpainting net and the refiner then train together as in the joint
stage (the spherical loss plus the voxel loss, :mod:`training.learn.losses`),
from the partial map of that depth; the depth net is kept as ``--init`` has
it (photos need RGB renders, which a burst does not have).  Device bring-up:
TF32, bf16 autocast for the nets, channels-last 2D and 3D tensors, the batch
the recipe names (halved on running out of memory).  No data loader is
needed: the samples are made where they are used.

Every ``--checkpoint-minutes`` (default 1) and at the end, the model's
weights are written as safetensors shards of at most 16 MiB
(:func:`write_shards`) into ``--out``, so that a call cut off still returns
weights; :func:`read_shards` (``genre train burst --join DIR --save FILE``)
turns them back into a weights file bit for bit.  ``log.csv`` holds the loss
curve, ``loss.png`` draws it, and the index's ``meta.summary`` the figures
(steps/s, samples/s, the device): with the ``wide`` model's two shards
that is 5 files of the 8 a device call brings back.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import hashlib
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from genre_backend.config import GenreConfig, get_preset
from genre_backend.frame import camera_rotation
from genre_backend.geometry.mesh_voxels import dilate, surface_lattice
from genre_backend.geometry.triangle_distance import near_surface_distance
from genre_backend.geometry.raster import mesh_depth
from genre_backend.geometry.spherical import crop_sph, pad_sph, raycast_triangles
from genre_backend.nets.model import GenRe, load_model, save_model
from genre_backend.arguments import add_device, add_out, add_seed

from ..data.pack import Pack, read_pack
from .losses import sph_loss, voxel_loss
from .recipe import BURST_RECIPES, BurstRecipe, get_burst_recipe

__all__ = ["BurstSpec", "Speed", "WAYS", "ViewMaker", "cached_distance_grid", "object_distance_grid", "widen", "write_shards", "read_shards", "run_burst", "main"]

SHARD_BYTES = 16 * 2**20 - 2**16  # a file from the device comes back if it is at most 16 MiB (64 KiB for the header)
INDEX_FILE = "weights.index.json"


@dataclass(frozen=True)
class BurstSpec:
    """One burst: what it reads, where it writes, how long it runs."""

    pack: str
    init: str
    out: str
    recipe: str = "wide"
    minutes: float = 7.0
    batch_size: int | None = None  # None: the recipe's
    device: str = "auto"
    seed: int = 0
    checkpoint_minutes: float = 1.0
    log_every: int = 20
    max_steps: int | None = None  # stop after this many steps too (tests, smoke runs)
    shapes: int | None = None  # only the first K shapes of the pack (tests, smoke runs)

    def __post_init__(self):
        get_burst_recipe(self.recipe)
        if not (math.isfinite(self.minutes) and self.minutes > 0):
            raise ValueError(f"minutes: expected a positive number, got {self.minutes!r}")
        if not (math.isfinite(self.checkpoint_minutes) and self.checkpoint_minutes > 0):
            raise ValueError(f"checkpoint_minutes: expected a positive number, got {self.checkpoint_minutes!r}")
        for name in ("batch_size", "max_steps", "shapes"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
                raise ValueError(f"{name}: expected a positive int, got {v!r}")


# --------------------------------------------------------------------------- samples made on the device


def object_distance_grid(vertices: torch.Tensor, faces: torch.Tensor, geometry, factor: int, exact: str = "auto") -> torch.Tensor:
    """A shape's truncated-distance target in the object frame: (R, R, R) uint8 (value × 255).

    R = ``factor`` × ``geometry.voxel_size``, over the cube [-E, E]³ with
    E = 0.5 + (band + 1)/N (a posed shape's band can reach past the unit
    cube's faces).  The value at a centre is ``clip(1 − d·N/band, 0, 1)``, d its
    exact distance to the mesh, measured only near the surface (the surface
    lattice's voxels, dilated past the band): by ``exact`` = ``"torch"``
    (:func:`near_surface_distance`, any device) or ``"igl"`` (libigl's AABB
    tree, CPU); ``"auto"``: igl on the CPU, torch elsewhere.
    """
    n, band = geometry.voxel_size, geometry.distance_band
    r = factor * n
    extent = 0.5 + (band + 1.0) / n
    out = torch.zeros((r, r, r), dtype=torch.uint8, device=vertices.device)
    if faces.shape[0] == 0:
        return out
    # the lattice at a spacing of half a grid voxel (2E/R): surface_lattice spaces points ≤ 1/(2·res) apart
    pts = surface_lattice(vertices.double(), faces, max(1, int(math.ceil(r / (2.0 * extent)))))
    idx = torch.floor((pts + extent) / (2 * extent) * r).long().clamp(0, r - 1)
    occ = torch.zeros(r**3, dtype=torch.bool, device=vertices.device)
    occ[(idx[:, 0] * r + idx[:, 1]) * r + idx[:, 2]] = True
    reach = int(math.ceil(band / n * r / (2 * extent))) + 1
    cand = torch.nonzero(dilate(occ.view(r, r, r), reach))
    centres = (cand.to(vertices.dtype) + 0.5) * (2 * extent / r) - extent
    if exact == "igl" or (exact == "auto" and vertices.device.type == "cpu"):
        # libigl's AABB tree: the same exact distances, ~100x faster than the pair tests on a CPU
        import igl
        import numpy as np

        sq, _, _ = igl.point_mesh_squared_distance(centres.detach().cpu().double().numpy(),
                                                   vertices.detach().cpu().double().numpy(),
                                                   faces.detach().cpu().long().numpy())
        d = torch.from_numpy(np.sqrt(np.maximum(sq, 0.0))).to(device=vertices.device, dtype=centres.dtype)
    else:
        d = near_surface_distance(centres, vertices[faces.long()], band / n)
    value = (1.0 - d * n / band).clamp(0.0, 1.0)
    out[tuple(cand.T)] = torch.round(value * 255.0).to(torch.uint8)
    return out


def cached_distance_grid(cache: str | os.PathLike | None, pack: Pack, i: int, vertices: torch.Tensor,
                         faces: torch.Tensor, geometry, factor: int) -> torch.Tensor:
    """:func:`object_distance_grid` of the pack's shape ``i``, read from ``cache`` when it holds it, else made and
    written there (``<cache>/<pack sha256[:16]>-N<voxels>-b<band>-x<factor>/<i>.npz``, compressed: a grid is
    nearly all zeros).  The key names everything the grid depends on, so a new pack or geometry never reads a
    stale grid.  ``cache`` None: always made."""
    import numpy as np

    if cache is None:
        return object_distance_grid(vertices, faces, geometry, factor)
    folder = Path(cache) / (f"{str(pack.meta.get('meshes_sha256', 'nosha'))[:16]}-N{geometry.voxel_size}"
                            f"-b{geometry.distance_band:g}-x{factor}")
    path = folder / f"{i:05d}.npz"
    try:
        with np.load(path) as z:
            return torch.from_numpy(z["grid"]).to(vertices.device)
    except (OSError, ValueError, KeyError):
        pass
    grid = object_distance_grid(vertices, faces, geometry, factor)
    folder.mkdir(parents=True, exist_ok=True)
    tmp = folder / f".{i:05d}.{os.getpid()}.tmp.npz"
    np.savez_compressed(tmp, grid=grid.cpu().numpy())
    os.replace(tmp, path)
    return grid


class ViewMaker:
    """Training samples of a pack's shapes from random views, made on one device (see the module doc).

    ``voxels``: make the refiner's target too (each shape's distance grid, built
    at set-up); False for the inpainting net alone, which needs no grid and starts
    at once.  ``grid_cache``: a folder where each shape's grid is kept
    (:func:`cached_distance_grid`), so that only the first set-up on a machine
    pays for them.
    """

    def __init__(self, pack: Pack, config: GenreConfig, device: torch.device, grid_factor: int = 2,
                 shapes: int | None = None, progress=None, voxels: bool = True, grid_cache: str | os.PathLike | None = None,
                 targets: str = "grid"):
        if targets not in ("grid", "exact"):
            raise ValueError(f"targets: expected 'grid' or 'exact', got {targets!r}")
        self.config, self.device, self.targets = config, device, targets
        self.voxels = voxels
        g = config.geometry
        if voxels and g.target != "distance":
            raise ValueError(f"a burst trains the distance target; the weights' target is {g.target!r}")
        count = len(pack) if shapes is None else min(shapes, len(pack))
        tris, offsets, grids = [], [0], []
        start = time.time()
        for i in range(count):
            v, f = pack.mesh(i)
            v = torch.from_numpy(v).to(device)
            f = torch.from_numpy(f).to(device)
            tris.append(v[f])
            offsets.append(offsets[-1] + f.shape[0])
            if voxels and targets == "grid":
                grids.append(cached_distance_grid(grid_cache, pack, i, v, f, g, grid_factor))
            if progress and grids and ((i + 1) % 100 == 0 or i + 1 == count):
                progress(f"distance grids: {i + 1}/{count} shapes, {time.time() - start:.0f} s")
        self.triangles = torch.cat(tris)  # (F, 3, 3) object frame
        self.offsets = torch.tensor(offsets, dtype=torch.int64, device=device)
        self.grids = torch.stack(grids) if grids else None  # (K, R, R, R) uint8
        self.extent = 0.5 + (g.distance_band + 1.0) / g.voxel_size
        n = g.voxel_size
        c = (torch.arange(n, dtype=torch.float32, device=device) + 0.5) / n - 0.5
        self.centres = torch.stack(torch.meshgrid(c, c, c, indexing="ij"), dim=-1).reshape(-1, 3)  # [ix, iy, iz]
        self.ids = pack.ids[:count]

    def __len__(self) -> int:
        return len(self.ids)

    def draw(self, gen: torch.Generator, batch: int, recipe: BurstRecipe) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Shape indices (B,), azimuths and elevations (B,) in degrees, drawn from ``gen`` (a CPU generator)."""
        shape = torch.randint(len(self), (batch,), generator=gen)
        az = torch.rand(batch, generator=gen) * 360.0
        el = recipe.elevation_min_deg + torch.rand(batch, generator=gen) * (recipe.elevation_max_deg - recipe.elevation_min_deg)
        return shape, az, el

    def make(self, shape: torch.Tensor, az: torch.Tensor, el: torch.Tensor, depth_noise: float = 0.0,
             gen: torch.Generator | None = None) -> dict[str, torch.Tensor]:
        """The samples of shapes ``shape`` (B,) seen from (``az``, ``el``) (B,) degrees.

        Returns ``depth`` (B, S, S) planar depth with the noise added inside
        the mask (background 0), ``true_depth``, ``mask`` (B, S, S) bool,
        ``full_sph`` (B, H, H) and, when the maker has grids, ``voxels`` (B, N, N, N) float in [0, 1].
        """
        g, cam, dev = self.config.geometry, self.config.camera, self.device
        b = shape.shape[0]
        rot = camera_rotation(az, el).to(dev)  # (B, 3, 3) camera-to-object
        lo, hi = self.offsets[shape.to(dev)], self.offsets[shape.to(dev) + 1]
        counts = hi - lo
        batch_index = torch.repeat_interleave(torch.arange(b, device=dev), counts)
        first = torch.cumsum(counts, 0) - counts
        within = torch.arange(int(counts.sum()), device=dev) - torch.repeat_interleave(first, counts)
        tris = self.triangles[torch.repeat_interleave(lo, counts) + within]  # (T, 3, 3) object frame
        tris = torch.einsum("tkc,tcd->tkd", tris, rot[batch_index])  # object_to_view: p @ R
        true_depth = mesh_depth(tris, batch_index, b, cam, g.image_size)
        mask = true_depth > 0
        depth = true_depth
        if depth_noise > 0:
            noise = torch.randn((b, 1, 4, 4), generator=gen).to(dev) * depth_noise
            noise = torch.nn.functional.interpolate(noise, size=(g.image_size,) * 2, mode="bicubic", align_corners=False)[:, 0]
            depth = torch.where(mask, true_depth + noise, true_depth)
        full_sph = raycast_triangles(tris, batch_index, b, g.sph_size)
        sample = {"depth": depth, "true_depth": true_depth, "mask": mask, "full_sph": full_sph}
        if not self.voxels:
            return sample
        if self.targets == "exact":
            from genre_backend.geometry.mesh_voxels import mesh_to_distance

            soup = torch.arange(3 * int(counts.max()), device=dev).view(-1, 3)
            vox = torch.stack([mesh_to_distance(tris[batch_index == k].reshape(-1, 3),
                                                soup[:int(counts[k])], g.voxel_size, g.distance_band)
                               for k in range(b)]).to(dev)
            return {**sample, "voxels": vox}
        # the view's voxel centres in the object frame (view_to_object: p @ Rᵀ), as grid_sample's (x=W, y=H, z=D)
        pts = torch.einsum("pc,bdc->bpd", self.centres, rot) / self.extent
        n = g.voxel_size
        grid = pts[..., [2, 1, 0]].reshape(b, n, n, n, 3)
        vox = torch.nn.functional.grid_sample(self.grids[shape.to(dev)][:, None].float(), grid, mode="bilinear",
                                              padding_mode="zeros", align_corners=False)[:, 0] / 255.0
        return {**sample, "voxels": vox}


# --------------------------------------------------------------------------- the model


def widen(model: GenRe, preset: str | None) -> tuple[GenRe, list[str]]:
    """``model`` with the inpainting net and refiner of ``preset`` (None: its own), its own depth net, geometry and camera;
    every tensor whose name and shape match is copied, the rest start afresh.  Returns the model and the
    names of the fresh tensors."""
    if preset is None:
        return model, []
    own = model.config.network  # the depth net is never trained by a burst: it stays the weights' own
    network = dataclasses.replace(get_preset(preset).network, depth_widths=own.depth_widths,
                                  depth_decoder_blocks=own.depth_decoder_blocks, depth_output_scale=own.depth_output_scale)
    config = dataclasses.replace(model.config, network=network)
    new = GenRe(config)
    old = model.state_dict()
    state = new.state_dict()
    fresh = []
    for k, v in state.items():
        if k in old and old[k].shape == v.shape:
            state[k] = old[k].clone()
        else:
            fresh.append(k)
    new.load_state_dict(state)
    return new, fresh


# --------------------------------------------------------------------------- shards


def write_shards(model: GenRe, out: str | os.PathLike, meta: dict, shard_bytes: int = SHARD_BYTES) -> list[Path]:
    """The model's state as safetensors shards of at most ``shard_bytes`` bytes of tensors (first-fit decreasing),
    plus ``weights.index.json``.

    A tensor larger than a shard is cut along its flattened length into parts
    (``name::k/n``).  The shards' names carry ``meta["step"]``; the index
    (config, ``meta``, each shard's sha256) is replaced last and the old set
    deleted after it, so a call cut off at any moment leaves a complete set
    that the index names.  Returns the shard paths.
    """
    from safetensors.torch import save_file

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    per_elem = {}
    items = []
    for name, t in model.state_dict().items():
        t = t.detach().cpu().contiguous()
        size = t.numel() * t.element_size()
        if size <= shard_bytes:
            items.append((name, t))
            continue
        flat, step = t.reshape(-1), max(1, shard_bytes // t.element_size())
        parts = [flat[i:i + step].clone() for i in range(0, flat.numel(), step)]
        per_elem[name] = list(t.shape)
        items += [(f"{name}::{k}/{len(parts)}", p) for k, p in enumerate(parts)]
    # first-fit decreasing: the fewest shards (a device call brings back 8 files at most)
    shards, used = [], []
    for name, t in sorted(items, key=lambda it: -it[1].numel() * it[1].element_size()):
        size = t.numel() * t.element_size()
        k = next((i for i, u in enumerate(used) if u + size <= shard_bytes), None)
        if k is None:
            shards.append({})
            used.append(0)
            k = len(shards) - 1
        shards[k][name] = t
        used[k] += size
    paths, digests = [], []
    tag = f"s{int(meta.get('step', 0)):07d}-"  # a new set never overwrites the set the index still names
    for k, tensors in enumerate(shards):
        path = out / f"weights-{tag}{k + 1:05d}-of-{len(shards):05d}.safetensors"
        tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
        save_file(tensors, str(tmp))
        os.replace(tmp, path)
        paths.append(path)
        digests.append(hashlib.sha256(path.read_bytes()).hexdigest())
    index = {"format": "genre-burst-shards/1", "config": model.config.to_dict(), "meta": meta,
             "split": per_elem, "shards": [{"file": p.name, "sha256": d} for p, d in zip(paths, digests)]}
    tmp = out / f".{INDEX_FILE}.tmp-{os.getpid()}"
    tmp.write_text(json.dumps(index, indent=1))
    os.replace(tmp, out / INDEX_FILE)
    for stale in out.glob("weights-*-of-*.safetensors"):  # only once the index names the new set
        if stale not in paths:
            stale.unlink()
    return paths


def read_shards(folder: str | os.PathLike, device: str = "cpu") -> tuple[GenRe, dict]:
    """The model written by :func:`write_shards` (each shard's sha256 checked) and the index's ``meta``."""
    from safetensors.torch import load_file

    folder = Path(folder)
    try:
        index = json.loads((folder / INDEX_FILE).read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{folder}: no readable {INDEX_FILE} ({exc})") from None
    if index.get("format") != "genre-burst-shards/1":
        raise ValueError(f"{folder}/{INDEX_FILE}: not a burst's shard index")
    tensors = {}
    for shard in index["shards"]:
        path = folder / shard["file"]
        if not path.is_file() or hashlib.sha256(path.read_bytes()).hexdigest() != shard["sha256"]:
            raise ValueError(f"{path}: missing or damaged (sha256 differs from the index)")
        tensors.update(load_file(str(path)))
    for name, shape in index.get("split", {}).items():
        parts = sorted((k for k in tensors if k.startswith(name + "::")), key=lambda k: int(k.rsplit("::", 1)[1].split("/")[0]))
        tensors[name] = torch.cat([tensors.pop(k) for k in parts]).reshape(shape)
    model = GenRe(GenreConfig.from_dict(index["config"]))
    model.load_state_dict(tensors, strict=True)
    return model.to(device).eval(), index.get("meta", {})


# --------------------------------------------------------------------------- the loop


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    steps = [r["step"] for r in rows]
    for key in ("loss", "voxel_bce", "sph"):
        ax.plot(steps, [r[key] for r in rows], label=key)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.legend()
    ax.set_title("GPU burst: training loss")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


@dataclass(frozen=True)
class Speed:
    """How each trained net runs: channels-last tensors and bf16 autocast, per net.

    Chosen per device by measurement (``genre bench train``): on CUDA every
    switch is on; on a CPU (:data:`CPU_SPEED`) channels-last for every net, and bf16 autocast where oneDNN runs
    bf16 natively (docs/lab/benchmarks.md).  Every switch off is the plain fp32 contiguous path, the reference the
    fast one is tested against.  ``genre train --speed WAY`` picks another (:meth:`from_way`).
    """

    inpaint_channels_last: bool = False
    inpaint_bf16: bool = False
    refiner_channels_last: bool = False
    refiner_bf16: bool = False
    # torch.compile of the refiner (in place: its state_dict keys stay). Measured on the quiet 2-core Xeon: 1.06x in
    # the refine stage, 0.99x joint (docs/lab/benchmarks.md), so CPU_SPEED leaves it off
    refiner_compile: bool = False
    depth_channels_last: bool = False  # the depth net (the stage trainer's depth and joint stages)
    depth_bf16: bool = False
    # Adam's update as one fused kernel over every tensor (``torch.optim.Adam(fused=True)``) instead of a Python loop
    # over the 313 weight tensors: 6x faster on the 2-core AVX2 EPYC (77 -> 13 ms a step, ~4 % of a joint step)
    fused_adam: bool = False

    @classmethod
    def for_device(cls, device: torch.device) -> Speed:
        return CUDA_SPEED if device.type == "cuda" else CPU_SPEED

    @classmethod
    def from_way(cls, way: str) -> Speed:
        """Every net run one of ``genre bench train``'s ways (:data:`WAYS`)."""
        if way not in WAYS:
            raise ValueError(f"speed: one of {', '.join(WAYS)}, got {way!r}")
        cl, bf16, compiled = WAYS[way]
        return cls(inpaint_channels_last=cl, inpaint_bf16=bf16, refiner_channels_last=cl, refiner_bf16=bf16,
                   refiner_compile=compiled, depth_channels_last=cl, depth_bf16=bf16, fused_adam=way != "fp32")

    def optimiser(self, params, lr: float, betas: tuple[float, float] = (0.9, 0.999),
                  weight_decay: float = 0.0) -> torch.optim.Adam:
        """Adam; with a weight decay, decoupled as in AdamW (the weights shrink by lr × weight_decay a step, apart
        from the gradient's moments); fused where :attr:`fused_adam` says (the same update to float rounding)."""
        opt = torch.optim.Adam(params, lr=lr, betas=betas, weight_decay=weight_decay,
                               decoupled_weight_decay=weight_decay > 0, fused=self.fused_adam or None)
        if self.fused_adam:
            opt.register_step_pre_hook(_layouts_of_the_weights)
        return opt

    def autocast(self, net: str, device: torch.device) -> torch.autocast:
        """bf16 autocast for ``net`` ("depth", "inpaint" or "refiner") where this speed has it on."""
        return torch.autocast(device.type, dtype=torch.bfloat16, enabled=getattr(self, f"{net}_bf16"))


def _layouts_of_the_weights(opt: torch.optim.Optimizer, args, kwargs) -> None:
    """Give each weight's gradient and moments the weight's own memory layout before a fused Adam step.  torch
    2.13's fused CPU kernel pairs a weight's numbers with its gradient's and moments' by memory offset and never
    checks their strides (CUDA's refuses a mismatch): a channels-last weight beside moments restored contiguous from
    a checkpoint got scrambled updates (``test_a_checkpoint_of_either_adam_resumes_...``).  Checking is ~1 ms a step;
    a copy happens only where the layouts differ."""
    for group in opt.param_groups:
        for p in group["params"]:
            if p.grad is not None and p.grad.stride() != p.stride():
                p.grad = torch.empty_like(p).copy_(p.grad)
            state = opt.state.get(p)
            for k, v in (state or {}).items():
                if torch.is_tensor(v) and v.shape == p.shape and v.stride() != p.stride():
                    state[k] = torch.empty_like(p, dtype=v.dtype).copy_(v)


# way → (channels-last, bf16 autocast, the refiner compiled with torch.compile), for every net alike
WAYS = {"fp32": (False, False, False), "channels-last": (True, False, False), "bf16": (False, True, False),
        "channels-last+bf16": (True, True, False), "channels-last+compile": (True, False, True)}


def _cpu_speed() -> Speed:
    """The CPU's record (``genre bench train``, docs/lab/benchmarks.md). Channels-last wins for every net on every
    CPU measured. bf16 autocast: on an AMD EPYC with native oneDNN bf16 (AVX-512-BF16), 2 threads, batch 16, each net
    faster with it than without (joint 1.42x over channels-last alone); where oneDNN emulates bf16 (an AVX2 EPYC) it
    is off. (On the AVX-512/AMX Xeon of the first sessions bf16 measured slower, but only on a loaded machine.)"""
    native = bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())
    return Speed.from_way("channels-last+bf16" if native else "channels-last")


REFERENCE_SPEED = Speed()
CUDA_SPEED = Speed.from_way("channels-last+bf16")
CPU_SPEED = _cpu_speed()


def _step_loss(model: GenRe, sample: dict, recipe: BurstRecipe, amp: bool | None = None, channels_last: bool | None = None,
               speed: Speed | None = None, refiner: bool = True) -> tuple[torch.Tensor, dict]:
    """One step's loss: the partial map (``sample["partial"]``, else made) and depth voxels of ``sample["depth"]``
    (no gradient), the inpainting net
    and (``refiner``) the refiner, run as ``speed`` says (default: :meth:`Speed.for_device`; ``amp`` and
    ``channels_last``, when given, set both nets' switches); the voxel loss plus ``sph_weight`` × the spherical
    loss, or the spherical loss alone without the refiner.  Returns (loss, {term: value})."""
    g = model.config.geometry
    device = sample["full_sph"].device
    speed = speed or Speed.for_device(device)
    if amp is not None:
        speed = dataclasses.replace(speed, inpaint_bf16=amp, refiner_bf16=amp)
    if channels_last is not None:
        speed = dataclasses.replace(speed, inpaint_channels_last=channels_last, refiner_channels_last=channels_last)
    with torch.no_grad():
        partial = sample["partial"] if "partial" in sample else model.partial_sph(sample["depth"])
    with speed.autocast("inpaint", device):
        padded = pad_sph(partial[:, None], g.sph_pad)
        if speed.inpaint_channels_last:
            padded = padded.contiguous(memory_format=torch.channels_last)
        parts = model.inpaint_net.forward_parts(padded)
    parts = {k: v.float() for k, v in parts.items()}
    l_sph, terms = sph_loss(parts, sample["full_sph"], g, recipe.sph_loss)
    if not refiner:
        return l_sph, {**terms, "sph": l_sph}
    with torch.no_grad():
        vox_depth = model.depth_voxels(sample["depth"])
    full = crop_sph(parts["map"], g.sph_pad)[:, 0]
    if "teacher" in sample:  # (B,) bool: these samples feed the refiner the true full map
        full = torch.where(sample["teacher"][:, None, None], sample["full_sph"], full)
    vox_sph = model.sph_voxels(full)
    with speed.autocast("refiner", device):
        x = torch.cat([vox_sph, vox_depth], dim=1)
        if speed.refiner_channels_last:
            x = x.contiguous(memory_format=torch.channels_last_3d)
        logits = model.refiner(x)
    l_vox, vox_terms = voxel_loss(logits.float(), sample["voxels"], recipe.surface_weight)
    terms.update(vox_terms)
    terms["sph"] = l_sph
    return l_vox + recipe.sph_weight * l_sph, terms


def apply_speed(model: GenRe, speed: Speed) -> GenRe:
    """The nets' parameters in the memory format ``speed`` names (channels-last 2D / 3D); the refiner compiled if it says."""
    if speed.inpaint_channels_last:
        model.inpaint_net.to(memory_format=torch.channels_last)
    if speed.refiner_channels_last:
        model.refiner.to(memory_format=torch.channels_last_3d)
    if speed.depth_channels_last:
        model.depth_net.to(memory_format=torch.channels_last)
    if speed.refiner_compile:
        model.refiner.compile()
    return model


def _bring_up(spec: BurstSpec, recipe: BurstRecipe, say) -> tuple[torch.device, GenRe, ViewMaker]:
    """The device (TF32 on CUDA), the model (widened to the recipe's preset, channels-last on CUDA) and the samples."""
    t0 = time.time()
    device = _device(spec.device)
    if device.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
        torch.backends.cudnn.benchmark = True
        say(f"device: {torch.cuda.get_device_name(device)}, torch {torch.__version__}")
    else:
        say(f"device: cpu ({torch.get_num_threads()} threads), torch {torch.__version__}")
    pack = read_pack(spec.pack)
    model, fresh = widen(load_model(spec.init), recipe.preset)
    say(f"model: {sum(p.numel() for p in model.parameters()):,} parameters; "
        f"{len(fresh)} tensors fresh (recipe {recipe.name}), the rest from {spec.init}")
    model = apply_speed(model.to(device), Speed.for_device(device))
    maker = ViewMaker(pack, model.config, device, recipe.grid_factor, spec.shapes, progress=say)
    say(f"pack: {len(maker)} shapes, {maker.triangles.shape[0]:,} triangles; set-up {time.time() - t0:.0f} s")
    return device, model, maker


def _lr(recipe: BurstRecipe, since: float, fraction: float) -> float:
    """The learning rate ``since`` seconds into training, ``fraction`` of the way through the budget."""
    warm = min(1.0, since / recipe.warmup_s) if recipe.warmup_s > 0 else 1.0
    cosine = 0.5 * (1 + math.cos(math.pi * min(fraction, 1.0)))
    return recipe.lr * warm * (recipe.lr_final + (1 - recipe.lr_final) * cosine)


def _write_outputs(out: Path, model: GenRe, rows: list[dict], meta: dict) -> None:
    """The shards (with ``meta``), log.csv and loss.png."""
    write_shards(model, out, meta)
    with open(out / "log.csv", "w", newline="") as fh:
        if rows:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    if rows:
        _plot(rows, out / "loss.png")


def run_burst(spec: BurstSpec, say=print) -> dict:
    """Run one burst; returns the summary (also in ``OUT/weights.index.json``'s ``meta``)."""
    t0 = time.time()
    deadline = t0 + spec.minutes * 60.0
    recipe = get_burst_recipe(spec.recipe)
    out = Path(spec.out)
    out.mkdir(parents=True, exist_ok=True)
    device, model, maker = _bring_up(spec, recipe, say)
    cuda = device.type == "cuda"
    for p in model.depth_net.parameters():
        p.requires_grad_(False)
    params = [p for net in (model.inpaint_net, model.refiner) for p in net.parameters()]
    opt = Speed.for_device(device).optimiser(params, recipe.lr, (recipe.beta1, recipe.beta2), recipe.weight_decay)
    model.train()
    model.depth_net.eval()
    gen = torch.Generator().manual_seed(spec.seed)
    batch = spec.batch_size or recipe.batch_size
    rows, step, samples = [], 0, 0
    train_start = last_ck = time.time()
    budget = max(deadline - train_start, 1e-3)

    def meta(final: bool) -> dict:
        return {"step": step, "samples": samples, "recipe": recipe.name, "init": str(spec.init), "pack_shapes": len(maker),
                "seconds": round(time.time() - t0, 1), "device": str(device), "final": final, "model": "burst"}

    while time.time() < deadline and (spec.max_steps is None or step < spec.max_steps):
        lr = _lr(recipe, time.time() - train_start, (time.time() - train_start) / budget)
        for group in opt.param_groups:
            group["lr"] = lr
        shape, az, el = maker.draw(gen, batch, recipe)
        try:
            loss, terms = _step_loss(model, maker.make(shape, az, el, recipe.depth_noise, gen), recipe)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        except torch.OutOfMemoryError:
            if batch == 1:
                raise
            batch //= 2
            opt.zero_grad(set_to_none=True)
            torch.cuda.empty_cache()
            say(f"out of memory: batch {batch}")
            continue
        step, samples = step + 1, samples + batch
        if step % spec.log_every == 0 or step == 1:
            elapsed = time.time() - train_start
            rows.append({"step": step, "seconds": round(time.time() - t0, 1), "lr": lr, "batch": batch,
                         "loss": float(loss.detach()), **{k: float(v.detach()) for k, v in terms.items()}})
            say(f"step {step:6d}  loss {rows[-1]['loss']:.4f}  voxel {rows[-1]['voxel_bce']:.4f}  sph {rows[-1]['sph']:.4f}  "
                f"{step / elapsed:.2f} steps/s  {samples / elapsed:.0f} samples/s  lr {lr:.2e}")
        if time.time() - last_ck >= spec.checkpoint_minutes * 60.0:
            _write_outputs(out, model, rows, meta(False))
            last_ck = time.time()
            say(f"checkpoint: step {step}, {out}")
    elapsed = time.time() - train_start
    summary = {"device": torch.cuda.get_device_name(device) if cuda else f"cpu ({torch.get_num_threads()} threads)",
               "steps": step, "samples": samples, "batch": batch, "train_seconds": round(elapsed, 1),
               "setup_seconds": round(train_start - t0, 1), "steps_per_s": step / max(elapsed, 1e-9),
               "samples_per_s": samples / max(elapsed, 1e-9), "recipe": recipe.name, "init": str(spec.init),
               "pack": str(spec.pack), "pack_shapes": len(maker), "last_loss": rows[-1]["loss"] if rows else None,
               "parameters": sum(p.numel() for p in model.parameters())}
    # (the summary travels in the index: a device call brings back 8 files at most)
    _write_outputs(out, model, rows, {**meta(True), "summary": summary})
    say(f"done: {step} steps in {elapsed:.0f} s ({summary['steps_per_s']:.2f} steps/s, "
        f"{summary['samples_per_s']:.0f} samples/s); weights in {out}")
    return summary


def main(argv: list[str] | None = None, prog: str = "genre train burst") -> int:
    parser = argparse.ArgumentParser(prog=prog, description="Train the inpainting net and the refiner on a GPU for a "
                                     "wall-clock budget, from a training pack (see training/learn/burst.py).")
    parser.add_argument("--pack", help="a training pack folder (genre data pack)")
    parser.add_argument("--init", help="weights to start from (e.g. genre_backend/weights/default.safetensors)")
    add_out(parser, help="the folder for the shards, their index, log.csv and loss.png ($OUT/burst)")
    parser.add_argument("--recipe", default="wide", choices=sorted(BURST_RECIPES), help="the burst recipe (default wide)")
    parser.add_argument("--minutes", type=float, default=7.0, help="wall-clock budget, set-up included (default 7)")
    parser.add_argument("--batch-size", type=int, default=None, help="override the recipe's batch")
    add_device(parser, default="auto", help="cuda, cpu or auto (default)")
    add_seed(parser)
    parser.add_argument("--checkpoint-minutes", type=float, default=1.0)
    parser.add_argument("--log-every", type=int, default=20)
    parser.add_argument("--max-steps", type=int, default=None, help="stop after this many steps as well")
    parser.add_argument("--shapes", type=int, default=None, help="only the first K shapes of the pack")
    parser.add_argument("--join", metavar="DIR", help="instead of training: join the shards in DIR into --save")
    parser.add_argument("--save", metavar="FILE", help="with --join: the weights file to write (float32)")
    args = parser.parse_args(argv)
    if args.join:
        if not args.save:
            parser.error("--join needs --save FILE")
        try:
            model, meta = read_shards(args.join)
        except ValueError as exc:
            print(f"{prog}: {exc}", file=sys.stderr)
            return 1
        save_model(model, args.save, {"burst": meta, "source": str(args.join)})
        print(f"wrote {args.save} from {args.join} (step {meta.get('step')}, recipe {meta.get('recipe')})")
        return 0
    if not (args.pack and args.init and args.out):
        parser.error("--pack, --init and --out are required")
    try:
        spec = BurstSpec(pack=args.pack, init=args.init, out=args.out, recipe=args.recipe, minutes=args.minutes,
                         batch_size=args.batch_size, device=args.device, seed=args.seed,
                         checkpoint_minutes=args.checkpoint_minutes, log_every=args.log_every,
                         max_steps=args.max_steps, shapes=args.shapes)
    except ValueError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 1
    return run_command(prog, lambda: run_burst(spec, say=lambda m: print(m, flush=True)))


def run_command(prog: str, work) -> int:
    """Run ``work()``; a ValueError or FileNotFoundError (bad input: a pack, weights, a spec) is one line on stderr
    and exit status 1."""
    try:
        work()
    except (ValueError, FileNotFoundError) as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
