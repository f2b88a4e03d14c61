import math

import numpy as np
import pytest
import torch

from genre_backend import frame
from genre_backend.config import CameraConfig, get_preset
from genre_backend.geometry.analytic import sphere_depth, sphere_silhouette_radius_px

CAM = CameraConfig()


def test_intrinsics_match_the_original_camera():
    k = frame.intrinsics(CAM, 256)
    assert k[0, 0].item() == pytest.approx(418.3, abs=0.1)
    assert k[0, 2].item() == 128.0 and k[1, 2].item() == 128.0
    assert CAM.fov_deg == pytest.approx(34.0, abs=0.05)


def test_camera_rotation_is_orthonormal_and_oriented():
    az = torch.tensor([0.0, 90.0, 33.0, -120.0])
    el = torch.tensor([0.0, 0.0, 20.0, -15.0])
    rot = frame.camera_rotation(az, el, dtype=torch.float64)
    eye = torch.eye(3, dtype=torch.float64).expand(4, 3, 3)
    assert torch.allclose(rot.transpose(1, 2) @ rot, eye, atol=1e-12)
    assert torch.allclose(torch.linalg.det(rot), torch.ones(4, dtype=torch.float64))
    loc = frame.camera_location(az, el, 2.2, dtype=torch.float64)
    # azimuth 0: in front of the object (on -Y); azimuth 90: on its right (+X)
    assert torch.allclose(loc[0], torch.tensor([0.0, -2.2, 0.0], dtype=torch.float64), atol=1e-12)
    assert torch.allclose(loc[1], torch.tensor([2.2, 0.0, 0.0], dtype=torch.float64), atol=1e-12)
    # elevation lifts the camera; the camera's up axis always has a positive Z component
    assert loc[2, 2].item() == pytest.approx(2.2 * math.sin(math.radians(20)))
    assert (rot[:, 2, 1] > 0).all()
    # the camera sits at (0, 0, d) in the view frame and its right axis is horizontal
    view = frame.object_to_view(loc[:, None, :], rot)[:, 0]
    assert torch.allclose(view, torch.tensor([0.0, 0.0, 2.2], dtype=torch.float64).expand(4, 3), atol=1e-12)
    assert torch.allclose(rot[:, 2, 0], torch.zeros(4, dtype=torch.float64), atol=1e-12)


def test_view_object_round_trip():
    rot = frame.camera_rotation(torch.tensor([10.0, 200.0]), torch.tensor([5.0, 40.0]))
    pts = torch.randn(2, 50, 3)
    assert torch.allclose(frame.view_to_object(frame.object_to_view(pts, rot), rot), pts, atol=1e-6)


@pytest.mark.parametrize("preset", ["default", "paper"])
def test_sphere_depth_back_projects_onto_the_sphere(preset):
    size = get_preset(preset).geometry.image_size
    r = 0.4
    depth = sphere_depth(CAM, size, r).float()
    pts = frame.depth_to_points(depth, CAM)[0]
    valid = frame.depth_valid_mask(depth)[0]
    assert valid.sum() > 0.95 * math.pi * sphere_silhouette_radius_px(CAM, size, r) ** 2
    err = (torch.linalg.vector_norm(pts[valid], dim=-1) - r).abs().max().item()
    assert err < 1e-4
    # projecting the points again gives back each pixel centre and its depth
    uv, z = frame.view_to_pixels(pts[valid].double(), CAM, size)
    rows, cols = torch.nonzero(valid, as_tuple=True)
    assert torch.allclose(uv[:, 0], cols.double() + 0.5, atol=1e-3)
    assert torch.allclose(uv[:, 1], rows.double() + 0.5, atol=1e-3)
    assert torch.allclose(z, depth[0][valid].double(), atol=1e-5)


def test_image_axes_follow_the_frame():
    # a point to the right of and above the centre lands right of and above the image centre
    uv, depth = frame.view_to_pixels(torch.tensor([[0.1, 0.2, 0.0]]), CAM, 128)
    assert uv[0, 0] > 64 and uv[0, 1] < 64
    assert depth[0].item() == pytest.approx(2.2)


def test_encode_raw_depth():
    raw = torch.tensor([1.5, 1e10, float("inf"), float("nan"), -1.0, 2.0])
    enc = frame.encode_raw_depth(raw)
    assert enc.tolist() == [1.5, 0.0, 0.0, 0.0, 0.0, 2.0]
    assert frame.depth_valid_mask(enc).tolist() == [True, False, False, False, False, True]


def test_blender_camera_transform_matches_the_frame():
    az, el = 37.0, 21.0
    rot = frame.camera_rotation(az, el, dtype=torch.float64)[0]
    loc = frame.camera_location(az, el, 2.2, dtype=torch.float64)[0]
    target = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    m = torch.eye(4, dtype=torch.float64)
    m[:3, :3] = rot * 1.7  # a scaled camera object: scale must be ignored
    m[:3, 3] = loc + target
    w2v = frame.blender_camera_to_view(m, target)
    pts = torch.randn(20, 3, dtype=torch.float64)
    via_blender = pts @ w2v[:3, :3].T + w2v[:3, 3]
    via_frame = frame.object_to_view((pts - target)[None], rot[None])[0]
    assert torch.allclose(via_blender, via_frame, atol=1e-12)
    # the front camera maps view up (+y) to Blender up (+Z) and the viewer side (+z) to -Y
    front = frame.VIEW_TO_BLENDER_FRONT
    assert torch.allclose(front @ torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    assert torch.allclose(front @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64))


def test_frame_agrees_with_blender_projection(tmp_path, monkeypatch):
    """An independent check: Blender's own camera projection of object points equals ours."""
    monkeypatch.setenv("BLENDER_USER_RESOURCES", str(tmp_path / "bl"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    bpy = pytest.importorskip("bpy")
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Matrix, Vector

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    size = 128
    scene.render.resolution_x = scene.render.resolution_y = size
    scene.render.resolution_percentage = 100
    cam_data = bpy.data.cameras.new("cam")
    cam_data.lens, cam_data.sensor_width, cam_data.sensor_fit = CAM.lens_mm, CAM.sensor_mm, "HORIZONTAL"
    cam = bpy.data.objects.new("cam", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    az, el = 123.0, 27.0
    rot = frame.camera_rotation(az, el, dtype=torch.float64)[0]
    loc = frame.camera_location(az, el, CAM.distance, dtype=torch.float64)[0]
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rot.numpy(), loc.numpy()
    cam.matrix_world = Matrix(m.tolist())
    bpy.context.view_layer.update()
    pts = torch.rand(30, 3, dtype=torch.float64) - 0.5
    view = frame.object_to_view(pts[None], rot[None])[0]
    uv, depth = frame.view_to_pixels(view, CAM, size)
    w2v = frame.blender_camera_to_view(np.array(cam.matrix_world))
    assert torch.allclose(pts @ w2v[:3, :3].T + w2v[:3, 3], view, atol=1e-5)
    for p, (u, v), z in zip(pts.tolist(), uv.tolist(), depth.tolist()):
        ndc = world_to_camera_view(scene, cam, Vector(p))
        # Blender: x in [0,1] left→right, y in [0,1] bottom→top, z = planar depth
        assert ndc.x * size == pytest.approx(u, abs=1e-3)
        assert (1.0 - ndc.y) * size == pytest.approx(v, abs=1e-3)
        assert ndc.z == pytest.approx(z, abs=1e-5)


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda: frame.depth_to_points(torch.zeros(2, 4, 5), CAM), "depth"),
        (lambda: frame.depth_to_points(torch.zeros(1, 4, 4, dtype=torch.int32), CAM), "float32"),
        (lambda: frame.depth_to_points(torch.full((1, 4, 4), float("nan")), CAM), "NaN"),
        (lambda: frame.camera_rotation(0.0, 90.0), "elevation"),
        (lambda: frame.object_to_view(torch.zeros(1, 5, 2), torch.eye(3)[None]), "points"),
    ],
)
def test_bad_inputs_raise_clear_errors(call, message):
    with pytest.raises(ValueError, match=message):
        call()
