"""The product-vs-protocol table and the learning curve, on hand-made eval folders with known means."""

import csv
import json
import math

import numpy as np
import pytest

from training.eval import product
from training.eval.protocol import FLOOR, REPRESENTATION


def _eval_dir(path, t, rows):
    """A 'genre eval' folder: thresholds.json choosing ``t`` for GenRe, per_view.csv with ``rows`` (key, shape, class, row, cd)."""
    path.mkdir(parents=True)
    (path / "thresholds.json").write_text(json.dumps({"seen": {"GenRe": t, FLOOR: 0.75, REPRESENTATION: 0.5}}))
    cols = ["key", "shape", "view", "class", "groups", "row", "cd1k@0.45", "cd1k@0.50", "cd1k@0.75"]
    with (path / "per_view.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols)
        w.writeheader()
        for key, shape, cls, row, cd in rows:
            other = 9.0  # what the other thresholds say: must never be read
            w.writerow({"key": key, "shape": shape, "view": key[-3:], "class": cls, "groups": "product-test", "row": row,
                        "cd1k@0.45": cd if t == 0.45 or row != "GenRe" else other,
                        "cd1k@0.50": cd if t == 0.50 or row == REPRESENTATION else other,
                        "cd1k@0.75": cd if row == FLOOR else other})
    return path


MANIFEST = {"shapes": [
    {"id": "plane", "class": "airplane", "source": "flightgear"},
    {"id": "lamp", "class": "lamp", "source": "sweethome3d"},
    {"id": "procedural-primitive-000", "class": "primitive", "source": "procedural", "extra": {"subkind": "cube"}},
    {"id": "procedural-lathe-000", "class": "lathe", "source": "procedural", "extra": {}},
]}


def _rows(cds):
    out = []
    for shape, cls, views in (("plane", "airplane", 2), ("lamp", "lamp", 1), ("procedural-primitive-000", "primitive", 1),
                              ("procedural-lathe-000", "lathe", 1)):
        for v in range(views):
            key = f"{shape}/{v:03d}"
            out += [(key, shape, cls, "GenRe", cds[shape][v]), (key, shape, cls, FLOOR, 0.02), (key, shape, cls, REPRESENTATION, 0.03)]
    return out


def test_compare_table_means_over_shapes_at_each_models_threshold(tmp_path):
    a = _eval_dir(tmp_path / "a", 0.45, _rows({"plane": [0.10, 0.20], "lamp": [0.11], "procedural-primitive-000": [0.04],
                                               "procedural-lathe-000": [0.10]}))
    b = _eval_dir(tmp_path / "b", 0.50, _rows({"plane": [0.16, 0.14], "lamp": [0.24], "procedural-primitive-000": [0.09],
                                               "procedural-lathe-000": [0.10]}))
    text = product.compare_table(a, b, MANIFEST)
    lines = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]] for line in text.splitlines() if line.startswith("| ")}
    # all: product (0.15 + 0.11 + 0.04 + 0.10) / 4 = 0.100 (plane: its two views first); protocol (0.15 + 0.24 + 0.09 + 0.10) / 4 = 0.145
    assert lines["all"][:4] == ["4", "0.100", "0.145", "0.690"]
    assert lines["seen by protocol"][:3] == ["1", "0.150", "0.150"]
    assert lines["unseen by protocol"][:3] == ["1", "0.110", "0.240"]
    assert lines["procedural"][:3] == ["2", "0.070", "0.095"]
    assert lines["regular primitives"][:3] == ["1", "0.040", "0.090"]
    assert lines["regular primitives"][4:6] == ["0.020", "2.00×"]
    assert lines["lathe"] == ["procedural", "1", "0.100", "0.100", "1.000"]
    assert "- cube (1): 0.040 (floor 0.020, 2.00×; protocol 0.090)" in text
    # a level given: the product read at 0.50 is the "other" 9.0 everywhere but the representation
    at = product.compare_table(a, b, MANIFEST, thresholds=(0.50, None))
    assert "| all | 4 | 9.000 | 0.145 |" in at and "product t = 0.50" in at


def test_curve_point_sums_the_stages_processor_time(tmp_path):
    run = tmp_path / "run"
    for stage, step, cpu in (("depth", 100, 3600.0), ("refine", 50, 1800.0)):
        (run / stage / "checkpoint").mkdir(parents=True)
        (run / stage / "checkpoint" / "state.json").write_text(json.dumps({"step": step, "cpu_s": cpu}))
    ev = _eval_dir(tmp_path / "e", 0.45, _rows({"plane": [0.1, 0.3], "lamp": [0.1], "procedural-primitive-000": [0.1],
                                                "procedural-lathe-000": [0.1]}))
    point = product.curve_point(run, ev)
    assert point["cpu_h"] == 1.5 and point["depth_steps"] == 100 and point["inpaint_steps"] == 0
    assert math.isclose(point["mean_cd"], 0.125)
    rows = product.append_curve(tmp_path / "curve.csv", point, "round 1")
    rows = product.append_curve(tmp_path / "curve.csv", dict(point, cpu_h=0.0, mean_cd=0.2), "warm start")
    rows = product.append_curve(tmp_path / "curve.csv", point, "round 1")  # replaced, not duplicated
    assert [r["label"] for r in rows] == ["warm start", "round 1"]
    assert [r["installed"] for r in rows] == ["", ""]
    rows = product.append_curve(tmp_path / "curve.csv", dict(point, cpu_h=2.0, mean_cd=0.1), "round 2", installed=True)
    assert [(r["label"], r["installed"]) for r in rows] == [("warm start", ""), ("round 1", ""), ("round 2", "yes")]
    product.plot_curve(rows, tmp_path / "curve.png")
    assert (tmp_path / "curve.png").stat().st_size > 1000
    # a run that started from weights trained before: their hours come first
    assert product.curve_point(run, ev, base_hours=2.25)["cpu_h"] == 3.75
    assert product.curve_point(None, ev, base_hours=2.25)["cpu_h"] == 2.25
    with pytest.raises(ValueError, match="base hours"):
        product.curve_point(run, ev, base_hours=-1.0)
    # weights taken from the depth stage, before the refiner ran: only the depth stage's hours count
    depth_only = product.curve_point(run, ev, stages=("depth",))
    assert depth_only["cpu_h"] == 1.0 and depth_only["refine_steps"] == 0 and depth_only["depth_steps"] == 100
    with pytest.raises(ValueError, match="stages"):
        product.curve_point(run, ev, stages=("depht",))
    with pytest.raises(ValueError, match="no view in common"):
        product.compare_table(ev, _eval_dir(tmp_path / "x", 0.45, []), MANIFEST)


def test_compare_table_reads_the_product_folders_chosen_row(tmp_path):
    """--product-row: the product folder's oracle row against the protocol's GenRe, at that row's own level."""
    rows = _rows({"plane": [0.10, 0.20], "lamp": [0.11], "procedural-primitive-000": [0.04], "procedural-lathe-000": [0.10]})
    oracle = [(key, shape, cls, "GenRe-SphOracle", cd / 2) for key, shape, cls, row, cd in rows if row == "GenRe"]
    a = _eval_dir(tmp_path / "a", 0.45, rows + oracle)
    chosen = json.loads((a / "thresholds.json").read_text())
    chosen["seen"]["GenRe-SphOracle"] = 0.45
    (a / "thresholds.json").write_text(json.dumps(chosen))
    b = _eval_dir(tmp_path / "b", 0.50, _rows({"plane": [0.16, 0.14], "lamp": [0.24], "procedural-primitive-000": [0.09],
                                               "procedural-lathe-000": [0.10]}))
    text = product.compare_table(a, b, MANIFEST, product_row="GenRe-SphOracle")
    lines = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]] for line in text.splitlines() if line.startswith("| ")}
    # half of GenRe's figures: all (0.075 + 0.055 + 0.02 + 0.05) / 4 = 0.050; the protocol's unchanged (0.145)
    assert lines["all"][:4] == ["4", "0.050", "0.145", "0.345"]
    assert lines["regular primitives"][:3] == ["1", "0.020", "0.090"] and lines["regular primitives"][5] == "1.00×"
    assert "its row GenRe-SphOracle" in text
    # the default row is still GenRe
    assert "| all | 4 | 0.100 | 0.145 |" in product.compare_table(a, b, MANIFEST)
    with pytest.raises(ValueError, match="no row 'GenRe-Oracle'"):
        product.compare_table(a, b, MANIFEST, product_row="GenRe-Oracle")


def test_fit_table_puts_training_views_beside_the_test_split(tmp_path):
    train = _eval_dir(tmp_path / "train", 0.45, _rows({"plane": [0.06, 0.08], "lamp": [0.05], "procedural-primitive-000": [0.03],
                                                       "procedural-lathe-000": [0.04]}))
    test = _eval_dir(tmp_path / "test", 0.45, _rows({"plane": [0.10, 0.20], "lamp": [0.11], "procedural-primitive-000": [0.04],
                                                     "procedural-lathe-000": [0.10]}))
    text = product.fit_table([("installed", train, test)])
    row = [c.strip() for c in text.splitlines()[2].split("|")[1:-1]]
    # train: (0.07 + 0.05 + 0.03 + 0.04) / 4 = 0.0475 over a floor of 0.02; test 0.100 (see above); 0.0475 / 0.1 = 0.475
    assert row == ["installed", "5", "0.0475", "2.38×", "5", "0.1000", "5.00×", "0.475"]
    out = tmp_path / "fit.md"
    assert product.main(["fit", "--model", "installed", str(train), str(test), "--out", str(out)]) == 0
    assert out.read_text() == text


def test_rule_figures_are_per_view_means_over_the_shared_views(tmp_path, capsys):
    a = _eval_dir(tmp_path / "a", 0.45, _rows({"plane": [0.10, 0.20], "lamp": [0.11], "procedural-primitive-000": [0.04],
                                               "procedural-lathe-000": [0.10]}))
    b_rows = _rows({"plane": [0.16, 0.14], "lamp": [0.24], "procedural-primitive-000": [0.09], "procedural-lathe-000": [0.10]})
    b = _eval_dir(tmp_path / "b", 0.45, [r for r in b_rows if r[1] != "lamp"])  # the candidate lacks the lamp's view
    f = product.rule_figures(a, b)
    # shared views: plane/000, plane/001, primitive, lathe; installed (0.10 + 0.20 + 0.04 + 0.10) / 4 = 0.11,
    # candidate (0.16 + 0.14 + 0.09 + 0.10) / 4 = 0.1225; lower only on plane/001
    assert f["views"] == 4 and f["better"] == 1
    assert f["installed"] == pytest.approx(0.11) and f["candidate"] == pytest.approx(0.1225)
    assert f["change_percent"] == pytest.approx(100 * (0.1225 / 0.11 - 1))
    assert product.main(["rule", "--installed", str(a), "--candidate", str(b)]) == 0
    # the same views' noise floor (0.02 each) beside: 0.1225 / 0.02 = 6.125
    assert f["floor"] == pytest.approx(0.02)
    assert capsys.readouterr().out.strip() == ("4 views: candidate 0.12250 against installed 0.11000 (+11.36 %), lower on 1; "
                                               "noise floor 0.02000, the candidate 6.12× it")
    assert product.rule_figures(a, b, threshold=0.50)["installed"] == pytest.approx(9.0)  # read at the level given
    # the candidate's own row named apart (a swept mesh option): read from the candidate only
    swept = [(k, sh, c, "GenRe [visible_fusion=on]", cd / 2) for k, sh, c, row, cd in b_rows if row == "GenRe"]
    c = _eval_dir(tmp_path / "c", 0.45, b_rows + swept)
    g = product.rule_figures(a, c, threshold=0.45, candidate_row="GenRe [visible_fusion=on]")
    assert g["views"] == 5 and g["candidate"] == pytest.approx((0.16 + 0.14 + 0.24 + 0.09 + 0.10) / 10)
    with pytest.raises(ValueError, match="share no scored view"):
        product.rule_figures(c, a, threshold=0.45, candidate_row="GenRe [visible_fusion=on]")  # the installed lacks it


def test_rule_figures_by_kind_show_where_a_change_lands(tmp_path, capsys):
    a = _eval_dir(tmp_path / "a", 0.45, _rows({"plane": [0.10, 0.20], "lamp": [0.11], "procedural-primitive-000": [0.04],
                                               "procedural-lathe-000": [0.10]}))
    b = _eval_dir(tmp_path / "b", 0.45, _rows({"plane": [0.16, 0.14], "lamp": [0.11], "procedural-primitive-000": [0.06],
                                               "procedural-lathe-000": [0.10]}))
    f = product.rule_figures(a, b, manifest=MANIFEST)
    kinds = f["by_kind"]
    assert sorted(kinds) == ["airplane", "cube", "lamp", "lathe"]  # the primitive by its kind, the rest by class
    assert kinds["airplane"]["views"] == 2 and kinds["airplane"]["better"] == 1
    assert kinds["airplane"]["change_percent"] == pytest.approx(0.0)  # (0.16 + 0.14) / 2 = (0.10 + 0.20) / 2
    assert kinds["cube"]["change_percent"] == pytest.approx(50.0) and kinds["lamp"]["change_percent"] == pytest.approx(0.0)
    assert sum(g["views"] for g in kinds.values()) == f["views"] == 5
    manifest = tmp_path / "manifest.json"
    manifest.write_text(json.dumps(MANIFEST))
    assert product.main(["rule", "--installed", str(a), "--candidate", str(b), "--by-kind", str(manifest)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("5 views:") and ("  cube: 1 views: candidate 0.06000 against installed 0.04000 (+50.00 %), lower on 0; "
                                                "noise floor 0.02000, the candidate 3.00× it") in lines


def _flat_dir(path, ratios):
    """A 'genre eval' folder of the flat group: one view per ratio, truth's depth ÷ width 0.1, the mesh's ratio × 0.1."""
    path.mkdir(parents=True)
    cols = ["key", "shape", "view", "class", "groups", "row", "dw_true", "dw@0.45", "dw@0.50"]
    with (path / "per_view.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols)
        w.writeheader()
        for i, r in enumerate(ratios):
            for row, dw in (("GenRe", 0.1 * r), (FLOOR, 0.1)):
                w.writerow({"key": f"flat-plate-{i:03d}/000", "shape": f"flat-plate-{i:03d}", "view": "000",
                            "class": "thin-plate", "groups": "flat-from-above", "row": row, "dw_true": 0.1,
                            "dw@0.45": dw, "dw@0.50": 99.0})  # another level's figure: never read at 0.45
    return path


def _rule_root(root, scale, flat_ratios):
    """One folder of the rule's score sets: every set's GenRe CDs the base ones times ``scale[set]``."""
    base = {"plane": [0.10, 0.20], "lamp": [0.11], "procedural-primitive-000": [0.04], "procedural-lathe-000": [0.10]}
    for names in product.RULE_SETS.values():
        for name in names:
            _eval_dir(root / name, 0.45, _rows({k: [c * scale.get(name, 1.0) for c in v] for k, v in base.items()}))
    _flat_dir(root / "flat", flat_ratios)
    (root / "photos_flat").mkdir()
    thinnest = 0.1 * float(np.median(flat_ratios))  # eval_photos.py's columns, "judged true" twice as it writes them
    (root / "photos_flat" / "photos.csv").write_text(
        "photo,depth/width (hand mask),judged true,thinnest depth/width,judged true,tilt°\n"
        f"plate,0.7,0.85,{thinnest:.2f},0.20,+34\n")
    return root


def test_the_verdict_applies_every_bar_of_the_rule(tmp_path, capsys):
    installed = _rule_root(tmp_path / "i", {}, [8.0, 9.0, 10.0])
    # photo-like halves -1.5 % and -0.6 % (mean -1.05 %), as rendered -3 % and +1 % (mean -1 %), primitives +0.9 %,
    # the flat group's median ratio 6 against 9: every bar holds, two of them just
    good = {"product_eval_photo": 0.985, "product_up_photo": 0.994, "product_eval": 0.97, "product_up": 1.01,
            "primitives_eval": 1.009}
    v = product.verdict(installed, _rule_root(tmp_path / "good", good, [6.0, 6.0, 12.0]))
    assert v["install"] and all(p["holds"] for p in v["parts"].values())
    assert v["parts"]["photo-like mean"]["figure"] == pytest.approx(-1.05)
    assert v["parts"]["as rendered mean"]["figure"] == pytest.approx(-1.0)
    assert v["parts"]["flat group depth ÷ width ratio"]["figure"] == pytest.approx(6.0)
    assert v["parts"]["flat group depth ÷ width ratio"]["bar"] == pytest.approx(9.0)
    assert v["product_mean"] == pytest.approx((-1.5 - 0.6 - 3.0 + 1.0) / 4)
    assert v["beside"] == {"plate": {"installed": 0.9, "candidate": 0.6, "truth": 0.2}}  # reported, not a part
    assert product.flat_photos(tmp_path / "nowhere") == {}  # no photos scored: nothing beside
    # each bar broken alone fails the whole
    for name, worse in [("product_up_photo", 0.999), ("product_up", 1.021), ("product_eval", 1.001),
                        ("primitives_eval", 1.011)]:
        v = product.verdict(installed, _rule_root(tmp_path / f"bad-{name}", {**good, name: worse}, [6.0]))
        assert not v["install"], name
    assert not product.verdict(installed, _rule_root(tmp_path / "thick", good, [9.5]))["install"]
    assert product.verdict(installed, tmp_path / "thick", product.ProductRule(flat_no_worse=False))["install"]
    assert product.main(["verdict", "--installed", str(installed), "--candidate", str(tmp_path / "good"),
                         "--json", str(tmp_path / "v.json")]) == 0
    out = capsys.readouterr().out
    assert "| photo-like mean | -1.05 % | ≤ -1.00 % | yes |" in out and "\ninstall: yes (level 0.45)\n" in out
    assert "\nBeside: the mean of the four product sets' changes -1.02 %\n" in out
    assert out.rstrip().endswith("plate 0.90 → 0.60 (0.20)")
    assert json.loads((tmp_path / "v.json").read_text())["install"] is True
    assert product.main(["verdict", "--installed", str(installed), "--candidate", str(tmp_path / "bad-product_up")]) == 0
    assert "| as rendered, product_up | +2.10 % | ≤ +2.00 % | **no** |" in capsys.readouterr().out


def _two_shape_root(root, cds):
    """The four product sets, each one view of shapes s1 and s2 with GenRe CDs ``cds`` (s1, s2)."""
    for names in (product.RULE_SETS["photo-like"], product.RULE_SETS["as rendered"]):
        for name in names:
            _eval_dir(root / name, 0.45, [(f"{s}/000", s, "lamp", "GenRe", c) for s, c in zip(("s1", "s2"), cds)])
    return root


def test_the_pooled_change_resamples_shapes_so_its_interval_spans_the_shapes_own_changes(tmp_path):
    installed = _two_shape_root(tmp_path / "i", (0.10, 0.10))
    names = [n for k in ("photo-like", "as rendered") for n in product.RULE_SETS[k]]
    dirs = lambda root: [root / n for n in names]  # noqa: E731
    # s1 10 % lower, s2 6 % higher: pooled -2 %. Two shapes drawn with replacement give s1 twice (1/4: -10 %), one
    # of each (1/2: -2 %) or s2 twice (1/4: +6 %), so the 2.5 and 97.5 percentiles are the shapes' own changes
    f = product.pooled_change(dirs(installed), dirs(_two_shape_root(tmp_path / "c", (0.09, 0.106))), 0.45)
    assert f["change"] == pytest.approx(-2.0) and (f["shapes"], f["views"]) == (2, 8)
    assert f["low"] == pytest.approx(-10.0) and f["high"] == pytest.approx(6.0)
    # every view 0.3 % lower: every resample says so, and the interval closes on the change
    f = product.pooled_change(dirs(installed), dirs(_two_shape_root(tmp_path / "even", (0.0997, 0.0997))), 0.45)
    assert f["low"] == pytest.approx(-0.3) and f["high"] == pytest.approx(-0.3)


def test_the_second_path_installs_a_candidate_no_worse_and_flatter_and_nothing_else(tmp_path, capsys):
    installed = _rule_root(tmp_path / "i", {}, [8.0, 9.0, 10.0])
    # every product set 0.3 % lower (ProductRule's 1 % not reached), primitives no worse, flat 7.6 against 9 (0.84)
    even = {"product_eval_photo": 0.997, "product_up_photo": 0.997, "product_eval": 0.997, "product_up": 0.997,
            "primitives_eval": 1.0}
    v = product.verdict(installed, _rule_root(tmp_path / "even", even, [7.6]), pareto=product.ParetoRule())
    assert not v["product_rule_install"] and v["pareto"]["install"] and v["install"]
    parts = v["pareto"]["parts"]
    assert parts["product sets pooled, upper 95 %"]["figure"] == pytest.approx(-0.3)
    assert parts["flat group depth ÷ width ratio"]["bar"] == pytest.approx(0.85 * 9.0)
    # each bar broken alone: one set 1.2 % worse (pooled still lower), the primitives 0.1 % worse, the flat group
    # only 0.87 of the installed file's, every set 0.6 % worse
    for name, scale, flat in [("one set", {**even, "product_up": 1.012}, [7.6]),
                              ("primitives", {**even, "primitives_eval": 1.001}, [7.6]),
                              ("flat", even, [7.83]),
                              ("product", {k: (1.006 if k != "primitives_eval" else 1.0) for k in even}, [7.6])]:
        v = product.verdict(installed, _rule_root(tmp_path / name.replace(" ", "-"), scale, flat),
                            pareto=product.ParetoRule())
        assert not v["pareto"]["install"] and not v["install"], name
    assert product.main(["verdict", "--installed", str(installed), "--candidate", str(tmp_path / "even"),
                         "--pareto"]) == 0
    out = capsys.readouterr().out
    assert "Second path (ParetoRule): the four product sets pooled -0.30 %" in out
    assert "| flat group depth ÷ width ratio | 7.60× | ≤ 7.65× | yes |" in out
    assert "by ProductRule: no; by ParetoRule: yes" in out and "\ninstall: yes (level 0.45)\n" in out
    with pytest.raises(SystemExit):
        product.main(["verdict", "--installed", str(installed), "--candidate", str(tmp_path / "even"), "--pareto",
                      "--no-flat"])
