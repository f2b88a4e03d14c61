"""One PNG that shows what a reconstruction did: ``genre reconstruct --preview``.

The sheet (:data:`SHEET`, 1,500 × 810 px) has a row of small panels at the
top (the framed photo, the mask, the predicted depth, the partial and the
inpainted full spherical maps, and a few lines of figures) above three large
views of the mesh, which take about 60 % of the sheet: from the photo's own
viewpoint (where it should match the photo's silhouette), from the object's
right (the camera turned 90° about the photo's vertical) and from behind,
where the parts GenRe had to hallucinate show.  The mesh views are rendered
with Blender's Workbench (:func:`genre_backend.output.blender.render_views`),
framed to fill their panels at one common scale, and carry the photo's colour
(:meth:`~genre_backend.inference.result.Reconstruction.texture`) when ``textured``.
"""

from __future__ import annotations

import numpy as np

from .blender import render_views

__all__ = ["SHEET", "MESH_VIEWS", "preview_layout", "preview_image"]

# Sheet size in pixels (width, height) and its grid: small panels on top, mesh views below.
SHEET = (1500, 810)
_SMALL, _BIG, _GAP, _TITLE = 236, 490, 8, 26
MESH_VIEWS = (("front", "mesh, photo viewpoint"), ("side", "mesh, from the right (90°)"), ("back", "mesh, from behind"))
_TOP = ("input", "mask", "depth", "partial_sph", "full_sph", "notes")


def preview_layout() -> dict[str, tuple[int, int, int, int]]:
    """Panel name → (x0, y0, x1, y1) in sheet pixels (rows downward), image area only (titles above it).

    Names: ``input``, ``mask``, ``depth``, ``partial_sph``, ``full_sph``,
    ``notes`` (the figures' text box) and the mesh views ``front``, ``side``,
    ``back``.
    """
    width, _ = SHEET
    boxes = {}
    step = (width - _GAP) / len(_TOP)
    for i, name in enumerate(_TOP):
        x0 = round(_GAP + i * step)
        boxes[name] = (x0, _TITLE, x0 + _SMALL, _TITLE + _SMALL)
    y0 = _TITLE + _SMALL + _TITLE + _GAP
    step = (width - _GAP) / len(MESH_VIEWS)
    for i, (name, _) in enumerate(MESH_VIEWS):
        x0 = round(_GAP + i * step)
        boxes[name] = (x0, y0, x0 + _BIG, y0 + _BIG)
    return boxes


def preview_image(result, samples: int = 16, textured: bool = False) -> np.ndarray:
    """(810, 1500, 3) uint8: the preview of a :class:`genre_backend.inference.result.Reconstruction`.

    ``textured``: the mesh views show the photo's colour (as ``--texture``
    writes it), else a neutral clay.  ``samples`` is kept for callers of
    the earlier Cycles preview and has no effect: the mesh views are
    rendered at their panels' size with Workbench.
    """
    del samples
    from .blender import private_matplotlib_config

    private_matplotlib_config()  # (never $HOME/.config/matplotlib)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    boxes = preview_layout()
    width, height = SHEET
    images = result.intermediate_images()
    big = _BIG
    if len(result.faces):
        uv = tex = None
        if textured:
            t = result.texture()
            uv, tex = t.face_uv, t.image
        views = render_views(result.vertices, result.faces, big, camera=result.config.camera, uv=uv, texture=tex,
                             views=tuple(name for name, _ in MESH_VIEWS))
    else:  # nothing above the threshold: say so instead of rendering an empty scene
        views = [np.full((big, big, 3), 255, np.uint8)] * len(MESH_VIEWS)
    top = {"input": ("photo (framed)", images["input"]), "mask": (f"mask ({result.mask_source})", images["mask"]),
           "depth": ("depth (near = bright)", images["depth"]), "partial_sph": ("partial spherical map", images["partial_sph"]),
           "full_sph": ("full spherical map (inpainted)", images["full_sph"])}
    colour = ", photo colour" if textured and len(result.faces) else ""
    panels = dict(top)
    for (name, title), img in zip(MESH_VIEWS, views):
        panels[name] = (title + colour, img)
    dpi = 100
    fig = plt.figure(figsize=(width / dpi, height / dpi), dpi=dpi)
    fig.patch.set_facecolor("white")

    def axes_at(box):
        x0, y0, x1, y1 = box
        return fig.add_axes((x0 / width, 1 - y1 / height, (x1 - x0) / width, (y1 - y0) / height))

    for name, (title, img) in panels.items():
        ax = axes_at(boxes[name])
        ax.imshow(img, cmap="gray" if img.ndim == 2 else None, interpolation="nearest" if name in top else "antialiased",
                  aspect="auto")
        ax.set_title(title, fontsize=10 if name in top else 12, pad=4)
        ax.axis("off")
    ax = axes_at(boxes["notes"])
    ax.axis("off")
    total = sum(v for k, v in result.timings.items() if k != "preview")
    ax.text(0.02, 0.5, "\n".join([
        f"{result.image.name}",
        f"{len(result.vertices):,} vertices" if len(result.faces) else "empty mesh:",
        f"{len(result.faces):,} faces" if len(result.faces) else "lower --threshold",
        f"threshold {result.options.threshold:.2f}",
        f"preset {result.config.preset}",
        f"reconstruction {total:.2f} s",
        "mesh views: one scale, framed",
    ]), fontsize=10, va="center", transform=ax.transAxes)
    fig.canvas.draw()
    rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return rgb
