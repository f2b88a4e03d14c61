"""Engines and Blenders agree on what a view means: depth, mask and camera.

* Workbench and EEVEE against Cycles on analytic shapes (a sphere, an
  off-centre cube): the same pixels hit the surface, the planar depth agrees
  to float precision away from the silhouette, the masks differ only at
  silhouette pixels.  EEVEE costs ~20-40 s here (shader compilation on a
  fresh machine, then several seconds per view on a software OpenGL), so it
  renders one view.
* ``--engine`` is recorded in the views folder and a folder refuses another
  engine; a machine without EGL gets one line and exit code 2 before Blender
  could abort, and so does an engine the Blender lacks.
* A stock Blender (Debian's 3.4.1) running training/render/blender_script.py
  writes the same views as the bpy module (skipped without ``blender`` on PATH).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("bpy")
trimesh = pytest.importorskip("trimesh")

from genre_backend.config import get_preset  # noqa: E402
from training.data import views as view_files  # noqa: E402
from training.render import cli as render_cli  # noqa: E402
from training.render import scene as render  # noqa: E402

ROOT = Path(__file__).resolve().parents[3]
CONFIG = get_preset("default")
POSES = [(0.0, 0.0), (137.0, 31.0)]
# Planar depth of the rasterisers (Workbench, EEVEE) vs Cycles' ray tracing, away from the silhouette:
# measured ≤ 2.3e-5 on these shapes (median 1e-6 to 9e-6; float32 steps are 2.4e-7 at depth 2).
INTERIOR_DEPTH_TOL = 1e-4
# The camera keys of a view's JSON (the rest is provenance: engine, samples, Blender version, lighting).
CAMERA_KEYS = ("shape_id", "view", "preset", "seed", "image_size", "azimuth_deg", "elevation_deg", "distance",
               "lens_mm", "sensor_mm", "focal_px", "rotation_cam_to_obj", "camera_location", "depth", "mask")


@pytest.fixture(scope="module")
def meshes(tmp_path_factory):
    folder = tmp_path_factory.mktemp("meshes")
    trimesh.creation.icosphere(subdivisions=5, radius=0.3).export(folder / "sphere.ply")
    cube = trimesh.creation.box(extents=[0.35] * 3)
    cube.apply_translation([0.12, -0.05, 0.08])
    cube.export(folder / "cube.obj")
    return folder


def _render(engine: str, samples: int, paths, poses=POSES) -> list[dict]:
    renderer = render.BlenderRenderer(CONFIG, render.RenderSettings(samples=samples, denoise=False, engine=engine))
    try:
        out = []
        for path in paths:
            renderer.load_shape(path)
            out += [renderer.render_view(az, el, np.random.default_rng(3)) for az, el in poses]
        return out
    finally:
        renderer.close()


def _silhouette_band(hit: np.ndarray) -> np.ndarray:
    """Pixels with a 3×3 neighbour on the other side of the hit/background edge."""
    padded = np.pad(hit, 1, mode="edge")
    shifted = [padded[1 + dy:1 + dy + hit.shape[0], 1 + dx:1 + dx + hit.shape[1]]
               for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
    return np.any([s != hit for s in shifted], axis=0)


def _compare(reference: dict, other: dict) -> dict:
    """Depth and mask agreement of two renders of the same view."""
    ra, rb = reference["raw_depth"], other["raw_depth"]
    ha, hb = ra < 1e5, rb < 1e5
    assert set(np.unique(ra[~ha])) <= {render.RAW_BACKGROUND} and set(np.unique(rb[~hb])) <= {render.RAW_BACKGROUND}
    band = _silhouette_band(ha)
    both = ha & hb
    diff = np.abs(ra - rb)
    ma, mb = reference["rgba"][..., 3] >= 128, other["rgba"][..., 3] >= 128
    return {
        "hits": int(ha.sum()),
        "hit_xor_outside_band": int(((ha ^ hb) & ~band).sum()),
        "interior_max": float(diff[both & ~band].max()),
        "median": float(np.median(diff[both])),
        "mask_xor_outside_band": int(((ma ^ mb) & ~band).sum()),
        "mask_xor": int((ma ^ mb).sum()),
    }


def _assert_same_geometry(reference: list[dict], other: list[dict]) -> None:
    for a, b in zip(reference, other, strict=True):
        stats = _compare(a, b)
        assert stats["hits"] > 500, stats
        assert stats["hit_xor_outside_band"] == 0, stats
        assert stats["interior_max"] < INTERIOR_DEPTH_TOL, stats
        assert stats["median"] < 2e-5, stats
        assert stats["mask_xor_outside_band"] == 0, stats
        np.testing.assert_array_equal(a["rotation"], b["rotation"])


def test_workbench_depth_and_mask_match_cycles(meshes):
    paths = [meshes / "sphere.ply", meshes / "cube.obj"]
    cycles = _render("cycles", 4, paths)
    workbench = _render("workbench", 1, paths)
    _assert_same_geometry(cycles, workbench)
    # Its anti-aliasing changes neither the depth (taken at the pixel centre) nor which pixels are hit.
    workbench_aa = _render("workbench", 8, paths[:1])
    np.testing.assert_array_equal(workbench_aa[0]["raw_depth"], workbench[0]["raw_depth"])


@pytest.mark.slow
def test_eevee_depth_and_mask_match_cycles(meshes):
    """One view, 2 samples: the RGB render plus EEVEE's one-sample depth pass (background ≈ far clip → 1e10)."""
    paths = [meshes / "sphere.ply"]
    pose = POSES[1:]
    cycles = _render("cycles", 4, paths, pose)
    eevee = _render("eevee", 2, paths, pose)
    _assert_same_geometry(cycles, eevee)
    rgb_a, rgb_b = cycles[0]["rgba"][..., :3].astype(int), eevee[0]["rgba"][..., :3].astype(int)
    inside = (cycles[0]["rgba"][..., 3] == 255) & (eevee[0]["rgba"][..., 3] == 255)
    assert np.abs(rgb_a - rgb_b)[inside].mean() < 40  # the same lighting, another renderer's noise and shading


def _cli(tmp: Path, shapes: Path, *extra: str) -> int:
    return render_cli.main(["--shapes", str(shapes), "--out", str(tmp / "out"), "--views", "1", "--no-progress",
                            "--samples", "1", *extra])


def test_engine_is_recorded_and_a_folder_keeps_its_engine(meshes, tmp_path, capsys):
    shapes = tmp_path / "shapes"
    shapes.mkdir()
    shutil.copy(meshes / "cube.obj", shapes / "cube.obj")
    assert _cli(tmp_path, shapes, "--engine", "workbench") == 0
    out = tmp_path / "out"
    assert view_files.read_render_settings(out)["engine"] == "workbench"
    view = view_files.load_view(out / "cube", 0)
    assert view["camera"]["engine"] == "workbench" and (view["depth"] > 0).sum() > 500
    capsys.readouterr()
    assert _cli(tmp_path, shapes) == 2  # cycles (the default) into a workbench folder
    err = capsys.readouterr().err
    assert "engine='workbench' (asked: 'cycles')" in err and len(err.strip().splitlines()) == 1
    assert view_files.read_render_settings(out)["lighting"] == "random"  # the lighting is recorded too
    assert _cli(tmp_path, shapes, "--engine", "workbench", "--lighting", "camera-side") == 2
    assert "lighting='random' (asked: 'camera-side')" in capsys.readouterr().err
    # Folders rendered before engines and lightings were a choice were Cycles folders lit at random.
    settings = json.loads((out / view_files.SETTINGS_FILE).read_text())
    del settings["engine"], settings["lighting"]
    (out / view_files.SETTINGS_FILE).write_text(json.dumps(settings))
    assert view_files.read_render_settings(out)["engine"] == "cycles"
    assert view_files.read_render_settings(out)["lighting"] == "random"


def test_classes_renders_only_those_classes(meshes, tmp_path, capsys):
    corpus = tmp_path / "corpus"
    corpus.mkdir()
    shutil.copy(meshes / "cube.obj", corpus / "cube.obj")
    manifest = corpus / "manifest.json"
    manifest.write_text(json.dumps({"shapes": [
        {"id": "p1", "class": "primitive", "split": "unassigned", "groups": ["product-train"], "mesh": "cube.obj"},
        {"id": "c1", "class": "chair", "split": "train", "groups": ["product-train"], "mesh": "cube.obj"},
        {"id": "p2", "class": "primitive", "split": "unassigned", "groups": ["product-test"], "mesh": "cube.obj"}]}))
    assert _cli(tmp_path, manifest, "--engine", "workbench", "--split", "product-train", "--classes", "primitive") == 0
    out = tmp_path / "out"
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["p1"]
    capsys.readouterr()
    assert _cli(tmp_path, manifest, "--engine", "workbench", "--classes", "sofa") == 2
    assert "no shape of the classes ['sofa']" in capsys.readouterr().err


def test_no_egl_is_one_line_before_blender_could_abort(meshes, tmp_path, capsys, monkeypatch):
    shapes = tmp_path / "shapes"
    shapes.mkdir()
    shutil.copy(meshes / "cube.obj", shapes / "cube.obj")
    real_cdll = render.ctypes.CDLL

    def no_egl(name, *args, **kwargs):
        if "EGL" in str(name):
            raise OSError(f"{name}: cannot open shared object file")
        return real_cdll(name, *args, **kwargs)

    if not sys.platform.startswith("linux"):
        pytest.skip("the EGL check is for Linux")
    assert render.engine_problem("eevee") is None  # this machine has libEGL and Mesa's EGL driver
    assert render.engine_problem("cycles") is None
    assert "unknown engine" in render.engine_problem("vray")
    empty = tmp_path / "no-vendors"
    empty.mkdir()
    monkeypatch.setenv("__EGL_VENDOR_LIBRARY_DIRS", str(empty))
    assert "needs an EGL driver" in render.engine_problem("workbench")
    monkeypatch.delenv("__EGL_VENDOR_LIBRARY_DIRS")
    monkeypatch.setattr(render.ctypes, "CDLL", no_egl)
    assert _cli(tmp_path, shapes, "--engine", "eevee") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "libEGL.so.1 is missing" in err[0] and "apt-get install libegl1" in err[0]
    assert not (tmp_path / "out" / view_files.SETTINGS_FILE).exists()
    assert render.engine_problem("cycles") is None  # Cycles needs no OpenGL


def test_an_engine_this_blender_lacks_is_one_line(meshes, tmp_path, capsys, monkeypatch):
    shapes = tmp_path / "shapes"
    shapes.mkdir()
    shutil.copy(meshes / "cube.obj", shapes / "cube.obj")
    monkeypatch.setitem(render._ENGINE_IDS, "workbench", ("BLENDER_WORKBENCH_NEXT",))  # as in a Blender without it
    assert _cli(tmp_path, shapes, "--engine", "workbench") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "has no workbench engine" in err[0] and "BLENDER_WORKBENCH_NEXT" in err[0], err
    assert not (tmp_path / "out" / view_files.SETTINGS_FILE).exists()  # the folder is not claimed for it


# ---------------------------------------------------------------------------- a stock Blender

BLENDER = shutil.which("blender")
SCRIPT = ROOT / "training" / "render" / "blender_script.py"


def _blender_env(tmp: Path, **extra) -> dict:
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp / "user"), XDG_CACHE_HOME=str(tmp / "xdg"),
               GENRE_BLENDER_CACHE=str(tmp / "cache"))
    # an activated virtual environment puts its bin/ first on PATH, and Blender's embedded Python then finds
    # the environment's pyvenv.cfg and its packages by itself: the stock Blender must not be run that way here
    venv = env.pop("VIRTUAL_ENV", None)
    if venv:
        env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep) if Path(p).parent != Path(venv))
    env.update(extra)
    return env


@pytest.mark.slow
@pytest.mark.blender
def test_stock_blender_writes_the_same_views_as_the_bpy_module(meshes, tmp_path):
    shapes = tmp_path / "shapes"
    shapes.mkdir()
    shutil.copy(meshes / "sphere.ply", shapes / "ball.ply")
    shutil.copy(meshes / "cube.obj", shapes / "cube.obj")
    # Debian's Blender has no denoiser: both render without it.
    args = ["--shapes", str(shapes), "--views", "2", "--samples", "8", "--no-denoise", "--no-progress"]
    stock = subprocess.run([BLENDER, "--background", "--factory-startup", "--python", str(SCRIPT), "--",
                            *args, "--out", str(tmp_path / "stock")],
                           cwd=tmp_path, env=_blender_env(tmp_path), capture_output=True, text=True, timeout=600)
    assert stock.returncode == 0, stock.stdout + stock.stderr
    assert "rendered 4 views of 2 shapes" in stock.stdout
    code = f"import sys; from training.render.cli import main; sys.exit(main({args + ['--out', str(tmp_path / 'module')]!r}))"
    module = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=_blender_env(tmp_path), capture_output=True,
                            text=True, timeout=600)
    assert module.returncode == 0, module.stderr
    versions = set()
    for shape in ("ball", "cube"):
        for k in range(2):
            a = view_files.load_view(tmp_path / "stock" / shape, k)
            b = view_files.load_view(tmp_path / "module" / shape, k)
            versions.add((a["camera"]["blender"], b["camera"]["blender"]))
            ha, hb = a["depth"] > 0, b["depth"] > 0
            np.testing.assert_array_equal(ha, hb)  # both ray-trace with Cycles: the same pixels hit
            assert ha.sum() > 500
            assert np.abs(a["depth"] - b["depth"]).max() < 1e-5  # measured ≤ 5e-7
            band = _silhouette_band(ha)
            mask_a, mask_b = a["mask"] >= 0.5, b["mask"] >= 0.5
            assert not ((mask_a ^ mask_b) & ~band).any()
            assert {key: a["camera"][key] for key in CAMERA_KEYS} == {key: b["camera"][key] for key in CAMERA_KEYS}
            assert a["camera"]["lighting"] == b["camera"]["lighting"]  # the same seeded lights
            assert a["rgb"].shape == b["rgb"].shape
    (stock_version, module_version), = versions
    assert stock_version != module_version  # really two Blenders (e.g. 3.4.1 and 5.0.1)
    assert view_files.read_render_settings(tmp_path / "stock") == view_files.read_render_settings(tmp_path / "module")


@pytest.mark.blender
def test_stock_blender_without_the_dependencies_says_what_is_missing(tmp_path):
    done = subprocess.run([BLENDER, "--background", "--factory-startup", "--python", str(SCRIPT), "--",
                           "--shapes", str(tmp_path), "--out", str(tmp_path / "out")],
                          cwd=tmp_path, env=_blender_env(tmp_path, GENRE_VENV=str(tmp_path / "no-venv")),
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2
    errors = [line for line in done.stderr.splitlines() if "error" in line]
    assert len(errors) == 1, done.stderr
    assert "cannot import" in errors[0] and "torch" in errors[0] and str(tmp_path / "no-venv") in errors[0]
    assert not (tmp_path / "out").exists()


def _corpus_glb(folder: Path) -> Path:
    """A sphere (radius 0.3, centred) with a PBR base colour, written by the corpus's own .glb writer (returned),
    and beside it ``crate.glb``, a box with vertex colours and no material.

    Debian's Blender 3.4.1 imported no such file: its glTF importer calls
    ``np.bool``, which numpy 1.24–1.26 lack (training/render/scene.py).
    """
    from training.data.corpus import _export_glb  # noqa: PLC0415

    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.3)
    sphere.visual = trimesh.visual.TextureVisuals(
        material=trimesh.visual.material.PBRMaterial(baseColorFactor=[200, 120, 60, 255], roughnessFactor=0.6))
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "ball.glb"
    _export_glb([sphere], path)
    # and a box with vertex colours and no material, as the corpus's CRRCSim, FlightGear and TORCS models
    box = trimesh.creation.box(extents=(0.5, 0.4, 0.3))
    box.visual = trimesh.visual.ColorVisuals(box, vertex_colors=np.tile([[255, 0, 0, 255]], (len(box.vertices), 1)))
    _export_glb([box], folder / "crate.glb")
    return path


def _speckle(rgb: np.ndarray, inside: np.ndarray) -> float:
    """Mean |RGB - its 3×3 median| (0-255) over ``inside`` (H, W) bool; ``rgb`` (H, W, 3) uint8."""
    from scipy import ndimage  # noqa: PLC0415

    rgb = rgb.astype(np.float64)
    med = np.stack([ndimage.median_filter(rgb[..., c], size=3) for c in range(3)], axis=2)
    return float(np.abs(rgb - med).mean(axis=2)[inside].mean())


@pytest.mark.slow
@pytest.mark.blender
def test_stock_blender_renders_corpus_glbs_with_exact_depth_their_colours_and_less_noise(tmp_path):

    from genre_backend import frame  # noqa: PLC0415
    from genre_backend.geometry.analytic import sphere_depth  # noqa: PLC0415

    shapes = tmp_path / "shapes"
    _corpus_glb(shapes)
    base = ["--shapes", str(shapes), "--views", "2", "--no-progress", "--samples", "16", "--seed", "3"]
    runs = {}
    for name, extra in (("denoised", []), ("raw", ["--no-denoise"])):
        done = subprocess.run([BLENDER, "--background", "--factory-startup", "--python", str(SCRIPT), "--", *base,
                               *extra, "--out", str(tmp_path / name)],
                              cwd=tmp_path, env=_blender_env(tmp_path), capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stdout + done.stderr
        assert "rendered 4 views of 2 shapes" in done.stdout, done.stdout + done.stderr
        runs[name] = [view_files.load_view(tmp_path / name / "ball", k) for k in range(2)]
        crates = [view_files.load_view(tmp_path / name / "crate", k) for k in range(2)]
        for view in crates:  # its own colours (3.4's importer makes no material: not the random default colour)
            assert "default_material" not in view["camera"]["lighting"], view["camera"]["lighting"]
            red, green, blue = view["rgb"][view["mask"] >= 0.999].astype(float).mean(axis=0)
            assert red > 2 * green and red > 2 * blue, (red, green, blue)
    truth = frame.encode_raw_depth(sphere_depth(CONFIG.camera, CONFIG.geometry.image_size, 0.3)[0]).numpy()
    hit = truth > 0
    band = _silhouette_band(hit)
    inside = hit & ~band
    for name, views in runs.items():
        for view in views:
            got = view["depth"]
            assert not ((got > 0) ^ hit)[~band].any(), name  # the same pixels hit, away from the outline
            # an icosphere (subdivision 5) lies within 7e-5 of the sphere along the normal
            assert np.abs(got - truth)[inside].max() < 5e-4, name
            assert not (((view["mask"] >= 0.5) ^ hit) & ~band).any(), name
    cams = [v["camera"] for v in runs["denoised"]]
    if not cams[0].get("denoise"):  # a Blender without OpenImageDenoise (Debian's 3.4.1): more samples instead
        assert all(c["denoiser"] == "samples" and c["samples"] == 16 * render.NO_DENOISER_SAMPLE_FACTOR for c in cams)
    assert all(v["camera"]["denoiser"] is None and v["camera"]["samples"] == 16 for v in runs["raw"])
    speckle = {name: [_speckle(v["rgb"], inside) for v in views] for name, views in runs.items()}
    # measured with 3.4.1: 16 samples 8.3 and 4.3; adaptive up to 256: 2.2 and 1.1 (scripts/render_noise.py)
    assert all(d < 0.5 * r for d, r in zip(speckle["denoised"], speckle["raw"])), speckle
