"""Weight averaging (training/learn/average.py): the arithmetic mean of the files' tensors, checked tensor by tensor."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from genre_backend.nets.model import GenRe, load_model, save_model
from support.tiny_data import TINY
from training.learn.average import average_models, main


def _model(seed: int) -> GenRe:
    torch.manual_seed(seed)
    model = GenRe(TINY)
    with torch.no_grad():  # batch-norm statistics and step counters away from their defaults, so that they are tested too
        for k, m in enumerate(x for x in model.modules() if isinstance(x, (torch.nn.BatchNorm2d, torch.nn.BatchNorm3d))):
            m.running_mean.uniform_(-1, 1)
            m.running_var.uniform_(0.5, 3.0)
            m.num_batches_tracked.fill_(10 * seed + k)
    return model.eval()


def test_the_average_is_the_weighted_mean_of_each_tensor_and_the_largest_counter():
    a, b, c = _model(1), _model(2), _model(3)
    avg = average_models([a, b, c], [1.0, 1.0, 2.0])  # normalised: 0.25, 0.25, 0.5
    sa, sb, sc, s = a.state_dict(), b.state_dict(), c.state_dict(), avg.state_dict()
    assert s.keys() == sa.keys()
    for name, t in s.items():
        if t.is_floating_point():
            expect = 0.25 * sa[name].double() + 0.25 * sb[name].double() + 0.5 * sc[name].double()
            assert torch.allclose(t.double(), expect, atol=1e-6), name
        else:
            assert int(t) == max(int(sa[name]), int(sb[name]), int(sc[name])), name


def test_a_model_averaged_with_itself_predicts_what_it_did():
    a = _model(4)
    avg = average_models([a, a])
    rgb = torch.rand(2, 3, 64, 64, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        assert torch.allclose(avg.depth_net(rgb)["depth"], a.depth_net(rgb)["depth"], atol=1e-6)


def test_files_of_other_configs_or_bad_weights_are_refused():
    a = _model(1)
    other = GenRe(dataclasses.replace(TINY, network=dataclasses.replace(TINY.network, refiner_nf=2)))
    with pytest.raises(ValueError, match="other nets"):
        average_models([a, other])
    with pytest.raises(ValueError, match="2 weights for 1"):
        average_models([a], [0.5, 0.5])
    with pytest.raises(ValueError, match="non-negative"):
        average_models([a, a], [1.0, -1.0])


def test_the_command_writes_a_file_that_loads(tmp_path, capsys):
    files = []
    for seed in (1, 2):
        files.append(tmp_path / f"s{seed}.safetensors")
        save_model(_model(seed), files[-1], storage="float16" if seed == 2 else "float32")  # a float16 file averages with a float32 one
    out = tmp_path / "avg.safetensors"
    assert main([str(f) for f in files] + ["--out", str(out)]) == 0
    got = load_model(out).state_dict()
    want = average_models([load_model(f) for f in files]).state_dict()
    assert all(torch.equal(got[k], want[k]) for k in want)
    # --out may not overwrite an input (argparse exits)
    with pytest.raises(SystemExit):
        main([str(files[0]), "--out", str(files[0])])
    assert main([str(files[0]), str(tmp_path / "missing.safetensors"), "--out", str(tmp_path / "x.safetensors")]) == 2
    assert "missing" in capsys.readouterr().err
