"""The package layering: every module imports, the backend never imports training, stages stay in order.

Layers (a module may import only its own layer and those before it):
  genre_backend: config, validation, atomic, weights_file, process → frame → geometry → nets → photo (the photo going in)
    → output (what is written) → inference (the pipeline) → frontends (genre reconstruct, genre serve) → cli
  training: data → render → learn → eval → chain (any of them may import the backend)
The add-on (blender_addon) imports neither package: it talks to the backend over a pipe.
"""

from __future__ import annotations

import ast
import importlib
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

BACKEND_LAYERS = {
    "genre_backend.config": 0, "genre_backend.validation": 0, "genre_backend.atomic": 0, "genre_backend.weights_file": 0,
    "genre_backend.process": 0, "genre_backend.protocol": 0, "genre_backend.arguments": 0,
    "genre_backend.frame": 1, "genre_backend.geometry": 2, "genre_backend.nets": 3,
    "genre_backend.photo": 4, "genre_backend.output": 5, "genre_backend.inference": 6, "genre_backend.frontends": 7,
    "genre_backend.cli": 8,
}
TRAINING_LAYERS = {"training.data": 0, "training.render": 1, "training.learn": 2, "training.eval": 3, "training.chain": 4}


def _modules(package: str) -> list[str]:
    pkg = importlib.import_module(package)
    return [package] + [m.name for m in pkgutil.walk_packages(pkg.__path__, package + ".")]


def _source(module: str) -> Path:
    rel = Path(*module.split("."))
    return REPO / (f"{rel}/__init__.py" if (REPO / rel).is_dir() else f"{rel}.py")


def _imports(module: str) -> set[str]:
    """Absolute names of every project module imported anywhere in ``module`` (also inside functions)."""
    path = _source(module)
    tree = ast.parse(path.read_text(), str(path))
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            out.add(target)
            out.update(f"{target}.{a.name}" for a in node.names)  # `from pkg import module`
    return {m for m in out if m.split(".")[0] in ("genre_backend", "training", "blender_addon")}


def _layer(module: str, layers: dict[str, int]) -> int | None:
    for prefix, rank in sorted(layers.items(), key=lambda kv: -len(kv[0])):
        if module == prefix or module.startswith(prefix + "."):
            return rank
    return None


@pytest.mark.parametrize("package", ["genre_backend", "training"])
def test_every_module_imports_in_a_fresh_interpreter(package):
    code = (
        "import importlib, pkgutil, sys\n"
        f"pkg = importlib.import_module({package!r})\n"
        "names = [m.name for m in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + '.')]\n"
        "for n in names: importlib.import_module(n)\n"
        "print(len(names))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert int(proc.stdout.strip()) >= 10


def test_backend_never_imports_training():
    offenders = {m: sorted(i for i in _imports(m) if i.startswith("training")) for m in _modules("genre_backend")}
    offenders = {m: v for m, v in offenders.items() if v}
    assert offenders == {}


def test_the_benchmarks_stand_apart_and_genre_bench_finds_them():
    """benchmarks/ times the backend from outside: no backend module imports it, and `genre bench` reaches it through
    the entry point (pyproject.toml) in a fresh interpreter, every module of it importable."""
    offenders = sorted(m for m in _modules("genre_backend") if any(i.split(".")[0] == "benchmarks" for i in _imports_any(m)))
    assert offenders == []
    code = ("import contextlib, importlib, io, pkgutil, benchmarks\n"
            "for m in pkgutil.walk_packages(benchmarks.__path__, 'benchmarks.'): importlib.import_module(m.name)\n"
            "from genre_backend.cli import main\n"
            "out = io.StringIO()\n"
            "with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):\n"
            "    main(['bench', '--help'])\n"
            "print(out.getvalue())\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "usage: genre bench" in proc.stdout and "{geometry,inference,layers,reconstruct" in proc.stdout, proc.stdout


def _imports_any(module: str) -> set[str]:
    """Every absolute module name ``module`` imports (project or not)."""
    tree = ast.parse(_source(module).read_text())
    names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    return names | {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and not n.level}


def _upward_imports(package: str, layers: dict[str, int]) -> list[str]:
    wrong = []
    for m in _modules(package):
        rank = _layer(m, layers)
        for imp in _imports(m):
            target = _layer(imp, layers)
            if rank is not None and target is not None and target > rank:
                wrong.append(f"{m} imports {imp}")
    return wrong


@pytest.mark.parametrize("package, layers", [("genre_backend", BACKEND_LAYERS), ("training", TRAINING_LAYERS)])
def test_layers_point_downwards(package, layers):
    assert _upward_imports(package, layers) == []


def test_addon_imports_neither_package():
    for path in (REPO / "blender_addon").glob("*.py"):
        tree = ast.parse(path.read_text())
        names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        names |= {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and not n.level}
        assert not {x.split(".")[0] for x in names} & {"genre_backend", "training"}, path


def test_the_view_file_names_are_spelled_in_one_module():
    hits = []
    for root in ("genre_backend", "training"):
        for path in (REPO / root).rglob("*.py"):
            if "view_{" in path.read_text():
                hits.append(str(path.relative_to(REPO)))
    assert hits == ["training/data/views.py"]


def test_the_shared_flags_are_defined_once():
    """``--weights``, ``--out``, ``--device``, ``--threads``, ``--seed`` and ``--jobs`` come from
    ``genre_backend.arguments`` in every parser of the backend, the training side and the scripts."""
    shared = {"--weights", "--out", "--device", "--threads", "--seed", "--jobs"}
    hand_written, parsers = [], 0
    for root in ("genre_backend", "training", "scripts"):
        for path in (REPO / root).rglob("*.py"):
            if path.name == "arguments.py":
                continue
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "add_argument":
                    parsers += 1
                    flags = {a.value for a in node.args if isinstance(a, ast.Constant)}
                    if flags & shared:
                        hand_written.append(f"{path.relative_to(REPO)}:{node.lineno} {sorted(flags & shared)}")
    assert parsers > 100  # the walk sees the parsers
    assert hand_written == []


def test_cli_lists_the_training_commands_without_importing_them():
    code = (
        "import sys\n"
        "from genre_backend.cli import commands\n"
        "names = list(commands())\n"
        "heavy = [m for m in ('torch', 'bpy', 'training.data.cli', 'training.learn.train', 'training.eval.cli', 'training.chain') if m in sys.modules]\n"
        "print(names, heavy)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "['bench', 'data', 'train', 'eval', 'chain', 'reconstruct', 'serve'] []"


# Modules `genre reconstruct` of a photo has no use for (matplotlib: the --preview sheet and the intermediates'
# PNGs; trimesh: PLY/GLB files and fitted shapes; training: the data/train/eval commands; …): none may be imported
# by the command's start or by a whole run; each costs a cold start up to seconds (docs/lab/benchmarks.md).
NOT_FOR_RECONSTRUCT = ("matplotlib", "training", "bpy", "trimesh", "networkx", "scipy.optimize", "shapely", "manifold3d",
                       "igl", "tensorboard")


def _imported(code: str) -> list[str]:
    """The modules of NOT_FOR_RECONSTRUCT that a fresh interpreter running ``code`` has imported at its end."""
    code += f"\nimport sys\nprint([m for m in {NOT_FOR_RECONSTRUCT!r} if m in sys.modules])\n"
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return ast.literal_eval(proc.stdout.strip().splitlines()[-1])


def test_reconstruct_starts_without_the_modules_it_does_not_use():
    """What `genre reconstruct` imports before any work: the cli, its dispatch of the command (which finds the
    backend's commands without looking up the registered ones: no training package), the command,
    the pipeline (torch)."""
    code = ("import contextlib, io\n"
            "from genre_backend.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):\n"
            "    main(['reconstruct', '--help'])\n"
            "import genre_backend.frontends.reconstruct_cli, genre_backend.inference.reconstruct\n"
            "import genre_backend.output.mesh_export, genre_backend.geometry.cleanup, genre_backend.geometry.primitives\n")
    assert _imported(code) == []


@pytest.mark.slow
def test_a_reconstruct_run_imports_none_of_the_modules_it_does_not_use(tmp_path):
    """A whole `genre reconstruct` of the example photo with the shipped weights and their options (the salient net's mask,
    mirror averaging, cleanup), run by the command's own entry point in a fresh interpreter."""
    out = tmp_path / "sofa.obj"
    code = ("from genre_backend.cli import main\n"
            f"assert main(['reconstruct', 'examples/sofa.png', '-o', {str(out)!r}, '--weights', 'default']) == 0\n")
    assert _imported(code) == []
    assert out.stat().st_size > 0


def test_addon_stage_labels_cover_the_backend_stages():
    from support.addon import load_addon_module

    backend = load_addon_module("backend")  # the add-on's process manager, loaded without bpy
    from genre_backend.inference.reconstruct import STAGES

    STAGE_LABELS = backend.STAGE_LABELS

    missing = [s for s in STAGES if s not in STAGE_LABELS]
    assert missing == []
    assert all(isinstance(v, str) and v for v in STAGE_LABELS.values())


def test_addon_keeps_no_copy_of_the_backends_options():
    """The add-on's option rows come from the backend's schema (`ready`): it declares no property of its own for a mesh
    option, so no default or range of the weights can go stale in it."""
    from genre_backend.inference.options import OPTIONS

    tree = ast.parse((REPO / "blender_addon" / "props.py").read_text())
    declared = {node.target.id for node in ast.walk(tree) if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)}
    assert "options" in declared and "quality" in declared
    assert declared & {o.name for o in OPTIONS} == set()
    assert declared & {"use_" + o.name for o in OPTIONS} == set()


def test_the_addons_protocol_is_the_backends():
    """blender_addon/protocol.py is an exact copy of genre_backend/protocol.py (python build_addon.py --schema)."""
    copy, source = REPO / "blender_addon" / "protocol.py", REPO / "genre_backend" / "protocol.py"
    assert copy.read_bytes() == source.read_bytes(), "blender_addon/protocol.py is stale: python build_addon.py --schema"
