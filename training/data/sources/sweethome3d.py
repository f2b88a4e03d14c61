"""Sweet Home 3D furniture: the five ``*.sh3f`` catalogues of the
``sweethome3d-furniture`` package and the default catalogue inside the
``sweethome3d`` jar.

A catalogue is a zip archive with a ``PluginFurnitureCatalog.properties``
(``DefaultFurnitureCatalog.properties`` inside the jar): a Java properties
file (Latin-1, ``\\uXXXX`` escapes, ``\\`` line continuations) with numbered
keys ``name#N``, ``category#N``, ``creator#N``, ``model#N`` (absolute path of
an OBJ inside the archive), ``multiPartModel#N`` (the OBJ's MTL and textures
lie beside it) and sometimes ``modelRotation#N`` (nine numbers, a 3x3 matrix
read row by row that turns the stored model into Sweet Home 3D's frame,
applied to column vectors as Sweet Home 3D's Java3D code does).

Frame: Sweet Home 3D models are Y-up and their front faces +Z (the catalogue's
``width``/``depth``/``height`` are the X/Z/Y extents after
``modelRotation``).  The canonical rotation is therefore
``Y_UP_FRONT_POS_Z @ modelRotation``.  Checked on the real catalogues by
comparing each model's canonical bounding-box proportions with the
catalogue's width/depth/height (X/Y/Z): ``extra['catalogue_size_cm']`` and the
``size_check`` the corpus builder records; chairs and tables come out with
legs along Z and seat/top horizontal.

Licences: ``BlendSwap-CC-0`` is CC0 (public domain); the other four plug-in
catalogues are CC-BY 3.0 (the ``creator`` is kept for attribution); the
default catalogue ships in the GPL-2+ ``sweethome3d`` package.
"""

from __future__ import annotations

import posixpath
import re
import tempfile
import zipfile
from pathlib import Path

import numpy as np
import trimesh

from . import Y_UP_FRONT_POS_Z, ShapeRecord, scene_parts, slug

__all__ = ["PACKAGES", "enumerate_shapes", "parse_properties", "catalogue_entries", "load_obj_from_zip"]

PACKAGES = ("sweethome3d-furniture", "sweethome3d")

_FURNITURE_DIR = "usr/share/sweethome3d/furniture"
_JAR = "usr/share/sweethome3d/sweethome3d.jar"
_DEFAULT_PROPERTIES = "com/eteks/sweethome3d/io/DefaultFurnitureCatalog.properties"
_PLUGIN_PROPERTIES = "PluginFurnitureCatalog.properties"
_ESCAPES = {"t": "\t", "n": "\n", "r": "\r", "f": "\f"}


def _unescape(text: str) -> str:
    out: list[str] = []
    i = 0
    while i < len(text):
        c = text[i]
        if c != "\\" or i + 1 >= len(text):
            out.append(c)
            i += 1
            continue
        nxt = text[i + 1]
        if nxt == "u" and re.fullmatch(r"[0-9a-fA-F]{4}", text[i + 2 : i + 6] or ""):
            out.append(chr(int(text[i + 2 : i + 6], 16)))
            i += 6
        else:
            out.append(_ESCAPES.get(nxt, nxt))
            i += 2
    return "".join(out)


def parse_properties(data: bytes) -> dict[str, str]:
    """Parse a Java ``.properties`` file.

    Args:
        data: the raw bytes (decoded as Latin-1, as Java does).

    Returns:
        key -> value, with ``\\uXXXX`` and backslash escapes resolved,
        continuation lines joined and comments (``#``/``!``) dropped.
    """
    if not isinstance(data, (bytes, bytearray)):
        raise TypeError("data must be bytes")
    lines = data.decode("latin-1").splitlines()
    props: dict[str, str] = {}
    i = 0
    while i < len(lines):
        line = lines[i].lstrip()
        i += 1
        if not line or line[0] in "#!":
            continue
        # join continuation lines (an odd number of trailing backslashes)
        while (len(line) - len(line.rstrip("\\"))) % 2 == 1 and i < len(lines):
            line = line[:-1] + lines[i].lstrip()
            i += 1
        # key ends at the first unescaped '=', ':' or whitespace
        k = 0
        while k < len(line):
            if line[k] == "\\":
                k += 2
                continue
            if line[k] in "=: \t":
                break
            k += 1
        key = line[:k]
        rest = line[k:].lstrip(" \t")
        if rest[:1] in ("=", ":"):
            rest = rest[1:].lstrip(" \t")
        props[_unescape(key)] = _unescape(rest)
    return props


def catalogue_entries(props: dict[str, str]) -> list[dict[str, str]]:
    """Group ``key#N`` properties into one dict per piece ``N`` (sorted by N).

    Only pieces that have a ``model#N`` are returned; each dict has the keys
    without the ``#N`` suffix plus ``"index"``.
    """
    pieces: dict[int, dict[str, str]] = {}
    for key, value in props.items():
        m = re.fullmatch(r"([A-Za-z]+)#(\d+)", key)
        if m:
            pieces.setdefault(int(m.group(2)), {})[m.group(1)] = value
    out = []
    for n in sorted(pieces):
        if "model" in pieces[n]:
            entry = dict(pieces[n])
            entry["index"] = str(n)
            out.append(entry)
    return out


def parse_model_rotation(text: str | None) -> np.ndarray:
    """``modelRotation`` value (9 numbers, row by row) -> ``(3, 3) float``; identity if absent."""
    if not text:
        return np.eye(3)
    values = [float(v) for v in text.split()]
    if len(values) != 9:
        raise ValueError(f"modelRotation needs 9 numbers, got {len(values)}: {text!r}")
    r = np.array(values).reshape(3, 3)
    # re-orthonormalise: the catalogues store 8 significant digits
    u, _s, vt = np.linalg.svd(r)
    r = u @ vt
    if np.linalg.det(r) < 0:
        raise ValueError(f"modelRotation is a reflection: {text!r}")
    return r


def _referenced_files(text: str, keywords: tuple[str, ...]) -> list[str]:
    names = []
    for line in text.splitlines():
        parts = line.strip().split()
        if len(parts) >= 2 and parts[0] in keywords:
            # options like "-s 1 1 1" may precede the file name: take the last token
            names.append(parts[-1])
    return names


def load_obj_from_zip(archive: Path, member: str) -> list[trimesh.Trimesh]:
    """Load an OBJ (with its MTL and textures) stored inside a zip archive.

    The OBJ, the MTL files it names and the textures those name are copied to
    a temporary folder keeping their relative layout, then loaded by trimesh.

    Returns:
        The model's parts (one per material), source coordinates.
    """
    with zipfile.ZipFile(archive) as zf:
        names = set(zf.namelist())
        if member not in names:
            raise ValueError(f"{archive}: no member {member!r}")
        base = posixpath.dirname(member)
        with tempfile.TemporaryDirectory(prefix="genre-sh3d-") as tmp:
            tmp_path = Path(tmp)

            def extract(name: str) -> str | None:
                name = posixpath.normpath(name)
                if name not in names or name.startswith(".."):
                    return None
                target = tmp_path / name
                target.parent.mkdir(parents=True, exist_ok=True)
                target.write_bytes(zf.read(name))
                return name

            extract(member)
            obj_text = zf.read(member).decode("latin-1")
            for mtl in _referenced_files(obj_text, ("mtllib",)):
                got = extract(posixpath.join(base, mtl))
                if got is None:
                    continue
                mtl_text = zf.read(got).decode("latin-1")
                for tex in _referenced_files(mtl_text, ("map_Kd", "map_Ka", "map_d", "map_Ks", "map_bump", "bump")):
                    extract(posixpath.join(posixpath.dirname(got), tex))
            loaded = trimesh.load(str(tmp_path / member), force="scene")
            parts = scene_parts(loaded)
            # pull texture images into memory before the folder disappears
            for part in parts:
                material = getattr(part.visual, "material", None)
                image = getattr(material, "image", None)
                if image is not None:
                    image.load()
    return parts


def _licence(catalogue: str) -> str:
    if catalogue == "default":
        return "GPL-2+"
    if "cc-0" in catalogue.lower():
        return "CC0"
    return "CC-BY-3.0"


def _records_for(archive: Path, properties_member: str, catalogue: str, package: str) -> list[ShapeRecord]:
    with zipfile.ZipFile(archive) as zf:
        props = parse_properties(zf.read(properties_member))
    records = []
    for entry in catalogue_entries(props):
        member = entry["model"].lstrip("/")
        try:
            model_rotation = parse_model_rotation(entry.get("modelRotation"))
        except ValueError:
            continue
        piece_id = entry.get("id", "") or posixpath.splitext(posixpath.basename(member))[0]
        shape_id = f"sh3d-{slug(catalogue)}-{slug(piece_id.split('#')[-1])}-{entry['index']}"
        size = tuple(float(entry.get(k, "nan") or "nan") for k in ("width", "depth", "height"))
        record = ShapeRecord(
            shape_id=shape_id,
            source="sweethome3d",
            package=package,
            path=f"{archive}!{member}",
            name=entry.get("name", piece_id).strip(),
            creator=entry.get("creator", "eTeks" if catalogue == "default" else "").strip(),
            licence=_licence(catalogue),
            category=entry.get("category", "").strip(),
            class_hint=None,
            rotation=Y_UP_FRONT_POS_Z @ model_rotation,
            load=lambda a=archive, m=member: load_obj_from_zip(a, m),
            extra={"catalogue_size_cm": list(size)},  # (width, depth, height) = canonical X, Y, Z extents
        )
        records.append(record)
    return records


def enumerate_shapes(root: Path) -> list[ShapeRecord]:
    """All pieces of the installed catalogues under ``root``.

    Args:
        root: folder holding ``sweethome3d-furniture/`` and ``sweethome3d/``
            (each the ``dpkg -x`` tree of that package); either may be missing.
    """
    root = Path(root)
    records: list[ShapeRecord] = []
    furniture = root / "sweethome3d-furniture" / _FURNITURE_DIR
    if furniture.is_dir():
        for archive in sorted(furniture.glob("*.sh3f")):
            records += _records_for(archive, _PLUGIN_PROPERTIES, archive.stem, "sweethome3d-furniture")
    jar = root / "sweethome3d" / _JAR
    if jar.is_file():
        records += _records_for(jar, _DEFAULT_PROPERTIES, "default", "sweethome3d")
    return records
