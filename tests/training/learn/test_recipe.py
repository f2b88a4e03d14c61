"""Training recipes: the named recipes reproduce the settings that trained the shipped weights."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import pytest

from training.learn.recipe import RECIPES, STAGES, StageRecipe, get_recipe
from training.learn.train import TrainConfig, main

REPO = Path(__file__).resolve().parents[3]

# Before recipes existed, genre train's defaults were these (train.py's DEFAULT_LR, steps 1000,
# batch 4, Adam betas (0.5, 0.9), surface weight 10) ...
HISTORIC_DEFAULTS = {"steps": 1000, "batch_size": 4, "beta1": 0.5, "beta2": 0.9, "surface_weight": 10.0}
HISTORIC_LR = {"depth": 1e-3, "inpaint": 1e-4, "refine": 1e-4, "joint": 1e-5, "completion": 1e-4, "onestep": 1e-3}
# ... and the research chain (then a shell script, train_default.sh) passed these flags to each stage (as of commit e91e108).
HISTORIC_SCRIPT_FLAGS = {
    "depth": ["--steps", "6000"],
    "inpaint": ["--steps", "3000"],
    "refine": ["--steps", "3000", "--lr", "1e-3", "--surface-weight", "0.1"],
    "joint": ["--steps", "400", "--surface-weight", "0.1"],
    "completion": ["--steps", "3000", "--lr", "1e-3", "--surface-weight", "0.1"],
    "onestep": ["--steps", "3000"],
}


def _dry_run(capsys, *args) -> dict:
    assert main([*args, "--dry-run"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    return json.loads(out[-1])


@pytest.mark.parametrize("stage", STAGES)
def test_paper_recipe_is_the_historic_default(stage, capsys):
    got = _dry_run(capsys, stage, "--data", "d", "--out", "o")
    assert {k: got[k] for k in HISTORIC_DEFAULTS} == HISTORIC_DEFAULTS
    assert got["lr"] == HISTORIC_LR[stage] and got["recipe"] == "paper" and got["preset"] == "default"


@pytest.mark.parametrize("stage", STAGES)
def test_shipped_recipe_equals_the_scripts_historic_flags(stage, capsys):
    historic = _dry_run(capsys, stage, "--data", "d", "--out", "o", *HISTORIC_SCRIPT_FLAGS[stage])
    shipped = _dry_run(capsys, "--recipe", "shipped", stage, "--data", "d", "--out", "o")
    historic.pop("recipe"), shipped.pop("recipe")
    assert shipped == historic


def test_explicit_options_override_the_recipe(capsys):
    got = _dry_run(capsys, "--recipe", "shipped", "refine", "--data", "d", "--out", "o", "--lr", "5e-4", "--steps", "7")
    assert (got["lr"], got["steps"], got["surface_weight"]) == (5e-4, 7, 0.1)


def _resolved_training_steps(chain) -> list[dict]:
    """The settings each training step of ``chain`` resolves to (``genre train``'s own argument parsing)."""
    from training.chain import Train
    from training.learn.train import parse_args

    out = []
    for step in chain.steps:
        if isinstance(step.action, Train):
            command = step.action.command()
            assert command[:2] == ("genre_backend.cli", "train")
            out.append(dataclasses.asdict(parse_args([*command[2:], "--dry-run"]).config))
    return out


def test_protocol_chain_names_the_recipe_and_resolves_to_the_historic_settings(tmp_path):
    from training.chain import CHAINS

    home = tmp_path / "home"
    chain = CHAINS["protocol"].build("protocol", home)
    resolved = _resolved_training_steps(chain)
    assert [r["stage"] for r in resolved] == ["depth", "inpaint", "refine", "joint", "completion", "onestep"]
    for step in chain.steps:
        line = step.action.describe(home)
        assert not line.startswith("genre train") or ("--recipe shipped" in line and "--lr" not in line
                                                       and "--surface-weight" not in line and "--steps" not in line)
    for r in resolved:
        historic = dataclasses.asdict(TrainConfig(stage=r["stage"], data=r["data"], out=r["out"], init=r["init"], progress=False,
                                                  **_flags_as_fields(HISTORIC_SCRIPT_FLAGS[r["stage"]])))
        historic.pop("recipe"), r.pop("recipe")
        assert r == historic
    assert all(d.startswith(str(home)) for r in resolved for d in r["data"])  # the views lie in the GenRe home
    assert not home.exists()  # building a plan writes nothing


def test_protocol_variants_start_from_the_protocol_weights(tmp_path):
    from training.chain import CHAINS

    weights = str(REPO / "genre_backend" / "weights" / "protocol.safetensors")
    photo = {r["stage"]: r for r in _resolved_training_steps(CHAINS["protocol-photo"].build("protocol-photo", tmp_path))}
    assert photo["depth"]["init"] == weights and photo["depth"]["photo_fraction"] == 0.8
    assert photo["depth"]["backgrounds"] == str(tmp_path / "backgrounds") and photo["depth"]["recipe"] == "photo"
    sharp = {r["stage"]: r for r in _resolved_training_steps(CHAINS["protocol-sharp"].build("protocol-sharp", tmp_path))}
    assert "depth" not in sharp and sharp["inpaint"]["init"] == weights and sharp["completion"]["init"] == weights
    assert sharp["refine"]["target"] == "distance" and sharp["onestep"]["init"] is None


def test_product_chain_starts_from_the_shipped_default_weights_under_the_home(tmp_path):
    from training.chain import CHAINS

    home = tmp_path / "home"
    default = str(REPO / "genre_backend" / "weights" / "default.safetensors")

    def plan(name, rounds=None):
        named = CHAINS[name]
        chain = named.build(name, home, rounds)
        return {s.name: s.action.describe(home) for s in chain.steps}, _resolved_training_steps(chain)

    steps, resolved = plan("product", 2)
    assert "--split product-train" in steps["render"] and "--split product-test" in steps["render_eval"]
    by_stage = {r["stage"]: r for r in resolved}
    assert by_stage["depth"]["init"] == default  # a run with no checkpoint starts from the shipped product weights
    assert by_stage["inpaint"]["init"] == f"{home}/runs/product/depth/best.safetensors"
    assert len(resolved) == 3 + 2 and all(r["recipe"] == "product" for r in resolved)
    assert all(r["data"] == [f"{home}/views/product", f"{home}/views/product_primitives"] for r in resolved)
    assert all(r["backgrounds"] == f"{home}/backgrounds" for r in resolved)
    assert [r["steps"] for r in resolved if r["stage"] == "joint"] == [600, 1200]  # rounds of the recipe's joint budget
    assert steps["keep_600"] == "copy $GENRE_HOME/runs/product/joint/final.safetensors $GENRE_HOME/runs/product/joint/round_600.safetensors"
    assert "--groups product-test" in steps["eval_joint_600"] and "learning_curve.csv" in steps["curve_joint_600"]
    assert "--classes primitive" in steps["render_primitives"] and "--split product-train" in steps["render_primitives"]
    assert "--classes primitive" in steps["render_primitives_eval"] and "--views 8" in steps["render_primitives_eval"]
    assert "$GENRE_HOME/views/primitives_eval" in steps["eval_primitives_joint_600"]
    # every score at the level of the weights the run starts from
    assert all("--threshold 0.45" in line for name, line in steps.items() if name.startswith(("curve_", "compare")))
    assert steps["curve_start"].endswith("--installed") and "--run" not in steps["curve_start"]
    assert "--installed" not in steps["curve_joint_600"]
    # continuing the shipped product model on a fresh machine: joint only, cumulative hours, prefixed labels
    steps, resolved = plan("product-continue")
    assert not {"depth", "inpaint", "refine"} & set(steps) and resolved[0]["init"] == default
    assert "--label s2_joint_600" in steps["curve_joint_600"] and "--base-hours 2.44" in steps["curve_joint_600"]
    # the refiner grown: the refine stage of product_full from the shipped weights, scored, then no joint round
    steps, resolved = plan("product-full")
    assert [(r["stage"], r["recipe"], r["init"]) for r in resolved] == [("refine", "product_full", default)]
    assert "--weights $GENRE_HOME/runs/product_full/refine/best.safetensors" in steps["eval_refine"]
    assert "--label refine" in steps["curve_refine"] and "--run $GENRE_HOME/runs/product_full" in steps["curve_refine"]
    assert "results/product/refine " in steps["compare"] and "primitives/refine " in steps["compare_primitives"]
    assert not home.exists()


def test_train_arguments_become_a_frozen_spec(tmp_path):
    from training.learn.train import TrainSpec, parse_args

    spec = parse_args(["refine", "--data", "d", "--out", "o", "--recipe", "shipped", "--steps", "7", "--dry-run"])
    assert isinstance(spec, TrainSpec) and spec.dry_run and spec.config.steps == 7 and spec.config.lr == 1e-3
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.dry_run = False
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"geometry": {"image_size": -1}}))
    with pytest.raises(SystemExit):  # a model config that is not one: the usage error, before anything trains
        parse_args(["depth", "--data", "d", "--out", "o", "--model-config", str(bad)])


def test_train_init_takes_a_shipped_name_as_weights_does(tmp_path, capsys):
    from genre_backend.weights_file import named_weights
    from training.learn.train import parse_args

    spec = parse_args(["depth", "--data", "d", "--out", "o", "--init", "default", "--inpaint-from", "protocol"])
    assert spec.config.init == str(named_weights("default")) and Path(spec.config.init).is_file()
    assert spec.config.inpaint_from == str(named_weights("protocol"))
    with pytest.raises(SystemExit):  # a bare word that is neither a name nor a file: the usage error, naming the choices
        parse_args(["depth", "--data", "d", "--out", "o", "--init", "defualt"])
    assert "give a name (default, protocol)" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # a path that is not there
        parse_args(["depth", "--data", "d", "--out", "o", "--init", str(tmp_path / "gone.safetensors")])
    assert "no such weights file" in capsys.readouterr().err


def _flags_as_fields(flags: list[str]) -> dict:
    out = {}
    for name, value in zip(flags[::2], flags[1::2]):
        key = name[2:].replace("-", "_")
        out[key] = int(value) if key == "steps" else float(value)
    return out


def shipped_target_is_the_models(recipes) -> bool:
    return all(recipes[name].target is None for name in ("paper", "shipped", "photo"))


def test_a_recipe_target_moves_the_model_to_it(tmp_path):
    from training.learn.train import TrainConfig

    assert TrainConfig(stage="refine", data="d", out="o", recipe="sharp").target == "distance"
    assert TrainConfig(stage="refine", data="d", out="o", recipe="shipped").target is None
    assert TrainConfig(stage="refine", data="d", out="o", recipe="shipped", target="shell").target == "shell"
    with pytest.raises(ValueError, match="target"):
        TrainConfig(stage="refine", data="d", out="o", target="occupancy")


def test_recipes_validate_their_values():
    assert set(RECIPES) == {"paper", "shipped", "photo", "sharp", "product", "product_full", "cycle"}
    # product_full = product with the refiner grown; only its refine stage differs
    full, product = RECIPES["product_full"], RECIPES["product"]
    assert full.refiner_full_nf == 8 and all(RECIPES[n].refiner_full_nf is None for n in RECIPES if n != "product_full")
    assert {k: v for k, v in full.stages.items() if k != "refine"} == {k: v for k, v in product.stages.items() if k != "refine"}
    assert full.target == product.target
    # sharp = shipped on the distance target, the two voxel nets with equal budgets
    sharp = RECIPES["sharp"]
    assert sharp.target == "distance" and shipped_target_is_the_models(RECIPES)
    assert sharp.stages["refine"].steps == sharp.stages["completion"].steps
    assert sharp.stages["inpaint"] == RECIPES["shipped"].stages["inpaint"]
    # photo = shipped, except the depth stage continued on photo-composited samples
    photo, shipped = RECIPES["photo"], RECIPES["shipped"]
    assert {k: v for k, v in photo.stages.items() if k != "depth"} == {k: v for k, v in shipped.stages.items() if k != "depth"}
    assert photo.stages["depth"].photo_fraction == 0.8 and all(s.photo_fraction == 0.0 for s in shipped.stages.values())
    # product: the distance target; only its joint stage adds the depth loss and composites photos there
    product = RECIPES["product"]
    assert product.target == "distance" and product.stages["joint"].depth_weight > 0
    from training.learn.train import TrainConfig

    joint = TrainConfig(stage="joint", data="d", out="o", recipe="product")
    assert joint.lr_at(0) == 1e-4 and joint.lr_at(1200) == pytest.approx(5e-5) and joint.lr_at(3600) == pytest.approx(1.25e-5)
    assert TrainConfig(stage="joint", data="d", out="o", recipe="shipped").lr_at(5000) == 1e-5  # no half-life: constant
    assert all(s.depth_weight == 0.0 for r in RECIPES.values() for name, s in r.stages.items() if not (r.name in ("product", "product_full", "cycle") and name == "joint"))
    # cycle = product with the depth, refine and joint stages in the installed file's regime (CYCLE_FLAGS below)
    cycle = RECIPES["cycle"]
    assert {k: v for k, v in cycle.stages.items() if k not in ("depth", "refine", "joint")} == {
        k: v for k, v in product.stages.items() if k not in ("depth", "refine", "joint")}
    assert cycle.target == product.target and all(cycle.stages[k].backdrop == 1.0 for k in ("depth", "refine", "joint"))
    with pytest.raises(ValueError, match="unknown recipe"):
        get_recipe("fast")
    for bad in ({"lr": 0.0}, {"lr": float("nan")}, {"lr": 1e-3, "steps": 0}, {"lr": 1e-3, "beta1": 1.0}, {"lr": 1e-3, "surface_weight": -1.0}, {"lr": 1e-3, "photo_fraction": 1.5}, {"lr": 1e-3, "sph_loss": "huber"}, {"lr": 1e-3, "depth_weight": -0.5}, {"lr": 1e-3, "lr_halflife": -1}, {"lr": 1e-3, "sph_teacher": 1.1}, {"lr": 1e-3, "depth_dropout": -0.1}, {"lr": 1e-3, "depth_dropout": True}, {"lr": 1e-3, "depth_gradient_weight": -1.0}, {"lr": 1e-3, "depth_gradient_weight": float("inf")}, {"lr": 1e-3, "depth_gradient_weight": True}):
        with pytest.raises(ValueError):
            StageRecipe(**bad)
    with pytest.raises(SystemExit):
        main(["refine", "--data", "d", "--out", "o", "--lr", "-1", "--dry-run"])
    # the refiner's input choices belong to the stages that have those inputs
    assert TrainConfig(stage="refine", data="d", out="o", sph_teacher=0.5, depth_dropout=0.5).sph_teacher == 0.5
    assert TrainConfig(stage="joint", data="d", out="o", depth_dropout=0.5).depth_dropout == 0.5
    with pytest.raises(ValueError, match="sph_teacher"):
        TrainConfig(stage="joint", data="d", out="o", sph_teacher=0.5)
    with pytest.raises(ValueError, match="depth_dropout"):
        TrainConfig(stage="inpaint", data="d", out="o", depth_dropout=0.5)
    assert all(s.sph_teacher == 0.0 and s.depth_dropout == 0.0 for r in RECIPES.values() for s in r.stages.values())


def test_a_recipe_grows_the_refiner_of_its_init_weights(tiny_views, tmp_path):
    """A product_full stage started from weights without the full-resolution branch trains with
    it and stores it; the option overrides the recipe and refuses a negative width."""
    from genre_backend.nets.model import GenRe, load_model, save_model
    import torch
    from support.tiny_data import TINY
    from training.learn.train import train

    assert TrainConfig(stage="refine", data="d", out="o", recipe="product_full").refiner_full_nf == 8
    assert TrainConfig(stage="refine", data="d", out="o", recipe="product").refiner_full_nf is None
    assert TrainConfig(stage="refine", data="d", out="o", recipe="product", refiner_full_nf=4).refiner_full_nf == 4
    with pytest.raises(ValueError, match="refiner_full_nf"):
        TrainConfig(stage="refine", data="d", out="o", refiner_full_nf=-1)
    views = tiny_views
    init = save_model(GenRe(TINY), tmp_path / "init.safetensors")
    cfg = TrainConfig(stage="refine", data=str(views), out=str(tmp_path / "run"), recipe="product_full", init=str(init),
                      steps=2, batch_size=2, val_fraction=0.0, augment=False, progress=False, refiner_full_nf=3)
    train(cfg)
    grown = load_model(tmp_path / "run" / "refine" / "final.safetensors")
    assert grown.config.network.refiner_full_nf == 3 and grown.refiner.full is not None
    assert grown.config.geometry.target == "distance"
    # the depth net was frozen and copied: its tensors are the init's
    before = load_model(init)
    for k, v in before.depth_net.state_dict().items():
        assert torch.equal(v, grown.depth_net.state_dict()[k]), k


def test_every_train_option_says_what_it_does(capsys):
    """``genre train --help`` is made from the fields' help texts: every option of a StageRecipe or TrainConfig
    field has one, and the recipe's options say that the recipe gives their default."""
    with pytest.raises(SystemExit):
        main(["joint", "--help"])
    text = " ".join(capsys.readouterr().out.split()).split(" options: ", 1)[1]  # (after the usage lines)
    from training.learn.train import _SPECIAL

    generated = [f.name for f in dataclasses.fields(TrainConfig) if f.name not in _SPECIAL]
    assert "steps" in generated and "seed" in generated and "backgrounds" in generated
    for name in generated:
        flag = "--" + name.replace("_", "-")
        after = text.split(f"{flag} {name.upper()} ", 1)[1]
        entry = re.split(r" --[a-z-]+( [A-Z_]+)? ", after, maxsplit=1)[0]
        assert len(entry) > 12 and not entry.startswith("(default"), (flag, entry)
        assert ("(default: the recipe's)" in entry) == (name in StageRecipe.keys()), (flag, entry)
    assert all(f.metadata.get("help") for f in dataclasses.fields(StageRecipe))


# The runs behind the installed product weights since 2026-12-05 were started with these flags on the product recipe
# (docs/training.md: depth-82-half, refine-83, joint-84; their seeds, snapshots and the depth run's long budget, read
# at step 3,000, left out); the cycle recipe holds them as named data.
CYCLE_FLAGS = {
    "depth": ["--batch-size", "8", "--lr", "3e-5", "--lr-halflife", "3000", "--depth-gradient-weight", "2", "--mirror", "0.5",
              "--weight-decay", "0.5", "--backdrop", "1.0", "--steps", "3000"],
    "refine": ["--batch-size", "8", "--lr", "3e-5", "--lr-halflife", "3000", "--photo-fraction", "0.8", "--backdrop", "1.0",
               "--steps", "2400"],
    "joint": ["--batch-size", "8", "--lr", "3e-5", "--lr-halflife", "3000", "--depth-gradient-weight", "2", "--mirror", "0.5",
              "--photo-fraction", "0.8", "--backdrop", "1.0", "--steps", "8000"],
}


def test_the_cycle_chain_trains_with_the_cycle_runs_flags(tmp_path, capsys):
    from training.chain import CHAINS, Train
    from training.learn.train import parse_args

    home = tmp_path / "home"
    chain = CHAINS["product-cycle"].build("product-cycle", home)
    trains = [s.action for s in chain.steps if isinstance(s.action, Train)]
    assert [t.stage for t in trains] == ["depth", "refine", "joint"]
    resolved = {}
    for t in trains:
        command = t.command()
        # the depth stage in this process's threads; the refine and joint stages data-parallel over two processes
        if t.stage == "depth":
            assert command[:2] == ("genre_backend.cli", "train")
            args = list(command[2:])
        else:
            assert command[:4] == ("torch.distributed.run", "--standalone", "--nproc_per_node=2", "-m")
            assert command[4] == "training.learn.train"
            args = list(command[5:])
        got = dataclasses.asdict(parse_args([*args, "--dry-run"]).config)
        assert "--lr" not in args and "--batch-size" not in args  # the recipe's values, not flags
        flags = _dry_run(capsys, "--recipe", "product", t.stage, "--data", *got["data"], "--out", got["out"],
                         "--init", got["init"], "--backgrounds", got["backgrounds"], "--no-progress",
                         *(("--depth-only", got["depth_only"]) if got["depth_only"] else ()), *CYCLE_FLAGS[t.stage])
        assert got.pop("recipe") == "cycle" and flags.pop("recipe") == "product"
        assert got == flags
        resolved[t.stage] = got
    depth, refine, joint = resolved["depth"], resolved["refine"], resolved["joint"]
    views = home / "views"
    assert depth["data"] == [str(views / "fresh88"), str(views / "fresh88"), str(views / "fresh_prim"), str(views / "thin74")]
    assert depth["init"] == str(REPO / "genre_backend" / "weights" / "default.safetensors")
    assert refine["init"] == str(home / "runs" / "cycle" / "graft" / "depth_grafted.safetensors")
    assert joint["init"] == str(home / "runs" / "cycle" / "refine" / "final.safetensors")
    assert joint["depth_only"] == str(views / "thin74") and joint["data"].count(str(views / "thin74")) == 1
    assert not home.exists()
