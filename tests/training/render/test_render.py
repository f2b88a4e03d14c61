"""Tests of the headless Blender renderer (training/render/) with real bpy.

Geometry is checked against analytic shapes: a sphere's planar depth, disc
silhouette and back-projected points; an off-centre box's image position,
depth and back-projection under the frame convention of genre_backend.frame.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("bpy")
trimesh = pytest.importorskip("trimesh")

from genre_backend import frame  # noqa: E402
from genre_backend.config import get_preset  # noqa: E402
from training.data import views as view_files  # noqa: E402
from training.render import backgrounds, randomness  # noqa: E402
from training.render import cli as render_cli  # noqa: E402
from training.render import scene as render  # noqa: E402

CONFIG = get_preset("default")
CAM = CONFIG.camera
SIZE = CONFIG.geometry.image_size
RADIUS = 0.3
# An off-centre box (object frame): right (+X), behind (+Y) and above (+Z) the origin.
BOX_CENTRE = np.array([0.25, 0.1, 0.15])
BOX_EXTENT = 0.16


@pytest.fixture(scope="module")
def renderer(tmp_path_factory):
    cache = tmp_path_factory.mktemp("blender-cache")
    render.prepare_blender_environment(cache)
    r = render.BlenderRenderer(CONFIG, render.RenderSettings(samples=16))
    yield r
    if r.is_active:
        r.close()


@pytest.fixture
def active_renderer(renderer):
    if not renderer.is_active:
        pytest.skip("another test replaced the module renderer")
    return renderer


@pytest.fixture(scope="module")
def sphere_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("meshes") / "sphere.ply"
    trimesh.creation.icosphere(subdivisions=5, radius=RADIUS).export(path)
    return path


@pytest.fixture(scope="module")
def box_paths(tmp_path_factory):
    folder = tmp_path_factory.mktemp("boxes")
    box = trimesh.creation.box(extents=[BOX_EXTENT] * 3)
    box.apply_translation(BOX_CENTRE)
    paths = {}
    for suffix in ("glb", "obj"):
        paths[suffix] = folder / f"box.{suffix}"
        box.export(paths[suffix])
    return paths


def _analytic_sphere(radius: float, inner_fraction: float):
    """Planar depth (S, S) of a centred sphere, its disc mask, and the mask of rays within inner_fraction·r."""
    f = CAM.focal_px(SIZE)
    c = (np.arange(SIZE) + 0.5 - SIZE / 2) / f
    xn, yn = c[None, :], -c[:, None]
    q = xn**2 + yn**2
    d = CAM.distance
    disc = d * d - (1 + q) * (d * d - radius**2)
    depth = np.where(disc > 0, (d - np.sqrt(np.maximum(disc, 0.0))) / (1 + q), 0.0)
    inner = d * d - (1 + q) * (d * d - (inner_fraction * radius) ** 2) > 0
    return depth, disc > 0, inner


def _encode(raw: np.ndarray) -> np.ndarray:
    return frame.encode_raw_depth(torch.from_numpy(raw)).numpy()


@pytest.mark.parametrize("view", [(0.0, 0.0), (137.0, 31.0)])
def test_sphere_depth_mask_and_backprojection(active_renderer, sphere_path, view):
    active_renderer.load_shape(sphere_path)
    out = active_renderer.render_view(*view, np.random.default_rng(0))
    assert out["rgba"].shape == (SIZE, SIZE, 4) and out["rgba"].dtype == np.uint8
    assert out["raw_depth"].shape == (SIZE, SIZE) and out["raw_depth"].dtype == np.float32
    depth = _encode(out["raw_depth"])
    expected, disc, inner = _analytic_sphere(RADIUS, 0.85)
    assert inner.sum() > 500
    # (a) planar Z-pass depth inside the silhouette
    assert np.abs(depth - expected)[inner].max() < 1e-3
    # background is encoded 0
    assert (depth[~disc] == 0).mean() > 0.999
    # (b) the film-alpha mask is the analytic disc
    mask = out["rgba"][..., 3] >= 128
    iou = (mask & disc).sum() / (mask | disc).sum()
    assert iou > 0.98
    # (c) back-projected depth lies on the sphere
    pts = frame.depth_to_points(torch.from_numpy(depth)[None], CAM)[0].numpy()
    assert np.abs(np.linalg.norm(pts, axis=-1) - RADIUS)[inner].max() < 2e-3


@pytest.mark.parametrize("view", [(30.0, 10.0), (200.0, 60.0), (300.0, -5.0)])
def test_camera_side_lighting_shades_the_side_that_faces_the_camera(active_renderer, sphere_path, view):
    """A grey sphere lit ``camera-side``: the key sun is within 60° of the camera's azimuth, and the sphere's
    brightness follows the key's cosine law (its brighter pixels are those whose normals face the key)."""
    settings = active_renderer.settings
    active_renderer.settings = dataclasses.replace(settings, lighting="camera-side")
    try:
        active_renderer.load_shape(sphere_path)
        out = active_renderer.render_view(*view, np.random.default_rng(int(view[0])))
    finally:
        active_renderer.settings = settings
    lighting = out["lighting"]
    assert lighting["kind"] == "camera-side" and 1 <= len(lighting["suns"]) <= 2
    key = lighting["suns"][0]
    # the camera sits at (sin az, -cos az) on the ground plane: azimuth az - 90° in the suns' (cos, sin) convention
    off = (key["azimuth_deg"] - (view[0] - 90.0) + 180.0) % 360.0 - 180.0
    assert abs(off) <= 60.0 + 1e-6 and 20.0 <= key["elevation_deg"] <= 70.0
    az, el = np.radians(key["azimuth_deg"]), np.radians(key["elevation_deg"])
    towards_key = np.array(out["rotation"]).T @ [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]
    depth = _encode(out["raw_depth"])
    _, _, inner = _analytic_sphere(RADIUS, 0.9)
    normals = frame.depth_to_points(torch.from_numpy(depth)[None], CAM)[0].numpy()[inner] / RADIUS
    luminance = out["rgba"][..., :3].astype(float).mean(-1)[inner]
    assert np.corrcoef(normals @ towards_key, luminance)[0, 1] > 0.5


def _mask_centroid(mask: np.ndarray) -> tuple[float, float]:
    rows, cols = np.nonzero(mask)
    return float(rows.mean()) + 0.5, float(cols.mean()) + 0.5


@pytest.mark.parametrize("suffix", ["glb", "obj"])
def test_off_centre_box_appears_where_the_frame_says(active_renderer, box_paths, suffix):
    active_renderer.load_shape(box_paths[suffix])
    bounds = active_renderer.shape_bounds()
    np.testing.assert_allclose(bounds, [BOX_CENTRE - BOX_EXTENT / 2, BOX_CENTRE + BOX_EXTENT / 2], atol=1e-5)
    centres = {}
    for az in (0.0, 90.0):
        out = active_renderer.render_view(az, 0.0, np.random.default_rng(1))
        mask = out["rgba"][..., 3] >= 128
        depth = _encode(out["raw_depth"])
        row, col = _mask_centroid(mask)
        centres[az] = (row, col, float(np.median(depth[depth > 0])))
        # The frame's own projection of the box centre agrees with the image (to perspective skew).
        rot = torch.from_numpy(out["rotation"])[None]
        np.testing.assert_allclose(rot[0].numpy(), frame.camera_rotation(az, 0.0, dtype=torch.float64)[0].numpy())
        pv = frame.object_to_view(torch.tensor(BOX_CENTRE)[None, None], rot)
        uv, _ = frame.view_to_pixels(pv, CAM, SIZE)
        u, v = uv[0, 0].tolist()
        assert abs(col - u) < 2.0 and abs(row - v) < 2.0
        # Depth back-projected to the object frame lands on the box surface.
        valid = torch.from_numpy(depth > 0)
        pts_view = frame.depth_to_points(torch.from_numpy(depth)[None], CAM)[0][valid][None].double()
        pts_obj = frame.view_to_object(pts_view, rot)[0].numpy()
        dist_out = np.abs(pts_obj - BOX_CENTRE).max(axis=1) - BOX_EXTENT / 2
        assert np.abs(dist_out).max() < 2e-3
    half = SIZE / 2
    # Azimuth 0 looks from the front (−Y): +X is on the image right, +Z up, +Y away from the camera.
    row0, col0, depth0 = centres[0.0]
    assert col0 > half + 15 and row0 < half - 5
    assert depth0 > CAM.distance + 0.1 - BOX_EXTENT / 2 - 1e-3
    # Azimuth 90 looks from +X: +X comes toward the camera, +Y is on the image right.
    row90, col90, depth90 = centres[90.0]
    assert half + 3 < col90 < col0 and row90 < half - 5
    assert depth90 < CAM.distance - 0.25 + 1e-3


def test_imported_formats_keep_stored_coordinates(active_renderer, box_paths, tmp_path):
    box = trimesh.load(box_paths["obj"], force="mesh")
    ply = tmp_path / "box.ply"
    box.export(ply)
    for path in (box_paths["glb"], box_paths["obj"], ply):
        active_renderer.load_shape(path)
        np.testing.assert_allclose(active_renderer.shape_bounds(), box.bounds, atol=1e-5, err_msg=str(path))


def test_background_varies_with_seed_and_mask_stays(active_renderer, box_paths, tmp_path):
    shape = view_files.ShapeEntry("box", box_paths["glb"], "test", None)
    views = [(30.0, 20.0)]
    loaded = []
    for seed in (3, 4):
        assert render.render_shape(active_renderer, shape, views, tmp_path / f"s{seed}", seed) == 1
        loaded.append(view_files.load_view(tmp_path / f"s{seed}" / "box", 0))
    a, b = loaded
    assert a["rgb"].shape == (SIZE, SIZE, 3) and a["rgb"].dtype == np.uint8
    assert a["depth"].dtype == np.float32 and a["mask"].dtype == np.float32
    np.testing.assert_array_equal(a["depth"], b["depth"])
    assert np.abs(a["mask"] - b["mask"]).max() < 0.05
    background = a["mask"] == 0
    assert background.mean() > 0.5
    diff = np.abs(a["rgb"].astype(int) - b["rgb"].astype(int))[background].mean()
    assert diff > 10
    cam = a["camera"]
    assert cam["azimuth_deg"] == 30.0 and cam["elevation_deg"] == 20.0 and cam["distance"] == CAM.distance
    assert cam["focal_px"] == pytest.approx(CAM.focal_px(SIZE))
    np.testing.assert_allclose(cam["rotation_cam_to_obj"], frame.camera_rotation(30.0, 20.0, dtype=torch.float64)[0])
    # Mask and depth agree except at edge pixels (depth is not anti-aliased).
    disagree = (a["mask"] >= 0.5) != (a["depth"] > 0)
    assert disagree.sum() <= 0.05 * (a["depth"] > 0).sum()


def test_backgrounds_are_deterministic_and_varied():
    imgs = [backgrounds.make_background(randomness.view_rng(7, "shape", k, 2), 32) for k in range(12)]
    again = backgrounds.make_background(randomness.view_rng(7, "shape", 5, 2), 32)
    np.testing.assert_array_equal(imgs[5][0], again[0])
    assert {info["kind"] for _, info in imgs} == {"solid", "gradient", "noise"}
    for img, _ in imgs:
        assert img.shape == (32, 32, 3) and img.dtype == np.float32 and img.min() >= 0 and img.max() <= 1
    views = randomness.sample_views("shape", 5, 0, CAM)
    assert views[:3] == randomness.sample_views("shape", 3, 0, CAM)
    assert all(0 <= az < 360 and CAM.elevation_min_deg <= el <= CAM.elevation_max_deg for az, el in views)
    with pytest.raises(ValueError):
        backgrounds.composite_over(np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4, 3)))


def test_discover_shapes_from_manifest_and_folder(tmp_path):
    corpus = tmp_path / "corpus"
    (corpus / "shapes").mkdir(parents=True)
    manifest = corpus / "manifest.json"
    manifest.write_text(json.dumps({"shapes": [{"id": "a1", "class": "chair", "split": "train"}]}))
    (shape,) = view_files.read_shapes(manifest)
    assert shape.path == corpus / "shapes" / "a1.glb" and shape.cls == "chair" and shape.split == "train"
    folder = tmp_path / "meshes"
    (folder / "lamp").mkdir(parents=True)
    (folder / "lamp" / "x.obj").write_text("v 0 0 0\n")
    (folder / "notes.txt").write_text("no mesh")
    (found,) = view_files.read_shapes(folder)
    assert found.id == "lamp__x" and found.cls == "lamp"
    manifest.write_text(json.dumps([{"class": "chair"}]))
    with pytest.raises(ValueError, match="id"):
        view_files.read_shapes(manifest)
    with pytest.raises(ValueError):
        view_files.read_shapes(tmp_path / "missing")


def test_importing_render_does_not_import_bpy():
    code = "import sys, training.render.scene, training.render.cli; assert 'bpy' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=Path(__file__).resolve().parents[3])


def test_cli_renders_resumes_and_records_failures(renderer, sphere_path, tmp_path, capsys):
    # Runs last in this file: main() builds its own BlenderRenderer, which replaces the module one.
    shapes = tmp_path / "shapes"
    (shapes / "ball").mkdir(parents=True)
    (shapes / "ball" / "s.ply").write_bytes(Path(sphere_path).read_bytes())
    (shapes / "broken.obj").write_text("this is not an obj file\n")
    out = tmp_path / "out"
    argv = ["--shapes", str(shapes), "--out", str(out), "--views", "2", "--seed", "5", "--no-progress"]
    assert render_cli.main(argv, "genre data render") == 1  # the broken shape is recorded
    failures = json.loads((out / "render_failures.json").read_text())
    assert list(failures) == ["broken"]
    shape_dir = out / "ball__s"
    assert all(view_files.view_is_complete(shape_dir, k) for k in range(2))
    assert not [p for p in shape_dir.iterdir() if p.name.startswith(".")]  # no temporary files left
    kept = (shape_dir / "view_000.npz").stat().st_mtime_ns
    first = view_files.load_view(shape_dir, 1)
    (shape_dir / "view_001.json").unlink()  # as if killed before the view's last file
    capsys.readouterr()
    # The broken shape is skipped, not retried, and its missing views make the run fail, saying how many.
    assert render_cli.main(argv, "genre data render") == 1
    assert (shape_dir / "view_000.npz").stat().st_mtime_ns == kept
    again = view_files.load_view(shape_dir, 1)
    np.testing.assert_array_equal(first["depth"], again["depth"])
    assert first["camera"]["azimuth_deg"] == again["camera"]["azimuth_deg"]
    captured = capsys.readouterr()
    assert "rendered 1 views" in captured.out
    assert "2 views of 1 shapes are missing: 1 shapes failed" in captured.err
    # Other settings into the same folder are refused.
    assert render_cli.main(argv[:-3] + ["--seed", "6", "--no-progress"], "genre data render") == 2
    assert render_cli.main(argv + ["--elevation", "70", "80"], "genre data render") == 2
    # --elevation: views from above, the range recorded; an empty or out-of-range one is refused
    (shapes / "broken.obj").unlink()
    above = tmp_path / "above"
    high = ["--shapes", str(shapes), "--out", str(above), "--views", "2", "--seed", "5", "--no-progress", "--elevation", "70", "80"]
    assert render_cli.main(high, "genre data render") == 0
    for k in range(2):
        assert 70.0 <= view_files.load_view(above / "ball__s", k)["camera"]["elevation_deg"] <= 80.0
    settings = json.loads((above / "render_settings.json").read_text())["camera"]
    assert (settings["elevation_min_deg"], settings["elevation_max_deg"]) == (70.0, 80.0)
    for bad in (["80", "70"], ["10", "95"]):
        assert render_cli.main(high[:-2] + bad, "genre data render") == 2  # (refused before anything is written)


@pytest.mark.slow
def test_render_killed_mid_run_resumes_without_corrupt_views(sphere_path, tmp_path):
    """kill -9 a rendering process after its first complete view; a second run completes every view."""
    import signal
    import time

    shapes = tmp_path / "shapes"
    shapes.mkdir()
    for name in ("a", "b"):
        (shapes / f"{name}.ply").write_bytes(Path(sphere_path).read_bytes())
    out = tmp_path / "out"
    code = (
        "import sys; from training.render.cli import main; "
        f"sys.exit(main(['--shapes', {str(shapes)!r}, '--out', {str(out)!r}, '--views', '3', '--no-progress'], 'r'))"
    )
    root = Path(__file__).resolve().parents[3]
    env = dict(os.environ, GENRE_BLENDER_CACHE=str(tmp_path / "cache"))
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=root, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while not (out / "a" / "view_000.json").exists():
            assert proc.poll() is None and time.monotonic() < deadline, "the renderer ended before its first view"
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    assert not all(view_files.view_is_complete(out / s, k) for s in ("a", "b") for k in range(3))
    subprocess.run([sys.executable, "-c", code], cwd=root, env=env, check=True, stdout=subprocess.DEVNULL)
    for s in ("a", "b"):
        names = sorted(p.name for p in (out / s).iterdir())
        assert names == [f"view_{k:03d}.{ext}" for k in range(3) for ext in ("json", "npz", "png")]
        for k in range(3):
            view = view_files.load_view(out / s, k)
            assert view["rgb"].shape == (SIZE, SIZE, 3) and (view["depth"] > 0).sum() > 100
    assert view_files.read_render_attempts(out) == view_files.RenderAttempts()  # the kill was an interruption
