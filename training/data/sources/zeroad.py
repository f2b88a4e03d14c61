"""0 A.D.'s buildings, props and plants (``0ad-data``, CC-BY-SA-3.0, Wildfire Games).

Shapes: the compiled meshes ``art/meshes/{structural,props,gaia}/*.dae.cached.pmd``
inside the package's ``mods/public/public.zip`` (read in place, never unpacked),
rigid (no bones: a unit's skinned body is left out) and of at least
:data:`MIN_FACES` triangles.  An actor file (``art/actors/**/*.xml``) names the
mesh of each variant and its textures; a mesh takes the ``baseTex`` of the
first actor variant that shows it (else the actor's first ``baseTex``), decoded from
its cached ``.dds`` by Pillow and shrunk to at most :data:`TEXTURE_SIZE` pixels.

Left out on purpose:

* meshes drawn with an alpha-tested material (``basic_trans*``, ``*_trans_*``
  other than ``player_trans``) whose texture is transparent under more than
  :data:`MAX_CUT_OUT` of their surface (sampled at each triangle's UV centre):
  leaves and fences drawn as cut-out cards would render as solid quads, since
  the renderer's depth is the geometry's.  Rocks and trunks drawn with those
  materials are opaque and kept;
* meshes no actor shows with a texture (editor markers, test meshes).

Classes: the source's own, by folder: ``structural`` -> ``building``, ``props``
-> ``prop``, ``gaia`` -> ``plant`` (trees, bushes, rocks).  None is a protocol
class (:data:`training.data.corpus.SEEN_CLASSES` and the unseen lists), so the
protocol's splits do not change; the product split holds out families of each
class as for any other source.  ``player_trans`` textures keep the player's
colour in their alpha channel, so textures are used as RGB.

Family: the file stem without trailing variant marks (``_a``, ``_2``, ``_new``),
so ``athen_house_a``/``athen_house_b`` and ``bush_1``/``bush_2`` stay on one side
of the product split and are compared as near-duplicates.

Frame: Y up (checked by eye on renders: buildings stand on their ground), and
the front taken as +Z, so ``(x, y, z) -> (x, -z, y)`` (:data:`Y_UP_FRONT_POS_Z`).
The heading is not checked: the renders' cameras circle the object, and
training mirrors half the views, so neither the front nor the handedness of
the game's frame matters to the nets.
"""

from __future__ import annotations

import functools
import io
import os
import re
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

from ..readers.pmd import read_pmd
from . import Y_UP_FRONT_POS_Z, ShapeRecord, slug

__all__ = ["PACKAGES", "enumerate_shapes", "MIN_FACES", "TEXTURE_SIZE", "MAX_CUT_OUT", "CLASSES", "mesh_textures",
           "family_of", "cut_out_fraction"]

PACKAGES = ("0ad-data",)
_ZIP = "usr/share/games/0ad/mods/public/public.zip"
_MESHES = "art/meshes/"
_SUFFIX = ".dae.cached.pmd"
_SKINS = "art/textures/skins/"
MIN_FACES = 200
TEXTURE_SIZE = 512
MAX_CUT_OUT = 0.02
CLASSES = {"structural": "building", "props": "prop", "gaia": "plant"}
_ALPHA_TESTED = re.compile(r"^basic_trans|(?<!player)_trans", re.IGNORECASE)
_VARIANT_MARK = re.compile(r"(_(\d+|[a-z]|new|old|low|lod\d*|alt\d*))+$", re.IGNORECASE)


def family_of(stem: str) -> str:
    """A mesh stem without its trailing variant marks (``athen_house_b_2`` -> ``athen_house``)."""
    base = _VARIANT_MARK.sub("", stem.lower())
    return base or stem.lower()


def _variant_pairs(root: ET.Element) -> list[tuple[str, str | None]]:
    """``(mesh, baseTex or None)`` of every variant of an actor that names a mesh; a variant without a
    texture of its own takes the actor's first (its groups often pick mesh and texture apart)."""
    pairs: list[tuple[str, str | None]] = []
    first: str | None = None
    for variant in root.iter("variant"):
        mesh = (variant.findtext("mesh") or "").strip()
        base = next((t.get("file").strip() for t in variant.iter("texture")
                     if t.get("name") == "baseTex" and t.get("file")), None)
        first = first or base
        if mesh:
            pairs.append((mesh, base))
    return [(m, b or first) for m, b in pairs]


def mesh_textures(archive: zipfile.ZipFile) -> tuple[dict[str, str], set[str]]:
    """What the actor files say about each mesh.

    Returns:
        ``({mesh member: texture member}, {mesh members some actor draws alpha-tested})``: the
        ``.pmd`` and ``.dds`` member names inside ``public.zip``; the first actor (in
        name order) that shows a mesh with a texture decides its texture.
    """
    names = set(archive.namelist())
    textures: dict[str, str] = {}
    alpha_tested: set[str] = set()
    for name in sorted(n for n in names if n.startswith("art/actors/") and n.endswith(".xml")):
        try:
            root = ET.fromstring(archive.read(name))
        except ET.ParseError:
            continue
        material = (root.findtext("material") or "").strip()
        alpha = bool(material) and bool(_ALPHA_TESTED.search(Path(material).stem))
        for mesh, base in _variant_pairs(root):
            member = _MESHES + mesh + ".cached.pmd" if mesh.endswith(".dae") else _MESHES + mesh
            if alpha:
                alpha_tested.add(member)
            if base and member not in textures:
                dds = _SKINS + base + ".cached.dds"
                if dds in names:
                    textures[member] = dds
    return textures, alpha_tested


def _archive(path: str) -> zipfile.ZipFile:
    """The open archive of this process: a forked worker must not share its parent's file offset."""
    return _open_archive(path, os.getpid())


@functools.lru_cache(maxsize=4)
def _open_archive(path: str, pid: int) -> zipfile.ZipFile:
    return zipfile.ZipFile(path)


def cut_out_fraction(mesh: trimesh.Trimesh, alpha: np.ndarray) -> float:
    """Share of ``mesh``'s area whose texture is transparent (alpha < 128) at each triangle's UV centre.

    Args:
        mesh: a mesh from :func:`read_pmd` (UVs in ``metadata["uv"]``, v from the image's bottom row).
        alpha: ``(h, w) uint8`` the texture's alpha channel, rows top-down.
    """
    uv = np.asarray(mesh.metadata["uv"], dtype=np.float64)[mesh.faces].mean(axis=1) % 1.0
    h, w = alpha.shape
    rows = np.minimum(((1.0 - uv[:, 1]) * h).astype(np.int64), h - 1)
    cols = np.minimum((uv[:, 0] * w).astype(np.int64), w - 1)
    area = mesh.area_faces
    total = float(area.sum())
    return float(area[alpha[rows, cols] < 128].sum()) / total if total > 0 else 0.0


def _load(zip_path: str, member: str, texture: str, alpha_tested: bool) -> list[trimesh.Trimesh]:
    archive = _archive(zip_path)
    mesh = read_pmd(archive.read(member))
    with Image.open(io.BytesIO(archive.read(texture))) as image:
        if alpha_tested:
            share = cut_out_fraction(mesh, np.asarray(image.convert("RGBA"))[:, :, 3])
            if share > MAX_CUT_OUT:
                raise ValueError(f"cut-out texture: {share:.0%} of the surface is transparent (> {MAX_CUT_OUT:.0%})")
        image = image.convert("RGB")
        image.thumbnail((TEXTURE_SIZE, TEXTURE_SIZE))
    # v counts from the image's bottom row, as trimesh's does: on the meshes of alpha-tested actors
    # that reading puts more of the surface on opaque texels than v from the top (see cut_out_fraction)
    uv = np.asarray(mesh.metadata["uv"], dtype=np.float64)
    visual = trimesh.visual.TextureVisuals(uv=uv, image=image)
    return [trimesh.Trimesh(mesh.vertices, mesh.faces, visual=visual, process=False)]


def enumerate_shapes(root: Path) -> list[ShapeRecord]:
    """The rigid, textured meshes of ``root/0ad-data``'s ``public.zip`` (cut-out ones refuse to load)."""
    zip_path = Path(root) / "0ad-data" / _ZIP
    if not zip_path.is_file():
        return []
    archive = _archive(str(zip_path))
    textures, alpha_tested = mesh_textures(archive)
    records = []
    for member in sorted(textures):
        if not member.endswith(_SUFFIX):
            continue
        folder = member[len(_MESHES):].split("/", 1)[0]
        if folder not in CLASSES:
            continue
        try:
            info = read_pmd(archive.read(member))
        except (KeyError, ValueError):
            continue
        if info.metadata["bones"] or len(info.faces) < MIN_FACES:
            continue
        rel = member[len(_MESHES):-len(_SUFFIX)]
        stem = rel.rsplit("/", 1)[-1]
        records.append(
            ShapeRecord(
                shape_id=f"zeroad-{slug(rel.replace('/', '-'))}",
                source="zeroad",
                package="0ad-data",
                path=f"{zip_path}!{member}",
                name=stem,
                creator="Wildfire Games (0 A.D.)",
                licence="CC-BY-SA-3.0",
                category=folder,
                class_hint=CLASSES[folder],
                rotation=Y_UP_FRONT_POS_Z,
                load=lambda z=str(zip_path), m=member, t=textures[member], a=member in alpha_tested: _load(z, m, t, a),
                family=f"zeroad-{folder}-{family_of(stem)}",
                extra={"texture": textures[member][len(_SKINS):]},
            )
        )
    return records
