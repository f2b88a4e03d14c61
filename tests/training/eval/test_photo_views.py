"""scripts/photo_views.py: rendered views made photo-like as training makes them, the rest of each view linked."""

import numpy as np
from PIL import Image

from support.scripts import load_script
from support.tiny_data import two_colour_backgrounds
from training.data.views import write_view

photo_views = load_script("photo_views")


def test_pictures_go_over_the_bank_photos_and_everything_else_is_the_original(tmp_path):
    s = 32
    rgb = np.full((s, s, 3), 40, np.uint8)  # a dark object on a dark render backdrop
    mask = np.zeros((s, s), np.float32)
    mask[8:24, 8:24] = 1.0
    depth = np.where(mask > 0, 2.0, 0.0).astype(np.float32)
    src = tmp_path / "views"
    for shape in ("a", "b"):
        (src / shape).mkdir(parents=True)
        for k in range(2):
            write_view(src / shape, k, rgb, depth, mask, {"image_size": s})
    bank = two_colour_backgrounds(tmp_path / "bg")
    args = [str(src), str(tmp_path / "out"), "--backgrounds", str(bank), "--seed", "3"]
    assert photo_views.main(args) == 0
    pictures = sorted((tmp_path / "out").rglob("*.png"))
    assert len(pictures) == 4 and not any(p.is_symlink() for p in pictures)
    others = [p for p in (tmp_path / "out").rglob("*") if p.is_file() and p.suffix != ".png"]
    assert others and all(p.is_symlink() and p.resolve() == (src / p.parent.name / p.name).resolve() for p in others)
    first = np.asarray(Image.open(pictures[0]).convert("RGB")).astype(int)
    inside, outside = first[mask > 0], first[mask == 0]
    # outside the object a bank photo (pure red or green before the camera's faults), inside the dark object
    assert (outside.max(1) - outside.min(1)).mean() > 100
    assert inside.mean() < 90 and (inside.max(1) - inside.min(1)).mean() < 40
    # the draws are the seed's and the view's: made again, the same bytes; another view, another draw
    again = tmp_path / "again"
    assert photo_views.main([str(src), str(again), "--backgrounds", str(bank), "--seed", "3"]) == 0
    assert all(p.read_bytes() == (again / p.relative_to(tmp_path / "out")).read_bytes() for p in pictures)
    assert len({p.read_bytes() for p in pictures}) == 4
    assert photo_views.view_seed(3, "a/view_000") != photo_views.view_seed(4, "a/view_000")
    assert photo_views.main([str(tmp_path / "missing"), str(again), "--backgrounds", str(bank)]) == 2
