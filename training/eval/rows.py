"""The models behind Table 1's rows and what each predicts for one view.

==========================  =====================================================================
GenRe                       the full model (depth net → partial map → inpainting → voxels → refiner)
GenRe-Oracle                the true depth (and mask) in place of the depth net
GenRe-SphOracle             the true depth and the true full spherical map: the refiner's inputs
                            all true (the paper's upper bound for the refiner, nested in Oracle)
3D Completion               depth net → depth voxels → a completion net of the refiner's size
GenRe-1step                 RGB → full spherical map in one U-ResNet → GenRe's projection and refiner
                            (the depth channel from GenRe's depth net)
Nearest training shape      the training view whose depth thumbnail is closest to the predicted
                            masked depth; its shape posed as it appears in that view
Truth through the            the view's true voxel target (GeometryConfig.target: the surface shell
representation              or the truncated distance) through marching cubes: what the
                            representation alone loses (the best any voxel row can do)
Noise floor                 the truth against itself resampled (the best any row can do)
==========================  =====================================================================

Every network gets the view's true mask (the film alpha), as the paper's
evaluation did.  When GenRe's weights carve to the silhouette
(``geometry.silhouette_carve``), every voxel row is carved by the same mask
before its mesh is made, the baselines included; the truth is not.  When they
fill the holes in the visible face from the depth map
(``geometry.visible_fusion``), every voxel row with a depth map does so with
its own (GenRe and GenRe-1step GenRe's depth net's, 3D Completion its own, the
oracles the true depth), after the carving.  When they seal the pits in the visible
front (*Seal Pits*), every learned voxel row does so (after any fusion; the truth is left as it is).  When they replace a mesh by a fitted
regular shape (``geometry.primitive_snap``), every row with a depth map is fitted
likewise, to its own depth map and its mesh at the weights' level.  When they average each view with its
mirror image (``geometry.test_time_mirror``), every learned row does so with its own model
(:func:`genre_backend.nets.model.mirror_averaged`).  When they paint the picture outside the mask plain
(``geometry.plain_backdrop``), every learned row sees that picture (the view's true silhouette is the mask).  These steps are ``genre reconstruct``'s own, in its order
(:class:`genre_backend.inference.options.MeshOptions`, resolved against the weights).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import torch

from genre_backend.config import GenreConfig
from genre_backend.nets.outputs import View
from genre_backend.inference.options import BY_NAME, OPTIONS, MeshOptions
from genre_backend.nets.model import GenRe, WeightsError, mirror_averaged
from genre_backend.photo.preprocess import on_plain_backdrop

from .protocol import DEPTH_BLENDS, DIAGNOSTIC_ROWS, REPRESENTATION, ROWS

__all__ = ['Models', 'predict', 'sweep_row', 'SWEEPABLE']

# the mesh options ``genre eval --sweep`` can vary: every setting the weights store (GeometryConfig's option fields)
# but the level, which every row is scored at anyway
SWEEPABLE = tuple(o.name for o in OPTIONS if o.weights and o.name != "threshold")


def sweep_row(name: str, value: Any) -> str:
    """The row name of GenRe with mesh option ``name`` set to ``value`` (``genre eval --sweep``)."""
    shown = ("on" if value else "off") if isinstance(value, bool) else f"{value:g}" if isinstance(value, float) else str(value)
    return f"GenRe [{name}={shown}]"


def median_offset(target: torch.Tensor, moved: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """The median of ``target - moved`` over ``valid``, per batch item, shaped to broadcast over ``moved`` (0 where
    nothing is valid): the shift along the view that puts ``moved`` at ``target``'s offset."""
    out = torch.zeros(moved.shape[0], dtype=moved.dtype, device=moved.device)
    for i in range(moved.shape[0]):
        diff = (target[i] - moved[i])[valid[i]]
        if diff.numel():
            out[i] = diff.median()
    return out.view(-1, *([1] * (moved.dim() - 1)))


@dataclass
class Models:
    genre: GenRe
    completion: torch.nn.Module | None = None
    onestep: torch.nn.Module | None = None
    nearest: object | None = None  # training.learn.baselines.NearestIndex
    wanted: tuple[str, ...] = ROWS  # the rows to produce
    # GenRe again with one mesh option changed, per (name, value): rows sweep_row(name, value) (genre eval --sweep)
    sweeps: tuple[tuple[str, Any], ...] = ()
    # the isosurface levels to score (genre eval --levels); empty: the weights' sweep (GeometryConfig.thresholds)
    levels: tuple[float, ...] = ()

    @property
    def config(self) -> GenreConfig:
        return self.genre.config

    def thresholds(self) -> list[float]:
        """The levels every grid row is scored at: ``levels``, or the weights' sweep from threshold_min to threshold_max."""
        return list(self.levels) if self.levels else self.config.geometry.thresholds()

    def rows(self) -> list[str]:
        rows = ["GenRe", "GenRe-Oracle", "GenRe-SphOracle", *DIAGNOSTIC_ROWS]
        if self.completion is not None:
            rows += ["3D Completion", "3D Completion-Oracle"]
        if self.onestep is not None:
            rows.append("GenRe-1step")
        if self.nearest is not None:
            rows.append("Nearest training shape")
        rows.append(REPRESENTATION)
        return [r for r in rows if r in self.wanted] + [sweep_row(n, v) for n, v in self.sweeps]

    def check(self) -> None:
        g = self.config.geometry
        for name, net in (("3D Completion", self.completion), ("GenRe-1step", self.onestep)):
            if net is not None and (net.config.geometry.image_size, net.config.geometry.sph_size, net.config.geometry.voxel_size) != (g.image_size, g.sph_size, g.voxel_size):
                raise WeightsError(f"{name}: its weights were made for another preset than GenRe's ({net.config.preset} vs {self.config.preset})")


def after_networks(out: dict[str, dict], mask: torch.Tensor, config, opts: MeshOptions) -> None:
    """The steps after the networks, genre reconstruct's own (options.py), on every learned row of ``out`` in place.

    A row with a ``"depth"`` map is learned; its depth and map go either way (no row keeps them), its ``"prob"``
    becomes the shaped grid, and a row the regular-shape stage snaps (fitted to the mesh at the weights' level)
    gains ``"mesh"``, that shape at every level.
    """
    for row in out.values():
        if isinstance(row, dict) and "depth" in row:
            view = View(mask, row.pop("depth"), config.camera, row.pop("sph", None))
            o, geometry = row.pop("options", opts), row.get("geometry", config.geometry)
            row["prob"] = o.shape_grid(row["prob"], view, geometry)
            if o.primitive_snap > 0:
                _, v, f, _ = o.mesh(row["prob"], geometry, clean=False)
                v, f, fit = o.snap_mesh(v, f, view)
                if fit is not None:
                    row["mesh"] = (v, f)


@torch.no_grad()
def predict(models: Models, sample: dict[str, torch.Tensor], device) -> dict[str, dict]:
    """Every row's prediction for one view: {row: {"prob": (N³) or "points": (P, 3)}}, plus "depth_abs_err".

    A row whose mesh the weights' regular-shape stage replaced (``geometry.primitive_snap``) also has
    ``"mesh"``: (vertices (V, 3), faces (F, 3)), which is scored at every level in place of ``prob``.
    """
    m = models.genre
    mask = sample["mask"][None].to(device)
    shown = sample["rgb"][None].to(device)  # the render; the picture the nets see follows the options (plain_backdrop)
    depth = sample["depth"][None].to(device)
    full = sample["full_sph"][None].to(device)
    out: dict[str, dict] = {}
    true_depth = torch.where(mask, depth, torch.zeros_like(depth))[0].cpu()
    opts = MeshOptions().resolved(m.config.geometry)  # the weights' own options, as genre reconstruct takes them by default
    mirror = opts.test_time_mirror  # every learned row alike
    rgb = on_plain_backdrop(shown, mask) if opts.plain_backdrop else shown
    g = m(rgb, mask=mask, mirror=mirror)
    def row_of(n) -> dict:  # a pass's grid and what the steps after the networks read of it
        return {"prob": torch.sigmoid(n.logits)[0, 0].cpu(), "depth": n.masked_depth[0].cpu(), "sph": n.full_sph[0].cpu()}

    out["GenRe"] = row_of(g)
    for name, value in models.sweeps:  # the networks run again only where the option changes their pass (the mirror)
        swept = dataclasses.replace(opts, **{name: value})
        same = swept.test_time_mirror == mirror and swept.plain_backdrop == opts.plain_backdrop
        s = g if same else m(on_plain_backdrop(shown, mask) if swept.plain_backdrop else shown, mask=mask,
                             mirror=swept.test_time_mirror)
        out[sweep_row(name, value)] = {**row_of(s), "options": swept,  # and its surface made with the changed setting (hole_closing)
                                       "geometry": dataclasses.replace(m.config.geometry, **{BY_NAME[name].weights: value})}
    pred_depth = g.masked_depth
    valid = mask & (depth > 0)
    err = float(((g.depth - depth).abs() * valid).sum() / valid.sum().clamp(min=1))
    out["depth_abs_err"] = err
    if "GenRe-Oracle" in models.wanted:
        out["GenRe-Oracle"] = row_of(m(rgb, mask=mask, depth=depth, mirror=mirror))
    for name, moved in (("GenRe-OffsetOracle", g.depth), ("GenRe-ReliefOracle", depth)):
        if name in models.wanted:  # one depth map moved along the view to the other's median offset over the mask
            other = depth if moved is g.depth else g.depth
            shifted = moved + median_offset(other, moved, valid)
            out[name] = row_of(m(rgb, mask=mask, depth=shifted, mirror=mirror))
    for name, share in DEPTH_BLENDS.items():
        if name in models.wanted:  # the true depth plus that share of the depth net's error, where the truth has depth
            blended = torch.where(valid, depth + share * (g.depth - depth), g.depth)
            out[name] = row_of(m(rgb, mask=mask, depth=blended, mirror=mirror))
    if "GenRe-SphOracle" in models.wanted:
        out["GenRe-SphOracle"] = row_of(m(rgb, mask=mask, depth=depth, full_sph=full, mirror=mirror))
    if models.completion is not None:
        def completion(r, k, d, s):
            return models.completion(r, mask=k, depth=d)["logits"]

        c = models.completion(rgb, mask=mask)
        logits = mirror_averaged(completion, rgb, mask, logits=c["logits"]) if mirror else c["logits"]
        out["3D Completion"] = {"prob": torch.sigmoid(logits)[0, 0].cpu(), "depth": c["masked_depth"][0].cpu()}
        if "3D Completion-Oracle" in models.wanted:  # the baseline from the true depth: GenRe-Oracle's counterpart
            logits = mirror_averaged(completion, rgb, mask, depth) if mirror else completion(rgb, mask, depth, None)
            out["3D Completion-Oracle"] = {"prob": torch.sigmoid(logits)[0, 0].cpu(), "depth": true_depth}
    if models.onestep is not None:
        own_map = models.onestep(rgb).clamp(0.0, 1.0)  # the view's own map: the refiner's input and the hull trim's

        def onestep(r, k, d, s):  # the depth channel from GenRe's depth net, as in the view's own pass
            if r is rgb:
                return m.refine(m.sph_voxels(own_map), m.depth_voxels(pred_depth))
            own = m.masked_depth(m.depth_net(r)["depth"], k)
            return m.refine(m.sph_voxels(models.onestep(r).clamp(0.0, 1.0)), m.depth_voxels(own))

        logits = mirror_averaged(onestep, rgb, mask) if mirror else onestep(rgb, mask, None, None)
        out["GenRe-1step"] = {"prob": torch.sigmoid(logits)[0, 0].cpu(), "depth": pred_depth[0].cpu(), "sph": own_map[0].cpu()}
    after_networks(out, mask[0], m.config, opts)
    if REPRESENTATION in models.wanted:
        out[REPRESENTATION] = {"prob": sample["voxels"]}
    if models.nearest is not None:
        i = models.nearest.query(pred_depth)[0]
        out["Nearest training shape"] = {"points": models.nearest.view_points(i), "retrieved": f"{models.nearest.shape_id(i)}/{models.nearest.views[i]}"}
    return out
