"""The mesh options: one frozen record, and the steps after the networks that they steer.

:class:`MeshOptions` holds every mesh option.  Its fields are made from the
fields that carry an :class:`~genre_backend.protocol.Option` in their
metadata: first those of the weights' ``GeometryConfig``
(``genre_backend/config.py``: the settings the weights store and choose,
``threshold`` being ``default_threshold``), then :class:`_OwnOptions`' (the
options with a plain default).  The metadata says the option's kind (float,
int, bool or a choice), its range, where its default comes from, a label and
one line of help.  From it come

* the checks (:meth:`Option.check`, the one check: one message style, ``WHERE: expected
  WHAT, got VALUE``; ``WHERE`` is ``--flag`` for the CLI, ``option 'name'``
  for ``genre serve`` and the bare name in Python);
* the merge of overrides onto the weights' defaults (:meth:`MeshOptions.over`,
  :meth:`MeshOptions.resolved`);
* ``genre reconstruct``'s flags (:func:`add_arguments`, :func:`from_arguments`),
  ``genre serve``'s option keys (:func:`parse_request_options`) and the schema
  its ``ready`` event publishes (:func:`schema`), from which the Blender add-on
  builds its rows;
* the named sets behind the add-on's *Quality* choice (:data:`QUALITIES`,
  ``quality`` in a request, ``--quality`` on the command line);
* the steps after the networks, in their one order, shared by ``genre
  reconstruct``, ``genre serve`` and ``genre eval``
  (:meth:`MeshOptions.shape_grid`: outline carve → visible fusion → pit
  sealing; :meth:`MeshOptions.mesh`: hole closing, marching cubes, clean-up,
  the sheets onto the surface; :meth:`MeshOptions.snap_mesh`: a fitted regular shape).

A new option is one field (``GeometryConfig``'s for a setting the weights store, :class:`_OwnOptions`' otherwise)
plus its tests and its use: the CLI flag, the server's key and result, the schema, the add-on's row, install's
flag, the fuzz test's values and ``docs/protocol.md``'s table (:func:`table`) follow from it.
Mask inputs (``mask``, a box, strokes) and output paths are not mesh options
and stay out of the record.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import torch

from ..config import SETTINGS, check_setting
from ..protocol import Option, OptionError
from ..protocol import shown as _shown
from ..nets.outputs import View

__all__ = [
    "Option",
    "OptionError",
    "MeshOptions",
    "OPTIONS",
    "QUALITIES",
    "DEFAULT_QUALITY",
    "schema",
    "add_arguments",
    "from_arguments",
    "parse_request_options",
    "mesh_of_probability",
]


def _option(**spec) -> Any:
    return field(default=None, metadata={"option": Option(**spec)})


@dataclass(frozen=True)
class _OwnOptions:
    """The options that do not follow the weights (their defaults are their own)."""

    all_parts: bool | None = _option(
        kind="bool", default=False, label="Keep All Parts",
        help="keep every separate piece of the mesh (off: pieces smaller than Smallest Part are dropped)")
    # how small a separate piece may be and stay (geometry.cleanup.clean_mesh's keep_fraction, whose default it repeats)
    min_part_share: float | None = _option(
        kind="float", lo=0.0, hi=1.0, default=0.05, metavar="SHARE", label="Smallest Part",
        help="drop separate pieces of the mesh smaller in area than this share of the largest (0 keeps every piece; "
             "all_parts overrides it)")
    texture: bool | None = _option(
        kind="bool", default=False, label="Colour from Photo",
        help="colour the mesh from the photo (OBJ: UVs, an .mtl and NAME_texture.png; glb: embedded; ply: vertex colours)")
    format: str | None = _option(
        kind="choice", choices=("obj", "ply", "glb"), label="Format",
        help="mesh file format (default: from the output's extension, else obj)")
    up: str | None = _option(
        kind="choice", choices=("y", "z"), label="Up Axis",
        help="the file's up axis: z (default for ply: Blender's axes) or y (the view frame; always so for obj and glb)")


_TYPES = {"float": "float | None", "int": "int | None", "bool": "bool | None", "choice": "str | None"}


def _fields() -> list[tuple[str, str, Any]]:
    """The record's fields: the weights' settings (``GeometryConfig``'s option fields), then the options of its own."""
    out = [(spec.name, _TYPES[spec.kind], field(default=None, metadata={"option": spec})) for spec in SETTINGS]
    for f in dataclasses.fields(_OwnOptions):
        spec = dataclasses.replace(f.metadata["option"], name=f.name)
        out.append((f.name, _TYPES[spec.kind], field(default=None, metadata={"option": spec})))
    return out


class _Record:
    """Every mesh option of one reconstruction; ``None``: the weights' own setting (or the option's default).

    Its fields are the option fields of the weights' ``GeometryConfig`` (``threshold`` is ``default_threshold``)
    followed by :class:`_OwnOptions`'.  Constructing one checks every value given (:class:`OptionError`).
    :meth:`resolved` fills the ``None`` fields from the weights' ``GeometryConfig``; the steps (:meth:`shape_grid`,
    :meth:`mesh`, :meth:`snap_mesh`) take a resolved one.
    """

    def __post_init__(self):
        for spec in OPTIONS:
            value = getattr(self, spec.name)
            if value is not None:
                object.__setattr__(self, spec.name, spec.check(value))

    @classmethod
    def from_mapping(cls, values: dict[str, Any], where: Callable[[Option], str] = lambda o: o.name,
                     show: Callable[[Any], str] = _shown) -> MeshOptions:
        """A record of ``{name: value}`` (``None`` values: not given); unknown names and bad values raise :class:`OptionError`,
        its message naming the option as ``where(option)`` says and quoting the value with ``show``."""
        unknown = sorted(set(values) - set(BY_NAME), key=str)
        if unknown:
            raise OptionError(f"unknown option(s) {', '.join(map(show, unknown))}; known: {', '.join(BY_NAME)}", str(unknown[0]))
        return cls(**{name: BY_NAME[name].check(v, where(BY_NAME[name]), show) for name, v in values.items() if v is not None})

    def given(self) -> dict[str, Any]:
        """The options set in this record (not ``None``)."""
        return {spec.name: getattr(self, spec.name) for spec in OPTIONS if getattr(self, spec.name) is not None}

    def over(self, base: MeshOptions) -> MeshOptions:
        """This record's values laid over ``base``'s (a ``None`` here keeps ``base``'s)."""
        return dataclasses.replace(base, **self.given())

    def resolved(self, geometry) -> MeshOptions:
        """Every ``None`` filled: from the weights' ``geometry`` (a ``GeometryConfig``) where the option follows them, else
        its default; :class:`OptionError` for an option these weights cannot take (``distance_only`` on shell weights)."""
        filled = {}
        for spec in OPTIONS:
            value = getattr(self, spec.name)
            if value is None:
                value = getattr(geometry, spec.weights) if spec.weights else spec.default
            filled[spec.name] = value if value is None else check_setting(spec, value, geometry.target, spec.name)
        return MeshOptions(**filled)

    @property
    def keep_fraction(self) -> float:
        """The share of the largest part's area below which a part is dropped: ``min_part_share`` (0 with ``all_parts``)."""
        return 0.0 if self.all_parts else self.min_part_share

    # ---- the steps after the networks, in their one order --------------------------------------------------
    def shape_grid(self, prob: torch.Tensor, view: View, geometry) -> torch.Tensor:
        """The probability grid (N, N, N) float32 on the CPU, steered by the resolved options before a mesh is made.

        In order: capped by the mask's outline ramp (``silhouette_carve``) and by the full spherical map's hull
        (``sph_hull_carve``, where the view has a map), the holes in the visible face filled from
        the masked depth (``visible_fusion``), the pits of the grid's own visible front sealed (*Seal Pits*), the
        dents of its back filled (*Seal Back*); the last three at ``threshold``.  ``view``: the mask, masked depth and
        camera (:class:`genre_backend.nets.outputs.View`).
        """
        from ..geometry.spherical import hull_ramp
        from ..geometry.visible_front import fuse_visible_surface, seal_back, seal_pits
        from ..geometry.voxels import silhouette_ramp

        if self.silhouette_carve:
            prob = torch.minimum(prob, silhouette_ramp(view.mask[None].cpu(), view.camera, prob.shape[-1])[0, 0])
        if self.sph_hull_carve and view.sph is not None:
            prob = torch.minimum(prob, hull_ramp(view.sph[None].float().cpu(), geometry)[0, 0])
        if self.visible_fusion:
            prob = fuse_visible_surface(prob, view.depth, view.camera, geometry, self.threshold)
        pits = self.pit_sealing
        if pits:
            prob = seal_pits(prob, view.mask.cpu().bool(), view.camera, geometry, self.threshold, pits)
        if self.back_sealing:
            prob = seal_back(prob, view.mask.cpu().bool(), view.camera, geometry, self.threshold)
        return prob

    def mesh(self, prob: torch.Tensor, geometry, clean: bool = True):
        """The mesh of a shaped grid (N, N, N) at ``threshold``, with ``hole_closing``; see :func:`mesh_of_probability`.

        ``clean=False`` keeps every part and cavity wall (the mesh ``genre eval`` fits a regular shape to).
        """
        return mesh_of_probability(prob, self.threshold, geometry, self.hole_closing, self.keep_fraction, clean=clean)

    def snap_mesh(self, vertices, faces, view: View):
        """The regular shape that replaces the mesh (``primitive_snap``; 0: off): ``(vertices (V, 3) float32, faces (F, 3)
        int64, fit)`` of the accepted fit, or the mesh as it was and ``None``.  ``view``: its masked depth and camera."""
        from ..geometry.primitives import snap

        if not self.primitive_snap > 0:
            return vertices, faces, None
        v, f, fit = snap(vertices, faces, view.depth, view.camera, self.primitive_snap)
        if fit is not None and fit.accepted(self.primitive_snap):
            return v, f, fit
        return v, f, None


MeshOptions = dataclasses.make_dataclass("MeshOptions", _fields(), bases=(_Record,), frozen=True,
                                        namespace={"__doc__": _Record.__doc__, "__module__": __name__})
OPTIONS: tuple[Option, ...] = tuple(f.metadata["option"] for f in dataclasses.fields(MeshOptions))
BY_NAME: dict[str, Option] = {o.name: o for o in OPTIONS}

# The named sets behind the add-on's Quality choice (and `quality` in a request, `--quality`): laid under the options
# given one by one.  Best: the weights' own settings, chosen on evaluation views.  Fast: without the mirror image's second
# pass through the networks (about half their time), the one setting that costs time.
QUALITIES: dict[str, MeshOptions] = {
    "best": MeshOptions(),
    "fast": MeshOptions(test_time_mirror=False),
}
QUALITY_LABELS = {"fast": ("Fast", "One pass through the networks (no mirror average): about half the time"),
                  "best": ("Best", "The weights' own settings, chosen on evaluation views")}
DEFAULT_QUALITY = "best"


def check_quality(value: Any, where: str = "quality", show: Callable[[Any], str] = _shown) -> MeshOptions:
    """The named set ``value`` (``"fast"``/``"best"``); :class:`OptionError` otherwise."""
    if not isinstance(value, str) or value not in QUALITIES:
        raise OptionError(f"{where}: expected one of {', '.join(map(repr, QUALITIES))}, got {show(value)}", "quality")
    return QUALITIES[value]


def schema(geometry=None) -> dict[str, Any]:
    """The record as ``genre serve``'s ``ready`` publishes it: ``{"options": [{name, type, min, max, min_open, max_open,
    choices, default, label, help, weights}, …], "qualities": [{name, label, help, options}, …]}``.

    ``default``: the weights' value (``geometry``, a ``GeometryConfig``) where the option follows them, else the
    option's own default (``null`` for one that depends on the output, as ``format``).
    """
    entries = []
    for spec in OPTIONS:
        default = getattr(geometry, spec.weights) if (spec.weights and geometry is not None) else spec.default
        entries.append({**spec.describe(), "default": default})
    qualities = [{"name": name, "label": QUALITY_LABELS[name][0], "help": QUALITY_LABELS[name][1], "options": q.given()}
                 for name, q in QUALITIES.items()]
    return {"options": entries, "qualities": qualities}


def mesh_of_probability(prob: torch.Tensor, threshold: float, geometry, hole_closing: int, keep_fraction: float | None = None,
                        clean: bool = True):
    """The mesh ``genre reconstruct`` makes of a probability grid (N, N, N), after any carving or fusion.

    For the distance target the enclosed voxels are filled first (:func:`fill_enclosed`, holes up to about
    ``2·hole_closing`` voxels sealed); marching cubes at ``threshold``; cavity walls and parts smaller than
    ``keep_fraction`` of the largest dropped (:func:`clean_mesh`; default 5 %; not with ``clean=False``); the sheets moved
    onto the surface (:func:`onto_surface`).  Returns ``(grid as meshed (N, N, N) float32, vertices (V, 3) float32, faces
    (F, 3) int64, CleanReport or None)``; the report is None, and the mesh empty, when no voxel reaches ``threshold``
    (and always with ``clean=False``).
    """
    from ..geometry.cleanup import DEFAULT_KEEP_FRACTION, clean_mesh
    from ..geometry.mesh_voxels import fill_enclosed, onto_surface, voxels_to_mesh

    if geometry.target == "distance":
        prob = torch.from_numpy(fill_enclosed(prob, threshold, hole_closing))  # the outer sheet only
    vertices, faces = voxels_to_mesh(prob, threshold)
    report = None
    if clean:
        if len(faces) == 0:
            return prob, vertices, faces, None
        vertices, faces, report = clean_mesh(vertices, faces, DEFAULT_KEEP_FRACTION if keep_fraction is None else keep_fraction)
    return prob, onto_surface(vertices, faces, threshold, geometry), faces, report


# ---- the front ends --------------------------------------------------------------------------------------------------
def add_arguments(parser) -> None:
    """``genre reconstruct``'s flag of every option (``--threshold T``, ``--silhouette-carve/--no-silhouette-carve``,
    ``--texture`` …) and ``--quality``; every default ``None`` (not given)."""
    import argparse

    for spec in OPTIONS:
        follows = f" (default: the weights' config, geometry.{spec.weights})" if spec.weights else ""
        text = f"{spec.help}{follows}".replace("%", "%%")
        if spec.kind == "bool" and spec.weights:
            parser.add_argument(spec.flag, dest=spec.name, action=argparse.BooleanOptionalAction, default=None, help=text)
        elif spec.kind == "bool":
            parser.add_argument(spec.flag, dest=spec.name, action="store_const", const=True, default=None, help=text)
        elif spec.kind == "choice":
            parser.add_argument(spec.flag, dest=spec.name, choices=spec.choices, default=None, help=text)
        else:
            text += f"; {spec.expected()}"
            parser.add_argument(spec.flag, dest=spec.name, type=float if spec.kind == "float" else int, metavar=spec.metavar,
                                default=None, help=text)
    parser.add_argument("--quality", choices=tuple(QUALITIES), default=None,
                        help="a named set of the options above, under any given one by one: "
                             + "; ".join(f"{n}: {QUALITY_LABELS[n][1]}" for n in QUALITIES) + f" (default: {DEFAULT_QUALITY})")


def from_arguments(args) -> MeshOptions:
    """The record of parsed :func:`add_arguments` flags (the quality's set under them); :class:`OptionError` names the
    flag (``--pit-sealing: expected an integer in [0, 8] (voxels), got 9``)."""
    given = MeshOptions.from_mapping({spec.name: getattr(args, spec.name) for spec in OPTIONS}, where=lambda o: o.flag,
                                     show=lambda v: f"{v:g}" if isinstance(v, float) else _shown(v))
    return given.over(QUALITIES[args.quality or DEFAULT_QUALITY])


def parse_request_options(options: dict[str, Any], show: Callable[[Any], str], extra: Iterable[str] = ()) -> MeshOptions:
    """The record of a ``genre serve`` request's ``options`` object (``null`` values: not given; ``quality`` lays its set
    under the rest); keys in ``extra`` (``save_intermediates``) are the caller's.  :class:`OptionError` names the option
    (``option 'threshold': expected a number in (0, 1), got 1.5``) or lists the unknown keys."""
    extra = tuple(extra)
    known = (*BY_NAME, "quality", *extra)
    unknown = [k for k in options if k not in known]
    if unknown:
        listed = ", ".join(map(show, sorted(unknown)))
        raise OptionError(f"unknown option(s) {listed}; known: {', '.join(known)}", str(unknown[0]))
    quality = options.get("quality")
    base = QUALITIES[DEFAULT_QUALITY] if quality is None else check_quality(quality, "option 'quality'", show)
    given = MeshOptions.from_mapping({k: v for k, v in options.items() if k in BY_NAME}, where=lambda o: f"option '{o.name}'",
                                     show=show)
    return given.over(base)


# ---- the options table of docs/protocol.md ---------------------------------------------------------------------------
TABLE_BEGIN, TABLE_END = "<!-- options table: generated from MeshOptions -->", "<!-- end of the options table -->"


def table() -> str:
    """The record as ``docs/protocol.md``'s table of options: one row per option, in the record's order."""
    rows = ["| option | value | default | what it does |", "| --- | --- | --- | --- |"]
    for spec in OPTIONS:
        default = f"the weights' `geometry.{spec.weights}`" if spec.weights else (
            "from the output" if spec.default is None else f"`{str(spec.default).lower()}`")
        if spec.distance_only:
            default += "; other than 0 or false: weights of the `distance` target only"
        rows.append(f"| `{spec.name}` | {spec.expected()} | {default} | {spec.label}: {spec.help} |")
    return "\n".join(rows) + "\n"


def write_table(path) -> bool:
    """Put :func:`table` between the markers of ``path`` (``docs/protocol.md``); whether the file changed."""
    from pathlib import Path

    text = Path(path).read_text(encoding="utf-8")
    head, _, rest = text.partition(TABLE_BEGIN + "\n")
    _, _, tail = rest.partition(TABLE_END)
    new = f"{head}{TABLE_BEGIN}\n{table()}{TABLE_END}{tail}"
    if new != text:
        Path(path).write_text(new, encoding="utf-8")
    return new != text


if __name__ == "__main__":  # python -m genre_backend.inference.options docs/protocol.md: the table written again
    import sys

    print("rewritten" if write_table(sys.argv[1]) else "up to date")
