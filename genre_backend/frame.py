"""The one coordinate frame and the one camera of the whole project.

Two frames exist, and only these two:

**Object frame** (canonical, Blender's world convention)
    Right-handed, +Z up, the object's front faces −Y, origin at the centre of
    the object's bounding box, bounding-box diagonal 1.  Shapes are stored in
    it and the renderer places cameras around it.

**View frame** (viewer-centred; every network input, output and mesh lives here)
    Right-handed, origin at the object centre, axes tied to the camera:

    * +x points to the right of the image,
    * +y points up in the image,
    * +z points from the object toward the camera.

    The camera sits at ``(0, 0, d)`` (``d`` = :attr:`CameraConfig.distance`)
    looking along −z.  These are exactly a Blender camera's local axes, moved
    so that the origin is the point the camera looks at.  The voxel cube
    ``[-0.5, 0.5]^3`` and the unit sphere of spherical maps are centred at the
    origin of this frame.

Images: pixel ``(row i, column j)`` has its centre at ``u = j + 0.5``,
``v = i + 0.5``; row 0 is the top of the image.  The principal point is the
image centre ``(W/2, H/2)``.

Depth is **planar** (distance along the camera's viewing axis, Blender's Z
pass), not distance along the ray.  After loading, background pixels are
encoded as ``BACKGROUND_DEPTH`` (0); a pixel is valid iff its depth is > 0.
"""

from __future__ import annotations

import torch

from .config import CameraConfig
from .validation import check_tensor

__all__ = [
    "BACKGROUND_DEPTH",
    "RAW_BACKGROUND_MIN",
    "intrinsics",
    "camera_rotation",
    "camera_location",
    "object_to_view",
    "view_to_object",
    "depth_to_points",
    "view_to_pixels",
    "encode_raw_depth",
    "depth_valid_mask",
    "blender_camera_to_view",
    "VIEW_TO_BLENDER_FRONT",
]

BACKGROUND_DEPTH = 0.0
# Raw Z-pass values at or above this are background (Cycles writes 1e10).
RAW_BACKGROUND_MIN = 1e5


def intrinsics(camera: CameraConfig, image_size: int, *, dtype=torch.float32, device=None) -> torch.Tensor:
    """Pinhole intrinsics ``K`` (3, 3) float for a square image of ``image_size`` pixels.

    ``K @ [x_c, -y_c, -z_c]`` (camera looking down −z, pixel v growing downward)
    gives homogeneous pixel coordinates ``(u, v)`` with pixel centres at +0.5.
    """
    if image_size <= 0:
        raise ValueError(f"image_size must be positive, got {image_size}")
    f = camera.focal_px(image_size)
    c = image_size / 2.0
    return torch.tensor([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]], dtype=dtype, device=device)


def _as_batch(name: str, value, dtype=torch.float32) -> torch.Tensor:
    t = torch.as_tensor(value, dtype=dtype)
    if t.dim() == 0:
        t = t.reshape(1)
    check_tensor(name, t, ("B",))
    return t


def camera_rotation(azimuth_deg, elevation_deg, *, dtype=torch.float32) -> torch.Tensor:
    """Camera-to-object rotations (B, 3, 3) for cameras looking at the origin.

    Columns are the camera's right, up and backward axes (= the view frame's
    x, y, z axes) expressed in the object frame.  Azimuth 0 puts the camera in
    front of the object (on −Y); positive azimuth turns it counter-clockwise
    seen from above (azimuth 90° looks at the object's right side, from +X).
    Elevation is the angle above the XY plane and must lie in (−90°, 90°).

    ``azimuth_deg``, ``elevation_deg``: floats or (B,) tensors, in degrees.
    """
    az = _as_batch("azimuth_deg", azimuth_deg, dtype)
    el = _as_batch("elevation_deg", elevation_deg, dtype)
    if az.shape != el.shape:
        raise ValueError(f"azimuth and elevation must have the same shape, got {tuple(az.shape)} and {tuple(el.shape)}")
    if bool((el.abs() >= 90.0).any()):
        raise ValueError("elevation must lie strictly between -90 and 90 degrees")
    az, el = torch.deg2rad(az), torch.deg2rad(el)
    back = torch.stack([torch.cos(el) * torch.sin(az), -torch.cos(el) * torch.cos(az), torch.sin(el)], dim=-1)
    right = torch.stack([torch.cos(az), torch.sin(az), torch.zeros_like(az)], dim=-1)
    up = torch.cross(back, right, dim=-1)
    return torch.stack([right, up, back], dim=-1)


def camera_location(azimuth_deg, elevation_deg, distance: float, *, dtype=torch.float32) -> torch.Tensor:
    """Camera centres (B, 3) in the object frame, ``distance`` from the origin."""
    return camera_rotation(azimuth_deg, elevation_deg, dtype=dtype)[..., :, 2] * distance


def object_to_view(points: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """Object-frame points (B, N, 3) → view-frame points (B, N, 3).

    ``rotation`` (B, 3, 3) is a camera-to-object rotation from
    :func:`camera_rotation`; the view frame is ``R^T p``.
    """
    check_tensor("points", points, ("B", None, 3))
    check_tensor("rotation", rotation, ("B", 3, 3))
    return points @ rotation


def view_to_object(points: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """View-frame points (B, N, 3) → object-frame points (B, N, 3); inverse of :func:`object_to_view`."""
    check_tensor("points", points, ("B", None, 3))
    check_tensor("rotation", rotation, ("B", 3, 3))
    return points @ rotation.transpose(-1, -2)


def depth_valid_mask(depth: torch.Tensor) -> torch.Tensor:
    """Valid-pixel mask (same shape, bool) of an encoded depth map: depth > 0."""
    return depth > BACKGROUND_DEPTH


def encode_raw_depth(raw: torch.Tensor) -> torch.Tensor:
    """Raw Z-pass depth (background ≥ 1e5 or non-finite) → encoded depth (background 0)."""
    if not isinstance(raw, torch.Tensor):
        raise ValueError(f"raw depth: expected a torch.Tensor, got {type(raw).__name__}")
    bad = ~torch.isfinite(raw) | (raw >= RAW_BACKGROUND_MIN) | (raw <= 0)
    return torch.where(bad, torch.zeros_like(raw), raw)


def depth_to_points(depth: torch.Tensor, camera: CameraConfig) -> torch.Tensor:
    """Back-project planar depth maps to view-frame points.

    depth: (B, H, W) float, planar depth (encoded: background 0), square images.
    Returns (B, H, W, 3) float view-frame points.  Background pixels produce
    meaningless points; use :func:`depth_valid_mask` to select the valid ones.
    """
    check_tensor("depth", depth, ("B", "S", "S"))
    size = depth.shape[-1]
    f = camera.focal_px(size)
    centre = torch.arange(size, dtype=depth.dtype, device=depth.device) + 0.5 - size / 2.0
    x = centre.view(1, 1, size) / f * depth
    y = -centre.view(1, size, 1) / f * depth
    z = camera.distance - depth
    return torch.stack([x, y, z], dim=-1)


def view_to_pixels(points: torch.Tensor, camera: CameraConfig, image_size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Project view-frame points (..., 3) to pixel coordinates.

    Returns ``(uv, depth)``: uv (..., 2) float with u along columns and v along
    rows (pixel centres at +0.5), and planar depth (...,) float.
    """
    check_tensor("points", points, ("...", 3))
    f = camera.focal_px(image_size)
    depth = camera.distance - points[..., 2]
    u = points[..., 0] * f / depth + image_size / 2.0
    v = -points[..., 1] * f / depth + image_size / 2.0
    return torch.stack([u, v], dim=-1), depth


def blender_camera_to_view(matrix_world, target=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """World → view transform (4, 4) float64 for a Blender camera.

    matrix_world: (4, 4) the camera object's ``matrix_world`` (any scale is
    removed); target: (3,) the world point the camera looks at (the object
    centre).  A Blender camera's local axes are right, up, backward, so the
    view frame is the camera's rotation applied to world points relative to
    ``target``: ``p_view = R^T (p_world − target)``.
    """
    m = torch.as_tensor(matrix_world, dtype=torch.float64)
    check_tensor("matrix_world", m, (4, 4))
    t = torch.as_tensor(target, dtype=torch.float64)
    check_tensor("target", t, (3,))
    rot = m[:3, :3] / torch.linalg.norm(m[:3, :3], dim=0, keepdim=True)
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3] = rot.T
    out[:3, 3] = -rot.T @ t
    return out


# View frame → Blender world for a camera in front of the object (azimuth 0,
# elevation 0): view +x → world +X, view +y → world +Z, view +z → world −Y.
# The add-on uses it to stand a viewer-centred mesh upright in a Z-up scene.
VIEW_TO_BLENDER_FRONT = camera_rotation(0.0, 0.0, dtype=torch.float64)[0]

