#!/usr/bin/env python3
"""Package the Blender add-on: ``python build_addon.py`` writes ``dist/``.

* ``dist/genre-<version>.zip`` -- the Blender 4.2+ extension, built and then
  validated with Blender's own extension tool (``blender_ext.py``, shipped in
  the ``bpy`` wheel; it runs under plain Python).
* ``dist/genre-<version>-legacy.zip`` -- the same code as a legacy add-on for
  Blender 3.4-4.1 (Edit > Preferences > Add-ons > Install), in a ``genre/``
  folder, without the manifest.

The version comes from ``blender_addon/blender_manifest.toml``;
``bl_info["version"]`` in ``blender_addon/__init__.py`` must repeat it.
"""

from __future__ import annotations

import argparse
import ast
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


def build_extension(out_dir: Path, tool: Path, ver: str) -> Path:
    """Build with ``blender_ext.py build`` from a clean copy of the sources, then ``validate`` the zip."""
    with tempfile.TemporaryDirectory(prefix="genre-addon-") as tmp:
        src = Path(tmp) / "genre"
        for path, rel in _source_files():
            (src / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, src / rel)
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
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as zf:
        for path, rel in _source_files():
            if rel.name == "blender_manifest.toml":
                continue  # a manifest would make Blender 4.2+ treat the zip as an extension
            zf.write(path, f"genre/{rel.as_posix()}")
    os.replace(tmp, target)
    return target


def build(out_dir: Path = ROOT / "dist") -> dict[str, Path]:
    ver = version()
    out_dir.mkdir(parents=True, exist_ok=True)
    tool = find_extension_tool()
    return {"extension": build_extension(out_dir, tool, ver), "legacy": build_legacy(out_dir, ver)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(ROOT / "dist"), help="output folder (default: dist/)")
    args = parser.parse_args(argv)
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
