"""The shipped weights: two named files (`default`, the product model; `protocol`, the research weights), found by name.

docs/reconstruct.md, "Which weights": `protocol` is trained on the seen classes only and behind every Table-1 number;
`default` is what users get (make demo, the add-on), the product model trained on every class
(genre chain product), at the level of the weights it started from (results/decisions.md).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from genre_backend.weights_file import WEIGHTS_DIR, WEIGHTS_NAMES, WeightsError, named_weights, resolve_weights, weights_extra

REPO = Path(__file__).resolve().parents[2]
MAX_SHIPPED_BYTES = 40_000_000  # both safetensors together (the repository stays small enough to clone)


def test_the_shipped_weights_are_two_named_files_within_the_size_budget():
    files = sorted(p.name for p in WEIGHTS_DIR.glob("*.safetensors"))
    assert files == ["default.safetensors", "protocol.safetensors"]
    total = sum((WEIGHTS_DIR / f).stat().st_size for f in files)
    assert total <= MAX_SHIPPED_BYTES, f"shipped weights take {total / 1e6:.1f} MB, the budget is {MAX_SHIPPED_BYTES / 1e6:.0f} MB"


@pytest.mark.parametrize("name", sorted(WEIGHTS_NAMES))
def test_each_shipped_file_loads_and_says_which_model_it_is(name):
    from genre_backend.nets.model import load_model

    path = named_weights(name)
    model = load_model(path)
    assert model.config.preset == "default"
    assert weights_extra(path)["model"] == name  # the file's own metadata…
    sidecar = json.loads(path.with_suffix(".json").read_text())
    assert sidecar["extra"]["model"] == name  # …and the readable sidecar
    # …and the same config (keys added since, such as geometry.hole_closing, read as their defaults)
    from genre_backend.config import GenreConfig

    assert GenreConfig.from_dict(sidecar["config"]) == model.config


def test_default_is_the_trained_product_model_at_the_protocols_level():
    """`default` is no longer the interim copy of `protocol`: the same depth net and refiner architecture, trained
    on (every tensor differs), with its own inpainting net (since the fourteenth run twice as wide, the hit head
    like `protocol`'s) and, since the thirty-seventh session (R68), a depth net twice as wide, at the same level."""
    import dataclasses

    import torch

    from genre_backend.nets.model import load_model

    extra = weights_extra(named_weights("default"))
    assert "copy_of" not in extra and extra["model"] == "default"
    a, b = load_model(named_weights("default")), load_model(named_weights("protocol"))
    assert (a.config.network.inpaint_head, b.config.network.inpaint_head) == ("hit", "hit")
    assert tuple(a.config.network.inpaint_widths) == (32, 64, 128, 256)
    assert tuple(b.config.network.inpaint_widths) == (16, 32, 64, 128)
    assert tuple(a.config.network.depth_widths) == (32, 64, 128, 256)
    assert tuple(b.config.network.depth_widths) == (16, 32, 64, 128)
    wider = ("inpaint_widths", "inpaint_decoder_blocks", "depth_widths")
    assert dataclasses.replace(a.config.network, **{k: getattr(b.config.network, k) for k in wider}) == b.config.network
    assert a.config.geometry.default_threshold == b.config.geometry.default_threshold
    for part in ("refiner",):
        sa, sb = getattr(a, part).state_dict(), getattr(b, part).state_dict()
        assert sa.keys() == sb.keys()
        floats = [k for k in sa if sa[k].is_floating_point()]
        changed = sum(not torch.equal(sa[k], sb[k]) for k in floats)
        assert changed > 0.9 * len(floats), part  # every net was trained on


def test_weights_resolve_by_name_or_path(tmp_path, monkeypatch):
    assert resolve_weights(None) == resolve_weights("") == WEIGHTS_DIR / "default.safetensors"
    assert resolve_weights("protocol") == WEIGHTS_DIR / "protocol.safetensors"
    assert resolve_weights("default") == named_weights("default")
    assert resolve_weights(str(tmp_path / "w.safetensors")) == tmp_path / "w.safetensors"  # a path, even a missing one
    assert resolve_weights("w.safetensors") == Path("w.safetensors")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "mymodel").write_bytes(b"")
    assert resolve_weights("mymodel") == Path("mymodel")  # an existing file of any name
    assert resolve_weights("./protocol") == Path("protocol")  # a file called like a name: through ./
    with pytest.raises(WeightsError, match=r"unknown weights 'product'.*default, protocol"):
        resolve_weights("product")
    with pytest.raises(ValueError, match="choose default or protocol"):
        named_weights("product")


def test_reconstruct_and_serve_name_the_choices_for_an_unknown_name(capsys):
    from genre_backend.frontends import reconstruct_cli, server

    assert reconstruct_cli.main([str(REPO / "examples" / "sofa.png"), "--weights", "product"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown weights 'product'" in err[0] and "default, protocol" in err[0] and "[bad_weights]" in err[0]
    assert server.main(["--weights", "product"]) == 1
    event = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert event["type"] == "error" and event["code"] == "bad_weights" and "default, protocol" in event["message"]


def test_serve_loads_the_protocol_weights_by_name():
    """`genre serve --weights protocol`: ready names the shipped protocol file."""
    import os
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "genre_backend.cli", "serve", "--weights", "protocol"], input='{"type": "shutdown"}\n',
                          capture_output=True, text=True, cwd=REPO, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr
    ready = json.loads(proc.stdout.splitlines()[0])
    assert ready["type"] == "ready" and ready["weights"] == str(WEIGHTS_DIR / "protocol.safetensors")
    assert ready["threshold"] == json.loads((WEIGHTS_DIR / "protocol.json").read_text())["config"]["geometry"]["default_threshold"]
