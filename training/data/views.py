"""The on-disk format of rendered views: the only module that knows its file names.

A views folder (written by ``genre data render``, completed by ``genre data
targets``) looks like this::

    VIEWS/render_settings.json            preset, seed, image size, camera, engine of the whole folder
    VIEWS/render_failures*.json           shapes given up on (one file per render shard)
    VIEWS/.render_inflight*.json          per render shard: the shape being rendered, crashes and interruptions
    VIEWS/.render_crash*.log              per render shard: what a crash of the renderer wrote (faulthandler)
    VIEWS/targets_failures.json           shapes whose targets failed
    VIEWS/<shape id>/view_KKK.png         RGB (S, S, 3) uint8, composited over the background
    VIEWS/<shape id>/view_KKK.npz         depth (S, S) float32 (planar, background 0), mask (S, S) float32
    VIEWS/<shape id>/view_KKK.json        camera and provenance (written last: its presence marks a complete view)
    VIEWS/<shape id>/view_KKK_targets.npz full/partial spherical maps and the packed surface shell
    VIEWS/<shape id>/surface_points.npz   10,000 surface points of the shape (object frame)

This module also owns the reader of shape lists (a corpus manifest or a
folder of meshes) as :class:`ShapeEntry` records, and the preset recorded
in ``render_settings.json`` that every later data command reads instead of
asking for it again.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from genre_backend.atomic import atomic_savez, atomic_write, atomic_write_json

__all__ = [
    "MESH_SUFFIXES",
    "SETTINGS_FILE",
    "FAILURES_GLOB",
    "TARGETS_FAILURES_FILE",
    "ViewRef",
    "ShapeEntry",
    "view_paths",
    "targets_path",
    "surface_points_path",
    "view_key",
    "view_indices",
    "view_is_complete",
    "load_view",
    "load_view_meta",
    "write_view",
    "remove_stale_temporaries",
    "find_views",
    "render_failures_path",
    "inflight_path",
    "crash_log_path",
    "RenderAttempts",
    "read_render_attempts",
    "write_render_attempts",
    "read_render_settings",
    "write_render_settings",
    "recorded_preset",
    "read_manifest",
    "manifest_index",
    "read_shapes",
]

MESH_SUFFIXES = (".glb", ".gltf", ".obj", ".ply")
SETTINGS_FILE = "render_settings.json"
FAILURES_GLOB = "render_failures*.json"
TARGETS_FAILURES_FILE = "targets_failures.json"
_SURFACE_POINTS = "surface_points.npz"
_VIEW_JSON = re.compile(r"view_(\d{3})\.json")


# --------------------------------------------------------------------------- one view


@dataclass(frozen=True)
class ViewRef:
    """One view of one shape: its shape folder and view index."""

    shape_dir: Path
    view: int

    @property
    def shape_id(self) -> str:
        return self.shape_dir.name

    @property
    def key(self) -> str:
        """``<shape id>/KKK``: the view's name in evaluation tables and file names."""
        return view_key(self.shape_dir, self.view)


def _stem(view: int) -> str:
    if view < 0 or view > 999:
        raise ValueError(f"view index must be in [0, 999], got {view}")
    return f"view_{view:03d}"


def view_paths(shape_dir: str | os.PathLike, view: int) -> dict[str, Path]:
    """The three files of a rendered view: ``{"png": …, "npz": …, "json": …}``."""
    base = Path(shape_dir) / _stem(view)
    return {"png": base.with_suffix(".png"), "npz": base.with_suffix(".npz"), "json": base.with_suffix(".json")}


def targets_path(shape_dir: str | os.PathLike, view: int) -> Path:
    """The targets file of a view (``genre data targets``)."""
    return Path(shape_dir) / f"{_stem(view)}_targets.npz"


def surface_points_path(shape_dir: str | os.PathLike) -> Path:
    """The shape's surface points for evaluation (object frame)."""
    return Path(shape_dir) / _SURFACE_POINTS


def view_key(shape_dir: str | os.PathLike, view: int) -> str:
    return f"{Path(shape_dir).name}/{view:03d}"


def view_indices(shape_dir: str | os.PathLike) -> list[int]:
    """Sorted indices of the views of a shape folder whose camera JSON exists."""
    out = []
    for p in Path(shape_dir).glob("view_*.json"):
        m = _VIEW_JSON.fullmatch(p.name)
        if m:
            out.append(int(m.group(1)))
    return sorted(out)


def view_is_complete(shape_dir: str | os.PathLike, view: int) -> bool:
    """True iff view ``view`` of the shape folder has all three files (the JSON is written last)."""
    return all(p.is_file() for p in view_paths(shape_dir, view).values())


def load_view_meta(shape_dir: str | os.PathLike, view: int) -> dict[str, Any]:
    """The camera/provenance JSON of a view."""
    return json.loads(view_paths(shape_dir, view)["json"].read_text())


def load_view(shape_dir: str | os.PathLike, view: int) -> dict[str, Any]:
    """Read back a view: ``rgb`` (H, W, 3) uint8, ``depth`` (H, W) float32, ``mask`` (H, W) float32, ``camera`` dict."""
    paths = view_paths(shape_dir, view)
    if not view_is_complete(shape_dir, view):
        raise ValueError(f"{shape_dir}: view {view} is not complete")
    from PIL import Image

    with Image.open(paths["png"]) as im:
        rgb = np.asarray(im.convert("RGB"), dtype=np.uint8).copy()
    with np.load(paths["npz"]) as z:
        depth, mask = z["depth"].copy(), z["mask"].copy()
    camera = json.loads(paths["json"].read_text())
    return {"rgb": rgb, "depth": depth, "mask": mask, "camera": camera}


def write_view(shape_dir: str | os.PathLike, view: int, rgb: np.ndarray, depth: np.ndarray, mask: np.ndarray, meta: dict) -> None:
    """Write a view's three files atomically, the JSON last (so a complete view is never half-written).

    rgb: (S, S, 3) uint8; depth, mask: (S, S) float32; meta: JSON-able dict.
    """
    from PIL import Image

    paths = view_paths(shape_dir, view)
    atomic_write(paths["png"], lambda fh: Image.fromarray(rgb, "RGB").save(fh, format="PNG"))
    atomic_savez(paths["npz"], depth=depth, mask=mask)
    atomic_write_json(paths["json"], meta)


def remove_stale_temporaries(shape_dir: str | os.PathLike) -> None:
    """Delete temporary view files left by a killed run (one process renders a shape at a time)."""
    for stale in Path(shape_dir).glob(".view_*.tmp-*"):
        stale.unlink(missing_ok=True)


def find_views(root: str | os.PathLike, shape_ids: set[str] | None = None, targets: bool = True,
               surface_points: bool = False) -> list[ViewRef]:
    """Every view under ``root`` with a complete render (and targets / surface points, if asked), sorted.

    ``shape_ids``: only these shapes.
    """
    refs = []
    for shape_dir in sorted(p for p in Path(root).iterdir() if p.is_dir()):
        if shape_ids is not None and shape_dir.name not in shape_ids:
            continue
        if surface_points and not surface_points_path(shape_dir).is_file():
            continue
        for k in view_indices(shape_dir):
            if (not targets or targets_path(shape_dir, k).is_file()) and view_paths(shape_dir, k)["npz"].is_file():
                refs.append(ViewRef(shape_dir, k))
    return refs



def gather_views(folders: list[str | os.PathLike], shape_ids: set[str] | None = None, targets: bool = True) -> list[ViewRef]:
    """The views of several folders (:func:`find_views` of each), in the order given.

    A folder named *k* times contributes its views *k* times, so a uniform draw
    over the result takes them *k* times as often: the training mix of a run
    (``genre train --data A B B``).  The same shape may be in several folders
    (renders of it with other settings); :func:`training.data.dataset.split_views`
    splits by shape id, so all of its views, from every folder, land on the same
    side of the train/validation split.
    """
    if not folders:
        raise ValueError("no view folders given")
    return [r for folder in folders for r in find_views(Path(folder), shape_ids, targets=targets)]

# --------------------------------------------------------------------------- the folder's settings


def render_failures_path(views_root: str | os.PathLike, shard: tuple[int, int] = (0, 1)) -> Path:
    """The failures file of one render shard (parallel shards never write the same file)."""
    return Path(views_root) / f"render_failures{_shard_tag(shard)}.json"


def _shard_tag(shard: tuple[int, int]) -> str:
    return "" if shard[1] == 1 else f".shard{shard[0]}of{shard[1]}"


def inflight_path(views_root: str | os.PathLike, shard: tuple[int, int] = (0, 1)) -> Path:
    """The hidden file of one render shard that records its attempts (:class:`RenderAttempts`)."""
    return Path(views_root) / f".render_inflight{_shard_tag(shard)}.json"


def crash_log_path(views_root: str | os.PathLike, shard: tuple[int, int] = (0, 1)) -> Path:
    """The hidden file of one render shard into which a crashing renderer writes (empty unless it crashed)."""
    return Path(views_root) / f".render_crash{_shard_tag(shard)}.log"


@dataclass
class RenderAttempts:
    """A render shard's record of unfinished work, kept across runs in :func:`inflight_path`.

    ``in_flight``: the shape being rendered (None between shapes); a run that
    finds it set knows the previous run died on that shape, and the crash log
    (:func:`crash_log_path`) tells a crash (something written) from a kill
    (nothing).  ``crashes`` and ``interruptions`` count those per shape
    until the shape is done.
    """

    in_flight: str | None = None
    crashes: dict[str, int] = field(default_factory=dict)
    interruptions: dict[str, int] = field(default_factory=dict)


def _counts(value: Any) -> dict[str, int]:
    if not isinstance(value, dict):
        return {}
    return {str(k): int(v) for k, v in value.items() if isinstance(v, int) and not isinstance(v, bool) and v > 0}


def read_render_attempts(views_root: str | os.PathLike, shard: tuple[int, int] = (0, 1)) -> RenderAttempts:
    """The shard's :class:`RenderAttempts` (empty when absent or unreadable).

    Files of older versions (``{shape id: attempts}``, written before crashes
    and kills were told apart) are read as interruptions.
    """
    try:
        data = json.loads(inflight_path(views_root, shard).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return RenderAttempts()
    if not isinstance(data, dict):
        return RenderAttempts()
    if "interruptions" not in data and "crashes" not in data and "in_flight" not in data:
        return RenderAttempts(interruptions=_counts(data))
    in_flight = data.get("in_flight")
    return RenderAttempts(in_flight if isinstance(in_flight, str) else None, _counts(data.get("crashes")),
                          _counts(data.get("interruptions")))


def write_render_attempts(views_root: str | os.PathLike, shard: tuple[int, int], attempts: RenderAttempts) -> None:
    atomic_write_json(inflight_path(views_root, shard), {"in_flight": attempts.in_flight,
                                                         "crashes": attempts.crashes,
                                                         "interruptions": attempts.interruptions})


def read_render_settings(views_root: str | os.PathLike) -> dict | None:
    """The folder's ``render_settings.json`` (None if absent or unreadable).

    Folders rendered before the engine was a choice were rendered with Cycles,
    and before the lighting was, lit at random: their settings read ``engine:
    cycles`` and ``lighting: random``.
    """
    try:
        settings = json.loads((Path(views_root) / SETTINGS_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if isinstance(settings, dict):
        settings.setdefault("engine", "cycles")
        settings.setdefault("lighting", "random")
    return settings


def write_render_settings(views_root: str | os.PathLike, settings: dict) -> None:
    atomic_write_json(Path(views_root) / SETTINGS_FILE, settings)


def recorded_preset(views_root: str | os.PathLike, asked: str | None = None) -> str:
    """The preset a views folder was rendered with; ``asked`` (a ``--preset`` option) must agree with it.

    A folder without ``render_settings.json`` (rendered by an old version)
    takes ``asked``, else ``default``.  Raises ValueError on a disagreement.
    """
    settings = read_render_settings(views_root)
    recorded = settings.get("preset") if isinstance(settings, dict) else None
    if recorded is None:
        return asked or "default"
    if asked is not None and asked != recorded:
        raise ValueError(f"{views_root} was rendered with preset {recorded!r}, not {asked!r} (leave out --preset)")
    return str(recorded)


# --------------------------------------------------------------------------- shape lists


@dataclass(frozen=True)
class ShapeEntry:
    """A shape as the data commands see it: id (also its views' sub-folder), mesh path, class, split, groups.

    The corpus builder's full record (source, creator, licence, …) is
    :class:`training.data.corpus.ManifestRecord`; this is what is read back.
    """

    id: str
    path: Path
    cls: str | None = None
    split: str | None = None
    groups: tuple[str, ...] = ()


def read_manifest(path: str | os.PathLike) -> dict:
    """A manifest JSON as a dict; ValueError with the reason if unreadable, FileNotFoundError if absent."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: run 'genre data build' first")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a readable JSON manifest ({exc})") from None


def _entry_list(data: Any, where: str) -> list[dict]:
    if isinstance(data, list):
        entries = data
    elif isinstance(data, dict):
        for key in ("shapes", "entries", "items"):
            if isinstance(data.get(key), list):
                entries = data[key]
                break
        else:
            raise ValueError(f"{where}: expected a list of shapes or an object with a 'shapes' list")
    else:
        raise ValueError(f"{where}: expected a list or an object, got {type(data).__name__}")
    for i, e in enumerate(entries):
        if not isinstance(e, dict) or not isinstance(e.get("id"), str) or not e["id"]:
            raise ValueError(f"{where}: entry {i} has no string 'id'")
    return entries


def manifest_index(manifest: dict | None) -> dict[str, dict]:
    """Shape id → manifest entry (empty for no manifest)."""
    if not manifest:
        return {}
    return {e["id"]: e for e in _entry_list(manifest, "manifest")}


def read_shapes(source: str | os.PathLike) -> list[ShapeEntry]:
    """The shapes named by a manifest JSON or found in a folder, in a stable order.

    Manifest: a list (or ``{"shapes": [...]}``) of entries with ``id`` and
    optionally ``class``, ``split``, ``groups`` and ``mesh`` (relative to the
    manifest's folder); without ``mesh`` the mesh is
    ``<manifest folder>/shapes/<id>.glb``.  Folder: every mesh file under it
    (recursively); the id is the relative path without suffix with ``/``
    replaced by ``__``, the class is the first sub-folder (if any).
    """
    src = Path(source)
    if src.is_file():
        data = read_manifest(src)
        base = src.parent
        shapes = []
        seen = set()
        for e in _entry_list(data, str(src)):
            # ("path" in corpus manifests is the *source* file, never the normalised mesh.)
            rel = e.get("mesh")
            path = (base / rel) if rel else base / "shapes" / f"{e['id']}.glb"
            if e["id"] in seen:
                raise ValueError(f"{src}: duplicate shape id {e['id']!r}")
            seen.add(e["id"])
            groups = tuple(str(g) for g in e.get("groups") or ())
            shapes.append(ShapeEntry(e["id"], path, e.get("class"), e.get("split"), groups))
        return shapes
    if src.is_dir():
        shapes = []
        for p in sorted(src.rglob("*")):
            if p.is_file() and p.suffix.lower() in MESH_SUFFIXES and not p.name.startswith("."):
                rel = p.relative_to(src)
                sid = "__".join(rel.with_suffix("").parts)
                cls = rel.parts[0] if len(rel.parts) > 1 else None
                shapes.append(ShapeEntry(sid, p, cls, None))
        return shapes
    raise ValueError(f"{src}: neither a manifest file nor a folder")
