import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from genre_backend.nets.model import GenRe, load_model, save_model
from support.tiny_data import TINY, tiny_train_config, two_colour_backgrounds
from training.learn.train import StageModule, train, weights_digest

REPO = Path(__file__).resolve().parents[3]


_cfg = tiny_train_config


@pytest.mark.slow
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


@pytest.mark.slow
def test_frozen_nets_stay_frozen(tiny_views, tmp_path):
    run = tmp_path / "run"
    train(_cfg("depth", tiny_views, run, steps=3), TINY)
    before = load_model(run / "depth" / "final.safetensors")
    train(_cfg("refine", tiny_views, run, steps=3, init=str(run / "depth" / "final.safetensors")))
    after = load_model(run / "refine" / "final.safetensors")
    assert weights_digest(before.depth_net) == weights_digest(after.depth_net)  # weights and BN statistics
    assert weights_digest(before.refiner) != weights_digest(after.refiner)


@pytest.mark.slow
def test_a_joint_stage_trains_the_depth_net_at_its_share_of_the_rate(tiny_views, tmp_path):
    run = tmp_path / "run"
    train(_cfg("depth", tiny_views, run, steps=3), TINY)
    init = run / "depth" / "final.safetensors"
    before = load_model(init)
    # 0: the depth net stays as --init gives it (weights and batch-norm statistics); the other two train
    train(_cfg("joint", tiny_views, tmp_path / "frozen", steps=3, init=str(init), depth_lr_scale=0.0, depth_weight=0.0))
    after = load_model(tmp_path / "frozen" / "joint" / "final.safetensors")
    assert weights_digest(before.depth_net) == weights_digest(after.depth_net)
    assert weights_digest(before.inpaint_net) != weights_digest(after.inpaint_net)
    assert weights_digest(before.refiner) != weights_digest(after.refiner)
    # a share: the depth net's group steps at that multiple of each step's rate, and a resumed run keeps it
    train(_cfg("joint", tiny_views, tmp_path / "share", steps=2, init=str(init), lr=1e-3, depth_lr_scale=0.25), TINY)
    train(_cfg("joint", tiny_views, tmp_path / "share", steps=3, init=str(init), lr=1e-3, depth_lr_scale=0.25), TINY)
    groups = json.loads((tmp_path / "share" / "joint" / "checkpoint" / "state.json").read_text())["param_groups"]
    assert [(g["lr"], g["lr_scale"]) for g in groups] == [(1e-3, 1.0), (2.5e-4, 0.25)]
    depth_count = len(list(before.depth_net.parameters()))
    assert len(groups[1]["params"]) == depth_count
    assert len(groups[0]["params"]) == len(list(before.parameters())) - depth_count
    # refused where it cannot apply
    with pytest.raises(ValueError, match="depth_lr_scale"):
        StageModule(GenRe(TINY), "refine", 0.1, depth_lr_scale=0.5)
    with pytest.raises(ValueError, match="depth_weight"):
        StageModule(GenRe(TINY), "joint", 0.1, depth_weight=1.0, depth_lr_scale=0.0)


@pytest.mark.parametrize("fused", [False, True])
def test_weight_decay_shrinks_the_maps_weights_and_leaves_biases_and_scales(fused):
    from training.learn.burst import Speed

    module = StageModule(GenRe(TINY), "depth", 0.1)
    trainable = [p for p in module.parameters() if p.requires_grad]
    assert module.param_groups() == [{"params": trainable}]  # no decay: one group, as before
    groups = module.param_groups(0.5)
    assert sorted(id(p) for g in groups for p in g["params"]) == sorted(map(id, trainable))
    assert {g["weight_decay"] for g in groups} == {0.5, 0.0}
    for g in groups:
        assert g["params"] and all((p.dim() > 1) == (g["weight_decay"] > 0) for p in g["params"])
    # with zero gradients Adam's step is zero, so each weight only decays: a conv's by 1 - lr * 0.5, a bias not at all
    before = [p.detach().clone() for p in trainable]
    opt = Speed(fused_adam=fused).optimiser(groups, lr=0.01, weight_decay=0.5)
    for p in trainable:
        p.grad = torch.zeros_like(p)
    opt.step()
    for p, b in zip(trainable, before):
        torch.testing.assert_close(p.detach(), b * (0.995 if p.dim() > 1 else 1.0), rtol=1e-6, atol=0)


def test_a_checkpoint_of_either_adam_resumes_under_the_other_with_the_same_update(tmp_path):
    """Adam's state written by the loop over tensors (``Speed.fused_adam`` off, as every checkpoint before it was)
    resumes under the fused kernel, and back: the running trainer's choice wins over the saved group's, and the next
    update is the one the writer itself would have made, to float rounding (measured 4e-9 and 1.5e-8 on weights up to 1)."""
    from training.learn.burst import Speed
    from training.learn.checkpoint import _load_optimizer, optimizer_tensors

    def fresh(seed):  # channels-last, as the trainer runs its nets (the checkpoint stores the moments contiguous)
        torch.manual_seed(seed)
        net = torch.nn.Sequential(torch.nn.Conv2d(3, 8, 3), torch.nn.BatchNorm2d(8), torch.nn.Conv2d(8, 2, 1))
        return net.to(memory_format=torch.channels_last)

    def step(net, opt, k):
        opt.zero_grad()
        net(torch.randn(2, 3, 9, 9, generator=torch.Generator().manual_seed(k))).square().mean().backward()
        opt.step()

    for writer, reader in ((False, True), (True, False)):
        net = fresh(0)
        opt = Speed(fused_adam=writer).optimiser(net.parameters(), lr=1e-2, betas=(0.5, 0.9))
        for k in range(3):
            step(net, opt, k)
        tensors, meta = optimizer_tensors(opt)
        tensors = {k: v.clone() for k, v in tensors.items()}  # as state.safetensors holds them (not the live state)
        meta = json.loads(json.dumps(meta))  # as state.json holds it
        weights = {k: v.clone() for k, v in net.state_dict().items()}
        step(net, opt, 3)  # the writer's own next update
        again = fresh(1)
        again.load_state_dict(weights)
        opt2 = Speed(fused_adam=reader).optimiser(again.parameters(), lr=1e-2, betas=(0.5, 0.9))
        _load_optimizer(opt2, tensors, meta)
        assert [g["fused"] for g in opt2.param_groups] == [reader or None]
        step(again, opt2, 3)
        moved = max(float((net.state_dict()[k] - weights[k]).abs().max()) for k in weights if weights[k].is_floating_point())
        assert moved > 1e-3  # the update is not nothing
        for k, v in net.state_dict().items():
            torch.testing.assert_close(again.state_dict()[k], v, rtol=1e-5, atol=1e-6)
        assert int(opt2.state_dict()["state"][0]["step"]) == 4


@pytest.mark.slow
def test_a_stage_with_weight_decay_keeps_it_across_a_resume(tiny_views, tmp_path):
    run = tmp_path / "run"
    train(_cfg("depth", tiny_views, run, steps=2, lr=1e-3, weight_decay=0.5), TINY)
    train(_cfg("depth", tiny_views, run, steps=3, lr=1e-3, weight_decay=0.5), TINY)
    state = json.loads((run / "depth" / "checkpoint" / "state.json").read_text())
    assert state["step"] == 3 and [g["weight_decay"] for g in state["param_groups"]] == [0.5, 0.0]
    assert json.loads((run / "depth" / "config.json").read_text())["train"]["weight_decay"] == 0.5


@pytest.mark.slow
def test_gradients_reach_the_depth_net_through_the_projections(tiny_views):
    from training.data.dataset import ViewDataset, find_views

    data = ViewDataset(find_views(tiny_views), TINY)
    batch = {k: torch.stack([data[i][k] for i in range(2)]) for k in data[0]}
    model = GenRe(TINY)
    module = StageModule(model, "joint", 10.0).train()
    out = model(batch["rgb"], mask=batch["mask"])
    loss3d, _ = module.voxel_loss(out.logits, batch)
    loss3d.backward()
    grad = sum(p.grad.abs().sum() for p in model.depth_net.parameters() if p.grad is not None)
    assert grad > 0
    # and through the spherical path alone (depth → partial map → inpainting → full map)
    model.zero_grad()
    out = model(batch["rgb"], mask=batch["mask"])
    out.full_sph.sum().backward()
    assert sum(p.grad.abs().sum() for p in model.depth_net.parameters() if p.grad is not None) > 0


def test_joint_depth_weight_adds_exactly_the_depth_loss(tiny_views):
    from training.data.dataset import ViewDataset, find_views

    data = ViewDataset(find_views(tiny_views), TINY)
    batch = {k: torch.stack([data[i][k] for i in range(2)]) for k in data[0]}
    model = GenRe(TINY).eval()
    with torch.no_grad():
        plain, _ = StageModule(model, "joint", 0.1, "mse", 0.0).eval()(batch)
        weighted, terms = StageModule(model, "joint", 0.1, "mse", 2.5).eval()(batch)
        own, _ = StageModule(model, "depth", 0.1).eval().depth_loss(model.depth_net(batch["rgb"]), batch)
    assert {"depth_mse", "silhouette_bce"} <= set(terms)
    assert torch.allclose(weighted - plain, 2.5 * own, rtol=1e-5, atol=1e-6)


def test_depth_only_samples_train_the_depth_net_s_own_loss_alone(tiny_views, tmp_path):
    """A joint batch with depth-only samples: their depth loss counts, the map's and the grid's losses are those of
    the other samples alone (each computed independently here), and a batch of depth-only samples still reaches
    every net, with zero gradient outside the depth net."""
    import shutil

    from training.data.dataset import ViewDataset
    from training.data.views import gather_views

    thin = tmp_path / "thin"
    shutil.copytree(tiny_views, thin)
    data = ViewDataset(gather_views([tiny_views, thin]), TINY, depth_only=thin)
    flags = [bool(data[i]["depth_only"]) for i in range(len(data))]
    assert flags == [False] * 4 + [True] * 4  # the second folder's four views
    torch.manual_seed(0)
    model = GenRe(TINY).eval()

    def stack(idx, keys):
        return {k: torch.stack([data[i][k] for i in idx]) for k in keys}

    mixed = stack([0, 5, 2], data[0].keys())
    plain = {k: v for k, v in stack([0, 2], data[0].keys()).items() if k != "depth_only"}
    with torch.no_grad():
        loss, terms = StageModule(model, "joint", 0.1, "mse", 2.0).eval()(mixed)
        others, other_terms = StageModule(model, "joint", 0.1, "mse", 0.0).eval()(plain)
        own, _ = StageModule(model, "depth", 0.1).eval().depth_loss(model.depth_net(mixed["rgb"]), mixed)
    assert torch.allclose(loss, others + 2.0 * own, rtol=1e-5, atol=1e-6)
    assert torch.allclose(terms["voxel_bce"], other_terms["voxel_bce"], rtol=1e-5)
    # every sample depth-only: the depth loss alone, and zero (not missing) gradients for the other nets
    only = stack([4, 5], data[0].keys())
    module = StageModule(model, "joint", 0.1, "mse", 2.0).eval()
    loss, _ = module(only)
    own, _ = module.depth_loss(model.depth_net(only["rgb"]), only)
    assert torch.allclose(loss, 2.0 * own, rtol=1e-5, atol=1e-6)
    loss.backward()
    for net in (model.inpaint_net, model.refiner):
        grads = [p.grad for p in net.parameters()]
        assert all(g is not None for g in grads) and all(float(g.abs().max()) == 0.0 for g in grads)
    assert sum(float(p.grad.abs().sum()) for p in model.depth_net.parameters() if p.grad is not None) > 0


def test_depth_only_is_a_joint_stage_folder_of_data_with_a_depth_loss(tiny_views, tmp_path):
    import shutil

    thin = tmp_path / "thin"
    shutil.copytree(tiny_views, thin)
    for stage in ("depth", "refine"):
        with pytest.raises(ValueError, match="only the joint stage"):
            _cfg(stage, tiny_views, tmp_path / "run", data=[str(tiny_views), str(thin)], depth_only=str(thin))
    with pytest.raises(ValueError, match="not one of the --data folders"):
        _cfg("joint", tiny_views, tmp_path / "run", depth_only=str(thin), depth_weight=1.0)
    with pytest.raises(ValueError, match="depth_weight > 0"):
        _cfg("joint", tiny_views, tmp_path / "run", data=[str(tiny_views), str(thin)], depth_only=str(thin), depth_weight=0.0)
    # a run with them: every view trains, and a folder without targets is refused, not silently dropped
    s = train(_cfg("joint", tiny_views, tmp_path / "run", data=[str(tiny_views), str(thin)], depth_only=str(thin),
                   depth_weight=1.0, steps=2), TINY)
    assert s["train_views"] == 8
    for f in thin.rglob("*_targets.npz"):
        f.unlink()
    with pytest.raises(ValueError, match="no complete training views"):
        train(_cfg("joint", tiny_views, tmp_path / "bare", data=[str(tiny_views), str(thin)], depth_only=str(thin),
                   depth_weight=1.0, steps=1), TINY)


def test_true_map_samples_feed_the_refiner_their_true_map_and_leave_the_map_unscored(tiny_views, tmp_path):
    """A joint batch with true-map samples: the refiner reads their true full map (the grid's loss of such a sample is
    the one made here by hand from the model's parts), the spherical loss is the other samples' counted as a mean over
    all, and a batch of true-map samples reaches the inpainting net with zero gradient, the refiner with some."""
    import shutil

    from training.data.dataset import ViewDataset
    from training.data.views import gather_views

    thin = tmp_path / "thin"
    shutil.copytree(tiny_views, thin)
    data = ViewDataset(gather_views([tiny_views, thin]), TINY, true_map=thin)
    assert [bool(data[i]["true_map"]) for i in range(len(data))] == [False] * 4 + [True] * 4
    assert "depth_only" not in data[0]
    torch.manual_seed(0)
    model = GenRe(TINY).eval()
    module = StageModule(model, "joint", 0.0, "mse", 0.0).eval()  # (the surface term is no mean over samples)

    def stack(idx, drop=()):
        return {k: torch.stack([data[i][k] for i in idx]) for k in data[0].keys() if k not in drop}

    with torch.no_grad():
        one = stack([5])
        depth = model.masked_depth(model.depth_net(one["rgb"])["depth"], one["mask"])
        logits = model.refiner(torch.cat([model.sph_voxels(one["full_sph"]), model.depth_voxels(depth)], dim=1))
        by_hand, _ = module.voxel_loss(logits, one)
        alone, alone_terms = module(one)
        mixed, terms = module(stack([0, 5, 2]))
        plain, plain_terms = module(stack([0, 2], drop=("true_map",)))
        unflagged, _ = module(stack([5], drop=("true_map",)))  # the same view, the net's own map
    assert torch.allclose(alone, by_hand, rtol=1e-5, atol=1e-7)
    assert not torch.allclose(unflagged, by_hand, rtol=1e-3)  # (the true map made a difference)
    map_terms = set(alone_terms) - {"voxel_bce", "surface_bce"}
    assert map_terms and all(float(alone_terms[k]) == 0.0 for k in map_terms)
    assert torch.allclose(3 * mixed, 2 * plain + by_hand, rtol=1e-5, atol=1e-6)
    for name in set(terms) - {"voxel_bce", "surface_bce"}:  # the map's terms: the flagged sample left out
        assert torch.allclose(terms[name], plain_terms[name], rtol=1e-5, atol=1e-7), name
    loss, _ = StageModule(model, "joint", 0.1, "mse", 0.0).eval()(stack([4, 6]))
    loss.backward()
    grads = [p.grad for p in model.inpaint_net.parameters()]
    assert all(g is not None for g in grads) and all(float(g.abs().max()) == 0.0 for g in grads)
    assert sum(float(p.grad.abs().sum()) for p in model.refiner.parameters() if p.grad is not None) > 0


def test_true_map_is_a_joint_stage_folder_of_data_apart_from_the_depth_only_one(tiny_views, tmp_path):
    import shutil

    thin, other = tmp_path / "thin", tmp_path / "other"
    shutil.copytree(tiny_views, thin)
    shutil.copytree(tiny_views, other)
    folders = [str(tiny_views), str(thin), str(other)]
    with pytest.raises(ValueError, match="only the joint stage"):
        _cfg("refine", tiny_views, tmp_path / "run", data=folders, true_map=str(thin))
    with pytest.raises(ValueError, match="not one of the --data folders"):
        _cfg("joint", tiny_views, tmp_path / "run", true_map=str(thin))
    with pytest.raises(ValueError, match="is the depth_only folder"):
        _cfg("joint", tiny_views, tmp_path / "run", data=folders, true_map=str(thin), depth_only=str(thin),
             depth_weight=1.0)
    s = train(_cfg("joint", tiny_views, tmp_path / "run", data=folders, true_map=str(thin), depth_only=str(other),
                   depth_weight=1.0, steps=2), TINY)
    assert s["train_views"] == 12 and s["last_loss"] > 0


def test_weights_that_trim_to_the_map_s_hull_are_trained_trimmed(tiny_views):
    """With ``geometry.sph_hull_carve`` the refine and joint stages score the refiner's logits capped by the hull of
    the map it read (as inference caps its probabilities), and the voxel loss reaches the inpainting net through it."""
    from genre_backend.geometry.spherical import hull_ramp, pad_sph
    from training.data.dataset import ViewDataset, find_views
    from training.learn.stage import hull_trimmed

    data = ViewDataset(find_views(tiny_views), TINY)
    batch = {k: torch.stack([data[i][k] for i in range(2)]) for k in data[0]}
    geometry = dataclasses.replace(TINY.geometry, sph_hull_carve=True, sph_hull_offset=2.0)
    model = GenRe(dataclasses.replace(TINY, geometry=geometry)).eval()
    module = StageModule(model, "joint", 0.1).eval()
    loss, _ = module(batch)
    out = model(batch["rgb"], mask=batch["mask"])
    trimmed = hull_trimmed(out.logits, out.full_sph, geometry)
    want, _ = module.voxel_loss(trimmed, batch)
    parts = model.inpaint_net.forward_parts(pad_sph(out.partial_sph[:, None], geometry.sph_pad))
    assert torch.allclose(loss, want + module.sph_loss(parts, batch)[0], rtol=1e-5)
    ramp = hull_ramp(out.full_sph, geometry)
    assert torch.allclose(torch.sigmoid(trimmed), torch.minimum(torch.sigmoid(out.logits), ramp), atol=2e-4)
    assert bool((ramp < 0.5).any()) and bool((ramp > 0.5).any())  # it trims something and keeps something
    # the voxel loss reaches the map through the trim, not only through the map's voxels
    full = out.full_sph.detach().requires_grad_()
    module.voxel_loss(hull_trimmed(out.logits.detach(), full, geometry), batch)[0].backward()
    assert full.grad is not None and float(full.grad.abs().sum()) > 0


def test_a_wider_trim_gradient_keeps_the_values_and_reaches_deeper_cuts():
    """``hull_grad_width``: the trimmed logits are the same; where a map cuts a ball by 3 voxels and the refiner
    fills the ball beyond the one-voxel ramp, that ramp passes the map no gradient and a 9-voxel one a push
    outward (the loss falls as the radius grows)."""
    from training.learn.stage import hull_trimmed

    geometry = dataclasses.replace(TINY.geometry, sph_hull_carve=True, sph_hull_spread=0, sph_hull_offset=0.0)
    n, size = geometry.voxel_size, TINY.geometry.sph_size
    axis = (torch.arange(n, dtype=torch.float32) + 0.5) / n - 0.5
    rho = torch.sqrt(axis[:, None, None] ** 2 + axis[None, :, None] ** 2 + axis[None, None, :] ** 2)
    truth = (rho <= 0.4).float()[None, None]  # a ball of radius 0.4: its full map's radius
    cut = 0.4 - 3.0 / n  # the map says 3 voxels less
    # the refiner fills only what lies beyond the one-voxel ramp: there the trim decides alone
    logits = torch.where(rho > cut + 1.5 / n, 6.0, -6.0)[None, None]
    grads = {}
    for width in (1.0, 9.0):
        sph = torch.full((1, size, size), 1.0 - cut, requires_grad=True)  # s = 1 - r
        capped = hull_trimmed(logits, sph, geometry, width)
        assert torch.allclose(capped, hull_trimmed(logits, sph.detach(), geometry)), "the values are the trim's"
        torch.nn.functional.binary_cross_entropy_with_logits(capped, truth).backward()
        grads[width] = sph.grad
    assert float(grads[1.0].abs().max()) == 0.0  # those voxels lie beyond the one-voxel ramp
    assert float(grads[9.0].sum()) > 0  # a larger s is a smaller radius: the loss wants the radius up
    assert 1.0 - cut < geometry.sph_nohit_min  # the map hits everywhere


def _depth_gradient_reference(pred, true, valid, strides):
    """depth_gradient_loss written out pixel pair by pixel pair."""
    err = (pred - true).double().numpy()
    ok = valid.numpy()
    per_stride = []
    for s in strides:
        total, count = 0.0, 0
        for b in range(err.shape[0]):
            rows, cols = range(0, err.shape[1], s), range(0, err.shape[2], s)
            for i in rows:
                for j in cols:
                    if not ok[b, i, j]:
                        continue
                    for di, dj in ((0, s), (s, 0)):
                        if i + di < err.shape[1] and j + dj < err.shape[2] and ok[b, i + di, j + dj]:
                            total += abs(err[b, i + di, j + dj] - err[b, i, j])
                            count += 1
        per_stride.append(total / count if count else 0.0)
    return sum(per_stride) / len(per_stride)


def test_depth_gradient_loss_against_its_reference_and_analytic_errors():
    from training.learn.train import depth_gradient_loss

    g = torch.Generator().manual_seed(0)
    pred, true = torch.rand(2, 13, 11, generator=g), torch.rand(2, 13, 11, generator=g)
    valid = torch.rand(2, 13, 11, generator=g) > 0.3
    for strides in ((1,), (1, 2, 4, 8), (3, 5)):
        got = float(depth_gradient_loss(pred, true, valid, strides))
        assert got == pytest.approx(_depth_gradient_reference(pred, true, valid, strides), rel=1e-5)
    # an offset is not a gradient error; a tilted plane error of slope a per pixel, on a full grid, is a·s
    # on each of the stride's horizontal pairs and 0 on its vertical ones
    h, w, a = 16, 16, 0.25
    x = torch.arange(w, dtype=torch.float32).expand(h, w)[None]
    full = torch.ones(1, h, w, dtype=torch.bool)
    assert float(depth_gradient_loss(true[:1, :h, :w].new_full((1, h, w), 0.7) + 3.0, torch.full((1, h, w), 0.7), full)) == 0.0
    tilted = float(depth_gradient_loss(a * x, torch.zeros(1, h, w), full))
    expected = sum(a * s * (h // s) * (w // s - 1) / ((h // s) * (w // s - 1) + (h // s - 1) * (w // s))
                   for s in (1, 2, 4, 8)) / 4
    assert tilted == pytest.approx(expected, rel=1e-6)
    # the pairs are taken inside the valid pixels only: a jump across an invalid column is not seen
    jump = torch.where(x < 8, torch.zeros_like(x), torch.full_like(x, 5.0))
    gap = (x != 7) & (x != 8)
    assert float(depth_gradient_loss(jump, torch.zeros(1, h, w), gap, (1,))) == 0.0
    assert float(depth_gradient_loss(jump, torch.zeros(1, h, w), full, (1,))) > 0.0
    assert float(depth_gradient_loss(pred, true, torch.zeros_like(valid))) == 0.0  # no pair: 0, not NaN
    with pytest.raises(ValueError, match="bool"):
        depth_gradient_loss(pred, true, valid.float())
    with pytest.raises(ValueError, match="true"):
        depth_gradient_loss(pred, true[:, :5], valid)
    with pytest.raises(ValueError, match="strides"):
        depth_gradient_loss(pred, true, valid, (0,))


def test_the_depth_gradient_weight_adds_exactly_its_term(tiny_views):
    from training.data.dataset import ViewDataset, find_views
    from training.learn.train import depth_gradient_loss

    data = ViewDataset(find_views(tiny_views), TINY)
    batch = {k: torch.stack([data[i][k] for i in range(2)]) for k in data[0]}
    model = GenRe(TINY).eval()
    with torch.no_grad():
        out = model.depth_net(batch["rgb"])
        plain, plain_terms = StageModule(model, "depth", 0.1).eval().depth_loss(out, batch)
        weighted, terms = StageModule(model, "depth", 0.1, depth_gradient_weight=3.0).eval().depth_loss(out, batch)
        scale = TINY.network.depth_output_scale
        own = depth_gradient_loss(out["depth"] * scale, batch["depth"] * scale, batch["depth"] > 0)
    assert "depth_gradient_l1" not in plain_terms and float(terms["depth_gradient_l1"]) > 0
    assert torch.allclose(weighted - plain, 3.0 * own, rtol=1e-5, atol=1e-6)


def test_depth_mse_splits_each_views_error_into_its_offset_and_its_relief():
    from training.learn.losses import depth_mse

    g = torch.Generator().manual_seed(3)
    pred, true = torch.rand(3, 9, 7, generator=g), torch.rand(3, 9, 7, generator=g)
    valid = torch.rand(3, 9, 7, generator=g) > 0.4
    valid[2] = False  # a view with nothing valid adds nothing
    plain = float((((pred - true) ** 2) * valid).sum() / valid.sum())
    assert float(depth_mse(pred, true, valid)) == pytest.approx(plain, rel=1e-6)  # weight 1: the plain MSE
    # written out view by view, in float64
    for w in (0.0, 0.1, 2.5):
        total = 0.0
        for b in range(3):
            e = (pred[b] - true[b]).double()[valid[b]]
            if e.numel():
                m = float(e.mean())
                total += float(((e - m) ** 2).sum()) + w * e.numel() * m * m
        assert float(depth_mse(pred, true, valid, w)) == pytest.approx(total / int(valid.sum()), rel=1e-5)
    # an offset per view (plus anything outside the mask) costs nothing at weight 0 and its square at weight 1
    shift = torch.tensor([0.3, -1.2, 7.0]).view(3, 1, 1)
    moved = torch.where(valid, true + shift, true + 50.0)
    assert float(depth_mse(moved, true, valid, 0.0)) == pytest.approx(0.0, abs=1e-6)
    n = valid.sum(dim=(1, 2)).double()
    assert float(depth_mse(moved, true, valid, 1.0)) == pytest.approx(float((n * shift.view(3).double() ** 2).sum() / n.sum()), rel=1e-5)
    assert float(depth_mse(pred, true, torch.zeros_like(valid))) == 0.0  # nothing valid: 0, not NaN
    with pytest.raises(ValueError, match="offset_weight"):
        depth_mse(pred, true, valid, -1.0)


def test_the_depth_offset_weight_reaches_the_depth_stages_loss(tiny_views):
    from training.data.dataset import ViewDataset, find_views
    from training.learn.losses import depth_mse

    data = ViewDataset(find_views(tiny_views), TINY)
    batch = {k: torch.stack([data[i][k] for i in range(2)]) for k in data[0]}
    model = GenRe(TINY).eval()
    scale = TINY.network.depth_output_scale
    terms = {}
    with torch.no_grad():
        out = model.depth_net(batch["rgb"])
        for w in (1.0, 0.1):
            terms[w] = float(StageModule(model, "depth", 0.1, depth_offset_weight=w).eval().depth_loss(out, batch)[1]["depth_mse"])
            own = depth_mse(out["depth"] * scale, batch["depth"] * scale, batch["depth"] > 0, w)
            assert terms[w] == pytest.approx(float(own), rel=1e-6)
        default = float(StageModule(model, "depth", 0.1).eval().depth_loss(out, batch)[1]["depth_mse"])
    assert default == terms[1.0]  # the stage's default weight is 1: the plain MSE
    assert terms[0.1] < terms[1.0]  # an untrained net is off in offset too: weighing it down lowers the term


def test_outline_loss_is_zero_at_the_truth_and_charges_a_part_left_out():
    from genre_backend.config import get_preset
    from training.learn.losses import outline_loss

    camera = get_preset("default").camera
    n = 32
    c = (torch.arange(n, dtype=torch.float32) + 0.5) / n - 0.5
    x, y, z = torch.meshgrid(c, c, c, indexing="ij")
    body = ((x * x + y * y + z * z).sqrt() <= 0.2).float()
    leg = ((x - 0.1).abs() < 0.04) & ((z - 0.1).abs() < 0.04) & (y < -0.1) & (y > -0.4)  # a thin part below
    truth = torch.maximum(body, leg.float())[None]
    logit = lambda p: torch.logit(p.clamp(1e-4, 1 - 1e-4))  # noqa: E731
    at_truth = float(outline_loss(logit(truth)[:, None], truth, camera))
    assert abs(at_truth) < 1e-3
    legless = logit(body[None])[:, None].requires_grad_(True)
    missing = outline_loss(legless, truth, camera)
    missing.backward()
    assert float(missing.detach()) > 100 * max(at_truth, 1e-6)
    # the voxels on the leg's rays are pushed up (a negative gradient), none pushed down there
    grad_leg = legless.grad[0, 0][leg]
    assert float(grad_leg.min()) < 0 and float(grad_leg.max()) <= 0
    # the voxel BCE spreads the same omission over N³ voxels: the outline's share of it is larger
    from training.learn.losses import voxel_loss

    vox, _ = voxel_loss(legless.detach(), truth, 0.0)
    assert float(missing.detach()) > float(vox)


def test_the_outline_weight_adds_exactly_its_term(tiny_views):
    from training.data.dataset import ViewDataset, find_views

    data = ViewDataset(find_views(tiny_views), TINY)
    batch = {k: torch.stack([data[i][k] for i in range(2)]) for k in data[0]}
    model = GenRe(TINY).eval()
    with torch.no_grad():
        plain, plain_terms = StageModule(model, "joint", 0.1).eval()(batch)
        weighted, terms = StageModule(model, "joint", 0.1, outline_weight=2.0).eval()(batch)
    assert "outline_bce" not in plain_terms and float(terms["outline_bce"]) > 0
    assert torch.allclose(weighted - plain, 2.0 * terms["outline_bce"], rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="outline_weight"):
        StageModule(model, "depth", 0.1, outline_weight=1.0)


def test_refiner_input_choices_change_exactly_the_chosen_samples_in_training_only(tiny_views):
    """depth_dropout empties the depth voxels and sph_teacher feeds the true full map, per sample by its coin."""
    from genre_backend.geometry.spherical import crop_sph, pad_sph
    from training.data.dataset import ViewDataset, find_views
    from training.learn.train import StepBatches

    data = ViewDataset(find_views(tiny_views), TINY)
    batches = StepBatches(data, 2, 0, 1, seed=0)
    batch = batches[3]
    assert batch["coin"].shape == (2, 2) and torch.equal(batch["coin"], batches[3]["coin"])  # a function of (seed, step)
    assert not torch.equal(batch["coin"], batches[4]["coin"])
    model = GenRe(TINY).eval()

    def refine_loss(module, vox_sph, vox_depth):
        return module.voxel_loss(model.refine(vox_sph, vox_depth), batch)[0]

    with torch.no_grad():
        depth = model.masked_depth(model.depth_net(batch["rgb"])["depth"], batch["mask"])
        pad = TINY.geometry.sph_pad
        inpainted = crop_sph(model.inpaint_net.forward_parts(pad_sph(model.partial_sph(depth)[:, None], pad))["map"], pad)[:, 0]
        vox_depth, vox_inpainted, vox_true = model.depth_voxels(depth), model.sph_voxels(inpainted), model.sph_voxels(batch["full_sph"])
        batch["coin"] = torch.tensor([[0.1, 0.9], [0.9, 0.1]])  # sample 0 takes the true map, sample 1 loses its depth
        chosen = StageModule(model, "refine", 0.1, sph_teacher=0.5, depth_dropout=0.5)
        chosen.train()
        for m in (model.depth_net, model.inpaint_net, model.refiner):
            m.eval()  # (the refiner's batch norm as in evaluation, so that the two losses compare)
        got = chosen(batch)[0]
        keep = torch.tensor([1.0, 0.0]).view(2, 1, 1, 1, 1)
        want = refine_loss(chosen, torch.cat([vox_true[:1], vox_inpainted[1:]]), vox_depth * keep)
        assert torch.allclose(got, want, rtol=1e-5, atol=1e-6)
        assert not torch.allclose(got, refine_loss(chosen, vox_inpainted, vox_depth), rtol=1e-4)
        chosen.eval()  # validation: every input as it is
        assert torch.allclose(chosen(batch)[0], refine_loss(chosen, vox_inpainted, vox_depth), rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_several_views_folders_and_processor_time_that_accumulates(tiny_views, tmp_path):
    run = tmp_path / "run"
    s = train(_cfg("joint", tiny_views, run, data=[str(tiny_views), str(tiny_views)], steps=3, depth_weight=1.0), TINY)
    assert s["train_views"] == 8  # the same four views from each folder
    assert s["cpu_s"] > 0
    first = json.loads((run / "joint" / "checkpoint" / "state.json").read_text())["cpu_s"]
    assert first > 0
    s2 = train(_cfg("joint", tiny_views, run, steps=6, depth_weight=1.0), TINY)
    assert s2["resumed_from"] == 3 and s2["cpu_s"] > first  # the resumed run adds to the checkpoint's time
    assert json.loads((run / "joint" / "final.json").read_text())["extra"]["cpu_s"] == s2["cpu_s"]


@pytest.mark.slow
def test_snapshots_are_the_weights_of_their_steps_and_average(tiny_views, tmp_path):
    from training.learn.average import average_models

    run = tmp_path / "run"
    train(_cfg("refine", tiny_views, run, steps=4, snapshot_every=2), TINY)
    snaps = sorted((run / "refine" / "snapshots").glob("*.safetensors"))
    assert [p.name for p in snaps] == ["step_0000002.safetensors", "step_0000004.safetensors"]
    last, final = load_model(snaps[-1]), load_model(run / "refine" / "final.safetensors")
    assert weights_digest(last) == weights_digest(final)  # the step-4 snapshot is the final weights
    first = load_model(snaps[0])
    assert weights_digest(first.refiner) != weights_digest(last.refiner)  # two steps moved the refiner
    mid = average_models([first, last])
    a, b, m = first.refiner.state_dict(), last.refiner.state_dict(), mid.refiner.state_dict()
    name = next(k for k in a if a[k].is_floating_point() and not torch.equal(a[k], b[k]))
    assert torch.allclose(m[name], (a[name] + b[name]) / 2, atol=1e-7)


@pytest.mark.slow
def test_a_stage_continued_with_another_learning_rate_trains_with_it(tiny_views, tmp_path):
    run = tmp_path / "run"
    train(_cfg("depth", tiny_views, run, steps=3, lr=1e-3), TINY)
    state = run / "depth" / "checkpoint" / "state.json"
    assert json.loads(state.read_text())["param_groups"][0]["lr"] == 1e-3
    train(_cfg("depth", tiny_views, run, steps=5, lr=2e-5), TINY)
    saved = json.loads(state.read_text())
    assert saved["step"] == 5 and saved["param_groups"][0]["lr"] == 2e-5  # not the checkpoint's 1e-3
    # a half-life: the rate of each step, logged as used
    train(_cfg("depth", tiny_views, tmp_path / "decay", steps=4, lr=1e-3, lr_halflife=2, log_every=1), TINY)
    import csv

    with (tmp_path / "decay" / "depth" / "log.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [float(r["lr"]) for r in rows if r["split"] == "train"] == pytest.approx([1e-3, 1e-3 * 2 ** -0.5, 5e-4, 5e-4 * 2 ** -0.5], rel=1e-5)  # (logged to 6 digits)


@pytest.mark.slow
def test_a_resumed_stage_keeps_the_config_it_was_trained_with(tiny_views, tmp_path):
    """The chain names --init only for a stage's first run: resuming without it keeps the weights' own settings."""
    import dataclasses

    from genre_backend.nets.model import save_model

    tuned = dataclasses.replace(TINY, geometry=dataclasses.replace(TINY.geometry, default_threshold=0.35))
    init = tmp_path / "init.safetensors"
    save_model(GenRe(tuned), init)
    run = tmp_path / "run"
    train(_cfg("refine", tiny_views, run, steps=2, init=str(init)), TINY)
    train(_cfg("refine", tiny_views, run, steps=4), TINY)  # resumed, no --init: a fresh model of the preset, then the checkpoint
    assert load_model(run / "refine" / "final.safetensors").config.geometry.default_threshold == 0.35


def _train_cmd(views, out, config_json, steps, extra=()):
    return [sys.executable, "-m", "training.learn.train", "depth", "--data", str(views), "--out", str(out), "--model-config", str(config_json),
            "--steps", str(steps), "--batch-size", "2", "--val-fraction", "0", "--no-progress", "--log-every", "1", *extra]


def _state(path):
    return load_model(path).state_dict()


def _log_rows(path):
    """log.csv's rows without the timing columns (they differ from run to run)."""
    import csv

    with open(path, newline="") as fh:
        return [{k: v for k, v in row.items() if k not in ("s_per_step", "samples_per_s")} for row in csv.DictReader(fh)]


def _last_logged_step(log_csv) -> int:
    try:
        lines = log_csv.read_text().splitlines()
    except OSError:
        return 0
    steps = [int(line.split(",", 1)[0]) for line in lines[1:] if line.split(",", 1)[0].isdigit()]
    return max(steps, default=0)


def _signal_when_logged(cmd, env, log_csv, step, signum, **popen):
    """Start ``cmd`` and send it ``signum`` once ``log_csv`` has a row for ``step`` (or it ended); the process."""
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, **{"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, **popen})
    deadline = time.time() + 300
    while _last_logged_step(log_csv) < step and proc.poll() is None and time.time() < deadline:
        time.sleep(0.002)
    proc.send_signal(signum)
    return proc


@pytest.mark.slow
def test_kill_between_checkpoints_and_resume_gives_identical_weights_and_log(tiny_views, tmp_path):
    """Depth stage with augmentation and validation (the table's two views; val_fraction 0.5 puts it there),
    checkpoints every 10 of 30 steps, SIGKILL a few steps after the step-10 checkpoint, the same command
    again: bit-identical final and best weights, and log.csv equal to the uninterrupted run's (one row per step)."""
    cfg_json = tmp_path / "tiny.json"
    cfg_json.write_text(json.dumps(TINY.to_dict()))
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    extra = ["--val-fraction", "0.5", "--val-every", "3", "--checkpoint-every", "10"]
    subprocess.run(_train_cmd(tiny_views, tmp_path / "a", cfg_json, 30, extra), check=True, cwd=REPO, env=env, capture_output=True)
    cmd = _train_cmd(tiny_views, tmp_path / "b", cfg_json, 30, extra)
    stage = tmp_path / "b" / "depth"
    _signal_when_logged(cmd, env, stage / "log.csv", 13, signal.SIGKILL).wait()
    killed_at = json.loads((stage / "checkpoint" / "state.json").read_text())["step"]
    logged = _last_logged_step(stage / "log.csv")
    assert killed_at == 10 and 10 < logged < 20, (killed_at, logged)  # between the checkpoints of steps 10 and 20
    done = subprocess.run(cmd, check=True, cwd=REPO, env=env, capture_output=True, text=True)
    summary = json.loads(done.stdout[done.stdout.index("{"):])
    assert summary["resumed_from"] == 10 and summary["val_views"] == 2
    for name in ("final", "best"):
        a, b = _state(tmp_path / "a" / "depth" / f"{name}.safetensors"), _state(stage / f"{name}.safetensors")
        assert a.keys() == b.keys()
        for k in a:
            assert torch.equal(a[k], b[k]), (name, k)
    rows_a, rows_b = _log_rows(tmp_path / "a" / "depth" / "log.csv"), _log_rows(stage / "log.csv")
    keys = [(r["step"], r["split"]) for r in rows_b]
    assert len(keys) == len(set(keys)) == 30 + 10  # a train row per step, a val row every 3 steps
    assert rows_b == rows_a


@pytest.mark.slow
def test_sigterm_checkpoints_the_last_step_and_the_same_command_resumes_it(tiny_views, tmp_path):
    """SIGTERM in the middle of a run (checkpoints only every 100 steps): the process exits with 128 + 15 after
    checkpointing the step it was on, writing no final weights; the same command again finishes with the weights
    and log.csv of an uninterrupted run, nothing trained twice and nothing lost."""
    cfg_json = tmp_path / "tiny.json"
    cfg_json.write_text(json.dumps(TINY.to_dict()))
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    extra = ["--checkpoint-every", "100", "--checkpoint-minutes", "100"]
    subprocess.run(_train_cmd(tiny_views, tmp_path / "a", cfg_json, 200, extra), check=True, cwd=REPO, env=env, capture_output=True)
    cmd = _train_cmd(tiny_views, tmp_path / "b", cfg_json, 200, extra)
    stage = tmp_path / "b" / "depth"
    proc = _signal_when_logged(cmd, env, stage / "log.csv", 5, signal.SIGTERM, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, (proc.returncode, err[-500:])
    stopped_at = json.loads((stage / "checkpoint" / "state.json").read_text())["step"]
    assert 5 <= stopped_at < 200 and stopped_at == _last_logged_step(stage / "log.csv")  # the step it was on, logged
    assert not (stage / "final.safetensors").exists() and f"after step {stopped_at}" in err
    summary = json.loads(out[out.index("{"):])
    assert summary["stopped"] == f"signal {int(signal.SIGTERM)}" and summary["checkpoint_step"] == stopped_at
    done = subprocess.run(cmd, check=True, cwd=REPO, env=env, capture_output=True, text=True)
    assert json.loads(done.stdout[done.stdout.index("{"):])["resumed_from"] == stopped_at
    a, b = _state(tmp_path / "a" / "depth" / "final.safetensors"), _state(stage / "final.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert _log_rows(stage / "log.csv") == _log_rows(tmp_path / "a" / "depth" / "log.csv")


def test_stop_signals_flag_the_first_signal_and_hand_a_second_to_the_old_handler():
    from training.learn.stop import StopSignals

    seen = []
    before = signal.signal(signal.SIGTERM, lambda signum, _frame: seen.append(signum))
    try:
        with StopSignals() as stop:
            assert stop.caught() == 0 and stop.agreed(1) == 0
            signal.raise_signal(signal.SIGTERM)
            assert stop.caught() == signal.SIGTERM and stop.agreed(1) == signal.SIGTERM and seen == []
            signal.raise_signal(signal.SIGTERM)  # a second one: the handler from before the block takes it
            assert seen == [signal.SIGTERM]
        signal.raise_signal(signal.SIGTERM)  # after the block: that handler again
        assert seen == [signal.SIGTERM] * 2
    finally:
        signal.signal(signal.SIGTERM, before)


def test_trim_log_keeps_the_rows_up_to_the_checkpoint(tmp_path):
    from training.learn.logs import LOG_FIELDS, trim_log

    log = tmp_path / "log.csv"
    head = ",".join(LOG_FIELDS) + "\r\n"
    rows = [f'{k},train,0.5,"{{""a"": 1, ""b"": 2}}",0.001,0.1,20.0\r\n' for k in range(1, 8)]
    log.write_text(head + "".join(rows) + "8,train,0.4", newline="")  # the last row cut off by a kill
    assert trim_log(log, 5)
    assert log.read_bytes().decode() == head + "".join(rows[:5])
    assert trim_log(log, 5) and log.read_bytes().decode() == head + "".join(rows[:5])  # nothing to drop: unchanged
    assert not trim_log(tmp_path / "none.csv", 3)
    log.write_text("other,columns\n1,2\n")
    assert not trim_log(log, 3) and log.read_text() == "other,columns\n1,2\n"  # not ours: left alone, a new log begins


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


@pytest.mark.slow
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


@pytest.mark.slow
def test_sigterm_to_torchrun_stops_both_processes_at_one_checkpointed_step(tiny_views, tmp_path):
    """torchrun passes SIGTERM to its two processes; they agree on the step to stop at (neither is left waiting in
    the next step's all-reduce), rank 0 checkpoints it, and the same command resumes from it."""
    cfg_json = tmp_path / "tiny.json"
    cfg_json.write_text(json.dumps(TINY.to_dict()))
    torchrun = Path(sys.executable).with_name("torchrun")

    def ddp(steps):
        return [str(torchrun), "--standalone", "--nproc_per_node=2",
                *_train_cmd(tiny_views, tmp_path / "ddp", cfg_json, steps, ["--checkpoint-minutes", "100"])[1:]]

    cmd = ddp(400)
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    stage = tmp_path / "ddp" / "depth"
    _signal_when_logged(cmd, env, stage / "log.csv", 5, signal.SIGTERM).wait(timeout=120)
    stopped_at = json.loads((stage / "checkpoint" / "state.json").read_text())["step"]
    assert 5 <= stopped_at < 400 and stopped_at == _last_logged_step(stage / "log.csv")
    assert not (stage / "final.safetensors").exists()
    resumed = subprocess.run(ddp(stopped_at + 3), cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, f"the resumed run failed ({resumed.returncode}):\n{resumed.stderr[-3000:]}"
    summary = json.loads((stage / "summary.json").read_text())
    assert summary["resumed_from"] == stopped_at and len(set(summary["rank_param_digests"])) == 1


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


@pytest.mark.slow
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
    # the level itself (the product model keeps that of the weights it started from)
    assert install(src, 0.4, tmp_path / "level.safetensors") == 0.4
    assert load_model(tmp_path / "level.safetensors").config.geometry.default_threshold == 0.4
    # the mesh's hole closing: kept unless given, stored when given, refused out of range
    assert load_model(tmp_path / "level.safetensors").config.geometry.hole_closing == 0
    install(src, 0.4, tmp_path / "closed.safetensors", hole_closing=1)
    closed = load_model(tmp_path / "closed.safetensors")
    assert closed.config.geometry.hole_closing == 1 and weights_digest(closed) == weights_digest(model)
    install(tmp_path / "closed.safetensors", 0.45, tmp_path / "again.safetensors")
    assert load_model(tmp_path / "again.safetensors").config.geometry.hole_closing == 1
    with pytest.raises(ValueError, match="hole_closing"):
        install(src, 0.4, tmp_path / "bad.safetensors", hole_closing=99)
    # float16 storage: half the file, the same config, the weights rounded to float16
    install(src, 0.4, tmp_path / "half.safetensors", storage="float16")
    assert (tmp_path / "half.safetensors").stat().st_size < 0.6 * (tmp_path / "level.safetensors").stat().st_size
    halved = load_model(tmp_path / "half.safetensors")
    assert halved.config == load_model(tmp_path / "level.safetensors").config
    assert weights_digest(halved) != weights_digest(model)
    for k, v in model.state_dict().items():
        rounded = v.half().to(v.dtype) if v.is_floating_point() and not k.endswith(("running_mean", "running_var")) else v
        assert torch.equal(halved.state_dict()[k], rounded), k
    # test-time mirroring: stored, and kept by a later install that does not name it
    assert load_model(tmp_path / "level.safetensors").config.geometry.test_time_mirror is False
    install(src, 0.4, tmp_path / "mirror.safetensors", test_time_mirror=True)
    assert load_model(tmp_path / "mirror.safetensors").config.geometry.test_time_mirror is True
    install(tmp_path / "mirror.safetensors", 0.45, tmp_path / "mirror2.safetensors")
    assert load_model(tmp_path / "mirror2.safetensors").config.geometry.test_time_mirror is True
    # pit sealing: stored for distance-target weights, kept by a later install, refused for the shell target
    import dataclasses

    distance = tmp_path / "distance.safetensors"
    save_model(GenRe(dataclasses.replace(TINY, geometry=dataclasses.replace(TINY.geometry, target="distance"))), distance)
    install(distance, 0.4, tmp_path / "pits.safetensors", pit_sealing=3)
    assert load_model(tmp_path / "pits.safetensors").config.geometry.pit_sealing == 3
    assert _extra(tmp_path / "pits.safetensors")["pit_sealing_from"].startswith("genre eval --sweep")
    install(tmp_path / "pits.safetensors", 0.45, tmp_path / "pits2.safetensors")
    assert load_model(tmp_path / "pits2.safetensors").config.geometry.pit_sealing == 3
    shell = tmp_path / "shell.safetensors"
    save_model(GenRe(dataclasses.replace(TINY, geometry=dataclasses.replace(TINY.geometry, target="shell"))), shell)
    with pytest.raises(ValueError, match="pit_sealing"):
        install(shell, 0.4, tmp_path / "bad_pits.safetensors", pit_sealing=2)
    # any other geometry setting by name, checked by the config
    install(src, 0.4, tmp_path / "keep.safetensors", sph_keep_seen=True)
    assert load_model(tmp_path / "keep.safetensors").config.geometry.sph_keep_seen is True
    assert load_model(src).config.geometry.sph_keep_seen is False
    with pytest.raises(ValueError, match="unknown geometry settings"):
        install(src, 0.4, tmp_path / "bad.safetensors", no_such=1)
    with pytest.raises(ValueError, match="sph_keep_seen"):
        install(src, 0.4, tmp_path / "bad.safetensors", sph_keep_seen=3)


def _extra(path) -> dict:
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as f:
        stored = json.loads((f.metadata() or {}).get("extra", "{}"))
    sidecar = json.loads(path.with_suffix(".json").read_text())["extra"]
    assert stored == sidecar  # the file's metadata and its sidecar say the same
    return stored


def test_install_into_a_named_weights_file(tmp_path, monkeypatch, capsys):
    """--name protocol|default picks genre_backend/weights/NAME.*, tagged extra.model = NAME; installing protocol
    rewrites the interim default while that is still tagged as a copy of protocol, and leaves a real product model alone."""
    import genre_backend.weights_file as gio
    from genre_backend.nets.model import save_model
    from training.eval.install import install, main

    monkeypatch.setattr(gio, "WEIGHTS_DIR", tmp_path / "shipped")
    src = tmp_path / "w.safetensors"
    save_model(GenRe(TINY), src)
    (tmp_path / "t.json").write_text(json.dumps({"seen": {"GenRe": 0.6}, "product": {"GenRe": [0.5, 0.9]}}))
    assert install(src, tmp_path / "t.json", name="default") == 0.5
    assert _extra(tmp_path / "shipped" / "default.safetensors")["model"] == "default"
    with pytest.raises(ValueError, match="unknown weights name 'product'"):
        install(src, tmp_path / "t.json", name="product")
    # the interim default: a copy of protocol, rewritten with it
    save_model(GenRe(TINY), tmp_path / "shipped" / "default.safetensors", {"model": "default", "copy_of": "protocol"})
    assert main(["--weights", str(src), "--thresholds", str(tmp_path / "t.json")]) == 0
    assert "also wrote" in capsys.readouterr().out
    protocol, default = _extra(tmp_path / "shipped" / "protocol.safetensors"), _extra(tmp_path / "shipped" / "default.safetensors")
    assert protocol == {"source": str(src), "threshold_from": str(tmp_path / "t.json"), "model": "protocol"}
    assert default == {**protocol, "model": "default", "copy_of": "protocol"}
    assert weights_digest(load_model(tmp_path / "shipped" / "default.safetensors")) == weights_digest(load_model(src))
    # a real product model is never overwritten by the research chain
    assert main(["--weights", str(src), "--thresholds", str(tmp_path / "t.json"), "--name", "default"]) == 0
    before = (tmp_path / "shipped" / "default.safetensors").read_bytes()
    assert main(["--weights", str(src), "--thresholds", str(tmp_path / "t.json")]) == 0
    assert "also wrote" not in capsys.readouterr().out
    assert (tmp_path / "shipped" / "default.safetensors").read_bytes() == before
    assert _extra(tmp_path / "shipped" / "default.safetensors")["model"] == "default"


@pytest.mark.slow
def test_the_hit_head_is_trained_fresh_at_the_inpaint_stage_and_refused_elsewhere(tiny_views, tmp_path):
    """--inpaint-head hit on weights with the paper's head: the inpaint stage starts a fresh
    inpainting net (the depth net kept) and fits four samples (hit BCE + radius MSE fall ≥ 5×; 15× measured);
    a later stage on the new weights keeps the head; another stage asked for a head change refuses."""
    from genre_backend.nets.model import save_model

    init = save_model(GenRe(TINY), tmp_path / "init.safetensors")
    run = tmp_path / "run"
    s = train(_cfg("inpaint", tiny_views, run, steps=150, lr=1e-3, init=str(init), inpaint_head="hit"))
    assert s["first_loss"] / s["last_loss"] >= 5, s
    trained = load_model(run / "inpaint" / "final.safetensors")
    assert trained.config.network.inpaint_head == "hit"
    assert weights_digest(trained.depth_net) == weights_digest(load_model(init).depth_net)
    train(_cfg("refine", tiny_views, run, steps=2, init=str(run / "inpaint" / "final.safetensors")))
    assert load_model(run / "refine" / "final.safetensors").config.network.inpaint_head == "hit"
    train(_cfg("joint", tiny_views, run, steps=2, log_every=1, init=str(run / "refine" / "final.safetensors")))
    import csv

    with (run / "joint" / "log.csv").open(newline="") as fh:
        terms = json.loads(list(csv.DictReader(fh))[-1]["terms"])
    assert {"sph_hit_bce", "sph_radius_mse", "voxel_bce"} <= set(terms), terms
    with pytest.raises(ValueError, match="train the inpaint stage first"):
        train(_cfg("refine", tiny_views, tmp_path / "other", steps=2, init=str(init), inpaint_head="hit"))


@pytest.mark.slow
def test_a_wider_inpainting_net_is_trained_fresh_at_the_inpaint_stage_and_refused_elsewhere(tiny_views, tmp_path):
    """--inpaint-widths: the inpaint stage starts a fresh inpainting net of those widths (the depth net and the
    refiner kept) and fits four samples; the next stage keeps it; another stage asked for new widths refuses;
    a malformed value is refused up front."""
    init = save_model(GenRe(TINY), tmp_path / "init.safetensors")
    run = tmp_path / "run"
    s = train(_cfg("inpaint", tiny_views, run, steps=80, lr=1e-3, init=str(init), inpaint_widths="16,32,64,128"))
    assert s["first_loss"] / s["last_loss"] >= 5, s
    trained = load_model(run / "inpaint" / "final.safetensors")
    assert trained.config.network.inpaint_widths == (16, 32, 64, 128)
    assert weights_digest(trained.depth_net) == weights_digest(load_model(init).depth_net)
    assert weights_digest(trained.refiner) == weights_digest(load_model(init).refiner)
    train(_cfg("refine", tiny_views, run, steps=2, init=str(run / "inpaint" / "final.safetensors")))
    assert load_model(run / "refine" / "final.safetensors").config.network.inpaint_widths == (16, 32, 64, 128)
    with pytest.raises(ValueError, match="train the inpaint stage first"):
        train(_cfg("refine", tiny_views, tmp_path / "other", steps=2, init=str(init), inpaint_widths=(16, 32, 64, 128)))
    for bad in ("16,32,64", "16,32,x,128", "0,32,64,128"):
        with pytest.raises(ValueError, match="inpaint_widths"):
            _cfg("inpaint", tiny_views, tmp_path / "bad", inpaint_widths=bad)


def test_inpaint_from_puts_another_runs_inpainting_net_under_the_init_weights(tiny_views, tmp_path):
    """--inpaint-from: the refine stage starts from --init's depth net and refiner with the donor's inpainting
    net, which it keeps frozen; a missing donor file is refused by the command line."""
    from genre_backend.nets.model import with_inpaint_net

    torch.manual_seed(1)
    init = save_model(GenRe(TINY), tmp_path / "init.safetensors")
    donor = save_model(with_inpaint_net(GenRe(TINY), head="hit", widths=(16, 32, 64, 128)), tmp_path / "donor.safetensors")
    run = tmp_path / "run"
    train(_cfg("refine", tiny_views, run, steps=3, init=str(init), inpaint_from=str(donor)))
    out = load_model(run / "refine" / "final.safetensors")
    assert out.config.network.inpaint_head == "hit" and out.config.network.inpaint_widths == (16, 32, 64, 128)
    assert weights_digest(out.inpaint_net) == weights_digest(load_model(donor).inpaint_net)
    assert weights_digest(out.depth_net) == weights_digest(load_model(init).depth_net)
    assert weights_digest(out.refiner) != weights_digest(load_model(init).refiner)  # the stage trained it
    from training.learn.train import main as train_main

    with pytest.raises(SystemExit):
        train_main(["refine", "--data", str(tiny_views), "--out", str(tmp_path / "x"), "--init", str(init),
                    "--inpaint-from", str(tmp_path / "missing.safetensors")])


@pytest.mark.slow
def test_photo_compositing_applies_to_the_stage_that_asks_for_it(tiny_views, tmp_path):
    """--photo-fraction on the refine stage shows the frozen depth net composited images (it was once ignored there)."""
    folder = two_colour_backgrounds(tmp_path / "bg")
    init = save_model(GenRe(TINY), tmp_path / "init.safetensors")
    digests = {}
    for photo in (0.0, 1.0):
        run = tmp_path / f"photo_{photo}"
        s = train(_cfg("refine", tiny_views, run, steps=3, init=str(init), augment=True, photo_fraction=photo,
                       backgrounds=str(folder)))
        assert s["photo_fraction"] == photo
        digests[photo] = weights_digest(load_model(run / "refine" / "final.safetensors").refiner)
    assert digests[0.0] != digests[1.0]
    with pytest.raises(ValueError, match="needs --backgrounds"):
        train(_cfg("refine", tiny_views, tmp_path / "nobg", steps=1, init=str(init), augment=True, photo_fraction=0.5))


def test_a_folder_named_twice_is_drawn_twice_and_a_shape_stays_on_one_side_of_the_split(tiny_views, tmp_path):
    import shutil

    from training.data.dataset import _unit_hash, find_views, split_views
    from training.data.views import gather_views

    one = find_views(tiny_views)
    shapes = sorted({r.shape_id for r in one})
    assert len(shapes) == 2
    # a second folder with the first shape's renders again (as views/default repeats views/product's seen shapes)
    other = tmp_path / "other"
    shutil.copytree(tiny_views / shapes[0], other / shapes[0])
    extra = find_views(other)
    assert len(extra) == sum(r.shape_id == shapes[0] for r in one) > 0
    refs = gather_views([tiny_views, other, other])
    assert len(refs) == len(one) + 2 * len(extra)
    assert sum(r.shape_dir.parent == other for r in refs) == 2 * len(extra)
    # a validation share that takes exactly one of the two shapes, whichever hashes lower
    hashes = {s: _unit_hash("validation:" + s) for s in shapes}
    low = min(hashes, key=hashes.get)
    train_refs, val_refs = split_views(refs, (hashes[low] + max(hashes.values())) / 2)
    assert {r.shape_id for r in val_refs} == {low} and low not in {r.shape_id for r in train_refs}
    assert len(train_refs) + len(val_refs) == len(refs)
    with pytest.raises(ValueError, match="no view folders"):
        gather_views([])


@pytest.mark.parametrize("way", ["channels-last", "channels-last+bf16"])
def test_the_stage_trainer_runs_the_cpu_fast_path_and_matches_the_plain_one(tiny_views, tmp_path, monkeypatch, way):
    """genre train's nets run as --speed says (auto: Speed.for_device; on the CPU every net channels-last, with bf16
    autocast where oneDNN runs bf16 natively); the joint stage's loss matches the plain fp32 contiguous path's at
    the first step (the same weights: other kernels, other rounding; within 1e-3, 1e-2 under bf16) and over the next
    five within 8 % at each step and 4 % on average.  Adam's first steps amplify the rounding of small gradients
    (each weight moves by about the learning rate whatever its gradient's size), so the trajectories wander: the
    plain path alone, with its last refiner layer computed two float-equivalent ways (torch's and by phases),
    drifted apart by up to 2.3 % here; under bf16 the fast path was 5.8 % off at one step, 2.5 % on average."""
    from training.learn import burst

    seen = {}

    def joint(name, speed):
        real = burst.apply_speed

        def spy(model, sp):
            out = real(model, sp)
            conv3d = next(m for m in model.refiner.modules() if isinstance(m, torch.nn.Conv3d))
            conv2d = next(m for m in model.depth_net.modules() if isinstance(m, torch.nn.Conv2d))
            seen[name] = (conv3d.weight.is_contiguous(memory_format=torch.channels_last_3d) and not conv3d.weight.is_contiguous(),
                          conv2d.weight.is_contiguous(memory_format=torch.channels_last) and not conv2d.weight.is_contiguous())
            return out

        monkeypatch.setattr("training.learn.loop.apply_speed", spy)
        run = tmp_path / name
        train(_cfg("joint", tiny_views, run, steps=6, lr=1e-3, log_every=1, speed=speed), TINY)
        assert json.loads((run / "joint" / "config.json").read_text())["speed"] == dataclasses.asdict(
            burst.Speed.from_way(speed))
        return _log_rows(run / "joint" / "log.csv")

    plain_rows = joint("plain", "fp32")
    fast_rows = joint("fast", way)
    assert seen == {"plain": (False, False), "fast": (True, True)}
    assert [r["step"] for r in fast_rows] == [r["step"] for r in plain_rows] and len(plain_rows) == 6
    plain, fast = [float(r["loss"]) for r in plain_rows], [float(r["loss"]) for r in fast_rows]
    assert fast[0] == pytest.approx(plain[0], rel=1e-2 if "bf16" in way else 1e-3)
    for a, b in zip(plain, fast):
        assert b == pytest.approx(a, rel=0.08), (plain, fast)
    assert sum(fast) / len(fast) == pytest.approx(sum(plain) / len(plain), rel=0.04), (plain, fast)


def test_the_cpu_speed_record_follows_the_processor():
    """auto on the CPU: every net channels-last; bf16 autocast exactly where oneDNN runs bf16 natively (genre bench
    train measured it faster there, and 3-4x slower where it is emulated: docs/lab/benchmarks.md)."""
    from training.learn import burst

    cpu = burst.Speed.for_device(torch.device("cpu"))
    native = torch.ops.mkldnn._is_mkldnn_bf16_supported()
    assert cpu == burst.Speed.from_way("channels-last+bf16" if native else "channels-last")
    assert cpu.depth_channels_last and cpu.inpaint_channels_last and cpu.refiner_channels_last
    assert burst.Speed.from_way("fp32") == burst.REFERENCE_SPEED
    with pytest.raises(ValueError, match="speed"):
        _cfg("joint", "views", "out", speed="fast")
