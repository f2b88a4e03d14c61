"""``genre chain NAME``: the training chains as data.

A chain is a list of :class:`Step` records, each one command of the project
(``genre data|train|eval …`` or ``python -m training.eval.…``, run with this
interpreter, ``sys.executable``) or a file copy, with the paths it reads and
writes.  The named chains (:data:`CHAINS`) are records too: which recipe,
which stages, how many joint rounds; the settings a stage trains with are its
recipe's (:mod:`training.learn.recipe`), never the chain's.

* ``protocol`` — the research weights (``protocol``: seen classes only, every
  Table-1 number): fetch, build, render, targets, the four stages (recipe
  ``shipped``), the evaluation views, the two trained baselines, ``genre
  eval`` into ``results/default`` and the installation of the weights.
  ``protocol-photo`` (recipe ``photo``: the depth net continued from the
  ``protocol`` weights on photo-composited renders) and ``protocol-sharp``
  (recipe ``sharp``: the depth net kept, the other stages continued from the
  ``protocol`` weights on the distance target) are its variants.
* ``product`` — the product weights (``default``): every class and the
  procedural shapes (recipe ``product``), depth, inpaint and refine from the
  shipped ``default`` weights, then ``--rounds`` rounds of the joint stage;
  round k trains the joint stage to k × the recipe's joint budget, keeps the
  weights (``joint/round_STEPS.safetensors``), scores them on the product test
  split and its primitives and adds a point to the learning curve
  (``results/product/learning_curve.csv``); the side-by-side tables end it.
  Installing stays a deliberate step (``results/decisions.md``).
  ``product-continue``: joint rounds straight from the shipped ``default``
  weights on a fresh machine (the curve's hours continued from the 2.44 h
  behind them, labels prefixed ``s2_``); ``product-full``: recipe
  ``product_full``, the refiner grown by its full-resolution branch, its
  refine stage from the shipped weights, scored, no joint round.
* ``eval-views`` — only what scoring a candidate needs on a fresh machine: the
  corpus, the product test split's views (from below 45° and, in
  ``views/product_up``, from 45–88°) and its primitives', and the
  flat-from-above group's shapes and views.
* ``train-views`` — the training views of the product runs since 2026-12-04
  (``views/fresh88``, ``fresh_prim``, ``thin74``, with their targets), made
  again on a fresh machine with the seeds their commands used.
* ``product-cycle`` — one cycle of the product weights from the installed
  file (recipe ``cycle``): those views, the depth stage, its depth net grafted
  into the installed file, the refine stage, the joint stage.  Reads and
  installs stay deliberate steps (``results/decisions.md``).

Every command resumes by itself (a stage from its checkpoint, renders and
scores view by view), so running a chain again continues it.  A step that
ends writes a marker, ``$GENRE_HOME/chains/NAME/STEP.json`` (its command and
time); a step is *finished* when its marker names the same command and every
path it writes exists.  ``--resume`` skips the finished steps at the chain's start
and runs the rest (a step after one that runs again runs again too: what it reads may have changed).  ``--dry-run``
prints the plan, one line per step (``[done]`` for the finished ones), and
runs and writes nothing.  Timings go to ``$GENRE_HOME/logs/chain.log``.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from genre_backend.atomic import atomic_write, atomic_write_json

from .data.corpus import REPO_ROOT, data_dir
from .learn.recipe import get_recipe

__all__ = ["Run", "Train", "Copy", "Step", "Chain", "ProtocolChain", "ProductChain", "EvalViewsChain", "TrainViewsChain",
           "CycleChain", "CHAINS", "ChainFailed",
           "plan_lines", "run_chain", "is_finished", "finished_prefix", "parse_args", "main"]

GENRE = "genre_backend.cli"  # `python -m genre_backend.cli` is `genre`


def _show(path: Path | str, home: Path | None = None) -> str:
    """A path as a plan shows it, quoted for a shell: under the GenRe home as ``$GENRE_HOME/…``, under the checkout
    relative to it."""
    p = Path(path)
    for root, prefix in ((home, "$GENRE_HOME/"), (REPO_ROOT, "")):
        if root is not None and p.is_relative_to(root):
            return prefix + shlex.quote(str(p.relative_to(root)))
    return shlex.quote(str(p))


@dataclass(frozen=True)
class Run:
    """A command of the project: ``python -m MODULE ARGS…`` (``genre ARGS…`` when the module is the CLI)."""

    module: str
    args: tuple[str, ...]

    def command(self) -> tuple[str, ...]:
        return (self.module, *self.args)

    def argv(self) -> list[str]:
        return [sys.executable, "-m", self.module, *self.args]

    def describe(self, home: Path | None = None) -> str:
        head = "genre" if self.module == GENRE else f"python -m {self.module}"
        return " ".join([head, *(_show(a, home) if a.startswith("/") else shlex.quote(a) for a in self.args)])


@dataclass(frozen=True)
class Train:
    """One ``genre train`` stage: ``recipe``'s settings for ``stage``, on ``data`` into ``out/stage``, starting from
    ``init``; ``steps`` (a joint round's target) and ``options`` (tests: a tiny model) override the recipe."""

    stage: str
    recipe: str
    data: tuple[Path, ...]
    out: Path
    init: Path | None = None
    steps: int | None = None
    backgrounds: Path | None = None
    options: tuple[str, ...] = ()
    processes: int = 1  # > 1: data-parallel, torchrun with this many one-thread processes (each its batch)

    def __post_init__(self):
        if self.processes < 1:
            raise ValueError(f"processes: expected an int >= 1, got {self.processes!r}")

    def _run(self) -> Run:
        args = ["--recipe", self.recipe, self.stage, "--data", *map(str, self.data), "--out", str(self.out)]
        if self.init is not None:
            args += ["--init", str(self.init)]
        if self.steps is not None:
            args += ["--steps", str(self.steps)]
        if self.backgrounds is not None:
            args += ["--backgrounds", str(self.backgrounds)]
        args += ["--no-progress", *self.options]
        if self.processes == 1:
            return Run(GENRE, ("train", *args))
        # torchrun gives each process one thread (OMP_NUM_THREADS=1) unless the environment names another count
        return Run("torch.distributed.run", ("--standalone", f"--nproc_per_node={self.processes}",
                                             "-m", "training.learn.train", *args))

    def command(self) -> tuple[str, ...]:
        return self._run().command()

    def argv(self) -> list[str]:
        return self._run().argv()

    def describe(self, home: Path | None = None) -> str:
        return self._run().describe(home)


@dataclass(frozen=True)
class Copy:
    """A file copied, atomically (a joint round's weights kept before the next round overwrites them)."""

    src: Path
    dst: Path

    def command(self) -> tuple[str, ...]:
        return ("copy", str(self.src), str(self.dst))

    def describe(self, home: Path | None = None) -> str:
        return f"copy {_show(self.src, home)} {_show(self.dst, home)}"


@dataclass(frozen=True)
class Step:
    """One step of a chain: its name (unique in the chain), what it does, and the paths it reads and writes."""

    name: str
    action: Run | Train | Copy
    reads: tuple[Path, ...] = ()
    writes: tuple[Path, ...] = ()


@dataclass(frozen=True)
class Chain:
    """A named list of steps, run in order."""

    name: str
    steps: tuple[Step, ...]

    def __post_init__(self):
        names = [s.name for s in self.steps]
        if len(names) != len(set(names)):
            raise ValueError(f"chain {self.name!r}: step names must be unique, got {names}")


# ---- the steps the chains are made of -------------------------------------------------------------
def _genre(name: str, *args: str | Path, reads=(), writes=()) -> Step:
    return Step(name, Run(GENRE, tuple(map(str, args))), tuple(reads), tuple(writes))


def _render(name: str, home: Path, split: str, out: Path, views: int, seed: int | None = None,
            classes: str | None = None, manifest: Path | None = None,
            elevation: tuple[int, int] | None = None) -> Step:
    """``genre data render`` of ``views`` views per shape of the manifest's ``split`` into ``out`` (the corpus's
    manifest unless ``manifest`` names another; the preset's elevations unless ``elevation`` is given)."""
    manifest = manifest or home / "corpus" / "manifest.json"
    args = ["data", "render", "--shapes", manifest, "--split", split]
    if classes:
        args += ["--classes", classes]
    args += ["--out", out, "--views", str(views), "--preset", "default"]
    if seed is not None:
        args += ["--seed", str(seed)]
    if elevation is not None:
        args += ["--elevation", *map(str, elevation)]
    return _genre(name, *args, "--no-progress", reads=(manifest,), writes=(out,))


def _targets(name: str, views: Path, preset: str | None = None) -> Step:
    """``genre data targets`` of the views in ``views`` (``preset``: the config they are made for; None: the views')."""
    args = ("data", "targets", "--views", views, *(("--preset", preset) if preset else ()), "--no-progress")
    return _genre(name, *args, reads=(views,), writes=(views,))


def _photo_framed(views: Path) -> list[Step]:
    """``views`` framed as ``genre reconstruct`` frames a photo (``genre data photo-frame``) into the folder of the same
    name with ``_pf`` added, with their targets: the sets the rules read since 2026-12-06 23:08
    (results/photo_framing.md)."""
    out = views.with_name(views.name + "_pf")
    return [_genre(f"photo_frame_{views.name}", "data", "photo-frame", "--views", views, "--out", out, "--no-progress",
                   reads=(views,), writes=(out,)),
            _targets(f"targets_{views.name}_pf", out)]


def _train(name: str, action: Train) -> Step:
    reads = (*action.data, *((action.init,) if action.init else ()), *((action.backgrounds,) if action.backgrounds else ()))
    stage_dir = action.out / action.stage
    return Step(name, action, reads, (stage_dir / "final.safetensors", stage_dir / "summary.json"))


def _corpus(home: Path) -> list[Step]:
    return [_genre("fetch", "data", "fetch", writes=(home / "cache" / "debs",)),
            _genre("build", "data", "build", reads=(home / "cache" / "debs",), writes=(home / "corpus" / "manifest.json",))]


def _backgrounds(home: Path) -> Step:
    return _genre("backgrounds", "data", "backgrounds", writes=(home / "backgrounds" / "index.json",))


def _weights(name: str) -> Path:
    return REPO_ROOT / "genre_backend" / "weights" / f"{name}.safetensors"


# ---- the research chain ------------------------------------------------------------------------
@dataclass(frozen=True)
class ProtocolChain:
    """The chain of the research weights, ``protocol``, with ``recipe``: ``shipped`` trains every stage afresh,
    ``photo`` continues the depth net from the ``protocol`` weights on photo-composited renders, ``sharp`` keeps
    their depth net and continues the other stages (and the 3D Completion net) from them."""

    recipe: str = "shipped"
    train_views_per_shape: int = 20
    eval_test_views: int = 3  # per seen-test shape (they also choose the threshold)
    eval_unseen_views: int = 1  # per unseen shape
    eval_jobs: int = 2

    def build(self, name: str, home: Path) -> Chain:
        views, eval_views, run = home / "views" / "default", home / "views" / "eval", home / "runs" / "default"
        results = REPO_ROOT / "results" / "default"
        steps = [*_corpus(home),
                 _render("render", home, "train", views, self.train_views_per_shape),
                 _targets("targets", views, "default")]
        train = dict(recipe=self.recipe, data=(views,), out=run)
        photo = self.recipe == "photo"
        if photo:
            steps.append(_backgrounds(home))
        if self.recipe == "sharp":  # the depth net kept: the stages after it continue the protocol weights
            depth_weights = completion_init = _weights("protocol")
        else:
            depth_weights = completion_init = run / "depth" / "best.safetensors"
            steps.append(_train("depth", Train("depth", init=_weights("protocol") if photo else None,
                                               backgrounds=home / "backgrounds" if photo else None, **train)))
        steps += [_train("inpaint", Train("inpaint", init=depth_weights, **train)),
                  _train("refine", Train("refine", init=run / "inpaint" / "best.safetensors", **train)),
                  _train("joint", Train("joint", init=run / "refine" / "best.safetensors", **train))]
        steps += [_render("render_eval", home, "test", eval_views, self.eval_test_views, seed=1),
                  *(_render(f"render_eval_{split}", home, split, eval_views, self.eval_unseen_views, seed=1)
                    for split in ("unseen", "unseen-pix3d")),
                  _targets("targets_eval", eval_views, "default"),
                  # the baselines, the recipe's budgets: 3D Completion from the same refiner, 1-step afresh
                  _train("completion", Train("completion", init=completion_init, **train)),
                  _train("onestep", Train("onestep", **train))]
        manifest = home / "corpus" / "manifest.json"
        steps.append(_genre("eval", "eval", "--data", eval_views, "--out", results, "--run", run, "--train-views", views,
                            "--manifest", manifest, "--jobs", str(self.eval_jobs), "--heatmap-shapes", "2", "--gallery", "2",
                            "--no-progress", reads=(eval_views, run, views, manifest),
                            writes=(results / "per_view.csv", results / "thresholds.json")))
        joint = run / "joint" / "best.safetensors"
        steps.append(Step("install", Run("training.eval.install", ("--weights", str(joint), "--thresholds",
                                                                   str(results / "thresholds.json"), "--name", "protocol")),
                          (joint, results / "thresholds.json"), (_weights("protocol"),)))
        return Chain(name, tuple(steps))


# ---- the product chain -------------------------------------------------------------------------
def _weights_level(path: Path) -> float:
    """The mesh threshold ``geometry.default_threshold`` stored in a weights file (its metadata only)."""
    from safetensors import safe_open

    from genre_backend.weights_file import stored_config

    if not path.is_file():
        raise ValueError(f"no such weights file: {path} (the product chains read their level from it)")
    with safe_open(str(path), framework="pt", device="cpu") as f:
        meta = f.metadata() or {}
    return stored_config(path, meta).geometry.default_threshold


@dataclass(frozen=True)
class ProductChain:
    """The chain of the product weights, ``default``: ``first`` is ``all`` (depth, inpaint and refine from
    ``init``), ``refine`` (the refine stage only) or ``none`` (joint rounds straight from ``init``); then
    ``rounds`` joint rounds of the recipe's joint budget each, every one kept, scored and put on the curve."""

    recipe: str = "product"
    first: str = "all"
    rounds: int = 1
    run: str = "product"  # $GENRE_HOME/runs/RUN
    init: str = "default"  # the shipped weights a run with no checkpoint starts from
    base_hours: float = 0.0  # the processor hours behind init (the curve's hours continue from them)
    curve_prefix: str = ""  # the curve's labels get it, so that a second run does not replace the first's points
    views_per_shape: int = 4
    primitive_views: int = 12
    eval_jobs: int = 2

    def build(self, name: str, home: Path, rounds: int | None = None) -> Chain:
        paths = _ProductPaths(home, home / "runs" / self.run)
        steps = [*_corpus(home), _backgrounds(home), *self._views(home, paths)]
        train = dict(recipe=self.recipe, data=(paths.views, paths.prim_views), out=paths.run,
                     backgrounds=home / "backgrounds")
        init = _weights(self.init)
        joint_init = init
        stages = {"all": ("depth", "inpaint", "refine"), "refine": ("refine",), "none": ()}[self.first]
        for stage in stages:
            steps.append(_train(stage, Train(stage, init=joint_init, **train)))
            joint_init = paths.run / stage / "best.safetensors"
        level = f"{_weights_level(init):g}"
        steps += [*self._evaluate(paths, "protocol", _weights("protocol")), *self._evaluate(paths, "start", init),
                  self._curve(paths, "start", None, level, installed=self.init == "default")]
        last = "start"
        if self.first == "refine":  # the refine stage's weights are a point of the curve of their own
            steps += [*self._evaluate(paths, "refine", joint_init), self._curve(paths, "refine", paths.run, level)]
            last = "refine"
        budget = get_recipe(self.recipe).stage("joint").steps
        for k in range(1, (self.rounds if rounds is None else rounds) + 1):
            steps += self._round(paths, train, joint_init, k * budget, level)
            last = f"joint_{k * budget}"
        return Chain(name, (*steps, *self._compare(paths, home, last, level)))

    def _views(self, home: Path, paths: _ProductPaths) -> list[Step]:
        """The training views (every class, and more of the primitives) and the evaluation views."""
        test, primitives_test = _product_eval_views(home, paths)
        return [_render("render", home, "product-train", paths.views, self.views_per_shape),
                _targets("targets", paths.views), *test,
                _render("render_primitives", home, "product-train", paths.prim_views, self.primitive_views, seed=2,
                        classes="primitive"),
                _targets("targets_primitives", paths.prim_views), *primitives_test]

    def _evaluate(self, paths: _ProductPaths, label: str, weights: Path) -> list[Step]:
        """``genre eval`` of ``weights`` on the product test split and on 8 views of each of its primitives."""
        steps = []
        for prefix, views, out in (("eval", paths.eval_views, paths.scores / label),
                                   ("eval_primitives", paths.prim_eval_views, paths.scores / "primitives" / label)):
            steps.append(_genre(f"{prefix}_{label}", "eval", "--data", views, "--weights", weights, "--groups", "product-test",
                                "--rows", "GenRe,Truth through the representation", "--out", out, "--jobs",
                                str(self.eval_jobs), "--no-figures", "--no-progress", reads=(views, weights),
                                writes=(out / "per_view.csv",)))
        return steps

    def _curve(self, paths: _ProductPaths, label: str, run: Path | None, level: str, installed: bool = False) -> Step:
        """The learning curve's point ``label``: the scores of ``eval_LABEL`` and the processor hours of ``run``
        (None: the starting point, 0 h on top of ``base_hours``)."""
        args = ["curve", *(("--run", str(run)) if run else ()), "--eval", str(paths.scores / label),
                "--label", self.curve_prefix + label, "--csv", str(paths.results / "learning_curve.csv"),
                "--threshold", level, "--base-hours", f"{self.base_hours:g}", *(("--installed",) if installed else ())]
        return Step(f"curve_{label}", Run("training.eval.product", tuple(args)), (paths.scores / label,),
                    (paths.results / "learning_curve.csv",))

    def _round(self, paths: _ProductPaths, train: dict, init: Path, target: int, level: str) -> list[Step]:
        """One joint round: train to ``target`` steps, keep its weights, score them, add them to the curve."""
        label = f"joint_{target}"
        final, kept = paths.run / "joint" / "final.safetensors", paths.run / "joint" / f"round_{target}.safetensors"
        return [_train(label, Train("joint", init=init, steps=target, **train)),
                Step(f"keep_{target}", Copy(final, kept), (final,), (kept,)),
                *self._evaluate(paths, label, kept), self._curve(paths, label, paths.run, level)]

    def _compare(self, paths: _ProductPaths, home: Path, last: str, level: str) -> list[Step]:
        """The side-by-side tables of the last weights scored against the protocol model's."""
        manifest = home / "corpus" / "manifest.json"
        steps = []
        for name, sub, out, title in (("compare", "", "table.md", ()),
                                      ("compare_primitives", "primitives", "primitives.md",
                                       ("--title", "Regular primitives of the product test split, 8 views each"))):
            product, protocol = paths.scores / sub / last, paths.scores / sub / "protocol"
            args = ("compare", "--product", str(product), "--protocol", str(protocol), "--manifest", str(manifest),
                    "--out", str(paths.results / out), "--threshold", level, *title)
            steps.append(Step(name, Run("training.eval.product", args), (product, protocol, manifest),
                              (paths.results / out,)))
        return steps


def _product_eval_views(home: Path, paths: _ProductPaths) -> tuple[list[Step], list[Step]]:
    """The product test split's views (one a shape) and its primitives' (8 a shape), each rendered and targeted."""
    return ([_render("render_eval", home, "product-test", paths.eval_views, 1, seed=1),
             _targets("targets_eval", paths.eval_views)],
            [_render("render_primitives_eval", home, "product-test", paths.prim_eval_views, 8, seed=3,
                     classes="primitive"),
             _targets("targets_primitives_eval", paths.prim_eval_views)])


@dataclass(frozen=True)
class EvalViewsChain:
    """What scoring a candidate against the installed file needs on a fresh machine, and nothing else: the corpus,
    the product test split's and its primitives' views as ``product`` renders them, the product test split's shapes
    once more from 45-88 degrees (``views/product_up``: the product rule scores every angle), and the flat-from-above group
    (``genre data flat-test``, 2 views a shape from 60-88 degrees: docs/evaluation.md), then each of them framed as a photo
    is (``VIEWS_pf``, :func:`_photo_framed`).  A CPU session's candidates are
    then scored with ``genre eval --data VIEWS --weights W --levels 0.45`` on each (docs/training.md)."""

    flat_views: int = 2
    flat_elevation: tuple[int, int] = (60, 88)
    up_elevation: tuple[int, int] = (45, 88)  # the product test's shapes from above too (results/decisions.md 2026-12-03)

    def build(self, name: str, home: Path) -> Chain:
        paths = _ProductPaths(home, home / "runs" / "product")
        test, primitives_test = _product_eval_views(home, paths)
        up_views = home / "views" / "product_up"
        test += [_render("render_eval_up", home, "product-test", up_views, 1, seed=71, elevation=self.up_elevation),
                 _targets("targets_eval_up", up_views)]
        flat_shapes, flat_views = home / "flat_test", home / "views" / "flat_eval"
        flat_manifest = flat_shapes / "manifest.json"
        flat = [_genre("flat_test", "data", "flat-test", "--out", flat_shapes, writes=(flat_manifest,)),
                _render("render_flat_eval", home, "flat-from-above", flat_views, self.flat_views, seed=5,
                        manifest=flat_manifest, elevation=self.flat_elevation),
                _targets("targets_flat_eval", flat_views)]
        framed = [step for views in (paths.eval_views, up_views, paths.prim_eval_views, flat_views)
                  for step in _photo_framed(views)]
        return Chain(name, (*_corpus(home), *test, *primitives_test, *flat, *framed))


@dataclass(frozen=True)
class TrainViewsChain:
    """The training views every product run since 2026-12-04 learns from, made again on a fresh machine: every
    product-train shape twice (``views/fresh88``), its primitives four times more (``views/fresh_prim``) and the
    thin shapes lying on the ground twice (``genre data thin``, ``views/thin74``), all from -10 to 88 degrees with
    their targets, then each framed as a photo is (``VIEWS_pf``); the seeds are the ones the runs' documented commands
    used (docs/training.md)."""

    elevation: tuple[int, int] = (-10, 88)

    def steps(self, home: Path) -> list[Step]:
        fresh88, fresh_prim, thin74 = _train_views(home)
        thin_manifest = home / "thin_train" / "manifest.json"
        return [*_corpus(home), _backgrounds(home),
                _render("render_fresh88", home, "product-train", fresh88, 2, seed=21, elevation=self.elevation),
                _targets("targets_fresh88", fresh88),
                _render("render_fresh_prim", home, "product-train", fresh_prim, 4, seed=22, classes="primitive",
                        elevation=self.elevation),
                _targets("targets_fresh_prim", fresh_prim),
                _genre("thin", "data", "thin", "--out", home / "thin_train", writes=(thin_manifest,)),
                _render("render_thin74", home, "product-train", thin74, 2, seed=74, manifest=thin_manifest,
                        elevation=self.elevation),
                _targets("targets_thin74", thin74)]

    def build(self, name: str, home: Path) -> Chain:
        framed = [step for views in _train_views(home) for step in _photo_framed(views)]
        return Chain(name, (*self.steps(home), *framed))


def _train_views(home: Path) -> tuple[Path, Path, Path]:
    """``views/fresh88``, ``fresh_prim`` and ``thin74``: the training views :class:`TrainViewsChain` makes."""
    return home / "views" / "fresh88", home / "views" / "fresh_prim", home / "views" / "thin74"


@dataclass(frozen=True)
class CycleChain:
    """One cycle of the product weights from ``init`` (recipe ``cycle``), the sequence behind the installed file
    since 2026-12-05 (depth-76-half → refine-77 → joint-78; depth-82-half → refine-83 → joint-84): the training
    views (:class:`TrainViewsChain`); the depth stage on them with the thin renders at about 8 % of the samples
    (``fresh88`` named twice); its depth net grafted into ``init`` (stored int8, as the installed file is); the refine
    stage from that file; the joint stage from the refine stage's, the thin renders there counting in the depth net's
    own loss alone (``--depth-only``).  The refine and joint stages train data-parallel, ``processes`` one-thread
    processes of the recipe's batch each.  Nothing is scored or installed here: each stage's weights are read by
    ``scripts/read_candidate.sh`` under a rule written before the read (``results/decisions.md``)."""

    recipe: str = "cycle"
    init: str = "default"
    run: str = "cycle"  # $GENRE_HOME/runs/RUN
    processes: int = 2

    def build(self, name: str, home: Path) -> Chain:
        (fresh88, fresh_prim, thin74), run = _train_views(home), home / "runs" / self.run
        init, grafted = _weights(self.init), run / "graft" / "depth_grafted.safetensors"
        common = dict(recipe=self.recipe, out=run, backgrounds=home / "backgrounds")
        steps = [*TrainViewsChain().steps(home),
                 _train("depth", Train("depth", init=init, data=(fresh88, fresh88, fresh_prim, thin74),
                                       **common)),
                 _genre("graft", "train", "graft", init, "--depth-from", run / "depth" / "final.safetensors",
                        "--storage", "int8", "--out", grafted,
                        reads=(init, run / "depth" / "final.safetensors"), writes=(grafted,)),
                 _train("refine", Train("refine", init=grafted, data=(fresh88, fresh_prim),
                                        processes=self.processes, **common)),
                 _train("joint", Train("joint", init=run / "refine" / "final.safetensors",
                                       data=(fresh88, fresh88, fresh_prim, fresh_prim, thin74),
                                       options=("--depth-only", str(thin74)), processes=self.processes, **common))]
        return Chain(name, tuple(steps))


@dataclass(frozen=True)
class _ProductPaths:
    home: Path
    run: Path

    @property
    def views(self) -> Path:
        return self.home / "views" / "product"

    @property
    def prim_views(self) -> Path:
        return self.home / "views" / "product_primitives"

    @property
    def eval_views(self) -> Path:
        return self.home / "views" / "product_eval"

    @property
    def prim_eval_views(self) -> Path:
        return self.home / "views" / "primitives_eval"

    @property
    def scores(self) -> Path:  # genre eval folders of each round (large; not committed)
        return self.home / "results" / "product"

    @property
    def results(self) -> Path:  # the committed tables and the learning curve
        return REPO_ROOT / "results" / "product"


CHAINS: dict[str, ProtocolChain | ProductChain | EvalViewsChain | TrainViewsChain | CycleChain] = {
    "protocol": ProtocolChain("shipped"),
    "protocol-photo": ProtocolChain("photo"),
    "protocol-sharp": ProtocolChain("sharp"),
    "product": ProductChain(),
    "product-continue": ProductChain(first="none", rounds=3, base_hours=2.44, curve_prefix="s2_"),
    "product-full": ProductChain(recipe="product_full", first="refine", rounds=0, run="product_full"),
    "eval-views": EvalViewsChain(),
    "train-views": TrainViewsChain(),
    "product-cycle": CycleChain(),
}


# ---- running a chain ---------------------------------------------------------------------------
class ChainFailed(RuntimeError):
    """A step's command failed; ``returncode`` is its exit status."""

    def __init__(self, step: str, returncode: int):
        super().__init__(f"step {step!r} failed (exit status {returncode})")
        self.step, self.returncode = step, returncode


def _marker(home: Path, chain: Chain, step: Step) -> Path:
    return home / "chains" / chain.name / f"{step.name}.json"


def is_finished(home: Path, chain: Chain, step: Step) -> bool:
    """Whether ``step`` ended: its marker names the same command, and every path it writes exists."""
    try:
        marker = json.loads(_marker(home, chain, step).read_text())
    except (OSError, ValueError):
        return False
    return (isinstance(marker, dict) and marker.get("command") == list(step.action.command())
            and all(p.exists() for p in step.writes))


def finished_prefix(chain: Chain, home: Path) -> int:
    """How many steps at the chain's start are finished: the ones ``--resume`` skips.  A step after an unfinished
    one runs again even when it finished once, as what it reads may have changed (its command resumes)."""
    count = 0
    for step in chain.steps:
        if not is_finished(home, chain, step):
            break
        count += 1
    return count


def plan_lines(chain: Chain, home: Path) -> list[str]:
    """One line per step: name, ``[done]`` when ``--resume`` would skip it, the command, what it reads and writes."""
    skipped = finished_prefix(chain, home)
    lines = []
    for i, step in enumerate(chain.steps):
        done = " [done]" if i < skipped else ""
        reads = ", ".join(_show(p, home) for p in step.reads) or "-"
        writes = ", ".join(_show(p, home) for p in step.writes) or "-"
        lines.append(f"{step.name}{done}: {step.action.describe(home)}  (reads {reads}; writes {writes})")
    return lines


def _execute(step: Step, home: Path) -> None:
    action = step.action
    if isinstance(action, Copy):
        action.dst.parent.mkdir(parents=True, exist_ok=True)
        with action.src.open("rb") as src:
            atomic_write(action.dst, lambda fh: fh.write(src.read()))
        return
    env = {**os.environ, "GENRE_HOME": str(home)}
    code = subprocess.run(action.argv(), cwd=REPO_ROOT, env=env).returncode
    if code != 0:
        raise ChainFailed(step.name, code)


def run_chain(chain: Chain, home: Path, resume: bool = False, say: Callable[[str], None] = print) -> list[str]:
    """Run ``chain``'s steps in order (``resume``: skip the finished ones at its start), each step's marker written
    when it ends;
    log lines go to ``say`` and ``$GENRE_HOME/logs/chain.log``.  Returns the names of the steps run.
    Raises :class:`ChainFailed` at the first step that fails (the steps after it do not run)."""
    logs = home / "logs"
    logs.mkdir(parents=True, exist_ok=True)

    def log(text: str) -> None:
        line = f"{time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())} {chain.name}: {text}"
        say(line)
        with (logs / "chain.log").open("a", encoding="utf-8") as fh:
            fh.write(line + "\n")

    skipped = finished_prefix(chain, home) if resume else 0
    for step in chain.steps[:skipped]:
        log(f"skip (finished): {step.name}")
    ran = []
    for step in chain.steps[skipped:]:
        t0 = time.monotonic()
        log(f"start: {step.name}: {step.action.describe(home)}")
        _execute(step, home)
        seconds = round(time.monotonic() - t0, 1)
        marker = _marker(home, chain, step)
        marker.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(marker, {"command": list(step.action.command()), "seconds": seconds,
                                                        "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())})
        log(f"done in {seconds} s: {step.name}")
        ran.append(step.name)
    return ran


# ---- the command line --------------------------------------------------------------------------
@dataclass(frozen=True)
class ChainSpec:
    """What one ``genre chain`` command line asks for."""

    name: str
    dry_run: bool = False
    resume: bool = False
    rounds: int | None = None  # the product chains' joint rounds (None: the chain's own)


def parse_args(argv: list[str], prog: str = "genre chain") -> ChainSpec:
    """``genre chain``'s arguments as a :class:`ChainSpec`; an unknown chain exits 2 with the known names."""
    parser = argparse.ArgumentParser(prog=prog, description="Run a named training chain (training/chain.py); every "
                                     "step resumes where it stopped.")
    parser.add_argument("name", help=f"the chain: {', '.join(CHAINS)}")
    parser.add_argument("--dry-run", action="store_true", help="print the plan, one line per step; run and write nothing")
    parser.add_argument("--resume", action="store_true", help="skip the steps that finished (their marker and outputs exist)")
    parser.add_argument("--rounds", type=int, default=None,
                        help="the product chains: joint rounds in all (round k trains to k x the recipe's joint steps)")
    args = parser.parse_args(argv)
    if args.name not in CHAINS:
        parser.error(f"unknown chain {args.name!r}; known chains: {', '.join(CHAINS)}")
    if args.rounds is not None and not isinstance(CHAINS[args.name], ProductChain):
        parser.error(f"chain {args.name!r} has no joint rounds (--rounds is for the product chains)")
    if args.rounds is not None and args.rounds < 0:
        parser.error(f"--rounds: expected an int >= 0, got {args.rounds}")
    return ChainSpec(args.name, args.dry_run, args.resume, args.rounds)


def run(spec: ChainSpec, prog: str = "genre chain") -> int:
    """Print the plan (``dry_run``) or run the chain; returns the exit status (a failed step's, else 0)."""
    home = data_dir()
    try:
        named = CHAINS[spec.name]
        chain = named.build(spec.name, home, spec.rounds) if isinstance(named, ProductChain) else named.build(spec.name, home)
    except ValueError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    if spec.dry_run:
        print("\n".join(plan_lines(chain, home)))
        return 0
    try:
        run_chain(chain, home, spec.resume)
    except ChainFailed as exc:
        print(f"{prog}: error: {exc}; run it again to continue", file=sys.stderr)
        return exc.returncode
    return 0


def main(argv: list[str] | None = None, prog: str = "genre chain") -> int:
    return run(parse_args(list(sys.argv[1:] if argv is None else argv), prog), prog)


if __name__ == "__main__":
    sys.exit(main())
