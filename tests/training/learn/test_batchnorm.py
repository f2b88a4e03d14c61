"""Batch-norm statistics re-estimated (training/learn/batchnorm.py): each layer's running mean and variance become
the mean over the batches of what its own input had, checked against hooks on an untouched copy of the model."""

from __future__ import annotations

import copy

import pytest
import torch

from genre_backend.nets.model import GenRe, load_model, save_model
from support.tiny_data import TINY
from training.learn.batchnorm import batch_norms, main, refresh_batch_norm, training_batches
from training.learn.stage import StageModule


def _model() -> GenRe:
    torch.manual_seed(0)
    model = GenRe(TINY)
    with torch.no_grad():  # statistics far from what the data give, so that a refresh that skipped a layer shows
        for m in batch_norms(model):
            m.running_mean.uniform_(-3, 3)
            m.running_var.uniform_(5.0, 9.0)
    return model.eval()


def _batches(views, model, count=3):
    return list(training_batches([str(views)], recipe="paper", backgrounds=None, samples=4 * count, batch_size=4,
                                 seed=1, model=model))


def _input_statistics(model: GenRe, batches) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Per layer, the mean over ``batches`` of its input's per-channel mean and unbiased variance (the reference)."""
    model = copy.deepcopy(model)
    norms = batch_norms(model)
    seen: dict[int, list[tuple[torch.Tensor, torch.Tensor]]] = {k: [] for k in range(len(norms))}

    def hook(k):
        def record(_module, inputs):
            x = inputs[0].detach().double().transpose(0, 1).flatten(1)  # (C, everything else)
            seen[k].append((x.mean(dim=1), x.var(dim=1, unbiased=True)))
        return record

    for k, m in enumerate(norms):
        m.register_forward_pre_hook(hook(k))
    stage = StageModule(model, "joint", surface_weight=0.0).train()
    with torch.no_grad():
        for b in batches:
            stage(b)
    return [(torch.stack([s[0] for s in seen[k]]).mean(0), torch.stack([s[1] for s in seen[k]]).mean(0))
            for k in range(len(norms))]


def test_each_layer_takes_the_mean_of_its_inputs_statistics_over_the_batches(tiny_views):
    model = _model()
    batches = _batches(tiny_views, model)
    expect = _input_statistics(model, batches)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    assert refresh_batch_norm(model, batches) == len(batches)
    assert not model.training
    norms = batch_norms(model)
    assert len(norms) == len(expect) > 20  # every net's layers: depth, inpainting, refiner
    for m, (mean, var) in zip(norms, expect):
        assert torch.allclose(m.running_mean.double(), mean, rtol=1e-4, atol=1e-5)
        assert torch.allclose(m.running_var.double(), var, rtol=1e-4, atol=1e-5)
        assert m.momentum == 0.1  # restored
    stats = ("running_mean", "running_var", "num_batches_tracked")
    for name, t in model.state_dict().items():  # nothing else moved
        if not name.endswith(stats):
            assert torch.equal(t, before[name]), name
    assert all(p.requires_grad for p in model.parameters())


def test_no_batches_leave_the_statistics_as_they_were(tiny_views):
    model = _model()
    before = [m.running_mean.clone() for m in batch_norms(model)]
    with pytest.raises(ValueError, match="no batches"):
        refresh_batch_norm(model, [])
    assert all(torch.equal(m.running_mean, b) for m, b in zip(batch_norms(model), before))


def test_the_command_writes_a_file_with_the_new_statistics(tiny_views, tmp_path, capsys):
    src = save_model(_model(), tmp_path / "w.safetensors")
    out = tmp_path / "w_bn.safetensors"
    assert main([str(src), "--data", str(tiny_views), "--recipe", "paper", "--samples", "8", "--batch-size", "4",
                 "--seed", "1", "--out", str(out)]) == 0
    assert "re-estimated on 2 batches of 4" in capsys.readouterr().out
    fresh = _model()
    refresh_batch_norm(fresh, _batches(tiny_views, fresh, count=2))
    written = load_model(out)
    for a, b in zip(batch_norms(written), batch_norms(fresh)):
        assert torch.allclose(a.running_var, b.running_var, rtol=1e-5, atol=1e-6)
    with pytest.raises(SystemExit):
        main([str(src), "--data", str(tiny_views), "--out", str(src)])
    assert main([str(tmp_path / "missing.safetensors"), "--data", str(tiny_views), "--out", str(out)]) == 2
