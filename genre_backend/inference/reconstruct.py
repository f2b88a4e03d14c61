"""Photo → mesh with trained weights: the reconstruction backend.

:class:`Reconstructor` loads a weights file once (the preset comes from the
file) and runs the pipeline stage by stage, so that each stage can be timed,
reported and cancelled:

=============  ==========================================================
``load``       decode the image (and the mask file)
``preprocess`` mask selection and canonical framing (:mod:`.preprocess`;
               runs the depth net once more when the silhouette is used)
``depth``      depth net on the framed image → planar depth + silhouette
``partial_sph`` masked depth → partial spherical map (exact ray cast)
``inpaint``    inpainting net → full spherical map
``voxels``     both back-projections → two voxel grids
``refine``     refiner → surface-shell logits
``mesh``       (outline trim,) marching cubes on sigmoid(logits) at the level
``write``      mesh export (done by :meth:`.result.Reconstruction.save_mesh`)
=============  ==========================================================

The mesh lives in the view frame of :mod:`genre_backend.frame`.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..weights_file import DEFAULT_WEIGHTS_NAME, named_weights
from ..geometry.cleanup import CleanReport, clean_mesh
from ..nets.model import GenRe, WeightsError, load_model, mirror_averaged
from ..output.mesh_export import MESH_FORMATS, OutputError, check_output_path, write_mesh
from ..nets.outputs import NetOutputs
from .options import MeshOptions, mesh_of_probability
from .result import Reconstruction
from ..photo.decode import ImageError, MIN_OBJECT_PIXELS, load_image
from ..photo.preprocess import Preprocessed, on_plain_backdrop, preprocess, uncrop
from ..photo.guidance import MaskGuidance
from ..photo.mask_doubt import doubt

__all__ = [
    "STAGES",
    "MESH_FORMATS",
    "mesh_of_probability",
    "DEFAULT_WEIGHTS",
    "Cancelled",
    "Hooks",
    "MaskGuidance",
    "OutputError",
    "Reconstructor",
    "error_code",
    "resolve_device",
    "check_output_path",
    "write_mesh",
]

STAGES = ("load", "preprocess", "depth", "partial_sph", "inpaint", "voxels", "refine", "mesh", "write")
# share of a typical job's time spent before each stage starts (for progress fractions)
_STAGE_WEIGHT = {"load": 0.02, "preprocess": 0.06, "depth": 0.14, "partial_sph": 0.14, "inpaint": 0.08, "voxels": 0.08, "refine": 0.36, "mesh": 0.08, "write": 0.04}
STAGE_START = {}
_acc = 0.0
for _s in STAGES:
    STAGE_START[_s] = round(_acc, 4)
    _acc += _STAGE_WEIGHT[_s]
del _acc, _s

DEFAULT_WEIGHTS = named_weights(DEFAULT_WEIGHTS_NAME)  # the product weights; --weights protocol|FILE picks others (weights_file.resolve_weights)

ProgressFn = Callable[[str, float], None]


class Cancelled(Exception):
    """The job was cancelled; raised at the next stage boundary."""


def error_code(exc: BaseException) -> str:
    """The ``genre serve`` error code of an exception raised by this module."""
    if isinstance(exc, (ImageError, OutputError)):
        return exc.code
    if isinstance(exc, WeightsError):
        return "bad_weights"
    if isinstance(exc, ValueError):
        return "bad_field"
    return "internal"


def resolve_device(device: str | torch.device) -> torch.device:
    """``"cpu"``, ``"cuda"`` or ``"cuda:N"`` → a usable device; a clear ValueError otherwise."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise ValueError(f"device: expected 'cpu' or 'cuda', got {device!r}") from None
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"device: expected 'cpu' or 'cuda', got {device!r}")
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError("device cuda: no CUDA device is available (this torch build or machine has none); use --device cpu")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"device {dev}: only {torch.cuda.device_count()} CUDA device(s) present")
    return dev


@dataclass(frozen=True)
class Hooks:
    """What a caller hears of a job and how it stops one: ``progress(stage, fraction)`` is called as each stage starts
    (fraction of the whole job done so far, :data:`STAGE_START`); ``should_cancel()`` is polled at every stage boundary,
    and when it returns True, :class:`Cancelled` is raised.  Either may be None."""

    progress: ProgressFn | None = None
    should_cancel: Callable[[], bool] | None = None


class _StageClock:
    """Times the stages of one job, reports each as it starts and polls for cancellation at every boundary
    (:class:`Hooks`); ``timings``: stage → seconds."""

    def __init__(self, sync: Callable[[], None], hooks: Hooks):
        self.sync, self.progress, self.should_cancel = sync, hooks.progress, hooks.should_cancel
        self.timings: dict[str, float] = {}
        self.name: str | None = None
        self.t0 = 0.0

    def __call__(self, name: str) -> None:
        if self.name is not None:
            self.sync()
            self.timings[self.name] = time.perf_counter() - self.t0
        if self.should_cancel is not None and self.should_cancel():
            raise Cancelled(f"cancelled before stage {name}")
        self.name, self.t0 = name, time.perf_counter()
        if name != "done" and self.progress is not None:
            self.progress(name, STAGE_START[name])


class Reconstructor:
    """A loaded model that turns photos into meshes; see the module docstring.

    ``weights_path``: a ``.safetensors`` file written by
    :func:`genre_backend.nets.model.save_model` (the preset comes from it).
    ``device``: ``"cpu"`` or ``"cuda"``.  Raises :class:`WeightsError` for a
    missing, corrupt or foreign weights file and ``ValueError`` for a device
    that is not there.
    """

    def __init__(self, weights_path: str | os.PathLike, device: str | torch.device = "cpu"):
        self.device = resolve_device(device)
        self.weights_path = Path(weights_path)
        self.model = self._prepare(load_model(self.weights_path, self.device))
        self.config = self.model.config
        self._first_pass = None

    @classmethod
    def from_model(cls, model: GenRe, device: str | torch.device = "cpu") -> Reconstructor:
        """Wrap a model built in memory (benchmarks); ``weights_path`` is None."""
        self = cls.__new__(cls)
        self.device = resolve_device(device)
        self.weights_path = None
        self.model = self._prepare(model.to(self.device).eval())
        self.config = model.config
        self._first_pass = None
        return self

    @staticmethod
    def _prepare(model: GenRe) -> GenRe:
        """Channels-last weights: the same numbers, 15–50% faster convolutions on the CPU (measured)."""
        import skimage.measure  # noqa: F401  (imported once here, not inside the first job's timings)

        model.depth_net.to(memory_format=torch.channels_last)
        model.inpaint_net.to(memory_format=torch.channels_last)
        model.refiner.to(memory_format=torch.channels_last_3d)
        return model

    @property
    def preset(self) -> str:
        return self.config.preset

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def _depth_net(self, rgb: torch.Tensor) -> dict[str, torch.Tensor]:
        """(3, S, S) float → depth-net outputs (batch of one), reusing the previous call's on the same input."""
        cached = self._first_pass
        if cached is not None and cached[0].shape == rgb.shape and torch.equal(cached[0], rgb):
            return cached[1]
        x = rgb[None].to(self.device).contiguous(memory_format=torch.channels_last)
        out = self.model.depth_net(x)
        self._first_pass = (rgb, out)
        return out

    def _silhouette(self, rgb: torch.Tensor) -> torch.Tensor:
        """(3, S, S) float → (S, S) float: the depth net's silhouette logits."""
        return self._depth_net(rgb)["silhouette_logits"][0].float().cpu()

    def run(self, image_path: str | os.PathLike, guidance: MaskGuidance | None = None, options: MeshOptions | None = None,
            hooks: Hooks | None = None, **overrides) -> Reconstruction:
        """Reconstruct one image; see :class:`Reconstruction` for the result.

        ``guidance``: the mask inputs and switches (:class:`.guidance.MaskGuidance`: a mask file, a person's box and
        strokes and the pixels they are over, ``refine`` and ``seeding``; None: the automatic mask, found in the photo
        when it has no alpha, :func:`.preprocess.preprocess`).  ``options``: the mesh options
        (:class:`.options.MeshOptions`; its ``None`` fields, and all of them when it is None, take the weights'
        settings); ``overrides``: options by name laid over it (``threshold=0.4``), checked alike
        (:class:`.options.OptionError`, a ValueError naming the option).  ``hooks``: progress and cancellation
        (:class:`Hooks`).  The steps after the networks are the options' own (:meth:`.options.MeshOptions.shape_grid`,
        :meth:`~.options.MeshOptions.mesh`, :meth:`~.options.MeshOptions.snap_mesh`).  Raises :class:`ImageError` for bad
        images, masks or images with no object.
        """
        guidance = MaskGuidance() if guidance is None else guidance
        opts = MeshOptions.from_mapping(overrides).over(options or MeshOptions()).resolved(self.config.geometry)
        stage = _StageClock(self._sync, hooks or Hooks())
        self._first_pass = None
        with torch.inference_mode():
            stage("load")
            image = load_image(image_path)
            stage("preprocess")
            pre: Preprocessed = preprocess(image, self.config, guidance, silhouette=self._silhouette)
            seen = pre.rgb if pre.mask is None or not opts.plain_backdrop else on_plain_backdrop(pre.rgb, pre.mask)
            nets = self._networks(pre, seen, opts, stage, image.path)
            stage("mesh")
            mesh = self._mesh(nets, opts, image.path, list(pre.notes))
            stage("done")
        photo_mask = pre.photo_mask
        if photo_mask is None:  # the crop's silhouette, back at the photo's pixels
            crop = tuple(v * image.scale for v in pre.crop_box)
            photo_mask = uncrop(nets.mask[0].cpu().numpy(), crop, image.size)
        inter = {"rgb": seen, **nets.images(), "probability": mesh.probability}
        return Reconstruction(
            image=Path(image_path),
            vertices=mesh.vertices,
            faces=mesh.faces,
            mask_source=pre.mask_source,
            options=opts,
            timings=stage.timings,
            crop_box=pre.crop_box,
            image_size=pre.image_size,
            config=self.config,
            intermediates={k: v.detach().cpu() for k, v in inter.items()},
            notes=mesh.notes,
            guidance=guidance,
            photo=image,
            fill=pre.fill,
            clean=mesh.clean,
            photo_mask=photo_mask,
            mask_warning="; ".join(w for w in (doubt(photo_mask), pre.mask_doubt) if w) or None,
            primitive=mesh.primitive,
        )

    def _networks(self, pre: Preprocessed, rgb: torch.Tensor, opts: MeshOptions, stage: _StageClock, path) -> NetOutputs:
        """The networks on one framed photo (:class:`genre_backend.nets.outputs.NetOutputs`); ``rgb`` (3, S, S): the
        picture they see (the framed photo, on a plain backdrop where ``opts.plain_backdrop`` says so)."""
        model = self.model
        stage("depth")
        out = self._depth_net(rgb)
        self._first_pass = None
        mask = out["silhouette_logits"] > 0 if pre.mask is None else pre.mask[None].to(self.device)
        masked = model.masked_depth(out["depth"], mask)
        if int((masked > 0).sum()) < MIN_OBJECT_PIXELS:
            what = "the depth net's silhouette is empty" if pre.mask is None else "the depth net found no surface inside the mask"
            raise ImageError("no_object", f"{path}: no object found ({what})")
        stage("partial_sph")
        partial = model.partial_sph(masked)
        stage("inpaint")
        full = model.full_sph(partial)
        stage("voxels")
        vox_sph = model.sph_voxels(full)
        vox_depth = model.depth_voxels(masked)
        stage("refine")
        logits = model.refine(vox_sph, vox_depth)
        if opts.test_time_mirror:  # the mirror image through every net, its output reflected back
            logits = mirror_averaged(lambda r, k, d, f: model(r, mask=k).logits, rgb[None].to(self.device), mask,
                                     logits=logits)
        return NetOutputs(depth=out["depth"], silhouette_logits=out["silhouette_logits"], mask=mask, masked_depth=masked,
                          partial_sph=partial, full_sph=full, vox_sph=vox_sph, vox_depth=vox_depth, logits=logits)

    def _mesh(self, nets: NetOutputs, opts: MeshOptions, path, notes: list[str]) -> _Meshed:
        """The steps after the networks, in the options' one order (:class:`_Meshed`)."""
        model = self.model
        view = nets.view(model.config.camera)
        prob = torch.sigmoid(nets.logits[0, 0]).float().cpu()
        prob = opts.shape_grid(prob, view, model.config.geometry)
        prob, vertices, faces, clean = opts.mesh(prob, model.config.geometry)
        if clean is None:
            raise ImageError("no_object", f"{path}: no object found (no voxel reaches the threshold {opts.threshold:g})")
        primitive = None
        vertices, faces, fit = opts.snap_mesh(vertices, faces, view)
        if fit is not None:
            primitive = fit.family
            vertices, faces, clean = clean_mesh(vertices, faces, 0.0)
            notes = [*notes, f"the mesh is a fitted {fit.describe()}"]
        return _Meshed(prob, vertices, faces, clean, primitive, notes)


@dataclass(frozen=True)
class _Meshed:
    """What the steps after the networks make: ``probability`` (N, N, N) CPU float (the grid as meshed), ``vertices``
    (V, 3), ``faces`` (F, 3), ``clean`` (the cleanup's report), ``primitive`` (a fitted family or None) and ``notes``
    (the run's, with the fit's when one replaced the mesh)."""

    probability: torch.Tensor
    vertices: np.ndarray
    faces: np.ndarray
    clean: CleanReport
    primitive: str | None
    notes: list[str]
