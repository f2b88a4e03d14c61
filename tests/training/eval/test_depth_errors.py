"""scripts/depth_errors.py: the relief errors of a depth prediction, and the flat plane's reference row."""

import numpy as np
import torch

from support.scripts import load_script

depth_errors = load_script("depth_errors")


class _Predicts:
    """A model whose depth net returns a fixed map, whatever the picture (only ``depth_net`` is read)."""

    def __init__(self, depth: np.ndarray):
        self.depth = torch.from_numpy(depth.astype(np.float32))[None]

    def depth_net(self, rgb):
        return {"depth": self.depth}


def _ramp_view(size: int = 32):
    """A square silhouette whose depth is a ramp 2.0 … 2.31 across it (planar, like a tilted card)."""
    mask = np.zeros((size, size), np.float32)
    mask[4:28, 4:28] = 1
    depth = np.where(mask > 0, 2.0 + 0.01 * np.arange(size)[None, :].repeat(size, 0), 0.0).astype(np.float32)
    return {"rgb": np.zeros((size, size, 3), np.uint8), "mask": mask, "depth": depth}


def test_a_shifted_truth_has_no_relief_error_and_the_flat_plane_scores_the_reliefs_own_spread():
    view = _ramp_view()
    inner = view["depth"][6:26, 6:26]  # the silhouette eroded by 2 px
    mae, ratio, offset, true_iqr = depth_errors.view_errors(_Predicts(view["depth"] + 0.05), view)
    assert mae < 1e-6 and np.isclose(ratio, 1.0) and np.isclose(offset, 0.05, atol=1e-6)
    # 20 columns 0.01 apart: the quartiles (linear between samples) at 4.75 and 14.25 steps, 0.095 apart
    assert np.isclose(true_iqr, 0.095, atol=1e-5)
    mae, ratio, offset, true_iqr = depth_errors.view_errors(None, view)
    assert np.isclose(mae, np.mean(np.abs(inner - np.median(inner))), atol=1e-6) and mae > 0.04
    assert ratio == 0.0 and np.isnan(offset) and np.isclose(true_iqr, 0.095, atol=1e-5)
    halved = 2.0 + 0.5 * (view["depth"] - 2.0)  # the same ramp at half its relief: too flat by two
    mae, ratio, _, _ = depth_errors.view_errors(_Predicts(halved), view)
    assert np.isclose(ratio, 0.5, atol=0.02) and np.isclose(mae, 0.5 * np.mean(np.abs(inner - np.median(inner))), atol=1e-3)


class _ReadsShading:
    """A depth net whose depth is the picture's red channel inside the silhouette: all of its relief is shading."""

    def depth_net(self, rgb):
        return {"depth": 2.0 + 0.31 * rgb[:, 0]}


def test_painting_the_object_one_colour_keeps_the_background_and_leaves_only_the_silhouette():
    view = _ramp_view()
    shade = np.round(255 * (view["depth"] - 2.0) / 0.31).clip(0, 255).astype(np.uint8)  # shading follows the ramp
    rgb = np.stack([shade, np.full_like(shade, 40), np.full_like(shade, 200)], -1)
    rgb[view["mask"] == 0] = (10, 250, 90)
    view["rgb"] = rgb
    flat = depth_errors.flat_coloured(view)
    inside, outside = view["mask"] > 0, view["mask"] == 0
    assert np.array_equal(flat["rgb"][outside], rgb[outside])
    assert np.ptp(flat["rgb"][inside].astype(int), axis=0).max() == 0  # one colour inside
    assert np.allclose(flat["rgb"][inside][0], rgb[inside].mean(0), atol=0.5)
    # the net that reads shading recovers the ramp from the picture, and nothing from the painted one
    mae_rgb, ratio_rgb, _, _ = depth_errors.view_errors(_ReadsShading(), view)
    mae_flat, ratio_flat, _, _ = depth_errors.view_errors(_ReadsShading(), flat)
    assert mae_rgb < 2e-3 and np.isclose(ratio_rgb, 1.0, atol=0.02)
    assert ratio_flat == 0.0 and np.isclose(mae_flat, depth_errors.view_errors(None, view)[0], atol=1e-6)


def test_follows_is_one_when_deeper_views_get_deeper_reliefs_and_minus_one_when_reversed():
    steep = [0.01 * (k + 1) for k in range(6)]  # six views, their true relief IQRs rising
    view = _ramp_view()
    rows = {}
    for name, scale in (("in order", lambda k: 0.5), ("reversed", lambda k: steep[5 - k] / steep[k])):
        errors = []
        for k, slope in enumerate(steep):  # each view a ramp of its own slope; the prediction the same ramp times scale(k)
            v = dict(view, depth=np.where(view["mask"] > 0, 2.0 + slope * np.arange(32)[None, :].repeat(32, 0), 0.0).astype(np.float32))
            errors.append(depth_errors.view_errors(_Predicts(2.0 + scale(k) * (v["depth"] - 2.0)), v))
        rows[name] = depth_errors.summary_cells(errors, np.zeros(6))
    assert rows["in order"][0] == "6" and rows["in order"][3] == "0.50" and rows["in order"][-2] == "1.00"
    assert rows["reversed"][-2] == "-1.00"  # the steepest view predicted as the gentlest, and so on
    flat = depth_errors.summary_cells([depth_errors.view_errors(None, view)] * 3, np.zeros(3), flat_plane=True)
    assert flat[4] == "–" and flat[-2] == "–" and flat[3] == "0.00" and flat[-1] == "–"


def _from_above(slope: float, size: int = 32) -> dict:
    """A card seen from straight above (camera frame = object frame), its top tilted: planar depth falls by ``slope``
    a column, so its height along the object's up is ``slope`` times the silhouette's 24 columns."""
    view = _ramp_view(size)
    cols = np.arange(size)[None, :].repeat(size, 0)
    view["depth"] = np.where(view["mask"] > 0, 2.2 - slope * cols, 0.0).astype(np.float32)
    view["camera"] = {"rotation_cam_to_obj": np.eye(3).tolist()}
    return view


def test_the_seen_surface_twice_as_tilted_is_twice_as_high_for_its_width_and_a_level_one_is_right():
    view = _from_above(0.002)
    width = np.ptp(np.percentile(depth_errors.depth_to_points(torch.from_numpy(view["depth"])[None],
                                                              depth_errors.CameraConfig())[0, 4:28, 4:28, 0], [1, 99]))
    # the truth's height: 0.002 a column; the 1st and 99th percentiles of 24 columns of 24 pixels are the first
    # and last columns, 23 apart (the width, the larger of the spreads along x and y, moves by under 1 % with the depth
    # across the card)
    assert np.isclose(depth_errors.up_over_width(view["depth"], view), 0.002 * 23 / width, rtol=0.01)
    assert np.isclose(depth_errors.seen_up_ratio(_Predicts(view["depth"]), view), 1.0)
    steeper = _from_above(0.004)["depth"]
    assert np.isclose(depth_errors.seen_up_ratio(_Predicts(steeper), view), 2.0, rtol=0.03)
    # the same card with the object's up along the camera's y (seen from the side, standing): its height is its 24
    # rows, as tall as it is wide
    side = dict(view, camera={"rotation_cam_to_obj": [[1, 0, 0], [0, 0, 1], [0, 1, 0]]})
    assert depth_errors.up_over_width(view["depth"], side) > 0.9  # 24 rows tall, 24 columns wide


def test_the_plain_backdrop_greys_only_what_lies_outside_the_silhouette():
    view = _ramp_view()
    view["rgb"] = np.full((32, 32, 3), (200, 30, 60), np.uint8)
    grey = depth_errors.on_backdrop(view)["rgb"]
    inside = view["mask"] > 0
    assert np.array_equal(grey[inside], view["rgb"][inside])
    assert np.all(grey[~inside] == 128)  # the neutral grey, 0.5 of 255 rounded
