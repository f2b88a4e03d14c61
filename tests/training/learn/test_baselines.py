"""The baselines of Table 1: their training stages, weights files and the nearest-shape index."""

import dataclasses
import json

import numpy as np
import pytest
import torch

from genre_backend import frame
from genre_backend.nets.model import WeightsError, load_model
from support.tiny_data import TINY, tiny_train_config
from training.learn.baselines import CompletionBaseline, NearestIndex, OneStepNet, build_nearest_index, load_baseline, save_baseline
from training.data.dataset import ViewDataset, find_views
from training.learn.train import train


_cfg = tiny_train_config


@pytest.mark.slow
def test_baseline_stages_overfit_four_samples(tiny_views, tmp_path):
    run = tmp_path / "run"
    train(_cfg("depth", tiny_views, run, steps=10, lr=3e-3), TINY)
    depth_weights = run / "depth" / "final.safetensors"
    s = train(_cfg("completion", tiny_views, run, steps=100, lr=3e-3, init=str(depth_weights)))
    assert s["train_views"] == 4
    assert s["first_loss"] / s["last_loss"] >= 10, s
    s = train(_cfg("onestep", tiny_views, run, steps=60, lr=3e-3), TINY)
    assert s["first_loss"] / s["last_loss"] >= 10, s
    # their own weights files; GenRe's format is untouched and refuses them
    comp = load_baseline(run / "completion" / "best.safetensors", "completion")
    assert isinstance(comp, CompletionBaseline) and comp.config == TINY
    assert isinstance(load_baseline(run / "onestep" / "final.safetensors"), OneStepNet)
    with pytest.raises(WeightsError):
        load_model(run / "completion" / "best.safetensors")
    with pytest.raises(WeightsError):
        load_baseline(run / "onestep" / "final.safetensors", "completion")
    with pytest.raises(WeightsError):
        load_baseline(depth_weights)
    # the completion net's depth net is the frozen one it started from
    genre = load_model(depth_weights)
    for k, v in genre.depth_net.state_dict().items():
        assert torch.equal(v, comp.depth_net.state_dict()[k]), k
    assert json.loads((run / "completion" / "best.json").read_text())["kind"] == "completion"


def test_baseline_stage_resumes_from_its_checkpoint(tiny_views, tmp_path):
    run = tmp_path / "run"
    train(_cfg("onestep", tiny_views, run, steps=2, checkpoint_every=1), TINY)
    s = train(_cfg("onestep", tiny_views, run, steps=4), TINY)
    assert s["resumed_from"] == 2
    # the checkpoint holds the baseline alone, so a change to GenRe's refiner does not stop it resuming
    from safetensors import safe_open

    with safe_open(str(run / "onestep" / "checkpoint" / "state.safetensors"), "pt") as f:
        assert {k.split(".")[0] for k in f.keys()} == {"baseline", "opt"}
    wider = dataclasses.replace(TINY, network=dataclasses.replace(TINY.network, refiner_nf=2 * TINY.network.refiner_nf))
    s = train(_cfg("onestep", tiny_views, run, steps=6), wider)
    assert s["resumed_from"] == 4


def test_save_load_round_trip_gives_the_same_outputs(tmp_path):
    torch.manual_seed(0)
    net = OneStepNet(TINY).eval()
    rgb = torch.rand(2, 3, 64, 64)
    save_baseline(net, tmp_path / "w.safetensors")
    again = load_baseline(tmp_path / "w.safetensors", "onestep")
    with torch.no_grad():
        assert torch.equal(net(rgb), again(rgb))
    assert net(rgb).shape == (2, TINY.geometry.sph_size, TINY.geometry.sph_size)
    with pytest.raises(WeightsError, match="not found"):
        load_baseline(tmp_path / "missing.safetensors")


def test_share_depth_net_gives_the_baseline_genres_depth_net_and_keeps_its_completion_net(tmp_path):
    from genre_backend.nets.model import GenRe, save_model
    from training.learn.baselines import main, share_depth_net

    torch.manual_seed(0)
    baseline = CompletionBaseline(TINY).eval()
    save_baseline(baseline, tmp_path / "completion.safetensors")
    genre = GenRe(TINY).eval()  # another random depth net
    save_model(genre, tmp_path / "genre.safetensors")
    assert main(["share-depth", "--completion", str(tmp_path / "completion.safetensors"), "--weights",
                 str(tmp_path / "genre.safetensors"), "--out", str(tmp_path / "shared.safetensors")]) == 0
    shared = load_baseline(tmp_path / "shared.safetensors", "completion").eval()
    for k, v in genre.depth_net.state_dict().items():
        assert torch.equal(shared.depth_net.state_dict()[k], v), k
    for k, v in baseline.completion.state_dict().items():
        assert torch.equal(shared.completion.state_dict()[k], v), k
    rgb, mask = torch.rand(1, 3, 64, 64), torch.zeros(1, 64, 64, dtype=torch.bool)
    mask[:, 16:48, 16:48] = True
    with torch.no_grad():  # the baseline's pass = GenRe's depth through the old completion net
        depth = genre.depth_net(rgb)["depth"]
        want = baseline.complete(baseline.depth_voxels(torch.where(mask, depth, torch.zeros_like(depth))))
        assert torch.allclose(shared(rgb, mask=mask)["logits"], want, atol=1e-6)
    paper = dataclasses.replace(TINY, geometry=dataclasses.replace(TINY.geometry, voxel_size=TINY.geometry.voxel_size * 2))
    save_model(GenRe(paper), tmp_path / "other.safetensors")
    with pytest.raises(WeightsError, match="preset"):
        share_depth_net(tmp_path / "completion.safetensors", tmp_path / "other.safetensors", tmp_path / "x.safetensors")
    assert main(["share-depth", "--completion", str(tmp_path / "missing.safetensors"), "--weights",
                 str(tmp_path / "genre.safetensors"), "--out", str(tmp_path / "y.safetensors")]) == 2


def test_nearest_index_retrieves_the_view_and_poses_its_shape(tiny_views, tmp_path):
    index = build_nearest_index(tiny_views, TINY)
    assert len(index.views) == 4
    index.save(tmp_path / "nn.safetensors", TINY)
    index = NearestIndex.load(tmp_path / "nn.safetensors")
    refs = find_views(tiny_views)
    data = ViewDataset(refs, TINY)
    for i, ref in enumerate(refs):
        s = data[i]
        j = index.query(s["depth"][None])[0]
        assert (index.shape_id(j), index.views[j]) == (ref.shape_id, ref.view)
        # the retrieved shape posed as it appears in the retrieved view: its view-frame points
        meta = json.loads((ref.shape_dir / f"view_{ref.view:03d}.json").read_text())
        with np.load(ref.shape_dir / "surface_points.npz") as z:
            obj = torch.from_numpy(z["points"]).double()
        expect = frame.object_to_view(obj[None], torch.tensor(meta["rotation_cam_to_obj"], dtype=torch.float64)[None])[0]
        assert torch.allclose(index.view_points(j).double(), expect, atol=1e-6)
