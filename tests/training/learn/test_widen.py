"""Widening the depth net (training/learn/widen.py): the wider net predicts what the narrower one did, and trains."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from genre_backend.nets.model import GenRe
from support.tiny_data import TINY
from training.learn.widen import widen_depth_net, widen_refiner

# the tiny preset with one basic block after each decoder fusion (as the shipped depth net has)
CONFIG = dataclasses.replace(TINY, network=dataclasses.replace(TINY.network, depth_decoder_blocks=1))


def _model_with_norms_moved(seed: int) -> GenRe:
    """A model whose batch-norm statistics and affine parameters are away from their defaults, so that copying them
    is tested too."""
    torch.manual_seed(seed)
    model = GenRe(CONFIG)
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, (torch.nn.BatchNorm2d, torch.nn.BatchNorm3d)):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.uniform_(0.5, 1.5)
                m.bias.uniform_(-0.2, 0.2)
    return model


def _both_depths(old: GenRe, new: GenRe, train_mode: bool, seed: int) -> tuple[dict, dict]:
    """Both depth nets' outputs on the same random pictures, in train or eval mode."""
    old.train(train_mode)
    new.train(train_mode)
    rgb = torch.rand(3, 3, 64, 64, generator=torch.Generator().manual_seed(seed))
    with torch.no_grad():
        return old.depth_net(rgb), new.depth_net(rgb)


@pytest.fixture(scope="module")
def narrow():
    return _model_with_norms_moved(0)


@pytest.mark.parametrize("train_mode", [False, True])
def test_the_wider_net_predicts_what_the_narrower_one_did(narrow, train_mode):
    wide = widen_depth_net(narrow, (16, 24, 48, 96), seed=3)
    assert wide.config.network.depth_widths == (16, 24, 48, 96)
    assert sum(p.numel() for p in wide.depth_net.parameters()) > 2 * sum(p.numel() for p in narrow.depth_net.parameters())
    a, b = _both_depths(narrow, wide, train_mode, seed=1)
    for head in ("depth", "silhouette_logits"):
        scale = a[head].abs().max().item()
        assert (a[head] - b[head]).abs().max().item() <= 1e-5 * max(scale, 1.0), head
    # the new channels are not dead: the deepest features of the wide encoder differ from zero there
    with torch.no_grad():
        _, deep = wide.depth_net.encoder(torch.rand(3, 3, 64, 64, generator=torch.Generator().manual_seed(1)))
    assert deep[:, 64:].abs().mean() > 1e-3
    narrow.eval()


def test_the_other_nets_are_copied_unchanged(narrow):
    wide = widen_depth_net(narrow, (8, 32, 32, 64))
    old, new = narrow.state_dict(), wide.state_dict()
    others = [k for k in old if not k.startswith("depth_net.")]
    assert others and all(torch.equal(old[k], new[k]) for k in others)


def test_one_step_moves_the_weights_from_new_channels_to_old_ones(narrow):
    wide = widen_depth_net(narrow, (16, 16, 32, 64)).train()
    head = wide.depth_net.decoders["depth"].head[-1]  # the last conv: 1 output from w1/2 inputs, 4 of them old
    assert torch.count_nonzero(head.weight[:, 4:]) == 0
    opt = torch.optim.SGD(wide.depth_net.parameters(), lr=0.1)
    out = wide.depth_net(torch.rand(2, 3, 64, 64))
    out["depth"].pow(2).mean().backward()
    opt.step()
    assert torch.count_nonzero(head.weight[:, 4:]) > 0


def test_narrowing_is_refused(narrow):
    with pytest.raises(ValueError, match="at least"):
        widen_depth_net(narrow, (4, 16, 32, 64))


# the refiner: a 32³ grid has four levels (4, 8, 16, 32 channels in TINY); capped at the deepest one's 32
@pytest.fixture(scope="module")
def narrow_refiner():
    return _model_with_norms_moved(2)


@pytest.mark.parametrize("train_mode", [False, True])
def test_the_wider_refiner_refines_what_the_narrower_one_did(narrow_refiner, train_mode):
    narrow = narrow_refiner
    wide = widen_refiner(narrow, 8, seed=5)
    widths = [d[0].out_channels for d in wide.refiner.down]
    assert widths == [8, 16, 32, 32] and [d[0].out_channels for d in narrow.refiner.down] == [4, 8, 16, 32]
    assert wide.config.network.refiner_nf == 8 and wide.config.network.refiner_max_width == 32
    assert sum(p.numel() for p in wide.refiner.parameters()) > 1.5 * sum(p.numel() for p in narrow.refiner.parameters())
    narrow.train(train_mode)
    wide.train(train_mode)
    grids = (torch.rand(2, 2, 32, 32, 32, generator=torch.Generator().manual_seed(4)) > 0.7).float()
    with torch.no_grad():
        a, b = narrow.refiner(grids), wide.refiner(grids)
        feats = wide.refiner.down[0](grids)
    assert a.shape == b.shape == (2, 1, 32, 32, 32)
    assert (a - b).abs().max().item() <= 1e-5 * max(a.abs().max().item(), 1.0)
    assert feats[:, 4:].abs().mean() > 1e-3  # the new channels compute something
    old, new = narrow.state_dict(), wide.state_dict()
    others = [k for k in old if not k.startswith("refiner.")]
    assert others and all(torch.equal(old[k], new[k]) for k in others)
    assert torch.equal(old["refiner.fc.1.weight"], new["refiner.fc.1.weight"])
    narrow.eval()


def test_narrowing_the_refiner_is_refused(narrow_refiner):
    with pytest.raises(ValueError, match="at least"):
        widen_refiner(narrow_refiner, 2)


def test_a_capped_refiner_keeps_its_cap(narrow_refiner):
    capped = GenRe(dataclasses.replace(CONFIG, network=dataclasses.replace(CONFIG.network, refiner_max_width=16)))
    wide = widen_refiner(capped, 8)
    assert [d[0].out_channels for d in wide.refiner.down] == [8, 16, 16, 16]
    grids = (torch.rand(1, 2, 32, 32, 32, generator=torch.Generator().manual_seed(7)) > 0.7).float()
    with torch.no_grad():
        assert torch.allclose(capped.eval().refiner(grids), wide.eval().refiner(grids), atol=1e-5)


def test_the_command_writes_a_wider_file_that_loads(narrow_refiner, tmp_path):
    from genre_backend.nets.model import load_model, save_model
    from training.learn.widen import main

    src = save_model(narrow_refiner.eval(), tmp_path / "narrow.safetensors", extra={"threshold_from": "a rule"})
    assert main(["--weights", str(src), "--refiner-nf", "6", "--depth-widths", "8", "16", "32", "96",
                 "--out", str(tmp_path / "wide.safetensors")]) == 0
    wide = load_model(tmp_path / "wide.safetensors")
    assert wide.config.network.refiner_nf == 6 and wide.config.network.depth_widths == (8, 16, 32, 96)
    grids = (torch.rand(1, 2, 32, 32, 32, generator=torch.Generator().manual_seed(6)) > 0.7).float()
    with torch.no_grad():
        assert torch.allclose(narrow_refiner.refiner(grids), wide.refiner(grids), atol=1e-5)
    from genre_backend.weights_file import weights_extra
    assert weights_extra(tmp_path / "wide.safetensors")["threshold_from"] == "a rule"
