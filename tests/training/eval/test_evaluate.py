"""`genre eval` on a tiny split made here: real renders, nets trained for a few steps."""

import csv
import json
import math

import numpy as np
import pytest
import torch
import trimesh

from genre_backend import frame
from genre_backend.geometry.metrics import chamfer_distance, fscore, fscore_reference, normalize_points
from support.scripts import load_script
from support.tiny_data import TINY, copy_tiny_views
from genre_backend.geometry.metrics import CloudScorer
from training.eval.cli import main
from training.eval.protocol import EMPTY_CD, FLOOR, ROWS, EvalView
from training.eval.report import flatness_table
from training.eval.runner import Truth, mesh_metrics, score_grid
from training.eval.statistics import aggregate, choose_thresholds
from training.learn.train import TrainConfig, train


# ---- F-score -----------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["kdtree", "brute"])
def test_fscore_matches_its_reference_and_is_one_on_identical_clouds(method):
    gen = torch.Generator().manual_seed(0)
    a, b = torch.rand(300, 3, generator=gen), torch.rand(200, 3, generator=gen)
    for t in (0.02, 0.05, 0.1):
        assert float(fscore(a, b, t, method=method)) == pytest.approx(fscore_reference(a.numpy(), b.numpy(), t), abs=1e-6)
    assert float(fscore(a, a, 0.01, method=method)) == 1.0
    batched = fscore(torch.stack([a, a + 10]), torch.stack([b[:150], b[:150]]), 0.05, method=method)
    assert float(batched[1]) == 0.0 and batched.shape == (2,)


def test_the_evaluation_metrics_are_the_library_ones():
    gen = torch.Generator().manual_seed(1)
    a, b = torch.rand(1024, 3, generator=gen), torch.rand(1024, 3, generator=gen) * torch.tensor([1.0, 0.5, 0.8])
    A, B = torch.rand(3000, 3, generator=gen), torch.rand(2500, 3, generator=gen) * torch.tensor([1.0, 0.5, 0.8])
    m = CloudScorer(b, B).metrics(a, A)
    na, nb, nA, nB = (normalize_points(x) for x in (a, b, A, B))
    assert m["cd1k"] == pytest.approx(float(chamfer_distance(na, nb)), rel=1e-5)
    assert m["cd10k"] == pytest.approx(float(chamfer_distance(nA, nB)), rel=1e-5)
    assert m["f1"] == pytest.approx(float(fscore(nA, nB, 0.01)), abs=1e-6)
    assert m["f2"] == pytest.approx(float(fscore(nA, nB, 0.02)), abs=1e-6)


# ---- the metric on known shapes ------------------------------------------------------------
def _lattice(n=11):
    g = torch.linspace(-0.5, 0.5, n)
    return torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)


def test_a_shifted_shape_gives_the_expected_cd():
    pts = _lattice()  # spacing 0.1
    d = 0.015  # between the two F-score thresholds (0.01, 0.02)
    moved = pts + torch.tensor([d, 0.0, 0.0])
    # before normalisation: every point's nearest neighbour is its own shifted copy → CD = 2d
    assert float(chamfer_distance(pts, moved)) == pytest.approx(2 * d, rel=1e-5)
    # normalisation (own bounding box) removes a pure shift
    assert float(chamfer_distance(normalize_points(pts), normalize_points(moved))) == pytest.approx(0.0, abs=1e-6)
    # a deformation survives it: move the interior points only (the bounding box stays) → CD = 2 d k / N
    interior = (pts.abs() < 0.45).all(dim=1)
    bent = pts.clone()
    bent[interior, 0] += d
    expect = 2 * d * int(interior.sum()) / len(pts)
    m = CloudScorer(pts, pts).metrics(bent, bent)
    assert m["cd1k"] == pytest.approx(expect, rel=1e-4)
    assert m["f1"] == pytest.approx(1 - int(interior.sum()) / len(pts), abs=1e-6)  # moved points are 0.015 away: out at 1 %, in at 2 %
    assert m["f2"] == 1.0


# ---- the tiny split and a few-step run -----------------------------------------------------
@pytest.fixture(scope="module")
def tiny(tiny_views_rendered, tmp_path_factory):
    root = tmp_path_factory.mktemp("evaltiny")
    views = copy_tiny_views(tiny_views_rendered, root)
    # a seen class and an unseen one: the box plays a seen-test chair, the table an unseen table
    manifest = {"shapes": [{"id": "box", "class": "chair", "split": "test"}, {"id": "table", "class": "table", "split": "unseen"}]}
    (root / "manifest.json").write_text(json.dumps(manifest))
    run = root / "run"

    def cfg(stage, steps, **kw):
        return TrainConfig(stage=stage, data=str(views), out=str(run), steps=steps, batch_size=2, val_fraction=0.0, augment=False, progress=False, **kw)

    train(cfg("depth", 3), TINY)
    train(cfg("inpaint", 2, init=str(run / "depth" / "final.safetensors")))
    train(cfg("refine", 2, init=str(run / "inpaint" / "final.safetensors")))
    train(cfg("completion", 2, init=str(run / "depth" / "final.safetensors")))
    train(cfg("onestep", 2), TINY)
    return root, views, run


def _args(root, views, run, out, *extra):
    return ["--data", str(views), "--run", str(run), "--train-views", str(views), "--manifest", str(root / "manifest.json"),
            "--out", str(out), "--no-progress", *extra]


def _read(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _tiny_genre_completion_and_a_view(tiny):
    """The tiny run's GenRe and 3D Completion, and one evaluation sample of its table."""
    from genre_backend.nets.model import load_model
    from training.data.dataset import ViewDataset, ViewRef
    from training.learn.baselines import load_baseline

    _, views, run = tiny
    genre = load_model(run / "refine" / "final.safetensors")
    completion = load_baseline(run / "completion" / "final.safetensors", "completion")
    return genre, completion, ViewDataset([ViewRef(views / "table", 0)], genre.config).sample(0, None)


def test_the_oracle_rows_feed_the_true_depth_and_the_plain_rows_the_predicted_one(tiny):
    from training.eval.rows import Models, predict

    genre, completion, sample = _tiny_genre_completion_and_a_view(tiny)
    out = predict(Models(genre, completion, None, wanted=ROWS), sample, "cpu")
    rgb, mask, depth = sample["rgb"][None], sample["mask"][None], sample["depth"][None]
    with torch.no_grad():
        expected = {
            "GenRe": genre(rgb, mask=mask).logits,
            "GenRe-Oracle": genre(rgb, mask=mask, depth=depth).logits,
            "3D Completion": completion(rgb, mask=mask)["logits"],
            "3D Completion-Oracle": completion(rgb, mask=mask, depth=depth)["logits"],
        }
    for row, logits in expected.items():
        assert torch.allclose(out[row]["prob"], torch.sigmoid(logits)[0, 0]), row
    # the true depth is not what the depth net predicts, so the oracle row is a different input, not a copy
    assert not torch.allclose(out["3D Completion-Oracle"]["prob"], out["3D Completion"]["prob"])


def test_median_offset_moves_one_depth_map_to_the_others_offset_over_the_mask():
    from training.eval.rows import median_offset

    g = torch.Generator().manual_seed(0)
    relief = torch.rand(2, 8, 8, generator=g)
    valid = torch.zeros(2, 8, 8, dtype=torch.bool)
    valid[0, 2:6, 2:6] = True  # the second item has nothing valid: no shift
    target = relief + torch.tensor([0.37, -1.0]).view(2, 1, 1)
    target[0, 0, 0] = 50.0  # outside the mask: ignored
    shift = median_offset(target, relief, valid)
    assert shift.shape == (2, 1, 1)
    assert shift[0].item() == pytest.approx(0.37, abs=1e-6) and shift[1].item() == 0.0
    # the median, not the mean: one outlier inside the mask does not move it
    target[0, 3, 3] = 100.0
    assert median_offset(target, relief, valid)[0].item() == pytest.approx(0.37, abs=1e-6)


def test_the_offset_and_relief_oracles_feed_one_depth_map_at_the_others_offset(tiny):
    from training.eval.protocol import DIAGNOSTIC_ROWS
    from training.eval.rows import Models, predict

    genre, _, sample = _tiny_genre_completion_and_a_view(tiny)
    out = predict(Models(genre, wanted=("GenRe", *DIAGNOSTIC_ROWS)), sample, "cpu")
    rgb, mask, depth = sample["rgb"][None], sample["mask"][None], sample["depth"][None]
    valid = mask & (depth > 0)
    with torch.no_grad():
        pred = genre(rgb, mask=mask).depth
    own_offset = (depth - pred)[valid].median()
    moved_pred = pred + own_offset  # the depth net's relief where the truth is
    moved_true = depth - own_offset  # the true relief where the depth net put it
    with torch.no_grad():
        for row, d in (("GenRe-OffsetOracle", moved_pred), ("GenRe-ReliefOracle", moved_true)):
            assert torch.allclose(out[row]["prob"], torch.sigmoid(genre(rgb, mask=mask, depth=d).logits)[0, 0], atol=1e-6), row
    # the two are other inputs than the plain row's (the tiny net's offset is not the truth's)
    assert not torch.allclose(out["GenRe-OffsetOracle"]["prob"], out["GenRe"]["prob"])
    # the blends: the true depth plus a share of the depth net's error; 0 would be GenRe-Oracle's input, 1 GenRe's
    from training.eval.protocol import DEPTH_BLENDS
    assert sorted(DEPTH_BLENDS.values()) == [0.25, 0.5, 0.75]
    with torch.no_grad():
        for row, share in DEPTH_BLENDS.items():
            d = torch.where(valid, depth + share * (pred - depth), pred)
            assert torch.allclose(out[row]["prob"], torch.sigmoid(genre(rgb, mask=mask, depth=d).logits)[0, 0], atol=1e-6), row
            assert not torch.allclose(out[row]["prob"], out["GenRe"]["prob"]), row
    # diagnostics are produced only when named
    assert not set(DIAGNOSTIC_ROWS) & set(predict(Models(genre, wanted=("GenRe",)), sample, "cpu"))


def test_weights_that_carve_to_the_silhouette_carve_every_voxel_row_alike_but_not_the_truth(tiny):
    import dataclasses

    from genre_backend.geometry.voxels import silhouette_ramp
    from training.eval.protocol import REPRESENTATION
    from training.eval.rows import Models, predict

    genre, completion, sample = _tiny_genre_completion_and_a_view(tiny)
    plain = predict(Models(genre, completion, None, wanted=ROWS), sample, "cpu")
    genre.config = dataclasses.replace(genre.config, geometry=dataclasses.replace(genre.config.geometry, silhouette_carve=True))
    carved = predict(Models(genre, completion, None, wanted=ROWS), sample, "cpu")
    ramp = silhouette_ramp(sample["mask"][None], genre.config.camera, genre.config.geometry.voxel_size)[0, 0]
    inside = ramp > 0
    assert 0 < int(inside.sum()) < inside.numel()
    rows = ["GenRe", "GenRe-Oracle", "GenRe-SphOracle", "3D Completion", "3D Completion-Oracle"]
    for row in rows:
        assert torch.equal(carved[row]["prob"], torch.minimum(plain[row]["prob"], ramp)), row
    assert any(float(plain[row]["prob"][~inside].max()) > 0.1 for row in rows)  # something was there to carve
    assert torch.equal(carved[REPRESENTATION]["prob"], plain[REPRESENTATION]["prob"])


def test_weights_that_trim_to_the_map_s_hull_trim_each_row_to_the_map_its_refiner_read(tiny):
    import dataclasses

    from genre_backend.geometry.spherical import sph_hull_ramp
    from training.eval.protocol import REPRESENTATION
    from training.eval.rows import Models, predict

    genre, completion, sample = _tiny_genre_completion_and_a_view(tiny)
    plain = predict(Models(genre, completion, None, wanted=ROWS), sample, "cpu")
    g = genre.config.geometry
    assert not (g.silhouette_carve or g.visible_fusion or g.pit_sealing)  # the trim is the only step after the nets here
    genre.config = dataclasses.replace(genre.config, geometry=dataclasses.replace(g, sph_hull_carve=True))
    trimmed = predict(Models(genre, completion, None, wanted=ROWS), sample, "cpu")
    rgb, mask, depth = sample["rgb"][None], sample["mask"][None], sample["depth"][None]
    with torch.no_grad():
        maps = {"GenRe": genre(rgb, mask=mask).full_sph, "GenRe-Oracle": genre(rgb, mask=mask, depth=depth).full_sph,
                "GenRe-SphOracle": sample["full_sph"][None]}
    for row, sph in maps.items():
        hull = sph_hull_ramp(sph, g.voxel_size, g.sph_nohit_min, g.sph_hull_spread)[0, 0]
        assert torch.equal(trimmed[row]["prob"], torch.minimum(plain[row]["prob"], hull)), row
        assert float(plain[row]["prob"][hull == 0].max()) > 0.1, row  # something was there to trim
    for row in ("3D Completion", "3D Completion-Oracle", REPRESENTATION):  # no map: untouched
        assert torch.equal(trimmed[row]["prob"], plain[row]["prob"]), row


def test_weights_that_fuse_the_visible_surface_fill_every_depth_row_from_its_own_depth(tiny):
    import dataclasses

    from genre_backend.geometry.visible_front import fuse_visible_surface
    from training.eval.protocol import REPRESENTATION
    from training.eval.rows import Models, predict

    genre, completion, sample = _tiny_genre_completion_and_a_view(tiny)
    geometry = dataclasses.replace(genre.config.geometry, target="distance")
    genre.config = dataclasses.replace(genre.config, geometry=geometry)
    plain = predict(Models(genre, completion, None, wanted=ROWS), sample, "cpu")
    genre.config = dataclasses.replace(genre.config, geometry=dataclasses.replace(geometry, visible_fusion=True))
    fused = predict(Models(genre, completion, None, wanted=ROWS), sample, "cpu")
    mask, depth = sample["mask"], sample["depth"]
    true_depth = torch.where(mask, depth, torch.zeros_like(depth))
    with torch.no_grad():
        own = {"GenRe": genre(sample["rgb"][None], mask=mask[None]).masked_depth[0],
               "3D Completion": completion(sample["rgb"][None], mask=mask[None])["masked_depth"][0]}
    depths = {**own, "GenRe-Oracle": true_depth, "GenRe-SphOracle": true_depth, "3D Completion-Oracle": true_depth}
    level = geometry.default_threshold
    for row, d in depths.items():
        want = fuse_visible_surface(plain[row]["prob"], d, genre.config.camera, genre.config.geometry, level)
        assert torch.equal(fused[row]["prob"], want), row
        assert "depth" not in fused[row]
    assert any(not torch.equal(fused[r]["prob"], plain[r]["prob"]) for r in depths)  # the tiny nets leave holes to fill
    assert torch.equal(fused[REPRESENTATION]["prob"], plain[REPRESENTATION]["prob"])


def test_weights_that_seal_pits_seal_every_learned_row_through_the_views_mask(tiny, monkeypatch):
    import dataclasses

    import genre_backend.geometry.visible_front as visible_front
    from genre_backend.geometry.visible_front import seal_pits
    from training.eval.protocol import REPRESENTATION
    from training.eval.rows import Models, predict

    genre, completion, sample = _tiny_genre_completion_and_a_view(tiny)
    geometry = dataclasses.replace(genre.config.geometry, target="distance")
    genre.config = dataclasses.replace(genre.config, geometry=geometry)
    plain = predict(Models(genre, completion, None, wanted=ROWS), sample, "cpu")
    calls = []

    def recording(prob, mask, camera, g, level, width):  # the real function, its calls recorded
        calls.append((prob.clone(), mask.clone(), level, width))
        return seal_pits(prob, mask, camera, g, level, width)

    monkeypatch.setattr(visible_front, "seal_pits", recording)  # (the options record imports it as each job runs)
    genre.config = dataclasses.replace(genre.config, geometry=dataclasses.replace(geometry, pit_sealing=8))
    sealed = predict(Models(genre, completion, None, wanted=ROWS), sample, "cpu")
    rows = ["GenRe", "GenRe-Oracle", "GenRe-SphOracle", "3D Completion", "3D Completion-Oracle"]
    assert len(calls) == len(rows)  # once per learned voxel row; the truth is not sealed
    for (prob, mask, level, width), row in zip(calls, rows):
        assert torch.equal(prob, plain[row]["prob"]), row
        assert torch.equal(mask, sample["mask"]) and mask.dtype == torch.bool
        assert (level, width) == (geometry.default_threshold, 8)
        want = seal_pits(plain[row]["prob"], sample["mask"], genre.config.camera, genre.config.geometry, level, 8)
        assert torch.equal(sealed[row]["prob"], want), row
    assert torch.equal(sealed[REPRESENTATION]["prob"], plain[REPRESENTATION]["prob"])


def test_a_perfect_prediction_sits_on_the_resampling_floor(tiny):
    _, views, _ = tiny
    meta = json.loads((views / "table" / "view_000.json").read_text())
    view = EvalView(views / "table", 0, "table", ("unseen",), meta)
    gt, again = Truth().posed(view)
    same = CloudScorer(gt[:1024], gt).metrics(gt[:1024], gt)
    assert same["cd1k"] == 0.0 and same["cd10k"] == 0.0 and same["f1"] == 1.0 and same["f2"] == 1.0
    floor = CloudScorer(gt[:1024], gt).metrics(again[:1024], again)
    assert 0.0 < floor["cd1k"] < 0.1 and floor["cd10k"] < floor["cd1k"]
    # the true mesh itself, posed, scored as a prediction: at the floor
    mesh = trimesh.load(meta["mesh"], force="mesh", process=False)
    rot = torch.tensor(meta["rotation_cam_to_obj"], dtype=torch.float64)[None]
    verts = frame.object_to_view(torch.tensor(mesh.vertices)[None], rot)[0].numpy()
    perfect = mesh_metrics(verts, np.asarray(mesh.faces), CloudScorer(gt[:1024], gt))
    assert perfect["cd1k"] == pytest.approx(floor["cd1k"], rel=0.25)
    assert perfect["f2"] > 0.95
    # the object's up in the view frame: the view-frame vertices' spread along it is the object-frame z spread
    up = Truth.up(view).double()
    assert float(up.norm()) == pytest.approx(1.0)
    assert float(np.ptp(verts @ up.numpy())) == pytest.approx(float(np.ptp(np.asarray(mesh.vertices)[:, 2])), rel=1e-6)
    scorer = CloudScorer(gt[:1024], gt, up=Truth.up(view))
    assert mesh_metrics(verts, np.asarray(mesh.faces), scorer)["dw"] == pytest.approx(scorer.dw_true, rel=0.05)


def test_the_flatness_table_gives_each_rows_median_ratio_at_its_seen_threshold():
    def rec(row, true, pred45, pred50):
        return {"row": row, "groups": "flat-from-above", "dw_true": str(true), "dw@0.45": str(pred45), "dw@0.50": str(pred50),
                "cd1k@0.45": "0.1", "cd1k@0.50": "0.2"}

    records = [rec("GenRe", 0.1, 0.8, 0.15), rec("GenRe", 0.1, 0.9, 0.3), rec("GenRe", 0.2, 0.3, 0.1), rec("GenRe", 0.1, "nan", 0.1),
               rec(FLOOR, 0.1, 0.1, 0.1), {**rec("GenRe", 0.1, 0.1, 0.1), "groups": "product-test"}]
    choice = {"seen": {"GenRe": 0.45, FLOOR: 0.45}}
    table = flatness_table(records, choice, ["GenRe"])
    # ratios at 0.45: 8, 9, 1.5, nan → median of the finite ones 8; within 2x: 1 of 4
    assert "| GenRe | 4 | 0.800 | 0.100 | 8.000 | 1 / 4 | 0.100 |" in table
    assert f"| {FLOOR} | 1 | 0.100 | 0.100 | 1.000 | 1 / 1 | 0.100 |" in table
    choice["seen"]["GenRe"] = 0.5  # ratios 1.5, 3, 0.5, 1 → median 1.25; within 2x: 3
    assert "| GenRe | 4 | 0.125 | 0.100 | 1.250 | 3 / 4 | 0.200 |" in flatness_table(records, choice, ["GenRe"])
    assert flatness_table([r for r in records if r["groups"] == "product-test"], choice, ["GenRe"]) == ""


@pytest.mark.slow
def test_genre_eval_writes_every_row_and_applies_the_seen_threshold(tiny, tmp_path, capsys):
    root, views, run = tiny
    out = tmp_path / "res"
    rc = main(_args(root, views, run, out, "--gallery", "1", "--heatmap-shapes", "1", "--heatmap-elevations", "20",
                    "--heatmap-azimuths", "2", "--render-samples", "2"))
    assert rc == 0
    printed = capsys.readouterr().out
    table = (out / "table.md").read_text()
    for row in (*ROWS, FLOOR):
        assert f"| {row} |" in table and f"| {row} |" in printed, row
    assert "seen-test" in table and "unseen" in table
    for name in ("per_view.csv", "per_shape.csv", "per_class.csv", "thresholds.json", "bars.png", "depth_vs_dissimilarity.png",
                 "viewpoint_heatmap.png", "gallery.png"):
        assert (out / name).is_file(), name
    records = _read(out / "per_view.csv")
    assert len(records) == 4 * (len(ROWS) + 1)
    choice = json.loads((out / "thresholds.json").read_text())
    thresholds = TINY.geometry.thresholds()
    per_class = {(r["row"], r["class"]): r for r in _read(out / "per_class.csv")}
    for row in ROWS:
        seen = [r for r in records if r["row"] == row and r["groups"] == "test"]
        unseen = [r for r in records if r["row"] == row and "unseen" in r["groups"].split("|")]
        means = {t: np.mean([float(r[f"cd1k@{t:.2f}"]) for r in seen]) for t in thresholds}
        t_star = choice["seen"][row]
        assert means[t_star] == pytest.approx(min(means.values()))  # chosen on seen-test views …
        applied = np.mean([float(r[f"cd1k@{t_star:.2f}"]) for r in unseen])
        assert float(per_class[(row, "table")]["cd1k_seen"]) == pytest.approx(applied, rel=1e-5)  # … and applied to unseen
        assert float(per_class[(row, "table")]["threshold_seen"]) == t_star
    # the seen threshold does not look at unseen data: worsen unseen CDs at it, choose again → the same
    spoiled = [dict(r) for r in records]
    for r in spoiled:
        if "unseen" in r["groups"].split("|"):
            for t in thresholds:
                r[f"cd1k@{t:.2f}"] = str(float(r[f"cd1k@{t:.2f}"]) + (5.0 if t == choice["seen"][r["row"]] else 0.0))
    again = choose_thresholds(spoiled, thresholds, 0.5)
    assert again["seen"] == choice["seen"]
    assert all(math.isfinite(v) for v in aggregate(records, choice)[2]["seen"]["unseen"].values())


@pytest.mark.slow
def test_eval_resumes_after_an_interruption(tiny, tmp_path):
    root, views, run = tiny
    out = tmp_path / "res"
    base = _args(root, views, run, out, "--no-figures", "--rows", "GenRe,Nearest training shape")
    assert main(base) == 0
    full = (out / "per_view.csv").read_text().splitlines()
    assert len(full) == 1 + 4 * 3
    # killed while writing the last view: its rows cut off mid-line
    (out / "per_view.csv").write_text("\n".join(full[:-2]) + "\n" + full[-2][: len(full[-2]) // 2])
    assert main(base) == 0
    resumed = (out / "per_view.csv").read_text().splitlines()
    assert sorted(resumed) == sorted(full)
    # the gallery of a run resumed from rows scored earlier (or by other processes) still gets its grids
    assert not (out / "grids").exists()
    assert main(_args(root, views, run, out, "--rows", "GenRe,Nearest training shape", "--gallery", "1", "--heatmap-shapes", "0",
                      "--render-samples", "2")) == 0
    assert len(list((out / "grids").glob("*.npz"))) == 2 and (out / "gallery.png").is_file()
    assert sorted((out / "per_view.csv").read_text().splitlines()) == sorted(full)
    # other rows (or weights) in the same folder: refused rather than mixed
    assert main(_args(root, views, run, out, "--no-figures", "--rows", "GenRe")) == 2


def test_missing_weights_or_data_give_a_clear_error(tiny, tmp_path, capsys):
    root, views, run = tiny
    assert main(_args(root, views, tmp_path / "nothing", tmp_path / "o")) == 2
    err = capsys.readouterr().err
    assert "weights not found" in err and "genre train" in err
    assert main(_args(root, tmp_path / "no_views", run, tmp_path / "o")) == 2
    assert "genre data render" in capsys.readouterr().err


def test_stage_errors_scores_every_stage_on_seen_test_views(tiny, capsys):
    root, views, run = tiny
    mod = load_script("stage_errors")
    assert mod.main(["--weights", str(run / "refine" / "final.safetensors"), "--views", str(views),
                     "--manifest", str(root / "manifest.json"), "--thresholds", "0.5",
                     "--completion", str(run / "completion" / "final.safetensors")]) == 0
    out = capsys.readouterr().out
    lines = {line[:36].strip(): line for line in out.splitlines()[1:]}
    assert out.startswith("1 seen-test views")  # the box (test split); the unseen table is never looked at
    assert set(lines) == {"true distance, its surface", "true spherical map, projected", "refiner <- true depth + true map",
                          "refiner <- true depth", "GenRe spherical map, projected", "GenRe",
                          "partial map (GenRe depth), projected", "partial map (true depth), projected",
                          "inpainted from true depth, projected", "GenRe partial map: MSE on its hits",
                          "inpainted map: MSE on those pixels", "inpainted map: MSE elsewhere",
                          "inpainted map: std of its hits", "true map: std of its hits", "depth |error| (median)",
                          "depth |error| less its offset", "depth |error| less its plane",
                          "depth error vs brightness (corr.)", "inpainted map: hit/no-hit as the tru", "inpainted map: MSE on unseen true hi",
                          "true map: share of no-hit pixels", "inpainted map: share of hit pixels",
                          "GenRe, spherical channel emptied", "GenRe, depth offset removed", "GenRe, trimmed to the outline",
                          "3D Completion <- true depth", "3D Completion, depth offset removed", "3D Completion"}
    for row in ("GenRe, spherical channel emptied", "GenRe, depth offset removed", "GenRe, trimmed to the outline", "3D Completion <- true depth",
                "3D Completion, depth offset removed", "3D Completion"):
        assert 0.0 < float(lines[row].split(": ")[1]) <= EMPTY_CD, row  # scored (an empty grid scores EMPTY_CD)
    # the representation's own error of a box at the tiny preset's voxel size: a fraction of a voxel, finite
    shell_cd = float(lines["true distance, its surface"].split(": ")[1])
    sph_cd = float(lines["true spherical map, projected"].split(": ")[1])
    assert 0.0 < shell_cd < 0.25 and 0.0 < sph_cd < 0.25
    parts = [float(lines[k].split()[-1]) for k in ("depth |error| (median)", "depth |error| less its offset", "depth |error| less its plane")]
    assert parts[0] >= 0 and parts[2] <= parts[1] + 1e-9  # a plane fits at least as well as an offset
    assert -1.0 <= float(lines["depth error vs brightness (corr.)"].split()[-1]) <= 1.0
    # the parts of an analytic error: an offset and a tilt are taken out exactly, a bump is not
    n = 32
    yy, xx = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    true = 2.0 + 0.01 * torch.sin(xx / 3.0)
    mask = (xx - 16) ** 2 + (yy - 16) ** 2 < 100
    tilted = mod.depth_error_parts(true + 0.05 + 0.2 * xx / n, true, mask)
    assert tilted["depth |error| (median)"] == pytest.approx(0.05 + 0.2 * 16 / n, abs=0.01)
    assert tilted["depth |error| less its offset"] == pytest.approx(float((0.2 * (xx[mask] - 16).abs() / n).median()), abs=1e-6)
    assert tilted["depth |error| less its plane"] < 1e-6
    bump = (mask & ((xx - 16) ** 2 + (yy - 16) ** 2 < 30)).double() * 0.1
    assert 0.01 < mod.depth_error_parts(true + bump, true, mask)["depth |error| less its plane"] < 0.1
    # an error that follows the brightness (dark pixels put too far) correlates with it negatively, exactly
    light = 0.2 + 0.6 * xx / n
    shaded = mod.depth_error_parts(true + 0.3 - 0.1 * light, true, mask, brightness=light)
    assert shaded["depth error vs brightness (corr.)"] == pytest.approx(-1.0, abs=1e-9)
    assert abs(mod.depth_error_parts(true + bump, true, mask, brightness=light)["depth error vs brightness (corr.)"]) < 0.1
    assert "depth error vs brightness (corr.)" not in tilted


def test_diagnostics_sample_seen_test_or_product_test_views_only(tiny, tmp_path):
    from training.eval.protocol import sample_seen_test_views

    root, views, _ = tiny
    manifest = tmp_path / "manifest.json"  # the box held out of the product's training, the table trained on
    manifest.write_text(json.dumps({"shapes": [
        {"id": "box", "class": "chair", "split": "test", "groups": ["test", "product-test"]},
        {"id": "table", "class": "table", "split": "unseen", "groups": ["unseen", "product-train"]}]}))
    assert [v.shape_dir.name for v in sample_seen_test_views(views, manifest, 5)] == ["box"]
    assert [v.shape_dir.name for v in sample_seen_test_views(views, manifest, 5, groups=("product-test",))] == ["box"]
    manifest.write_text(json.dumps({"shapes": [
        {"id": "box", "class": "chair", "split": "test", "groups": ["test", "product-train"]},
        {"id": "table", "class": "table", "split": "unseen", "groups": ["unseen", "product-test"]}]}))
    assert [v.shape_dir.name for v in sample_seen_test_views(views, manifest, 5, groups=("product-test",))] == ["table"]
    with pytest.raises(ValueError, match="unseen"):  # the unseen classes stay out of every diagnostic
        sample_seen_test_views(views, manifest, 5, groups=("unseen",))


def test_score_grid_sweeps_the_configured_range():
    import trimesh

    from genre_backend.config import get_preset
    from genre_backend.geometry.mesh_voxels import mesh_to_shell
    from genre_backend.geometry.metrics import sample_surface
    from training.eval.protocol import EMPTY_CD
    from training.eval.runner import score_grid

    g = get_preset("default").geometry
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.35)
    shell = mesh_to_shell(torch.tensor(sphere.vertices), torch.tensor(sphere.faces), 32, 1).float()
    prob = shell * 0.9 + 0.05  # 0.95 on the shell, 0.05 elsewhere
    gt = sample_surface(sphere.vertices, sphere.faces, 10_000, seed=3)
    scorer = CloudScorer(gt[:1024], gt)
    result = {t: m["cd10k"] for t, m in score_grid(prob, g.thresholds(), scorer).items()}
    assert list(result) == g.thresholds()
    # each cloud is normalised on its own, so the shell's two sheets score alike at every level
    assert all(0.0 < v < 0.1 for v in result.values())
    assert score_grid(torch.zeros(8, 8, 8), [0.5], scorer)[0.5]["cd1k"] == EMPTY_CD


@pytest.mark.slow
def test_parallel_workers_write_the_same_rows(tiny, tmp_path):
    root, views, run = tiny
    rows = "GenRe,3D Completion,Truth through the representation"
    assert main(_args(root, views, run, tmp_path / "one", "--no-figures", "--rows", rows)) == 0
    assert main(_args(root, views, run, tmp_path / "two", "--no-figures", "--rows", rows, "--jobs", "2")) == 0
    one = (tmp_path / "one" / "per_view.csv").read_text().splitlines()
    two = (tmp_path / "two" / "per_view.csv").read_text().splitlines()
    assert one[0] == two[0] and sorted(one[1:]) == sorted(two[1:]) and len(one) == 1 + 4 * 4
    assert "2 processes" in (tmp_path / "two" / "table.md").read_text()
    assert main(_args(root, views, run, tmp_path / "bad", "--jobs", "0")) == 2


def test_levels_score_only_those_levels_with_the_sweeps_figures_there(tiny, tmp_path, capsys):
    root, views, run = tiny
    rows = ("--no-figures", "--rows", "GenRe", "--sweep", "hole_closing=0")
    assert main(_args(root, views, run, tmp_path / "all", *rows)) == 0
    assert main(_args(root, views, run, tmp_path / "one", *rows, "--levels", "0.5,0.40")) == 0
    full = {(r["key"], r["row"]): r for r in _read(tmp_path / "all" / "per_view.csv")}
    some = _read(tmp_path / "one" / "per_view.csv")
    assert len(some) == len(full) == 4 * 3  # GenRe, its sweep row, the floor
    levels = sorted({k.split("@")[1] for k in some[0] if "@" in k})
    assert levels == ["0.40", "0.50"] and len(TINY.geometry.thresholds()) > 2
    for r in some:  # the same meshes, so the same figures, as the whole sweep's at those levels
        for k, v in r.items():
            assert v == full[(r["key"], r["row"])][k], (r["row"], k)
    assert json.loads((tmp_path / "one" / "eval_config.json").read_text())["levels"] == [0.4, 0.5]
    # a folder scored at other levels is refused rather than mixed; a bad list before anything runs
    assert main(_args(root, views, run, tmp_path / "one", *rows)) == 2
    for bad in ("x", "0", "1.2", ""):
        assert main(_args(root, views, run, tmp_path / "bad", *rows, "--levels", bad)) == 2, bad
        assert "--levels" in capsys.readouterr().err
    assert not (tmp_path / "bad" / "per_view.csv").exists()


@pytest.mark.slow
def test_the_distance_target_is_nearer_the_truth_than_the_shell(tiny):
    """Truth through each representation, at its best threshold, against the resampling floor."""
    import dataclasses

    from genre_backend.geometry.mesh_voxels import mesh_to_target

    _, views, _ = tiny
    for shape in ("box", "table"):
        meta = json.loads((views / shape / "view_000.json").read_text())
        view = EvalView(views / shape, 0, shape, ("unseen",), meta)
        gt, again = Truth().posed(view)
        scorer = CloudScorer(gt[:1024], gt)
        floor = scorer.metrics(again[:1024], again)["cd1k"]
        mesh = trimesh.load(meta["mesh"], force="mesh", process=False)
        rot = torch.tensor(meta["rotation_cam_to_obj"], dtype=torch.float64)[None]
        verts = frame.object_to_view(torch.tensor(mesh.vertices)[None], rot)[0]
        best = {}
        for kind in ("shell", "distance"):
            grid = mesh_to_target(verts, torch.tensor(mesh.faces), dataclasses.replace(TINY.geometry, target=kind))
            best[kind] = min(m["cd1k"] for m in score_grid(grid, TINY.geometry.thresholds(), scorer).values())
        assert best["distance"] < 0.8 * best["shell"], (shape, best, floor)
        assert best["distance"] < 1.6 * floor, (shape, best, floor)


def test_closed_meshes_are_told_from_ones_with_holes_or_tunnels():
    from training.eval.runner import is_closed
    from training.eval.statistics import product_threshold

    sphere = trimesh.creation.icosphere(2)
    torus = trimesh.creation.torus(0.3, 0.1)
    two = trimesh.util.concatenate([sphere, trimesh.creation.icosphere(1).apply_translation([3, 0, 0])])
    assert is_closed(sphere.faces) and is_closed(two.faces)
    assert not is_closed(torus.faces)  # a tunnel
    assert not is_closed(sphere.faces[1:])  # a hole
    assert not is_closed(np.zeros((0, 3), int))
    # the product threshold: lowest CD among the thresholds closed in ≥ 90 % of the views
    recs = [{"shape": f"s{i}", "cd1k@0.30": "0.2", "closed@0.30": "1", "cd1k@0.50": "0.1", "closed@0.50": str(float(i < 5)),
             "cd1k@0.70": "0.3", "closed@0.70": "1"} for i in range(10)]
    assert product_threshold(recs, [0.3, 0.5, 0.7], 0.5) == (0.3, 1.0)


def test_hole_closing_rule_takes_the_least_sealing_that_closes_enough():
    from training.eval.statistics import choose_hole_closing

    assert choose_hole_closing({0: 0.74, 1: 0.91, 2: 0.95, 3: 0.97}) == 1
    assert choose_hole_closing({0: 0.95, 1: 0.97}) == 0
    assert choose_hole_closing({0: 0.74, 1: 0.84, 2: 0.84, 3: 0.83}) == 1  # none reaches 90 %: the most closed, smaller k
    assert choose_hole_closing({0: float("nan"), 2: 0.5}) == 2
    with pytest.raises(ValueError, match="no closed share"):
        choose_hole_closing({0: float("nan")})


def test_representation_floor_scores_the_truth_through_each_representation(tiny, capsys):
    root, views, _ = tiny
    mod = load_script("representation_floor")
    assert mod.main(["--views", str(views), "--manifest", str(root / "manifest.json"), "--thresholds", "0.5"]) == 0
    lines = {line[:36].strip(): float(line[36:]) for line in capsys.readouterr().out.splitlines()[1:]}
    assert set(lines) == {"noise floor (truth resampled)", "shell, t=0.50", "distance, plain, t=0.50", "distance, moved, t=0.50",
                          "distance, shipped, t=0.50", "solid (winding number), t=0.50"}
    # the box at 64³: the moved distance sheets sit on the floor's scale, the shell well above it
    assert lines["distance, moved, t=0.50"] < lines["distance, plain, t=0.50"] < lines["shell, t=0.50"]
    assert lines["distance, shipped, t=0.50"] < 1.5 * lines["noise floor (truth resampled)"]


def test_a_sweep_scores_genre_again_at_each_setting_and_applies_the_hole_closing_rule(tiny, tmp_path, monkeypatch):
    import dataclasses

    from genre_backend.geometry.mesh_voxels import grid_to_surface
    from training.eval.rows import Models, predict, sweep_row
    from training.eval.statistics import choose_hole_closing

    root, views, run = tiny
    genre, _, sample = _tiny_genre_completion_and_a_view(tiny)
    geometry = genre.config.geometry
    own = geometry.hole_closing
    out = tmp_path / "sweep"
    assert main(_args(root, views, run, out, "--rows", "GenRe", "--no-figures", "--gallery", "0",
                      "--sweep", f"hole_closing=0,3,{own}", "--sweep", "visible_fusion=off")) == 0
    table = (out / "table.md").read_text()
    records = _read(out / "per_view.csv")
    assert {r["row"] for r in records} == {"GenRe", "GenRe [hole_closing=0]", "GenRe [hole_closing=3]",
                                           sweep_row("hole_closing", own), "GenRe [visible_fusion=off]", FLOOR}
    # the weights' own setting swept gives GenRe's own numbers, view by view, at every level
    by_key = lambda row: sorted((r for r in records if r["row"] == row), key=lambda r: r["key"])  # noqa: E731
    for a, b in zip(by_key("GenRe"), by_key(sweep_row("hole_closing", own)), strict=True):
        assert {k: v for k, v in a.items() if k not in ("row", "depth_abs_err")} == \
            {k: v for k, v in b.items() if k not in ("row", "depth_abs_err")}
    # a swept row is GenRe's grid, its surface made with the changed setting
    pred = predict(Models(genre, wanted=("GenRe",), sweeps=(("hole_closing", 3),)), sample, "cpu")
    swept = pred[sweep_row("hole_closing", 3)]
    assert torch.equal(swept["prob"], pred["GenRe"]["prob"])
    assert swept["geometry"] == dataclasses.replace(geometry, hole_closing=3)
    from training.eval import runner

    seen = []
    monkeypatch.setattr(runner, "grid_to_surface", lambda p, t, g: (seen.append(g.hole_closing), grid_to_surface(p, t, g))[1])
    from training.eval.protocol import find_eval_views

    manifest = json.loads((root / "manifest.json").read_text())
    view = next(v for v in find_eval_views([views], manifest, ("unseen",)) if v.shape_dir.name == "table" and v.view == 0)
    runner.score_view(Models(genre, wanted=("GenRe",), sweeps=(("hole_closing", 3),)), view, sample, runner.Truth(), "cpu")
    n = len(geometry.thresholds())
    assert seen == [own] * n + [3] * n  # GenRe's surfaces with the weights' k, the swept row's with k = 3
    # the table's closed shares are the records' means, and the rule is applied to the seen-test ones
    level = min(geometry.thresholds(), key=lambda t: abs(t - geometry.default_threshold))
    shares = {k: float(np.mean([float(r[f"closed@{level:.2f}"]) for r in records
                                if r["row"] == sweep_row("hole_closing", k) and r["groups"] == "test"])) for k in (0, 3, own)}
    assert f"seen-test closed share reaches 90 %): **{choose_hole_closing(shares)}**" in table
    assert "| hole_closing | 3 |" in table and "| visible_fusion | False |" in table


def test_a_bad_sweep_is_refused_before_anything_runs(tiny, tmp_path, capsys):
    root, views, run = tiny
    for bad in ("hole_closing", "colour=1", "hole_closing=x", "pit_sealing=-1", "threshold=0.5"):
        assert main(_args(root, views, run, tmp_path / "bad", "--rows", "GenRe", "--sweep", bad)) == 2, bad
        assert "--sweep" in capsys.readouterr().err
    assert not (tmp_path / "bad" / "per_view.csv").exists()


def test_weights_that_mirror_average_every_learned_row_with_its_own_model(tiny):
    import dataclasses

    from genre_backend.geometry.voxels import mirror_voxels
    from genre_backend.nets.model import mean_probability_logits
    from training.eval.protocol import REPRESENTATION
    from training.eval.rows import Models, predict

    genre, completion, sample = _tiny_genre_completion_and_a_view(tiny)
    plain = predict(Models(genre, completion, None, wanted=ROWS), sample, "cpu")
    genre.config = dataclasses.replace(genre.config, geometry=dataclasses.replace(genre.config.geometry, test_time_mirror=True))
    both = predict(Models(genre, completion, None, wanted=ROWS), sample, "cpu")
    rgb, mask, depth = sample["rgb"][None], sample["mask"][None], sample["depth"][None]
    flip = {"rgb": rgb.flip(-1), "mask": mask.flip(-1), "depth": depth.flip(-1)}
    with torch.no_grad():
        pairs = {
            "GenRe": (genre(rgb, mask=mask).logits, genre(flip["rgb"], mask=flip["mask"]).logits),
            "GenRe-Oracle": (genre(rgb, mask=mask, depth=depth).logits,
                             genre(flip["rgb"], mask=flip["mask"], depth=flip["depth"]).logits),
            "3D Completion": (completion(rgb, mask=mask)["logits"], completion(flip["rgb"], mask=flip["mask"])["logits"]),
            "3D Completion-Oracle": (completion(rgb, mask=mask, depth=depth)["logits"],
                                     completion(flip["rgb"], mask=flip["mask"], depth=flip["depth"])["logits"]),
        }
    for row, (own, mirrored) in pairs.items():
        want = torch.sigmoid(mean_probability_logits(own, mirror_voxels(mirrored)))[0, 0]
        assert torch.allclose(both[row]["prob"], want, atol=1e-5), row
        assert not torch.allclose(both[row]["prob"], plain[row]["prob"], atol=1e-3), row  # the tiny nets are not symmetric
    assert torch.equal(both[REPRESENTATION]["prob"], plain[REPRESENTATION]["prob"])  # the truth is left as it is


def test_weights_on_a_plain_backdrop_show_every_learned_row_the_painted_picture(tiny):
    import dataclasses

    from genre_backend.photo.preprocess import on_plain_backdrop
    from training.eval.protocol import REPRESENTATION
    from training.eval.rows import Models, predict, sweep_row

    genre, completion, sample = _tiny_genre_completion_and_a_view(tiny)
    painted = dict(sample, rgb=on_plain_backdrop(sample["rgb"], sample["mask"]))
    assert not torch.equal(painted["rgb"], sample["rgb"])  # the render's background is not the neutral grey
    want = predict(Models(genre, completion, None, wanted=ROWS), painted, "cpu")
    swept = predict(Models(genre, completion, None, wanted=ROWS, sweeps=(("plain_backdrop", True),)), sample, "cpu")
    plain = dataclasses.replace(genre.config.geometry, plain_backdrop=True)
    genre.config = dataclasses.replace(genre.config, geometry=plain)
    got = predict(Models(genre, completion, None, wanted=ROWS), sample, "cpu")
    for row in ("GenRe", "GenRe-Oracle", "GenRe-SphOracle", "3D Completion", "3D Completion-Oracle"):
        assert torch.equal(got[row]["prob"], want[row]["prob"]), row
    assert torch.equal(swept[sweep_row("plain_backdrop", True)]["prob"], want["GenRe"]["prob"])
    assert not torch.allclose(swept["GenRe"]["prob"], want["GenRe"]["prob"], atol=1e-4)  # the tiny nets read the background
    assert torch.equal(got[REPRESENTATION]["prob"], want[REPRESENTATION]["prob"])


def test_cd_split_parts_add_up_to_genre_evals_cd_of_each_view_and_row(tiny, tmp_path):
    """scripts/cd_split.py: the four parts of every view and row sum to the CD genre eval scores there."""
    root, views, run = tiny
    weights = str(run / "refine" / "best.safetensors")  # (what --run scores)
    assert main(_args(root, views, run, tmp_path / "eval", "--no-figures", "--rows", "GenRe,GenRe-SphOracle", "--levels", "0.45")) == 0
    split = load_script("cd_split")
    assert split.main(["--data", str(views), "--groups", "test,unseen", "--manifest", str(root / "manifest.json"), "--weights",
                       weights, "--name", "tiny", "--rows", "GenRe,GenRe-SphOracle", "--level", "0.45", "--jobs", "1",
                       "--out", str(tmp_path / "split")]) == 0
    scored = {(r["key"], r["row"]): float(r["cd1k@0.45"]) for r in _read(tmp_path / "eval" / "per_view.csv")}
    parts = _read(tmp_path / "split" / "per_view.csv")
    assert {(r["key"], r["row"]) for r in parts} == set(scored)  # every view, GenRe, its oracle and the floor
    for r in parts:
        four = sum(float(r[k]) for k in split.PARTS)
        assert four == pytest.approx(float(r["cd"]), rel=1e-4) and four == pytest.approx(scored[(r["key"], r["row"])], rel=1e-4)
        assert 0 <= float(r["pred_seen_share"]) <= 1 and 0 < float(r["gt_seen_share"]) < 1
    # a second run with the same name finds every view done and only rewrites the table
    assert split.main(["--data", str(views), "--groups", "test,unseen", "--manifest", str(root / "manifest.json"), "--weights",
                       weights, "--name", "tiny", "--out", str(tmp_path / "split")]) == 0
    assert len(_read(tmp_path / "split" / "per_view.csv")) == len(parts)
    # a file cut mid-line by a kill: that view's lines go and it is scored again, the rest are kept
    path = tmp_path / "split" / "per_view.csv"
    path.write_bytes(path.read_bytes()[:-3])  # (the last field still looks like a number)
    assert split.main(["--data", str(views), "--groups", "test,unseen", "--manifest", str(root / "manifest.json"), "--weights",
                       weights, "--name", "tiny", "--rows", "GenRe,GenRe-SphOracle", "--out", str(tmp_path / "split")]) == 0
    again = _read(path)
    assert sorted((r["key"], r["row"], r["cd"]) for r in again) == sorted((r["key"], r["row"], r["cd"]) for r in parts)
    assert "| tiny | GenRe-SphOracle |" in (tmp_path / "split" / "table.md").read_text()
