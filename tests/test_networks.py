import pytest
import torch

from genre_backend.config import get_preset
from genre_backend.nets.depth_net import DepthNet
from genre_backend.nets.inpaint_net import InpaintNet
from genre_backend.nets.model import GenRe, WeightsError, load_model, save_model
from genre_backend.nets.refiner import VoxelRefiner
from genre_backend.nets.uresnet import count_parameters


def test_paper_parameter_counts_match_the_original():
    cfg = get_preset("paper")
    counts = {
        "depth": count_parameters(DepthNet(cfg)),
        "inpaint": count_parameters(InpaintNet(cfg)),
        "refiner": count_parameters(VoxelRefiner(128, cfg.network.refiner_nf, cfg.network.refiner_fc)),
    }
    for name, original in (("depth", 30.8e6), ("inpaint", 15.9e6), ("refiner", 53.5e6)):
        assert abs(counts[name] / original - 1) < 0.05, (name, counts[name])


@torch.no_grad()
def test_paper_nets_run_on_batch_one():
    cfg = get_preset("paper")
    g = cfg.geometry
    out = DepthNet(cfg).eval()(torch.rand(1, 3, 256, 256))
    assert out["depth"].shape == (1, 256, 256) and out["silhouette_logits"].shape == (1, 256, 256)
    full = InpaintNet(cfg).eval()(torch.ones(1, g.sph_size, g.sph_size))
    assert full.shape == (1, 128, 128)
    logits = VoxelRefiner(128, cfg.network.refiner_nf, cfg.network.refiner_fc).eval()(torch.zeros(1, 2, 128, 128, 128))
    assert logits.shape == (1, 1, 128, 128, 128)
    assert torch.isfinite(logits).all()


@torch.no_grad()
def test_refiner_sees_its_input_at_full_resolution():
    """With the coarse trunk silenced, the logits are the skip alone: at initialisation a
    3×3×3 box sum of both input grids × SKIP_INIT, voxel for voxel (held to a plain loop)."""
    import numpy as np

    from genre_backend.nets.refiner import SKIP_INIT

    n = 16
    net = VoxelRefiner(n, 4, 16).eval()
    torch.nn.init.zeros_(net.out.weight)
    torch.nn.init.zeros_(net.out.bias)  # (initialised at OUT_BIAS_INIT)
    x = torch.zeros(1, 2, n, n, n)
    gen = torch.Generator().manual_seed(0)
    hits = torch.randint(0, n, (12, 4), generator=gen)
    for c, i, j, k in hits.tolist():
        x[0, c % 2, i, j, k] = 0.3 + 0.05 * (i % 5)
    logits = net(x)[0, 0].numpy()
    grid = x[0].sum(0).numpy()
    pad = np.pad(grid, 1)
    ref = np.zeros_like(grid)
    for i in range(n):
        for j in range(n):
            for k in range(n):
                ref[i, j, k] = SKIP_INIT * pad[i:i + 3, j:j + 3, k:k + 3].sum()
    np.testing.assert_allclose(logits, ref, atol=1e-5)
    assert (logits > 0).sum() >= 27  # one isolated hit already lights its whole neighbourhood


@torch.no_grad()
def test_default_model_shapes():
    cfg = get_preset("default")
    g = cfg.geometry
    out = GenRe(cfg).eval()(torch.rand(2, 3, g.image_size, g.image_size))
    assert out["depth"].shape == (2, 128, 128)
    assert out["partial_sph"].shape == out["full_sph"].shape == (2, 64, 64)
    assert out["vox_sph"].shape == out["vox_depth"].shape == out["logits"].shape == (2, 1, 64, 64, 64)
    assert out["mask"].dtype == torch.bool


def test_oracle_inputs_replace_network_outputs():
    cfg = get_preset("default")
    model = GenRe(cfg).eval()
    g = cfg.geometry
    depth = torch.full((1, g.image_size, g.image_size), 2.0)
    mask = torch.zeros(1, g.image_size, g.image_size, dtype=torch.bool)
    mask[:, 40:80, 40:80] = True
    full = torch.full((1, g.sph_size, g.sph_size), 0.7)
    with torch.no_grad():
        out = model(torch.rand(1, 3, g.image_size, g.image_size), mask=mask, depth=depth, full_sph=full)
    assert torch.equal(out["full_sph"], full)
    assert torch.equal(out["masked_depth"][0, 40:80, 40:80], depth[0, 40:80, 40:80])
    assert (out["masked_depth"][~mask] == 0).all()


def test_weights_round_trip_and_bad_files(tmp_path):
    cfg = get_preset("default")
    model = GenRe(cfg)
    path = save_model(model, tmp_path / "w.safetensors", {"note": "test"})
    assert path.with_suffix(".json").is_file()
    loaded = load_model(path)
    assert loaded.config == cfg
    for (k, a), (_, b) in zip(sorted(model.state_dict().items()), sorted(loaded.state_dict().items())):
        assert torch.equal(a, b), k
    with pytest.raises(WeightsError, match="not found"):
        load_model(tmp_path / "missing.safetensors")
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(path.read_bytes()[:1000])
    with pytest.raises(WeightsError, match="not a readable"):
        load_model(bad)
    from safetensors.torch import save_file

    other = tmp_path / "other.safetensors"
    save_file({"x": torch.zeros(2)}, str(other), metadata={"format": "genre-weights/0"})
    with pytest.raises(WeightsError, match="format"):
        load_model(other)
