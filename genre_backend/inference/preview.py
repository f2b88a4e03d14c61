"""One PNG that shows what a reconstruction did: ``genre reconstruct --preview``.

Top row: the framed photo, the mask, the predicted depth, the partial and the
inpainted full spherical map.  Bottom row: the mesh rendered with Blender
(Cycles on the CPU, :func:`genre_backend.inference.blender.render_meshes`) from the
photo's own viewpoint, where it should match the photo's silhouette, and from
the right side, where the parts GenRe had to hallucinate show.
"""

from __future__ import annotations

import numpy as np

from .blender import render_meshes

__all__ = ["preview_image"]


def preview_image(result, samples: int = 16, size: int | None = None) -> np.ndarray:
    """(H, W, 3) uint8: the preview of a :class:`genre_backend.inference.reconstruct.Reconstruction`.

    ``size``: side of each panel in pixels (default: twice the preset's image
    size, at least 256).  ``samples``: Cycles samples of the two mesh renders.
    """
    from .blender import private_matplotlib_config

    private_matplotlib_config()  # (never $HOME/.config/matplotlib)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    size = size or max(256, 2 * result.config.geometry.image_size)
    images = result.intermediate_images()
    if len(result.faces):
        front, side = render_meshes([(result.vertices, result.faces)], size=size, samples=samples, camera=result.config.camera)[0]
    else:  # nothing above the threshold: say so instead of rendering an empty scene
        front = side = np.full((size, size, 3), 255, np.uint8)
    top = [("photo (framed)", images["input"]), (f"mask ({result.mask_source})", images["mask"]),
           ("depth (near = bright)", images["depth"]), ("partial spherical map", images["partial_sph"]),
           ("full spherical map (inpainted)", images["full_sph"])]
    bottom = [("mesh, photo viewpoint", front), ("mesh, from the right", side)]
    fig, axes = plt.subplots(2, 5, figsize=(15, 6.6))
    for ax, (title, img) in zip(axes[0], top):
        ax.imshow(img, cmap="gray" if img.ndim == 2 else None, interpolation="nearest")
        ax.set_title(title, fontsize=10)
    for ax, (title, img) in zip(axes[1], bottom):
        ax.imshow(img)
        ax.set_title(title, fontsize=10)
    for ax in axes.ravel():
        ax.axis("off")
    total = sum(v for k, v in result.timings.items() if k != "preview")
    axes[1, 2].text(0.0, 0.5, "\n".join([
        f"{result.image.name}",
        f"{len(result.vertices):,} vertices, {len(result.faces):,} faces" if len(result.faces) else "empty mesh: lower --threshold",
        f"threshold {result.threshold:.2f}, preset {result.config.preset}",
        f"reconstruction {total:.2f} s",
    ]), fontsize=11, va="center", transform=axes[1, 2].transAxes)
    fig.tight_layout()
    fig.canvas.draw()
    rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return rgb
