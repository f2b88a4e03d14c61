"""Real photographs behind the training objects: fetched from Debian's wallpaper packages, with their licences.

The seed paper composited its renders over real scene photographs (SUN); the
offline equivalent here is Debian's desktop wallpapers, most of which are
photographs (landscapes, plants, rooms, streets).  ``genre data backgrounds``:

1. ``apt-get download`` + ``dpkg -x`` the packages (:func:`training.data.corpus.fetch`,
   the same cache as the shape corpus; nothing is installed);
2. finds their images (JPEG, PNG, WebP at least 400 px on the short side; of
   a wallpaper shipped at several resolutions only the largest is kept);
3. writes each, scaled to :data:`LONG_SIDE` px on its long side, as
   ``backgrounds/images/<package>__<n>.jpg`` and records in
   ``backgrounds/index.json`` its package, version, path inside the package and
   licence (the DEP-5 ``copyright`` stanza whose ``Files:`` pattern matches it,
   the last match winning, as DEP-5 says).

:class:`BackgroundBank` then gives seeded random crops (scale, position,
mirror) of those photos for :mod:`training.data.dataset` to composite the
rendered object over, through its film alpha.
"""

from __future__ import annotations

import fnmatch
import hashlib
import io
import json
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from genre_backend.atomic import atomic_write_bytes, atomic_write_json

__all__ = ["PACKAGES", "LONG_SIDE", "INDEX_NAME", "BackgroundImage", "prepare_backgrounds", "read_index", "licence_for", "BackgroundBank"]

log = logging.getLogger(__name__)

PACKAGES = ("gnome-backgrounds", "mate-backgrounds", "lomiri-wallpapers-16.04", "lomiri-wallpapers-20.04", "ukui-wallpapers", "plasma-workspace-wallpapers")
LONG_SIDE = 512  # stored size: crops of it are resized to the 128² (or 256²) network input
MIN_SHORT_SIDE = 400
INDEX_NAME = "index.json"
_EXTENSIONS = (".jpg", ".jpeg", ".png", ".webp")


@dataclass(frozen=True)
class BackgroundImage:
    """One prepared background: ``file`` (inside the backgrounds folder) and where it came from."""

    file: str
    package: str
    version: str
    source: str  # path inside the package, e.g. usr/share/backgrounds/gnome/foo.jpg
    licence: str
    width: int
    height: int


def _dep5_stanzas(text: str) -> list[tuple[list[str], str]]:
    """(Files patterns, License name) of each DEP-5 ``Files:`` stanza of a copyright file, in order."""
    stanzas = []
    for block in re.split(r"\n\s*\n", text):
        files = re.search(r"^Files:\s*(.+(?:\n[ \t]+.+)*)", block, flags=re.M)
        licence = re.search(r"^License:\s*(\S.*)$", block, flags=re.M)
        if files and licence:
            stanzas.append((files.group(1).split(), licence.group(1).strip()))
    return stanzas


def _matches(pattern: str, tails: set[str], name: str) -> bool:
    """A DEP-5 pattern against an installed path: the whole pattern against any trailing part of the path,
    or (a pattern naming a file, not ``dir/*``) its last component against the file name."""
    if pattern == "*" or any(fnmatch.fnmatchcase(t, pattern) for t in tails):
        return True
    last = pattern.rsplit("/", 1)[-1]
    return "*" not in last and fnmatch.fnmatchcase(name, last)


def licence_for(relative: str, copyright_text: str) -> str:
    """The licence of ``relative`` (a path inside the package's source tree or install tree) per a DEP-5 file.

    DEP-5 ``Files:`` patterns name paths in the *source* tree, which rarely
    match the installed path, so a pattern matches when it matches any
    trailing part of the path, or when its last component names the file.  The last matching
    stanza wins.  A free-form (not DEP-5) file gives the licences its
    "Licensed under …" sentences name, for every file; ``"unknown"`` when
    nothing matches.
    """
    parts = relative.split("/")
    tails = {"/".join(parts[i:]) for i in range(len(parts))}
    stanzas = _dep5_stanzas(copyright_text)
    if not stanzas:  # free-form copyright file: the licences it names, for the whole package
        named = sorted({re.sub(r"(\s+[Ll]icen[cs]e)?\.?\s*$", "", m) for m in re.findall(r"Licensed under (?:the )?([^\n]+)", copyright_text)})
        return " or ".join(named) if named else "unknown"
    found = "unknown"
    for patterns, licence in stanzas:
        if any(_matches(p, tails, parts[-1]) for p in patterns):
            found = licence
    return found


def _candidates(root: Path) -> list[Path]:
    """Image files of an unpacked package, one per wallpaper (the largest of a multi-resolution set)."""
    files = [p for p in root.rglob("*") if p.is_file() and p.suffix.lower() in _EXTENSIONS and "/icons/" not in p.as_posix()]
    best: dict[str, Path] = {}
    for p in files:
        # KDE wallpapers: NAME/contents/images/1920x1080.jpg … (and images_dark/): one per folder
        key = p.parent.as_posix() if re.fullmatch(r"\d+x\d+", p.stem) else p.as_posix()
        if key not in best or p.stat().st_size > best[key].stat().st_size:
            best[key] = p
    return sorted(best.values())


def prepare_backgrounds(data_dir: Path, packages=PACKAGES, long_side: int = LONG_SIDE) -> list[BackgroundImage]:
    """Fetch the packages and write ``data_dir/backgrounds`` (images + index); returns the index.

    Resumable: images already written are kept.  Duplicate images (same
    pixels at the stored size) are written once.
    """
    from PIL import Image

    from .corpus import fetch

    status = fetch(packages, data_dir)
    out = Path(data_dir) / "backgrounds"
    images_dir = out / "images"
    images_dir.mkdir(parents=True, exist_ok=True)
    index: list[BackgroundImage] = []
    seen: set[str] = set()
    for package in packages:
        if status.get(package, "").startswith("failed"):
            log.error("%s: %s", package, status[package])
            continue
        root = Path(data_dir) / "cache" / "unpacked" / package
        marker = (root / ".complete").read_text().strip() if (root / ".complete").is_file() else ""
        version = marker.split("_")[1] if marker.count("_") >= 2 else ""
        copyright_file = root / "usr" / "share" / "doc" / package / "copyright"
        copyright_text = copyright_file.read_text(errors="replace") if copyright_file.is_file() else ""
        n = 0
        for path in _candidates(root):
            rel = path.relative_to(root).as_posix()
            try:
                with Image.open(path) as im:
                    if min(im.size) < MIN_SHORT_SIDE:
                        continue
                    im.draft("RGB", (long_side, long_side))  # JPEG: decode at reduced size
                    rgb = im.convert("RGB")
            except (OSError, ValueError) as exc:
                log.warning("%s: skipped (%s)", rel, exc)
                continue
            scale = long_side / max(rgb.size)
            if scale < 1:
                rgb = rgb.resize((max(1, round(rgb.width * scale)), max(1, round(rgb.height * scale))), Image.LANCZOS)
            digest = hashlib.sha256(rgb.tobytes()).hexdigest()
            if digest in seen:
                continue
            seen.add(digest)
            name = f"{package}__{n:03d}.jpg"
            n += 1
            target = images_dir / name
            if not target.is_file():
                buf = io.BytesIO()
                rgb.save(buf, format="JPEG", quality=92)
                atomic_write_bytes(target, buf.getvalue())
            index.append(BackgroundImage(f"images/{name}", package, version, rel, licence_for(rel, copyright_text), rgb.width, rgb.height))
    atomic_write_json(out / INDEX_NAME, {"format": "genre-backgrounds/1", "images": [vars(b) for b in index]})
    return index


def read_index(folder: str | Path) -> list[BackgroundImage]:
    """The images of a backgrounds folder (``prepare_backgrounds``'s ``index.json``); a clear error if there is none."""
    path = Path(folder) / INDEX_NAME
    try:
        data = json.loads(path.read_text())
        images = [BackgroundImage(**row) for row in data["images"]]
    except FileNotFoundError:
        raise ValueError(f"{path}: no backgrounds index; run 'genre data backgrounds' first") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a backgrounds index ({exc})") from None
    if not images:
        raise ValueError(f"{path}: the backgrounds index lists no images")
    return images


class BackgroundBank:
    """Seeded random crops of the prepared photos.

    ``folder``: a backgrounds folder (``index.json`` + ``images/``).  Images
    are decoded on first use and kept (uint8; ~0.5 MB each).
    """

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self.images = read_index(self.folder)
        self._cache: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.images)

    def _pixels(self, i: int) -> np.ndarray:
        if i not in self._cache:
            from PIL import Image

            with Image.open(self.folder / self.images[i].file) as im:
                self._cache[i] = np.asarray(im.convert("RGB"))
        return self._cache[i]

    def sample(self, gen: torch.Generator, size: int) -> torch.Tensor:
        """A (3, size, size) float crop in [0, 1]: a random photo, a square of 35–100 % of its short side at a
        random place, mirrored half the time, resized to ``size``."""
        from PIL import Image

        u = torch.rand(5, generator=gen).tolist()
        img = self._pixels(min(int(u[0] * len(self.images)), len(self.images) - 1))
        h, w = img.shape[:2]
        side = max(8, int(min(h, w) * (0.35 + 0.65 * u[1])))
        x0, y0 = int((w - side) * u[2]), int((h - side) * u[3])
        crop = Image.fromarray(img[y0:y0 + side, x0:x0 + side]).resize((size, size), Image.BILINEAR)
        arr = np.asarray(crop, dtype=np.float32) / 255.0
        if u[4] < 0.5:
            arr = arr[:, ::-1]
        return torch.from_numpy(np.ascontiguousarray(arr)).permute(2, 0, 1).contiguous()
