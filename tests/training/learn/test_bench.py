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


def test_rows_of_a_batch_split_over_two_processes_beside_the_plain_path(capsys, tmp_path):
    weights = save_model(GenRe(TINY), tmp_path / "tiny.safetensors")
    assert main(["--stages", "depth", "--ways", "fp32", "--batch", "2", "--processes", "1,2", "--rounds", "2",
                 "--steps", "1", "--threads", "2", "--weights", str(weights)]) == 0
    out = capsys.readouterr().out
    assert "over 1,2 processes" in out.splitlines()[0]
    rows = dict(re.findall(r"^\| (depth, 2(?: \(2 processes × 1\))?) \| ([\d.]+)/s \([\d.]+×\) \|$", out, re.M))
    assert set(rows) == {"depth, 2", "depth, 2 (2 processes × 1)"} and all(float(r) > 0 for r in rows.values())
    assert "depth/2/fp32/2p" in out  # the spawned processes' set-up is reported too


@pytest.mark.parametrize("argv", [["--processes", "0"], ["--processes", "2", "--batch", "3"]])
def test_a_bad_process_count_is_refused(argv):
    with pytest.raises(SystemExit):
        main(["--stages", "depth", *argv])


def _sum_in(rank: int, init: str, out) -> None:
    import torch
    import torch.distributed as dist

    from training.learn.bench import _gradient_sum

    dist.init_process_group("gloo", init_method=init, rank=rank, world_size=2)
    a = torch.nn.Parameter(torch.zeros(2, 3, 4, 5).contiguous(memory_format=torch.channels_last))
    b = torch.nn.Parameter(torch.zeros(7))
    a.grad = (torch.arange(120.0).view(2, 3, 4, 5) * (rank + 1)).contiguous(memory_format=torch.channels_last)
    b.grad = torch.full((7,), float(rank))
    _gradient_sum(2)([a, b])
    out.put((rank, a.grad.is_contiguous(memory_format=torch.channels_last), a.grad.clone(), b.grad.clone()))
    dist.destroy_process_group()


def test_the_gradient_exchange_averages_every_gradient_over_the_processes_in_its_own_layout(tmp_path):
    import torch
    import torch.multiprocessing as mp

    ctx = mp.get_context("spawn")
    out = ctx.Queue()
    procs = [ctx.Process(target=_sum_in, args=(r, f"file://{tmp_path / 'rdv'}", out)) for r in range(2)]
    for p in procs:
        p.start()
    got = [out.get(timeout=120) for _ in procs]
    for p in procs:
        p.join(timeout=60)
    assert sorted(r for r, *_ in got) == [0, 1]
    for _, channels_last, a, b in got:
        assert channels_last  # the gradient keeps its weight's layout
        assert torch.equal(a, torch.arange(120.0).view(2, 3, 4, 5) * 1.5)  # (1× + 2×) / 2, element by element
        assert torch.equal(b, torch.full((7,), 0.5))
