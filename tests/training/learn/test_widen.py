"""Widening the depth net (training/learn/widen.py): the wider net predicts what the narrower one did, and trains."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from genre_backend.nets.model import GenRe
from support.tiny_data import TINY
from training.learn.widen import widen_depth_net

# the tiny preset with one basic block after each decoder fusion (as the shipped depth net has)
CONFIG = dataclasses.replace(TINY, network=dataclasses.replace(TINY.network, depth_decoder_blocks=1))


@pytest.fixture(scope="module")
def narrow():
    torch.manual_seed(0)
    model = GenRe(CONFIG)
    # batch-norm statistics and affine parameters away from their defaults, so that copying them is tested too
    with torch.no_grad():
        for m in model.depth_net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.uniform_(0.5, 1.5)
                m.bias.uniform_(-0.2, 0.2)
    return model


@pytest.mark.parametrize("train_mode", [False, True])
def test_the_wider_net_predicts_what_the_narrower_one_did(narrow, train_mode):
    wide = widen_depth_net(narrow, (16, 24, 48, 96), seed=3)
    assert wide.config.network.depth_widths == (16, 24, 48, 96)
    assert sum(p.numel() for p in wide.depth_net.parameters()) > 2 * sum(p.numel() for p in narrow.depth_net.parameters())
    narrow.train(train_mode)
    wide.train(train_mode)
    rgb = torch.rand(3, 3, 64, 64, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        a, b = narrow.depth_net(rgb), wide.depth_net(rgb)
    for head in ("depth", "silhouette_logits"):
        scale = a[head].abs().max().item()
        assert (a[head] - b[head]).abs().max().item() <= 1e-5 * max(scale, 1.0), head
    # the new channels are not dead: the deepest features of the wide encoder differ from zero there
    with torch.no_grad():
        _, deep = wide.depth_net.encoder(rgb)
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
