"""The mesh files the backend writes, and the checks before writing anything.

Formats (:data:`MESH_FORMATS`), each optionally coloured from the photo
(:class:`~.colour.PhotoTexture`):

=======  ==========================  =============================================
format   plain                       with ``texture``
=======  ==========================  =============================================
``obj``  ``NAME.obj``                ``NAME.obj`` with ``vt`` UVs per face corner,
                                     ``NAME.mtl`` (``map_Kd``) and
                                     ``NAME_texture.png``
``ply``  ``NAME.ply``                vertex colours (the texture sampled at each
                                     vertex's own UV)
``glb``  ``NAME.glb``                one file: UVs and the texture embedded as the
                                     PBR base colour; a vertex with two UVs (on
                                     the outline of what the photo shows) is
                                     split in two
=======  ==========================  =============================================

Axes.  The mesh lives in the view frame (:mod:`genre_backend.frame`: +x
right, +y up, +z toward the camera).  ``obj`` and ``glb`` are always written
in it, +y up: glTF requires +y up with the front toward +z, and Blender's OBJ
importer (like most tools) reads an OBJ that way; both come into Blender
upright, front toward −Y.  ``ply`` has no axis convention and Blender's PLY
importer takes the file's axes as its own (+z up), so a PLY is written +z up
by default (``up="z"``: (x, y, z) → (x, −z, y), :data:`Y_UP_TO_Z_UP`, a proper
rotation, so faces keep their winding): it lands in Blender exactly where the
OBJ and glTF land.  ``up="y"`` writes a PLY in the view frame itself.
``up="z"`` with ``obj`` or ``glb`` is refused (their importers would lay it
on its back).

Every file is written atomically (temporary file in the same folder, then
rename: :func:`genre_backend.atomic.atomic_write_bytes`), and every path is
checked first (:func:`check_output_path`): an input is never overwritten,
nor a device or FIFO.
"""

from __future__ import annotations

import io
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_all, atomic_write_bytes, tmp_prefix

__all__ = [
    "MESH_FORMATS",
    "UP_AXES",
    "Y_UP_TO_Z_UP",
    "resolve_format",
    "resolve_up",
    "MAX_ECHO",
    "OutputError",
    "short",
    "check_output_path",
    "check_outputs",
    "check_folder_fillable",
    "INTERMEDIATE_NAMES",
    "mesh_files",
    "write_mesh",
    "write_png",
    "png_bytes",
]

MESH_FORMATS = ("obj", "ply", "glb")
UP_AXES = ("y", "z")
# View frame (+y up, +z toward the camera) → +z up with the front toward −y (Blender's world):
# (x, y, z) → (x, −z, y).  The same map Blender's OBJ and glTF importers apply to a +y-up file.
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
MAX_ECHO = 300  # characters of a user's path quoted back in a message


class OutputError(ValueError):
    """The mesh (or intermediates) cannot be written where asked; protocol code ``output_unwritable``."""

    code = "output_unwritable"


def short(value: object, limit: int = MAX_ECHO) -> str:
    """``str(value)`` cut to ``limit`` characters (a message never echoes a 10 MB path back)."""
    text = str(value)
    return text if len(text) <= limit else f"{text[:limit]}… ({len(text):,} characters)"


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def check_output_path(path: str | os.PathLike, inputs: Sequence[str | os.PathLike | None] = ()) -> Path:
    """Fail early (``OutputError``) if a file cannot or must not be written at ``path``.

    Refused: a folder, a missing or unwritable folder, a read-only file, an
    existing path that is not a regular file (a device, a FIFO, a socket:
    replacing ``/dev/null`` with a mesh is never what was meant), an
    over-long name, and any of ``inputs`` (the photo, the mask): an input is
    never overwritten.
    """
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    try:
        if path.is_dir():
            raise OutputError(f"{short(path)}: output path is a directory")
        if not parent.is_dir():
            raise OutputError(f"{short(path)}: cannot write here: folder {short(parent)} does not exist")
        if path.exists() and not path.is_file():
            raise OutputError(f"{short(path)}: exists and is not a regular file (a device, FIFO or socket); choose another output")
        for inp in inputs:
            if inp is not None and _same_file(path, Path(inp)):
                raise OutputError(f"{short(path)}: is an input of this job; an input is never overwritten")
        if path.exists() and not os.access(path, os.W_OK):
            raise OutputError(f"{short(path)}: cannot write here: file is read-only")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise OutputError(f"{short(path)}: cannot write here: folder {short(parent)} is not writable")
        os.stat(parent / (tmp_prefix(path) + "x" * 8))  # a name too long for the file system fails here, not after the work
    except FileNotFoundError:
        pass  # (the expected answer of the last line)
    except OSError as exc:
        raise OutputError(f"{short(path)}: cannot write here: {exc.strerror or exc}") from None
    return path


INTERMEDIATE_NAMES = ("input", "mask", "silhouette", "depth", "partial_sph", "full_sph", "vox_sph", "vox_depth",
                      "probability", "mask_in_photo")  # the PNGs ``save_intermediates`` writes (NAME.png)


def check_folder_fillable(folder: str | os.PathLike, names: Sequence[str] = (), inputs: Sequence[str | os.PathLike | None] = (),
                          what: str = "intermediates folder") -> Path:
    """Fail early (``OutputError``) if ``folder`` cannot be made (when missing) and filled with files called ``names``.

    An existing ``folder`` must be a writable folder, and every ``names``
    entry in it must pass :func:`check_output_path`; a missing one needs its
    nearest existing ancestor to be a writable folder (nothing is created here).
    """
    folder = Path(folder)
    try:
        if folder.exists() or folder.is_symlink():
            if not folder.is_dir():
                raise OutputError(f"{short(folder)}: {what} is a file, not a folder")
            if not os.access(folder, os.W_OK | os.X_OK):
                raise OutputError(f"{short(folder)}: {what} is not writable")
            for name in names:
                check_output_path(folder / name, inputs)
            return folder
        for part in folder.parts:  # a component too long for the file system fails here
            if len(os.fsencode(part)) > 255:
                raise OutputError(f"{short(folder)}: cannot create the {what}: File name too long")
        ancestor = folder.parent
        while not (ancestor.exists() or ancestor.is_symlink()) and ancestor != ancestor.parent:
            ancestor = ancestor.parent
        if not ancestor.is_dir():
            raise OutputError(f"{short(folder)}: cannot create the {what}: {short(ancestor)} is not a folder")
        if not os.access(ancestor, os.W_OK | os.X_OK):
            raise OutputError(f"{short(folder)}: cannot create the {what}: folder {short(ancestor)} is not writable")
    except OSError as exc:
        raise OutputError(f"{short(folder)}: {what}: {exc.strerror or exc}") from None
    return folder


def check_outputs(mesh: str | os.PathLike, fmt: str | None = None, textured: bool = False,
                  inputs: Sequence[str | os.PathLike | None] = (), intermediates: str | os.PathLike | None = None,
                  preview: str | os.PathLike | None = None) -> list[Path]:
    """Every output of one job checked before any network runs: the mesh files, the preview, the intermediates folder.

    Returns the mesh files (:func:`mesh_files`); raises ``OutputError`` for the first one that cannot be written.
    """
    files = mesh_files(mesh, fmt, textured)
    for p in files:
        check_output_path(p, inputs)
    if preview is not None:
        if any(Path(preview) == p for p in files):
            raise OutputError(f"{short(preview)}: the preview would overwrite the mesh")
        check_output_path(preview, inputs)
    if intermediates is not None:
        check_folder_fillable(intermediates, [f"{n}.png" for n in INTERMEDIATE_NAMES], inputs)
    return files


def _write(path: Path, data: bytes) -> None:
    """:func:`genre_backend.atomic.atomic_write_bytes`, with an OS error as a one-line :class:`OutputError`."""
    try:
        atomic_write_bytes(path, data)
    except OSError as exc:
        raise OutputError(f"{short(path)}: cannot write here: {exc.strerror or exc}") from None


def png_bytes(array: np.ndarray) -> bytes:
    """(H, W) or (H, W, 3|4) uint8 → PNG file bytes."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG")
    return buf.getvalue()


def write_png(path: str | os.PathLike, array: np.ndarray) -> Path:
    """Write an image (uint8 array) as PNG atomically."""
    path = Path(path)
    _write(path, png_bytes(array))
    return path


def resolve_format(path: str | os.PathLike, fmt: str | None) -> str:
    """The format a mesh is written in: ``fmt``, else the path's extension if it is one of :data:`MESH_FORMATS`, else obj."""
    if fmt is None:
        ext = Path(path).suffix.lower().lstrip(".")
        fmt = ext if ext in MESH_FORMATS else "obj"
    if fmt not in MESH_FORMATS:
        raise ValueError(f"format: expected one of {', '.join(MESH_FORMATS)}, got {fmt!r}")
    return fmt



def resolve_up(fmt: str, up: str | None) -> str:
    """The up axis a file of format ``fmt`` is written with: ``up``, else z for ply and y for obj and glb.

    ``up="z"`` is for ply only (ValueError otherwise): OBJ and glTF files are +y up by their importers' convention.
    """
    if up is None:
        return "z" if fmt == "ply" else "y"
    if up not in UP_AXES:
        raise ValueError(f"up: expected 'y' or 'z', got {short(up, 40)!r}")
    if up == "z" and fmt != "ply":
        raise ValueError(f"up: 'z' is for ply only; {fmt} is always written +y up, as its importers expect")
    return up


def _ply_comment(data: bytes, up: str) -> bytes:
    """Say the axes in the PLY header (a ``comment`` line after ``format``; readers skip comments)."""
    axes = ("+x right, +z up, front toward -y (Blender's axes; the view frame turned +y up -> +z up)" if up == "z"
            else "+x right, +y up, +z toward the camera (the view frame)")
    head, sep, rest = data.partition(b"\n")  # "ply"
    fmt_line, sep2, rest = rest.partition(b"\n")  # "format ..."
    return head + sep + fmt_line + sep2 + f"comment GenRe mesh: {axes}\n".encode("ascii") + rest


def mesh_files(path: str | os.PathLike, fmt: str | None = None, textured: bool = False) -> list[Path]:
    """Every file :func:`write_mesh` writes for ``path``: the mesh first, then an OBJ's material and texture."""
    path = Path(path)
    if resolve_format(path, fmt) == "obj" and textured and path.name:  # (no name, e.g. "/": refused by the checks)
        return [path, path.with_suffix(".mtl"), path.with_name(path.stem + "_texture.png")]
    return [path]


def _obj_text(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray | None, mtl_name: str | None,
              face_uv: np.ndarray | None = None) -> str:
    """An OBJ's text; ``uv`` (N, 2) its ``vt`` lines, ``face_uv`` (F, 3) int the ``vt`` of each face corner
    (default: the vertex's own, ``f a/a``)."""
    lines = ["# GenRe mesh (view frame: +x right, +y up, +z toward the camera)"]
    if mtl_name:
        lines += [f"mtllib {mtl_name}", "usemtl photo"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in np.asarray(vertices, np.float64)]
    f = np.asarray(faces, np.int64) + 1
    if uv is not None:
        t = f if face_uv is None else np.asarray(face_uv, np.int64) + 1
        lines += [f"vt {u:.6f} {v:.6f}" for u, v in np.asarray(uv, np.float64)]
        lines += [f"f {a}/{ta} {b}/{tb} {c}/{tc}" for (a, b, c), (ta, tb, tc) in zip(f, t)]
    else:
        lines += [f"f {a} {b} {c}" for a, b, c in f]
    return "\n".join(lines) + "\n"


def write_mesh(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray, fmt: str | None = None,
               texture=None, inputs: Sequence[str | os.PathLike | None] = (), up: str | None = None,
               ) -> tuple[Path, str, list[Path]]:
    """Write a mesh atomically as obj, ply or glb, coloured from the photo when ``texture`` is given.

    vertices: (V, 3) float in the view frame; faces: (F, 3) int; ``fmt``
    None: from the file's extension, else obj; ``texture``: a
    :class:`~.colour.PhotoTexture` for these vertices, or None; ``inputs``:
    files never to overwrite; ``up``: the file's up axis (:func:`resolve_up`:
    default z for ply, y for obj and glb; see the module's "Axes").  All paths
    are checked before the first write.  Returns (mesh path, format, every
    file written).
    """
    path = Path(path)
    fmt = resolve_format(path, fmt)
    up = resolve_up(fmt, up)
    files = mesh_files(path, fmt, texture is not None)
    for p in files:
        check_output_path(p, inputs)
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if texture is not None and (len(texture.uv) != len(v) or len(texture.face_uv) != len(f)):
        raise ValueError(f"texture: {len(texture.uv)} UVs for {len(v)} vertices, {len(texture.face_uv)} for {len(f)} faces")
    if fmt == "obj":
        # (file names that are not UTF-8 reach Python as lone surrogates: written back as their own bytes)
        if texture is None:
            _write(path, _obj_text(v, f, None, None).encode("utf-8", "surrogateescape"))
        else:
            mtl, png = files[1], files[2]
            uv, _, corner_uv = texture.corners(f)
            data = {  # everything encoded before the first write
                png: png_bytes(texture.image),
                mtl: f"newmtl photo\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nillum 1\nmap_Kd {png.name}\n".encode("utf-8", "surrogateescape"),
                path: _obj_text(v, f, uv, mtl.name, corner_uv).encode("utf-8", "surrogateescape"),
            }
            try:  # one unit: all three written to temporaries, then renamed together (never an .mtl without its .obj)
                atomic_write_all([(target, (lambda fh, payload=payload: fh.write(payload))) for target, payload in data.items()])
            except OSError as exc:
                raise OutputError(f"{short(path)}: cannot write here: {exc.strerror or exc}") from None
        return path, fmt, files
    import trimesh  # (ply and glb only: an OBJ is written without importing trimesh)

    if up == "z":  # (ply only)
        v = v @ Y_UP_TO_Z_UP.T
    if texture is not None and fmt == "glb":  # one UV per vertex: a vertex with two (photo and smooth) is split
        uv, vertex, f = texture.corners(f)
        v = v[vertex]
    mesh = trimesh.Trimesh(vertices=v, faces=f, process=False)
    if texture is not None and fmt == "ply":
        mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=texture.vertex_colours())
    elif texture is not None:  # glb
        from PIL import Image

        material = trimesh.visual.material.PBRMaterial(
            name="photo", baseColorTexture=Image.fromarray(texture.image), metallicFactor=0.0, roughnessFactor=1.0,
        )
        mesh.visual = trimesh.visual.TextureVisuals(uv=np.asarray(uv, np.float64), material=material)
    data = mesh.export(file_type=fmt)
    data = data.encode() if isinstance(data, str) else data
    if fmt == "ply":
        data = _ply_comment(data, up)
    _write(path, data)
    return path, fmt, files
