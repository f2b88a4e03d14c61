"""Masks of photos without a user mask: GrabCut refinement, the doubtful-mask warning, mask_in_photo.png."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from genre_backend.frontends import reconstruct_cli
from genre_backend.photo.decode import load_image, load_mask
from genre_backend.inference.reconstruct import Reconstructor
from genre_backend.photo.guidance import MaskGuidance
from genre_backend.photo.mask_doubt import border_touch, cover, doubt
from genre_backend.photo.segment import refine_mask


def _photo(w: int = 240, h: int = 180, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """((h, w, 3) uint8 photo, (h, w) bool object): a shaded, noisy brown ellipse on a noisy green-to-grey gradient."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    obj = ((xx - 0.55 * w) / (0.26 * w)) ** 2 + ((yy - 0.52 * h) / (0.3 * h)) ** 2 <= 1.0
    t = yy / h
    bg = np.stack([60 + 90 * t, 140 - 20 * t, 70 + 80 * t], axis=-1)
    shade = 0.75 + 0.25 * np.cos((xx - 0.5 * w) / w * 3.0)
    fg = np.stack([170 * shade, 95 * shade, 45 * shade], axis=-1)
    img = np.where(obj[..., None], fg, bg) + rng.normal(0.0, 12.0, (h, w, 3))
    return np.clip(img, 0, 255).astype(np.uint8), obj


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum()) / float((a | b).sum())


# ---- GrabCut on a photo whose object is known --------------------------------------------------
def test_grabcut_border_seeding_finds_the_object():
    rgb, truth = _photo()
    mask, used = refine_mask(rgb, seeding="border")
    assert used == "border" and mask.shape == truth.shape and mask.dtype == bool
    assert _iou(mask, truth) >= 0.95


def test_grabcut_network_seeding_corrects_a_rough_silhouette():
    from scipy.ndimage import binary_dilation, gaussian_filter

    rgb, truth = _photo(seed=1)
    # a silhouette like the depth net's on a photo: blurred, 6 px too wide, and a false blob in a corner
    rough = binary_dilation(truth, iterations=6)
    rough[5:40, 5:50] = True
    prob = np.clip(gaussian_filter(rough.astype(np.float64), 4.0), 0.0, 1.0)
    before = _iou(prob > 0.5, truth)
    mask, used = refine_mask(rgb, prob, "network")
    assert used == "network"
    after = _iou(mask, truth)
    assert before < 0.8 and after >= 0.9 and after > before + 0.1, (before, after)
    # a silhouette that is the whole frame is doubtful: "auto" seeds from the border instead
    mask, used = refine_mask(rgb, np.ones(truth.shape), "auto")
    assert used == "border" and _iou(mask, truth) >= 0.95
    with pytest.raises(ValueError, match="needs the silhouette probability"):
        refine_mask(rgb, None, "network")
    with pytest.raises(ValueError, match="seeding"):
        refine_mask(rgb, None, "corners")


def test_doubt_measures():
    frame = np.ones((40, 60), bool)
    assert cover(frame) == 1.0 and border_touch(frame) == 1.0
    assert doubt(frame) == "the mask covers 100% of the photo and touches 100% of its border: it is probably the photo's frame, not the object"
    centred = np.zeros((40, 60), bool)
    centred[10:30, 15:45] = True
    assert doubt(centred) is None and border_touch(centred) == 0.0
    # a thin frame: little of the photo, all of its border
    ring = ~centred
    ring[2:-2, 2:-2] = False
    assert cover(ring) < 0.85 and border_touch(ring) == 1.0 and doubt(ring, "silhouette").startswith("the silhouette touches 100% of its border")
    # touching the bottom edge only (an object cut by the frame) is no doubt: 60 of the 196 border pixels
    bottom = np.zeros((40, 60), bool)
    bottom[20:, :] = True
    assert border_touch(bottom) == pytest.approx((60 + 2 * 19) / 196) and doubt(bottom) is None


# ---- through the reconstruction -----------------------------------------------------------------
class _FrameSilhouette(torch.nn.Module):
    """The depth net with its silhouette replaced by the whole frame (what it does on many real photos)."""

    def __init__(self, net: torch.nn.Module):
        super().__init__()
        self.net = net

    def forward(self, x):
        out = dict(self.net(x))
        out["silhouette_logits"] = torch.full_like(out["silhouette_logits"], 8.0)
        return out


@pytest.fixture(scope="module")
def photo(tmp_path_factory):
    rgb, truth = _photo(w=203, h=151, seed=2)  # odd sizes: no pixel may shift on the way back
    d = tmp_path_factory.mktemp("masks")
    Image.fromarray(rgb).save(d / "photo.png")
    return d / "photo.png", truth


def test_mask_warning_when_the_silhouette_is_the_whole_frame(trained, photo, tmp_path, monkeypatch, capsys):
    rec = Reconstructor(trained[0])
    rec.model.depth_net = _FrameSilhouette(rec.model.depth_net)
    path, truth = photo
    res = rec.run(path, MaskGuidance(refine=False))  # the silhouette as it is: the whole photo
    assert res.mask_source == "silhouette" and res.photo_mask.all()
    assert res.mask_warning == "the mask covers 100% of the photo and touches 100% of its border: it is probably the photo's frame, not the object"
    res = rec.run(path)  # refined: the salient net's mask, whatever the silhouette
    assert res.mask_source == "salient" and res.mask_warning is None
    assert _iou(res.photo_mask, truth) >= 0.9
    # the command line says so on stderr, and still writes the mesh
    original = Reconstructor._prepare
    monkeypatch.setattr(Reconstructor, "_prepare", staticmethod(lambda model: _frame(original(model))))
    code = reconstruct_cli.main([str(path), "-o", str(tmp_path / "a.obj"), "--weights", str(trained[0]), "--no-refine"])
    out, err = capsys.readouterr()
    assert code == 0 and (tmp_path / "a.obj").is_file() and "mask: silhouette" in out
    assert f"warning: {path}: doubtful mask: the mask covers 100% of the photo" in err and "--mask" in err
    code = reconstruct_cli.main([str(path), "-o", str(tmp_path / "b.obj"), "--weights", str(trained[0])])
    out, err = capsys.readouterr()
    assert code == 0 and "mask: salient" in out and "warning" not in err


def _frame(model):
    model.depth_net = _FrameSilhouette(model.depth_net)
    return model


def test_mask_in_photo_projects_back_exactly(trained, photo, tmp_path):
    rec = Reconstructor(trained[0])
    path, _ = photo
    auto = rec.run(path)
    assert auto.mask_source == "salient"
    written = {p.name: p for p in auto.save_intermediates(tmp_path / "inter")}
    with Image.open(written["mask_in_photo.png"]) as im:
        assert im.size == (203, 151) and im.mode == "L"
        pixels = np.asarray(im)
    assert set(np.unique(pixels)) == {0, 255}
    assert np.array_equal(pixels == 255, auto.mask_in_photo()) and np.array_equal(auto.mask_in_photo(), auto.photo_mask)
    # the mask over the photo (what the add-on's panel shows): the object's pixels as in the photo, bar its yellow
    # outline; the background dimmed and tinted blue
    with Image.open(written["mask_overlay.png"]) as im:
        assert im.size == (203, 151) and im.mode == "RGB"
        overlay = np.asarray(im).astype(int)
    photo_rgb = np.asarray(Image.open(path).convert("RGB")).astype(int)
    from scipy.ndimage import binary_erosion

    inner, outside = binary_erosion(auto.photo_mask, iterations=2), ~auto.photo_mask
    assert np.array_equal(overlay[inner], photo_rgb[inner])
    far = binary_erosion(outside, iterations=2)  # (clear of the outline)
    dimmed = photo_rgb[far] * 0.35 + [20, 40, 110]
    assert np.abs(overlay[far] - dimmed).max() <= 1
    edge = auto.photo_mask & ~binary_erosion(auto.photo_mask)
    assert (np.abs(overlay[edge] - [255, 220, 0]).sum(1) == 0).mean() > 0.8
    again = rec.run(path, MaskGuidance(mask=written["mask_in_photo.png"]))
    assert again.mask_source == "file"
    assert again.crop_box == auto.crop_box
    assert torch.equal(again.intermediates["mask"], auto.intermediates["mask"])
    assert torch.equal(again.intermediates["rgb"], auto.intermediates["rgb"])
    # without refinement the crop comes from the first silhouette pass and the mask from the second;
    # that mask, in the photo's pixels and cropped again by the same square, is the network's mask
    from genre_backend.photo.preprocess import crop_resize

    plain = rec.run(path, MaskGuidance(refine=False))
    back = tmp_path / "plain_mask.png"
    Image.fromarray(plain.mask_in_photo().astype(np.uint8) * 255, "L").save(back)
    assert np.array_equal(load_mask(back, load_image(path)), plain.photo_mask)
    size = rec.config.geometry.image_size
    recut = crop_resize(plain.photo_mask.astype(np.uint8) * 255, plain.crop_box, size, 0) >= 128
    assert _iou(recut, plain.intermediates["mask"].numpy()) >= 0.95


# ---- the doubt of a cut, box and strokes ------------------------------------------------------
def test_edge_run_and_model_overlap():
    from genre_backend.photo.grabcut import grabcut_models, border_seeds
    from genre_backend.photo.mask_doubt import cut_doubt, edge_run, model_overlap

    m = np.zeros((20, 30), bool)
    m[5:15, 5:25] = True
    assert edge_run(m) == 0.0 and edge_run(m, 5) == 1.0  # the ring 5 pixels in is all object
    m[2:5, 10:16] = True  # reaches the ring 2 pixels in along 6 of its 26 + 16 + 24 + 14 = 80 pixels
    assert edge_run(m, 2) == pytest.approx(6 / 80)
    assert edge_run(np.ones((20, 30), bool), 2) == 1.0
    # a run that wraps past the ring's start is one run: rows 2 and 3 of column 2 plus row 2's start
    w = np.zeros((20, 30), bool)
    w[2, 2:6] = True
    w[3:6, 2] = True
    assert edge_run(w, 2) == pytest.approx(7 / 80)
    rgb, truth = _photo()
    cut, fgd, bgd = grabcut_models(rgb, border_seeds(*truth.shape))
    assert _iou(cut, truth) >= 0.95 and fgd.shape == bgd.shape == (1, 65)
    assert model_overlap(rgb, truth, fgd, bgd) < 0.02  # brown on green: the models separate
    assert model_overlap(rgb, ~truth, fgd, bgd) > 0.95  # the background, judged as object, is background
    assert cut_doubt(rgb, cut, fgd, bgd, 2) is None
    warning = cut_doubt(rgb, ~truth, fgd, bgd, 2)
    assert warning.startswith("the mask has colours that barely separate from the background's (")
    assert "; it also runs along the photo's edge for 100% of it" in warning


def test_box_and_strokes_seeding():
    from genre_backend.photo.segment import segment

    rgb, truth = _photo(seed=3)
    rows, cols = np.flatnonzero(truth.any(axis=1)), np.flatnonzero(truth.any(axis=0))
    box = (cols[0] - 6.0, rows[0] - 6.0, cols[-1] + 7.0, rows[-1] + 7.0)
    found = segment(rgb, box=box)
    assert found.seeding == "box" and _iou(found.mask, truth) >= 0.95
    assert not found.mask[:, : int(box[0])].any()  # nothing outside the box
    # a box that cuts the object: the part outside is lost, and GrabCut keeps inside it
    half = segment(rgb, box=(box[0], box[1], (box[0] + box[2]) / 2, box[3])).mask
    assert not half[:, int((box[0] + box[2]) / 2) + 1:].any() and half.sum() > 0.3 * truth.sum()
    # strokes: a background scribble across the object's right half takes that half out
    bg = np.zeros(truth.shape, bool)
    cx = int(np.mean(cols))
    bg[:, cx + 5: cx + 8] = True
    fg = np.zeros(truth.shape, bool)
    fg[int(np.mean(rows)), cols[0] + 5: cx - 5] = True
    cut = segment(rgb, object_strokes=fg, background_strokes=bg)
    assert cut.seeding == "strokes" and not cut.mask[:, cx + 5: cx + 8].any()
    assert cut.mask[fg].all() and _iou(cut.mask, truth & (np.arange(truth.shape[1]) < cx + 5)) >= 0.8
    both = segment(rgb, box=box, object_strokes=fg)
    assert both.seeding == "box+strokes" and _iou(both.mask, truth) >= 0.95
    with pytest.raises(ValueError, match="object_strokes: expected the photo's 240×180 pixels"):
        segment(rgb, object_strokes=fg[:10])


def test_check_box():
    from genre_backend.validation import check_box

    assert check_box("box", "1, 2.5,30,40") == (1.0, 2.5, 30.0, 40.0) and check_box("box", [0, 0, 5, 5]) == (0.0, 0.0, 5.0, 5.0)
    for bad, text in (("1,2,3", "four numbers"), ("a,b,c,d", "four numbers"), ([1, 2, 3, True], "four numbers"),
                      ([5, 0, 1, 4], "x0 < x1"), ([0, 4, 1, 4], "y0 < y1"), ([0, 0, float("nan"), 3], "finite"),
                      ([0, 0, 10 ** 400, 1], "finite"), ("0,0,inf,1", "finite"), ({"x0": 1}, "four numbers"), (7, "four numbers")):
        with pytest.raises(ValueError, match=text):
            check_box("box", bad)


PHOTOS = Path(__file__).resolve().parents[3] / "examples" / "photos"


def _strokes_file(name: str, path: Path) -> Path:
    """The scribbles of ``examples/photos/strokes.json`` for one photo as a strokes image (white, black, grey 128)."""
    import json

    drawn = json.loads((PHOTOS / "strokes.json").read_text())[name]
    with Image.open(next(PHOTOS.glob(f"{name}.*"))) as im:
        size = im.size
    out = Image.new("L", size, 128)
    from PIL import ImageDraw

    draw = ImageDraw.Draw(out)
    for kind, value in (("object", 255), ("background", 0)):
        for line in drawn[kind]:
            draw.line([tuple(p) for p in line], fill=value, width=7)
    out.save(path)
    return path


@pytest.mark.slow
def test_real_photos_box_and_doubt_figures():
    """GrabCut's figures in docs/masks.md (scripts/mask_box.py --grabcut: the fallback without the salient net)."""
    import sys

    sys.path.insert(0, str(PHOTOS.parents[1] / "scripts"))
    try:
        from mask_box import measure
    finally:
        sys.path.pop(0)
    rows = {r["name"]: r for r in measure(PHOTOS, seeding="border")}
    assert len(rows) == 9
    auto = np.mean([r["auto_iou"] for r in rows.values()])
    box = np.mean([r["box_iou"] for r in rows.values()])
    assert auto == pytest.approx(0.812, abs=0.005) and box == pytest.approx(0.905, abs=0.005)
    assert rows["robin"]["box_iou"] > rows["robin"]["auto_iou"] + 0.05 and rows["squirrel"]["box_iou"] > rows["squirrel"]["auto_iou"] + 0.2
    wrong = {n for n, r in rows.items() if r["auto_iou"] < 0.8}
    warned = {n for n, r in rows.items() if r["auto_warning"]}
    assert wrong == {"robin", "squirrel"} and wrong <= warned and warned - wrong == {"hand", "quokka"}
    assert "colours that barely separate" in rows["robin"]["auto_warning"]
    assert "runs along the photo's edge" in rows["squirrel"]["auto_warning"]
    # the box's cut sees sharpness too (feature_cut.feature_grabcut): the robin's box mask, still wrong, is warned by its colours
    assert {n for n, r in rows.items() if r["box_warning"]} == {"robin"} and rows["robin"]["box_iou"] < 0.8
    assert "colours that barely separate" in rows["robin"]["box_warning"]
    assert rows["quokka"]["box_iou"] > 0.9 and rows["robin"]["box_iou"] > 0.75
    # the automatic cut runs on out of the squirrel's box along the branch: that spill is one more background model
    assert rows["squirrel"]["box_iou"] > 0.8 and rows["bus"]["box_iou"] > 0.895


@pytest.mark.slow
def test_cli_box_and_strokes_on_a_real_photo(trained, tmp_path, capsys):
    from genre_backend.photo.decode import load_mask

    photo = PHOTOS / "squirrel.jpg"
    image = load_image(photo)
    hand = load_mask(PHOTOS / "squirrel_mask.png", image)
    strokes = _strokes_file("squirrel", tmp_path / "strokes.png")
    ious = {}
    for name, extra in (("auto", []), ("box", ["--box", "127,95,364,366"]), ("strokes", ["--strokes", str(strokes)]),
                        ("box+strokes", ["--box", "127,95,364,366", "--strokes", str(strokes)])):
        code = reconstruct_cli.main([str(photo), "-o", str(tmp_path / f"{name}.obj"), "--weights", str(trained[0]),
                                     "--save-intermediates", str(tmp_path / name), *extra])
        out, err = capsys.readouterr()
        assert code == 0, err
        assert f"mask: {'salient' if name == 'auto' else name}" in out
        if name == "auto":  # the net is unsure of the tail's fuzzy edge and the leaves in its hands: warned
            assert "doubtful mask: the mask has an outline the salient net is unsure of" in err and "--box and --strokes" in err
        ious[name] = _iou(np.asarray(Image.open(tmp_path / name / "mask_in_photo.png")) > 127, hand)
    # the salient net's masks (docs/masks.md): automatic 0.846; the box looks at its crop, since the whole photo's mask
    # runs out of it (0.878); the scribbles, drawn for GrabCut's mistakes, move it a little (0.854, with the box 0.885)
    assert ious["auto"] == pytest.approx(0.846, abs=0.01) and ious["box"] > ious["auto"] + 0.02, ious
    assert ious["strokes"] > ious["auto"] and ious["box+strokes"] > 0.875, ious
    # refused before any work: with --mask, several images, --no-refine, a malformed box, a box off the photo
    for argv, text in (([str(photo), "--mask", str(PHOTOS / "squirrel_mask.png"), "--box", "1,1,9,9"], "either --mask or --box"),
                       ([str(photo), str(photo), "--strokes", str(strokes)], "--strokes applies to one image"),
                       ([str(photo), "--no-refine", "--box", "1,1,9,9"], "--no-refine turns it off"),
                       ([str(photo), "--box", "9,1,1,9"], "x0 < x1")):
        with pytest.raises(SystemExit) as exc:
            reconstruct_cli.main([*argv, "-o", str(tmp_path / "x.obj"), "--weights", str(trained[0])])
        assert exc.value.code == 2 and text in capsys.readouterr().err
    code = reconstruct_cli.main([str(photo), "--box", "600,500,700,600", "-o", str(tmp_path / "x.obj"), "--weights", str(trained[0])])
    assert code == 1 and "is not inside the 535×426 photo" in capsys.readouterr().err and not (tmp_path / "x.obj").exists()
    code = reconstruct_cli.main([str(photo), "--strokes", str(PHOTOS / "robin_mask.png"), "-o", str(tmp_path / "x.obj"),
                                 "--weights", str(trained[0])])
    assert code == 1 and "strokes image is 380×254, the image is 535×426 [bad_mask]" in capsys.readouterr().err


@pytest.mark.slow
def test_serve_box_and_strokes(trained, tmp_path):
    from support.server import ServerProcess

    photo = PHOTOS / "squirrel.jpg"
    strokes = _strokes_file("squirrel", tmp_path / "strokes.png")
    grey = tmp_path / "grey.png"
    Image.new("L", (535, 426), 128).save(grey)
    with Image.open(photo) as im:  # stored turned 90° anticlockwise, EXIF orientation 6; its scribbles turned alike
        turned = _stored_copy(im.convert("RGB"), 6, tmp_path / "squirrel_o6.jpg")
    with Image.open(strokes) as im:
        im.transpose(_TO_STORED[6]).save(tmp_path / "strokes_o6.png")
    s = ServerProcess("--weights", str(trained[0]))
    try:
        assert s.next(timeout=300)["type"] == "ready"
        base = {"type": "reconstruct", "image": str(photo)}
        bad = [({"box": [1, 2, 3]}, "bad_field", "field box: expected four numbers"),
               ({"box": "1,2,3,4"}, "bad_field", "field box: expected four numbers"),
               ({"box": [10, 0, 5, 9]}, "bad_field", "x0 < x1"),
               ({"box": [0, 0, True, 9]}, "bad_field", "four numbers"),
               ({"box": [0, 0, "NaN", 9]}, "bad_field", "four numbers"),
               ({"strokes": ""}, "bad_field", "field 'strokes' must be a non-empty string"),
               ({"strokes": "a\u0000b"}, "bad_field", "NUL"),
               ({"box": [0, 0, 9, 9], "mask": str(PHOTOS / "squirrel_mask.png")}, "bad_field", "either 'mask' or 'box'"),
               ({"box": [600, 500, 700, 600]}, "bad_mask", "is not inside the 535×426 photo"),
               ({"strokes": str(PHOTOS / "robin.jpg")}, "bad_mask", "strokes image is 380×254"),
               ({"strokes": str(grey)}, "bad_mask", "no strokes"),
               ({"strokes": str(tmp_path / "missing.png")}, "bad_mask", "no such file"),
               ({"strokes": str(strokes), "guidance_frame": "sideways"}, "bad_field", "field 'guidance_frame': expected one of 'upright', 'stored'"),
               ({"strokes": str(strokes), "guidance_frame": 6}, "bad_field", "got 6"),
               ({"strokes": str(strokes), "guidance_frame": "stored", "image": str(turned)}, "bad_mask",
                "strokes image is 535×426, the image is 426×535 as stored")]
        for i, (fields, code, text) in enumerate(bad):
            s.send({**base, "id": f"bad{i}", "output": str(tmp_path / f"bad{i}.obj"), **fields})
            events = s.until(lambda e, i=i: e["type"] in ("result", "error") and e["id"] == f"bad{i}")
            ev = events[-1]
            assert ev["type"] == "error" and ev["code"] == code and text in ev["message"], (fields, ev)
            stages = {e["stage"] for e in events if e["type"] == "progress"}
            assert stages <= {"load", "preprocess"}, stages  # refused before any network ran
            assert not (tmp_path / f"bad{i}.obj").exists()
        for name, fields in (("box", {"box": [127, 95, 364, 366]}), ("strokes", {"strokes": str(strokes)}),
                             ("box+strokes", {"box": [127.0, 95.0, 364.0, 366.0], "strokes": str(strokes)})):
            s.send({**base, "id": name, "output": str(tmp_path / f"{name}.obj"), **fields})
            ev = s.until(lambda e, name=name: e["type"] in ("result", "error") and e["id"] == name)[-1]
            assert ev["type"] == "result" and ev["mask_source"] == name and ev["faces"] > 0, ev
        # scribbles over the stored pixels of a turned file (as Blender shows it): turned with the photo
        s.send({**base, "id": "turned", "image": str(turned), "output": str(tmp_path / "turned.obj"), "guidance_frame": "stored",
                "strokes": str(tmp_path / "strokes_o6.png"), "options": {"save_intermediates": str(tmp_path / "turned")}})
        ev = s.until(lambda e: e["type"] in ("result", "error") and e["id"] == "turned")[-1]
        assert ev["type"] == "result" and ev["mask_source"] == "strokes" and ev["camera"]["exif_orientation"] == 6, ev
        hand = load_mask(PHOTOS / "squirrel_mask.png", load_image(photo))
        assert _iou(np.asarray(Image.open(tmp_path / "turned" / "mask_in_photo.png")) > 127, hand) > 0.75
        s.send({**base, "id": "auto", "output": str(tmp_path / "auto.obj")})
        ev = s.until(lambda e: e["type"] in ("result", "error") and e["id"] == "auto")[-1]
        assert ev["mask_source"] == "salient" and ev["mask_warning"].startswith("the mask has an outline the salient net is unsure of")
        s.send({"type": "shutdown", "id": "end"})
        s.until(lambda e: e["type"] == "bye")
    finally:
        assert s.close() == 0


# ---- box and strokes over the photo's pixels as stored (guidance_frame "stored"): every EXIF orientation -------
# Pillow's transposition that undoes each EXIF orientation's turn: the stored pixels of a file that shows the photo
# upright once ImageOps.exif_transpose has turned it (5 and 7 are their own inverse; 6 and 8 undo each other).
_TO_STORED = {2: Image.Transpose.FLIP_LEFT_RIGHT, 3: Image.Transpose.ROTATE_180, 4: Image.Transpose.FLIP_TOP_BOTTOM,
              5: Image.Transpose.TRANSPOSE, 6: Image.Transpose.ROTATE_90, 7: Image.Transpose.TRANSVERSE, 8: Image.Transpose.ROTATE_270}


def _stored_copy(im: Image.Image, orientation: int, path: Path) -> Path:
    """Save ``im`` (upright) so that its file stores turned pixels and an EXIF orientation that turns them back."""
    exif = Image.Exif()
    exif[0x0112] = orientation
    stored = im if orientation == 1 else im.transpose(_TO_STORED[orientation])
    stored.save(path, exif=exif.tobytes(), **({"quality": 95} if path.suffix == ".jpg" else {}))
    return path


def test_upright_array_and_box_match_pillows_exif_transpose(tmp_path):
    from PIL import ImageOps

    from genre_backend.photo.decode import stored_size, upright_array, upright_box

    rng = np.random.default_rng(0)
    upright = Image.fromarray(rng.integers(0, 255, (7, 11, 3), dtype=np.uint8))  # 11 wide, 7 high
    for o in range(1, 9):
        path = _stored_copy(upright, o, tmp_path / f"o{o}.png")
        image = load_image(path)
        with Image.open(path) as im:
            stored = np.asarray(im.convert("RGB"))
            assert np.array_equal(np.asarray(ImageOps.exif_transpose(im).convert("RGB")), np.asarray(upright))
        assert image.exif_orientation == o and image.original_size == (11, 7) and stored_size(image) == stored.shape[1::-1]
        assert np.array_equal(upright_array(stored, o), np.asarray(upright)) and np.array_equal(image.rgb, np.asarray(upright))
        # a box around stored pixels lands around the same pixels upright
        marks = np.zeros(stored.shape[:2], bool)
        marks[1:4, 2:3] = True  # rows 1-3, column 2: the box (2, 1, 3, 4)
        exif = Image.Exif()
        exif[0x0112] = o
        Image.fromarray(marks).save(tmp_path / "marks.png", exif=exif.tobytes())
        with Image.open(tmp_path / "marks.png") as im:
            rows, cols = np.nonzero(np.asarray(ImageOps.exif_transpose(im)))
        assert upright_box((2, 1, 3, 4), o, stored.shape[1::-1]) == (cols.min(), rows.min(), cols.max() + 1, rows.max() + 1), o
    with pytest.raises(ValueError, match="orientation"):
        upright_box((0, 0, 1, 1), 9, (2, 2))


@pytest.mark.slow
def test_stored_frame_box_and_strokes_land_on_the_object_for_every_exif_orientation(tmp_path):
    """The squirrel saved as JPEGs that store turned pixels with EXIF orientations 1-8, its scribbles and box drawn
    over those stored pixels (as in Blender's Image Editor): with guidance_frame "stored" the mask GrabCut finds is
    the squirrel's, as good as the upright scribbles' on the upright photo; taken as upright, they are refused
    (90° turns: another size) or are worse (the mirrors and 180°: the squirrel sits near the middle, so they miss
    only partly, IoU 0.35-0.84: the vertical mirror's box overlaps the right one, and since the box's cut models
    the automatic cut's spill out of the box it reaches 0.84 against 0.87, hence a margin of 0.03)."""
    from genre_backend.config import GenreConfig
    from genre_backend.photo.decode import ImageError
    from genre_backend.photo.preprocess import preprocess

    config = GenreConfig()
    with Image.open(PHOTOS / "squirrel.jpg") as im:
        photo = im.convert("RGB")
    hand_upright = np.asarray(Image.open(PHOTOS / "squirrel_mask.png").convert("L")) > 127
    strokes = Image.open(_strokes_file("squirrel", tmp_path / "strokes.png"))
    box_marks = Image.fromarray(np.pad(np.ones((366 - 95, 364 - 127), bool), ((95, 426 - 366), (127, 535 - 364))))
    ious = {}
    for o in range(1, 9):
        path = _stored_copy(photo, o, tmp_path / f"squirrel_o{o}.jpg")
        stored_strokes = strokes if o == 1 else strokes.transpose(_TO_STORED[o])
        stored_strokes.save(tmp_path / f"strokes_o{o}.png")
        rows, cols = np.nonzero(np.asarray(box_marks if o == 1 else box_marks.transpose(_TO_STORED[o])))
        box = (float(cols.min()), float(rows.min()), float(cols.max() + 1), float(rows.max() + 1))  # over the stored pixels
        image = load_image(path)
        assert image.exif_orientation == o and image.original_size == (535, 426)
        pre = preprocess(image, config, MaskGuidance(box=box, strokes=tmp_path / f"strokes_o{o}.png", frame="stored"))
        assert pre.mask_source == "box+strokes"
        ious[o] = _iou(pre.photo_mask, hand_upright)
        if o != 1:  # the same inputs read as upright (the frame before guidance_frame): refused, or off the squirrel
            try:
                wrong = preprocess(image, config, MaskGuidance(box=box, strokes=tmp_path / f"strokes_o{o}.png")).photo_mask
            except ImageError as exc:
                assert o in (5, 6, 7, 8) and exc.code == "bad_mask" and "strokes image is 426×535, the image is 535×426" in str(exc)
            else:
                assert o in (2, 3, 4) and _iou(wrong, hand_upright) < ious[o] - 0.03, (o, _iou(wrong, hand_upright), ious[o])
    # (as the upright photo with its upright scribbles, 0.872 in docs/masks.md; JPEG's re-encoding moves it a little)
    assert all(v > 0.85 for v in ious.values()) and max(ious.values()) - min(ious.values()) < 0.03, ious
    with pytest.raises(ImageError, match=r"strokes image is 535×426, the image is 426×535 as stored"):
        preprocess(load_image(tmp_path / "squirrel_o6.jpg"), config, MaskGuidance(strokes=tmp_path / "strokes_o1.png", frame="stored"))
    with pytest.raises(ImageError, match=r"the box 500,0,535,10 is not inside the 426×535 photo as stored"):
        preprocess(load_image(tmp_path / "squirrel_o6.jpg"), config, MaskGuidance(box=(500, 0, 535, 10), frame="stored"))


@pytest.mark.parametrize("name", ["apple", "bus", "hand", "quokka"])
def test_the_box_cut_without_sharpness_is_opencvs_grabcut(name, monkeypatch):
    """feature_cut.feature_grabcut (GrabCut over PyMaxflow with a sharpness feature) against its reference, OpenCV's
    GrabCut, from the same labels: with the sharpness weighted 0 the two cuts agree (IoU ≥ 0.99; they differ in
    the mixtures' start and the floating point, and on the robin, whose cut is unstable, they part to 0.89)."""
    from genre_backend.photo import feature_cut
    from genre_backend.photo.grabcut import box_seeds, grabcut

    with Image.open(next(PHOTOS.glob(f"{name}.*"))) as im:
        im = im.convert("RGB")
        im.thumbnail((320, 320))
        rgb = np.asarray(im)
    h, w = rgb.shape[:2]
    labels = box_seeds(h, w, (0.1 * w, 0.1 * h, 0.9 * w, 0.9 * h))
    reference = grabcut(rgb, labels)
    monkeypatch.setattr(feature_cut, "SHARPNESS_WEIGHT", 0.0)
    ours, objects, backgrounds = feature_cut.feature_grabcut(rgb, labels)
    assert objects is not None and backgrounds is not None
    assert 0.1 < reference.mean() < 0.9
    assert (reference & ours).sum() / (reference | ours).sum() >= 0.99
