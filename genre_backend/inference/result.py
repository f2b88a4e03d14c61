"""The result of one reconstruction: the mesh in the view frame, the intermediates, and the files made from them.

:class:`Reconstruction` is what :meth:`~genre_backend.inference.reconstruct.Reconstructor.run` returns: it writes the
mesh (:meth:`Reconstruction.save_mesh`), the intermediate images, the preview sheet, and gives the camera that matches
the photo, the mask at the photo's own size and the colour from the photo.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..config import GenreConfig
from ..geometry.cleanup import CleanReport
from ..output.mesh_export import OutputError, check_output_path, resolve_format, resolve_up, short, write_mesh, write_png
from ..output.colour import MAX_TEXTURE_SIDE, PhotoTexture, photo_texture
from .options import MeshOptions
from ..photo.decode import LoadedImage
from ..photo.guidance import MaskGuidance
from ..photo.preprocess import composite, crop_resize

__all__ = ["Reconstruction", "MASK_OVERLAY_SIDE"]


# the long side of the mask-over-photo picture save_intermediates writes (mask_overlay.png; the add-on shows it)
MASK_OVERLAY_SIDE = 320


def _colour(values: np.ndarray, valid: np.ndarray, lo: float, hi: float, cmap: str) -> np.ndarray:
    """(H, W) floats → (H, W, 3) uint8 colour map; invalid pixels black.  Without matplotlib (the runtime install,
    which the add-on's Install Backend makes: it asks for the intermediates only for the mask's pictures) grey levels."""
    from ..output.blender import private_matplotlib_config

    t = np.clip((values - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    private_matplotlib_config()  # (never $HOME/.config/matplotlib)
    try:
        import matplotlib
    except ImportError:
        rgb = np.repeat((t * 255).astype(np.uint8)[..., None], 3, axis=-1)
    else:
        rgb = (matplotlib.colormaps[cmap](t)[..., :3] * 255).astype(np.uint8)
    rgb[~valid] = 0
    return rgb


def _upscale(img: np.ndarray, min_side: int = 256) -> np.ndarray:
    k = max(1, min_side // max(img.shape[:2]))
    return np.repeat(np.repeat(img, k, axis=0), k, axis=1)


@dataclass
class Reconstruction:
    """The result of one image.

    ``vertices`` (V, 3) float32 and ``faces`` (F, 3) int64: the mesh in the
    view frame.  ``mask_source``: ``"file"``, ``"alpha"``, ``"salient"``, ``"grabcut"``,
    ``"box"``, ``"strokes"``, ``"box+strokes"`` or ``"silhouette"``.  ``photo_mask``: (H, W) bool, the mask the networks
    used at the decoded photo's pixels (:meth:`mask_in_photo` gives it at
    the photo's own size).  ``mask_warning``: one line when that mask is
    doubtful (:func:`genre_backend.photo.mask_doubt.doubt`: it covers most
    of the photo or touches most of its border; :func:`~genre_backend.photo.mask_doubt.cut_doubt`:
    GrabCut's colours barely separate it, or it runs along the photo's edge; :func:`~genre_backend.photo.mask_doubt.salient_doubt`:
    the salient net's mask; or the net could not be loaded and GrabCut's mask was used), else None.
    ``options``: the mesh options as the mesh was made (:class:`.options.MeshOptions`, resolved against the weights:
    no field ``None``).  ``primitive``: the family of the fitted shape that replaced the
    mesh (``"box"``, ``"cylinder"``, ``"cone"``, ``"torus"``, ``"ellipsoid"``), else None.
    ``guidance``: the mask inputs it was run with (:class:`genre_backend.photo.guidance.MaskGuidance`).
    ``timings``: stage → seconds.  ``crop_box``: (x0, y0, x1, y1) in the
    original image.  ``intermediates`` (S = image size, H = spherical map
    size, N = voxel grid size), CPU tensors: ``rgb`` (3, S, S), ``depth``
    (S, S) raw depth-net output, ``silhouette_logits`` (S, S), ``mask`` (S, S)
    bool, ``masked_depth`` (S, S), ``partial_sph`` (H, H), ``full_sph``
    (H, H), ``vox_sph`` (N, N, N), ``vox_depth`` (N, N, N), ``logits``
    (N, N, N), ``probability`` (N, N, N).  ``photo``: the decoded photo
    (for :meth:`texture`), ``fill``: the colour the framing gave parts of
    the crop outside it.  ``clean``: what the mesh clean-up did (parts
    before/after, watertight), :func:`genre_backend.geometry.cleanup.clean_mesh`.
    ``files``: every file the last :meth:`save_mesh` wrote; ``up``: the up
    axis of that mesh file (``y``: the view frame; ``z``: a PLY turned +z up).
    """

    image: Path
    vertices: np.ndarray
    faces: np.ndarray
    mask_source: str
    options: MeshOptions
    timings: dict[str, float]
    crop_box: tuple[float, float, float, float]
    image_size: tuple[int, int]
    config: GenreConfig
    intermediates: dict[str, torch.Tensor] = field(repr=False)
    notes: list[str] = field(default_factory=list)
    guidance: MaskGuidance = field(default_factory=MaskGuidance)
    photo: LoadedImage | None = field(default=None, repr=False)
    fill: tuple[int, int, int] = (0, 0, 0)
    clean: CleanReport | None = None
    files: list[Path] = field(default_factory=list)
    up: str = "y"
    photo_mask: np.ndarray | None = field(default=None, repr=False)
    mask_warning: str | None = None
    primitive: str | None = None
    _texture: PhotoTexture | None = field(default=None, repr=False)

    @property
    def inputs(self) -> tuple[Path, ...]:
        """The files this result was made from (never overwritten by its own outputs)."""
        return (self.image, *self.guidance.files)

    def camera(self) -> dict:
        """The view the mesh is posed for (protocol ``camera`` object).

        ``lens_mm``, ``sensor_mm`` and ``distance`` describe the backend's
        square camera; it sees exactly ``crop_box`` (x0, y0, x1, y1; pixels of
        the photo as displayed, rows downward, may extend past the photo) of
        the photo, whose size is ``image_size`` (width, height).
        ``exif_orientation``: the photo file's EXIF orientation (1-8; 1: none),
        which ``crop_box`` and ``image_size`` already apply: a client that
        shows the file with a loader that ignores it must turn the pixels.
        """
        c = self.config.camera
        return {
            "lens_mm": c.lens_mm,
            "sensor_mm": c.sensor_mm,
            "distance": c.distance,
            "crop_box": [round(float(v), 3) for v in self.crop_box],
            "image_size": [int(v) for v in self.image_size],
            "exif_orientation": int(self.photo.exif_orientation) if self.photo is not None else 1,
        }

    def mask_in_photo(self) -> np.ndarray:
        """(height, width) bool at the photo's own size (``image_size``): the mask the networks used.

        Written by :meth:`save_intermediates` as ``mask_in_photo.png``; given
        back as a mask file (``--mask``) it reproduces this result's crop and
        network mask (exactly when the photo was not downscaled on decoding).
        """
        if self.photo_mask is None:
            raise ValueError("this reconstruction keeps no mask at the photo's pixels")
        w, h = self.image_size
        mask = self.photo_mask
        if mask.shape != (h, w):  # the photo was downscaled on decoding: nearest pixel back to its size
            rows = np.minimum((np.arange(h) + 0.5) * mask.shape[0] / h, mask.shape[0] - 1).astype(np.int64)
            cols = np.minimum((np.arange(w) + 0.5) * mask.shape[1] / w, mask.shape[1] - 1).astype(np.int64)
            mask = mask[np.ix_(rows, cols)]
        return mask

    def mask_overlay(self, side: int = MASK_OVERLAY_SIDE) -> np.ndarray:
        """(h, w, 3) uint8: the photo at up to ``side`` pixels on its long side with the mask the networks used over
        it: the background dimmed to a third and tinted blue, the mask's outline yellow.  What the add-on's panel
        shows after a run (``mask_overlay.png`` of :meth:`save_intermediates`), so that a wrong mask is seen at once."""
        import cv2  # noqa: PLC0415

        if self.photo_mask is None or self.photo is None:
            raise ValueError("this reconstruction keeps no mask and photo at the photo's pixels")
        rgb = composite(self.photo)
        h, w = rgb.shape[:2]
        k = min(1.0, side / max(h, w))
        size = (max(1, round(w * k)), max(1, round(h * k)))
        small = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA) if k < 1.0 else rgb.copy()
        mask = cv2.resize(self.photo_mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST).astype(bool)
        out = small.astype(np.float32)
        out[~mask] = out[~mask] * 0.35 + np.array([20.0, 40.0, 110.0], np.float32)
        out = np.clip(out, 0, 255).astype(np.uint8)
        contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(out, contours, -1, (255, 220, 0), max(1, round(max(size) / 160)))
        return out

    def texture(self) -> PhotoTexture:
        """The mesh's colour from the photo (:mod:`.colour`): corner UVs into an atlas of the photo's crop (at up to
        2,048 px) and its smooth copy.

        Needs the decoded photo (``photo``); computed once and kept.
        """
        if self._texture is None:
            if self.photo is None:
                raise ValueError("this reconstruction keeps no photo to colour the mesh from")
            x0, y0, x1, y1 = (v * self.photo.scale for v in self.crop_box)  # original → decoded pixels
            side = int(np.clip(round(x1 - x0), self.config.geometry.image_size, MAX_TEXTURE_SIDE))
            image = crop_resize(composite(self.photo), (x0, y0, x1, y1), side, self.fill)
            mask = self.intermediates["mask"].numpy().astype(bool)  # (photo_texture shrinks it)
            self._texture = photo_texture(self.vertices, self.faces, self.config.camera, mask, image)
        return self._texture

    def save_mesh(self, path: str | os.PathLike, fmt: str | None = None, texture: bool = False,
                  up: str | None = None) -> tuple[Path, str]:
        """Write the mesh atomically (obj, ply or glb; default from the extension); times the ``write`` stage.

        ``texture``: colour it from the photo (:meth:`texture`; an OBJ gets
        its ``.mtl`` and ``_texture.png`` beside it, see
        :mod:`.mesh_export`).  ``up``: the file's up axis, ``y`` or ``z``
        (default: z for ply, y for obj and glb; ``z`` is for ply only:
        :func:`.mesh_export.resolve_up`).  The files written are in
        ``files``, the axis used in ``up``.
        """
        t0 = time.perf_counter()
        used_up = resolve_up(resolve_format(path, fmt), up)  # (a wrong axis fails before the texture is made)
        tex = self.texture() if texture else None
        out, used, self.files = write_mesh(path, self.vertices, self.faces, fmt, texture=tex, inputs=self.inputs, up=used_up)
        self.up = used_up
        self.timings["write"] = time.perf_counter() - t0
        return out, used

    def save_intermediates(self, folder: str | os.PathLike) -> list[Path]:
        """Write PNGs a person can look at into ``folder`` (created); returns the paths.

        ``input.png`` (the framed image), ``mask.png``, ``depth.png`` (masked
        depth, near = bright; background black), ``silhouette.png``,
        ``partial_sph.png`` and ``full_sph.png`` (far from the centre = bright, on the partial map's scale; no
        hit black), ``vox_sph.png``, ``vox_depth.png`` and ``probability.png``
        (max-projections along view −z, −x and −y, side by side), and
        ``mask_in_photo.png``: the mask at the photo's own size (white object
        on black, :meth:`mask_in_photo`), to correct in any editor and give
        back with ``--mask``; ``mask_overlay.png``: the mask over the photo
        (:meth:`mask_overlay`), to see at once whether it is right.
        """
        folder = Path(folder)
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"{short(folder)}: cannot create the intermediates folder: {exc.strerror or exc}") from None
        if not os.access(folder, os.W_OK | os.X_OK):
            raise OutputError(f"{short(folder)}: intermediates folder is not writable")
        images = {name: _upscale(img) for name, img in self.intermediate_images().items()}
        if self.photo_mask is not None:
            images["mask_in_photo"] = self.mask_in_photo().astype(np.uint8) * 255  # the photo's own pixels, never scaled
            if self.photo is not None:
                images["mask_overlay"] = self.mask_overlay()
        for name in images:  # all checks before the first write
            check_output_path(folder / f"{name}.png", self.inputs)
        paths = []
        for name, img in images.items():
            p = folder / f"{name}.png"
            write_png(p, img)
            paths.append(p)
        return paths

    def save_preview(self, path: str | os.PathLike, samples: int = 16, texture: bool = False) -> Path:
        """Write one PNG a person can judge the result by (:func:`genre_backend.output.preview.preview_image`).

        ``texture``: the mesh views show the photo's colour (:meth:`texture`).
        """
        from ..output.preview import preview_image

        path = Path(path)
        check_output_path(path, self.inputs)
        t0 = time.perf_counter()
        write_png(path, preview_image(self, samples=samples, textured=texture))
        self.timings["preview"] = time.perf_counter() - t0
        return path

    def intermediate_images(self) -> dict[str, np.ndarray]:
        """The intermediates as images at their own resolution: name → (h, w) or (h, w, 3) uint8.

        Names as in :meth:`save_intermediates`.
        """
        it = {k: v.detach().cpu().float().numpy() for k, v in self.intermediates.items()}
        g = self.config.geometry
        images: dict[str, np.ndarray] = {}
        images["input"] = (np.clip(it["rgb"].transpose(1, 2, 0), 0, 1) * 255).astype(np.uint8)
        images["mask"] = (it["mask"] > 0.5).astype(np.uint8) * 255
        images["silhouette"] = (1.0 / (1.0 + np.exp(-it["silhouette_logits"])) * 255).astype(np.uint8)
        d = it["masked_depth"]
        valid = d > 0
        lo, hi = (float(d[valid].min()), float(d[valid].max())) if valid.any() else (0.0, 1.0)
        images["depth"] = _colour(hi + lo - d, valid, lo, hi, "magma")  # near = bright
        # both maps on one colour scale, the partial map's range of hits (the inpainted map's
        # values outside it are clipped), and one no-hit rule (black)
        partial_hits = it["partial_sph"] < g.sph_nohit_min
        near = 1.0 - it["partial_sph"][partial_hits]
        lo, hi = (float(near.min()), float(near.max())) if near.size else (0.0, 1.0)
        for name in ("partial_sph", "full_sph"):
            s = it[name]
            images[name] = _colour(1.0 - s, s < g.sph_nohit_min, lo, hi, "viridis")
        for name in ("vox_sph", "vox_depth", "probability"):
            v = it[name]  # [x, y, z]
            front = v.max(axis=2).T[::-1]  # rows −y, cols +x (as seen from the camera)
            side = v.max(axis=0).T[::-1, ::-1]  # seen from +x: rows −y, cols −z
            top = v.max(axis=1).T  # seen from +y: rows +z, cols +x
            sep = np.ones((v.shape[1], 1), np.float32)
            images[name] = _colour(np.concatenate([front, sep, side, sep, top], axis=1), np.ones((v.shape[1], 3 * v.shape[0] + 2), bool), 0.0, 1.0, "gray")
        return images
