"""Training samples: rendered views with their ground-truth targets.

A sample is one view written by :mod:`training.render.scene` plus its
:mod:`training.data.targets` file.  Tensors (S = image size, H = spherical map
size, N = voxel grid size):

* ``rgb``         (3, S, S) float in [0, 1]
* ``depth``       (S, S) float, planar depth, 0 outside the mask or where the Z pass saw nothing
* ``mask``        (S, S) bool, the film alpha > 0.5 (the silhouette target)
* ``full_sph``    (H, H) float, ``partial_sph`` (H, H) float
* ``voxels``      (N, N, N) float in [0, 1], the refiner's target (``GeometryConfig.target``:
  the surface shell or the truncated distance)

Augmentation (training only) follows the original: brightness, contrast and
saturation each scaled by U[0.6, 1.4] in random order, then PCA lighting noise.
It is seeded per sample by the caller, so a resumed run sees the same pixels.

**Photo-like samples** (``backgrounds`` given, ``photo_fraction`` > 0): a
share of the samples has the rendered object composited through its film
alpha over a random crop of a real photograph
(:class:`training.data.photo_backgrounds.BackgroundBank`), and every sample
then goes through a camera's faults (:func:`photometric`: exposure, white
balance, blur, sensor noise, JPEG).

**Mirrored samples** (``mirror`` > 0, training only): that share of the
samples is the view of the scene reflected in the view frame's x = 0 plane
(:func:`mirror_sample`): the image, depth and mask flipped left to right, the
spherical maps and voxels reflected with them.  The reflection is exact (the
camera's principal point is the image centre), so a mirrored sample is a view
the renderer could have made of the mirrored object, with every target true.

**Stretched samples** (``stretch`` > 0, training only, the depth stage's samples: no targets): that share of the
samples has its picture, film alpha and depth scaled left to right about the image centre
(:func:`stretch_sample`).  With the principal point at the centre, the image of the object scaled by ``s`` along
the camera's x axis is the image scaled by ``s`` across, at the same planar depth: so a stretched sample is the
exact picture and depth of a wider or narrower object (only its shading keeps the old surface's normals), a
new shape for a depth net whose unseen error follows the number of shapes it saw.

**Plain-backdrop samples** (``backdrop`` > 0, training only): that share of the samples has every pixel outside its
mask painted the neutral grey after the camera's faults, the picture the networks are given in use with the mesh
option ``geometry.plain_backdrop`` on (:func:`genre_backend.photo.preprocess.on_plain_backdrop`).  With
``plain_backdrop`` every sample is painted so, seeded or not: a training run validates a model whose
``geometry.plain_backdrop`` is on on the picture ``genre eval`` and ``genre reconstruct`` show its nets.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import torch

from genre_backend.config import GenreConfig
from genre_backend.geometry.spherical import mirror_sph
from genre_backend.geometry.voxels import mirror_voxels
from genre_backend.photo.preprocess import on_plain_backdrop

from .targets import load_targets
from .views import ViewRef, find_views, view_paths

__all__ = ["ViewRef", "ViewDataset", "find_views", "split_views", "augment_rgb", "photometric", "composite_alpha",
           "mirror_sample", "stretch_sample", "STRETCH_RANGE"]

# the factor of a stretched sample is log-uniform in this range (then cut so the object stays in the frame)
STRETCH_RANGE = (0.7, 1.4)

# ImageNet RGB PCA (eigenvalues, eigenvectors as columns): the standard "lighting" noise
_PCA_EIGVAL = torch.tensor([0.2175, 0.0188, 0.0045])
_PCA_EIGVEC = torch.tensor([[-0.5675, 0.7192, 0.4009], [-0.5808, -0.0045, -0.8140], [-0.5836, -0.6948, 0.4203]])


def _unit_hash(text: str) -> float:
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "big") / 2**64


def split_views(refs: list[ViewRef], val_fraction: float) -> tuple[list[ViewRef], list[ViewRef]]:
    """Deterministic train/validation split **by shape** (a salted hash of the shape id).

    The salt keeps this split independent of the corpus's train/test split,
    which thresholds the unsalted hash: without it every training shape
    would hash above the test fraction and validation would be empty.
    """
    val_ids = {r.shape_id for r in refs if _unit_hash("validation:" + r.shape_id) < val_fraction}
    train = [r for r in refs if r.shape_id not in val_ids]
    val = [r for r in refs if r.shape_id in val_ids]
    return train, val


def mirror_sample(sample: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The sample of the scene reflected in the view frame's x = 0 plane (see the module docstring).

    Images (``rgb`` (3, S, S), ``depth``, ``mask`` (S, S)) flip their columns;
    spherical maps (``full_sph``, ``partial_sph``) reverse their azimuth
    (:func:`~genre_backend.geometry.spherical.mirror_sph`); ``voxels``
    (N, N, N) flip along x (:func:`~genre_backend.geometry.voxels.mirror_voxels`).
    Other entries are kept.  Its own inverse.
    """
    out = dict(sample)
    for key in ("rgb", "depth", "mask"):
        if key in out:
            out[key] = torch.flip(out[key], dims=(-1,))
    for key in ("full_sph", "partial_sph"):
        if key in out:
            out[key] = mirror_sph(out[key])
    if "voxels" in out:
        out["voxels"] = mirror_voxels(out["voxels"])
    return out


def stretch_sample(rgb: torch.Tensor, alpha: torch.Tensor, depth: torch.Tensor, factor: float
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The view of the object scaled by ``factor`` along the camera's x axis (see the module docstring).

    ``rgb`` (3, S, S), ``alpha`` (S, S) film alpha and ``depth`` (S, S) planar depth are resampled at column
    ``c + (j - c) / factor`` (c the image centre): the picture and alpha bilinearly, the depth as the blend of
    the neighbouring columns that are object (never blended with the background's); a pixel is object where the
    nearest column is, and its returned alpha is on that side of 0.5, so that the mask and the depth agree.
    """
    size = rgb.shape[-1]
    x = (torch.arange(size, dtype=torch.float32) + 0.5) / size * 2.0 - 1.0  # align_corners=False pixel centres
    grid = torch.stack(torch.broadcast_tensors((x / factor)[None, :], x[:, None]), dim=-1)[None]  # (1, S, S, 2): (x, y)

    def sample(t: torch.Tensor, mode: str) -> torch.Tensor:
        return torch.nn.functional.grid_sample(t[None], grid, mode=mode, padding_mode="zeros", align_corners=False)[0]

    rgb_s = sample(rgb, "bilinear")
    alpha_b = sample(alpha[None], "bilinear")[0]
    object_n = sample(alpha[None], "nearest")[0] > 0.5
    # the depth: the blend of the two neighbouring columns that are object (never of object and background)
    inside = ((alpha > 0.5) & (depth > 0)).to(depth.dtype)
    weight = sample(inside[None], "bilinear")[0]
    blend = sample((depth * inside)[None], "bilinear")[0] / weight.clamp(min=1e-6)
    object_n &= weight > 0
    # the blend's own side of 0.5 must agree with the nearest column's: the silhouette follows the depth
    alpha_s = torch.where(object_n, alpha_b.clamp(min=0.5 + 1e-3), alpha_b.clamp(max=0.5))
    return rgb_s, alpha_s, torch.where(object_n, blend, torch.zeros_like(blend))


def stretch_factor(alpha: torch.Tensor, gen: torch.Generator) -> float:
    """A factor log-uniform in :data:`STRETCH_RANGE`, cut so that the object (alpha > 0) stays a pixel inside the frame."""
    lo, hi = STRETCH_RANGE
    factor = float(np.exp(np.log(lo) + float(torch.rand((), generator=gen)) * (np.log(hi) - np.log(lo))))
    cols = torch.nonzero(alpha.amax(dim=0) > 0).flatten()
    if cols.numel():
        size = alpha.shape[-1]
        centre = size / 2.0
        reach = float(torch.maximum(centre - cols.min(), cols.max() + 1 - centre))  # the object's half-width in pixels
        factor = min(factor, (centre - 1.0) / max(reach, 1.0))
    return factor


def augment_rgb(rgb: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Colour jitter (brightness, contrast, saturation ×U[0.6, 1.4], random order) + PCA lighting; (3, S, S) in [0, 1]."""
    gray_w = torch.tensor([0.299, 0.587, 0.114]).view(3, 1, 1)
    for op in torch.randperm(3, generator=gen).tolist():
        f = 0.6 + 0.8 * torch.rand((), generator=gen)
        if op == 0:
            rgb = rgb * f
        elif op == 1:
            rgb = (rgb - (rgb * gray_w).sum(0).mean()) * f + (rgb * gray_w).sum(0).mean()
        else:
            gray = (rgb * gray_w).sum(0, keepdim=True)
            rgb = (rgb - gray) * f + gray
    alpha = torch.randn(3, generator=gen) * 0.1
    rgb = rgb + (_PCA_EIGVEC @ (alpha * _PCA_EIGVAL)).view(3, 1, 1)
    return rgb.clamp(0.0, 1.0)


def composite_alpha(rgb: torch.Tensor, alpha: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """``rgb`` (3, S, S) over ``background`` (3, S, S) through ``alpha`` (S, S) in [0, 1]: rgb·α + bg·(1 − α).

    The render's own background is already mixed into its edge pixels (by
    1 − α); those few pixels keep a trace of it.
    """
    a = alpha.clamp(0.0, 1.0).unsqueeze(0)
    return rgb * a + background * (1.0 - a)


def _gaussian_blur(rgb: torch.Tensor, sigma: float) -> torch.Tensor:
    radius = max(1, int(round(2.5 * sigma)))
    x = torch.arange(-radius, radius + 1, dtype=rgb.dtype)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    img = rgb.unsqueeze(0)
    img = torch.nn.functional.conv2d(torch.nn.functional.pad(img, (radius, radius, 0, 0), mode="replicate"), k.view(1, 1, 1, -1).expand(3, 1, 1, -1), groups=3)
    img = torch.nn.functional.conv2d(torch.nn.functional.pad(img, (0, 0, radius, radius), mode="replicate"), k.view(1, 1, -1, 1).expand(3, 1, -1, 1), groups=3)
    return img[0]


def photometric(rgb: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """A camera's faults on (3, S, S) in [0, 1]: exposure ×2^U[−0.7, 0.7], white balance (per channel
    ×U[0.85, 1.15]), Gaussian blur (σ U[0.3, 1.2] px, 30 %), sensor noise (σ U[0, 0.03], 50 %) and
    JPEG compression (quality 35–95, 40 %)."""
    u = torch.rand(9, generator=gen)
    rgb = rgb * float(2.0 ** (1.4 * u[0] - 0.7))
    rgb = rgb * (0.85 + 0.3 * torch.rand(3, generator=gen)).view(3, 1, 1)
    if u[1] < 0.3:
        rgb = _gaussian_blur(rgb, 0.3 + 0.9 * float(u[2]))
    if u[3] < 0.5:
        rgb = rgb + torch.randn(rgb.shape, generator=gen) * (0.03 * float(u[4]))
    rgb = rgb.clamp(0.0, 1.0)
    if u[5] < 0.4:
        import io

        from PIL import Image

        buf = io.BytesIO()
        Image.fromarray((rgb.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)).save(buf, format="JPEG", quality=int(35 + 60 * float(u[6])))
        buf.seek(0)
        with Image.open(buf) as im:
            rgb = torch.from_numpy(np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0).permute(2, 0, 1).contiguous()
    return rgb


class ViewDataset(torch.utils.data.Dataset):
    """Samples of a list of views; ``sample(i, seed)`` applies seeded augmentation when ``augment``."""

    def __init__(self, refs: list[ViewRef], config: GenreConfig, augment: bool = False, targets: bool = True,
                 backgrounds=None, photo_fraction: float = 0.0, mirror: float = 0.0, stretch: float = 0.0,
                 backdrop: float = 0.0, depth_only: str | Path | None = None, plain_backdrop: bool = False,
                 true_map: str | Path | None = None):
        if not refs:
            raise ValueError("no complete views (render + targets) to train on")
        if not 0.0 <= photo_fraction <= 1.0:
            raise ValueError(f"photo_fraction: expected a value in [0, 1], got {photo_fraction}")
        if isinstance(mirror, bool) or not 0.0 <= mirror <= 1.0:
            raise ValueError(f"mirror: expected a share in [0, 1], got {mirror!r}")
        if isinstance(stretch, bool) or not 0.0 <= stretch <= 1.0:
            raise ValueError(f"stretch: expected a share in [0, 1], got {stretch!r}")
        if isinstance(backdrop, bool) or not 0.0 <= backdrop <= 1.0:
            raise ValueError(f"backdrop: expected a share in [0, 1], got {backdrop!r}")
        if stretch > 0 and targets:
            raise ValueError("stretch: only samples without targets (the depth stage's) can be stretched")
        if photo_fraction > 0 and backgrounds is None:
            raise ValueError("photo_fraction > 0 needs backgrounds (a BackgroundBank of 'genre data backgrounds')")
        self.refs = list(refs)
        self.config = config
        self.augment = augment
        self.targets = targets  # False: only rgb, depth and mask (all the depth stage needs)
        self.backgrounds = backgrounds if photo_fraction > 0 else None
        self.photo_fraction = photo_fraction
        self.mirror = mirror  # the share of seeded samples mirrored (independent of ``augment``: it is geometric)
        self.stretch = stretch  # the share of seeded samples stretched across (geometric too)
        self.backdrop = backdrop  # the share of seeded samples painted grey outside the mask
        # every sample painted so, seeded or not: the validation views of weights that paint their photos in use
        self.plain_backdrop = plain_backdrop
        # the views under the folders ``depth_only`` and ``true_map`` (TrainConfig's): every sample says whether it is
        # one of them
        self.depth_only = self._under(depth_only)
        self.true_map = self._under(true_map)

    def _under(self, folder: str | Path | None) -> set[int] | None:
        """The indices of the views under ``folder`` (None without one)."""
        if folder is None:
            return None
        root = Path(folder).resolve()
        return {i for i, r in enumerate(self.refs) if r.shape_dir.parent.resolve() == root}

    def __len__(self) -> int:
        return len(self.refs)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        return self.sample(index, None)

    def sample(self, index: int, seed: int | None) -> dict[str, torch.Tensor]:
        from PIL import Image

        ref = self.refs[index]
        paths = view_paths(ref.shape_dir, ref.view)
        size = self.config.geometry.image_size
        meta = json.loads(paths["json"].read_text())
        if int(meta["image_size"]) != size:
            raise ValueError(f"{paths['json'].with_suffix('')}: rendered at {meta['image_size']}², the config wants {size}²")
        with Image.open(paths["png"]) as im:
            rgb = torch.from_numpy(np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0).permute(2, 0, 1).contiguous()
        with np.load(paths["npz"]) as z:
            depth = torch.from_numpy(z["depth"].astype(np.float32))
            alpha = torch.from_numpy(z["mask"].astype(np.float32))
            mask = alpha > 0.5
        # the stretch's own seeded draws (as the mirror's), before the colour's, so that stream stays as it was
        if self.stretch > 0 and seed is not None:
            gen_s = torch.Generator().manual_seed((seed * 2246822519 + 131) % (1 << 63))
            if float(torch.rand((), generator=gen_s)) < self.stretch:
                rgb, alpha, depth = stretch_sample(rgb, alpha, depth, stretch_factor(alpha, gen_s))
                mask = alpha > 0.5
        if self.augment and seed is not None:
            gen = torch.Generator().manual_seed(seed)
            if self.backgrounds is None:
                rgb = augment_rgb(rgb, gen)
            else:
                if float(torch.rand((), generator=gen)) < self.photo_fraction:
                    rgb = composite_alpha(rgb, alpha, self.backgrounds.sample(gen, size))
                rgb = photometric(augment_rgb(rgb, gen), gen)
        if self.backdrop > 0 and seed is not None:  # its own seeded draw, as the mirror's
            coin = torch.rand((), generator=torch.Generator().manual_seed((seed * 3266489917 + 61) % (1 << 63)))
            if float(coin) < self.backdrop:
                rgb = on_plain_backdrop(rgb, mask)
        elif self.plain_backdrop:
            rgb = on_plain_backdrop(rgb, mask)
        sample = {
            "rgb": rgb,
            "depth": torch.where(mask, depth, torch.zeros_like(depth)),  # 0 where either says background
            "mask": mask,
        }
        if self.targets:
            t = load_targets(ref.shape_dir, ref.view, self.config.geometry)
            sample["full_sph"] = torch.from_numpy(t["full_sph"])
            sample["partial_sph"] = torch.from_numpy(t["partial_sph"])
            sample["voxels"] = torch.from_numpy(t["voxels"])
        # the mirror's own seeded draw, so that the colour augmentation's stream is the same with or without it
        if self.mirror > 0 and seed is not None:
            coin = torch.rand((), generator=torch.Generator().manual_seed((seed * 2654435761 + 97) % (1 << 63)))
            if float(coin) < self.mirror:
                sample = mirror_sample(sample)
        for flag in ("depth_only", "true_map"):
            members = getattr(self, flag)
            if members is not None:
                sample[flag] = torch.tensor(index in members)
        return sample
