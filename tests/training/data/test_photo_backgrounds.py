"""Real-photo backgrounds (training.data.photo_backgrounds) and photo-like samples (training.data.dataset)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from PIL import Image

from training.data.dataset import ViewDataset, composite_alpha, find_views, photometric
from training.data.photo_backgrounds import BackgroundBank, licence_for, prepare_backgrounds, read_index
from training.data.views import write_view
from support.tiny_data import TINY, two_colour_backgrounds

DEP5 = """Format: https://www.debian.org/doc/packaging-manuals/copyright-format/1.0/

Files: *
Copyright: someone
License: GPL-2+

Files: 16.04/Bridge_by_Someone.jpg
Copyright: a photographer
License: CC-BY-SA-4.0

Files: wallpapers/Next/*
License: LGPL-3
"""


def test_licence_of_each_file_from_a_dep5_copyright_file():
    assert licence_for("usr/share/backgrounds/Bridge_by_Someone.jpg", DEP5) == "CC-BY-SA-4.0"  # the file's own stanza (last match wins)
    assert licence_for("usr/share/backgrounds/Other.jpg", DEP5) == "GPL-2+"  # only "*" matches
    assert licence_for("usr/share/wallpapers/Next/contents/images/1920x1080.png", DEP5) == "LGPL-3"
    free = "Image Authors:\n - A.jpg:\n   Licensed under Creative Commons Attribution-ShareAlike 3.0 License.\n"
    assert licence_for("usr/share/backgrounds/A.jpg", free) == "Creative Commons Attribution-ShareAlike 3.0"
    assert licence_for("x.jpg", "no licence words here") == "unknown"


def _image(path, size, seed):
    path.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    Image.fromarray(rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)).save(path)


def test_prepare_keeps_one_image_per_wallpaper_with_its_licence_and_size(tmp_path):
    root = tmp_path / "data"
    pkg = root / "cache" / "unpacked" / "fake-wallpapers"
    (pkg / "usr/share/doc/fake-wallpapers").mkdir(parents=True)
    (pkg / "usr/share/doc/fake-wallpapers/copyright").write_text(DEP5)
    (pkg / ".complete").write_text("fake-wallpapers_1.0-1_all.deb\n")  # unpacked already: nothing is downloaded
    _image(pkg / "usr/share/backgrounds/Bridge_by_Someone.jpg", (1200, 800), 0)
    _image(pkg / "usr/share/wallpapers/Next/contents/images/1920x1080.png", (960, 540), 1)  # one wallpaper at
    _image(pkg / "usr/share/wallpapers/Next/contents/images/640x480.png", (640, 480), 2)  # two resolutions
    _image(pkg / "usr/share/backgrounds/tiny.png", (300, 200), 3)  # too small
    _image(pkg / "usr/share/icons/x.png", (512, 512), 4)  # an icon, not a wallpaper
    index = prepare_backgrounds(root, ["fake-wallpapers"], long_side=256)
    assert [(b.source, b.licence, b.version) for b in index] == [
        ("usr/share/backgrounds/Bridge_by_Someone.jpg", "CC-BY-SA-4.0", "1.0-1"),
        ("usr/share/wallpapers/Next/contents/images/1920x1080.png", "LGPL-3", "1.0-1"),
    ]
    assert [(b.width, b.height) for b in index] == [(256, 171), (256, 144)]
    for b in index:
        with Image.open(root / "backgrounds" / b.file) as im:
            assert im.size == (b.width, b.height)
    assert read_index(root / "backgrounds") == index
    with pytest.raises(ValueError, match="genre data backgrounds"):
        read_index(tmp_path / "nowhere")


@pytest.fixture()
def bank(tmp_path):
    return BackgroundBank(two_colour_backgrounds(tmp_path / "bg"))


def test_bank_crops_are_seeded_and_in_range(bank):
    a = bank.sample(torch.Generator().manual_seed(5), 32)
    b = bank.sample(torch.Generator().manual_seed(5), 32)
    assert a.shape == (3, 32, 32) and torch.equal(a, b)
    assert 0.0 <= float(a.min()) and float(a.max()) <= 1.0
    colours = {tuple((bank.sample(torch.Generator().manual_seed(s), 8)[:, 4, 4] > 0.5).tolist()) for s in range(20)}
    assert colours == {(True, False, False), (False, True, False)}  # both photos are drawn


def test_composite_and_photometric():
    rgb, bg = torch.full((3, 4, 4), 0.2), torch.full((3, 4, 4), 0.9)
    alpha = torch.tensor([[1.0, 0.0, 0.5, 0.25]]).expand(4, 4)
    out = composite_alpha(rgb, alpha, bg)
    assert torch.allclose(out[:, :, 0], rgb[:, :, 0]) and torch.allclose(out[:, :, 1], bg[:, :, 1])
    assert torch.allclose(out[:, :, 2], torch.full((3, 4), 0.55)) and torch.allclose(out[:, :, 3], torch.full((3, 4), 0.725))
    img = torch.rand(3, 32, 32, generator=torch.Generator().manual_seed(0))
    outs = [photometric(img, torch.Generator().manual_seed(s)) for s in range(12)]
    assert all(o.shape == img.shape and float(o.min()) >= 0 and float(o.max()) <= 1 for o in outs)
    assert torch.equal(outs[3], photometric(img, torch.Generator().manual_seed(3)))
    assert all(not torch.equal(o, img) for o in outs)  # exposure and white balance always act


def test_photo_like_samples_keep_the_object_and_change_the_background(tmp_path, bank):
    cfg = dataclasses.replace(TINY, geometry=dataclasses.replace(TINY.geometry, image_size=32))
    s = 32
    rgb = np.full((s, s, 3), 128, np.uint8)
    mask = np.zeros((s, s), np.float32)
    mask[8:24, 8:24] = 1.0
    depth = np.where(mask > 0, 2.0, 0.0).astype(np.float32)
    (tmp_path / "v" / "shape").mkdir(parents=True)
    for k in range(2):
        write_view(tmp_path / "v" / "shape", k, rgb, depth, mask, {"image_size": s})
    refs = find_views(tmp_path / "v", None, targets=False)
    plain = ViewDataset(refs, cfg, augment=True, targets=False)
    photo = ViewDataset(refs, cfg, augment=True, targets=False, backgrounds=bank, photo_fraction=1.0)
    a, b = photo.sample(0, 7), photo.sample(0, 7)
    assert torch.equal(a["rgb"], b["rgb"])  # seeded: a resumed run sees the same pixels
    assert torch.equal(a["mask"], plain.sample(0, 7)["mask"]) and torch.equal(a["depth"], plain.sample(0, 7)["depth"])
    # outside the object the photo's colour (pure red or green, before the camera's faults) dominates
    outside = a["rgb"][:, ~a["mask"]]
    spread = (outside.max(0).values - outside.min(0).values).mean()
    assert spread > 0.3, spread
    with pytest.raises(ValueError, match="backgrounds"):
        ViewDataset(refs, cfg, augment=True, targets=False, photo_fraction=0.5)


def test_backdrop_samples_are_grey_outside_the_mask_and_keep_everything_else(tmp_path, bank):
    """--backdrop P: that share of the seeded samples is painted the neutral grey outside its mask, after the photo
    and the camera's faults, exactly as the mesh option plain_backdrop paints a photo; inside the mask, and the
    samples it leaves alone, are the pixels without it (its coin is a draw of its own)."""
    from genre_backend.photo.preprocess import NEUTRAL_BACKGROUND, on_plain_backdrop

    cfg = dataclasses.replace(TINY, geometry=dataclasses.replace(TINY.geometry, image_size=32))
    s = 32
    rgb = np.random.default_rng(0).integers(0, 256, (s, s, 3), dtype=np.uint8)
    mask = np.zeros((s, s), np.float32)
    mask[6:20, 10:26] = 1.0
    depth = np.where(mask > 0, 2.0, 0.0).astype(np.float32)
    (tmp_path / "v" / "shape").mkdir(parents=True)
    write_view(tmp_path / "v" / "shape", 0, rgb, depth, mask, {"image_size": s})
    refs = find_views(tmp_path / "v", None, targets=False)
    common = dict(augment=True, targets=False, backgrounds=bank, photo_fraction=1.0)
    without = ViewDataset(refs, cfg, **common)
    always = ViewDataset(refs, cfg, backdrop=1.0, **common)
    a, b = always.sample(0, 11), without.sample(0, 11)
    inside = a["mask"]
    assert int(inside.sum()) == 14 * 16
    assert torch.equal(a["rgb"][:, inside], b["rgb"][:, inside])
    grey = torch.tensor(NEUTRAL_BACKGROUND).view(3, 1)
    assert torch.equal(a["rgb"][:, ~inside], grey.expand(3, int((~inside).sum())))
    assert float((b["rgb"][:, ~inside] - grey).abs().mean()) > 0.05  # the photo was there before
    assert torch.equal(always[0]["rgb"], without[0]["rgb"])  # unseeded samples: the share's coin never paints
    # the validation views of a model that paints its photos: every sample painted, seeded or not
    val = ViewDataset(refs, cfg, targets=False, plain_backdrop=True)
    raw = ViewDataset(refs, cfg, targets=False).sample(0, None)
    assert torch.equal(val.sample(0, None)["rgb"], on_plain_backdrop(raw["rgb"], raw["mask"]))
    assert torch.equal(val.sample(0, None)["rgb"][:, ~inside], grey.expand(3, int((~inside).sum())))
    half = ViewDataset(refs, cfg, backdrop=0.5, **common)
    painted = [bool((half.sample(0, k)["rgb"][:, ~inside] == grey).all()) for k in range(200)]
    assert 70 <= sum(painted) <= 130, sum(painted)  # about half, each seed's coin its own
    with pytest.raises(ValueError, match="backdrop"):
        ViewDataset(refs, cfg, backdrop=1.5, **common)


def test_a_run_validates_a_painting_model_on_painted_pictures(tmp_path):
    """The training loop's validation views are painted grey outside their mask exactly when the model's
    geometry.plain_backdrop is on, as genre eval and genre reconstruct show its nets; its training views are left to
    --backdrop's share."""
    from training.learn.loop import _datasets
    from training.learn.train import parse_args

    cfg = dataclasses.replace(TINY, geometry=dataclasses.replace(TINY.geometry, image_size=32))
    rgb = np.random.default_rng(1).integers(0, 256, (32, 32, 3), dtype=np.uint8)
    mask = np.zeros((32, 32), np.float32)
    mask[8:24, 8:24] = 1.0
    for k in range(8):
        (tmp_path / "v" / f"shape{k}").mkdir(parents=True)
        write_view(tmp_path / "v" / f"shape{k}", 0, rgb, np.where(mask > 0, 2.0, 0.0).astype(np.float32), mask,
                   {"image_size": 32})
    tcfg = parse_args(["depth", "--data", str(tmp_path / "v"), "--out", str(tmp_path / "run"), "--photo-fraction", "0",
                       "--backdrop", "0"]).config
    tcfg = dataclasses.replace(tcfg, val_fraction=0.5)
    for paints in (True, False):
        model_cfg = dataclasses.replace(cfg, geometry=dataclasses.replace(cfg.geometry, plain_backdrop=paints))
        train_set, val_set, _ = _datasets(tcfg, model_cfg)
        assert len(train_set) and len(val_set), (len(train_set), len(val_set))
        def one_colour_outside(sample):
            outside = sample["rgb"][:, ~sample["mask"]]
            return bool((outside == outside[:, :1]).all())

        assert val_set.plain_backdrop is paints and one_colour_outside(val_set.sample(0, None)) is paints
        assert not train_set.plain_backdrop and not one_colour_outside(train_set.sample(0, 3))
