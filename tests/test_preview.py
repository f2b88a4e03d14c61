"""Mesh previews rendered with Blender: the cameras sit where the view frame says."""

import math

import numpy as np
import pytest
import trimesh

from genre_backend.geometry.analytic import sphere_silhouette_radius_px
from genre_backend.inference.blender import render_meshes
from genre_backend.config import CameraConfig

SIZE = 96


def _silhouette(rgb: np.ndarray) -> np.ndarray:
    return (rgb.astype(int).sum(axis=2) < 3 * 250)  # the background is pure white


@pytest.fixture(scope="module")
def renders():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.3)
    # a small cube at +x (right in the photo) and -z (away from the camera)
    cube = trimesh.creation.box(extents=[0.2] * 3)
    cube.apply_translation([0.25, 0.0, -0.25])
    return render_meshes([(sphere.vertices, sphere.faces), (cube.vertices, cube.faces)], size=SIZE, samples=4)


def test_sphere_silhouette_matches_the_analytic_disc_from_both_cameras(renders):
    expected_r = sphere_silhouette_radius_px(CameraConfig(), SIZE, 0.3)
    for img in renders[0]:
        sil = _silhouette(img)
        area_r = math.sqrt(sil.sum() / math.pi)
        assert area_r == pytest.approx(expected_r, abs=1.0)
        ys, xs = np.nonzero(sil)
        assert xs.mean() == pytest.approx((SIZE - 1) / 2, abs=0.5)
        assert ys.mean() == pytest.approx((SIZE - 1) / 2, abs=0.5)


def test_front_and_side_cameras_are_oriented_as_documented(renders):
    front, side = (_silhouette(img) for img in renders[1])
    c = (SIZE - 1) / 2
    # photo viewpoint: +x is to the right
    assert np.nonzero(front)[1].mean() > c + 10
    # from the right (camera on +x looking along -x): the image's right is -z, away from the camera
    assert np.nonzero(side)[1].mean() > c + 10
    # the cube's y extent is centred in both
    for sil in (front, side):
        assert np.nonzero(sil)[0].mean() == pytest.approx(c, abs=1.0)


def test_bad_arguments():
    with pytest.raises(ValueError, match="positive"):
        render_meshes([], size=0)
