"""The shape corpus: fetch the Debian packages, enumerate, load, normalise,
classify, filter, de-duplicate, split, and write the manifest and meshes.

Layout under the GenRe home (:func:`data_dir`: ``$GENRE_HOME``, default
``~/.cache/genre``; outside the checkout, GPL data never enters git)::

    cache/debs/PKG_*.deb            apt-get download
    cache/unpacked/PKG/             dpkg -x of that .deb (+ .complete marker)
    corpus/manifest.json            one entry per kept shape, the splits, the skips
    corpus/shapes/<shape_id>.glb    the normalised mesh (materials/textures kept)

Every kept shape is in the canonical object frame of
:mod:`genre_backend.frame`: +Z up, front toward −Y, bounding-box centre at
the origin, bounding-box diagonal exactly 1.  ``transform`` in the manifest
is the ``(4, 4)`` matrix that took the source file's coordinates there
(``v_canonical = T @ [v, 1]``).

The rules (classes, junk, near-duplicates, split) are data at the top of this
module so that ``genre data stats`` can print exactly what was applied.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
import subprocess
import tempfile
from collections import Counter
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from genre_backend.atomic import atomic_write_bytes, atomic_write_text

from .sources import ShapeRecord, rotation_to_list
from .views import read_manifest
from .sources import crrcsim, flightgear, gl117, procedural, sweethome3d, torcs, trigger_rally, zeroad

__all__ = [
    "REPO_ROOT",
    "SOURCES",
    "DEBIAN_PACKAGES",
    "DEFAULT_SOURCES",
    "OPT_IN_SOURCES",
    "CLASS_RULES",
    "CLASS_ALIASES",
    "SEEN_CLASSES",
    "UNSEEN_CLASSES",
    "UNSEEN_PIX3D_CLASSES",
    "TEST_FRACTION",
    "data_dir",
    "fetch",
    "classify",
    "split_of",
    "groups_of",
    "PRODUCT_TEST_FRACTION",
    "PRODUCT_GROUPS",
    "product_groups",
    "normalise_parts",
    "check_geometry",
    "junk_reason",
    "find_near_duplicates",
    "ManifestRecord",
    "SkipEntry",
    "build",
    "load_manifest",
    "rules_text",
]

log = logging.getLogger("genre.data")

REPO_ROOT = Path(__file__).resolve().parents[2]

# --------------------------------------------------------------------------- sources

SOURCES = {
    "sweethome3d": sweethome3d,
    "flightgear": flightgear,
    "torcs": torcs,
    "crrcsim": crrcsim,
    "gl117": gl117,
    "trigger_rally": trigger_rally,
    "procedural": procedural,
    "zeroad": zeroad,
}
# Sources used only when named (``genre data fetch --packages``, ``genre data build --sources``): 0 A.D.'s 1.4 GB
# package, built in a GenRe home of its own, so the main corpus, its splits and the recorded runs' renders keep
# their meaning (docs/data.md).
OPT_IN_SOURCES = ("zeroad",)
DEFAULT_SOURCES: tuple[str, ...] = tuple(n for n in SOURCES if n not in OPT_IN_SOURCES)
DEBIAN_PACKAGES: tuple[str, ...] = tuple(p for n in DEFAULT_SOURCES for p in SOURCES[n].PACKAGES)

# --------------------------------------------------------------------------- classes

SEEN_CLASSES = ("airplane", "car", "chair")
UNSEEN_CLASSES = ("bench", "vessel", "sofa", "table", "phone", "cabinet", "speaker", "lamp", "display")
UNSEEN_PIX3D_CLASSES = ("bed", "bookcase", "desk", "sofa", "table", "wardrobe")
TEST_FRACTION = 0.15

# Ordered: the first rule whose pattern matches the lower-cased name wins.
# Named exceptions come first, then lamps ("table lamp", "desk lamp"), sofas
# before beds ("sofa bed"), wardrobes before cabinets ("wardrobe with
# drawers"), bedside tables and desks before tables.
CLASS_RULES: list[tuple[str, str]] = [
    # named exceptions first: things whose names contain a class word but are not of that class
    ("other", r"remote control|tennis bat|rocking horse|shipping container|\bfan\b|freezer|flashlight|candle"
              r"|abdominal bench|workbench|wheelchair|headphone"),
    ("lamp", r"\blamps?\b|lampshade|chandelier|\bsconce|\blights?\b|\bspots?\b|spotlight|lantern|lamppost"),
    ("sofa", r"\bsofas?\b|\bcouch|\bsettee|loveseat|chesterfield|\bfuton"),
    ("chair", r"arm ?chairs?\b|\bchairs?\b|\bstools?\b|recliner"),
    ("bench", r"\bbench(es)?\b"),
    ("desk", r"\bdesks?\b|writing table|\bbureau\b"),
    ("wardrobe", r"wardrobe|armoire|\bcloset"),
    ("cabinet", r"cabinet|cupboard|dresser|sideboard|\bbuffet|commode|chest of drawers|\bchest\b|drawers?\b"
                r"|credenza|\bhutch|nightstand|night ?table|bedside|\bfiling|\blocker|\bvanity|showcase|vitrine"
                r"|tv stand|tv unit"),
    ("bed", r"\bbeds?\b|\bcrib\b|\bcot\b|\bbunk|\bcradle"),
    ("bookcase", r"book ?cases?|book ?shel|shelving|\bshel(f|ves)\b|etag[eè]re"),
    ("table", r"\btables?\b"),
    ("display", r"\btv\b|television|\bmonitor\b|\blcd\b|\bplasma\b|flat ?screen|computer screen|\bimac\b"),
    ("speaker", r"speaker|subwoofer"),
    ("phone", r"\bphones?\b|telephone|smartphone|iphone"),
    ("vessel", r"boats?\b|\bships?\b|\byacht|\bferry|trawler|freighter|\btanker|\bcanoe|\bkayak|\bbarge"),
    ("airplane", r"airplane|aeroplane|aircraft|\bjet\b|glider|airliner|\bplane\b|biplane"),
    ("car", r"\bcars?\b|automobile|pick-?up|\bsuv\b|sedan|hatchback|humvee|\bjeep|limousine|\bvan\b"
            r"|chevrolet|\bford\b|peugeot|renault|seat leon|\bvw\b|volkswagen|beetle"),
    ("helicopter", r"helicopter|\bheli\b|copter"),
    ("rifle", r"\brifle|shotgun|musket"),
]
# Catalogue categories used when no name rule matched.
CATEGORY_RULES: list[tuple[str, str]] = [("lamp", r"^lights?$")]
# Class names given by a source or a folder name, mapped onto project classes.
CLASS_ALIASES: dict[str, str] = {
    "armchair": "chair",
    "stool": "chair",
    "chairs": "chair",
    "watercraft": "vessel",
    "boat": "vessel",
    "ship": "vessel",
    "monitor": "display",
    "tv": "display",
    "telephone": "phone",
    "cellphone": "phone",
    "loudspeaker": "speaker",
    "bookshelf": "bookcase",
    "couch": "sofa",
    "plane": "airplane",
    "aeroplane": "airplane",
    "automobile": "car",
}
_COMPILED_RULES = [(cls, re.compile(pat)) for cls, pat in CLASS_RULES]
_COMPILED_CATEGORY = [(cls, re.compile(pat)) for cls, pat in CATEGORY_RULES]

# --------------------------------------------------------------------------- junk and sanity

MIN_FACES = 12  # fewer triangles than a box: a billboard, a marker or a flare
MIN_THICKNESS = 2e-3  # thinnest bbox side / diagonal below this: a ground plane, a wake, a billboard
MAX_SOURCE_DIAGONAL = 1e5  # source units; beyond this the file's scale is broken
MIN_SOURCE_DIAGONAL = 1e-5
JUNK_NAME = re.compile(r"shadow|billboard|\bground\b|\bwake\b|drop ?tank|\bflare|\bchaff|\bsmoke", re.IGNORECASE)

# --------------------------------------------------------------------------- near-duplicates

# Two kept shapes of one source and class are near-duplicates when EITHER
#   (a) same geometry: equal face and vertex counts and normalised bbox
#       extents equal to within DUP_SAME_EXTENT (liveries of one model), OR
#   (b) same design: same family and face counts within DUP_FAMILY_FACES
#       (relative) and extents within DUP_FAMILY_EXTENT (variants of one body),
#   OR
#   (c) same hull: both have at least DUP_HULL_MIN_FACES faces, extents
#       within DUP_SAME_EXTENT and face counts within DUP_HULL_FACES (one model
#       re-exported with a few parts changed, e.g. FlightGear's two Maritime
#       Prepositioning ships; simple shapes such as bottles and basins match
#       each other's extents by chance, hence the minimum).
# Of a group the shape with the smallest id is kept.
DUP_SAME_EXTENT = 1e-3
DUP_FAMILY_FACES = 0.05
DUP_FAMILY_EXTENT = 0.02
DUP_HULL_FACES = 0.10
DUP_HULL_MIN_FACES = 1000


def rules_text() -> str:
    """The class, junk, duplicate and split rules, as printed by ``genre data stats``."""
    lines = ["Class rules (first match on the lower-cased name wins; a source's own class, if any, is used first):"]
    for cls, pat in CLASS_RULES:
        lines.append(f"  {cls:<10} {pat}")
    for cls, pat in CATEGORY_RULES:
        lines.append(f"  {cls:<10} category {pat}   (only when no name rule matched)")
    lines.append(f"  aliases    {', '.join(f'{k}->{v}' for k, v in sorted(CLASS_ALIASES.items()))}")
    lines.append("  otherwise  'other'")
    lines += [
        "Skip rules: unreadable file; no triangles; non-finite vertices; total area 0; "
        f"bbox diagonal outside [{MIN_SOURCE_DIAGONAL:g}, {MAX_SOURCE_DIAGONAL:g}] source units.",
        f"Junk rules: fewer than {MIN_FACES} triangles; thinnest bbox side < {MIN_THICKNESS:g} x diagonal "
        f"(ground planes, wakes, billboards); name matches /{JUNK_NAME.pattern}/; plus each source's "
        "object/file rules (see training/sources/*.py).",
        "Near-duplicates (same source and class): (a) equal face and vertex counts and canonical bbox extents "
        f"within {DUP_SAME_EXTENT:g}; or (b) same family, face counts within {DUP_FAMILY_FACES:.0%} and extents "
        f"within {DUP_FAMILY_EXTENT:g}; or (c) both >= {DUP_HULL_MIN_FACES} faces, extents within "
        f"{DUP_SAME_EXTENT:g} and face counts within {DUP_HULL_FACES:.0%}.  The smallest id of a group is kept.",
        f"Split: seen {list(SEEN_CLASSES)} -> 'test' if sha256(id) maps below {TEST_FRACTION} else 'train'; "
        f"unseen {list(UNSEEN_CLASSES)}; unseen-pix3d {list(UNSEEN_PIX3D_CLASSES)} "
        "(sofa and table belong to both unseen groups); any other class -> 'unassigned'.",
    ]
    return "\n".join(lines)


def classify(name: str, category: str = "", class_hint: str | None = None) -> str:
    """The project class of a shape.

    Args:
        name: the shape's name (catalogue name, file stem).
        category: the source's category (used only by :data:`CATEGORY_RULES`).
        class_hint: a class decided by the source or a folder name; aliases
            are applied and it wins over the name rules.

    Returns:
        A class name (``"other"`` when nothing matched).
    """
    if class_hint:
        hint = class_hint.strip().lower()
        return CLASS_ALIASES.get(hint, hint)
    text = re.sub(r"[_]+", " ", name.lower())
    for cls, pattern in _COMPILED_RULES:
        if pattern.search(text):
            return cls
    cat = category.strip().lower()
    for cls, pattern in _COMPILED_CATEGORY:
        if pattern.search(cat):
            return cls
    return "other"


def _unit_hash(shape_id: str) -> float:
    digest = hashlib.sha256(shape_id.encode("utf-8")).digest()
    return int.from_bytes(digest[:8], "big") / 2.0**64


def split_of(shape_id: str, cls: str) -> str:
    """``"train"``/``"test"`` for seen classes (by a hash of the id), ``"unseen"``
    for the unseen classes of either group, else ``"unassigned"``."""
    if cls in SEEN_CLASSES:
        return "test" if _unit_hash(shape_id) < TEST_FRACTION else "train"
    if cls in UNSEEN_CLASSES or cls in UNSEEN_PIX3D_CLASSES:
        return "unseen"
    return "unassigned"


def groups_of(cls: str, split: str) -> list[str]:
    """All split lists a shape belongs to (a sofa is in ``unseen`` and ``unseen-pix3d``)."""
    out = []
    if split in ("train", "test"):
        out.append(split)
    if cls in UNSEEN_CLASSES:
        out.append("unseen")
    if cls in UNSEEN_PIX3D_CLASSES:
        out.append("unseen-pix3d")
    return out


# The product model (the weights users get) trains on every class; its test split holds out
# shapes of *every* class, the unassigned ones included.  Seen classes keep the protocol's
# split, so no shape the protocol model trained on is ever a product test shape; every other
# class holds out the families whose hash falls below PRODUCT_TEST_FRACTION (a family's variants
# stay together), and a class of two or more shapes holds out at least its lowest-hash family.
PRODUCT_TEST_FRACTION = 0.15
PRODUCT_GROUPS = ("product-train", "product-test")


def _product_hash(family: str) -> float:
    return _unit_hash("product/" + family)


def product_groups(shapes: Iterable[tuple[str, str, str, str]]) -> dict[str, str]:
    """The product split of a whole corpus.

    Args:
        shapes: ``(id, class, protocol split, family)`` of every kept shape.

    Returns:
        ``{id: "product-train" | "product-test"}`` for every shape.
    """
    shapes = list(shapes)
    out: dict[str, str] = {}
    by_class: dict[str, list[tuple[str, str]]] = {}
    for sid, cls, split, family in shapes:
        if cls in SEEN_CLASSES:
            out[sid] = "product-test" if split == "test" else "product-train"
        else:
            by_class.setdefault(cls, []).append((sid, family or sid))
    for members in by_class.values():
        held = {fam for _, fam in members if _product_hash(fam) < PRODUCT_TEST_FRACTION}
        if not held and len(members) >= 2:
            held = {min((fam for _, fam in members), key=_product_hash)}
        for sid, fam in members:
            out[sid] = "product-test" if fam in held else "product-train"
    return out


# --------------------------------------------------------------------------- fetch


def data_dir(explicit: str | Path | None = None) -> Path:
    """The GenRe home: where the corpus, views, runs, logs and results in progress live.

    The first of: ``explicit`` (e.g. ``genre data --data-dir``);
    ``$GENRE_HOME``; ``$GENRE_DATA_DIR`` (the old name, still honoured);
    ``$XDG_CACHE_HOME/genre``; ``~/.cache/genre``.  Outside the checkout, so
    GPL data never sits in a git work tree; ``genre chain`` asks this
    function too (:mod:`training.chain`).  Empty variables count as
    unset; the path is made absolute (``~`` expanded), never created here.
    """
    if explicit:
        return Path(explicit).expanduser().resolve()
    for name in ("GENRE_HOME", "GENRE_DATA_DIR"):
        env = os.environ.get(name)
        if env:
            return Path(env).expanduser().resolve()
    cache = os.environ.get("XDG_CACHE_HOME")
    base = Path(cache).expanduser() if cache and os.path.isabs(os.path.expanduser(cache)) else Path.home() / ".cache"
    return (base / "genre").resolve()


def _find_deb(debs: Path, package: str) -> Path | None:
    found = sorted(debs.glob(f"{package}_*.deb"))
    return found[-1] if found else None


def fetch(
    packages: Iterable[str] = DEBIAN_PACKAGES,
    root: Path | None = None,
    *,
    runner: Callable[..., subprocess.CompletedProcess] = subprocess.run,
) -> dict[str, str]:
    """Download and unpack Debian packages into ``root/cache``.

    ``apt-get download PKG`` runs in ``cache/debs`` unless a ``PKG_*.deb`` is
    already there; ``dpkg -x`` unpacks into ``cache/unpacked/PKG`` (via a
    temporary folder, then a rename, then a ``.complete`` marker) unless the
    marker exists.  Nothing is installed on the system.

    Returns:
        ``{package: "cached" | "unpacked" | "failed: <reason>"}``.
    """
    root = data_dir(root)
    debs = root / "cache" / "debs"
    unpacked = root / "cache" / "unpacked"
    debs.mkdir(parents=True, exist_ok=True)
    unpacked.mkdir(parents=True, exist_ok=True)
    status: dict[str, str] = {}
    for package in packages:
        if not re.fullmatch(r"[a-z0-9][a-z0-9+.-]+", package):
            status[package] = "failed: not a Debian package name"
            continue
        target = unpacked / package
        if (target / ".complete").is_file():
            status[package] = "cached"
            continue
        deb = _find_deb(debs, package)
        if deb is None:
            log.info("apt-get download %s", package)
            res = runner(["apt-get", "download", package], cwd=debs, capture_output=True, text=True)
            deb = _find_deb(debs, package)
            if res.returncode != 0 or deb is None:
                status[package] = f"failed: apt-get download: {(res.stderr or '').strip()[-300:]}"
                log.error("%s: %s", package, status[package])
                continue
        tmp = Path(tempfile.mkdtemp(prefix=f".{package}-", dir=unpacked))
        log.info("dpkg -x %s", deb.name)
        res = runner(["dpkg", "-x", str(deb), str(tmp)], capture_output=True, text=True)
        if res.returncode != 0:
            shutil.rmtree(tmp, ignore_errors=True)
            status[package] = f"failed: dpkg -x: {(res.stderr or '').strip()[-300:]}"
            log.error("%s: %s", package, status[package])
            continue
        if target.exists():
            shutil.rmtree(target)
        tmp.rename(target)
        (target / ".complete").write_text(deb.name + "\n")
        status[package] = "unpacked"
    return status


# --------------------------------------------------------------------------- geometry


def _all_vertices(parts: list[trimesh.Trimesh]) -> np.ndarray:
    return np.concatenate([np.asarray(p.vertices, dtype=np.float64).reshape(-1, 3) for p in parts])


def check_geometry(parts: list[trimesh.Trimesh]) -> str | None:
    """Why a loaded model cannot be used, or ``None`` if it can.

    Args:
        parts: the model's meshes in source coordinates.

    Returns:
        ``"empty"``, ``"nan-vertices"``, ``"zero-area"``, ``"absurd-size ..."``
        or ``None``.
    """
    parts = [p for p in parts if len(p.faces)]
    if not parts:
        return "empty"
    vertices = _all_vertices(parts)
    if not np.all(np.isfinite(vertices)):
        return "nan-vertices"
    area = float(sum(p.area for p in parts))
    if not np.isfinite(area) or area <= 0.0:
        return "zero-area"
    diagonal = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    if not (MIN_SOURCE_DIAGONAL <= diagonal <= MAX_SOURCE_DIAGONAL):
        return f"absurd-size (diagonal {diagonal:.3g})"
    return None


def normalise_parts(
    parts: list[trimesh.Trimesh], rotation: np.ndarray, *, align_long_axis: bool = False
) -> tuple[list[trimesh.Trimesh], np.ndarray]:
    """Rotate into the canonical frame, centre the bounding box, scale its diagonal to 1.

    Args:
        parts: meshes in source coordinates (modified copies are returned).
        rotation: ``(3, 3) float`` source -> canonical rotation.
        align_long_axis: turn the longer horizontal extent onto Y (90 degrees
            about Z) when X is longer.

    Returns:
        ``(parts, T)``: the transformed meshes and the ``(4, 4) float``
        transform applied (``v' = T @ [v, 1]``).
    """
    rotation = np.asarray(rotation, dtype=np.float64)
    if rotation.shape != (3, 3):
        raise ValueError(f"rotation must be (3, 3), got {rotation.shape}")
    vertices = _all_vertices(parts) @ rotation.T
    if align_long_axis:
        extent = np.ptp(vertices, axis=0)
        if extent[0] > extent[1]:
            quarter = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
            rotation = quarter @ rotation
            vertices = vertices @ quarter.T
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    centre = (lo + hi) / 2.0
    diagonal = float(np.linalg.norm(hi - lo))
    if not diagonal > 0:
        raise ValueError("degenerate bounding box")
    scale = 1.0 / diagonal
    transform = np.eye(4)
    transform[:3, :3] = scale * rotation
    transform[:3, 3] = -scale * centre
    out = []
    for part in parts:
        copy = part.copy()
        copy.apply_transform(transform)
        out.append(copy)
    return out, transform


def junk_reason(name: str, parts: list[trimesh.Trimesh]) -> str | None:
    """Readable junk rules on a *normalised* model; ``None`` when it is kept."""
    if JUNK_NAME.search(name):
        return f"junk: name matches {JUNK_NAME.pattern!r}"
    faces = sum(len(p.faces) for p in parts)
    if faces < MIN_FACES:
        return f"junk: {faces} triangles (< {MIN_FACES}, billboard/marker)"
    extent = np.ptp(_all_vertices(parts), axis=0)
    if extent.min() < MIN_THICKNESS:
        return f"junk: flat (thinnest side {extent.min():.2g} of the diagonal: ground plane/billboard)"
    return None


# --------------------------------------------------------------------------- records


@dataclass
class ManifestRecord:
    """One kept shape in the manifest.

    ``transform`` is the ``(4, 4)`` source -> canonical matrix as nested lists;
    ``extents`` the canonical bbox side lengths ``(3,)`` (their norm is 1).
    """

    id: str
    source: str
    package: str | None
    path: str
    name: str
    category: str
    creator: str
    licence: str
    cls: str
    split: str
    groups: list[str]
    faces: int
    vertices: int
    parts: int
    watertight: bool
    textured: bool
    extents: list[float]
    transform: list[list[float]]
    mesh: str
    family: str
    extra: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        d = asdict(self)
        d["class"] = d.pop("cls")
        return d


@dataclass
class SkipEntry:
    """A model that was found but not kept, with the reason."""

    id: str
    source: str
    path: str
    name: str
    reason: str


def _display_path(path: str, root: Path) -> str:
    """Path as installed by the package (``/usr/share/...``) when it lies in the unpack cache."""
    unpacked = str(root / "cache" / "unpacked") + os.sep
    if path.startswith(unpacked):
        rest = path[len(unpacked):]
        return "/" + rest.split(os.sep, 1)[1] if os.sep in rest else rest
    return path


def _is_textured(parts: list[trimesh.Trimesh]) -> bool:
    for p in parts:
        material = getattr(p.visual, "material", None)
        if material is not None and (getattr(material, "image", None) is not None
                                     or getattr(material, "baseColorTexture", None) is not None):
            return True
    return False


def _export_glb(parts: list[trimesh.Trimesh], target: Path) -> None:
    scene = trimesh.Scene()
    for i, part in enumerate(parts):
        scene.add_geometry(part, geom_name=f"part{i}")
    atomic_write_bytes(target, scene.export(file_type="glb"))


def process_record(record: ShapeRecord, root: Path, shapes_dir: Path) -> dict:
    """Load, check, normalise, classify and export one record.

    Returns:
        ``{"entry": ManifestRecord}`` or ``{"skip": SkipEntry}``; never raises for
        a bad file.
    """
    shown = _display_path(record.path, root)

    def skip(reason: str) -> dict:
        log.info("skip %s: %s", record.shape_id, reason)
        return {"skip": SkipEntry(record.shape_id, record.source, shown, record.name, reason)}

    try:
        parts = [p for p in record.load() if isinstance(p, trimesh.Trimesh) and len(p.faces)]
    except (ValueError, OSError, KeyError, IndexError, EOFError) as exc:
        return skip(f"unreadable: {exc}"[:300])
    except Exception as exc:  # third-party loaders raise anything on broken files
        return skip(f"unreadable: {type(exc).__name__}: {exc}"[:300])
    problem = check_geometry(parts)
    if problem:
        return skip(problem)
    try:
        parts, transform = normalise_parts(parts, record.rotation, align_long_axis=record.align_long_axis)
    except ValueError as exc:
        return skip(f"degenerate: {exc}")
    junk = junk_reason(record.name, parts)
    if junk:
        return skip(junk)
    cls = classify(record.name, record.category, record.class_hint)
    split = split_of(record.shape_id, cls)
    vertices = _all_vertices(parts)
    extents = np.ptp(vertices, axis=0)
    extra = dict(record.extra)
    size = extra.get("catalogue_size_cm")
    if size and all(np.isfinite(size)) and min(size) > 0:
        expected = np.asarray(size, dtype=np.float64) / np.linalg.norm(size)
        extra["catalogue_extent_error"] = round(float(np.abs(expected - extents).max()), 4)
    merged = trimesh.util.concatenate([trimesh.Trimesh(p.vertices, p.faces, process=False) for p in parts])
    merged.merge_vertices()
    mesh_rel = f"shapes/{record.shape_id}.glb"
    try:
        _export_glb(parts, shapes_dir / f"{record.shape_id}.glb")
    except Exception as exc:  # a material trimesh cannot write: fall back to plain geometry
        log.warning("%s: textured export failed (%s); writing geometry only", record.shape_id, exc)
        plain = [trimesh.Trimesh(p.vertices, p.faces, process=False) for p in parts]
        _export_glb(plain, shapes_dir / f"{record.shape_id}.glb")
    entry = ManifestRecord(
        id=record.shape_id,
        source=record.source,
        package=record.package,
        path=shown,
        name=record.name,
        category=record.category,
        creator=record.creator,
        licence=record.licence,
        cls=cls,
        split=split,
        groups=groups_of(cls, split),
        faces=int(sum(len(p.faces) for p in parts)),
        vertices=int(sum(len(p.vertices) for p in parts)),
        parts=len(parts),
        watertight=bool(merged.is_watertight),
        textured=_is_textured(parts),
        extents=[round(float(e), 6) for e in extents],
        transform=[[round(float(v), 12) for v in row] for row in transform],
        mesh=mesh_rel,
        family=record.family,
        extra=extra,
    )
    entry.extra["source_rotation"] = rotation_to_list(transform[:3, :3] / np.linalg.norm(transform[:3, 0]))
    return {"entry": entry}


def find_near_duplicates(entries: list[ManifestRecord]) -> dict[str, str]:
    """Near-duplicate groups by the rules above.

    Returns:
        ``{dropped id: kept id}``.
    """
    dropped: dict[str, str] = {}
    groups: dict[tuple[str, str], list[ManifestRecord]] = {}
    for e in entries:
        groups.setdefault((e.source, e.cls), []).append(e)
    for members in groups.values():
        members = sorted(members, key=lambda e: e.id)
        ext = np.array([e.extents for e in members])
        for i, a in enumerate(members):
            if a.id in dropped:
                continue
            for j in range(i + 1, len(members)):
                b = members[j]
                if b.id in dropped:
                    continue
                diff = float(np.abs(ext[i] - ext[j]).max())
                same = a.faces == b.faces and a.vertices == b.vertices and diff <= DUP_SAME_EXTENT
                family = (
                    a.family == b.family
                    and abs(a.faces - b.faces) <= DUP_FAMILY_FACES * max(a.faces, b.faces)
                    and diff <= DUP_FAMILY_EXTENT
                )
                hull = (
                    min(a.faces, b.faces) >= DUP_HULL_MIN_FACES
                    and diff <= DUP_SAME_EXTENT
                    and abs(a.faces - b.faces) <= DUP_HULL_FACES * max(a.faces, b.faces)
                )
                if same or family or hull:
                    dropped[b.id] = a.id
    return dropped


# --------------------------------------------------------------------------- build

_WORKER: dict = {}


def enumerate_records(
    root: Path, sources: Iterable[str] | None = None, extra: list[ShapeRecord] | None = None
) -> list[ShapeRecord]:
    """Records of the chosen Debian sources (by default :data:`DEFAULT_SOURCES`) plus ``extra`` ones."""
    root = data_dir(root)
    unpacked = root / "cache" / "unpacked"
    chosen = list(DEFAULT_SOURCES) if sources is None else list(sources)
    records: list[ShapeRecord] = []
    for name in chosen:
        if name not in SOURCES:
            raise ValueError(f"unknown source {name!r}; known: {', '.join(SOURCES)}")
        found = SOURCES[name].enumerate_shapes(unpacked)
        log.info("%s: %d models", name, len(found))
        records += found
    records += list(extra or [])
    ids = Counter(r.shape_id for r in records)
    clashes = [i for i, n in ids.items() if n > 1]
    if clashes:
        raise ValueError(f"duplicate shape ids: {clashes[:5]}")
    return records


def _worker_init(root: str, sources: list[str] | None, extra_specs: list[tuple], shapes_dir: str) -> None:
    logging.getLogger("trimesh").setLevel(logging.ERROR)
    _WORKER["root"] = Path(root)
    _WORKER["shapes_dir"] = Path(shapes_dir)
    _WORKER["records"] = {r.shape_id: r for r in _records_from_specs(Path(root), sources, extra_specs)}


def _records_from_specs(root: Path, sources: list[str] | None, extra_specs: list[tuple]) -> list[ShapeRecord]:
    from .sources import folder, shapenet

    extra: list[ShapeRecord] = []
    for kind, path, opts in extra_specs:
        if kind == "shapenet":
            extra += shapenet.enumerate_shapes(Path(path), **opts)
        elif kind == "folder":
            extra += folder.enumerate_shapes(Path(path), **opts)
        else:
            raise ValueError(f"unknown extra source {kind!r}")
    return enumerate_records(root, sources, extra)


def _worker_run(shape_id: str) -> dict:
    record = _WORKER["records"][shape_id]
    return process_record(record, _WORKER["root"], _WORKER["shapes_dir"])


def _process_records(records: list, root: Path, shapes_dir: Path, sources: list[str] | None, extra_specs: list[tuple],
                     jobs: int, progress: Callable[[int, int], None] | None) -> list[dict]:
    """:func:`process_record` of every record, in order (``jobs`` > 1: in worker processes); ``progress(done, total)``."""
    results: list[dict] = []
    ids = [r.shape_id for r in records]
    if jobs <= 1:
        for k, record in enumerate(records):
            results.append(process_record(record, root, shapes_dir))
            if progress:
                progress(k + 1, len(records))
        return results
    with ProcessPoolExecutor(
        max_workers=jobs, initializer=_worker_init,
        initargs=(str(root), sources, extra_specs, str(shapes_dir)),
    ) as pool:
        for k, result in enumerate(pool.map(_worker_run, ids, chunksize=2)):
            results.append(result)
            if progress:
                progress(k + 1, len(records))
    return results


def build(
    root: Path | None = None,
    *,
    sources: list[str] | None = None,
    extra_specs: list[tuple] | None = None,
    jobs: int = 1,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Build ``corpus/manifest.json`` and ``corpus/shapes/*.glb`` under the data folder.

    Args:
        root: data folder (see :func:`data_dir`).
        sources: Debian source names to use (default: :data:`DEFAULT_SOURCES`, every source but the opt-in ones).
        extra_specs: user sources, ``("shapenet" | "folder", path, options)``.
        jobs: worker processes (1 = in this process).
        progress: called as ``progress(done, total)``.

    Returns:
        The manifest dict (also written to disk).
    """
    root = data_dir(root)
    extra_specs = list(extra_specs or [])
    corpus = root / "corpus"
    shapes_dir = corpus / "shapes"
    shapes_dir.mkdir(parents=True, exist_ok=True)
    records = _records_from_specs(root, sources, extra_specs)
    if not records:
        raise ValueError(f"no models found under {root / 'cache' / 'unpacked'}: run 'genre data fetch' first")
    results = _process_records(records, root, shapes_dir, sources, extra_specs, jobs, progress)
    entries = [r["entry"] for r in results if "entry" in r]
    skips = [r["skip"] for r in results if "skip" in r]
    dropped = find_near_duplicates(entries)
    kept = []
    for e in entries:
        if e.id in dropped:
            skips.append(SkipEntry(e.id, e.source, e.path, e.name, f"near-duplicate of {dropped[e.id]}"))
            (shapes_dir / f"{e.id}.glb").unlink(missing_ok=True)
        else:
            kept.append(e)
    product = product_groups((e.id, e.cls, e.split, e.family) for e in kept)
    for e in kept:
        e.groups = [*e.groups, product[e.id]]
    # meshes of shapes no longer in the corpus (an earlier build) are removed
    kept_files = {f"{e.id}.glb" for e in kept}
    for f in shapes_dir.glob("*.glb"):
        if f.name not in kept_files:
            f.unlink()
    manifest = {
        "version": 1,
        "frame": "right-handed, +Z up, front toward -Y, bbox centre at origin, bbox diagonal 1",
        "data_dir_note": "GPL data: never commit this folder",
        "rules": rules_text(),
        "classes": {
            "seen": list(SEEN_CLASSES),
            "unseen": list(UNSEEN_CLASSES),
            "unseen-pix3d": list(UNSEEN_PIX3D_CLASSES),
        },
        "splits": {
            name: sorted(e.id for e in kept if name in e.groups)
            for name in ("train", "test", "unseen", "unseen-pix3d", *PRODUCT_GROUPS)
        },
        "shapes": [e.to_json() for e in sorted(kept, key=lambda e: e.id)],
        "skipped": [asdict(s) for s in sorted(skips, key=lambda s: s.id)],
    }
    atomic_write_text(corpus / "manifest.json", json.dumps(manifest, indent=1, ensure_ascii=False))
    return manifest


def load_manifest(root: Path | None = None) -> dict:
    """Read ``corpus/manifest.json``; ``FileNotFoundError`` with a hint if absent."""
    return read_manifest(data_dir(root) / "corpus" / "manifest.json")
