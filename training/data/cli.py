"""``genre data``: fetch, build, inspect (and render) the training corpus.

    genre data fetch  [--data-dir D] [--packages P ...]
    genre data build  [--data-dir D] [--sources S ...] [--shapenet DIR] [--folder DIR] [--jobs N]
    genre data stats  [--data-dir D]
    genre data credits [--split S] [--out F]
    genre data render ...   (see training/render/cli.py)
    genre data targets ...  (see training/data/targets.py)
    genre data show ...     (see training/data/show.py)
    genre data pack ...     (see training/data/pack.py)
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from collections import Counter, defaultdict
from pathlib import Path
from genre_backend.arguments import add_jobs, add_out, add_seed

__all__ = ["main", "format_stats", "format_credits"]


def _skip_kind(reason: str) -> str:
    """Group a skip reason: the text before the first ':' or '(' (``"junk: flat"`` keeps two words)."""
    if reason.startswith("junk:"):
        detail = reason[5:].strip()
        if detail.startswith("name"):
            return "junk: name"
        if detail.startswith("flat"):
            return "junk: flat"
        return "junk: too few triangles"
    if reason.startswith("near-duplicate"):
        return "near-duplicate"
    return reason.split(":")[0].split("(")[0].strip()


def _table(title: str, rows: list[tuple], header: tuple) -> list[str]:
    widths = [max(len(str(x)) for x in col) for col in zip(header, *rows)] if rows else [len(h) for h in header]
    out = [title]
    out.append("  " + "  ".join(str(h).ljust(w) if i == 0 else str(h).rjust(w) for i, (h, w) in enumerate(zip(header, widths))))
    for row in rows:
        out.append("  " + "  ".join(str(x).ljust(w) if i == 0 else str(x).rjust(w) for i, (x, w) in enumerate(zip(row, widths))))
    return out


def format_stats(manifest: dict) -> str:
    """The counts of a manifest (per class x split, source, licence, split; skips) and the rules."""
    shapes = manifest["shapes"]
    skipped = manifest.get("skipped", [])
    splits = ("train", "test", "unseen", "unassigned")
    product = ("product-train", "product-test")  # the product model's split (every class holds out shapes)
    by_class: dict[str, Counter] = defaultdict(Counter)
    for s in shapes:
        by_class[s["class"]][s["split"]] += 1
        for g in s.get("groups", ()):
            if g in product:
                by_class[s["class"]][g] += 1
    seen = manifest["classes"]["seen"]
    unseen = manifest["classes"]["unseen"]
    pix3d = manifest["classes"]["unseen-pix3d"]

    def group(cls: str) -> str:
        g = []
        if cls in seen:
            g.append("seen")
        if cls in unseen:
            g.append("unseen")
        if cls in pix3d:
            g.append("pix3d")
        return "+".join(g) or "-"

    def total(cls: str) -> int:
        return sum(by_class[cls][s] for s in splits)

    order = sorted(by_class, key=lambda c: (group(c) == "-", -total(c), c))
    rows = [(c, group(c), *(by_class[c][s] for s in (*splits, *product)), total(c),
             "  (<10: small)" if 0 < total(c) < 10 and group(c) != "-" else "") for c in order]
    totals = Counter(s["split"] for s in shapes) + Counter(g for s in shapes for g in s.get("groups", ()) if g in product)
    rows.append(("TOTAL", "", *(totals[s] for s in (*splits, *product)), len(shapes), ""))
    lines = _table("Shapes per class and split:", rows, ("class", "group", *splits, *product, "total", ""))
    lines.append("")
    lines.append("Split lists (a sofa/table is in both unseen lists): " + ", ".join(
        f"{k} {len(v)}" for k, v in manifest["splits"].items()))
    lines.append("")
    src = Counter((s["source"], s.get("package") or "-") for s in shapes)
    src_skip = Counter(s["source"] for s in skipped)
    rows = [(f"{k[0]} ({k[1]})", v, src_skip.get(k[0], 0)) for k, v in sorted(src.items())]
    lines += _table("Per source:", rows, ("source (package)", "kept", "skipped"))
    lines.append("")
    lic = Counter(s["licence"] for s in shapes)
    lines += _table("Per licence:", sorted(lic.items(), key=lambda kv: -kv[1]), ("licence", "shapes"))
    lines.append("")
    reasons = Counter((s["source"], _skip_kind(s["reason"])) for s in skipped)
    rows = [(f"{k[1]} [{k[0]}]", v) for k, v in sorted(reasons.items(), key=lambda kv: (kv[0][1], kv[0][0]))]
    rows.append(("TOTAL", len(skipped)))
    lines += _table("Skipped (reason [source]):", rows, ("reason", "count"))
    textured = sum(1 for s in shapes if s.get("textured"))
    watertight = sum(1 for s in shapes if s.get("watertight"))
    lines.append("")
    lines.append(f"Textured: {textured}/{len(shapes)}; watertight: {watertight}/{len(shapes)}")
    errs = [s["extra"]["catalogue_extent_error"] for s in shapes if "catalogue_extent_error" in s.get("extra", {})]
    if errs:
        bad = sum(1 for e in errs if e > 0.02)
        lines.append(f"Sweet Home 3D orientation check: {len(errs) - bad}/{len(errs)} models have canonical X/Y/Z "
                     f"extents within 0.02 of the catalogue's width/depth/height (max error {max(errs):.3f})")
    lines.append("")
    lines.append(manifest.get("rules", ""))
    return "\n".join(lines)


def format_credits(manifest: dict, split: str) -> str:
    """Markdown: the shapes of ``split`` (a split or a group) with their class, source, creator and licence."""
    shapes = [s for s in manifest["shapes"] if s["split"] == split or split in s.get("groups", [])]
    if not shapes:
        raise ValueError(f"no shapes in split {split!r}")
    licences = Counter(s["licence"] for s in shapes)
    lines = [f"# Shapes of the '{split}' split ({len(shapes)})", "",
             "Licences: " + ", ".join(f"{k} {v}" for k, v in sorted(licences.items())) + ".", "",
             "| shape | class | name | source (package) | creator | licence |", "|---|---|---|---|---|---|"]
    for s in sorted(shapes, key=lambda s: (s["class"], s["id"])):
        cells = [s["id"], s["class"], s.get("name") or "", f"{s['source']} ({s.get('package') or '-'})",
                 s.get("creator") or "", s["licence"]]
        lines.append("| " + " | ".join(str(c).replace("|", "/") for c in cells) + " |")
    return "\n".join(lines) + "\n"


def _parser(prog: str) -> argparse.ArgumentParser:
    from .corpus import DEBIAN_PACKAGES, OPT_IN_SOURCES, SOURCES

    parser = argparse.ArgumentParser(prog=prog, description="Fetch, build and inspect the training corpus.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--data-dir", default=None,
                        help="the GenRe home (default: $GENRE_HOME, else $GENRE_DATA_DIR, else $XDG_CACHE_HOME/genre, else ~/.cache/genre)")
    common.add_argument("-v", "--verbose", action="store_true", help="log every skipped file")

    p = sub.add_parser("fetch", parents=[common], help="apt-get download + dpkg -x the model packages")
    p.add_argument("--packages", nargs="+", default=list(DEBIAN_PACKAGES), metavar="PKG",
                   help=f"packages (default: {' '.join(DEBIAN_PACKAGES)})")

    from .photo_backgrounds import PACKAGES as BACKGROUND_PACKAGES

    p = sub.add_parser("backgrounds", parents=[common],
                       help="real photographs (Debian wallpaper packages) behind the objects: DATA/backgrounds/ with licences")
    p.add_argument("--packages", nargs="+", default=list(BACKGROUND_PACKAGES), metavar="PKG",
                   help=f"packages (default: {' '.join(BACKGROUND_PACKAGES)})")

    p = sub.add_parser("build", parents=[common], help="normalise, classify, split; write corpus/manifest.json")
    p.add_argument("--sources", nargs="+", choices=list(SOURCES), default=None, help="Debian sources to use (default: all but the opt-in "
                   + ", ".join(OPT_IN_SOURCES) + ", built in a home of its own: docs/data.md)")
    p.add_argument("--no-debian", action="store_true", help="use only --shapenet/--folder sources")
    p.add_argument("--shapenet", default=None, metavar="DIR", help="a ShapeNetCore v1/v2 folder")
    p.add_argument("--shapenet-front", default="+z", help="ShapeNet's front axis (default +z; up is +y)")
    p.add_argument("--folder", action="append", default=[], metavar="DIR",
                   help="a folder of meshes, class = sub-folder name (repeatable)")
    p.add_argument("--folder-up", default="+z", help="up axis of --folder meshes (default +z)")
    p.add_argument("--folder-front", default="-y", help="front axis of --folder meshes (default -y)")
    add_jobs(p, default=max(1, min(8, (os.cpu_count() or 1))),
                   help="worker processes (default: CPUs, at most 8)")

    sub.add_parser("stats", parents=[common], help="counts per class, split, source, licence; skips; rules")
    p = sub.add_parser("credits", parents=[common], help="Markdown list of the shapes of a split with creator and licence")
    p.add_argument("--split", default="train", help="split or group (default: train)")
    add_out(p, help="write here (default: standard output)")
    p = sub.add_parser("flat-test", parents=[common], help="flat shapes lying on the ground, for genre eval's flat-from-above group "
                                         "(training/data/sources/thin.py; in no training set): OUT/manifest.json + meshes")
    add_out(p, required=True, help="output folder")
    p.add_argument("--per-kind", type=int, default=6, help="shapes of each flat kind (plate, card, book, leaf; default 6)")
    p = sub.add_parser("thin", parents=[common], help="the pack's thin shapes (plates, cards, books, leaves, bowls, rods) lying on "
                       "the ground, for rendering training views (training/data/sources/thin.py): OUT/manifest.json + meshes")
    add_out(p, required=True, help="output folder")
    p.add_argument("--per-kind", type=int, default=40, help="shapes of each thin kind (default 40, as genre data pack --thin)")
    p = sub.add_parser("squashed", parents=[common], help="ellipsoids, cylinders and boxes squashed to a random thickness, lying "
                       "flat: one outline, every depth (training/data/sources/squashed.py): OUT/manifest.json + meshes")
    add_out(p, required=True, help="output folder")
    p.add_argument("--per-kind", type=int, default=100, help="shapes of each kind (default 100)")
    add_seed(p, help="seed of the shapes (default 0)")
    p = sub.add_parser("furniture", parents=[common], help="procedural tables, chairs, stools, benches, shelves, cabinets, beds, "
                       "sofas and lamps built from parts, for the depth net (training/data/sources/furniture.py): "
                       "OUT/manifest.json + meshes")
    add_out(p, required=True, help="output folder")
    p.add_argument("--per-kind", type=int, default=100, help="shapes of each kind (default 100)")
    add_seed(p, help="seed of the shapes (default 0)")
    sub.add_parser("render", add_help=False, help="render views of the corpus (training/render/cli.py)")
    sub.add_parser("targets", add_help=False, help="ground-truth targets of rendered views (training/data/targets.py)")
    sub.add_parser("show", add_help=False, help="contact sheet PNG of a few samples (training/data/show.py)")
    sub.add_parser("pack", add_help=False, help="the training shapes' meshes for a GPU burst (training/data/pack.py)")
    sub.add_parser("photo-frame", add_help=False, help="rendered views framed as a photo is (training/data/photo_framing.py)")
    return parser


def _targets_main():
    from . import targets

    return targets.main


def _show_main():
    from . import show

    return show.main


def _photo_frame_main():
    from . import photo_framing

    return photo_framing.main


def _pack_main():
    from . import pack

    return pack.main


def _fetch(args: argparse.Namespace, prog: str) -> int:
    """``genre data fetch``: the Debian model packages into the GenRe home; 1 when one failed."""
    from . import corpus

    root = corpus.data_dir(args.data_dir)
    print(f"data folder: {root}")
    status = corpus.fetch(args.packages, root)
    for pkg, st in status.items():
        print(f"  {pkg:<24} {st}")
    return 0 if all(not s.startswith("failed") for s in status.values()) else 1


def _backgrounds(args: argparse.Namespace, prog: str) -> int:
    """``genre data backgrounds``: photographs behind the objects, with their licences; 1 when none."""
    from . import corpus
    from .photo_backgrounds import prepare_backgrounds

    root = corpus.data_dir(args.data_dir)
    start = time.time()
    index = prepare_backgrounds(root, args.packages)
    counts = Counter((b.package, b.licence) for b in index)
    for (pkg, licence), n in sorted(counts.items()):
        print(f"  {pkg:<28} {n:4d}  {licence}")
    print(f"wrote {root / 'backgrounds' / 'index.json'}: {len(index)} photos from {len({b.package for b in index})} packages, {time.time() - start:.0f} s")
    return 0 if index else 1


def _build(args: argparse.Namespace, prog: str) -> int:
    """``genre data build``: ``corpus/manifest.json`` and the normalised meshes; 1 when nothing was found."""
    from . import corpus

    if args.jobs < 1:
        print(f"{prog} build: --jobs must be >= 1", file=sys.stderr)
        return 2
    extra = []
    if args.shapenet:
        extra.append(("shapenet", args.shapenet, {"front": args.shapenet_front}))
    for folder in args.folder:
        extra.append(("folder", folder, {"up": args.folder_up, "front": args.folder_front}))
    sources = [] if args.no_debian else args.sources
    root = corpus.data_dir(args.data_dir)
    start = time.time()

    def progress(done: int, total: int) -> None:
        if done == total or done % 25 == 0:
            rate = done / max(time.time() - start, 1e-9)
            eta = (total - done) / max(rate, 1e-9)
            print(f"\r  {done}/{total} models  ({rate:.1f}/s, ETA {eta:4.0f} s)", end="", file=sys.stderr, flush=True)

    try:
        manifest = corpus.build(root, sources=sources, extra_specs=extra, jobs=args.jobs, progress=progress)
    except (ValueError, FileNotFoundError) as exc:
        print(f"\n{prog} build: {exc}", file=sys.stderr)
        return 1
    print(file=sys.stderr)
    print(f"wrote {root / 'corpus' / 'manifest.json'}: {len(manifest['shapes'])} shapes kept, "
          f"{len(manifest['skipped'])} skipped, {time.time() - start:.0f} s")
    return 0


def _from_manifest(args: argparse.Namespace, prog: str) -> int:
    """``genre data stats`` and ``genre data credits``: read the manifest, print (or write) its summary."""
    from . import corpus

    try:  # stats and credits read the manifest
        manifest = corpus.load_manifest(args.data_dir)
    except FileNotFoundError as exc:
        print(f"{prog} {args.command}: {exc}", file=sys.stderr)
        return 1
    if args.command == "stats":
        print(format_stats(manifest))
        return 0
    try:
        text = format_credits(manifest, args.split)
    except ValueError as exc:
        print(f"{prog} credits: {exc}", file=sys.stderr)
        return 1
    if args.out:
        from pathlib import Path

        Path(args.out).write_text(text)
    else:
        print(text, end="")
    return 0


def _write_shapes(out: Path, entries: list[tuple[str, str, object]], split: str, groups: list[str], seed: int,
                  source: str) -> None:
    """Each ``(id, class, trimesh)`` as OUT/shapes/ID.glb, and OUT/manifest.json naming them (the renderer's input)."""
    from genre_backend.atomic import atomic_write_json

    (out / "shapes").mkdir(parents=True, exist_ok=True)
    rows = []
    for sid, cls, mesh in entries:
        mesh.export(out / "shapes" / f"{sid}.glb")
        rows.append({"id": sid, "class": cls, "split": split, "groups": groups, "mesh": f"shapes/{sid}.glb",
                     "source": source, "licence": "CC0", "extents": [round(float(e), 6) for e in mesh.extents]})
    atomic_write_json(out / "manifest.json", {"seed": seed, "shapes": rows})


def _procedural_shapes(args: argparse.Namespace, prog: str, make, kinds, limit: int, split: str, group: str,
                       seed: int, source: str, what: str) -> int:
    """Write ``make(kind, k)`` for each kind and k < ``--per-kind`` with :func:`_write_shapes`; 2 on a bad count."""
    if not 1 <= args.per_kind <= limit:
        print(f"{prog}: --per-kind must be in 1..{limit}, got {args.per_kind}", file=sys.stderr)
        return 2
    entries = [make(kind, k) for kind in kinds for k in range(args.per_kind)]
    _write_shapes(Path(args.out), entries, split, [group], seed, source=source)
    print(f"{prog}: {len(entries)} {what} on the ground plane in {args.out}")
    return 0


def _flat_test(args: argparse.Namespace, prog: str) -> int:
    """``genre data flat-test``: the flat-from-above eval shapes as GLB files and a manifest (split ``flat-test``)."""
    from .sources.thin import FLAT_KINDS, FLAT_TEST_SEED, flat_test_shape

    return _procedural_shapes(args, prog, flat_test_shape, FLAT_KINDS, 100, "flat-test", "flat-from-above",
                              FLAT_TEST_SEED, "procedural-thin", "flat shapes")


def _thin(args: argparse.Namespace, prog: str) -> int:
    """``genre data thin``: the pack's thin shapes (seed 0) lying on the ground, split ``product-train``, to render."""
    from .sources.thin import KINDS, lying_thin_shape

    return _procedural_shapes(args, prog, lying_thin_shape, KINDS, 1000, "product-train", "thin", 0,
                              "procedural-thin", "thin training shapes")


def _squashed(args: argparse.Namespace, prog: str) -> int:
    """``genre data squashed``: ellipsoids, cylinders and boxes of random thickness lying flat, split ``product-train``."""
    from .sources.squashed import KINDS, squashed_shape

    return _procedural_shapes(args, prog, lambda kind, k: squashed_shape(kind, k, args.seed), KINDS, 1000,
                              "product-train", "squashed", args.seed, "procedural-squashed", "squashed training shapes")


def _furniture(args: argparse.Namespace, prog: str) -> int:
    """``genre data furniture``: procedural furniture and lamps standing upright, split ``product-train``."""
    from .sources.furniture import KINDS, furniture_shape

    return _procedural_shapes(args, prog, lambda kind, k: furniture_shape(kind, k, args.seed), KINDS, 5000,
                              "product-train", "furniture", args.seed, "procedural-furniture", "furniture shapes")


_COMMANDS = {"fetch": _fetch, "backgrounds": _backgrounds, "build": _build, "stats": _from_manifest,
             "credits": _from_manifest, "flat-test": _flat_test, "thin": _thin, "squashed": _squashed,
             "furniture": _furniture}


def main(argv: list[str] | None = None, prog: str = "genre data", delegated: dict | None = None) -> int:
    """Entry point of ``genre data``; returns a process exit code.

    ``delegated``: more subcommands (name → loader returning ``main(argv, prog)``)
    from later layers; ``training/commands.py`` adds ``render`` this way, so
    the data layer does not import the renderer.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    loaders = {"targets": _targets_main, "show": _show_main, "pack": _pack_main, "photo-frame": _photo_frame_main, **(delegated or {})}
    if argv and argv[0] in loaders:
        return int(loaders[argv[0]]()(argv[1:], prog=f"{prog} {argv[0]}") or 0)
    args = _parser(prog).parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("trimesh").setLevel(logging.ERROR)
    return _COMMANDS[args.command](args, prog)
