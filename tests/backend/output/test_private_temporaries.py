"""No temporary file or folder at a name another user can guess and plant a link at (issue 43, part 2).

``genre reconstruct --preview`` rendered through ``/tmp/genre_mesh_render_<pid>.png``:
a symbolic link planted there beforehand made Blender overwrite the file it
pointed at.  Every temporary now lies in a fresh :func:`tempfile.mkdtemp`
folder.  These tests plant links at the old fixed names (and at the other
predictable names the project used under the temp folder) pointing at a
victim file, render a preview, and check that the victim is untouched.
"""

from __future__ import annotations

import os
import stat
import tempfile
from pathlib import Path

import numpy as np
import pytest
import trimesh

from genre_backend.output import blender

REPO = Path(__file__).resolve().parents[3]
VICTIM_TEXT = b"the user's precious file\n"


def _predictable_names(folder: Path, generic: bool = True) -> list[Path]:
    """Names under a temp folder that the project wrote (the first three), or could be guessed to write, for this
    process; ``generic``: also names without the process id (planted only in the stand-in temp folder)."""
    pid = os.getpid()
    names = [f"genre_mesh_render_{pid}.png", f"genre_textured_{pid}.png", f"genre_textured_{pid}.tex.png",
             f"genre_textured_{pid}", f"genre_mesh_render_{pid}"]
    if generic:
        names += ["genre_mesh_render.png", "genre_textured.png", "render.png", "texture.png", "preview.png"]
    return [folder / n for n in names]


@pytest.fixture
def planted(tmp_path, monkeypatch):
    """(victim, shared): links to a victim file planted at every predictable name of this process in the real
    temp folder, and at those and more in a world-writable stand-in that the code under test then takes for the
    temp folder."""
    blender.import_bpy()  # (its cache folder is made once per process, in the real temp folder)
    victim = tmp_path / "victim.txt"
    victim.write_bytes(VICTIM_TEXT)
    shared = tmp_path / "shared-tmp"
    shared.mkdir()
    shared.chmod(0o1777)
    links = []
    for name in _predictable_names(Path(tempfile.gettempdir()), generic=False) + _predictable_names(shared):
        if not os.path.lexists(name):
            name.symlink_to(victim)
            links.append(name)
    monkeypatch.setattr(tempfile, "tempdir", str(shared))
    yield victim, shared
    for link in links:
        if link.is_symlink():
            link.unlink()


def _untouched(victim: Path, shared: Path) -> None:
    assert victim.read_bytes() == VICTIM_TEXT and not victim.is_symlink()
    for name in _predictable_names(shared):
        assert name.is_symlink(), f"{name} was replaced"
    left = sorted(p.name for p in shared.iterdir() if not p.is_symlink())
    assert left == [], f"temporaries left behind: {left}"


def test_preview_render_does_not_follow_a_planted_link(planted):
    victim, shared = planted
    box = trimesh.creation.box(extents=[0.4] * 3)
    front, side = blender.render_meshes([(box.vertices, box.faces)], size=16, samples=1)[0]
    assert front.shape == side.shape == (16, 16, 3) and (front < 250).any()  # it did render
    _untouched(victim, shared)


def test_textured_render_does_not_follow_a_planted_link(planted):
    victim, shared = planted
    box = trimesh.creation.box(extents=[0.4] * 3)
    uv = np.random.default_rng(0).random((len(box.vertices), 2))
    texture = np.full((8, 8, 3), 128, np.uint8)
    rgb, covered = blender.render_textured(box.vertices, box.faces, uv, texture, 16)
    assert rgb.shape == (16, 16, 3) and covered.any()
    _untouched(victim, shared)


def test_scratch_folders_are_private_and_removed(tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    with blender.private_scratch("genre-x-") as a, blender.private_scratch("genre-x-") as b:
        assert a != b and a.parent == tmp_path
        assert stat.S_IMODE(a.stat().st_mode) == 0o700 and not a.is_symlink()
        (a / "render.png").write_bytes(b"x")
    assert not a.exists() and not b.exists()


def _victim_dir(tmp_path: Path) -> Path:
    d = tmp_path / "victim-dir"
    d.mkdir()
    return d


def test_the_blender_cache_folder_is_not_a_planted_link(tmp_path, monkeypatch):
    shared = tmp_path / "shared-tmp"
    shared.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(shared))
    monkeypatch.delenv("GENRE_BLENDER_CACHE", raising=False)
    monkeypatch.setenv("BLENDER_USER_RESOURCES", "unchanged")  # (setdefault: this process's bpy keeps its own)
    monkeypatch.setenv("XDG_CACHE_HOME", "unchanged")
    victim = _victim_dir(tmp_path)
    fixed = shared / f"genre-blender-{os.getuid()}"
    fixed.symlink_to(victim)
    root = blender.prepare_blender_environment()
    assert root != fixed and root.parent == shared and not root.is_symlink()
    assert stat.S_IMODE(root.stat().st_mode) == 0o700
    assert list(victim.iterdir()) == [] and fixed.is_symlink()
    # the fixed name, free, is made private; an own folder left open to others is closed
    fixed.unlink()
    assert blender.own_private_folder(fixed) == fixed and stat.S_IMODE(fixed.stat().st_mode) == 0o700
    fixed.chmod(0o777)
    assert blender.own_private_folder(fixed) == fixed and stat.S_IMODE(fixed.stat().st_mode) == 0o700
    (shared / "a-file").write_text("x")
    assert blender.own_private_folder(shared / "a-file") is None


def _addon_backend():
    from support.addon import load_addon_module

    return load_addon_module("backend")


def test_the_addons_job_folder_is_not_a_planted_link(tmp_path, monkeypatch):
    backend = _addon_backend()
    shared = tmp_path / "shared-tmp"
    shared.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(shared))
    victim = _victim_dir(tmp_path)
    name = f"genre-addon-jobs-{os.getuid()}"
    (shared / name).symlink_to(victim)
    root = Path(backend.private_temp_root(name))
    assert root != shared / name and root.parent == shared and stat.S_IMODE(root.stat().st_mode) == 0o700
    assert list(victim.iterdir()) == []
    (shared / name).unlink()
    assert Path(backend.private_temp_root(name)) == shared / name
    assert stat.S_IMODE((shared / name).stat().st_mode) == 0o700


def test_no_fixed_temporary_names_are_left_in_the_sources():
    """Grep the packages and the add-on: a name in the shared temp folder is built only by the two functions
    that check what they find there (own_private_folder's caller, private_temp_root); every other temporary
    goes through mkstemp / mkdtemp / TemporaryDirectory."""
    import re

    allowed = {("genre_backend/output/blender.py", "prepare_blender_environment"),
               ("blender_addon/backend.py", "private_temp_root")}
    pattern = re.compile(r"gettempdir\(|[\"']/tmp\b|/var/tmp")
    found = set()
    for folder in ("genre_backend", "training", "blender_addon"):
        for path in sorted((REPO / folder).rglob("*.py")):
            function = ""
            for line in path.read_text(encoding="utf-8").splitlines():
                m = re.match(r"def (\w+)", line)
                if m:
                    function = m.group(1)
                if pattern.search(line):
                    found.add((path.relative_to(REPO).as_posix(), function))
    assert found == allowed
