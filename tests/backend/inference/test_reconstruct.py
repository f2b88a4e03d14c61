"""The reconstruction backend and ``genre reconstruct``, with weights trained here by the project's own code."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from genre_backend.frontends import reconstruct_cli
from genre_backend.nets.model import WEIGHTS_FORMAT, WeightsError, load_model
from genre_backend.inference.reconstruct import (DEFAULT_WEIGHTS, STAGES, Cancelled, Hooks, OutputError, Reconstructor,
                                                 error_code)
from genre_backend.photo.guidance import MaskGuidance
from genre_backend.photo.decode import ImageError
from support.files import huge_png
from support.tiny_data import TINY

REPO = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """The tiny model runs faster on one thread (and much faster when other jobs share the CPU)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def rec(trained):
    return Reconstructor(trained[0])


@pytest.fixture(scope="module")
def photos(trained, tmp_path_factory):
    """A rendered view as RGB, RGBA (alpha = the render's mask), its mask file, and every odd variant."""
    views = trained[1]
    d = tmp_path_factory.mktemp("photos")
    rgb = np.asarray(Image.open(views / "box" / "view_000.png").convert("RGB"))
    mask = np.load(views / "box" / "view_000.npz")["mask"] > 0.5
    p = {}
    p["rgb"] = views / "box" / "view_000.png"
    p["rgba"] = d / "rgba.png"
    Image.fromarray(np.dstack([rgb, mask.astype(np.uint8) * 255]), "RGBA").save(p["rgba"])
    p["mask"] = d / "mask.png"
    Image.fromarray(mask.astype(np.uint8) * 255, "L").save(p["mask"])
    p["empty_mask"] = d / "empty_mask.png"
    Image.new("L", rgb.shape[1::-1], 0).save(p["empty_mask"])
    p["small_mask"] = d / "small_mask.png"
    Image.new("L", (rgb.shape[1] // 2, rgb.shape[0] // 2), 255).save(p["small_mask"])
    p["transparent"] = d / "transparent.png"
    Image.new("RGBA", (64, 64), (200, 30, 30, 0)).save(p["transparent"])
    # accepted odd formats, all of the same render
    gray = np.asarray(Image.fromarray(rgb).convert("L"))
    p["gray16"] = d / "gray16.png"
    Image.fromarray(gray.astype(np.uint16) * 257).save(p["gray16"])
    assert Image.open(p["gray16"]).mode.startswith("I")
    p["gray"] = d / "gray.png"
    Image.fromarray(gray, "L").save(p["gray"])
    p["palette"] = d / "palette.png"
    Image.fromarray(rgb).quantize(64).save(p["palette"])
    p["cmyk"] = d / "cmyk.jpg"
    Image.fromarray(rgb).convert("CMYK").save(p["cmyk"], quality=95)
    p["animated"] = d / "animated.gif"
    first = Image.fromarray(rgb).quantize(128)
    first.save(p["animated"], save_all=True, append_images=[Image.new("P", first.size, 3)], duration=100, loop=0)
    # bad files
    p["text"] = d / "notes.png"
    p["text"].write_text("this is not an image\n")
    p["zero"] = d / "zero.png"
    p["zero"].write_bytes(b"")
    data = p["rgb"].read_bytes()
    p["truncated"] = d / "truncated.png"
    p["truncated"].write_bytes(data[: len(data) // 2])
    p["directory"] = d / "folder.png"
    p["directory"].mkdir()
    p["missing"] = d / "missing.png"
    p["huge"] = d / "huge.png"
    p["huge"].write_bytes(huge_png(30000, 30000))
    return p


# ---- the pipeline ------------------------------------------------------------------------------
def test_reconstructs_a_rendered_view_in_the_view_frame(rec, photos, trained, tmp_path):
    stages = []
    res = rec.run(photos["rgb"], hooks=Hooks(lambda s, f: stages.append((s, f))))
    assert res.mask_source == "salient"
    assert [s for s, _ in stages] == list(STAGES[:-1])
    fractions = [f for _, f in stages]
    assert fractions == sorted(fractions) and 0.0 <= fractions[0] and fractions[-1] < 1.0
    assert set(res.timings) == set(STAGES[:-1])
    assert res.vertices.dtype == np.float32 and res.vertices.shape[1] == 3
    assert res.faces.dtype == np.int64 and res.faces.shape[1] == 3 and len(res.faces) > 50
    assert np.abs(res.vertices).max() <= 0.5 + 1e-5  # inside the voxel cube of the view frame
    # every intermediate, with its documented shape
    g = TINY.geometry
    shapes = {"rgb": (3, 64, 64), "depth": (64, 64), "mask": (64, 64), "partial_sph": (g.sph_size,) * 2, "full_sph": (g.sph_size,) * 2,
              "vox_sph": (g.voxel_size,) * 3, "vox_depth": (g.voxel_size,) * 3, "logits": (g.voxel_size,) * 3}
    for name, shape in shapes.items():
        assert tuple(res.intermediates[name].shape) == shape, name
    assert res.intermediates["mask"].dtype == torch.bool and res.intermediates["mask"].any()
    # the reconstruction resembles the box it was rendered from, posed as seen
    meta = json.loads((trained[1] / "box" / "view_000.json").read_text())
    box = trimesh.load(trained[1].parent / "meshes" / "box.ply")
    rot = np.asarray(meta["rotation_cam_to_obj"])
    gt = box.vertices @ rot  # object → view frame (frame.object_to_view)
    lo, hi = res.vertices.min(0), res.vertices.max(0)
    assert np.all(np.abs((lo + hi) / 2 - (gt.min(0) + gt.max(0)) / 2) < 0.15), (lo, hi, gt.min(0), gt.max(0))
    # files: mesh and intermediates
    path, fmt = res.save_mesh(tmp_path / "box.glb")
    assert fmt == "glb" and len(trimesh.load(path, force="mesh").faces) == len(res.faces)
    pngs = res.save_intermediates(tmp_path / "inter")
    names = {p.name for p in pngs}
    assert {"input.png", "mask.png", "depth.png", "partial_sph.png", "full_sph.png", "vox_sph.png", "vox_depth.png", "mask_in_photo.png"} <= names
    for p in pngs:
        with Image.open(p) as im:
            assert im.size[0] >= 64
    assert not list(tmp_path.glob(".*tmp*"))  # atomic writes leave no temporary files


def test_mask_source_order(rec, photos):
    assert rec.run(photos["rgb"], MaskGuidance(mask=photos["mask"])).mask_source == "file"
    assert rec.run(photos["rgba"], MaskGuidance(mask=photos["mask"])).mask_source == "file"
    assert rec.run(photos["rgba"]).mask_source == "alpha"
    assert rec.run(photos["rgb"]).mask_source == "salient"
    assert rec.run(photos["rgb"], MaskGuidance(refine=False)).mask_source == "silhouette"
    # an opaque alpha channel is no mask: the photo is segmented
    opaque = photos["rgba"].with_name("opaque.png")
    Image.open(photos["rgb"]).convert("RGBA").save(opaque)
    assert rec.run(opaque).mask_source == "salient"


@pytest.mark.parametrize("kind", ["gray16", "gray", "palette", "cmyk", "animated"])
def test_odd_but_valid_images_reconstruct(rec, photos, kind):
    res = rec.run(photos[kind], MaskGuidance(mask=photos["mask"]))
    assert len(res.faces) > 0 and res.mask_source == "file"


def test_cancel_at_a_stage_boundary(rec, photos):
    seen = []

    def progress(stage, fraction):
        seen.append(stage)

    with pytest.raises(Cancelled):
        rec.run(photos["rgba"], hooks=Hooks(progress, lambda: "inpaint" in seen))
    assert seen[-1] == "inpaint" and seen == list(STAGES[: STAGES.index("inpaint") + 1])


def test_bad_arguments_and_weights(trained, tmp_path):
    corrupt = tmp_path / "corrupt.safetensors"
    corrupt.write_bytes(trained[0].read_bytes()[:1000])
    with pytest.raises(WeightsError, match="not a readable safetensors"):
        Reconstructor(corrupt)
    from safetensors.torch import save_file

    model = load_model(trained[0])
    other = tmp_path / "other.safetensors"
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(other), metadata={"format": "genre-weights/0", "config": "{}"})
    with pytest.raises(WeightsError, match=r"genre-weights/0.*" + WEIGHTS_FORMAT):
        Reconstructor(other)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="no CUDA device"):
            Reconstructor(trained[0], device="cuda")
    with pytest.raises(ValueError, match="device"):
        Reconstructor(trained[0], device="tpu")


# ---- the command line -----------------------------------------------------------------------------
def _cli(capsys, *args):
    code = reconstruct_cli.main([str(a) for a in args], prog="genre reconstruct")
    out, err = capsys.readouterr()
    return code, out, err


def test_cli_writes_each_format(trained, photos, tmp_path, capsys):
    for fmt in ("obj", "ply", "glb"):
        code, out, err = _cli(capsys, photos["rgb"], "-o", tmp_path / f"m.{fmt}", "--weights", trained[0], "--threshold", 0.5)
        assert code == 0, err
        assert "mask: salient" in out
        assert len(trimesh.load(tmp_path / f"m.{fmt}", force="mesh").faces) > 0
    with pytest.raises(SystemExit) as exc:  # argparse: the format contradicts the extension
        _cli(capsys, photos["rgba"], "-o", tmp_path / "x.obj", "--format", "ply", "--weights", trained[0])
    assert exc.value.code == 2 and "does not match" in capsys.readouterr().err
    folder = tmp_path / "folder"
    folder.mkdir()
    code, out, err = _cli(capsys, photos["rgba"], "-o", folder, "--format", "ply", "--weights", trained[0], "--save-intermediates", tmp_path / "inter")
    assert code == 0, err
    assert (folder / "rgba.ply").is_file() and (tmp_path / "inter" / "full_sph.png").is_file()


def test_cli_texture_and_parts(trained, photos, tmp_path, capsys):
    code, out, err = _cli(capsys, photos["rgba"], "-o", tmp_path / "c.obj", "--texture", "--weights", trained[0])
    assert code == 0, err
    assert "coloured from the photo" in out and "watertight" in out
    assert {p.name for p in tmp_path.iterdir()} == {"c.obj", "c.mtl", "c_texture.png"}
    mesh = trimesh.load(tmp_path / "c.obj", process=False)
    assert len(mesh.visual.uv) == len(mesh.vertices)
    # the default drops small parts; --all-parts keeps them (never fewer parts than the default)
    counts = {}
    for flag in ((), ("--all-parts",)):
        code, out, err = _cli(capsys, photos["rgb"], "-o", tmp_path / "p.ply", "--weights", trained[0], "--threshold", 0.3, *flag)
        assert code == 0, err
        counts[flag] = int(out.split(" part")[0].rsplit(", ", 1)[1])
        assert counts[flag] == len(trimesh.load(tmp_path / "p.ply", process=False).split(only_watertight=False))
    assert counts[()] <= counts[("--all-parts",)]
    # an OBJ's texture must not replace the photo it is made from
    photo = tmp_path / "q_texture.png"
    photo.write_bytes(photos["rgba"].read_bytes())
    code, out, err = _cli(capsys, photo, "-o", tmp_path / "q.obj", "--texture", "--weights", trained[0])
    assert code == 1 and "input" in err and "[output_unwritable]" in err
    assert photo.read_bytes() == photos["rgba"].read_bytes() and not (tmp_path / "q.obj").exists()


BAD_INPUTS = {
    "text": ("bad_image", "not an image"),
    "zero": ("bad_image", "empty file (0 bytes)"),
    "truncated": ("bad_image", "truncated"),
    "directory": ("bad_image", "is a directory"),
    "missing": ("bad_image", "no such file"),
    "huge": ("bad_image", "too large"),
    "transparent": ("no_object", "no object"),
}


def test_cli_many_images_one_line_per_bad_input(trained, photos, tmp_path, capsys):
    good = [photos["rgb"], photos["rgba"], photos["gray"], photos["palette"], photos["cmyk"], photos["animated"], photos["gray16"]]
    bad = [photos[k] for k in BAD_INPUTS]
    out_dir = tmp_path / "meshes"
    code, out, err = _cli(capsys, *good[:2], *bad, *good[2:], "-o", out_dir, "--weights", trained[0], "--format", "ply")
    assert code == 1
    errors = [line for line in err.splitlines() if "error:" in line]
    assert len(errors) == len(bad), err
    for (kind, (code_name, text)), line in zip(BAD_INPUTS.items(), errors):
        assert str(photos[kind]) in line and text in line and f"[{code_name}]" in line, (kind, line)
    written = sorted(p.name for p in out_dir.iterdir())
    # every good image was reconstructed (grayscale and friends through GrabCut) or failed cleanly
    ok_lines = [line for line in out.splitlines() if " -> " in line]
    assert len(ok_lines) + 0 == len(written) and len(written) >= 2
    assert f"{len(bad)} of {len(good) + len(bad)} images failed" in err


@pytest.mark.parametrize(
    "mask, code_name, text",
    [("empty_mask", "bad_mask", "empty mask"), ("small_mask", "bad_mask", "mask is 32×32, the image is 64×64"), ("missing", "bad_mask", "no such file"),
     ("text", "bad_mask", "not an image")],
)
def test_cli_bad_masks(trained, photos, tmp_path, capsys, mask, code_name, text):
    code, out, err = _cli(capsys, photos["rgb"], "--mask", photos[mask], "-o", tmp_path / "m.obj", "--weights", trained[0])
    assert code == 1
    lines = err.strip().splitlines()
    assert len(lines) == 1 and text in lines[0] and f"[{code_name}]" in lines[0], err
    assert not (tmp_path / "m.obj").exists()


def test_cli_unwritable_output_and_bad_weights(trained, photos, tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    for out in (blocker / "m.obj", tmp_path / "no" / "such" / "dir" / "m.obj"):
        code, _, err = _cli(capsys, photos["rgba"], "-o", out, "--weights", trained[0])
        assert code == 1 and "[output_unwritable]" in err and len(err.strip().splitlines()) == 1, err
    corrupt = tmp_path / "corrupt.safetensors"
    corrupt.write_bytes(b"\x00" * 100)
    code, _, err = _cli(capsys, photos["rgba"], "-o", tmp_path / "m.obj", "--weights", corrupt)
    assert code == 1 and "[bad_weights]" in err and len(err.strip().splitlines()) == 1
    code, _, err = _cli(capsys, photos["rgba"], "-o", tmp_path / "m.obj", "--weights", tmp_path / "nope.safetensors")
    assert code == 1 and "weights file not found" in err
    if not DEFAULT_WEIGHTS.is_file():
        code, _, err = _cli(capsys, photos["rgba"], "-o", tmp_path / "m.obj")
        assert code == 1 and str(DEFAULT_WEIGHTS) in err and "--weights" in err and "genre train" in err


@pytest.mark.slow
def test_genre_entry_point(trained, photos, tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    out = tmp_path / "m.obj"
    inter = tmp_path / "inter"
    proc = subprocess.run([sys.executable, "-m", "genre_backend.cli", "reconstruct", str(photos["rgba"]), "-o", str(out), "--weights", str(trained[0]),
                           "--save-intermediates", str(inter)], capture_output=True, text=True, cwd=REPO, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "mask: alpha" in proc.stdout and out.is_file() and (inter / "depth.png").is_file()
    proc = subprocess.run([sys.executable, "-m", "genre_backend.cli", "reconstruct", str(photos["huge"]), "--weights", str(trained[0])],
                          capture_output=True, text=True, cwd=REPO, env=env, timeout=300)
    assert proc.returncode == 1 and "too large" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


def test_error_codes():
    assert error_code(ImageError("bad_mask", "x")) == "bad_mask"
    assert error_code(OutputError("x")) == "output_unwritable"
    assert error_code(WeightsError("x")) == "bad_weights"
    assert error_code(RuntimeError("x")) == "internal"


def test_cli_preview_shows_the_mesh(trained, photos, tmp_path, capsys):
    from PIL import Image

    code, out, err = _cli(capsys, photos["rgba"], "-o", tmp_path / "m.obj", "--weights", trained[0], "--preview")
    assert code == 0, err
    with Image.open(tmp_path / "m_preview.png") as im:
        rgb = np.asarray(im.convert("RGB"))
    from genre_backend.output.preview import SHEET, preview_layout

    assert rgb.shape == (SHEET[1], SHEET[0], 3)
    # the large front panel holds the mesh rendered in Blender: shaded clay pixels, not an empty white square
    x0, y0, x1, y1 = preview_layout()["front"]
    panel = rgb[y0:y1, x0:x1].astype(int)
    assert (panel.sum(axis=2) < 3 * 240).sum() > 0.05 * panel.shape[0] * panel.shape[1]


def test_hole_closing_is_the_weights_unless_asked(rec, photos, tmp_path, capsys, trained):
    assert rec.run(photos["rgba"]).options.hole_closing == rec.config.geometry.hole_closing == 0
    assert rec.run(photos["rgba"], hole_closing=3).options.hole_closing == 3
    for bad in (99, -1, 1.5, True):
        with pytest.raises(ValueError, match="hole_closing"):
            rec.run(photos["rgba"], hole_closing=bad)
    code, out, err = _cli(capsys, photos["rgba"], "-o", tmp_path / "h.obj", "--weights", trained[0], "--hole-closing", 2)
    assert code == 0, err
    with pytest.raises(SystemExit) as exc:
        _cli(capsys, photos["rgba"], "-o", tmp_path / "h.obj", "--weights", trained[0], "--hole-closing", 99)
    assert exc.value.code == 2 and "--hole-closing" in capsys.readouterr().err


def test_pit_sealing_fills_the_pits_of_the_grids_own_front(photos, tmp_path, capsys, trained):
    import dataclasses

    from genre_backend.geometry.mesh_voxels import fill_enclosed
    from genre_backend.geometry.visible_front import seal_pits
    from genre_backend.nets.model import load_model

    model = load_model(trained[0])
    g = model.config.geometry
    if g.target != "distance":  # pits are sealed in the distance target only
        model.config = dataclasses.replace(model.config, geometry=dataclasses.replace(g, target="distance"))
    rec = Reconstructor.from_model(model)
    assert rec.config.geometry.pit_sealing == 0  # weights stored without the key: off
    plain = rec.run(photos["rgba"], threshold=0.3)
    sealed = rec.run(photos["rgba"], threshold=0.3, pit_sealing=8)
    assert (plain.options.pit_sealing, sealed.options.pit_sealing) == (0, 8)
    inter = sealed.intermediates
    assert torch.equal(inter["logits"], plain.intermediates["logits"])  # the nets are untouched
    expected = seal_pits(torch.sigmoid(inter["logits"]), inter["mask"], rec.config.camera, rec.config.geometry, 0.3, 8)
    expected = torch.from_numpy(fill_enclosed(expected, 0.3, sealed.options.hole_closing))
    assert torch.allclose(inter["probability"], expected)
    for bad in (-1, 9, 2.5, True):
        with pytest.raises(ValueError, match="pit_sealing"):
            rec.run(photos["rgba"], pit_sealing=bad)
    model.config = dataclasses.replace(model.config, geometry=dataclasses.replace(model.config.geometry, target="shell"))
    with pytest.raises(ValueError, match="pit_sealing"):
        Reconstructor.from_model(model).run(photos["rgba"], pit_sealing=2)
    with pytest.raises(SystemExit) as exc:
        _cli(capsys, photos["rgba"], "-o", tmp_path / "p.obj", "--weights", trained[0], "--pit-sealing", 9)
    assert exc.value.code == 2 and "--pit-sealing" in capsys.readouterr().err
    if g.target == "distance":
        code, out, err = _cli(capsys, photos["rgba"], "-o", tmp_path / "p.obj", "--weights", trained[0], "--pit-sealing", 2)
        assert code == 0, err

def test_visible_fusion_fills_the_holes_in_the_visible_face_from_the_depth(photos, tmp_path, capsys, trained):
    import dataclasses

    from genre_backend.geometry.mesh_voxels import fill_enclosed
    from genre_backend.geometry.visible_front import fuse_visible_surface
    from genre_backend.nets.model import load_model

    model = load_model(trained[0])
    g = model.config.geometry
    if g.target != "distance":  # the fusion is defined on the distance target only
        model.config = dataclasses.replace(model.config, geometry=dataclasses.replace(g, target="distance"))
    rec = Reconstructor.from_model(model)
    assert rec.config.geometry.visible_fusion is False  # weights stored without the key: off
    plain = rec.run(photos["rgba"], threshold=0.3)
    fused = rec.run(photos["rgba"], threshold=0.3, visible_fusion=True)
    assert (plain.options.visible_fusion, fused.options.visible_fusion) == (False, True)
    inter = fused.intermediates
    assert torch.equal(inter["logits"], plain.intermediates["logits"])  # the nets are untouched
    expected = fuse_visible_surface(torch.sigmoid(inter["logits"]), inter["masked_depth"], rec.config.camera, rec.config.geometry, 0.3)
    expected = torch.from_numpy(fill_enclosed(expected, 0.3, fused.options.hole_closing))
    assert torch.allclose(inter["probability"], expected)
    for bad in (1, "yes"):
        with pytest.raises(ValueError, match="visible_fusion"):
            rec.run(photos["rgba"], visible_fusion=bad)
    shell = dataclasses.replace(model.config.geometry, target="shell")
    model.config = dataclasses.replace(model.config, geometry=shell)
    with pytest.raises(ValueError, match="visible_fusion"):
        Reconstructor.from_model(model).run(photos["rgba"], visible_fusion=True)
    if g.target == "distance":
        code, out, err = _cli(capsys, photos["rgba"], "-o", tmp_path / "f.obj", "--weights", trained[0], "--visible-fusion")
        assert code == 0 and (tmp_path / "f.obj").is_file(), err


@pytest.mark.slow
def test_primitive_snap_replaces_the_mesh_by_the_fitted_shape(rec, photos, tmp_path, capsys, trained):
    from genre_backend.geometry.cleanup import is_watertight
    from genre_backend.geometry.primitive_shapes import FAMILIES
    from genre_backend.geometry.primitives import snap

    assert rec.config.geometry.primitive_snap == 0.0  # weights stored without the key: off
    plain = rec.run(photos["rgba"], threshold=0.3)
    assert plain.primitive is None and plain.options.primitive_snap == 0.0
    snapped = rec.run(photos["rgba"], threshold=0.3, primitive_snap=0.99)  # so loose that the best fit is always taken
    assert snapped.primitive in FAMILIES and snapped.options.primitive_snap == 0.99
    assert torch.equal(snapped.intermediates["logits"], plain.intermediates["logits"])  # the nets are untouched
    v, f, fit = snap(plain.vertices, plain.faces, plain.intermediates["masked_depth"], rec.config.camera, 0.99)
    assert fit.family == snapped.primitive and np.allclose(v, snapped.vertices) and np.array_equal(f, snapped.faces)
    assert is_watertight(snapped.faces) and snapped.clean.parts == 1
    assert any(snapped.primitive in note for note in snapped.notes)
    strict = rec.run(photos["rgba"], threshold=0.3, primitive_snap=1e-6)  # nothing fits that well: the mesh stays
    assert strict.primitive is None and np.array_equal(strict.faces, plain.faces)
    for bad in (1.0, -0.1, True, "0.1", float("nan")):
        with pytest.raises(ValueError, match="primitive_snap"):
            rec.run(photos["rgba"], primitive_snap=bad)
    code, out, err = _cli(capsys, photos["rgba"], "-o", tmp_path / "p.obj", "--weights", trained[0], "--primitive-snap", 0.99)
    assert code == 0 and "a fitted" in out, err
    with pytest.raises(SystemExit) as exc:
        _cli(capsys, photos["rgba"], "-o", tmp_path / "p.obj", "--weights", trained[0], "--primitive-snap", 1.5)
    assert exc.value.code == 2 and "--primitive-snap" in capsys.readouterr().err


def test_plain_backdrop_paints_the_photo_outside_the_mask_grey(rec, photos, tmp_path, trained):
    from genre_backend.photo.preprocess import NEUTRAL_BACKGROUND, on_plain_backdrop

    rgb = np.asarray(Image.open(photos["rgb"]).convert("RGB"))
    mask = np.asarray(Image.open(photos["mask"])) > 127
    noisy = rgb.copy()
    noisy[~mask] = np.random.default_rng(0).integers(0, 256, size=(int((~mask).sum()), 3), dtype=np.uint8)
    Image.fromarray(noisy).save(tmp_path / "noisy.png")
    guide = MaskGuidance(mask=photos["mask"])
    assert rec.config.geometry.plain_backdrop is False  # weights stored without the key: off
    off = rec.run(tmp_path / "noisy.png", guide, threshold=0.3)
    on = rec.run(tmp_path / "noisy.png", guide, threshold=0.3, plain_backdrop=True)
    assert (off.options.plain_backdrop, on.options.plain_backdrop) == (False, True)
    seen, kept, inside = on.intermediates["rgb"], off.intermediates["rgb"], on.intermediates["mask"]
    grey = torch.tensor(NEUTRAL_BACKGROUND).view(3, 1, 1).expand_as(seen)
    assert torch.equal(seen[:, ~inside], grey[:, ~inside])  # the nets saw grey outside the mask ...
    assert torch.equal(seen[:, inside], kept[:, inside])  # ... and the framed photo inside it
    assert (kept[:, ~inside] - grey[:, ~inside]).abs().mean() > 0.1  # where the noise is, without the option
    with torch.no_grad():  # what the nets made is the pipeline on that picture
        want = rec.model(seen[None], mask=inside[None]).logits[0, 0]
    assert torch.allclose(on.intermediates["logits"], want, atol=1e-5)
    assert not torch.allclose(on.intermediates["logits"], off.intermediates["logits"], atol=1e-3)
    # the depth net's own silhouette is no mask to paint by: without one the option changes nothing
    own = MaskGuidance(refine=False)
    assert torch.equal(rec.run(photos["rgb"], own, plain_backdrop=True).intermediates["logits"],
                       rec.run(photos["rgb"], own).intermediates["logits"])
    with pytest.raises(ValueError, match="on_plain_backdrop"):
        on_plain_backdrop(seen[:2], inside)
    with pytest.raises(ValueError, match="plain_backdrop"):
        rec.run(photos["rgb"], plain_backdrop="yes")


def test_test_time_mirror_averages_the_photo_with_its_mirror_image(rec, photos, tmp_path, capsys, trained):
    from genre_backend.geometry.voxels import mirror_voxels
    from genre_backend.nets.model import mean_probability_logits

    assert rec.config.geometry.test_time_mirror is False  # weights stored without the key: off
    plain = rec.run(photos["rgba"], threshold=0.3)
    both = rec.run(photos["rgba"], threshold=0.3, test_time_mirror=True)
    assert (plain.options.test_time_mirror, both.options.test_time_mirror) == (False, True)
    inter = plain.intermediates
    with torch.no_grad():  # the mirror image of the crop the nets saw, with the mirror image of its mask
        mirrored = rec.model(inter["rgb"].flip(-1)[None], mask=inter["mask"].flip(-1)[None]).logits
    want = mean_probability_logits(inter["logits"][None, None], mirror_voxels(mirrored))[0, 0]
    assert torch.allclose(both.intermediates["logits"], want, atol=1e-5)
    assert torch.equal(both.intermediates["masked_depth"], inter["masked_depth"])  # the rest is the photo's own
    assert not np.array_equal(both.faces, plain.faces) or not np.allclose(both.vertices, plain.vertices)
    for bad in (1, "yes", 0.5):
        with pytest.raises(ValueError, match="test_time_mirror"):
            rec.run(photos["rgba"], test_time_mirror=bad)
    code, out, err = _cli(capsys, photos["rgba"], "-o", tmp_path / "m.obj", "--weights", trained[0], "--test-time-mirror")
    assert code == 0 and (tmp_path / "m.obj").is_file(), err


def test_silhouette_carve_empties_what_falls_outside_the_mask(rec, photos, tmp_path, capsys, trained):
    from genre_backend.geometry.mesh_voxels import fill_enclosed
    from genre_backend.geometry.voxels import silhouette_ramp

    assert rec.config.geometry.silhouette_carve is False  # weights stored without the key: off
    plain = rec.run(photos["rgba"], threshold=0.3)
    carved = rec.run(photos["rgba"], threshold=0.3, silhouette_carve=True)
    assert (plain.options.silhouette_carve, carved.options.silhouette_carve) == (False, True)
    ramp = silhouette_ramp(carved.intermediates["mask"][None], rec.config.camera, rec.config.geometry.voxel_size)[0, 0]
    inside = ramp > 0
    p0, p1 = plain.intermediates["probability"], carved.intermediates["probability"]
    assert torch.equal(carved.intermediates["logits"], plain.intermediates["logits"])  # the nets are untouched
    expected = torch.minimum(torch.sigmoid(carved.intermediates["logits"]), ramp)
    if rec.config.geometry.target == "distance":  # then the enclosed voxels are filled, as without the carve
        expected = torch.from_numpy(fill_enclosed(expected, 0.3, carved.options.hole_closing))
    assert bool((p1[~inside] == 0).all()) and torch.allclose(p1, expected)
    assert float(p0[~inside].max()) > 0.3  # the tiny refiner spills past the outline, so the carve removes something
    for bad in (1, "yes", 0.5):
        with pytest.raises(ValueError, match="silhouette_carve"):
            rec.run(photos["rgba"], silhouette_carve=bad)
    code, out, err = _cli(capsys, photos["rgba"], "-o", tmp_path / "c.obj", "--weights", trained[0], "--silhouette-carve")
    assert code == 0 and (tmp_path / "c.obj").is_file(), err


def test_sph_hull_carve_empties_what_lies_beyond_the_full_map_s_surface(rec, photos, tmp_path, capsys, trained):
    from genre_backend.geometry.mesh_voxels import fill_enclosed
    from genre_backend.geometry.spherical import sph_hull_ramp

    g = rec.config.geometry
    assert g.sph_hull_carve is False  # weights stored without the key: off
    plain = rec.run(photos["rgba"], threshold=0.3)
    trimmed = rec.run(photos["rgba"], threshold=0.3, sph_hull_carve=True)
    assert (plain.options.sph_hull_carve, trimmed.options.sph_hull_carve) == (False, True)
    assert torch.equal(trimmed.intermediates["logits"], plain.intermediates["logits"])  # the nets are untouched
    hull = sph_hull_ramp(trimmed.intermediates["full_sph"][None], g.voxel_size, g.sph_nohit_min, g.sph_hull_spread)[0, 0]
    expected = torch.minimum(torch.sigmoid(trimmed.intermediates["logits"]), hull)
    if g.target == "distance":  # then the enclosed voxels are filled, as without the trim
        expected = torch.from_numpy(fill_enclosed(expected, 0.3, trimmed.options.hole_closing))
    p0, p1 = plain.intermediates["probability"], trimmed.intermediates["probability"]
    assert torch.allclose(p1, expected) and bool((p1[hull == 0] == 0).all())
    assert float(p0[hull == 0].max()) > 0.3  # the tiny refiner spills past its map, so the trim removes something
    code, out, err = _cli(capsys, photos["rgba"], "-o", tmp_path / "h.obj", "--weights", trained[0], "--sph-hull-carve")
    assert code == 0 and (tmp_path / "h.obj").is_file(), err


_EXIT_SCRIPT = """
import atexit, sys, threading
from pathlib import Path
from genre_backend import cli
mark, thread = Path(sys.argv[1]), sys.argv[2]
atexit.register(lambda: mark.write_text("exit functions ran"))
if thread == "thread":
    threading.Thread(target=lambda: (__import__("time").sleep(0.5), Path(f"{mark}.thread").write_text("done"))).start()
sys.stdout.write("unflushed, no newline")
sys.argv = ["genre", "reconstruct", f"{mark}.missing.png"]
cli.run()
"""


@pytest.mark.parametrize("thread", ["none", "thread"])
def test_genre_reconstruct_ends_quickly_but_whole(tmp_path, thread):
    """The process of a quick-exit command (genre reconstruct) skips the interpreter's tear-down (its time:
    ``genre bench reconstruct``'s exit row), but its exit status, its exit functions and its buffered output are
    kept; a thread still running is waited for (a normal exit)."""
    mark = tmp_path / "mark"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "-c", _EXIT_SCRIPT, str(mark), thread], capture_output=True, text=True,
                          cwd=REPO, env=env, timeout=300)
    assert proc.returncode == 1, proc.stderr  # the missing photo: one line, status 1
    assert proc.stdout == "unflushed, no newline"
    assert proc.stderr.endswith("mark.missing.png: no such file [bad_image]\n") and proc.stderr.count("\n") == 1
    assert mark.read_text() == "exit functions ran"
    assert (tmp_path / "mark.thread").is_file() == (thread == "thread")


def test_weights_that_keep_the_seen_side_keep_it_in_reconstruction_as_in_the_model(photos, trained, tmp_path):
    """``geometry.sph_keep_seen``: the full map ``genre reconstruct`` refines is the model's own (its seen side the
    partial map's), so the shipped pipeline and ``genre eval`` (the model's forward) give the same grid."""
    import dataclasses

    from genre_backend.nets.model import GenRe, load_model, save_model

    model = load_model(trained[0])
    keep = GenRe(dataclasses.replace(model.config, geometry=dataclasses.replace(model.config.geometry, sph_keep_seen=True)))
    keep.load_state_dict(model.state_dict())
    save_model(keep, tmp_path / "keep.safetensors")
    inter = Reconstructor(tmp_path / "keep.safetensors").run(photos["rgba"], threshold=0.3).intermediates
    seen = inter["partial_sph"] < model.config.geometry.sph_nohit_min
    assert 0 < int(seen.sum()) < seen.numel()
    assert torch.equal(inter["full_sph"][seen], inter["partial_sph"][seen])
    with torch.no_grad():
        out = keep.eval()(inter["rgb"][None], mask=inter["mask"][None])
    # the same map and grid to float rounding: the two paths' convolutions round differently (with the tiny weights
    # trained by fused Adam, measured up to 8e-6 on 7 of 1,024 radii of ~0.9 and 1.2e-4 on 7 of 32,768 logits up to
    # 4.6; a different map would be off by 1e-2 or more)
    assert torch.allclose(inter["full_sph"], out.full_sph[0], atol=2e-5)
    assert torch.allclose(inter["logits"], out.logits[0, 0], atol=5e-4)
