"""The training pack: the one on-disk format a GPU burst trains from (``genre data pack``).

A burst runs on a lent machine with its own Python, torch and numpy but no
Blender, no trimesh and no network, and everything it reads must travel with
the working tree (64 MiB in all).  Rendered views and their per-view voxel
targets do not fit (about 40 KB a view), so the pack holds **the training
shapes' meshes**, and the burst makes every view, depth map, spherical map
and voxel target itself on the GPU (:mod:`training.learn.burst`).  Any number
of views, at any elevation, can be made from a mesh.

A pack is a folder::

    PACK/pack.json     format, version, the split it was cut from, the shapes
                       (id, class, source, licence, faces before and after
                       decimation), counts per class, and the sha256 of meshes.npz
    PACK/meshes.npz    vertices (V, 3) uint16 — object-frame coordinates
                       quantised over [-0.5, 0.5] (step 1/65535) —, faces
                       (F, 3) uint16 indices local to each shape,
                       vertex_offsets (N + 1,) int64 and face_offsets (N + 1,)
                       int64: shape i owns vertices[vo[i]:vo[i+1]] and
                       faces[fo[i]:fo[i+1]]

``thin=N`` adds, after the manifest's shapes, N shapes of every kind of
:mod:`training.data.sources.thin` (procedural plates, cards, books, leaves,
thin-walled bowls and rods: ``thin-<kind>-<k>``, class ``thin-<kind>``,
source ``procedural-thin``, CC0).  They are training-only shapes, in no
corpus split and with no test members; pack.json records ``thin``.

Meshes above ``max_faces`` triangles are decimated (quadric error,
``fast_simplification``) to that many.  **A pack never holds a test shape**:
the builder refuses a split that is not a training split, and every shape
whose split or groups name a test split; :func:`read_pack` checks it again.

Reading needs numpy alone (the device side); building needs trimesh.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from genre_backend.arguments import add_out

__all__ = ["PACK_FORMAT", "DEVICE_CARRY_MIB", "TREE_BUDGET_MIB", "PACK_BUDGET_MIB", "WHEELS_BUDGET_MIB", "TRAIN_SPLITS", "TEST_SPLITS", "Pack", "pack_bytes", "build_pack", "read_pack",
           "quantise", "dequantise", "main"]

PACK_FORMAT = "genre-pack/1"
# What travels to a device call (64 MiB in all): the tracked tree, the pack and the carried wheels (.whl).
# tests/training/learn/test_burst.py holds the tree to its budget; the builder refuses a pack over its own.
DEVICE_CARRY_MIB = 64
TREE_BUDGET_MIB = 42  # 40 until 2026-12-01, when the tree reached it; the pack measures 14.75 MiB
PACK_BUDGET_MIB = 18
WHEELS_BUDGET_MIB = 1
TRAIN_SPLITS = ("product-train", "train")  # the product model's training split; the protocol's (seen classes)
TEST_SPLITS = ("product-test", "test")
_JSON, _ARRAYS = "pack.json", "meshes.npz"
_Q = 65535.0


def quantise(vertices: np.ndarray) -> np.ndarray:
    """Object-frame vertices (V, 3) within [-0.5, 0.5] → uint16 (V, 3); values outside are clipped."""
    return np.round((np.clip(np.asarray(vertices, np.float64), -0.5, 0.5) + 0.5) * _Q).astype(np.uint16)


def dequantise(q: np.ndarray) -> np.ndarray:
    """Inverse of :func:`quantise`: uint16 (V, 3) → float32 (V, 3); error at most 0.5/65535."""
    return (q.astype(np.float32) / np.float32(_Q) - np.float32(0.5)).astype(np.float32)


@dataclass(frozen=True)
class Pack:
    """A read pack: ``meta`` (pack.json), the concatenated arrays and the offsets (see the module doc)."""

    root: Path
    meta: dict
    vertices: np.ndarray  # (V, 3) uint16
    faces: np.ndarray  # (F, 3) uint16
    vertex_offsets: np.ndarray  # (N + 1,) int64
    face_offsets: np.ndarray  # (N + 1,) int64

    def __len__(self) -> int:
        return len(self.vertex_offsets) - 1

    @property
    def ids(self) -> list[str]:
        return [s["id"] for s in self.meta["shapes"]]

    def mesh(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Shape ``i``: vertices (V, 3) float32 in the object frame, faces (F, 3) int64."""
        v0, v1 = self.vertex_offsets[i], self.vertex_offsets[i + 1]
        f0, f1 = self.face_offsets[i], self.face_offsets[i + 1]
        return dequantise(self.vertices[v0:v1]), self.faces[f0:f1].astype(np.int64)


def pack_bytes(root: str | os.PathLike) -> int:
    """The pack's size on disk in bytes (what it adds to a device call's 64 MiB)."""
    return sum(p.stat().st_size for p in Path(root).iterdir() if p.is_file())


def _is_test(entry: dict) -> bool:
    return entry.get("split") in TEST_SPLITS or any(g in TEST_SPLITS for g in entry.get("groups") or ())


def _decimate(vertices: np.ndarray, faces: np.ndarray, max_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Merge duplicate vertices, drop degenerate faces, and decimate to at most ``max_faces`` triangles."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=True)  # merges coincident vertices
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) > max_faces:
        import fast_simplification

        v, f = fast_simplification.simplify(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32),
                                            target_count=max_faces)
        mesh = trimesh.Trimesh(v, f, process=True)
        mesh.update_faces(mesh.nondegenerate_faces())
        mesh.remove_unreferenced_vertices()
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)


def _training_entries(manifest_path: Path, split: str, limit: int | None) -> list[dict]:
    """The manifest's shapes of the training ``split``, less any a test split names; ValueError for a test split or none."""
    from .views import read_manifest

    if split not in TRAIN_SPLITS:
        raise ValueError(f"split {split!r}: a pack is cut from a training split ({', '.join(TRAIN_SPLITS)}), never a test split")
    manifest = read_manifest(manifest_path)
    entries = [e for e in manifest["shapes"] if e.get("split") == split or split in (e.get("groups") or ())]
    entries = [e for e in entries if not _is_test(e)][:limit]
    if not entries:
        raise ValueError(f"{manifest_path}: no shapes of split {split!r}")
    return entries


def build_pack(manifest_path: str | os.PathLike, out: str | os.PathLike, split: str = "product-train",
               max_faces: int = 2000, limit: int | None = None, max_mib: float | None = None,
               progress: bool = False, thin: int = 0) -> dict:
    """Write a pack of the shapes of ``split`` (a training split) of a corpus manifest into ``out``.

    ``thin``: shapes per kind of :func:`training.data.sources.thin.thin_shapes`
    (seed 0) added after the manifest's shapes (training-only; 0: none).

    Returns the pack's metadata (pack.json).  Raises ValueError for a test
    split, a manifest without such shapes, or a pack larger than ``max_mib``.
    """
    import trimesh

    from genre_backend.atomic import atomic_write, atomic_write_json

    if isinstance(max_faces, bool) or not isinstance(max_faces, int) or not 4 <= max_faces <= 65535:
        raise ValueError(f"max_faces: expected an int in [4, 65535], got {max_faces!r}")
    if isinstance(thin, bool) or not isinstance(thin, int) or not 0 <= thin <= 1000:
        raise ValueError(f"thin: expected an int in [0, 1000] (shapes per kind), got {thin!r}")
    manifest_path = Path(manifest_path)
    entries = _training_entries(manifest_path, split, limit)
    start = time.time()
    verts, faces, vo, fo, shapes = [], [], [0], [0], []

    def add(entry: dict, mesh) -> None:
        v, f = _decimate(np.asarray(mesh.vertices), np.asarray(mesh.faces), max_faces)
        if len(v) > 65535:
            raise ValueError(f"{entry['id']}: {len(v)} vertices after decimation (uint16 indices hold 65,535)")
        verts.append(quantise(v))
        faces.append(f.astype(np.uint16))
        vo.append(vo[-1] + len(v))
        fo.append(fo[-1] + len(f))
        shapes.append({**entry, "faces": int(len(f)), "faces_source": int(len(mesh.faces))})

    for k, e in enumerate(entries):
        rel = e.get("mesh")
        path = (manifest_path.parent / rel) if rel else manifest_path.parent / "shapes" / f"{e['id']}.glb"
        mesh = trimesh.load(path, force="mesh", process=False)
        add({"id": e["id"], "class": e.get("class"), "source": e.get("source"), "licence": e.get("licence")}, mesh)
        if progress and (k + 1) % 50 == 0:
            print(f"\r  {k + 1}/{len(entries)} shapes ({time.time() - start:.0f} s)", end="", file=sys.stderr, flush=True)
    if thin:
        from .sources.thin import thin_shapes

        known = {s["id"] for s in shapes}
        for sid, cls, mesh in thin_shapes(thin):
            if sid in known:
                raise ValueError(f"{sid}: a thin shape's id is already in the manifest")
            add({"id": sid, "class": cls, "source": "procedural-thin", "licence": "CC0"}, mesh)
    if progress:
        print(file=sys.stderr)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    arrays = {"vertices": np.concatenate(verts), "faces": np.concatenate(faces),
              "vertex_offsets": np.asarray(vo, np.int64), "face_offsets": np.asarray(fo, np.int64)}
    atomic_write(out / _ARRAYS, lambda fh: np.savez_compressed(fh, **arrays))
    digest = hashlib.sha256((out / _ARRAYS).read_bytes()).hexdigest()
    meta = {
        "format": PACK_FORMAT,
        "split": split,
        "manifest": str(manifest_path),
        "manifest_sha256": hashlib.sha256(manifest_path.read_bytes()).hexdigest(),
        "max_faces": max_faces,
        "thin": thin,
        "shapes": shapes,
        "classes": dict(sorted(Counter(s["class"] for s in shapes).items())),
        "faces_total": int(fo[-1]),
        "meshes_sha256": digest,
        "built_s": round(time.time() - start, 1),
    }
    atomic_write_json(out / _JSON, meta)
    size = pack_bytes(out)
    if max_mib is not None and size > max_mib * 2**20:
        raise ValueError(f"{out}: the pack is {size / 2**20:.1f} MiB, over the {max_mib} MiB budget "
                         f"(fewer --max-faces, or --limit)")
    return meta


def read_pack(root: str | os.PathLike, verify: bool = True) -> Pack:
    """Read a pack folder (numpy only).  ``verify``: check meshes.npz's sha256 against pack.json.

    Raises ValueError with the reason for a missing, foreign, damaged or test-holding pack.
    """
    root = Path(root)
    try:
        meta = json.loads((root / _JSON).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ValueError(f"{root}: not a readable pack ({exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != PACK_FORMAT:
        raise ValueError(f"{root}: not a {PACK_FORMAT} pack (format {meta.get('format') if isinstance(meta, dict) else None!r})")
    if meta.get("split") not in TRAIN_SPLITS or any(_is_test(s) for s in meta.get("shapes", [])):
        raise ValueError(f"{root}: the pack names a test split")
    raw = (root / _ARRAYS).read_bytes() if (root / _ARRAYS).is_file() else b""
    if verify and hashlib.sha256(raw).hexdigest() != meta.get("meshes_sha256"):
        raise ValueError(f"{root}/{_ARRAYS}: missing or damaged (sha256 differs from pack.json)")
    import io

    with np.load(io.BytesIO(raw)) as z:
        arrays = {k: z[k] for k in ("vertices", "faces", "vertex_offsets", "face_offsets")}
    vo, fo = arrays["vertex_offsets"], arrays["face_offsets"]
    n = len(meta["shapes"])
    if len(vo) != n + 1 or len(fo) != n + 1 or vo[-1] != len(arrays["vertices"]) or fo[-1] != len(arrays["faces"]):
        raise ValueError(f"{root}: offsets do not match the arrays")
    return Pack(root, meta, **arrays)


def main(argv: list[str] | None = None, prog: str = "genre data pack") -> int:
    parser = argparse.ArgumentParser(prog=prog, description="Write a training pack (the training shapes' meshes, "
                                     "compressed) for a GPU burst (training/learn/burst.py).")
    parser.add_argument("--shapes", required=True, help="the corpus manifest ($GENRE_HOME/corpus/manifest.json)")
    add_out(parser, required=True, help="the pack folder (e.g. .pack in the checkout, which git ignores)")
    parser.add_argument("--split", default="product-train", choices=TRAIN_SPLITS, help="the training split (default product-train)")
    parser.add_argument("--max-faces", type=int, default=2000, help="decimate meshes above this many triangles (default 2000)")
    parser.add_argument("--limit", type=int, default=None, help="only the first K shapes (tests, smoke runs)")
    parser.add_argument("--max-mib", type=float, default=PACK_BUDGET_MIB,
                        help=f"refuse a pack larger than this (default {PACK_BUDGET_MIB} MiB: what a device call leaves it)")
    parser.add_argument("--thin", type=int, default=40, metavar="N",
                        help="add N procedural flat and thin shapes of every kind (plates, cards, books, leaves, "
                             "thin-walled bowls, rods; training/data/sources/thin.py): training-only shapes, in no "
                             "corpus split and with no test members (default 40: 240 shapes; 0: none)")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    try:
        meta = build_pack(args.shapes, args.out, args.split, args.max_faces, args.limit, args.max_mib,
                          progress=not args.no_progress, thin=args.thin)
    except (ValueError, FileNotFoundError) as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 1
    size = pack_bytes(args.out)
    thin = f", {args.thin} thin shapes per kind" if args.thin else ""
    print(f"wrote {args.out}: {len(meta['shapes'])} shapes of {args.split}{thin} ({len(meta['classes'])} classes), "
          f"{meta['faces_total']:,} triangles, {size / 2**20:.2f} MiB, {meta['built_s']:.0f} s")
    return 0
