"""What Debian's ``0ad-data`` holds for the corpus: every compiled mesh (``.pmd``) of its ``public.zip``, read.

0 A.D.'s art (CC-BY-SA-3.0, Wildfire Games) is the largest set of artist-made meshes the registries offer that
the corpus does not use yet. This prints how many of its meshes read (``training.data.readers.read_pmd``), how
many are rigid (no bones: not a unit's skinned body part), and of the rigid ones with at least ``--min-faces``
triangles, how many lie in each folder under ``art/meshes/`` (buildings, props, flora, helmets, ...); then how
many actor files (``art/actors/*.xml``, which name each mesh's textures) and skin textures (``.dds``) it holds,
and how many of a seeded sample of those textures Pillow decodes.

    mkdir -p $GENRE_HOME/cache/0ad && cd $GENRE_HOME/cache/0ad && apt-get download 0ad-data && dpkg -x 0ad-data_*.deb x
    python scripts/survey_0ad.py $GENRE_HOME/cache/0ad/x/usr/share/games/0ad/mods/public/public.zip
"""

from __future__ import annotations

import argparse
import collections
import io
import random
import zipfile

from PIL import Image

from training.data.readers import read_pmd


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("zip", help="0ad-data's mods/public/public.zip")
    parser.add_argument("--textures", type=int, default=200, help="how many skin textures to decode (seed 0)")
    parser.add_argument("--min-faces", type=int, default=200, help="the rigid meshes counted per folder have this many triangles or more")
    args = parser.parse_args()
    archive = zipfile.ZipFile(args.zip)
    read, failed, rigid = 0, [], collections.Counter()
    for name in archive.namelist():
        if not name.lower().endswith(".pmd"):
            continue
        try:
            mesh = read_pmd(archive.read(name))
        except ValueError as exc:
            failed.append(f"{name}: {exc}")
            continue
        read += 1
        if mesh.metadata["bones"] == 0 and len(mesh.faces) >= args.min_faces:
            parts = name.split("/")
            rigid[parts[2] if len(parts) > 3 and parts[:2] == ["art", "meshes"] else "(elsewhere)"] += 1
    print(f"{read + len(failed)} .pmd files: {read} read, {len(failed)} refused")
    for line in failed[:10]:
        print("  refused:", line)
    print(f"rigid with >= {args.min_faces} triangles: {sum(rigid.values())}")
    for folder, count in rigid.most_common():
        print(f"  {count:5d}  art/meshes/{folder}")
    names = archive.namelist()
    actors = [n for n in names if n.startswith("art/actors/") and n.endswith(".xml")]
    skins = sorted(n for n in names if n.startswith("art/textures/skins/") and n.lower().endswith(".dds"))
    sample = random.Random(0).sample(skins, min(args.textures, len(skins)))
    modes = collections.Counter()
    for name in sample:
        try:
            with Image.open(io.BytesIO(archive.read(name))) as image:
                image.load()
                modes[image.mode] += 1
        except (OSError, ValueError) as exc:
            modes[f"refused ({type(exc).__name__})"] += 1
    print(f"{len(actors)} actor files; {len(skins)} skin textures, of {len(sample)} sampled, Pillow gives: {dict(modes)}")


if __name__ == "__main__":
    main()
