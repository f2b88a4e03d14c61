#!/usr/bin/env python3
"""Package the Blender add-on: ``python build_addon.py`` writes ``dist/``.

* ``dist/genre-<version>.zip`` -- the Blender 4.2+ extension, built and then
  validated with Blender's own extension tool (``blender_ext.py``, shipped in
  the ``bpy`` wheel; it runs under plain Python).
* ``dist/genre-<version>-legacy.zip`` -- the same code as a legacy add-on for
  Blender 3.4-4.1 (Edit > Preferences > Add-ons > Install), in a ``genre/``
  folder, without the manifest.

Both carry ``backend/``: the backend as a pure-Python wheel built here from
``genre_backend/`` alone (no ``training``), with the shipped ``default``
weights inside it, and the mask net's hash-pinned requirement
(``scripts/model-requirements.txt``).  The add-on's Install Backend button
pip-installs them with the runtime dependencies (docs/install.md), so the
zip needs nothing else from this repository.

The version comes from ``blender_addon/blender_manifest.toml``;
``bl_info["version"]`` in ``blender_addon/__init__.py`` must repeat it.
"""

from __future__ import annotations

import argparse
import ast
import base64
import hashlib
import io
import json
import os
import shutil
import subprocess
import sys
import tempfile
import tomllib
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent
SOURCE = ROOT / "blender_addon"
EXCLUDE_DIRS = {"__pycache__"}
EXCLUDE_SUFFIXES = {".pyc", ".pyo", ".zip"}
BACKEND = ROOT / "genre_backend"
# the weights files the wheel carries (genre_backend/weights/): the product model and its card; `protocol` stays behind
SHIPPED_WEIGHTS = ("default.safetensors", "default.json", "MODEL_CARD.md", "TRAINING_SHAPES_DEFAULT.md")
BUNDLE = "backend"  # the add-on's folder with the wheel and the mask net's requirement
MODEL_REQUIREMENTS = ROOT / "scripts" / "model-requirements.txt"
SCHEMA = SOURCE / "options_schema.json"  # the Advanced rows before the backend has started (blender_addon/schema.py)
# genre serve's messages, dependency-free: the add-on keeps an exact copy (the build refuses a stale one)
PROTOCOL, PROTOCOL_COPY = ROOT / "genre_backend" / "protocol.py", SOURCE / "protocol.py"
ZIP_TIME = (1980, 1, 1, 0, 0, 0)  # every file's time in the wheel: the same tree gives the same bytes


class BuildError(RuntimeError):
    pass


def manifest() -> dict:
    with open(SOURCE / "blender_manifest.toml", "rb") as fh:
        return tomllib.load(fh)


def bl_info(path: Path = SOURCE / "__init__.py") -> dict:
    """``bl_info`` read the way Blender reads it (a literal, without running the module)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "bl_info" for t in node.targets):
            return ast.literal_eval(node.value)
    raise BuildError(f"{path}: no bl_info")


def version() -> str:
    """The add-on's version (from the manifest), after checking that ``bl_info`` agrees."""
    v = manifest()["version"]
    legacy = ".".join(str(n) for n in bl_info()["version"])
    if v != legacy:
        raise BuildError(f"version mismatch: blender_manifest.toml says {v}, bl_info in __init__.py says {legacy}")
    return v


def find_extension_tool() -> Path:
    """``blender_ext.py`` from the installed ``bpy`` wheel (found without importing bpy)."""
    import importlib.util

    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        raise BuildError("the bpy module is not installed in this Python; run the build with the project's .venv/bin/python")
    for base in spec.submodule_search_locations:
        for tool in sorted(Path(base).glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py")):
            return tool
    raise BuildError("blender_ext.py not found in the bpy package")


def _run_tool(tool: Path, *args: str) -> str:
    proc = subprocess.run([sys.executable, str(tool), *args], capture_output=True, text=True)
    out = (proc.stdout + proc.stderr).strip()
    if proc.returncode != 0:
        raise BuildError(f"blender_ext.py {args[0]} failed (exit {proc.returncode}):\n{out}")
    return out


def _source_files():
    for dirpath, dirnames, filenames in os.walk(SOURCE):
        dirnames[:] = sorted(d for d in dirnames if d not in EXCLUDE_DIRS and not d.startswith("."))
        for name in sorted(filenames):
            if Path(name).suffix in EXCLUDE_SUFFIXES or name.startswith("."):
                continue
            path = Path(dirpath) / name
            yield path, path.relative_to(SOURCE)


def backend_version() -> str:
    """``genre_backend.__version__``, read without importing the package."""
    tree = ast.parse((BACKEND / "__init__.py").read_text(encoding="utf-8"))
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__version__" for t in node.targets):
            return ast.literal_eval(node.value)
    raise BuildError("genre_backend/__init__.py: no __version__")


def _backend_files():
    """(path, name in the wheel) of the backend: its Python modules and the shipped weights, sorted."""
    for path in sorted(BACKEND.rglob("*")):
        rel = path.relative_to(ROOT)
        if path.is_dir() or "__pycache__" in rel.parts:
            continue
        if rel.parts[1] == "weights" and len(rel.parts) == 3:
            if path.name in SHIPPED_WEIGHTS:
                yield path, rel.as_posix()
        elif path.suffix == ".py":
            yield path, rel.as_posix()
    for path in [ROOT / "NOTICE", *sorted((ROOT / "licenses").glob("*"))]:
        yield path, None  # (licence files: into the .dist-info folder)


def _wheel_metadata(ver: str) -> dict[str, bytes]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    lines = ["Metadata-Version: 2.1", "Name: genre", f"Version: {ver}", f"Summary: {project['description']}",
             f"License: {project['license']['text']}", f"Requires-Python: {project['requires-python']}"]
    lines += [f"Requires-Dist: {req}" for req in project["dependencies"]]
    scripts = "".join(f"{name} = {target}\n" for name, target in project["scripts"].items())
    return {
        "METADATA": ("\n".join(lines) + "\n").encode(),
        "WHEEL": b"Wheel-Version: 1.0\nGenerator: genre build_addon.py\nRoot-Is-Purelib: true\nTag: py3-none-any\n",
        "entry_points.txt": f"[console_scripts]\n{scripts}".encode(),
    }


def build_wheel(out_dir: Path) -> Path:
    """``genre-<version>-py3-none-any.whl``: ``genre_backend`` with the shipped default weights and the runtime's
    requirements (pyproject's plain dependencies), the same bytes for the same tree."""
    ver = backend_version()
    info = f"genre-{ver}.dist-info"
    entries = [(name or f"{info}/licenses/{path.name}", path.read_bytes()) for path, name in _backend_files()]
    entries += [(f"{info}/{name}", data) for name, data in _wheel_metadata(ver).items()]
    record = "".join(f"{name},sha256={base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b'=').decode()},{len(data)}\n"
                     for name, data in entries) + f"{info}/RECORD,,\n"
    entries.append((f"{info}/RECORD", record.encode()))
    target = out_dir / f"genre-{ver}-py3-none-any.whl"
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in entries:
            entry = zipfile.ZipInfo(name, ZIP_TIME)
            entry.external_attr = 0o644 << 16
            entry.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(entry, data)
    target.write_bytes(buffer.getvalue())
    return target


def stage(dest: Path, manifest: bool = True) -> Path:
    """The add-on as it ships, in ``dest``: its sources (``manifest``: with ``blender_manifest.toml``) and
    ``backend/`` (the wheel and the mask net's requirement)."""
    for path, rel in _source_files():
        if rel.name == "blender_manifest.toml" and not manifest:
            continue  # a manifest would make Blender 4.2+ treat the zip as an extension
        (dest / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(path, dest / rel)
    (dest / BUNDLE).mkdir(parents=True, exist_ok=True)
    build_wheel(dest / BUNDLE)
    shutil.copy2(MODEL_REQUIREMENTS, dest / BUNDLE / MODEL_REQUIREMENTS.name)
    return dest


def build_extension(out_dir: Path, tool: Path, ver: str) -> Path:
    """Build with ``blender_ext.py build`` from a clean copy of the sources, then ``validate`` the zip."""
    with tempfile.TemporaryDirectory(prefix="genre-addon-") as tmp:
        src = stage(Path(tmp) / "genre")
        target = out_dir / f"genre-{ver}.zip"
        target.unlink(missing_ok=True)
        _run_tool(tool, "build", "--source-dir", str(src), "--output-dir", str(out_dir))
    if not target.is_file():
        raise BuildError(f"blender_ext.py build did not write {target}")
    _run_tool(tool, "validate", str(target))
    return target


def build_legacy(out_dir: Path, ver: str) -> Path:
    """A zip with one ``genre/`` folder, as Blender 3.x's add-on installer expects."""
    target = out_dir / f"genre-{ver}-legacy.zip"
    tmp = target.with_suffix(".zip.tmp")
    with tempfile.TemporaryDirectory(prefix="genre-addon-") as folder, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as zf:
        src = stage(Path(folder) / "genre", manifest=False)
        for path in sorted(src.rglob("*")):
            if path.is_file():
                zf.write(path, f"genre/{path.relative_to(src).as_posix()}")
    os.replace(tmp, target)
    return target


def options_schema() -> str:
    """The mesh options' schema ``genre serve --weights default`` publishes (its ``ready`` event's ``options`` and
    ``qualities``), as the add-on keeps it in ``options_schema.json``."""
    from safetensors import safe_open

    from genre_backend.inference.options import schema
    from genre_backend.weights_file import named_weights, stored_config

    path = named_weights("default")
    with safe_open(str(path), "np") as fh:
        meta = fh.metadata() or {}
    return json.dumps(schema(stored_config(path, meta).geometry), indent=1) + "\n"


def check_schema() -> None:
    if not SCHEMA.is_file() or SCHEMA.read_text(encoding="utf-8") != options_schema():
        raise BuildError(f"{SCHEMA.relative_to(ROOT)} is not the backend's schema: run python build_addon.py --schema")
    if not PROTOCOL_COPY.is_file() or PROTOCOL_COPY.read_bytes() != PROTOCOL.read_bytes():
        raise BuildError(f"{PROTOCOL_COPY.relative_to(ROOT)} is not {PROTOCOL.relative_to(ROOT)}: run python build_addon.py --schema")


def build(out_dir: Path = ROOT / "dist") -> dict[str, Path]:
    ver = version()
    check_schema()
    out_dir.mkdir(parents=True, exist_ok=True)
    tool = find_extension_tool()
    return {"extension": build_extension(out_dir, tool, ver), "legacy": build_legacy(out_dir, ver)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(ROOT / "dist"), help="output folder (default: dist/)")
    parser.add_argument("--schema", action="store_true",
                        help=f"write {SCHEMA.relative_to(ROOT)} and {PROTOCOL_COPY.relative_to(ROOT)} from the backend, then build")
    args = parser.parse_args(argv)
    if args.schema:
        SCHEMA.write_text(options_schema(), encoding="utf-8")
        shutil.copy2(PROTOCOL, PROTOCOL_COPY)
    try:
        built = build(Path(args.out))
    except BuildError as exc:
        print(f"build_addon: {exc}", file=sys.stderr)
        return 1
    for kind, path in built.items():
        print(f"{kind}: {path} ({path.stat().st_size:,} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
