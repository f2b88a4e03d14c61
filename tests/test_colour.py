"""Colour from the photo (genre_backend.inference.colour), mesh files that carry it, and its check through Blender."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from PIL import Image

from genre_backend.config import CameraConfig
from genre_backend.inference.colour import photo_texture, project, sample_bilinear, seen_vertices, zbuffer, zbuffer_reference
from genre_backend.inference.mesh_export import OutputError, mesh_files, write_mesh

CAM = CameraConfig()


def _sphere(radius=0.35, subdivisions=3, centre=(0.0, 0.0, 0.0)):
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    m.apply_translation(centre)
    return np.asarray(m.vertices), np.asarray(m.faces)


def test_zbuffer_matches_the_per_face_reference_and_the_analytic_sphere():
    v, f = _sphere(subdivisions=2)
    fast = zbuffer(v, f, CAM, 48)
    ref = zbuffer_reference(v, f, CAM, 48)
    assert np.array_equal(np.isinf(fast), np.isinf(ref))
    assert np.allclose(fast[np.isfinite(fast)], ref[np.isfinite(ref)], atol=1e-12)
    # front of a sphere of radius R centred at the origin, seen from distance d: planar depth along the
    # optical axis d − R at the centre pixel (the polyhedron lies inside the sphere: at most deeper)
    centre = fast[23:25, 23:25]
    assert np.all(centre >= CAM.distance - 0.35 - 1e-9) and np.all(centre <= CAM.distance - 0.35 + 0.01)


def test_seen_vertices_of_a_sphere_are_its_front_cap():
    """A point p of a sphere (radius R, centre 0) is visible from the camera c iff p·c > R²."""
    v, f = _sphere(subdivisions=4)
    mask = np.ones((128, 128), bool)
    seen = seen_vertices(v, f, CAM, mask, tolerance=0.02)
    visible = v[:, 2] * CAM.distance > 0.35**2
    margin = np.abs(v[:, 2] * CAM.distance - 0.35**2) > 0.02  # away from the silhouette
    assert np.array_equal(seen[margin], visible[margin])
    # a second sphere right behind the first is hidden where the first covers it
    v2, f2 = _sphere(radius=0.2, subdivisions=3, centre=(0.0, 0.0, -0.6))
    vv, ff = np.concatenate([v, v2]), np.concatenate([f, f2 + len(v)])
    seen2 = seen_vertices(vv, ff, CAM, mask, tolerance=0.02)
    assert not seen2[len(v):].any()
    # and the mask limits what is seen
    half = mask.copy()
    half[:, 64:] = False
    seen3 = seen_vertices(v, f, CAM, half, tolerance=0.02)
    uv, _ = project(v, CAM, 128)
    assert not seen3[uv[:, 0] >= 64].any() and seen3[(uv[:, 0] < 60) & seen].all()


def test_photo_texture_uvs_are_projections_and_hidden_vertices_borrow_the_nearest_seen():
    v, f = _sphere(subdivisions=3)
    image = np.zeros((64, 64, 3), np.uint8)
    tex = photo_texture(v, f, CAM, np.ones((128, 128), bool), image, tolerance=0.02)
    uv, _ = project(v, CAM, 128)
    expect = np.stack([uv[:, 0] / 128, 1 - uv[:, 1] / 128], axis=1)
    assert np.allclose(tex.uv[tex.seen], expect[tex.seen], atol=1e-6)
    hidden = np.flatnonzero(~tex.seen)
    assert len(hidden) > 0
    seen_idx = np.flatnonzero(tex.seen)
    for i in hidden[:: max(1, len(hidden) // 25)]:
        j = seen_idx[np.argmin(np.linalg.norm(v[seen_idx] - v[i], axis=1))]
        assert np.allclose(tex.uv[i], tex.uv[j])
    with pytest.raises(ValueError, match="uint8"):
        photo_texture(v, f, CAM, np.ones((128, 128), bool), image.astype(np.float32), tolerance=0.02)


def test_sample_bilinear_against_pixel_centres():
    img = np.arange(4 * 4 * 3, dtype=np.uint8).reshape(4, 4, 3) * 5
    # pixel (row 1, col 2) has its centre at u = 2.5/4, v = 1 − 1.5/4
    assert np.array_equal(sample_bilinear(img, np.array([[2.5 / 4, 1 - 1.5 / 4]])), img[1:2, 2])
    mid = sample_bilinear(img, np.array([[2.0 / 4, 1 - 1.5 / 4]]))  # half-way between columns 1 and 2
    assert np.array_equal(mid[0], np.rint((img[1, 1].astype(float) + img[1, 2]) / 2).astype(np.uint8))


def test_textured_files_in_each_format_read_back(tmp_path):
    v, f = _sphere(subdivisions=2)
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (32, 32, 3), dtype=np.uint8)
    tex = photo_texture(v, f, CAM, np.ones((128, 128), bool), image, tolerance=0.02)

    path, fmt, files = write_mesh(tmp_path / "m.obj", v, f, texture=tex)
    assert files == mesh_files(tmp_path / "m.obj", "obj", True) == [tmp_path / "m.obj", tmp_path / "m.mtl", tmp_path / "m_texture.png"]
    assert np.array_equal(np.asarray(Image.open(files[2])), image)
    assert "map_Kd m_texture.png" in files[1].read_text()
    back = trimesh.load(path, process=False)
    assert np.allclose(back.vertices, v, atol=1e-6) and np.array_equal(back.faces, f)
    assert np.allclose(back.visual.uv, tex.uv, atol=1e-6)

    path, _, files = write_mesh(tmp_path / "m.glb", v, f, texture=tex)
    assert files == [path]
    back = trimesh.load(path, force="mesh", process=False)
    assert np.allclose(back.visual.uv, tex.uv, atol=1e-6)
    assert np.array_equal(np.asarray(back.visual.material.baseColorTexture.convert("RGB")), image)

    path, _, _ = write_mesh(tmp_path / "m.ply", v, f, texture=tex)
    back = trimesh.load(path, process=False)
    assert np.array_equal(back.visual.vertex_colors, tex.vertex_colours())

    # a path with no file name has no companions (it is then refused as a folder, not a crash)
    from pathlib import Path

    assert mesh_files("/", "obj", True) == [Path("/")]
    with pytest.raises(OutputError, match="directory"):
        write_mesh("/", v, f, "obj", texture=tex)
    # never over an input, checked before anything is written
    photo = tmp_path / "x_texture.png"
    photo.write_bytes(b"the user's photo")
    with pytest.raises(OutputError, match="input"):
        write_mesh(tmp_path / "x.obj", v, f, texture=tex, inputs=(photo,))
    assert photo.read_bytes() == b"the user's photo" and not (tmp_path / "x.obj").exists()


def test_textured_mesh_rendered_through_the_camera_reproduces_the_texture():
    """Blender (Workbench, flat) renders the sphere with its UVs: inside the seen cap, the texture comes back."""
    from genre_backend.inference.blender import render_textured

    v, f = _sphere(subdivisions=5)
    yy, xx = np.mgrid[0:256, 0:256]
    image = np.stack([xx, yy, (xx + yy) // 2], axis=-1).astype(np.uint8)  # a smooth gradient
    tex = photo_texture(v, f, CAM, np.ones((128, 128), bool), image, tolerance=0.02)
    rgb, covered = render_textured(v, f, tex.uv, tex.image, 256)
    # the sphere's silhouette: radius R seen at distance d spans tan(asin(R/d)) · focal pixels
    focal = CAM.focal_px(256)
    radius_px = np.tan(np.arcsin(0.35 / CAM.distance)) * focal
    r = np.hypot(xx + 0.5 - 128, yy + 0.5 - 128)
    assert covered[r < radius_px - 2].all() and not covered[r > radius_px + 2].any()
    inner = r < radius_px - 3
    err = np.abs(rgb[inner].astype(float) - image[inner]).mean()
    assert err < 1.5, err


REPO = __import__("pathlib").Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("photo, mask", [
    ("examples/sofa.png", None),  # no mask: found by GrabCut
    ("examples/photos/apple.jpg", "examples/photos/apple_mask.png"),  # real photos, hand-made masks
    ("examples/photos/orange.jpg", "examples/photos/orange_mask.png"),
])
def test_shipped_model_coloured_mesh_reproduces_the_photo_through_its_camera(photo, mask):
    """The issue's check: render the textured mesh (flat, unlit) through the matching camera; inside the
    mask, where the mesh covers it, the mean absolute error to the photo is at most 8/255; one part.
    (``scripts/colour_check.py`` prints the figures.)"""
    from genre_backend.inference.blender import photo_colour_error
    from genre_backend.inference.reconstruct import DEFAULT_WEIGHTS, Reconstructor

    result = Reconstructor(DEFAULT_WEIGHTS).run(REPO / photo, mask_path=None if mask is None else REPO / mask)
    assert result.clean.parts == 1 and result.clean.watertight
    mae, coverage = photo_colour_error(result, 256)
    assert coverage >= 0.9, coverage  # the mesh covers the mask
    assert mae <= 8.0, mae


def test_textured_obj_with_a_name_that_is_not_utf8(tmp_path):
    """A Latin-1 file name (bytes caf\\xe9) reaches Python with a lone surrogate; the .mtl must name the texture
    by the same bytes, and the OBJ its .mtl."""
    import os

    v, f = _sphere(subdivisions=1)
    tex = photo_texture(v, f, CAM, np.ones((128, 128), bool), np.zeros((8, 8, 3), np.uint8), tolerance=0.02)
    name = os.fsdecode(b"caf\xe9.obj")
    _, _, files = write_mesh(tmp_path / name, v, f, texture=tex)
    assert sorted(os.listdir(os.fsencode(tmp_path))) == [b"caf\xe9.mtl", b"caf\xe9.obj", b"caf\xe9_texture.png"]
    assert b"map_Kd caf\xe9_texture.png" in (tmp_path / os.fsdecode(b"caf\xe9.mtl")).read_bytes()
    assert b"mtllib caf\xe9.mtl" in (tmp_path / name).read_bytes()
