"""Typed configuration: every resolution, width and threshold of the project.

Three presets share one code path:

* ``paper``   -- the numbers of the original GenRe (256² images, 128² spherical
  maps padded to 160², 128³ voxels).
* ``default`` -- the CPU preset this project trains and ships (128² images,
  64² spherical maps padded to 96², 64³ voxels, narrow networks).
* ``wide``    -- ``default``'s resolutions with the nets a GPU burst trains
  (the shipped weights' inpainting net; a refiner twice as wide at the fine
  levels, capped at 64 channels, with a full-resolution branch).

Modules never hard-code a resolution: they take a :class:`GenreConfig` (or one
of its parts) and read it from there.  Configs round-trip through plain JSON
(:meth:`GenreConfig.to_dict` / :meth:`GenreConfig.from_dict`) so that they can
be stored beside weights without pickle.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

from .protocol import Option, OptionError
from .validation import MAX_HOLE_CLOSING, check_threshold

__all__ = [
    "CameraConfig",
    "GeometryConfig",
    "SETTINGS",
    "check_setting",
    "NetworkConfig",
    "INPAINT_HEADS",
    "GenreConfig",
    "PRESETS",
    "TARGETS",
    "get_preset",
]

# ---- bounds: what a config may hold (a weights file carries one; anything outside is refused at load) ----
# The resolutions are bounded by what one 24 GiB device (or the CPU's memory) can run: at the bounds
# the refiner's full-resolution grids are 256³ (64 MiB a channel) and the spherical map's points
# (512·8)² = 16.8 M.  The widths are bounded each here, and the whole model's parameter count at
# load (nets.model.MAX_PARAMETERS), so that building a model never allocates more than a few GiB.
MAX_IMAGE_SIZE = 1024
MAX_SPH_SIZE = 512
MAX_VOXEL_SIZE = 256
MAX_SPH_SUPERSAMPLE = 8
MAX_SHELL_DILATION = 8
MAX_CHAMFER_POINTS = 1_000_000
MIN_THRESHOLD_STEP = 0.001
MIN_OBJECT_FRACTION = 0.05
MAX_NET_WIDTH = 2048  # each of depth_widths, inpaint_widths
MAX_DECODER_BLOCKS = 8
MAX_REFINER_NF = 64
MAX_REFINER_FC = 8192
MAX_REFINER_FULL_NF = 256
MAX_FULL_BRANCH_FLOATS = 2**29  # refiner_full_nf · voxel_size³: 2 GiB of float32 per full-resolution activation
MAX_MM = 1000.0  # lens and sensor, millimetres
MIN_FOV_DEG, MAX_FOV_DEG = 1.0, 170.0
# The camera must stay outside the voxel cube [-0.5, 0.5]³, whose corners lie √3/2 ≈ 0.866 from its
# centre, and near enough for the object (diagonal 1) to span more than a pixel or two.
MIN_DISTANCE, MAX_DISTANCE = 0.87, 100.0
MAX_PRESET_CHARS = 100


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _check_int(where: str, value, lo: int, hi: int) -> None:
    if not (isinstance(value, int) and not isinstance(value, bool) and lo <= value <= hi):
        raise ValueError(f"{where}: expected an int in [{lo}, {hi:,}], got {_shown(value)}")


def _check_float(where: str, value, lo: float, hi: float, lo_open: bool = False) -> None:
    ok = _number(value) and math.isfinite(value) and (lo < value if lo_open else lo <= value) and value <= hi
    if not ok:
        raise ValueError(f"{where}: expected a finite number in {'(' if lo_open else '['}{lo:g}, {hi:g}], got {_shown(value)}")


def _shown(value) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:80] + "…"


@dataclass(frozen=True)
class CameraConfig:
    """The pinhole camera every view is rendered and reconstructed with.

    The defaults are the original's: a 50 mm lens on a square 30.594 mm
    sensor (horizontal field of view ≈ 34.0°), 2.2 units from the object
    centre.  Objects are normalised to a bounding-box diagonal of 1.
    """

    lens_mm: float = 50.0
    sensor_mm: float = 30.594
    distance: float = 2.2
    # Elevation range (degrees) of random training views; azimuth is uniform.
    elevation_min_deg: float = -10.0
    elevation_max_deg: float = 45.0

    def __post_init__(self):
        _check_float("camera.lens_mm", self.lens_mm, 0.0, MAX_MM, lo_open=True)
        _check_float("camera.sensor_mm", self.sensor_mm, 0.0, MAX_MM, lo_open=True)
        if not MIN_FOV_DEG <= self.fov_deg <= MAX_FOV_DEG:
            raise ValueError(f"camera: lens_mm {self.lens_mm:g} on sensor_mm {self.sensor_mm:g} gives a field of view of "
                             f"{self.fov_deg:.3g}°, expected {MIN_FOV_DEG:g}–{MAX_FOV_DEG:g}°")
        _check_float("camera.distance", self.distance, MIN_DISTANCE, MAX_DISTANCE, lo_open=True)
        _check_float("camera.elevation_min_deg", self.elevation_min_deg, -90.0, 90.0)
        _check_float("camera.elevation_max_deg", self.elevation_max_deg, -90.0, 90.0)
        if self.elevation_min_deg > self.elevation_max_deg:
            raise ValueError(f"camera: elevation_min_deg {self.elevation_min_deg:g} is above elevation_max_deg {self.elevation_max_deg:g}")

    @property
    def fov_deg(self) -> float:
        """Full horizontal (= vertical, square sensor) field of view in degrees."""
        return math.degrees(2.0 * math.atan(0.5 * self.sensor_mm / self.lens_mm))

    def focal_px(self, image_size: int) -> float:
        """Focal length in pixels for a square image of ``image_size`` pixels."""
        return self.lens_mm / self.sensor_mm * image_size


TARGETS = ("shell", "distance")  # the refiner's representations (GeometryConfig.target)


def _setting(default: Any, **spec) -> Any:
    """A field that is also a mesh option: its default and its :class:`~genre_backend.protocol.Option`."""
    return field(default=default, metadata={"option": Option(**spec)})


def check_setting(spec: Option, value: Any, target: str, where: str) -> Any:
    """``value`` of the setting ``spec`` checked (:meth:`Option.check`), and refused when it is on but ``target`` is
    not the distance target that a ``distance_only`` setting needs; :class:`~genre_backend.protocol.OptionError`."""
    value = spec.check(value, where)
    if spec.distance_only and value and target != "distance":
        raise OptionError(f"{where}: these weights predict the {target!r} target; only distance grids take it", spec.name)
    return value


@dataclass(frozen=True)
class GeometryConfig:
    """Resolutions and tolerances of the deterministic geometry between the nets."""

    image_size: int = 128
    sph_size: int = 64  # spherical maps are sph_size × sph_size (polar × azimuth)
    sph_pad: int = 16  # periodic padding on each side before the inpainting net (padded side: a multiple of 32)
    voxel_size: int = 64  # voxels over the cube [-0.5, 0.5]^3
    # Spherical map → points: values ≥ sph_nohit_min count as "no hit"; the map is resampled sph_supersample times
    # finer first so that the points leave no holes in the grid (docs/lab/reconstruct-settings.md, "The network levels").
    sph_nohit_min: float = 0.9999
    sph_supersample: int = 2
    # The inpainting net's "hit" head (network.inpaint_head): a ray of the full map hits the surface where the head's
    # hit probability exceeds this.  A dropped part of the back costs Chamfer far more than a point near the true
    # radius; at 0.2 nearly every ray hits (measured: docs/lab/reconstruct-settings.md, "The network levels").
    sph_hit_probability: float = 0.2
    # Depth → surface triangulation: a triangle of neighbouring pixels is kept only if its longest 3D edge is at most
    # this many times the pixel footprint at its depth (depth/focal); 10 keeps surfaces up to ~84° from facing the
    # camera and drops the jumps between an object's parts or to the background.
    depth_edge_max_ratio: float = 10.0
    # What the refiner predicts (genre_backend.geometry.mesh_voxels.mesh_to_target):
    # "shell" -- the paper's surface shell: surface voxels dilated shell_dilation times
    #            (26-neighbourhood); its marching-cubes surface lies 1-2 voxels off the true one.
    # "distance" -- a truncated unsigned distance: 1 − d/(distance_band voxels), clipped to
    #            [0, 1]; threshold t is the iso-surface at (1 − t)·distance_band voxels from
    #            the surface, so its sheets lie a fraction of a voxel off it and thin parts
    #            (an open sheet, a wire) stay.
    # Weights stored without the key were trained on the shell.
    target: str = "shell"
    shell_dilation: int = 1
    distance_band: float = 2.0
    # The distance target's surface (geometry.mesh_voxels.onto_surface): the sheets are moved back
    # toward the surface but stop this many voxels short of it, so that a part thinner than a voxel
    # (a wing, a sheet) keeps a thickness of twice this instead of collapsing into two coincident
    # sheets with opposite normals (its cost: docs/lab/reconstruct-settings.md, "The network levels").
    surface_margin: float = 0.25
    # The isosurface level a mesh is cut at: chosen on seen-test views by ``genre eval`` and stored by
    # training/eval/install.py (--thresholds); the mesh option ``threshold``.
    default_threshold: float = _setting(
        0.5, name="threshold", kind="float", lo=0.0, hi=1.0, lo_open=True, hi_open=True, metavar="T", label="Threshold",
        help="isosurface level of the voxel grid: lower gives a fuller shape")
    # The distance target's holes (geometry.mesh_voxels.fill_enclosed): a blurry prediction leaves
    # gaps in the tube around the surface, through which the tube's inner sheet joins the outer one
    # (a hole into the object).  Gaps up to about twice this many voxels across are sealed (a
    # morphological closing of the object before its inside is filled); openings wider than that
    # (a torus's hole, a cup's mouth) stay.  0: nothing is sealed.  Weights stored without the key: 0.
    hole_closing: int = _setting(
        0, kind="int", lo=0, hi=12, unit="voxels", metavar="K", label="Seal Holes",
        help="seal holes in the mesh up to about twice this many voxels across (0: none; more also fills narrow gaps "
             "between parts)", chosen="genre eval --sweep hole_closing=… on seen-test views (its rule in the table)")
    # The one-view visual hull (geometry.voxels.silhouette_ramp): the refiner's output is capped by
    # a ramp that falls from 1 to 0 across the object's outline (one voxel wide, 0.5 on the outline)
    # before the mesh is made, in reconstruction and in evaluation (every learned row alike; never
    # in training).  The refiner's blur spills past the outline the photo shows (measured:
    # docs/lab/reconstruct-settings.md, "Trimmed to the outline").  Weights stored without the key: off.
    silhouette_carve: bool = _setting(
        False, kind="bool", label="Trim to Outline",
        help="cut away what would stick out past the object's outline (the mask) before the mesh is made",
        chosen="chosen on seen-test views (results/decisions.md)")
    # The full map's radial hull (geometry.spherical.sph_hull_ramp: a pixel holds the largest radius its ray meets):
    # the refiner's output capped by a one-voxel ramp across the hull of the map it read, before the mesh is made,
    # in reconstruction and evaluation; weights that store it on are also trained so (training/learn/stage.py).
    # Chosen by scripts/sph_hull.py's rule (results/decisions.md).  Weights stored without the key: off.
    sph_hull_carve: bool = _setting(
        False, kind="bool", label="Trim to Shape Map",
        help="cut away what lies beyond the surface the spherical map (the networks' all-round guess) bounds: "
             "for flat things (a plate, a card); it flattens round ones too", chosen="scripts/sph_hull.py (results/decisions.md)")
    # Map pixels the hull is widened by (2 by that rule; a trim trained through a widened hull teaches only each
    # window's largest pixel and grows spikes, so trained weights store 0) and voxels it is moved outward (the
    # distance target's band, up to distance_band voxels outside the surface, needs the room in training).
    sph_hull_spread: int = 2
    sph_hull_offset: float = 0.0
    # Holes in the face the camera sees (geometry.visible_front.fuse_visible_surface): the object's pixels
    # whose ray meets nothing above the level get the masked depth map's own surface (its distance
    # target, max with the refiner's) before the mesh is made, in reconstruction and in evaluation
    # (every row with a depth map alike). Chosen per weights on seen-test views by
    # scripts/visible_fusion.py (docs/lab/reconstruct-settings.md, "Holes in the side the photo shows").
    # Weights stored without the key: off.
    visible_fusion: bool = _setting(
        False, kind="bool", distance_only=True, label="Fill Visible Holes",
        help="fill the holes the model leaves in the side the photo shows with the estimated depth's surface",
        chosen="scripts/visible_fusion.py on seen-test views")
    # Pits in the face the camera sees (geometry.visible_front.seal_pits): a blurry front wall falling through onto
    # the back's inside leaves a narrow, deep well; basins of the visible front deeper than 2 voxels and at most about
    # twice this across are filled with the front around them, in reconstruction and evaluation, after any fusion
    # (docs/lab/reconstruct-settings.md, "Pits in the side the photo shows").  Weights stored without the key: 0.
    pit_sealing: int = _setting(
        0, kind="int", lo=0, hi=MAX_HOLE_CLOSING, unit="voxels", distance_only=True, metavar="K", label="Seal Pits",
        help="fill narrow, deep wells in the side the photo shows, up to about twice this many voxels across, with the "
             "surface around them (0: none)", chosen="genre eval --sweep on the product test split (results/decisions.md)")
    # Dents in the unseen back (geometry.visible_front.seal_back: a faint back leaves a dish inside a rim) filled to
    # their rim, after the pits; on only by the rule in results/decisions.md.  Weights stored without the key: off.
    back_sealing: bool = _setting(
        False, kind="bool", distance_only=True, label="Seal Back",
        help="fill the dents in the back the networks guess (the side the photo does not show) up to the rim around "
             "them, so that a round thing is not hollowed out behind", chosen="results/decisions.md")
    # Regular shapes (geometry.primitives.snap): the mesh is replaced by the box, cylinder, cone, torus or
    # ellipsoid fitted to the mask's outline, the mesh and the depth when its disagreement (1 - the IoU of
    # its silhouette with the mask, or twice the mesh's mean distance to it over its diagonal, whichever
    # is larger) is at most this; in reconstruction and in evaluation (every row with a depth map alike).
    # Stored only by the rule in results/decisions.md.  Weights stored without the key: 0 (off).
    primitive_snap: float = _setting(
        0.0, kind="float", lo=0.0, hi=1.0, hi_open=True, metavar="TOL", label="Snap Shapes",
        help="replace the mesh by a fitted box, cylinder, cone, torus or ellipsoid when its silhouette matches the mask "
             "and it stays on the mesh within this tolerance (0: never)",
        chosen="scripts/primitive_snap.py on training-split views (results/decisions.md)")
    # Test-time mirroring (nets.model.mirror_averaged): the view is also run reflected left to right (the
    # scene mirrored in the view frame's x = 0 plane, a view the nets were trained on with --mirror), the
    # refiner's output reflected back and the two probabilities averaged before the mesh is made; in
    # reconstruction and in evaluation (every learned row alike).  Twice the nets' time.  Turned on only by
    # the rule in results/decisions.md.  Weights stored without the key: off.
    test_time_mirror: bool = _setting(
        False, kind="bool", label="Mirror Average",
        help="also run the photo's mirror image and average the two (about twice the networks' time)",
        chosen="results/decisions.md")
    # The photo outside a given mask (not the depth net's own silhouette) painted grey before any net sees it
    # (photo.preprocess.on_plain_backdrop), in reconstruction and evaluation alike.  Weights without the key: off.
    plain_backdrop: bool = _setting(
        False, kind="bool", label="Plain Backdrop",
        help="paint the photo outside the mask plain grey before the networks see it (a mask from a file, the alpha, "
             "a box, strokes or the salient net)", chosen="results/decisions.md")
    # The seen side kept: the full spherical map takes the partial map's own value wherever the partial map
    # sees the surface, the inpainting net's elsewhere (nets.model.GenRe.forward).  The net predicts every
    # pixel afresh; on the seen side its map is ~1.7x further from the truth than its own input
    # (scripts/inpaint_errors.py, results/stage_errors/inpaint.md).  Turned on only by the rule in
    # results/decisions.md.  Weights stored without the key: off.
    sph_keep_seen: bool = False
    # Isosurface thresholds swept in evaluation (inclusive range, step).  The paper swept 0.30–0.70 (the ``paper``
    # preset keeps that); the default preset's seen-test choice sat at its top (0.70, 0.75), so it goes on to 0.90.
    threshold_min: float = 0.30
    threshold_max: float = 0.90
    threshold_step: float = 0.05
    chamfer_points: int = 1024
    # Framing of photos (genre_backend.photo.preprocess): the square crop is sized so that the mask's longest side
    # spans this fraction of the image.  Measured medians: 0.50 over 88 real default renders (aircraft), 0.66 over the
    # box/table test renders; canonical renders (diagonal 1 at distance 2.2) span 0.45-0.7.
    object_fraction: float = 0.5

    def __post_init__(self):
        for name, hi in (("image_size", MAX_IMAGE_SIZE), ("sph_size", MAX_SPH_SIZE), ("voxel_size", MAX_VOXEL_SIZE),
                         ("sph_supersample", MAX_SPH_SUPERSAMPLE), ("chamfer_points", MAX_CHAMFER_POINTS)):
            _check_int(f"geometry.{name}", getattr(self, name), 1, hi)
        _check_int("geometry.sph_pad", self.sph_pad, 0, self.sph_size)
        _check_int("geometry.shell_dilation", self.shell_dilation, 0, MAX_SHELL_DILATION)
        _check_float("geometry.sph_nohit_min", self.sph_nohit_min, 0.0, 1.0, lo_open=True)
        _check_float("geometry.depth_edge_max_ratio", self.depth_edge_max_ratio, 0.0, 1000.0, lo_open=True)
        _check_float("geometry.threshold_step", self.threshold_step, MIN_THRESHOLD_STEP, 1.0)
        _check_float("geometry.object_fraction", self.object_fraction, MIN_OBJECT_FRACTION, 1.0)
        if self.target not in TARGETS:
            raise ValueError(f"geometry.target: expected one of {TARGETS}, got {self.target!r}")
        if not (math.isfinite(self.distance_band) and 0.5 <= self.distance_band <= 8.0):
            raise ValueError(f"geometry.distance_band: expected voxels in [0.5, 8], got {self.distance_band!r}")
        for spec in SETTINGS:
            check_setting(spec, getattr(self, spec.weights), self.target, f"geometry.{spec.weights}")
        if not isinstance(self.sph_keep_seen, bool):
            raise ValueError(f"geometry.sph_keep_seen: expected true or false, got {self.sph_keep_seen!r}")
        _check_int("geometry.sph_hull_spread", self.sph_hull_spread, 0, 8)
        _check_float("geometry.sph_hull_offset", self.sph_hull_offset, 0.0, 8.0)
        if not (math.isfinite(self.surface_margin) and 0.0 <= self.surface_margin <= self.distance_band):
            raise ValueError(f"geometry.surface_margin: expected voxels in [0, distance_band], got {self.surface_margin!r}")
        for name in ("threshold_min", "threshold_max"):
            check_threshold(f"geometry.{name}", getattr(self, name))
        if not (self.threshold_min <= self.threshold_max and self.threshold_step > 0):
            raise ValueError(f"geometry: threshold sweep {self.threshold_min}..{self.threshold_max} step {self.threshold_step} is empty")
        if not (math.isfinite(self.sph_hit_probability) and 0.0 < self.sph_hit_probability < 1.0):
            raise ValueError(f"geometry.sph_hit_probability: expected a number in (0, 1), got {self.sph_hit_probability!r}")

    @property
    def voxel_pitch(self) -> float:
        """Edge length of one voxel in world units (the cube has edge 1)."""
        return 1.0 / self.voxel_size

    @property
    def sph_padded_size(self) -> int:
        return self.sph_size + 2 * self.sph_pad

    def thresholds(self) -> list[float]:
        """The isosurface thresholds to sweep, rounded to the step's precision."""
        n = int(round((self.threshold_max - self.threshold_min) / self.threshold_step))
        return [round(self.threshold_min + i * self.threshold_step, 6) for i in range(n + 1)]


# the fields of GeometryConfig that are also mesh options, in their order (name: the option's, weights: the field's)
SETTINGS: tuple[Option, ...] = tuple(
    dataclasses.replace(f.metadata["option"], name=f.metadata["option"].name or f.name, weights=f.name)
    for f in dataclasses.fields(GeometryConfig) if "option" in f.metadata)

INPAINT_HEADS = ("value", "hit")


@dataclass(frozen=True)
class NetworkConfig:
    """Widths of the three networks (see :mod:`genre_backend.nets.uresnet` and :mod:`genre_backend.nets.refiner`).

    The ``paper`` preset reproduces the original's sizes: depth net 29.9 M
    parameters (original 30.8 M), inpainting net 15.7 M (15.9 M), refiner
    52.5 M (53.5 M).
    """

    # U-ResNet-18 widths of the four ResNet stages, for the depth and inpainting nets
    depth_widths: tuple[int, int, int, int] = (16, 32, 64, 128)
    depth_decoder_blocks: int = 1  # basic blocks after each decoder fusion (one decoder per head)
    inpaint_widths: tuple[int, int, int, int] = (16, 32, 64, 128)
    inpaint_decoder_blocks: int = 0
    # what the inpainting net predicts (genre_backend.nets.inpaint_net): "value", the paper's one map
    # regressed with "no hit" = 1 as a value; or "hit", a hit probability and the radius as two outputs
    # (a third of a full map is "no hit", and regressing it as a value blurs it into the radii).
    # Weights stored without the key are "value".
    inpaint_head: str = "value"
    refiner_nf: int = 8  # refiner base width; level k has nf·2^k channels
    refiner_fc: int = 256  # width of the refiner's fully-connected bottleneck
    # width of the refiner's non-linear full-resolution branch (0: none; weights stored without the key
    # have none).  The presets have none; the product recipe grows one (training/learn/recipe.py).
    refiner_full_nf: int = 0
    # the refiner's widths nf·2^k capped at this (0: no cap; weights stored without the key have none): the preset
    # 'wide' has a wide base without the parameters of the deepest levels, so that its file stays small enough to
    # travel to a lent GPU and back (training/data/pack.py: the carry budget)
    refiner_max_width: int = 0
    # the depth net predicts planar depth as distance + output / depth_output_scale
    depth_output_scale: float = 10.0

    def __post_init__(self):
        for name in ("depth_widths", "inpaint_widths"):
            widths = getattr(self, name)
            if not (isinstance(widths, (tuple, list)) and len(widths) == 4):
                raise ValueError(f"network.{name}: expected 4 widths, got {_shown(widths)}")
            for w in widths:
                _check_int(f"network.{name}", w, 1, MAX_NET_WIDTH)
        _check_int("network.depth_decoder_blocks", self.depth_decoder_blocks, 0, MAX_DECODER_BLOCKS)
        _check_int("network.inpaint_decoder_blocks", self.inpaint_decoder_blocks, 0, MAX_DECODER_BLOCKS)
        _check_int("network.refiner_nf", self.refiner_nf, 1, MAX_REFINER_NF)
        _check_int("network.refiner_fc", self.refiner_fc, 1, MAX_REFINER_FC)
        _check_int("network.refiner_max_width", self.refiner_max_width, 0, MAX_NET_WIDTH)
        if self.inpaint_head not in INPAINT_HEADS:
            raise ValueError(f"network.inpaint_head: expected one of {INPAINT_HEADS}, got {self.inpaint_head!r}")
        if not (isinstance(self.refiner_full_nf, int) and not isinstance(self.refiner_full_nf, bool)
                and 0 <= self.refiner_full_nf <= MAX_REFINER_FULL_NF):
            raise ValueError(f"network.refiner_full_nf: expected an int in [0, {MAX_REFINER_FULL_NF}] (0: no full-resolution "
                             f"branch), got {_shown(self.refiner_full_nf)}")
        _check_float("network.depth_output_scale", self.depth_output_scale, 0.0, 1e6, lo_open=True)


@dataclass(frozen=True)
class GenreConfig:
    """The whole configuration of one model: preset name, camera, geometry and networks."""

    preset: str = "default"
    camera: CameraConfig = field(default_factory=CameraConfig)
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)

    def __post_init__(self):
        if not (isinstance(self.preset, str) and 0 < len(self.preset) <= MAX_PRESET_CHARS and self.preset.isprintable()):
            raise ValueError(f"preset: expected a printable name of 1 to {MAX_PRESET_CHARS} characters, got {_shown(self.preset)}")
        floats = self.network.refiner_full_nf * self.geometry.voxel_size ** 3
        if floats > MAX_FULL_BRANCH_FLOATS:
            raise ValueError(f"network.refiner_full_nf {self.network.refiner_full_nf} at geometry.voxel_size "
                             f"{self.geometry.voxel_size}: {floats:,} floats per full-resolution activation, at most "
                             f"{MAX_FULL_BRANCH_FLOATS:,}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> GenreConfig:
        """Build a config from :meth:`to_dict` output, rejecting unknown keys."""
        return _from_dict(cls, data, "config")


def _from_dict(cls: type, data: Any, where: str):
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected an object, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(data) - set(fields)
    if unknown:
        raise ValueError(f"{where}: unknown keys {sorted(unknown)}")
    kwargs = {}
    for name, value in data.items():
        ftype = fields[name].type
        ftype = ftype if isinstance(ftype, str) else getattr(ftype, "__name__", "")
        sub = _DATACLASS_TYPES.get(ftype)
        if sub:
            value = _from_dict(sub, value, f"{where}.{name}")
        else:
            if ftype.startswith("tuple") and isinstance(value, list):
                value = tuple(value)  # JSON has no tuples
            _check_type(f"{where}.{name}", ftype, value)
        kwargs[name] = value
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise ValueError(f"{where}: {exc}") from None


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _check_type(where: str, ftype: str, value: Any) -> None:
    """Refuse a stored value whose JSON type is not the field's (``"64"`` for an int, ``null`` for widths, NaN)."""
    if ftype == "int":
        ok = _is_int(value)
    elif ftype == "float":
        ok = (_is_int(value) or isinstance(value, float)) and math.isfinite(value)
    elif ftype == "str":
        ok = isinstance(value, str)
    elif ftype == "bool":
        ok = isinstance(value, bool)
    elif ftype.startswith("tuple[int"):
        ok = isinstance(value, tuple) and len(value) == ftype.count("int") and all(_is_int(v) and v > 0 for v in value)
    else:  # pragma: no cover  (a field type this reader does not know yet)
        raise TypeError(f"{where}: no JSON check for field type {ftype!r}")
    if not ok:
        shown = repr(value)
        raise ValueError(f"{where}: expected {ftype}, got {shown if len(shown) <= 80 else shown[:80] + '…'}")


_DATACLASS_TYPES: dict[str, type] = {
    "CameraConfig": CameraConfig,
    "GeometryConfig": GeometryConfig,
    "NetworkConfig": NetworkConfig,
}


PRESETS: dict[str, GenreConfig] = {
    "default": GenreConfig(preset="default", geometry=GeometryConfig(target="distance")),
    # the nets a GPU burst trains (training/learn/recipe.py: BURST_RECIPES["wide"]): the shipped default weights'
    # depth and inpainting nets; a refiner twice as wide at every resolution down to 8³ (base 16, capped at 64)
    # with a 16-channel full-resolution branch: 4x the default refiner's work at 32³ and 16³ for the same
    # 2.4 M parameters, so that the weights file stays the size of today's (the carry budget, training/data/pack.py)
    "wide": GenreConfig(
        preset="wide",
        geometry=GeometryConfig(target="distance"),
        network=NetworkConfig(inpaint_widths=(32, 64, 128, 256), inpaint_head="hit", refiner_nf=16, refiner_fc=256,
                              refiner_full_nf=16, refiner_max_width=64),
    ),
    "paper": GenreConfig(
        preset="paper",
        geometry=GeometryConfig(image_size=256, sph_size=128, sph_pad=16, voxel_size=128, threshold_max=0.70, target="shell"),
        network=NetworkConfig(
            depth_widths=(64, 128, 256, 512),
            depth_decoder_blocks=3,
            inpaint_widths=(64, 128, 256, 512),
            inpaint_decoder_blocks=0,
            refiner_nf=20,
            refiner_fc=640,
        ),
    ),
}


def get_preset(name: str) -> GenreConfig:
    """Return the named preset (``"default"`` or ``"paper"``)."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}") from None
