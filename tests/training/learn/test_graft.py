"""Grafting (training/learn/graft.py): a weights file with another file's depth or inpainting net, checked net by net."""

from __future__ import annotations

import dataclasses as dc

import pytest
import torch

from genre_backend.nets.model import GenRe, load_model, save_model, with_depth_net_of
from genre_backend.weights_file import named_weights, weights_extra
from support.tiny_data import TINY
from training.eval.cli import _shipped_note
from training.learn.graft import main

WIDE_DEPTH = dc.replace(TINY, network=dc.replace(TINY.network, depth_widths=(12, 24, 48, 96), depth_decoder_blocks=1,
                                                 depth_output_scale=5.0))
SETTINGS = dc.replace(TINY, geometry=dc.replace(TINY.geometry, hole_closing=2))  # a mesh setting the base carries


def _model(config, seed: int) -> GenRe:
    torch.manual_seed(seed)
    return GenRe(config).eval()


def _same(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


def test_the_donors_depth_net_with_its_widths_and_the_bases_other_nets_and_settings():
    base, donor = _model(SETTINGS, 1), _model(WIDE_DEPTH, 2)
    new = with_depth_net_of(base, donor)
    assert new.config.network.depth_widths == (12, 24, 48, 96) and new.config.network.depth_output_scale == 5.0
    assert new.config.geometry.hole_closing == 2 and new.config.network.inpaint_widths == TINY.network.inpaint_widths
    assert _same(new.depth_net, donor.depth_net) and _same(new.inpaint_net, base.inpaint_net)
    assert _same(new.refiner, base.refiner) and not _same(new.inpaint_net, donor.inpaint_net)
    rgb = torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():  # the grafted model's depth is the donor's, to the bit
        assert torch.equal(new.eval().depth_net(rgb)["depth"], donor.depth_net(rgb)["depth"])
    other = _model(dc.replace(TINY, geometry=dc.replace(TINY.geometry, image_size=128)), 3)
    with pytest.raises(ValueError, match="cannot move"):
        with_depth_net_of(base, other)


def test_the_command_keeps_the_bases_record_and_names_its_donors(tmp_path, capsys):
    base = save_model(_model(SETTINGS, 1), tmp_path / "base.safetensors", {"source": "run A"})
    depth = save_model(_model(WIDE_DEPTH, 2), tmp_path / "depth.safetensors")
    inpaint = save_model(_model(TINY, 3), tmp_path / "inpaint.safetensors")
    out = tmp_path / "graft.safetensors"
    assert main([str(base), "--depth-from", str(depth), "--inpaint-from", str(inpaint), "--out", str(out),
                 "--storage", "float16"]) == 0
    got, want_depth, want_inpaint, want_base = (load_model(p) for p in (out, depth, inpaint, base))
    for part, source in (("depth_net", want_depth), ("inpaint_net", want_inpaint), ("refiner", want_base)):
        s, w = getattr(got, part).state_dict(), getattr(source, part).state_dict()
        for k, v in s.items():  # float16 storage: within its rounding
            assert torch.allclose(v.float(), w[k].float(), rtol=1e-3, atol=1e-4), (part, k)
    assert got.config.geometry.hole_closing == 2
    extra = weights_extra(out)
    assert extra["source"] == "run A"
    assert extra["grafted"] == {"base": str(base), "depth_net": str(depth), "inpaint_net": str(inpaint)}
    with pytest.raises(SystemExit):  # no donor named: the usage error
        main([str(base), "--out", str(tmp_path / "x.safetensors")])
    with pytest.raises(SystemExit):  # writing over an input
        main([str(base), "--depth-from", str(depth), "--out", str(base)])
    assert main([str(base), "--depth-from", str(tmp_path / "gone.safetensors"), "--out", str(tmp_path / "y.safetensors")]) == 2
    assert "gone.safetensors" in capsys.readouterr().err and not (tmp_path / "y.safetensors").exists()
    # a shipped name is a base too; the product model's pictures are not the tiny net's size
    assert main(["default", "--depth-from", str(depth), "--out", str(tmp_path / "z.safetensors")]) == 2
    assert "cannot move between them" in capsys.readouterr().err


def test_a_grafted_file_keeps_its_shipped_record_but_the_eval_report_does_not_call_it_the_shipped_file(tmp_path):
    base = save_model(_model(SETTINGS, 1), tmp_path / "base.safetensors", {"model": "default"})
    depth = save_model(_model(SETTINGS, 2), tmp_path / "depth.safetensors")
    out = tmp_path / "grafted.safetensors"
    assert main([str(base), "--depth-from", str(depth), "--out", str(out)]) == 0
    assert weights_extra(out)["model"] == "default"  # the record says what it was made from
    assert _shipped_note(out, "default") == " (made from the shipped 'default' weights, not that file)"
    assert _shipped_note(named_weights("default"), "default") == " (the shipped 'default' weights)"
    assert _shipped_note(out, "mine") == " (made from weights installed as 'mine')"
    assert _shipped_note(out, None) == "" and _shipped_note(None, "default") == ""
