"""scripts/sph_hull.py's trim gate: the per-view files read back and every candidate gate scored on them."""

import csv

import pytest

from support.scripts import load_script

sph_hull = load_script("sph_hull")


def _write(path, rows):
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["key", "trim", "cd", "ratio", "thin", "kept"], lineterminator="\n")
        w.writeheader()
        for key, off, trimmed, thin in rows:
            w.writerow({"key": key, "trim": "off", "cd": off, "ratio": 3.0, "thin": 0.8, "kept": 1.0})
            w.writerow({"key": key, "trim": "spread 2", "cd": trimmed, "ratio": 1.5, "thin": thin, "kept": 0.5})


def test_gates_pick_the_trimmed_cd_below_the_threshold_and_average_the_sets_means(tmp_path, capsys):
    # a set where trimming helps the flat-reading views (thin 0.1) and hurts the others (thin 0.6), and one of flat views
    _write(tmp_path / "a.csv", [("r/0", 0.10, 0.14, 0.6), ("r/1", 0.12, 0.16, 0.6), ("f/0", 0.20, 0.10, 0.1)])
    _write(tmp_path / "b.csv", [("p/0", 0.30, 0.20, 0.1), ("p/1", 0.30, 0.40, float("nan"))])
    sets = [sph_hull._read_set([tmp_path / "a.csv"], "spread 2"), sph_hull._read_set([tmp_path / "b.csv"], "spread 2")]
    cds, ratios = sph_hull._gated(sets[0], "thin", 0.3)
    assert list(cds) == pytest.approx([0.10, 0.12, 0.10]) and list(ratios) == [3.0, 3.0, 1.5]
    assert list(sph_hull._gated(sets[1], "thin", 0.3)[0]) == pytest.approx([0.20, 0.30])  # a nan feature never trims
    assert list(sph_hull._gated(sets[1], None, float("inf"))[0]) == pytest.approx([0.20, 0.40])  # always
    assert list(sph_hull._gated(sets[1], None, -float("inf"))[0]) == pytest.approx([0.30, 0.30])  # never

    assert sph_hull.main(["--choose-gate", str(tmp_path / "a.csv"), str(tmp_path / "b.csv")]) == 0
    table = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| ")][2:]
    best = [c.strip() for c in table[0].split("|")[1:-1]]
    # the lowest mean of the two sets' means: trim where thin < τ for a τ between 0.1 and 0.6 (a 0.34, b 0.25)
    assert best[0].startswith("thin <") and float(best[2]) == pytest.approx((0.32 / 3 + 0.25) / 2, abs=1e-5)
    never = next(row for row in table if row.startswith("| never"))
    assert float(never.split("|")[3]) == pytest.approx((0.42 / 3 + 0.30) / 2, abs=1e-5)

    assert sph_hull.main(["--choose-gate", str(tmp_path / "a.csv"), "--gate", "thin:0.3"]) == 0
    row = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| a ")][0].split("|")
    assert float(row[4]) == pytest.approx(0.32 / 3, abs=1e-5) and row[6].strip() == "1 / 0" and row[7].strip() == "1"
    with pytest.raises(SystemExit):
        sph_hull.main(["--choose-gate", str(tmp_path / "a.csv"), "--gate", "volume:0.3"])
