"""scripts/shading_spread.py: the luminance spread inside a silhouette, and a shape's thickness."""

import numpy as np

from support.scripts import load_script

shading_spread = load_script("shading_spread")


def test_an_evenly_lit_object_has_no_spread_and_a_grey_ramp_the_spread_of_its_percentiles():
    n = 64
    mask = np.zeros((n, n))
    mask[8:56, 8:56] = 1.0
    rgb = np.zeros((n, n, 3), np.uint8)
    rgb[...] = 255  # the background, outside the silhouette, must not count
    rgb[8:56, 8:56] = (200, 40, 90)
    assert shading_spread.luminance_spread(rgb, mask) == 0.0
    # A grey ramp across the object's columns: eroded by 2 px, columns 10..53 hold greys 10*4 .. 53*4 (of 255),
    # equally many pixels each, so the 10th and 90th percentiles of 44 equal groups are known.
    ramp = np.repeat((np.arange(n) * 4).astype(np.uint8)[None, :], n, 0)
    rgb = np.stack([ramp] * 3, -1)
    greys = np.arange(10, 54) * 4 / 255.0
    expected = np.percentile(np.repeat(greys, 44), 90) - np.percentile(np.repeat(greys, 44), 10)
    assert abs(shading_spread.luminance_spread(rgb, mask) - expected) < 1e-9
    assert shading_spread.luminance_spread(rgb, np.zeros((n, n))) is None


def test_thickness_is_the_up_extent_over_the_larger_extent_across():
    assert np.isclose(shading_spread.thickness([0.8, 0.4, 0.04]), 0.05)
    assert shading_spread.thickness([0.3, 0.6, 0.6]) == 1.0
