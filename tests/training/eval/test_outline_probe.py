"""scripts/outline_probe.py: its three shapes share one outline from above and differ in depth as it says."""

import numpy as np

from support.scripts import load_script

outline_probe = load_script("outline_probe")


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


def test_centre_height_of_a_paraboloid_dome_and_of_a_tilted_plane():
    # A paraboloid cap over a disc of radius R = 30 px facing the camera: depth = 2 - h (1 - r²/R²). The ring 4–6 px
    # inside the outline is r in (24, 26]: mean r² ≈ (24² + 26²) / 2. The middle is the tenth of the pixels more
    # than 2 px inside (r < 28) farthest from the outline: r < 28 √0.1, mean r² half of that squared. So the
    # middle stands h (ring r² - middle r²) / R² nearer than the ring.
    n, radius, h = 80, 30.0, 0.2
    y, x = np.mgrid[:n, :n] - (n - 1) / 2
    r2 = (x ** 2 + y ** 2) / radius ** 2
    inside = r2 < 1
    dome = 2.0 - h * (1 - r2)
    got = outline_probe.centre_height(dome, inside)
    expected = h * ((24 ** 2 + 26 ** 2) / 2 - 28 ** 2 * 0.1 / 2) / radius ** 2
    assert abs(got - expected) < 0.04 * expected, (got, expected)
    # A plane, tilted or not, square over a symmetric silhouette: the middle and the ring average the same depth.
    assert abs(outline_probe.centre_height(2.0 + 0.003 * x, inside)) < 1e-9
    np.testing.assert_raises(ValueError, outline_probe.centre_height, dome, np.zeros((n, n), bool))
