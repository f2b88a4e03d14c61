"""One weights file from two: the depth net of DEPTH (with its widths), the inpainting net and refiner of NETS (same geometry and camera).

The start of a bank session whose depth net was trained apart (docs/training.md, "Training on the depth net's own
depth")::

    python scripts/splice_weights.py $H/runs/up88/depth/best.safetensors $H/runs/session/both/weights.safetensors OUT
"""

from __future__ import annotations

import dataclasses
import sys

from genre_backend.nets.model import GenRe, load_model, save_model


def main(argv: list[str]) -> int:
    if len(argv) != 3:
        print(__doc__, file=sys.stderr)
        return 2
    depth, nets, out = argv
    a, b = load_model(depth), load_model(nets)
    if a.config.geometry != b.config.geometry or a.config.camera != b.config.camera:
        print("the two files differ in geometry or camera: their nets do not fit together", file=sys.stderr)
        return 1
    # the depth net's own sizes come with it (a widened depth net: training/learn/widen.py)
    depth_fields = {f: getattr(a.config.network, f) for f in ("depth_widths", "depth_decoder_blocks", "depth_output_scale")}
    spliced = GenRe(dataclasses.replace(b.config, network=dataclasses.replace(b.config.network, **depth_fields)))
    spliced.load_state_dict({**b.state_dict(), **{f"depth_net.{k}": v for k, v in a.depth_net.state_dict().items()}})
    save_model(spliced, out, {"spliced": {"depth_net": depth, "inpaint_net+refiner": nets}})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
