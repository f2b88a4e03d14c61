"""The measuring end of ``genre bench reconstruct``: run in a fresh process inside the checkout being timed.

``genre bench reconstruct`` starts this file (``runpy`` with the timed checkout first on ``sys.path``) so that
the same probe can time this checkout and an older one side by side; it therefore uses only the API that
``genre reconstruct`` itself uses (``genre_backend.cli.main`` and, where the checkout has it, the end of its
process, ``process.exit_process``; ``Reconstructor(weights).run(image, hooks=Hooks(progress))``, ``Reconstruction.save_mesh``).  Two modes:

``warm IMAGE WEIGHTS``
    one process: load the weights, run the image once to warm up and print a summary line, then one timed
    run per ``run`` line on stdin (one JSON line each), with the weights' own options (the defaults of
    ``genre reconstruct``); each stage is timed from the ``progress`` call that starts it to the next one
    (the last, ``mesh``, ends when ``run`` returns), and ``write`` is ``save_mesh`` of an OBJ.

``cold IMAGE OUT WEIGHTS``
    the real ``genre reconstruct IMAGE -o OUT --weights WEIGHTS`` (``python -m genre_backend.cli``) in this
    fresh process, with wall-clock stamps taken around its parts: the imports
    (from the first import of torch to the end of ``genre_backend.inference.reconstruct``'s), the weights' loading, each
    stage's start and the mesh's write.  The stamps come from wrapping the ``Reconstructor`` class as its
    module is first imported, so the command itself runs unchanged.  Also reports which heavy modules the
    process had imported when it finished.
"""

from __future__ import annotations

import json
import sys
import time

T_START = time.time()

# the modules a reader of the cold figures asks about: imported by ``genre reconstruct`` of a photo or not
WATCHED = ("torch", "numpy", "PIL", "cv2", "scipy", "skimage", "trimesh", "networkx", "matplotlib", "training", "bpy",
           "tqdm", "igl", "shapely", "manifold3d")


def _watched_modules() -> list[str]:
    return [m for m in WATCHED if m in sys.modules]


def warm(image: str, weights: str) -> None:
    """Load the weights, run the image once (warm-up), print ``ready``; then one timed run per ``run`` line read
    from stdin, each printed as one JSON line, until ``quit`` (so that the parent can take turns between
    checkouts run by run)."""
    import tempfile
    from pathlib import Path

    t0 = time.perf_counter()
    from genre_backend.inference import reconstruct

    try:
        from genre_backend.weights_file import resolve_weights
    except ImportError:  # a checkout from before genre_backend.io was split (an --against one)
        from genre_backend.io import resolve_weights

    t1 = time.perf_counter()
    rec = reconstruct.Reconstructor(resolve_weights(weights))
    t2 = time.perf_counter()
    import torch

    def one(out: Path) -> tuple[dict, object]:
        marks: list[tuple[str, float]] = []
        start = time.perf_counter()
        result = rec.run(image, **_progress(reconstruct, lambda stage, fraction: marks.append((stage, time.perf_counter()))))
        end = time.perf_counter()
        result.save_mesh(out)
        written = time.perf_counter()
        stages = {name: (marks[k + 1][1] if k + 1 < len(marks) else end) - at for k, (name, at) in enumerate(marks)}
        stages["write"] = written - end
        stages["total"] = written - start
        return stages, result

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "mesh.obj"
        _, result = one(out)  # the first run warms up caches and the allocator
        opts = getattr(result, "options", result)  # (a checkout older than the options record: the result's own fields)
        print(json.dumps({
            "mode": "warm", "threads": torch.get_num_threads(), "import_s": t1 - t0, "weights_s": t2 - t1,
            "vertices": int(len(result.vertices)), "faces": int(len(result.faces)), "mask_source": result.mask_source,
            "test_time_mirror": bool(getattr(opts, "test_time_mirror", False)), "threshold": float(opts.threshold),
        }), flush=True)
        for line in sys.stdin:
            if line.strip() != "run":
                break
            stages, _ = one(out)
            print(json.dumps(stages), flush=True)


class _StampImport:
    """A ``sys.meta_path`` finder that stamps the import of ``genre_backend.inference.reconstruct`` and wraps
    its ``Reconstructor`` (weights loading, each stage, the mesh's write) once the module has run."""

    NAME = "genre_backend.inference.reconstruct"

    def __init__(self, stamps: list):
        self.stamps = stamps
        self.torch = False

    def find_spec(self, name, path, target=None):
        if name == "torch" and not self.torch:  # the imports' part starts with torch's, wherever the command asks for it
            self.torch = True
            self.stamps.append(("import reconstruct", time.time()))
        if name != self.NAME:
            return None
        import importlib.util

        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        run_module = spec.loader.exec_module
        stamps = self.stamps

        def exec_module(module):
            if not self.torch:
                stamps.append(("import reconstruct", time.time()))
            run_module(module)
            stamps.append(("cli", time.time()))
            _wrap(module.Reconstructor, getattr(module, "Hooks", None), stamps)

        spec.loader.exec_module = exec_module
        return spec


def _progress(module, progress) -> dict:
    """``run``'s keyword for a progress callback: ``hooks=Hooks(progress)``, or ``progress=`` in a checkout from before
    the hooks were one value (an --against one)."""
    hooks_type = getattr(module, "Hooks", None)
    return {"progress": progress} if hooks_type is None else {"hooks": hooks_type(progress)}


def _wrap(cls, hooks_type, stamps: list) -> None:
    init, run = cls.__init__, cls.run

    def timed_init(self, *args, **kwargs):
        stamps.append(("weights", time.time()))
        init(self, *args, **kwargs)
        stamps.append(("cli", time.time()))

    def timed_run(self, *args, **kwargs):
        if hooks_type is None:  # a checkout from before the hooks were one value: run(..., progress=…)
            given = kwargs.pop("progress", None)
        else:
            if len(args) > 3:  # (image, guidance, options, hooks)
                args, kwargs = args[:3], {**kwargs, "hooks": args[3]}
            hooks = kwargs.pop("hooks", None) or hooks_type()
            given = hooks.progress

        def stamped(stage, fraction):
            stamps.append((stage, time.time()))
            if given is not None:
                given(stage, fraction)

        if hooks_type is None:
            kwargs["progress"] = stamped
        else:
            kwargs["hooks"] = hooks_type(stamped, hooks.should_cancel)
        result = run(self, *args, **kwargs)
        stamps.append(("cli", time.time()))
        save = result.save_mesh

        def timed_save(*a, **kw):
            stamps.append(("write", time.time()))
            try:
                return save(*a, **kw)
            finally:
                stamps.append(("cli", time.time()))

        result.save_mesh = timed_save
        return result

    cls.__init__, cls.run = timed_init, timed_run


def cold(image: str, out: str, weights: str) -> dict:
    stamps: list[tuple[str, float]] = [("python + cli", T_START)]
    sys.meta_path.insert(0, _StampImport(stamps))
    sys.argv = ["genre", "reconstruct", image, "-o", out, "--weights", weights]
    import importlib

    # the command itself, as `python -m genre_backend.cli reconstruct …` runs it (run(): main, then the exit); by
    # name, as a user's shell starts it: the probe measures the layer above it, it does not build on it
    cli = importlib.import_module("genre_backend.cli")
    try:
        rc = cli.main()
    except SystemExit as exc:
        rc = exc.code if isinstance(exc.code, int) else 1
    stamps.append(("end", time.time()))
    return {"mode": "cold", "rc": rc, "stamps": stamps, "modules": _watched_modules(), "module_count": len(sys.modules)}


def probe(argv: list[str]) -> int:
    mode, *rest = argv
    if mode == "warm":
        warm(rest[0], rest[1])
        return 0
    if mode != "cold":
        raise SystemExit(f"bench_probe: unknown mode {mode!r}")
    summary = cold(*rest)
    print("\n" + json.dumps(summary))
    # the process ends as `genre reconstruct`'s does (the "exit" row): a checkout from before the quick exit (its
    # cli has no run()) exits as usual; this checkout's genre_backend.process must not stand in for it
    if not hasattr(sys.modules["genre_backend.cli"], "run"):
        return 0
    from genre_backend.process import exit_process

    exit_process(0, quick=True)


if __name__ == "__main__":
    sys.exit(probe(sys.argv[1:]))
