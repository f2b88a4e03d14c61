"""scripts/inpaint_errors.py: the hidden and visible side's scores of a full spherical map against the truth."""

import numpy as np
import torch

from support.scripts import load_script

inpaint_errors = load_script("inpaint_errors")

NOHIT_MIN = 0.99  # a map value s = 1 − r at or above it is "no hit"


def _truth(size: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """A full map of radius 0.4 everywhere but one no-hit column; the left half seen."""
    true = torch.full((size, size), 0.6)
    true[:, -1] = 1.0
    seen = torch.zeros(size, size, dtype=torch.bool)
    seen[:, : size // 2] = True
    return true, seen


def test_an_inflated_map_has_a_positive_radius_bias_and_a_cutting_one_a_negative():
    true, seen = _truth()
    grown = torch.where(true < NOHIT_MIN, true - 0.1, true)  # every hit 0.1 further out
    s = inpaint_errors.scores(grown, true, seen, NOHIT_MIN)
    assert np.isclose(s["radius_bias"], 0.1, atol=1e-6) and np.isclose(s["rmse"], 0.1, atol=1e-6)
    assert s["hit_iou"] == 1.0 and s["visible"] > 0.099
    cut = torch.where(true < NOHIT_MIN, true + 0.05, true)
    assert np.isclose(inpaint_errors.scores(cut, true, seen, NOHIT_MIN)["radius_bias"], -0.05, atol=1e-6)


def test_a_missed_hidden_column_costs_its_radius_and_the_hit_iou():
    true, seen = _truth()
    pred = true.clone()
    pred[:, 4] = 1.0  # one of the three hidden hit columns predicted empty
    s = inpaint_errors.scores(pred, true, seen, NOHIT_MIN)
    assert np.isclose(s["hit_iou"], 2 / 3, atol=1e-6)  # hidden hits: 3 true columns, 2 predicted, no extra
    # over the true hidden hits (24 pixels), 8 miss by the radius 0.4
    assert np.isclose(s["radius_bias"], -0.4 / 3, atol=1e-6) and np.isclose(s["rmse_hits"], np.sqrt(0.16 / 3), atol=1e-6)
    assert s["visible"] == 0.0
