"""scripts/outline_probe.py: its three shapes share one outline from above and differ in depth as it says."""

import importlib.util
from pathlib import Path

import numpy as np

_SPEC = importlib.util.spec_from_file_location("outline_probe", Path(__file__).parents[3] / "scripts" / "outline_probe.py")
outline_probe = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(outline_probe)


def test_the_ball_the_flattened_ellipsoid_and_the_disc_share_a_footprint_and_not_a_depth():
    shapes = outline_probe.probe_shapes()
    width = 2 * outline_probe.RADIUS
    for name, mesh in shapes.items():
        np.testing.assert_allclose(mesh.extents[:2], [width, width], rtol=0.01, err_msg=name)
        assert mesh.is_watertight, name
    depth = {name: mesh.extents[2] / width for name, mesh in shapes.items()}
    assert np.isclose(depth["ball"], 1.0, rtol=0.01)
    assert np.isclose(depth["dome"], 0.35, rtol=0.01)
    assert np.isclose(depth["disc"], 0.03, rtol=0.01)


def test_depth_range_reads_only_the_inner_pixels():
    depth = np.array([[0.0, 5.0], [2.0, 2.5]])
    inner = np.array([[False, False], [True, True]])
    assert outline_probe.depth_range(depth, inner) == 0.5
