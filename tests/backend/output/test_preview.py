"""Mesh previews rendered with Blender: the cameras sit where the view frame says."""

import math

import numpy as np
import pytest
import trimesh

from genre_backend.geometry.analytic import sphere_silhouette_radius_px
from genre_backend.output.blender import render_meshes, render_views
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


# --- the preview sheet: mesh views that fill it, framed, from the front, the side and the back ---


def _colourful_box():
    """A box 0.6 wide, 0.3 tall, 0.15 deep (thin along z, the camera's axis), with a texture of four colours."""
    box = trimesh.creation.box(extents=[0.6, 0.3, 0.15])
    box = box.subdivide().subdivide()
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    uv = np.stack([(v[:, 0] + 0.3) / 0.6, (v[:, 1] + 0.15) / 0.3], axis=1)
    tex = np.zeros((64, 64, 3), np.uint8)
    tex[:32, :32], tex[:32, 32:], tex[32:, :32], tex[32:, 32:] = (220, 40, 40), (40, 200, 60), (40, 60, 220), (230, 200, 30)
    return v, f, uv, tex


def test_views_are_framed_and_turned_as_documented():
    v, f, _, _ = _colourful_box()
    front, side, back = (_silhouette(img) for img in render_views(v, f, 128))
    for sil in (front, side, back):
        ys, xs = np.nonzero(sil)
        assert (xs.mean(), ys.mean()) == pytest.approx((63.5, 63.5), abs=3)  # centred by the lens shift

    def width(sil):
        return np.ptp(np.nonzero(sil)[1]) + 1

    # one common zoom: the widest view (the front, 0.6 across) spans ~92 % of the panel
    assert width(front) > 0.85 * 128 and width(back) > 0.85 * 128
    # the side view shows the box's side: 0.15 deep against 0.6 wide (plus perspective), not the front again
    assert width(side) < 0.45 * width(front)


def test_textured_views_show_the_texture_and_the_back_mirrored():
    v, f, uv, tex = _colourful_box()
    front, _, back = render_views(v, f, 96, uv=uv, texture=tex)
    clay = render_views(v, f, 96)[0]

    def saturation(img):
        sil = _silhouette(img)
        px = img[sil].astype(float)
        return float(((px.max(axis=1) - px.min(axis=1)) / np.maximum(px.max(axis=1), 1)).mean())

    assert saturation(front) > saturation(clay) + 0.3
    # the upper half of the box: its left and right quarters of the texture differ
    left, right = front[32:44, 10:30].reshape(-1, 3).mean(0), front[32:44, 66:86].reshape(-1, 3).mean(0)
    back_left = back[32:44, 10:30].reshape(-1, 3).mean(0)
    assert not np.allclose(left, right, atol=30)  # the texture varies across the front
    assert np.allclose(back_left, right, atol=40)  # from behind, the object's right is on the left


REPO = __import__("pathlib").Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def sofa_sheets():
    """(layout, untextured sheet, textured sheet) of the shipped model's demo reconstruction."""
    from genre_backend.output.preview import preview_image, preview_layout
    from genre_backend.inference.reconstruct import DEFAULT_WEIGHTS, Reconstructor

    result = Reconstructor(DEFAULT_WEIGHTS).run(REPO / "examples/sofa.png")
    return preview_layout(), preview_image(result), preview_image(result, textured=True)


def _mesh_pixels(sheet, box):
    x0, y0, x1, y1 = box
    panel = sheet[y0:y1, x0:x1]
    return panel[_silhouette(panel)]


def test_preview_mesh_views_fill_the_sheet(sofa_sheets):
    from genre_backend.output.preview import MESH_VIEWS, SHEET

    layout, plain, textured = sofa_sheets
    assert plain.shape == textured.shape == (SHEET[1], SHEET[0], 3)
    area = plain.shape[0] * plain.shape[1]
    panels = sum((x1 - x0) * (y1 - y0) for name, _ in MESH_VIEWS for x0, y0, x1, y1 in [layout[name]])
    assert panels >= 0.5 * area, panels / area
    for sheet in (plain, textured):
        # the sofa itself, not white space around it: 15 % of the sheet (a wide, low object in square panels;
        # the old sheet's two 130 px views covered under 2 %)
        covered = sum(len(_mesh_pixels(sheet, layout[name])) for name, _ in MESH_VIEWS)
        assert covered >= 0.12 * area, covered / area
        spans = []
        for name, _ in MESH_VIEWS:  # every view shows the mesh, none is an empty panel
            x0, y0, x1, y1 = layout[name]
            sil = _silhouette(sheet[y0:y1, x0:x1])
            assert sil.sum() >= 0.1 * (x1 - x0) * (y1 - y0), name
            ys, xs = np.nonzero(sil)
            spans.append(max(np.ptp(xs) / (x1 - x0), np.ptp(ys) / (y1 - y0)))
        assert max(spans) > 0.85, spans  # framed: the widest view spans the panel
    # the small panels stay: the photo's panel is not blank
    x0, y0, x1, y1 = layout["input"]
    assert plain[y0:y1, x0:x1].std() > 10


def test_textured_preview_is_coloured_where_the_plain_one_is_clay(sofa_sheets):
    from genre_backend.output.preview import MESH_VIEWS

    layout, plain, textured = sofa_sheets

    def saturation(sheet, name):
        px = _mesh_pixels(sheet, layout[name]).astype(float)
        return float(((px.max(axis=1) - px.min(axis=1)) / np.maximum(px.max(axis=1), 1)).mean())

    for name, _ in MESH_VIEWS:
        assert saturation(textured, name) > saturation(plain, name) + 0.05, name
