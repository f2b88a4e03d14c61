"""``genre bench train`` (training/learn/bench.py): one row per stage and batch size, ratios to the plain path's first batch."""

from __future__ import annotations

import re

import pytest

from genre_backend.nets.model import GenRe, save_model
from support.tiny_data import TINY
from training.learn.bench import cpu_description, main


def test_rows_per_batch_size_and_the_device_named(capsys, tmp_path):
    weights = save_model(GenRe(TINY), tmp_path / "tiny.safetensors")
    assert main(["--stages", "depth", "--ways", "fp32,channels-last", "--batch", "1,2", "--rounds", "1",
                 "--steps", "1", "--threads", "1", "--weights", str(weights)]) == 0
    out = capsys.readouterr().out
    assert cpu_description() in out.splitlines()[0] and "torch CPU capability" in out.splitlines()[0]
    rows = {m.group(1): m.group(2) for m in re.finditer(r"^\| (depth, \d) \| (.*) \|$", out, re.M)}
    assert set(rows) == {"depth, 1", "depth, 2"}
    cells = [re.fullmatch(r"([\d.]+)/s \(([\d.]+)×\)", c.strip()) for c in rows["depth, 1"].split("|")]
    assert all(cells) and cells[0].group(2) == "1.00"  # the plain path at the first batch is the reference
    for row in rows.values():  # each ratio is its rate over the reference rate
        for c in row.split("|"):
            rate, ratio = map(float, re.fullmatch(r"([\d.]+)/s \(([\d.]+)×\)", c.strip()).groups())
            assert ratio == pytest.approx(rate / float(cells[0].group(1)), abs=0.011)


@pytest.mark.parametrize("batch", ["4,x", "0", ","])
def test_a_bad_batch_list_is_refused(batch):
    with pytest.raises(SystemExit):
        main(["--stages", "depth", "--batch", batch])
