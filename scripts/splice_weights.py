"""One weights file from two: the depth net of DEPTH, the inpainting net and refiner of NETS (same geometry and camera).

The start of a bank session whose depth net was trained apart (docs/training.md, "Training on the depth net's own
depth")::

    python scripts/splice_weights.py $H/runs/up88/depth/best.safetensors $H/runs/session/both/weights.safetensors OUT
"""

from __future__ import annotations

import sys

from genre_backend.nets.model import load_model, save_model


def main(argv: list[str]) -> int:
    if len(argv) != 3:
        print(__doc__, file=sys.stderr)
        return 2
    depth, nets, out = argv
    a, b = load_model(depth), load_model(nets)
    if a.config.geometry != b.config.geometry or a.config.camera != b.config.camera:
        print("the two files differ in geometry or camera: their nets do not fit together", file=sys.stderr)
        return 1
    b.depth_net.load_state_dict(a.depth_net.state_dict())
    save_model(b, out, {"spliced": {"depth_net": depth, "inpaint_net+refiner": nets}})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
