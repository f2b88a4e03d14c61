"""Install trained weights as the backend's default, with the threshold chosen on seen-test data.

    python -m training.eval.install --weights runs/default/joint/best.safetensors \\
        --thresholds results/default/thresholds.json --out genre_backend/weights/default.safetensors

The isosurface threshold stored in the installed weights' config
(``geometry.default_threshold``, what ``genre reconstruct`` and ``genre
serve`` use unless asked otherwise) becomes GenRe's threshold chosen by
``genre eval`` on seen-test views only, never tuned on unseen classes:
``thresholds.json`` → ``product`` → ``GenRe`` (the lowest CD among
thresholds whose meshes are closed in 90 % of the views) when the run has
it, else → ``seen`` → ``GenRe`` (the lowest CD).  Writes the
``.safetensors`` and its ``.json`` atomically (:func:`genre_backend.nets.model.save_model`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from genre_backend.nets.model import WeightsError, load_model, save_model

__all__ = ["install", "main"]


def install(weights: Path, thresholds: Path, out: Path) -> float:
    """Copy ``weights`` to ``out`` with the seen-test threshold of GenRe; returns that threshold."""
    chosen = json.loads(Path(thresholds).read_text())
    try:
        t = float(chosen["product"]["GenRe"][0]) if "GenRe" in chosen.get("product", {}) else float(chosen["seen"]["GenRe"])
    except (KeyError, TypeError, ValueError, IndexError):
        raise ValueError(f"{thresholds}: no seen-test threshold for GenRe (run 'genre eval' with seen-test views)") from None
    if not 0.0 < t < 1.0:
        raise ValueError(f"{thresholds}: GenRe's threshold {t} is not in (0, 1)")
    model = load_model(weights)
    config = model.config
    model.config = dataclasses.replace(config, geometry=dataclasses.replace(config.geometry, default_threshold=t))
    out.parent.mkdir(parents=True, exist_ok=True)
    save_model(model, out, {"source": str(weights), "threshold_from": str(thresholds)})
    return t


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m training.eval.install", description=__doc__.split("\n\n")[0])
    p.add_argument("--weights", required=True, type=Path)
    p.add_argument("--thresholds", required=True, type=Path)
    p.add_argument("--out", required=True, type=Path)
    args = p.parse_args(argv)
    try:
        t = install(args.weights, args.thresholds, args.out)
    except (ValueError, WeightsError, OSError) as exc:
        print(f"install: {exc}", file=sys.stderr)
        return 1
    print(f"installed {args.weights} as {args.out} (default threshold {t:.2f}, chosen on seen-test views)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
