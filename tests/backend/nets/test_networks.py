import math

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
    assert out.depth.shape == (2, 128, 128)
    assert out.partial_sph.shape == out.full_sph.shape == (2, 64, 64)
    assert out.vox_sph.shape == out.vox_depth.shape == out.logits.shape == (2, 1, 64, 64, 64)
    assert out.mask.dtype == torch.bool


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
    assert torch.equal(out.full_sph, full)
    assert torch.equal(out.masked_depth[0, 40:80, 40:80], depth[0, 40:80, 40:80])
    assert (out.masked_depth[~mask] == 0).all()


def test_keeping_the_seen_side_takes_the_partial_map_where_it_sees_and_the_net_elsewhere():
    import dataclasses

    cfg = get_preset("default")
    g = cfg.geometry
    torch.manual_seed(0)
    plain = GenRe(cfg).eval()
    keep = GenRe(dataclasses.replace(cfg, geometry=dataclasses.replace(g, sph_keep_seen=True))).eval()
    keep.load_state_dict(plain.state_dict())
    # a box 1.9–2.1 units away, seen face-on: the partial map sees the near hemisphere's middle
    depth = torch.full((1, g.image_size, g.image_size), 2.0)
    mask = torch.zeros(1, g.image_size, g.image_size, dtype=torch.bool)
    mask[:, 40:88, 40:88] = True
    rgb = torch.rand(1, 3, g.image_size, g.image_size)
    with torch.no_grad():
        a, b = plain(rgb, mask=mask, depth=depth), keep(rgb, mask=mask, depth=depth)
    seen = a.partial_sph < g.sph_nohit_min
    assert 50 < int(seen.sum()) < g.sph_size ** 2 // 2
    assert torch.equal(b.full_sph[seen], a.partial_sph[seen])
    assert torch.equal(b.full_sph[~seen], a.full_sph[~seen])
    assert not torch.equal(a.full_sph[seen], a.partial_sph[seen])  # the net alone does not copy its input


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


def _stored(tmp_path, storage: str):
    """A random default-preset model, its float32 file, its file in ``storage``, and that file's tensor dtypes."""
    from safetensors import safe_open

    torch.manual_seed(0)
    model = GenRe(get_preset("default")).eval()
    full = save_model(model, tmp_path / "full.safetensors")
    path = save_model(model, tmp_path / f"{storage}.safetensors", storage=storage)
    with safe_open(str(path), framework="pt") as f:
        assert f.metadata()["storage"] == storage
        kinds = {k: f.get_tensor(k).dtype for k in f.keys()}
    return model, full, path, kinds


def _nets_follow(model, loaded, tol: float) -> None:
    """Each net of ``loaded`` on the float32 ``model``'s own inputs is within ``tol`` of its largest output."""
    rgb = torch.rand(1, 3, 128, 128)
    with torch.no_grad():
        a = model(rgb)
        depth = loaded(rgb).depth
        full = loaded.inpaint_net(a.partial_sph)
        logits = loaded.refine(a.vox_sph, a.vox_depth)
    for got, want in ((depth, a.depth), (full, a.full_sph), (logits, a.logits)):
        assert (got - want).abs().max() <= tol * want.abs().max(), (got - want).abs().max()


@pytest.mark.slow
def test_half_storage_halves_the_file_and_loads_into_float32(tmp_path):
    """save_model(storage="float16"): the weights stored as float16, the batch-norm statistics as float32, the step
    counters as integers; load_model gives the float32 model with the weights rounded to float16, whose nets
    follow the original's within the rounding; a value float16 cannot hold is kept in float32."""
    model, full, half, kinds = _stored(tmp_path, "float16")
    assert 0.45 < half.stat().st_size / full.stat().st_size < 0.55
    assert set(kinds.values()) == {torch.float16, torch.float32, torch.int64}
    for k, dtype in kinds.items():  # the weights halved; the batch-norm statistics and step counters kept
        assert dtype == (torch.int64 if k.endswith("num_batches_tracked") else
                         torch.float32 if k.endswith(("running_mean", "running_var")) else torch.float16), k
    loaded = load_model(half)
    for k, v in model.state_dict().items():
        got = loaded.state_dict()[k]
        assert got.dtype == v.dtype, k
        want = v.to(torch.float16).to(v.dtype) if kinds[k] == torch.float16 else v
        assert torch.equal(got, want), k
    _nets_follow(model, loaded, 1e-2)
    # a statistic beyond float16's range (a refiner's running variance reached 6e7) survives the round trip
    bn = next(k for k in model.state_dict() if k.startswith("refiner") and k.endswith("running_var"))
    model.state_dict()[bn].fill_(6e7)
    model.state_dict()["refiner.skip.weight"].view(-1)[0] = 1e6  # a weight float16 cannot hold stays float32
    again = load_model(save_model(model, tmp_path / "big.safetensors", storage="float16")).state_dict()
    assert torch.equal(again[bn], model.state_dict()[bn])
    assert torch.equal(again["refiner.skip.weight"], model.state_dict()["refiner.skip.weight"])


@pytest.mark.slow
def test_int8_storage_quarters_the_large_weights_within_half_a_step(tmp_path):
    """save_model(storage="int8"): every weight of two or more dimensions and 1,024 or more elements stored as int8
    rows with one scale per output channel (the row's largest magnitude / 127), each value read back within half a
    step of the original; the small tensors as float16, the batch-norm statistics exact; the nets follow the
    original's within the rounding, and the file is about a quarter of the float32 one."""
    from genre_backend.weights_file import INT8_SCALE_SUFFIX

    model, full, packed, kinds = _stored(tmp_path, "int8")
    assert 0.25 < packed.stat().st_size / full.stat().st_size < 0.30
    loaded = load_model(packed).state_dict()
    big = 0
    for k, v in model.state_dict().items():
        got = loaded[k]
        assert got.dtype == v.dtype and got.shape == v.shape, k
        if kinds[k] == torch.int8:
            big += 1
            assert v.dim() >= 2 and v.numel() >= 1024 and kinds[k + INT8_SCALE_SUFFIX] == torch.float32, k
            rows = v.reshape(v.shape[0], -1)
            step = rows.abs().amax(dim=1, keepdim=True) / 127
            assert bool(((got.reshape(rows.shape) - rows).abs() <= step / 2 + 1e-7).all()), k
        elif k.endswith(("running_mean", "running_var")) or not v.is_floating_point():
            assert torch.equal(got, v), k
        else:
            assert v.dim() < 2 or v.numel() < 1024, k
            assert torch.equal(got, v.to(torch.float16).to(v.dtype)), k
    assert big >= 20
    _nets_follow(model, load_model(packed), 5e-2)


@pytest.mark.slow
def test_grown_refiner_starts_with_the_same_output_and_then_learns_a_sharp_band():
    """grow_refiner adds the full-resolution branch with the logits unchanged; the branch then fits,
    within a few hundred steps, a one-voxel band around an input surface that the coarse path
    (frozen here) and the linear skip cannot sharpen further: the loss falls well below where it starts."""
    import dataclasses

    from genre_backend.nets.model import grow_refiner
    from support.tiny_data import TINY

    torch.manual_seed(0)
    model = GenRe(TINY).eval()
    grown = grow_refiner(model, 4).eval()
    assert grown.config.network.refiner_full_nf == 4 and model.config.network.refiner_full_nf == 0
    n = TINY.geometry.voxel_size
    # an input grid: the surface voxels of an axis-aligned box (a cube's faces), on both channels
    box = torch.zeros(n, n, n, dtype=torch.bool)
    lo, hi = n // 4, 3 * n // 4
    box[lo:hi, lo:hi, lo:hi] = True
    inner = torch.zeros_like(box)
    inner[lo + 1:hi - 1, lo + 1:hi - 1, lo + 1:hi - 1] = True
    surface = (box & ~inner).float()
    x = surface.expand(1, 2, n, n, n).clone()
    with torch.no_grad():
        assert torch.equal(model.refiner(x), grown.refiner(x))
    assert grow_refiner(grown, 4) is grown
    with pytest.raises(ValueError, match="already has"):
        grow_refiner(grown, 8)
    with pytest.raises(ValueError, match="unexpected"):
        grown.refiner.load_grown({**model.refiner.state_dict(), "extra.weight": torch.zeros(1)})
    with pytest.raises(ValueError, match="refiner_full_nf"):
        dataclasses.replace(TINY.network, refiner_full_nf=-1)
    # train the branch alone toward the surface itself (1 on the box's faces, 0 elsewhere)
    ref = grown.refiner.train()
    for name, p in ref.named_parameters():
        p.requires_grad_(name.startswith("full."))
    opt = torch.optim.Adam([p for p in ref.parameters() if p.requires_grad], lr=1e-2)
    target = surface[None, None]
    losses = []
    for _ in range(200):
        loss = torch.nn.functional.binary_cross_entropy_with_logits(ref(x), target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.2 * losses[0], (losses[0], losses[-1])
    with torch.no_grad():
        ref.eval()
        pred = torch.sigmoid(ref(x))[0, 0] > 0.5
    iou = float((pred & surface.bool()).sum() / (pred | surface.bool()).sum())
    assert iou > 0.95, iou


def test_weights_with_a_full_resolution_branch_round_trip(tmp_path):
    from genre_backend.nets.model import grow_refiner
    from support.tiny_data import TINY

    grown = grow_refiner(GenRe(TINY), 4)
    with torch.no_grad():
        grown.refiner.full[-1].weight.normal_()  # not the zero initialisation
    loaded = load_model(save_model(grown, tmp_path / "g.safetensors"))
    assert loaded.config == grown.config and loaded.config.network.refiner_full_nf == 4
    for (k, a), (_, b) in zip(sorted(grown.state_dict().items()), sorted(loaded.state_dict().items())):
        assert torch.equal(a, b), k


def test_hit_head_composes_its_map_from_the_hit_logits_and_the_seen_radius(tmp_path):
    """With the decoder's output zeroed and the hit bias set, the "hit" head returns the seen
    pixels' values unchanged, radius 0 (clamped to MAX_HIT_VALUE) on the unseen ones, and
    exactly "no hit" wherever the hit probability is at most geometry.sph_hit_probability; its weights round-trip and config
    dicts written before the key existed load with the paper's "value" head."""
    import dataclasses

    from genre_backend.config import GenreConfig
    from genre_backend.geometry.spherical import pad_sph
    from genre_backend.nets.inpaint_net import MAX_HIT_VALUE
    from support.tiny_data import TINY

    cfg = dataclasses.replace(TINY, network=dataclasses.replace(TINY.network, inpaint_head="hit"))
    net = InpaintNet(cfg).eval()
    assert net.encoder.stem[0].in_channels == 2 and net.decoder.head[-1].out_channels == 2
    size, pad = cfg.geometry.sph_size, cfg.geometry.sph_pad
    partial = torch.ones(1, size, size)
    partial[0, 8:20, 10:22] = torch.linspace(0.6, 0.95, 12)[:, None]
    last = net.decoder.head[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.copy_(torch.tensor([1.0, 0.0]))  # hit everywhere, radius unchanged
        full = net(partial)
        seen = partial < 1
        assert torch.equal(full[seen], partial[seen])
        assert torch.all(full[~seen] == MAX_HIT_VALUE)
        last.bias.copy_(torch.tensor([-3.0, 0.0]))  # no hit anywhere
        assert torch.all(net(partial) == 1.0)
        # the map is where(hit logit > 0, 1 − radius, 1) for trained-looking outputs too
        last.weight.normal_(std=0.1)
        last.bias.copy_(torch.tensor([net.hit_logit_min, 0.0]))  # around the decision, so both kinds appear
        parts = net.forward_parts(pad_sph(partial[:, None], pad))
        want = torch.where(torch.sigmoid(parts["hit_logits"]) > cfg.geometry.sph_hit_probability, (1 - parts["radius"]).clamp(0, MAX_HIT_VALUE), torch.ones_like(parts["radius"]))
        assert torch.equal(parts["map"], want)
        assert 0 < float((parts["map"] < 1).float().mean()) < 1
    model = GenRe(cfg)
    loaded = load_model(save_model(model, tmp_path / "hit.safetensors"))
    assert loaded.config.network.inpaint_head == "hit"
    for (k, a), (_, b) in zip(sorted(model.state_dict().items()), sorted(loaded.state_dict().items())):
        assert torch.equal(a, b), k
    old = TINY.to_dict()
    del old["network"]["inpaint_head"]
    assert GenreConfig.from_dict(old).network.inpaint_head == "value"
    with pytest.raises(ValueError, match="inpaint_head"):
        dataclasses.replace(TINY.network, inpaint_head="mask")


def test_with_inpaint_net_of_takes_the_donors_inpainting_net_and_keeps_the_rest():
    """The transplant: the donor's head, widths, weights and hit level; the model's depth net, refiner and config."""
    import dataclasses as dc

    from genre_backend.nets.model import with_inpaint_net, with_inpaint_net_of
    from support.tiny_data import TINY

    torch.manual_seed(0)
    model = GenRe(TINY)
    donor = with_inpaint_net(GenRe(dc.replace(TINY, geometry=dc.replace(TINY.geometry, sph_hit_probability=0.1))),
                             head="hit", widths=(16, 32, 64, 128))
    new = with_inpaint_net_of(model, donor)
    assert new.config.network.inpaint_head == "hit" and new.config.network.inpaint_widths == (16, 32, 64, 128)
    assert new.config.geometry.sph_hit_probability == 0.1
    assert new.config.network.refiner_nf == model.config.network.refiner_nf
    for part, source in (("depth_net", model), ("refiner", model), ("inpaint_net", donor)):
        want = getattr(source, part).state_dict()
        for k, v in getattr(new, part).state_dict().items():
            assert torch.equal(v, want[k]), (part, k)
    # the transplanted model computes the donor's maps from the same partial map
    x = torch.rand(1, TINY.geometry.sph_size, TINY.geometry.sph_size)
    with torch.no_grad():
        assert torch.allclose(new.eval().inpaint_net(x), donor.eval().inpaint_net(x))
    other = GenRe(dc.replace(TINY, geometry=dc.replace(TINY.geometry, sph_size=TINY.geometry.sph_size * 2)))
    with pytest.raises(ValueError, match="spherical maps"):
        with_inpaint_net_of(model, other)


def test_with_inpaint_net_keeps_the_other_nets():
    from genre_backend.nets.model import with_inpaint_net
    from support.tiny_data import TINY

    model = GenRe(TINY)
    assert with_inpaint_net(model, head="value") is model
    assert with_inpaint_net(model, widths=TINY.network.inpaint_widths) is model
    new = with_inpaint_net(model, head="hit")
    assert new.config.network.inpaint_head == "hit"
    wide = with_inpaint_net(model, widths=(16, 32, 64, 128))
    assert wide.config.network.inpaint_widths == (16, 32, 64, 128) and wide.config.network.inpaint_head == "value"
    def n_params(m):
        return sum(p.numel() for p in m.inpaint_net.parameters())

    assert n_params(wide) > 3 * n_params(model)  # (conv weights grow with the square of the width)
    for other in (new, wide):
        for part in ("depth_net", "refiner"):
            for k, v in getattr(model, part).state_dict().items():
                assert torch.equal(v, getattr(other, part).state_dict()[k]), (part, k)


def test_mean_probability_logits_is_the_mean_of_the_probabilities_and_stays_finite():
    from genre_backend.nets.model import mean_probability_logits

    g = torch.Generator().manual_seed(0)
    a = torch.randn(5, 7, generator=g, dtype=torch.float64) * 6
    b = torch.randn(5, 7, generator=g, dtype=torch.float64) * 6
    got = mean_probability_logits(a, b)
    assert torch.allclose(torch.sigmoid(got), (torch.sigmoid(a) + torch.sigmoid(b)) / 2, atol=1e-12)
    assert torch.allclose(mean_probability_logits(a, a), a, atol=1e-9)  # the mean of a probability with itself
    # confident logits: the naive log(p / (1 - p)) of the float32 mean is infinite here, these stay finite and right
    big = torch.tensor([200.0, -200.0, 90.0, -90.0])
    other = torch.tensor([150.0, -300.0, -90.0, 90.0])
    out = mean_probability_logits(big, other)
    assert torch.isfinite(out).all()
    # 1 − p = (e^−200 + e^−150)/2 ≈ e^−150/2, so the logit is 150 + log 2; p ≈ e^−200/2: −200 − log 2;
    # p = (σ(90) + σ(−90))/2 = 1/2 exactly: 0
    assert abs(float(out[0]) - (150.0 + math.log(2.0))) < 1e-3
    assert abs(float(out[1]) - (-200.0 - math.log(2.0))) < 1e-3
    assert abs(float(out[2])) < 1e-4 and abs(float(out[3])) < 1e-4
    with pytest.raises(ValueError, match="shapes"):
        mean_probability_logits(torch.zeros(2), torch.zeros(3))


def test_mirror_averaged_gives_a_mirror_symmetric_model_its_own_output_and_reflects_the_mirror_image_back():
    """The reflection is exact: a model that is geometry alone (depth → voxels, which commutes with the mirror)
    gets its own logits back from an object that is nowhere near symmetric; a model that ignores its input gets
    the mean of its output and that output reflected (so the mirror image's logits were reflected back along x)."""
    from genre_backend.frame import depth_to_points
    from genre_backend.geometry.voxels import mirror_voxels, points_to_voxels
    from genre_backend.nets.model import mean_probability_logits, mirror_averaged

    cfg = get_preset("default")
    s, n = cfg.geometry.image_size, cfg.geometry.voxel_size
    ys, xs = torch.meshgrid(torch.arange(s), torch.arange(s), indexing="ij")
    mask = ((xs - 40) ** 2 + (ys - 50) ** 2 < 25 ** 2) | ((xs > 60) & (xs < 70) & (ys > 20) & (ys < 100))  # a disc and a post, off centre
    depth = torch.where(mask, 2.0 + 0.003 * xs + 0.001 * ys, torch.zeros(()))[None].float()
    mask = mask[None]

    def geometric(rgb, m, d, sph):  # the voxels of the masked depth's points, as logits
        pts = depth_to_points(torch.where(m, d, torch.zeros_like(d)), cfg.camera).flatten(1, 2)
        return points_to_voxels(pts, n, m.flatten(1))[:, None] * 8.0 - 4.0

    rgb = torch.rand(1, 3, s, s)
    own = geometric(rgb, mask, depth, None)
    assert not torch.equal(own, mirror_voxels(own))  # the object is not symmetric
    assert torch.allclose(mirror_averaged(geometric, rgb, mask, depth), own, atol=1e-5)

    fixed = torch.randn(1, 1, n, n, n, generator=torch.Generator().manual_seed(1)) * 3

    def blind(rgb, m, d, sph):
        return fixed

    got = mirror_averaged(blind, rgb, mask, depth)
    assert torch.allclose(got, mean_probability_logits(fixed, mirror_voxels(fixed)), atol=1e-6)
    assert not torch.allclose(got, fixed, atol=1e-2)
    # the inputs handed to the mirrored pass: columns flipped, the spherical map by mirror_sph
    seen = []
    sph = torch.rand(1, cfg.geometry.sph_size, cfg.geometry.sph_size)
    mirror_averaged(lambda r, m, d, f: seen.append((r, m, d, f)) or fixed, rgb, mask, depth, sph, logits=fixed)
    (r, m, d, f), = seen
    from genre_backend.geometry.spherical import mirror_sph

    assert torch.equal(r, rgb.flip(-1)) and torch.equal(m, mask.flip(-1)) and torch.equal(d, depth.flip(-1))
    assert torch.equal(f, mirror_sph(sph))


@torch.no_grad()
def test_genre_forward_with_mirror_averages_the_view_and_its_mirror_image():
    from genre_backend.geometry.voxels import mirror_voxels
    from genre_backend.nets.model import mean_probability_logits

    torch.manual_seed(0)
    model = GenRe(get_preset("default")).eval()
    s = model.config.geometry.image_size
    rgb = torch.rand(1, 3, s, s)
    mask = torch.zeros(1, s, s, dtype=torch.bool)
    mask[:, 30:90, 20:70] = True
    plain = model(rgb, mask=mask)
    mirrored = model(rgb.flip(-1), mask=mask.flip(-1))
    both = model(rgb, mask=mask, mirror=True)
    assert torch.allclose(both.logits, mean_probability_logits(plain.logits, mirror_voxels(mirrored.logits)), atol=1e-5)
    assert torch.equal(both.depth, plain.depth) and torch.equal(both.full_sph, plain.full_sph)  # the view's own
    assert not torch.allclose(both.logits, plain.logits, atol=1e-3)  # random nets are not symmetric
    from genre_backend.config import GeometryConfig

    for bad in (1, "yes"):
        with pytest.raises(ValueError, match="test_time_mirror"):
            GeometryConfig(test_time_mirror=bad)
