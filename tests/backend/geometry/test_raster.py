"""seen_from_camera: which points of a surface the camera sees, against analytic shapes."""

import math

import pytest
import torch
import trimesh

from genre_backend.config import get_preset
from genre_backend.geometry.metrics import sample_surface
from genre_backend.geometry.raster import seen_from_camera


def _triangles(mesh: trimesh.Trimesh) -> torch.Tensor:
    return torch.tensor(mesh.vertices[mesh.faces], dtype=torch.float64)


def test_a_sphere_shows_the_cap_its_tangent_cone_bounds():
    # from a point at distance d, a sphere of radius r shows the cap up to cos(theta) = r / d: (1 - r/d) / 2 of its area
    camera = get_preset("default").camera
    r = 0.4
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=r)
    points = sample_surface(mesh.vertices, mesh.faces, 20_000, seed=3)
    seen = seen_from_camera(points, _triangles(mesh), camera)
    assert float(seen.float().mean()) == pytest.approx((1 - r / camera.distance) / 2, abs=0.01)
    # and exactly the points on the near side of the tangent plane's circle
    cos_theta = points[:, 2].double() / r
    assert bool(seen[cos_theta > r / camera.distance + 0.1].all())
    assert not bool(seen[cos_theta < r / camera.distance - 0.05].any())


def test_a_cube_face_on_shows_its_front_face_and_a_tolerance_band():
    camera = get_preset("default").camera
    side, tol = 0.5, 0.02
    mesh = trimesh.creation.box(extents=(side, side, side))
    points = sample_surface(mesh.vertices, mesh.faces, 30_000, seed=4)
    seen = seen_from_camera(points, _triangles(mesh), camera, tolerance=tol)
    z = points[:, 2].double()
    assert bool(seen[z > side / 2 - 1e-6].all())  # the front face
    assert not bool(seen[z < side / 2 - tol - 0.005].any())  # the sides beyond the band and the back
    band = 4 * side * tol / (6 * side * side)  # the sides' strips within the tolerance of the front's depth
    assert float(seen.float().mean()) == pytest.approx(1 / 6 + band, abs=0.01)


def test_points_outside_the_picture_are_hidden():
    camera = get_preset("default").camera
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    far_off = torch.tensor([[5.0, 0.0, 0.0], [0.0, 0.0, 0.3]])
    seen = seen_from_camera(far_off, _triangles(mesh), camera)
    assert seen.tolist() == [False, True]
    assert math.isclose(camera.distance, 2.2)
