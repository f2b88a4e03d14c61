"""Renders framed as the photo path frames a photo (training/data/photo_framing.py) agree with their framed meshes."""

import json
from pathlib import Path

import numpy as np
import torch
import trimesh

from genre_backend import frame
from genre_backend.photo.preprocess import mask_bbox
from support.tiny_data import TINY
from test_targets import check_voxel_target
from training.data.dataset import find_views
from training.data.photo_framing import Framing, frame_folder, frame_view, framed_points, framing_of, photo_framing
from training.data.targets import build_targets, load_targets
from genre_backend.geometry.spherical import sph_directions

FRACTION = 0.45


def _framed_mesh(shape_dir: Path, view: int) -> tuple[trimesh.Trimesh, Framing, dict, float]:
    """The view's mesh posed in the framed view's frame, its framing, the view's JSON, and the posed mesh's reach
    (its farthest vertex from the origin before the framing)."""
    meta = json.loads((shape_dir / f"view_{view:03d}.json").read_text())
    mesh = trimesh.load(meta["mesh"], force="mesh", process=False)
    rot = torch.tensor(meta["rotation_cam_to_obj"], dtype=torch.float64)
    framing = framing_of(meta)
    posed = frame.object_to_view(torch.tensor(mesh.vertices)[None], rot[None])[0]
    verts = framed_points(posed, framing)
    return trimesh.Trimesh(verts.numpy(), mesh.faces, process=False), framing, meta, float(posed.norm(dim=1).max())


def test_framed_views_agree_with_their_framed_meshes(tiny_views, tmp_path):
    out = tmp_path / "framed"
    counts = frame_folder(tiny_views, out, FRACTION, TINY.camera, progress=False)
    assert counts == {"framed": 4, "kept": 0, "left_out": 0}
    assert build_targets(out, TINY, progress=False)["written"] == 4
    size, dist = TINY.geometry.image_size, TINY.camera.distance
    for ref in find_views(out):
        mesh, framing, meta, reach = _framed_mesh(ref.shape_dir, ref.view)
        assert meta["photo_framing"]["fraction"] == FRACTION
        with np.load(ref.shape_dir / f"view_{ref.view:03d}.npz") as z:
            depth, alpha = z["depth"], z["mask"]
        # the photo path's framing: the mask's longest side spans the fraction, centred (to a pixel)
        x0, y0, x1, y1 = mask_bbox(alpha > 0.5)
        assert abs(max(x1 - x0, y1 - y0) - FRACTION * size) <= 1.5
        assert abs((x0 + x1) / 2 - size / 2) <= 1.0 and abs((y0 + y1) / 2 - size / 2) <= 1.0
        # the mask and the depth agree everywhere
        assert np.array_equal(alpha > 0.5, depth > 0)
        # the depth back-projects onto the framed mesh, up to the magnification's perspective error: a point at
        # (x, z) lands k·|x z (1 - k) / (D - z) + b k z / D| across from its framed place, at most this for the view
        k, b = framing.scale, float(np.hypot(*framing.offset))
        bound = k * (reach * reach * abs(1 - k) / (dist - reach) + b * k * reach / dist)
        pts = frame.depth_to_points(torch.from_numpy(depth)[None].double(), TINY.camera)[0].numpy()[depth > 0]
        off = np.abs(trimesh.proximity.signed_distance(mesh, pts))
        assert off.mean() < 0.005 + bound / 2 and off.max() < 0.02 + bound, (off.mean(), off.max(), bound)
        # the full map is the framed mesh's: every hit lies on it
        t = load_targets(ref.shape_dir, ref.view, TINY.geometry)
        h = TINY.geometry.sph_size
        dirs = sph_directions(h, dtype=torch.float64).numpy()
        hits = t["full_sph"] < 1
        assert hits.sum() > 0.05 * h * h
        assert trimesh.proximity.closest_point(mesh, (1 - t["full_sph"][hits])[:, None] * dirs[hits])[1].max() < 1e-4
        check_voxel_target(mesh, t["voxels"], TINY.geometry)
    # a second run keeps what is there
    assert frame_folder(tiny_views, out, FRACTION, TINY.camera, progress=False) == {"framed": 0, "kept": 4, "left_out": 0}


def test_a_view_already_framed_so_is_unchanged():
    size = 64
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (size, size, 3), dtype=np.uint8)
    alpha = np.zeros((size, size), np.float32)
    alpha[16:48, 20:44] = 1.0  # the longest side (32) is half the image, centred
    depth = np.where(alpha > 0.5, 2.0 + rng.random((size, size)) * 0.1, 0.0).astype(np.float32)
    framing = photo_framing(alpha, 0.5, TINY.camera)
    assert framing.box == (0.0, 0.0, 64.0, 64.0) and framing.scale == 1.0 and framing.offset == (0.0, 0.0)
    rgb_f, depth_f, alpha_f = frame_view(rgb, depth, alpha, framing, TINY.camera)
    assert np.array_equal(rgb_f, rgb) and np.allclose(depth_f, depth) and np.array_equal(alpha_f > 0.5, alpha > 0.5)


def test_framing_magnifies_about_the_box_centre():
    """A mask off centre and small: the box, the magnification and the offset follow from the photo path's crop."""
    size = 64
    alpha = np.zeros((size, size), np.float32)
    alpha[10:26, 40:48] = 1.0  # 16 rows × 8 columns, centre (44, 18)
    framing = photo_framing(alpha, 0.5, TINY.camera)
    assert framing.box == (28.0, 2.0, 60.0, 34.0)  # side 16 / 0.5 = 32, centred on the box
    assert framing.scale == 2.0
    f = TINY.camera.focal_px(size)
    assert np.allclose(framing.offset, ((44 - 32) * TINY.camera.distance / f, -(18 - 32) * TINY.camera.distance / f))
    p = torch.tensor([[0.1, 0.2, 0.3]], dtype=torch.float64)
    assert torch.allclose(framed_points(p, framing), 2.0 * (p - torch.tensor([[*framing.offset, 0.0]], dtype=torch.float64)))


def test_each_half_of_the_framing_alone():
    """``centre``: the photo's centre at the render's size; ``size``: the photo's size about the render's centre."""
    size = 64
    alpha = np.zeros((size, size), np.float32)
    alpha[10:26, 40:48] = 1.0
    both = photo_framing(alpha, 0.5, TINY.camera)
    centre = photo_framing(alpha, 0.5, TINY.camera, "centre")
    assert centre.box == (12.0, -14.0, 76.0, 50.0) and centre.scale == 1.0 and centre.offset == both.offset
    sized = photo_framing(alpha, 0.5, TINY.camera, "size")
    assert sized.box == (16.0, 16.0, 48.0, 48.0) and sized.scale == both.scale and sized.offset == (0.0, 0.0)
    assert framing_of({"photo_framing": sized.to_meta()}) == sized


def test_a_folder_without_targets_is_refused_with_a_clear_error(tiny_views, tmp_path, capsys):
    import shutil

    from training.data.photo_framing import main

    src = tmp_path / "views"
    shutil.copytree(tiny_views, src)
    for points in src.glob("*/surface_points.npz"):
        points.unlink()
    assert main(["--views", str(src), "--out", str(tmp_path / "framed"), "--no-progress"]) == 1
    assert "no surface_points.npz: run 'genre data targets" in capsys.readouterr().err
