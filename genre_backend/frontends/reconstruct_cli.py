"""``genre reconstruct IMAGE… [-o OUT] [--mask M | --box x0,y0,x1,y1 --strokes S] [MESH OPTIONS] [--quality fast|best]
[--no-refine] [--save-intermediates DIR] [--preview] [--weights W] [--device cpu|cuda]``.

The mesh options (``--threshold T``, ``--hole-closing K``, ``--texture``, ``--format obj|ply|glb``, ``--up y|z``, …)
are the fields of :class:`.options.MeshOptions`, one flag each (:func:`.options.add_arguments`).

One image or many (a progress bar on stderr for many).  Each mesh is written
atomically; every bad input gets one line on stderr naming the file and the
problem (with its ``genre serve`` error code), the other images go on, and the
exit status is 1 if any image failed (2 for bad arguments).  A doubtful mask
(one that covers most of the photo or touches most of its border: probably
the photo's frame, not the object; or one whose outline the salient net is
unsure of, that is one of several objects, cut off by the frame or tiny; or,
without the net, a GrabCut mask whose colours barely separate from the
background's or that runs along the photo's edge: :mod:`.segment`) gets a
warning line on stderr; the mesh is still written.  ``--box`` (a box around
the object, the photo's pixels) and ``--strokes`` (an image the photo's size:
white strokes on the object, black on the background, mid grey or
transparency elsewhere) guide the salient net's mask; the result line then says ``mask: box``, ``mask:
strokes`` or ``mask: box+strokes``.

Axes: OBJ and glb are written +y up (the view frame), as their importers
expect; a PLY is written +z up by default (``--up z``: Blender's axes, front
toward −y), ``--up y`` keeps the view frame.  All three land alike in
Blender (:mod:`.mesh_export`, "Axes").  ``--up z`` is for PLY only.

Outputs: with one image, ``-o`` is the mesh file (or an existing folder);
with many, ``-o`` is a folder (created if needed) that receives
``<image stem>.<format>``.  Default: the current folder.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..arguments import DEVICES, add_device, add_weights
from ..process import say

__all__ = ["main", "output_paths"]


def output_paths(images: list[Path], out: str | None, fmt: str) -> list[Path]:
    """The mesh path of every image; names that would collide get ``-2``, ``-3``… appended."""
    if len(images) == 1 and out is not None and not _is_dir(out) and not out.endswith(os.sep):
        path = Path(out)
        # a new name without an extension gets the format's, so that what is written opens by its name (a path that
        # is already there, a device or a pipe, is left as named for the output checks to judge)
        keep = path.suffix or path.name in ("", ".", "..") or _lexists(path)
        return [path if keep else path.with_name(f"{path.name}.{fmt}")]
    folder = Path(out) if out is not None else Path(".")
    seen: dict[str, int] = {}
    paths = []
    for image in images:
        stem = image.stem or "mesh"
        n = seen.get(stem, 0) + 1
        seen[stem] = n
        paths.append(folder / (f"{stem}.{fmt}" if n == 1 else f"{stem}-{n}.{fmt}"))
    return paths


def _lexists(path: Path) -> bool:
    """Whether anything (a dangling link too) is at ``path``; False for a name the OS refuses."""
    try:
        return os.path.lexists(path)
    except (OSError, ValueError):
        return False


def _is_dir(path: str | os.PathLike) -> bool:
    """``Path.is_dir`` that answers False for a name the OS refuses (too long, …) instead of raising."""
    try:
        return Path(path).is_dir()
    except OSError:
        return False


def _one_line(exc: BaseException, limit: int = 2000) -> str:
    text = str(exc).strip().splitlines()
    line = text[0] if text else exc.__class__.__name__
    return line if len(line) <= limit else f"{line[:limit]}… ({len(line):,} characters)"


class _Terminated(BaseException):
    """SIGTERM arrived (raised in the main thread, like KeyboardInterrupt for SIGINT)."""


def main(argv: list[str] | None = None, prog: str = "genre reconstruct") -> int:
    """Run ``genre reconstruct``; SIGINT prints ``PROG: interrupted`` and returns 130, SIGTERM ``PROG: terminated``
    and 143 (no traceback; the file being written is dropped with its temporaries)."""
    import signal
    import threading

    def on_term(signum, frame):
        raise _Terminated()

    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, on_term)
    try:
        return _main(argv, prog)
    except KeyboardInterrupt:
        say(f"{prog}: interrupted")
        return 130
    except _Terminated:
        say(f"{prog}: terminated")
        return 143
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _parser(prog: str) -> argparse.ArgumentParser:
    """``genre reconstruct``'s arguments: the photos, their mask inputs, every mesh option of the record, the rest."""
    from ..inference.options import add_arguments

    parser = argparse.ArgumentParser(prog=prog, description="Turn photos of objects into meshes (posed as seen, in the view frame).")
    parser.add_argument("images", nargs="+", metavar="IMAGE", help="image files (PNG, JPEG, …); RGBA images use their alpha as the mask")
    parser.add_argument("-o", "--output", metavar="OUT", help="mesh file (one image; a name without an extension gets the format's) or folder "
                                                         "(default: the current folder)")
    parser.add_argument("--mask", metavar="M", help="mask file for the (single) image: white object on black, same size")
    parser.add_argument("--box", metavar="X0,Y0,X1,Y1",
                        help="a box around the object in the (single) photo's pixels (left, top, right, bottom; x right, "
                             "y down): the object is found inside it")
    parser.add_argument("--strokes", metavar="S",
                        help="strokes image for the (single) photo, the photo's size: white (>= 192) on the object, black "
                             "(<= 63) on the background, mid grey (128) or transparent elsewhere; the mask keeps them")
    add_arguments(parser)  # every mesh option (genre_backend/inference/options.py) and --quality
    parser.add_argument("--no-refine", action="store_true",
                        help="without --mask or alpha, use the depth net's silhouette as it is (default: find the object in the photo by the salient-object net)")
    parser.add_argument("--save-intermediates", metavar="DIR",
                        help="write PNGs of depth, mask, spherical maps and voxels here, and mask_in_photo.png: the mask at the photo's size, to correct and give back with --mask")
    parser.add_argument("--preview", action="store_true",
                        help="also write MESH_preview.png beside each mesh: small panels of the photo, mask, depth and spherical maps above three large Blender views of the mesh (photo viewpoint, right side, back), in the photo's colour with --texture")
    add_weights(parser)
    add_device(parser, choices=list(DEVICES))
    return parser


@dataclass(frozen=True)
class ReconstructSpec:
    """One ``genre reconstruct`` call, checked: ``outputs[i]`` is the mesh of ``images[i]``, written as ``fmt`` with
    ``up`` as its up axis; ``options`` the mesh options (:class:`.options.MeshOptions`, None fields: the weights');
    ``guidance`` the (single) photo's mask inputs (:class:`genre_backend.photo.guidance.MaskGuidance`: ``--mask``,
    ``--box`` (x0, y0, x1, y1, the photo's pixels), ``--strokes``, ``--no-refine``)."""

    prog: str
    images: tuple[Path, ...]
    outputs: tuple[Path, ...]
    output: str | None
    fmt: str
    up: str
    options: Any
    guidance: Any
    save_intermediates: str | None
    preview: bool
    weights: str | None
    device: str

    @property
    def many(self) -> bool:
        return len(self.images) > 1


def _mask_inputs(parser: argparse.ArgumentParser, args: argparse.Namespace) -> tuple[float, float, float, float] | None:
    """Check that --mask, --box and --strokes go with one photo and not with each other; the box, checked."""
    if args.mask and len(args.images) > 1:
        parser.error("--mask applies to one image; give one image per call")
    if args.box is not None or args.strokes is not None:
        used = " and ".join(n for n, v in (("--box", args.box), ("--strokes", args.strokes)) if v is not None)
        if len(args.images) > 1:
            verb = "apply" if " and " in used else "applies"
            parser.error(f"{used} {verb} to one image; give one image per call")
        if args.mask:
            parser.error(f"give either --mask or {used}, not both")
        if args.no_refine:
            parser.error(f"{used} guide the mask found in the photo; --no-refine turns it off")
    if args.box is None:
        return None
    from ..validation import check_box

    try:
        return check_box("--box", args.box)
    except ValueError as exc:
        parser.error(str(exc))


def parse_spec(argv: list[str] | None, prog: str) -> ReconstructSpec:
    """The command line as a :class:`ReconstructSpec`; bad arguments exit 2 with argparse's message."""
    from ..output.mesh_export import resolve_up
    from ..inference.options import OptionError, from_arguments
    from ..inference.reconstruct import MESH_FORMATS
    from ..photo.guidance import MaskGuidance

    parser = _parser(prog)
    args = parser.parse_args(argv)
    _check_extras(parser, args)
    box = _mask_inputs(parser, args)
    try:
        options = from_arguments(args)
    except OptionError as exc:
        parser.error(str(exc))
    images = [Path(p) for p in args.images]
    fmt = options.format
    if len(images) == 1 and args.output and not _is_dir(args.output) and not args.output.endswith(os.sep):
        ext = Path(args.output).suffix.lower().lstrip(".")
        if fmt is None:
            fmt = ext if ext in MESH_FORMATS else "obj"
        elif ext in MESH_FORMATS and ext != fmt:
            parser.error(f"--format {fmt} does not match the output's extension .{ext}")
    fmt = fmt or "obj"
    try:
        up = resolve_up(fmt, options.up)
    except ValueError as exc:
        parser.error(f"--{exc}")
    return ReconstructSpec(prog, tuple(images), tuple(output_paths(images, args.output, fmt)), args.output, fmt, up,
                           options, MaskGuidance(mask=args.mask, box=box, strokes=args.strokes, refine=not args.no_refine),
                           args.save_intermediates, args.preview, args.weights, args.device)


def _check_extras(parser, args) -> None:
    """--preview needs the ``genre[preview]`` extra (bpy, matplotlib), which the runtime install leaves out: say so
    before any work.  (--save-intermediates without matplotlib draws its maps in grey.)"""
    import importlib.util

    missing = [name for name in ("bpy", "matplotlib") if args.preview and importlib.util.find_spec(name) is None]
    if missing:
        parser.error(f"--preview needs {' and '.join(missing)}, which this install lacks: pip install 'genre[preview]'")


def _main(argv: list[str] | None, prog: str) -> int:
    return reconstruct_all(parse_spec(argv, prog))


def _fail(prog: str, message: str, code: str) -> int:
    say(f"{prog}: error: {message} [{code}]")
    return 1


def _output_folder(spec: ReconstructSpec) -> int:
    """With several photos, make ``-o`` a folder (0), or say why it cannot be one (1)."""
    if not (spec.many and spec.output):
        return 0
    out_dir = Path(spec.output)
    if os.path.exists(out_dir) and not _is_dir(out_dir):
        return _fail(spec.prog, f"{out_dir}: with several images, -o must be a folder", "output_unwritable")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return _fail(spec.prog, f"{out_dir}: cannot create the output folder ({exc.strerror or exc})", "output_unwritable")
    return 0


def _load(spec: ReconstructSpec):
    """The :class:`.reconstruct.Reconstructor` of ``spec.weights``, or the exit status 1 after one line on stderr."""
    from ..weights_file import DEFAULT_WEIGHTS_NAME, WEIGHTS_NAMES, WeightsError, resolve_weights
    from ..inference.reconstruct import Reconstructor, error_code

    try:
        weights = resolve_weights(spec.weights)
    except WeightsError as exc:
        return _fail(spec.prog, f"--weights: {exc}", "bad_weights")
    name = spec.weights or DEFAULT_WEIGHTS_NAME
    if name in WEIGHTS_NAMES and not weights.is_file():
        return _fail(spec.prog, f"no {name} weights at {weights}: the trained weights are not installed yet; "
                     "train them with 'genre train depth|inpaint|refine …' (see 'genre train --help') and pass "
                     "--weights RUN/refine/best.safetensors", "bad_weights")
    try:
        return Reconstructor(weights, spec.device)
    except (WeightsError, ValueError) as exc:
        return _fail(spec.prog, _one_line(exc), error_code(exc))
    except Exception as exc:  # noqa: BLE001  (load_model turns a bad file into WeightsError; anything else is one line too)
        return _fail(spec.prog, f"internal error while loading {weights}: {exc.__class__.__name__}: {_one_line(exc)}", "internal")


def reconstruct_all(spec: ReconstructSpec) -> int:
    """Reconstruct every photo of ``spec`` (a progress bar on stderr for several); 0 when all were written, else 1."""
    status = _output_folder(spec)
    if status:
        return status
    rec = _load(spec)
    if isinstance(rec, int):
        return rec
    bar = None
    if spec.many and sys.stderr is not None:  # (no bar on a closed stderr)
        from tqdm import tqdm

        bar = tqdm(total=len(spec.images), desc="reconstruct", unit="image", file=sys.stderr, dynamic_ncols=True)

    def tell(text: str, err: bool = False) -> None:
        """One line on stdout (``err``: stderr), else on the other stream when that one is closed or broken: a
        mesh written is never turned into a failure by a reader that has gone."""
        if bar is not None:
            try:
                bar.write(text, file=sys.stderr if err else sys.stdout)
                return
            except (OSError, ValueError, AttributeError):
                pass
        say(text, err=err)

    failed = 0
    try:  # (on Ctrl-C or SIGTERM the bar is closed first: the one-line message comes on a line of its own)
        for image, out in zip(spec.images, spec.outputs):
            failed += not _reconstruct_one(spec, rec, image, out, tell)
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    if failed and spec.many:
        say(f"{spec.prog}: {failed} of {len(spec.images)} images failed")
    return 1 if failed else 0


def _reconstruct_one(spec: ReconstructSpec, rec, image: Path, out: Path, say: Callable[..., None]) -> bool:
    """Write one photo's mesh (and its intermediates and preview) and say so; a bad input is one line, False."""
    from ..output.mesh_export import check_outputs
    from ..inference.reconstruct import error_code

    textured = bool(spec.options.texture)
    try:
        intermediates = None
        if spec.save_intermediates:
            intermediates = Path(spec.save_intermediates) / image.stem if spec.many else Path(spec.save_intermediates)
        preview = out.with_name(out.stem + "_preview.png") if spec.preview else None
        check_outputs(out, spec.fmt, textured, (image, *spec.guidance.files), intermediates, preview)  # every output, before any work
        result = rec.run(image, spec.guidance, spec.options)
        path, used = result.save_mesh(out, spec.fmt, texture=textured, up=spec.up)
        if intermediates is not None:
            result.save_intermediates(intermediates)
        if preview is not None:
            result.save_preview(preview, texture=textured)
        say(_result_line(image, path, used, result, textured))
        if result.mask_warning:
            fix = "check mask_in_photo.png in the intermediates folder and give it back corrected with --mask" if spec.save_intermediates \
                else "look at the mask with --save-intermediates DIR (mask_in_photo.png) and give a corrected one with --mask"
            fix += ", or guide it with --box and --strokes"
            say(f"{spec.prog}: warning: {image}: doubtful mask: {result.mask_warning}; {fix}", err=True)
        return True
    except Exception as exc:  # one bad input must not stop the others
        code = error_code(exc)
        msg = _one_line(exc) if code != "internal" else f"internal error: {exc.__class__.__name__}: {_one_line(exc)}"
        if str(image) not in msg:
            msg = f"{image}: {msg}"
        say(f"{spec.prog}: error: {msg} [{code}]", err=True)
        return False


def _result_line(image: Path, path: Path, fmt: str, result, textured: bool) -> str:
    """The one line ``genre reconstruct`` prints for a written mesh: its file, size, parts, colour, mask and time."""
    clean = result.clean
    shape = f"{clean.parts} part{'s' if clean.parts != 1 else ''}{', watertight' if clean.watertight else ', not watertight'}"
    if clean.parts_before != clean.parts:
        shape += f"; {clean.parts_before - clean.parts} small or inner parts dropped"
    if result.primitive is not None:
        shape += f"; a fitted {result.primitive}"
    colour = ", coloured from the photo" if textured else ""
    axis = ", +z up" if result.up == "z" else ""
    total = sum(result.timings.values())
    return (f"{image} -> {path} ({fmt}{axis}, {len(result.vertices)} vertices, {len(result.faces)} faces, {shape}{colour}, "
            f"mask: {result.mask_source}, {total:.2f} s)")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
