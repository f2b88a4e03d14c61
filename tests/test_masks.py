"""Masks of photos without a user mask: GrabCut refinement, the doubtful-mask warning, mask_in_photo.png."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from genre_backend.inference import reconstruct_cli
from genre_backend.inference.preprocess import load_image, load_mask
from genre_backend.inference.reconstruct import Reconstructor
from genre_backend.inference.segment import border_touch, cover, doubt, refine_mask


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
    mask, used = refine_mask(rgb)
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
    res = rec.run(path, refine=False)  # the silhouette as it is: the whole photo
    assert res.mask_source == "silhouette" and res.photo_mask.all()
    assert res.mask_warning == "the mask covers 100% of the photo and touches 100% of its border: it is probably the photo's frame, not the object"
    res = rec.run(path)  # refined: GrabCut, seeded from the photo's border since the silhouette is doubtful
    assert res.mask_source == "grabcut" and res.mask_warning is None
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
    assert code == 0 and "mask: grabcut" in out and "warning" not in err


def _frame(model):
    model.depth_net = _FrameSilhouette(model.depth_net)
    return model


def test_mask_in_photo_projects_back_exactly(trained, photo, tmp_path):
    rec = Reconstructor(trained[0])
    path, _ = photo
    auto = rec.run(path)
    assert auto.mask_source == "grabcut"
    written = {p.name: p for p in auto.save_intermediates(tmp_path / "inter")}
    with Image.open(written["mask_in_photo.png"]) as im:
        assert im.size == (203, 151) and im.mode == "L"
        pixels = np.asarray(im)
    assert set(np.unique(pixels)) == {0, 255}
    assert np.array_equal(pixels == 255, auto.mask_in_photo()) and np.array_equal(auto.mask_in_photo(), auto.photo_mask)
    again = rec.run(path, mask_path=written["mask_in_photo.png"])
    assert again.mask_source == "file"
    assert again.crop_box == auto.crop_box
    assert torch.equal(again.intermediates["mask"], auto.intermediates["mask"])
    assert torch.equal(again.intermediates["rgb"], auto.intermediates["rgb"])
    # without refinement the crop comes from the first silhouette pass and the mask from the second;
    # that mask, in the photo's pixels and cropped again by the same square, is the network's mask
    from genre_backend.inference.preprocess import crop_resize

    plain = rec.run(path, refine=False)
    back = tmp_path / "plain_mask.png"
    Image.fromarray(plain.mask_in_photo().astype(np.uint8) * 255, "L").save(back)
    assert np.array_equal(load_mask(back, load_image(path)), plain.photo_mask)
    size = rec.config.geometry.image_size
    recut = crop_resize(plain.photo_mask.astype(np.uint8) * 255, plain.crop_box, size, 0) >= 128
    assert _iou(recut, plain.intermediates["mask"].numpy()) >= 0.95
