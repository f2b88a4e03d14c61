"""genre chain: the named training chains as data (training/chain.py): their plans, resuming, refusals."""

from __future__ import annotations

import json
import sys

import pytest

from support.tiny_data import TINY
from training import chain as chains
from training.chain import CHAINS, Chain, ChainFailed, Copy, Run, Step, Train, main, run_chain

_DATA = ["fetch", "build"]
_PROTOCOL_TAIL = ["inpaint", "refine", "joint", "render_eval", "render_eval_unseen", "render_eval_unseen-pix3d", "targets_eval",
                  "completion", "onestep", "eval", "install"]
_PRODUCT_VIEWS = ["backgrounds", "render", "targets", "render_eval", "targets_eval", "render_primitives", "targets_primitives",
                  "render_primitives_eval", "targets_primitives_eval"]
_TRAIN_VIEWS = ["backgrounds", "render_fresh88", "targets_fresh88", "render_fresh_prim", "targets_fresh_prim", "thin",
                "render_thin74", "targets_thin74"]
_START = ["eval_protocol", "eval_primitives_protocol", "eval_start", "eval_primitives_start", "curve_start"]


def _round(n: int) -> list[str]:
    return [f"joint_{n}", f"keep_{n}", f"eval_joint_{n}", f"eval_primitives_joint_{n}", f"curve_joint_{n}"]


def _framed(*views: str) -> list[str]:
    return [step for v in views for step in (f"photo_frame_{v}", f"targets_{v}_pf")]


EXPECTED = {
    "protocol": [*_DATA, "render", "targets", "depth", *_PROTOCOL_TAIL],
    "protocol-photo": [*_DATA, "render", "targets", "backgrounds", "depth", *_PROTOCOL_TAIL],
    "protocol-sharp": [*_DATA, "render", "targets", *_PROTOCOL_TAIL],  # the depth net kept
    "product": [*_DATA, *_PRODUCT_VIEWS, "depth", "inpaint", "refine", *_START, *_round(600), "compare", "compare_primitives"],
    "product-continue": [*_DATA, *_PRODUCT_VIEWS, *_START, *_round(600), *_round(1200), *_round(1800), "compare",
                         "compare_primitives"],
    "product-full": [*_DATA, *_PRODUCT_VIEWS, "refine", *_START, "eval_refine", "eval_primitives_refine", "curve_refine",
                     "compare", "compare_primitives"],
    "eval-views": [*_DATA, "render_eval", "targets_eval", "render_eval_up", "targets_eval_up", "render_primitives_eval",
                   "targets_primitives_eval", "flat_test",
                   "render_flat_eval", "targets_flat_eval",
                   *_framed("product_eval", "product_up", "primitives_eval", "flat_eval")],
    "train-views": [*_DATA, *_TRAIN_VIEWS, *_framed("fresh88", "fresh_prim", "thin74")],
    "product-cycle": [*_DATA, *_TRAIN_VIEWS, "depth", "graft", "refine", "joint"],
}


def _plan(capsys, *argv) -> list[str]:
    assert main([*argv, "--dry-run"]) == 0
    return capsys.readouterr().out.splitlines()


def test_the_named_chains_are_the_expected_ones():
    assert sorted(CHAINS) == sorted(EXPECTED)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_dry_run_prints_each_step_with_what_it_reads_and_writes(name, capsys, monkeypatch, tmp_path):
    monkeypatch.setenv("GENRE_HOME", str(tmp_path / "home"))
    lines = _plan(capsys, name)
    assert [line.split(":", 1)[0] for line in lines] == EXPECTED[name]
    assert all("(reads " in line and "; writes " in line for line in lines)
    assert not any("[done]" in line for line in lines)
    assert not (tmp_path / "home").exists()  # a dry run writes nothing, not even the log folder


def test_rounds_are_cumulative_targets_of_the_recipes_joint_budget(capsys, monkeypatch, tmp_path):
    monkeypatch.setenv("GENRE_HOME", str(tmp_path / "home"))
    lines = {line.split(":", 1)[0]: line for line in _plan(capsys, "product", "--rounds", "3")}
    assert [k for k in lines if k.startswith("joint_")] == ["joint_600", "joint_1200", "joint_1800"]
    assert "--steps 1800" in lines["joint_1800"] and "--product $GENRE_HOME/results/product/joint_1800 " in lines["compare"]
    assert "--weights $GENRE_HOME/runs/product/joint/round_1200.safetensors " in lines["eval_joint_1200"]
    assert not any(k.startswith("joint_") for k in (line.split(":", 1)[0] for line in _plan(capsys, "product", "--rounds", "0")))
    with pytest.raises(SystemExit) as exc:
        main(["protocol", "--rounds", "2", "--dry-run"])
    assert exc.value.code == 2 and "no joint rounds" in capsys.readouterr().err


def test_an_unknown_chain_is_refused_with_the_known_names(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["train_default", "--dry-run"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "unknown chain 'train_default'" in err and all(name in err for name in CHAINS)


def test_the_steps_run_with_this_interpreter_and_no_shell():
    source = chains.__file__ and open(chains.__file__).read()
    assert ".venv" not in source and "bash" not in source and "shell=True" not in source
    chain = CHAINS["product"].build("product", chains.REPO_ROOT / "nowhere")
    for step in chain.steps:
        if isinstance(step.action, (Run, Train)):
            argv = step.action.argv()
            assert argv[:2] == [sys.executable, "-m"] and ".venv" not in " ".join(argv[2:])
            assert argv[2] in ("genre_backend.cli", "training.eval.product", "training.eval.install")


def test_data_parallel_stages_run_torchrun_with_this_interpreter(tmp_path):
    chain = CHAINS["product-cycle"].build("product-cycle", tmp_path)
    trains = {s.name: s.action for s in chain.steps if isinstance(s.action, Train)}
    assert trains["depth"].argv()[:4] == [sys.executable, "-m", "genre_backend.cli", "train"]
    for name in ("refine", "joint"):
        argv = trains[name].argv()
        assert argv[:7] == [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", "-m",
                            "training.learn.train"]
        assert argv[7:9] == ["--recipe", "cycle"] and name in argv
    graft = next(s for s in chain.steps if s.name == "graft")
    depth_final = trains["depth"].out / "depth" / "final.safetensors"
    assert graft.reads[1] == depth_final and graft.action.args[graft.action.args.index("--depth-from") + 1] == str(depth_final)
    assert graft.writes == (trains["refine"].init,) and trains["joint"].init == trains["refine"].out / "refine" / "final.safetensors"
    with pytest.raises(ValueError, match="processes"):
        Train("joint", "cycle", (tmp_path,), tmp_path, processes=0)


def _tiny_chain(views, home, config_json, steps: int) -> Chain:
    """Train the tiny depth net ``steps`` steps, then keep a copy of its weights."""
    run = home / "runs" / "tiny"
    options = ("--model-config", str(config_json), "--batch-size", "2", "--val-fraction", "0", "--no-augment")
    final, kept = run / "depth" / "final.safetensors", run / "kept.safetensors"
    return Chain("tiny", (
        Step("depth", Train("depth", recipe="paper", data=(views,), out=run, steps=steps, options=options), (views,),
             (final, run / "depth" / "summary.json")),
        Step("keep", Copy(final, kept), (final,), (kept,)),
    ))


@pytest.mark.slow
def test_resume_skips_the_finished_steps_and_runs_the_rest(tiny_views, tmp_path, monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    home = tmp_path / "home"
    config_json = tmp_path / "tiny.json"
    config_json.write_text(json.dumps(TINY.to_dict()))
    said = []
    chain = _tiny_chain(tiny_views, home, config_json, steps=2)
    assert run_chain(chain, home, resume=True, say=said.append) == ["depth", "keep"]
    kept = home / "runs" / "tiny" / "kept.safetensors"
    marker = json.loads((home / "chains" / "tiny" / "depth.json").read_text())
    assert marker["command"] == list(chain.steps[0].action.command()) and kept.read_bytes() == (
        home / "runs" / "tiny" / "depth" / "final.safetensors").read_bytes()
    assert all(" [done]:" in line for line in chains.plan_lines(chain, home))
    # everything finished: nothing runs
    assert run_chain(chain, home, resume=True, say=said.append) == []
    assert any("skip (finished): keep" in line for line in said)
    assert "skip (finished): depth" in (home / "logs" / "chain.log").read_text()
    # an output gone: that step runs again
    kept.unlink()
    assert run_chain(chain, home, resume=True, say=said.append) == ["keep"]
    # a step whose command changed (a longer budget) is not finished: it and the steps after it run
    longer = _tiny_chain(tiny_views, home, config_json, steps=3)
    assert run_chain(longer, home, resume=True, say=said.append) == ["depth", "keep"]
    summary = json.loads((home / "runs" / "tiny" / "depth" / "summary.json").read_text())
    assert summary["resumed_from"] == 2 and summary["steps"] == 3  # the stage continued from its checkpoint
    # without --resume every step runs again
    assert run_chain(longer, home, say=said.append) == ["depth", "keep"]


@pytest.mark.slow
def test_a_failing_step_stops_the_chain_without_a_marker(tmp_path):
    home = tmp_path / "home"
    chain = Chain("failing", (Step("bad", Run("training.eval.install", ("--no-such-option",))),
                              Step("after", Copy(tmp_path / "a", tmp_path / "b"))))
    with pytest.raises(ChainFailed) as exc:
        run_chain(chain, home, resume=True, say=lambda _: None)
    assert exc.value.step == "bad" and exc.value.returncode == 2
    assert not (home / "chains" / "failing").exists() and not (tmp_path / "b").exists()
    with pytest.raises(ValueError, match="unique"):
        Chain("twice", (Step("a", Copy(tmp_path / "a", tmp_path / "b")), Step("a", Copy(tmp_path / "a", tmp_path / "c"))))
