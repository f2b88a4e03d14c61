"""scripts/normals_probe.py: angles between normal maps, and a depth stage's head read back from its checkpoint."""

import math

import pytest
import torch

from support.scripts import load_script
from support.tiny_data import TINY, tiny_train_config
from training.learn.train import train

normals_probe = load_script("normals_probe")


def test_angles_are_the_mean_angle_and_the_mean_one_minus_cos_over_the_kept_pixels():
    true = torch.zeros(3, 2, 2)
    true[2] = 1.0
    pred = torch.zeros(3, 2, 2)
    pred[2] = 2.0  # any length: the same direction
    pred[:, 0, 1] = torch.tensor([1.0, 0.0, 1.0])  # 45° off
    pred[:, 1, 0] = torch.tensor([0.0, -3.0, 0.0])  # 90° off, but not kept
    keep = torch.tensor([[True, True], [False, True]])
    angle, one_minus_cos = normals_probe.angles(pred, true, keep)
    assert angle == pytest.approx(15.0, abs=1e-3)
    assert one_minus_cos == pytest.approx((1 - math.cos(math.pi / 4)) / 3, abs=1e-6)


@pytest.mark.slow
def test_the_probe_reads_a_stage_s_head_and_its_depth_matches_the_same_weights_file(tiny_views, tmp_path, capsys):
    run = tmp_path / "run"
    train(tiny_train_config("depth", tiny_views, run, steps=2, normals_weight=1.0), TINY)
    final = run / "depth" / "final.safetensors"  # the checkpoint's nets at its last step
    assert normals_probe.main(["--views", str(tiny_views), "--stage", str(run / "depth"), "--weights", str(final)]) == 0
    rows = [line.split(" | ") for line in capsys.readouterr().out.splitlines()[2:]]
    assert [r[1] for r in rows] == ["normals head", "its own depth's normals", f"{final}: its depth's normals"]
    own, same = rows[1][2:], rows[2][2:]
    assert own == same and int(own[0]) > 0 and 0 < float(own[1]) < 180
    plain = tmp_path / "plain"
    train(tiny_train_config("depth", tiny_views, plain, steps=1), TINY)
    with pytest.raises(SystemExit, match="no normals head"):
        normals_probe.main(["--views", str(tiny_views), "--stage", str(plain / "depth")])
