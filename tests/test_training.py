import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from genre_backend.nets.model import GenRe, load_model
from tiny_data import TINY, tiny_train_config
from training.learn.train import StageModule, train, weights_digest

REPO = Path(__file__).resolve().parents[1]


_cfg = tiny_train_config


def test_every_stage_overfits_four_samples(tiny_views, tmp_path):
    run = tmp_path / "run"
    s = train(_cfg("depth", tiny_views, run, steps=60, lr=3e-3), TINY)
    assert s["train_views"] == 4
    assert s["first_loss"] / s["last_loss"] >= 10
    prev = run / "depth" / "final.safetensors"
    for stage, steps, lr in (("inpaint", 80, 1e-3), ("refine", 120, 3e-3)):
        s = train(_cfg(stage, tiny_views, run, steps=steps, lr=lr, init=str(prev)))
        assert s["first_loss"] / s["last_loss"] >= 10, (stage, s)
        prev = run / stage / "final.safetensors"
    # joint fine-tuning from fresh weights, so that there is a loss to bring down
    s = train(_cfg("joint", tiny_views, tmp_path / "joint", steps=100, lr=3e-3), TINY)
    assert s["first_loss"] / s["last_loss"] >= 10
    # each stage leaves its files
    for name in ("best.safetensors", "final.safetensors", "log.csv", "loss.png", "config.json", "summary.json"):
        assert (run / "refine" / name).is_file(), name
    assert load_model(run / "refine" / "best.safetensors").config == TINY


def test_frozen_nets_stay_frozen(tiny_views, tmp_path):
    run = tmp_path / "run"
    train(_cfg("depth", tiny_views, run, steps=3), TINY)
    before = load_model(run / "depth" / "final.safetensors")
    train(_cfg("refine", tiny_views, run, steps=3, init=str(run / "depth" / "final.safetensors")))
    after = load_model(run / "refine" / "final.safetensors")
    assert weights_digest(before.depth_net) == weights_digest(after.depth_net)  # weights and BN statistics
    assert weights_digest(before.refiner) != weights_digest(after.refiner)


def test_gradients_reach_the_depth_net_through_the_projections(tiny_views):
    from training.data.dataset import ViewDataset, find_views

    data = ViewDataset(find_views(tiny_views), TINY)
    batch = {k: torch.stack([data[i][k] for i in range(2)]) for k in data[0]}
    model = GenRe(TINY)
    module = StageModule(model, "joint", 10.0).train()
    out = model(batch["rgb"], mask=batch["mask"])
    loss3d, _ = module.shell_loss(out["logits"], batch)
    loss3d.backward()
    grad = sum(p.grad.abs().sum() for p in model.depth_net.parameters() if p.grad is not None)
    assert grad > 0
    # and through the spherical path alone (depth → partial map → inpainting → full map)
    model.zero_grad()
    out = model(batch["rgb"], mask=batch["mask"])
    out["full_sph"].sum().backward()
    assert sum(p.grad.abs().sum() for p in model.depth_net.parameters() if p.grad is not None) > 0


def _train_cmd(views, out, config_json, steps, extra=()):
    return [sys.executable, "-m", "training.learn.train", "depth", "--data", str(views), "--out", str(out), "--model-config", str(config_json),
            "--steps", str(steps), "--batch-size", "2", "--val-fraction", "0", "--no-progress", "--log-every", "1", *extra]


def _state(path):
    return load_model(path).state_dict()


def test_kill_and_resume_gives_the_same_weights(tiny_views, tmp_path):
    cfg_json = tmp_path / "tiny.json"
    cfg_json.write_text(json.dumps(TINY.to_dict()))
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    # reference: 20 steps in one go
    subprocess.run(_train_cmd(tiny_views, tmp_path / "a", cfg_json, 20), check=True, cwd=REPO, env=env, capture_output=True)
    # interrupted: checkpoint every step, SIGKILL once step 10 is on disk, then run the same command again
    cmd = _train_cmd(tiny_views, tmp_path / "b", cfg_json, 20, ["--checkpoint-every", "1"])
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    state = tmp_path / "b" / "depth" / "checkpoint" / "state.json"
    deadline = time.time() + 300
    while time.time() < deadline:
        try:
            if json.loads(state.read_text())["step"] >= 10:
                break
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    killed_at = json.loads(state.read_text())["step"]
    assert 10 <= killed_at < 20
    done = subprocess.run(cmd, check=True, cwd=REPO, env=env, capture_output=True, text=True)
    summary = json.loads(done.stdout[done.stdout.index("{"):])
    assert summary["resumed_from"] == killed_at
    a, b = _state(tmp_path / "a" / "depth" / "final.safetensors"), _state(tmp_path / "b" / "depth" / "final.safetensors")
    for k in a:
        assert torch.allclose(a[k].float(), b[k].float(), atol=1e-6, rtol=1e-5), k


def test_resuming_with_another_architecture_says_which_checkpoint(tiny_views, tmp_path, capsys):
    import dataclasses

    from training.learn.train import CheckpointMismatch

    run = tmp_path / "run"
    train(_cfg("refine", tiny_views, run, steps=1, checkpoint_every=1), TINY)
    wider = dataclasses.replace(TINY, network=dataclasses.replace(TINY.network, refiner_nf=2 * TINY.network.refiner_nf))
    ck = run / "refine" / "checkpoint"
    with pytest.raises(CheckpointMismatch, match="refine") as err:
        train(_cfg("refine", tiny_views, run, steps=2), wider)
    assert str(ck) in str(err.value) and "delete" in str(err.value)
    assert (ck / "state.json").is_file()  # nothing was overwritten
    # the command line says so in one line and exits 2, no traceback
    from training.learn.train import main

    cfg_json = tmp_path / "wider.json"
    cfg_json.write_text(json.dumps(wider.to_dict()))
    argv = ["refine", "--data", str(tiny_views), "--out", str(run), "--model-config", str(cfg_json), "--steps", "2",
            "--batch-size", "4", "--val-fraction", "0", "--no-augment", "--no-progress"]
    assert main(argv) == 2
    assert f"genre train: error: {ck} was written for a different model" in capsys.readouterr().err


def test_ddp_with_two_cpu_processes(tiny_views, tmp_path):
    cfg_json = tmp_path / "tiny.json"
    cfg_json.write_text(json.dumps(TINY.to_dict()))
    torchrun = Path(sys.executable).with_name("torchrun")
    cmd = [str(torchrun), "--standalone", "--nproc_per_node=2", *_train_cmd(tiny_views, tmp_path / "ddp", cfg_json, 4)[1:]]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    subprocess.run(cmd, check=True, cwd=REPO, env=env, capture_output=True, timeout=300)
    summary = json.loads((tmp_path / "ddp" / "depth" / "summary.json").read_text())
    assert summary["world_size"] == 2
    assert len(set(summary["rank_param_digests"])) == 1  # all-reduced gradients keep parameters equal
    assert len(set(summary["rank_digests"])) == 1
    assert summary["rank_digests"][0] == weights_digest(load_model(tmp_path / "ddp" / "depth" / "final.safetensors"))


def test_validation_shapes_come_from_the_training_split():
    """The corpus puts a seen shape in 'train' when an unsalted hash of its id is
    >= TEST_FRACTION; the validation split must still find ~val_fraction of them."""
    from training.data.corpus import split_of
    from training.data.dataset import ViewRef, split_views

    ids = [f"shape-{i:04d}" for i in range(2000)]
    train_ids = [s for s in ids if split_of(s, "chair") == "train"]
    refs = [ViewRef(Path("/views") / s, v) for s in train_ids for v in range(2)]
    train_refs, val_refs = split_views(refs, 0.05)
    val_ids = {r.shape_id for r in val_refs}
    assert 0.03 < len(val_ids) / len(train_ids) < 0.07
    assert not val_ids & {r.shape_id for r in train_refs}  # by shape: no shape on both sides
    assert len(train_refs) + len(val_refs) == len(refs)
    assert split_views(refs, 0.05) == (train_refs, val_refs)  # deterministic


def test_install_stores_the_seen_test_threshold(tmp_path):
    from genre_backend.nets.model import save_model
    from training.eval.install import install

    src = tmp_path / "w.safetensors"
    model = GenRe(TINY)
    save_model(model, src)
    (tmp_path / "t.json").write_text(json.dumps({"seen": {"GenRe": 0.65, "3D Completion": 0.4}}))
    assert install(src, tmp_path / "t.json", tmp_path / "out" / "d.safetensors") == 0.65
    loaded = load_model(tmp_path / "out" / "d.safetensors")
    assert loaded.config.geometry.default_threshold == 0.65
    assert weights_digest(loaded) == weights_digest(model)  # the weights themselves are unchanged
    (tmp_path / "bad.json").write_text(json.dumps({"seen": {}}))
    with pytest.raises(ValueError, match="no seen-test threshold"):
        install(src, tmp_path / "bad.json", tmp_path / "x.safetensors")
