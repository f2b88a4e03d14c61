"""Image decoding, mask selection and framing (no network needed)."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
import torch
from PIL import Image, ImageOps

from genre_backend.config import get_preset
from support.files import huge_png
from genre_backend.photo.decode import ImageError, load_image
from genre_backend.photo.guidance import MaskGuidance
from genre_backend.photo.preprocess import (
    NEUTRAL_BACKGROUND,
    crop_resize,
    mask_bbox,
    preprocess,
    square_crop_box,
)

CFG = get_preset("default")
S = CFG.geometry.image_size


def _photo(w=200, h=120, box=(60, 30, 140, 90), colour=(200, 40, 40), bg=(30, 90, 160)) -> np.ndarray:
    """(h, w, 3) uint8: a coloured rectangle ``box`` (x0, y0, x1, y1) on a plain background."""
    a = np.empty((h, w, 3), np.uint8)
    a[:] = bg
    x0, y0, x1, y1 = box
    a[y0:y1, x0:x1] = colour
    return a


def _save(tmp_path, name, array_or_image, **kw):
    p = tmp_path / name
    im = array_or_image if isinstance(array_or_image, Image.Image) else Image.fromarray(array_or_image)
    im.save(p, **kw)
    return p


def _not_background(rgb: torch.Tensor) -> torch.Tensor:
    """A silhouette function for the framing tests: pixels far from the border's median colour."""
    border = torch.cat([rgb[:, 0], rgb[:, -1], rgb[:, :, 0], rgb[:, :, -1]], dim=1).median(dim=1).values
    return (rgb - border[:, None, None]).abs().sum(0) > 0.2


def _huge_png(width, height) -> bytes:
    return huge_png(width, height, colour_type=2)


# ---- decoding errors ---------------------------------------------------------------------------
def test_unreadable_files_give_one_line_errors(tmp_path):
    good = _save(tmp_path, "good.png", _photo())
    cases = {
        "missing": (tmp_path / "missing.png", "no such file"),
        "directory": (tmp_path, "is a directory"),
        "zero": (tmp_path / "zero.png", "empty file (0 bytes)"),
        "text": (tmp_path / "text.jpg", "not an image"),
        "truncated": (tmp_path / "trunc.png", "truncated"),
        "corrupt": (tmp_path / "corrupt.png", "corrupt"),
        "huge": (tmp_path / "huge.png", "too large (900 Mpx"),
    }
    (tmp_path / "zero.png").write_bytes(b"")
    (tmp_path / "text.jpg").write_text("definitely not a JPEG\n" * 10)
    data = good.read_bytes()
    (tmp_path / "trunc.png").write_bytes(data[: len(data) // 2])
    (tmp_path / "corrupt.png").write_bytes(data[:60] + bytes(len(data) - 60))  # IDAT zeroed out
    (tmp_path / "huge.png").write_bytes(_huge_png(30000, 30000))
    for name, (path, text) in cases.items():
        with pytest.raises(ImageError) as exc:
            load_image(path)
        assert exc.value.code == "bad_image", name
        msg = str(exc.value)
        assert text in msg and "\n" not in msg and str(path) in msg, (name, msg)


def test_huge_image_is_refused_without_decoding(tmp_path):
    path = tmp_path / "huge.png"
    path.write_bytes(_huge_png(30000, 30000))
    tracemalloc.start()
    with pytest.raises(ImageError, match="too large"):
        load_image(path)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 20 * 2**20  # a decoded 30000² RGB image would need 2.7 GB


def test_large_image_is_downscaled(tmp_path):
    a = _photo(w=6000, h=300, box=(2000, 50, 4000, 250))
    img = load_image(_save(tmp_path, "wide.png", a), work_side=2048)
    assert img.size == (2048, 102) and img.original_size == (6000, 300)
    assert any("downscaled" in n for n in img.notes)
    pre = preprocess(img, CFG, silhouette=_not_background)
    x0, y0, x1, y1 = pre.crop_box  # reported in the original's pixels
    px = 6000 / S  # the first silhouette pass sees the whole image at S² pixels: its bounding box is good to ±1 of them
    assert abs((x0 + x1) / 2 - 3000) < px and abs((x1 - x0) - 2000 / CFG.geometry.object_fraction) < 2 * px / CFG.geometry.object_fraction


def test_jpeg_draft_decodes_big_jpegs_reduced(tmp_path):
    p = _save(tmp_path, "big.jpg", _photo(w=4000, h=3000, box=(1000, 1000, 3000, 2000)), quality=80)
    img = load_image(p, max_pixels=2_000_000)
    assert img.size[0] <= 2000 and img.original_size == (4000, 3000)


# ---- accepted modes ----------------------------------------------------------------------------
def test_modes_are_converted(tmp_path):
    base = _photo()
    gray8 = np.asarray(Image.fromarray(base).convert("L"))
    g16 = _save(tmp_path, "g16.png", Image.fromarray(gray8.astype(np.uint16) * 257))
    assert Image.open(g16).mode.startswith("I")
    img = load_image(g16)
    assert img.rgb.dtype == np.uint8 and np.abs(img.rgb[..., 0].astype(int) - gray8).max() <= 1
    assert load_image(_save(tmp_path, "g.png", gray8)).rgb.shape == (120, 200, 3)
    cmyk = load_image(_save(tmp_path, "c.jpg", Image.fromarray(base).convert("CMYK"), quality=95))
    assert np.abs(cmyk.rgb[60, 100].astype(int) - [200, 40, 40]).max() < 25
    pal = Image.fromarray(base).convert("P", palette=Image.ADAPTIVE, colors=8)
    pal.info["transparency"] = pal.getpixel((0, 0))  # the background colour's index is transparent
    img = load_image(_save(tmp_path, "p.png", pal, transparency=pal.getpixel((0, 0))))
    assert img.has_transparency() and img.alpha[60, 100] == 255 and img.alpha[0, 0] == 0
    bw = load_image(_save(tmp_path, "b.png", Image.fromarray(gray8 > 100)))
    assert bw.rgb.shape == (120, 200, 3)


def test_animated_takes_the_first_frame(tmp_path):
    frames = [Image.new("RGB", (40, 30), c) for c in ((255, 0, 0), (0, 255, 0), (0, 0, 255))]
    p = tmp_path / "anim.gif"
    frames[0].save(p, save_all=True, append_images=frames[1:], duration=50, loop=0)
    img = load_image(p)
    assert tuple(img.rgb[10, 10]) == (255, 0, 0) and any("3 frames" in n for n in img.notes)


def test_exif_orientation_is_applied(tmp_path):
    a = _photo(w=80, h=40, box=(0, 0, 20, 40))  # object on the left
    exif = Image.Exif()
    exif[0x0112] = 6  # rotate 90° clockwise to display
    p = _save(tmp_path, "rot.jpg", a, exif=exif.tobytes(), quality=95)
    img = load_image(p)
    assert img.size == (40, 80) and img.original_size == (40, 80)
    # the left of the stored image is the top of the displayed one
    assert img.rgb[5, 20, 0] > 150 and img.rgb[75, 20, 0] < 100
    assert img.exif_orientation == 6 and "EXIF orientation 6 applied" in img.notes


@pytest.mark.parametrize("orientation", range(1, 9))
def test_every_exif_orientation_matches_pillows_transpose(tmp_path, orientation):
    """All eight tags (flips included) give Pillow's own upright image, and the tag is kept for clients."""
    rng = np.random.default_rng(orientation)
    a = rng.integers(0, 256, (6, 10, 3), dtype=np.uint8)  # no symmetry: any wrong turn or flip shows
    exif = Image.Exif()
    exif[0x0112] = orientation
    p = _save(tmp_path, "o.png", a, exif=exif.tobytes())
    with Image.open(p) as im:
        assert im.getexif().get(0x0112) == orientation  # the tag survived the PNG
        want = np.asarray(ImageOps.exif_transpose(im).convert("RGB"))
    img = load_image(p)
    assert img.exif_orientation == orientation
    np.testing.assert_array_equal(img.rgb, want)
    assert img.original_size == (want.shape[1], want.shape[0])
    assert (f"EXIF orientation {orientation} applied" in img.notes) == (orientation != 1)


# ---- masks and framing -------------------------------------------------------------------------
def test_square_crop_box():
    assert square_crop_box((10, 20, 30, 60), 0.5) == (-20.0, 0.0, 60.0, 80.0)
    with pytest.raises(ValueError):
        square_crop_box((0, 0, 1, 1), 0.0)


def test_framing_puts_the_object_in_the_middle_at_object_fraction(tmp_path):
    img = load_image(_save(tmp_path, "p.png", _photo(box=(20, 10, 100, 50))))
    for refine, source in ((False, "silhouette"), (True, "salient")):
        pre = preprocess(img, CFG, MaskGuidance(refine=refine), silhouette=_not_background)
        assert pre.mask_source == source and pre.rgb.shape == (3, S, S)
        assert (pre.mask is None) == (not refine)
        sil = _not_background(pre.rgb).numpy()
        x0, y0, x1, y1 = mask_bbox(sil)
        assert abs((x1 - x0) - CFG.geometry.object_fraction * S) <= 2
        assert abs((x0 + x1) / 2 - S / 2) <= 1.5 and abs((y0 + y1) / 2 - S / 2) <= 1.5
        # padding outside the photo has the photo's border colour
        assert torch.allclose(pre.rgb[:, 0, 0], torch.tensor([30, 90, 160]) / 255.0, atol=0.01)


def test_mask_order_file_alpha_silhouette(tmp_path):
    a = _photo()
    alpha = np.zeros(a.shape[:2], np.uint8)
    alpha[30:90, 60:140] = 255
    rgba = load_image(_save(tmp_path, "rgba.png", np.dstack([a, alpha])))
    rgb = load_image(_save(tmp_path, "rgb.png", a))
    file_mask = np.zeros(a.shape[:2], np.uint8)
    file_mask[40:80, 70:130] = 255
    mpath = _save(tmp_path, "mask.png", file_mask)

    def no_silhouette(_):
        raise AssertionError("the silhouette must not be used when a mask or alpha is there")

    pre = preprocess(rgba, CFG, MaskGuidance(mask=mpath), silhouette=no_silhouette)
    assert pre.mask_source == "file"
    x0, y0, x1, y1 = mask_bbox(pre.mask.numpy())
    assert abs((x1 - x0) - CFG.geometry.object_fraction * S) <= 2
    pre = preprocess(rgba, CFG, silhouette=no_silhouette)
    assert pre.mask_source == "alpha" and pre.mask.sum() > 0
    assert preprocess(rgb, CFG, silhouette=_not_background).mask_source == "salient"
    assert preprocess(rgb, CFG, MaskGuidance(seeding="border"), silhouette=_not_background).mask_source == "grabcut"
    assert preprocess(rgb, CFG, MaskGuidance(refine=False), silhouette=_not_background).mask_source == "silhouette"


def test_rgba_is_composited_over_the_neutral_background(tmp_path):
    a = np.zeros((50, 50, 4), np.uint8)
    a[..., :3] = 255  # white but transparent outside the object
    a[20:30, 20:30] = (10, 200, 10, 255)
    pre = preprocess(load_image(_save(tmp_path, "t.png", a)), CFG)
    assert torch.allclose(pre.rgb[:, 0, 0], torch.tensor(NEUTRAL_BACKGROUND), atol=0.01)
    assert torch.allclose(pre.rgb[:, S // 2, S // 2], torch.tensor([10, 200, 10]) / 255.0, atol=0.01)


def test_mask_errors(tmp_path):
    img = load_image(_save(tmp_path, "p.png", _photo()))
    for name, mask, text in (
        ("empty.png", np.zeros((120, 200), np.uint8), "empty mask"),
        ("small.png", np.full((60, 100), 255, np.uint8), "mask is 100×60, the image is 200×120"),
    ):
        with pytest.raises(ImageError, match=text) as exc:
            preprocess(img, CFG, MaskGuidance(mask=_save(tmp_path, name, mask)), silhouette=_not_background)
        assert exc.value.code == "bad_mask"
    (tmp_path / "zero.png").write_bytes(b"")
    with pytest.raises(ImageError, match="0 bytes") as exc:
        preprocess(img, CFG, MaskGuidance(mask=tmp_path / "zero.png"))
    assert exc.value.code == "bad_mask"


def test_no_object(tmp_path):
    clear = np.zeros((40, 40, 4), np.uint8)
    with pytest.raises(ImageError, match="no object") as exc:
        preprocess(load_image(_save(tmp_path, "clear.png", clear)), CFG)
    assert exc.value.code == "no_object"
    plain = np.full((40, 60, 3), 77, np.uint8)
    with pytest.raises(ImageError, match="no object") as exc:
        preprocess(load_image(_save(tmp_path, "plain.png", plain)), CFG, silhouette=_not_background)
    assert exc.value.code == "no_object"


def test_crop_resize_far_outside_uses_little_memory():
    a = np.full((100, 100, 3), 200, np.uint8)
    out = crop_resize(a, (-1e6, -1e6, 1e6, 1e6), 64, (1, 2, 3))
    assert out.shape == (64, 64, 3) and tuple(out[0, 0]) == (1, 2, 3)
