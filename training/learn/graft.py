"""``genre train graft``: one weights file made of another's nets, net by net.

A stage run's files hold every net, the ones it froze included: a depth-stage
run started from the installed file carries that file's inpainting net and
refiner, possibly older than the installed ones by the time it is read.  A
candidate is then the installed file with the run's depth net in its place:

    genre train graft default --depth-from RUN/depth/snapshots/step_0010000.safetensors --out C.safetensors --storage int8

The base's config (its mesh settings among it) and its ``extra`` record are
kept, with a ``grafted`` entry naming each donor; each donor brings its net's
widths too (:func:`~genre_backend.nets.model.with_depth_net_of`,
:func:`~genre_backend.nets.model.with_inpaint_net_of`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from genre_backend.arguments import add_out, add_storage
from genre_backend.nets.model import load_model, save_model, with_depth_net_of, with_inpaint_net_of
from genre_backend.weights_file import WeightsError, resolve_weights, weights_extra

__all__ = ["GRAFTS", "main"]

# net → (option, the function that puts a donor's net of that kind in a model)
GRAFTS = {"depth_net": ("--depth-from", with_depth_net_of), "inpaint_net": ("--inpaint-from", with_inpaint_net_of)}


def main(argv: list[str] | None = None, prog: str = "genre train graft") -> int:
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    ap.add_argument("base", help="the weights the other nets and the settings come from: a shipped name or a file")
    for net, (flag, _) in GRAFTS.items():
        ap.add_argument(flag, dest=net, metavar="W", help=f"the weights whose {net.replace('_', ' ')} replaces the base's")
    add_out(ap, required=True, help="the grafted weights file (.safetensors; a .json beside it)")
    add_storage(ap)
    args = ap.parse_args(argv)
    donors = {net: getattr(args, net) for net in GRAFTS if getattr(args, net)}
    if not donors:
        ap.error(f"name a donor: {' or '.join(flag for flag, _ in GRAFTS.values())}")
    try:
        base = resolve_weights(args.base)
        files = {net: resolve_weights(w) for net, w in donors.items()}
        if Path(args.out).resolve() in {base.resolve(), *(f.resolve() for f in files.values())}:
            ap.error("--out is one of the input files")
        model, extra = load_model(base), weights_extra(base)
        for net, path in files.items():
            model = GRAFTS[net][1](model, load_model(path))
    except (WeightsError, ValueError) as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    extra = {**extra, "grafted": {"base": str(base), **{net: str(path) for net, path in files.items()}}}
    save_model(model, args.out, extra, storage=args.storage)
    print(f"{base.name} with {', '.join(f'the {net} of {path}' for net, path in files.items())} -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
