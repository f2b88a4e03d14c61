"""``genre data render`` inside a stock Blender, for machines without the ``bpy`` module::

    blender --background --factory-startup --python training/render/blender_script.py -- \\
        --shapes ~/.cache/genre/corpus/manifest.json --out ~/.cache/genre/views/default --views 20

Everything after ``--`` is ``genre data render``'s arguments, and the files
written are the same (RGB, Z-pass planar depth, mask, camera JSON;
:mod:`training.data.views`).  Tested with Debian's Blender 3.4.1, whose
Python is the system's 3.11, and the ``bpy`` 5.0.1 module.

Blender's Python must import the project and its dependencies (numpy, torch,
Pillow, tqdm).  This script puts the repository first on ``sys.path`` and
then the site-packages of the virtual environment ``$GENRE_VENV`` (default:
the repository's ``.venv``, made by ``scripts/setup.sh``) when its Python
version is Blender's; whatever is still missing is named in one line and the
exit code is 2.  The exit code is otherwise ``genre data render``'s.

The environment's numpy (1.26) is then the one Blender's own add-ons use as
well: Debian's Blender 3.4.1 brings no numpy of its own (it would use the
system's ``python3-numpy``, 1.24, not installed here), and both lack the
``np.bool`` that 3.4's glTF importer calls; :mod:`training.render.scene`
lends it for each import (numpy 2's alias) rather than keeping torch's
numpy off the path.

Importing this module does nothing; Blender runs it as ``__main__``.
"""

from __future__ import annotations

import importlib.util
import os
import site
import sys
from pathlib import Path

__all__ = ["REQUIRED_MODULES", "venv_site_packages", "add_project_paths", "missing_modules", "run"]

REPO = Path(__file__).resolve().parents[2]
# What rendering imports (the project's two packages and the third-party modules they need for it).
REQUIRED_MODULES = ("numpy", "torch", "PIL", "tqdm", "genre_backend", "training")
PROG = "blender_script.py"


def venv_site_packages(venv: str | os.PathLike | None = None) -> tuple[Path | None, str]:
    """The site-packages folder of ``venv`` ($GENRE_VENV, else the repository's .venv) for this Python.

    Returns (folder or None, a note saying what was looked for and found).
    """
    root = Path(venv or os.environ.get("GENRE_VENV") or REPO / ".venv")
    version = f"python{sys.version_info[0]}.{sys.version_info[1]}"
    folder = root / "lib" / version / "site-packages"
    if folder.is_dir():
        return folder, f"using {folder}"
    if not root.is_dir():
        return None, f"no virtual environment at {root} (scripts/setup.sh makes one; GENRE_VENV names another)"
    others = sorted(p.parent.name for p in root.glob("lib/python3*/site-packages"))
    return None, (f"{root} has no {version} site-packages (it has: {', '.join(others) or 'none'}); "
                  f"this Blender's Python is {sys.version.split()[0]}")


def add_project_paths(venv: str | os.PathLike | None = None) -> str:
    """Put the repository, then the virtual environment's site-packages (with its .pth files), first on sys.path.

    Returns the note of :func:`venv_site_packages`.
    """
    folder, note = venv_site_packages(venv)
    before = list(sys.path)
    if folder is not None:
        site.addsitedir(str(folder))  # appends it and what its .pth files name (e.g. an editable install)
    added = [p for p in sys.path if p not in before]
    rest = [p for p in before if p != str(REPO)]
    sys.path[:] = [str(REPO)] + added + rest
    return note


def missing_modules(names=REQUIRED_MODULES) -> list[str]:
    """Those of ``names`` this Python cannot import."""
    missing = []
    for name in names:
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            missing.append(name)
    return missing


def run(argv: list[str]) -> int:
    """Set up the import paths, check the dependencies and run ``genre data render`` with ``argv``."""
    note = add_project_paths()
    missing = missing_modules()
    if missing:
        print(f"{PROG}: error: this Blender's Python {sys.version.split()[0]} ({sys.executable}) cannot import "
              f"{', '.join(missing)}; {note}", file=sys.stderr, flush=True)
        return 2
    from training.render.cli import main  # noqa: PLC0415

    return main(argv, prog=PROG)


def _remove_blender_tempdir() -> None:
    """Delete this Blender session's temporary folder (its own shutdown would have)."""
    import shutil  # noqa: PLC0415

    bpy = sys.modules.get("bpy")
    tempdir = getattr(getattr(bpy, "app", None), "tempdir", "") if bpy else ""
    if tempdir and Path(tempdir).name.startswith("blender_"):
        shutil.rmtree(tempdir, ignore_errors=True)


def _arguments_after_separator(argv: list[str]) -> list[str]:
    return argv[argv.index("--") + 1:] if "--" in argv else []


if __name__ == "__main__":
    try:
        code = run(_arguments_after_separator(sys.argv))
    except SystemExit as exc:  # argparse's --help and usage errors
        code = exc.code if isinstance(exc.code, int) else 2
    except KeyboardInterrupt:
        code = 130
    except BaseException as exc:  # noqa: BLE001  (Blender would print it and still exit 0)
        import traceback  # noqa: PLC0415

        traceback.print_exc()
        print(f"{PROG}: error: {type(exc).__name__}: {exc}", file=sys.stderr)
        code = 1
    # Leave without Blender's shutdown: it unregisters "add-ons" by probing every module in sys.modules,
    # which torch's lazy namespaces answer (3.4.1 prints tracebacks, and has been seen to crash there).
    _remove_blender_tempdir()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
