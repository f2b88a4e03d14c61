"""The full GenRe model: three networks joined by the differentiable projections.

``rgb → DepthNet → (depth, silhouette) → depth_to_sph → InpaintNet →
sph_to_voxels ⊕ depth → voxels → VoxelRefiner → surface-shell logits``

Every projection is the differentiable one from the geometry core, so a 3D
loss on the logits reaches the depth net (joint fine-tuning).

Weights are stored as one safetensors file whose metadata carries the
resolved config and a format version (no pickle); :func:`save_model` also
writes the config beside it as JSON for people to read.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import torch
from torch import nn

from ..config import GenreConfig
from .depth_net import DepthNet
from ..frame import depth_to_points
from .inpaint_net import InpaintNet
from .outputs import NetOutputs
from .refiner import VoxelRefiner
from ..geometry.spherical import depth_to_sph, mirror_sph, sph_to_voxels
from ..validation import check_tensor
from ..geometry.voxels import mirror_voxels, points_to_voxels
from ..weights_file import (INT8_SCALE_SUFFIX, STORAGES, WeightsError, check_state, pack_int8, read_weights, save_weights,
                            stored_config)

__all__ = ["GenRe", "mirror_averaged", "mean_probability_logits", "grow_refiner", "with_inpaint_net", "with_inpaint_net_of", "with_depth_net_of", "save_model", "load_model", "WEIGHTS_FORMAT", "WeightsError", "MAX_PARAMETERS"]

WEIGHTS_FORMAT = "genre-weights/1"


class GenRe(nn.Module):
    def __init__(self, config: GenreConfig):
        super().__init__()
        self.config = config
        g = config.geometry
        self.depth_net = DepthNet(config)
        self.inpaint_net = InpaintNet(config)
        n = config.network
        self.refiner = VoxelRefiner(g.voxel_size, n.refiner_nf, n.refiner_fc, n.refiner_full_nf, n.refiner_max_width)

    # -- the projections between the networks --------------------------------------------
    def masked_depth(self, depth: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Depth (B, S, S) with background (mask False) set to 0."""
        return torch.where(mask, depth, torch.zeros_like(depth))

    def partial_sph(self, depth: torch.Tensor) -> torch.Tensor:
        """Masked depth (B, S, S) → partial spherical maps (B, H, H)."""
        g = self.config.geometry
        return depth_to_sph(depth, self.config.camera, g.sph_size, g.depth_edge_max_ratio)

    def full_sph(self, partial: torch.Tensor) -> torch.Tensor:
        """Partial spherical maps (B, H, H) → full ones: the inpainting net's, its seen side the partial map's own
        where the weights say so (``geometry.sph_keep_seen``)."""
        full = self.inpaint_net(partial)
        if self.config.geometry.sph_keep_seen:
            full = torch.where(partial < self.config.geometry.sph_nohit_min, partial, full)
        return full

    def depth_voxels(self, depth: torch.Tensor) -> torch.Tensor:
        """Masked depth (B, S, S) → voxels (B, 1, N, N, N) by the paper's rule."""
        pts = depth_to_points(depth, self.config.camera).flatten(1, 2)
        return points_to_voxels(pts, self.config.geometry.voxel_size, (depth > 0).flatten(1))

    def sph_voxels(self, sph: torch.Tensor) -> torch.Tensor:
        """Full spherical maps (B, H, H) → voxels (B, 1, N, N, N)."""
        g = self.config.geometry
        return sph_to_voxels(sph, g.voxel_size, g.sph_nohit_min, g.sph_supersample)

    def refine(self, vox_sph: torch.Tensor, vox_depth: torch.Tensor) -> torch.Tensor:
        return self.refiner(torch.cat([vox_sph, vox_depth], dim=1))

    # -- the whole pipeline -----------------------------------------------------------------
    def forward(self, rgb: torch.Tensor, mask: torch.Tensor | None = None, depth: torch.Tensor | None = None,
                full_sph: torch.Tensor | None = None, mirror: bool = False) -> NetOutputs:
        """Run the pipeline; every intermediate is returned (:class:`.outputs.NetOutputs`).

        rgb: (B, 3, S, S) in [0, 1].  mask: (B, S, S) bool, optional (else the
        depth net's silhouette > 0.5).  ``depth`` (B, S, S) or ``full_sph``
        (B, H, H) replace the depth net's or the inpainting net's output (the
        oracle variants).  ``mirror``: ``logits`` are :func:`mirror_averaged`'s
        (the view and its mirror image; ``geometry.test_time_mirror``); the
        other intermediates are the view's own.
        """
        s = self.config.geometry.image_size
        check_tensor("rgb", rgb, ("B", 3, s, s))
        net = self.depth_net(rgb)
        if mask is None:
            mask = net["silhouette_logits"] > 0
        planar = net["depth"] if depth is None else depth
        masked = self.masked_depth(planar, mask)
        partial = self.partial_sph(masked)
        full = self.full_sph(partial) if full_sph is None else full_sph
        vox_sph, vox_depth = self.sph_voxels(full), self.depth_voxels(masked)
        logits = self.refine(vox_sph, vox_depth)
        if mirror:
            logits = mirror_averaged(lambda r, k, d, s: self.forward(r, k, d, s).logits, rgb, mask, depth, full_sph,
                                     logits=logits)
        return NetOutputs(depth=planar, silhouette_logits=net["silhouette_logits"], mask=mask, masked_depth=masked,
                          partial_sph=partial, full_sph=full, vox_sph=vox_sph, vox_depth=vox_depth, logits=logits)


def mean_probability_logits(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Logits whose sigmoid is the mean of ``sigmoid(a)`` and ``sigmoid(b)`` (same shapes), finite wherever both are.

    Computed in log space (``log p − log(1 − p)`` with each term a log-sum-exp
    of log-sigmoids), so that confident logits do not round to a probability of
    exactly 0 or 1.
    """
    if a.shape != b.shape:
        raise ValueError(f"logits of different shapes: {tuple(a.shape)} and {tuple(b.shape)}")
    f = torch.nn.functional.logsigmoid
    return torch.logaddexp(f(a), f(b)) - torch.logaddexp(f(-a), f(-b))


def mirror_averaged(predict, rgb: torch.Tensor, mask: torch.Tensor | None = None, depth: torch.Tensor | None = None,
                    full_sph: torch.Tensor | None = None, logits: torch.Tensor | None = None) -> torch.Tensor:
    """Voxel logits (B, 1, N, N, N) of a view and of its mirror image, averaged as probabilities.

    ``predict(rgb, mask, depth, full_sph)`` → logits (B, 1, N, N, N) is any
    row's model (``None`` inputs are passed as ``None``).  The mirror image is
    the scene reflected in the view frame's x = 0 plane: ``rgb`` (B, 3, S, S),
    ``mask`` and ``depth`` (B, S, S) flip their columns, ``full_sph`` (B, H, H)
    is :func:`~genre_backend.geometry.spherical.mirror_sph`'s; its logits are
    reflected back (:func:`~genre_backend.geometry.voxels.mirror_voxels`) and
    joined to the view's own (``logits``, computed when not given) by
    :func:`mean_probability_logits`.  A model that is itself symmetric under
    the reflection gets its own logits back.
    """
    def flip(x):
        return None if x is None else torch.flip(x, dims=(-1,))

    if logits is None:
        logits = predict(rgb, mask, depth, full_sph)
    mirrored = predict(flip(rgb), flip(mask), flip(depth), None if full_sph is None else mirror_sph(full_sph))
    return mean_probability_logits(logits, mirror_voxels(mirrored))


def grow_refiner(model: GenRe, full_nf: int) -> GenRe:
    """``model`` with a full-resolution refiner branch of ``full_nf`` channels added.

    The depth and inpainting nets and the rest of the refiner are copied; the
    new branch starts at zero output, so the grown model's logits equal
    ``model``'s.  A model that already has a branch of that width is returned
    as it is; one with a branch of another width is refused (ValueError).
    """
    have = model.config.network.refiner_full_nf
    if have == full_nf:
        return model
    if have:
        raise ValueError(f"the refiner already has a full-resolution branch of width {have}; cannot make it {full_nf}")
    config = dataclasses.replace(model.config, network=dataclasses.replace(model.config.network, refiner_full_nf=full_nf))
    grown = GenRe(config).to(next(model.parameters()).device)
    grown.depth_net.load_state_dict(model.depth_net.state_dict())
    grown.inpaint_net.load_state_dict(model.inpaint_net.state_dict())
    grown.refiner.load_grown(model.refiner.state_dict())
    return grown.train(model.training)


def with_inpaint_net(model: GenRe, *, head: str | None = None, widths: tuple[int, int, int, int] | None = None) -> GenRe:
    """``model`` with a freshly initialised inpainting net of ``head`` and ``widths`` (NetworkConfig).

    ``None`` keeps the model's value.  The depth net and the refiner are
    copied.  A model whose inpainting net already has that head and those
    widths is returned as it is.
    """
    net = model.config.network
    head = net.inpaint_head if head is None else head
    widths = tuple(net.inpaint_widths) if widths is None else tuple(int(w) for w in widths)
    if net.inpaint_head == head and tuple(net.inpaint_widths) == widths:
        return model
    config = dataclasses.replace(model.config, network=dataclasses.replace(net, inpaint_head=head, inpaint_widths=widths))
    new = GenRe(config).to(next(model.parameters()).device)
    new.depth_net.load_state_dict(model.depth_net.state_dict())
    new.refiner.load_state_dict(model.refiner.state_dict())
    return new.train(model.training)


def _with_net_of(model: GenRe, donor: GenRe, config: GenreConfig, part: str) -> GenRe:
    """A model of ``config`` holding ``donor``'s net ``part`` and ``model``'s other nets, on ``model``'s device and
    in its training mode."""
    new = GenRe(config).to(next(model.parameters()).device)
    for name in ("depth_net", "inpaint_net", "refiner"):
        getattr(new, name).load_state_dict(getattr(donor if name == part else model, name).state_dict())
    return new.train(model.training)


def with_inpaint_net_of(model: GenRe, donor: GenRe) -> GenRe:
    """``model`` with ``donor``'s trained inpainting net: its head, widths, weights and hit decision level.

    The depth net and the refiner (and the rest of the config) are
    ``model``'s.  This puts an inpainting net trained in one run (e.g. a wider
    net, ``genre train inpaint --inpaint-widths``) under the depth net and
    refiner of later weights, before a refine stage teaches the refiner its
    maps.  The two models must share the spherical map's size (ValueError).
    """
    mg, dg = model.config.geometry, donor.config.geometry
    if (mg.sph_size, mg.sph_pad) != (dg.sph_size, dg.sph_pad):
        raise ValueError(f"the donor's spherical maps are {dg.sph_size} (pad {dg.sph_pad}), the model's {mg.sph_size} "
                         f"(pad {mg.sph_pad}): an inpainting net cannot move between them")
    net = model.config.network
    dnet = donor.config.network
    config = dataclasses.replace(
        model.config,
        network=dataclasses.replace(net, inpaint_head=dnet.inpaint_head, inpaint_widths=tuple(dnet.inpaint_widths),
                                    inpaint_decoder_blocks=dnet.inpaint_decoder_blocks),
        geometry=dataclasses.replace(mg, sph_hit_probability=dg.sph_hit_probability))
    return _with_net_of(model, donor, config, "inpaint_net")


def with_depth_net_of(model: GenRe, donor: GenRe) -> GenRe:
    """``model`` with ``donor``'s trained depth net: its widths, decoder blocks, output scale and weights.

    The inpainting net, the refiner and the rest of the config (the mesh
    settings among it) are ``model``'s.  This reads a depth-stage run (whose
    files hold the other nets it started from) under later weights' other
    nets.  The two must share the picture's size and the camera (ValueError).
    """
    mg, dg = model.config.geometry, donor.config.geometry
    if mg.image_size != dg.image_size or model.config.camera != donor.config.camera:
        raise ValueError(f"the donor's depth net sees {dg.image_size} px through {donor.config.camera}, the model's "
                         f"{mg.image_size} px through {model.config.camera}: a depth net cannot move between them")
    net, dnet = model.config.network, donor.config.network
    config = dataclasses.replace(
        model.config, network=dataclasses.replace(net, depth_widths=tuple(dnet.depth_widths),
                                                  depth_decoder_blocks=dnet.depth_decoder_blocks,
                                                  depth_output_scale=dnet.depth_output_scale))
    return _with_net_of(model, donor, config, "depth_net")


def _half_if_it_fits(name: str, tensor: torch.Tensor) -> torch.Tensor:
    """``tensor`` as float16 for :func:`save_model`'s half storage, unless it is a batch-norm statistic, not
    floating-point, or has a value float16 cannot hold (it is then returned as it is)."""
    if not tensor.is_floating_point() or name.endswith(("running_mean", "running_var")):
        return tensor
    half = tensor.to(torch.float16)
    return half if bool(torch.isfinite(half).all()) else tensor


def save_model(model: GenRe, path: str | os.PathLike, extra: dict | None = None, *, storage: str = "float32") -> Path:
    """Write ``path`` (.safetensors, config in its metadata) atomically, and ``path`` with .json beside it.

    ``storage`` (one of :data:`~genre_backend.weights_file.STORAGES`):
    ``float16`` stores the floating-point weights as float16 (half the file);
    ``int8`` stores the large ones as int8 rows with a scale per output
    channel (:func:`~genre_backend.weights_file.pack_int8`, about a quarter)
    and the rest as float16.  The batch-norm statistics stay float32 (a
    running variance can exceed float16's range, 65,504: one of the
    refiner's reaches 6e7), as does any tensor that float16 cannot hold, and
    the step counters stay integers.  :func:`load_model` reads any of them
    into the float32 model, so inference always computes in float32.
    """
    if storage not in STORAGES:
        raise ValueError(f"storage {storage!r}: choose {', '.join(STORAGES)}")
    config = model.config.to_dict()
    meta = {"format": WEIGHTS_FORMAT, "config": json.dumps(config)}
    if extra:
        meta["extra"] = json.dumps(extra)
    state = model.state_dict()
    if storage == "int8":
        state = pack_int8(state)  # (the batch-norm statistics are vectors, left as they are)
    if storage != "float32":
        state = {k: v if k.endswith(INT8_SCALE_SUFFIX) else _half_if_it_fits(k, v) for k, v in state.items()}
        meta["storage"] = storage
    return save_weights(path, state, meta, {"format": WEIGHTS_FORMAT, "config": config, "extra": extra or {},
                                            **({"storage": storage} if storage != "float32" else {})})


# The most parameters a weights file's config may ask for, counted on the meta device before anything
# is allocated: 500 M float32 parameters are 2 GiB (the paper preset has 98 M, the default 1.6 M).
MAX_PARAMETERS = 500_000_000


def load_model(path: str | os.PathLike, device: str | torch.device = "cpu") -> GenRe:
    """Load a model saved by :func:`save_model`; the config (preset) comes from the file.

    The file is checked whole before the model is built: the metadata's JSON
    within bounds, every config field in range (:mod:`genre_backend.config`),
    the model the config describes built on the meta device (no memory) and
    its parameters counted (at most :data:`MAX_PARAMETERS`), and every tensor
    present, of the model's shape, floating-point and finite where the
    model's is (:func:`genre_backend.weights_file.check_state`).  Anything else raised
    while the model is built and loaded becomes a :class:`WeightsError` too.
    Raises :class:`WeightsError` with a one-line reason for a missing,
    corrupt, foreign, hostile or version-mismatched file.
    """
    state, meta = read_weights(path, WEIGHTS_FORMAT)
    config = stored_config(path, meta)
    try:
        with torch.device("meta"):
            skeleton = GenRe(config)
        wanted = skeleton.state_dict()
    except Exception as exc:  # noqa: BLE001  (a config the networks cannot be built from)
        raise WeightsError(f"{path}: the stored config does not make a model ({_reason(exc)})") from None
    count = sum(t.numel() for t in wanted.values())
    if count > MAX_PARAMETERS:
        raise WeightsError(f"{path}: the stored config asks for {count:,} parameters, at most {MAX_PARAMETERS:,}")
    check_state(wanted, state, path)
    del skeleton, wanted
    try:
        model = GenRe(config)
        model.load_state_dict(state, strict=True)  # (checked above: names, shapes, dtypes, finite values)
        return model.to(device).eval()
    except WeightsError:
        raise
    except Exception as exc:  # noqa: BLE001  (whatever else building it raises: the file is refused whole)
        raise WeightsError(f"{path}: the model could not be built from the file ({_reason(exc)})") from None


def _reason(exc: BaseException, limit: int = 300) -> str:
    lines = str(exc).strip().splitlines()
    line = f"{exc.__class__.__name__}: {lines[0]}" if lines else exc.__class__.__name__
    return line if len(line) <= limit else line[:limit] + "…"
