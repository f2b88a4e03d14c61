"""Install trained weights as one of the backend's shipped weights, with the threshold chosen on seen-test data.

    python -m training.eval.install --weights $GENRE_HOME/runs/default/joint/best.safetensors \\
        --thresholds results/default/thresholds.json --name protocol

``--name`` picks which shipped weights the file becomes
(``genre_backend/weights/NAME.safetensors`` + ``NAME.json``): ``protocol``
(the default here: the research weights, trained on the seen classes only,
behind every Table-1 number) or ``default`` (the product model for users,
trained on everything).  ``--out FILE`` writes elsewhere instead (still
tagged with ``--name``).  The name is stored in the weights' ``extra``
(``"model": NAME``), in the file's metadata and its JSON sidecar.  While
the shipped ``default`` is still the interim copy of ``protocol`` (its
``extra`` says ``"copy_of": "protocol"``), installing ``protocol`` writes
that copy again, so the two never drift apart before the product model
exists.

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

from genre_backend.weights_file import DEFAULT_WEIGHTS_NAME, PROTOCOL_WEIGHTS_NAME, WEIGHTS_NAMES, named_weights
from genre_backend.nets.model import WeightsError, load_model, save_model

__all__ = ["install", "main"]


def _is_interim_copy_of_protocol(path: Path) -> bool:
    try:
        extra = json.loads(path.with_suffix(".json").read_text()).get("extra") or {}
    except (OSError, ValueError, AttributeError):
        return False
    return extra.get("copy_of") == PROTOCOL_WEIGHTS_NAME


# where each mesh setting install stores was chosen (the weights' extra.SETTING_from)
_SETTING_FROM = {
    "hole_closing": "scripts/hole_closing.py on seen-test views",
    "silhouette_carve": "chosen on seen-test views (results/decisions.md)",
    "visible_fusion": "scripts/visible_fusion.py on seen-test views",
    "primitive_snap": "scripts/primitive_snap.py on training-split views (results/decisions.md)",
    "test_time_mirror": "results/decisions.md",
    "pit_sealing": "scripts/visible_fusion.py --pit-sealing (results/decisions.md)",
    "sph_hit_probability": "scripts/stage_errors.py --hit-levels on seen-test views",
}


def _threshold(thresholds: Path | float) -> float:
    """GenRe's level: the number itself, or from a ``thresholds.json`` (the product split's first, else seen-test's)."""
    if isinstance(thresholds, (int, float)):
        chosen = {"seen": {"GenRe": float(thresholds)}}
    else:
        chosen = json.loads(Path(thresholds).read_text())
    try:
        t = float(chosen["product"]["GenRe"][0]) if "GenRe" in chosen.get("product", {}) else float(chosen["seen"]["GenRe"])
    except (KeyError, TypeError, ValueError, IndexError):
        raise ValueError(f"{thresholds}: no seen-test threshold for GenRe (run 'genre eval' with seen-test views)") from None
    if not 0.0 < t < 1.0:
        raise ValueError(f"{thresholds}: GenRe's threshold {t} is not in (0, 1)")
    return t


def install(weights: Path, thresholds: Path | float, out: Path | None = None, *, name: str = PROTOCOL_WEIGHTS_NAME,
            hole_closing: int | None = None, sph_hit_probability: float | None = None,
            silhouette_carve: bool | None = None, visible_fusion: bool | None = None,
            primitive_snap: float | None = None, test_time_mirror: bool | None = None, half: bool = False,
            pit_sealing: int | None = None, settings: dict | None = None) -> float:
    """Copy ``weights`` to ``out`` (default: the shipped weights ``name``) with the seen-test threshold of GenRe.

    ``thresholds``: a ``thresholds.json`` of ``genre eval`` on seen-test views, or the level itself
    (the product model keeps the level of the weights it started from: results/decisions.md).
    Returns that threshold.  ``name`` (``protocol`` or ``default``) is stored as ``extra.model``.
    ``hole_closing``: the mesh setting ``geometry.hole_closing`` to store (chosen on seen-test views by
    ``scripts/hole_closing.py``); None keeps the weights' own.
    ``sph_hit_probability``: the hit-head inpainting net's decision level to store
    (``geometry.sph_hit_probability``, chosen on seen-test views by ``scripts/stage_errors.py --hit-levels``);
    None keeps the weights' own.  ``silhouette_carve``: store ``geometry.silhouette_carve`` (carve the
    refiner's output to the mask's outline; chosen on seen-test views); None keeps the weights' own.
    ``visible_fusion``: store ``geometry.visible_fusion`` (fill the holes in the visible face from the
    depth map; chosen on seen-test views by ``scripts/visible_fusion.py``); None keeps the weights' own.
    ``primitive_snap``: store ``geometry.primitive_snap`` (the regular-shape stage's tolerance, 0: off; chosen
    on training-split views by ``scripts/primitive_snap.py``); None keeps the weights' own.
    ``test_time_mirror``: store ``geometry.test_time_mirror`` (average each view with its mirror image; turned on
    only by the rule in results/decisions.md); None keeps the weights' own.
    ``pit_sealing``: store ``geometry.pit_sealing`` (voxels; the widest pit in the visible front sealed, 0: off;
    chosen by ``scripts/visible_fusion.py --pit-sealing`` and the rule in results/decisions.md); None keeps
    the weights' own.
    ``half``: store the weights as float16, the batch-norm statistics as float32 (``save_model(half=True)``:
    half the file, read back into float32).
    ``settings``: any other ``geometry`` fields to store, by name (``--set NAME=JSON``), checked by the config.
    """
    if name not in WEIGHTS_NAMES:
        raise ValueError(f"unknown weights name {name!r}: choose {' or '.join(WEIGHTS_NAMES)}")
    t = _threshold(thresholds)
    model = load_model(weights)
    config = model.config
    geometry = dataclasses.replace(config.geometry, default_threshold=t)
    if hole_closing is not None:
        geometry = dataclasses.replace(geometry, hole_closing=int(hole_closing))  # (validated by the config)
    if silhouette_carve is not None:
        geometry = dataclasses.replace(geometry, silhouette_carve=bool(silhouette_carve))
    if visible_fusion is not None:
        geometry = dataclasses.replace(geometry, visible_fusion=bool(visible_fusion))
    if primitive_snap is not None:
        if name == PROTOCOL_WEIGHTS_NAME and primitive_snap > 0:
            raise ValueError("the protocol weights never snap to regular shapes: Table 1 is GenRe alone")
        geometry = dataclasses.replace(geometry, primitive_snap=float(primitive_snap))
    if test_time_mirror is not None:
        geometry = dataclasses.replace(geometry, test_time_mirror=bool(test_time_mirror))
    if pit_sealing is not None:
        geometry = dataclasses.replace(geometry, pit_sealing=pit_sealing)  # (validated by the config)
    if sph_hit_probability is not None:
        if config.network.inpaint_head != "hit":
            raise ValueError(f"{weights}: --sph-hit-probability needs hit-head weights (network.inpaint_head = 'hit'), "
                             f"these have {config.network.inpaint_head!r}")
        geometry = dataclasses.replace(geometry, sph_hit_probability=float(sph_hit_probability))
    if settings:
        known = {f.name for f in dataclasses.fields(geometry)}
        unknown = sorted(set(settings) - known)
        if unknown:
            raise ValueError(f"--set: unknown geometry settings {unknown}")
        geometry = dataclasses.replace(geometry, **settings)  # (validated by the config)
    model.config = dataclasses.replace(config, geometry=geometry)
    shipped = named_weights(name)
    out = Path(out) if out is not None else shipped
    out.parent.mkdir(parents=True, exist_ok=True)
    given = {"hole_closing": hole_closing, "silhouette_carve": silhouette_carve, "visible_fusion": visible_fusion,
             "primitive_snap": primitive_snap, "test_time_mirror": test_time_mirror, "pit_sealing": pit_sealing,
             "sph_hit_probability": sph_hit_probability, **(settings or {})}
    extra = {"source": str(weights), "threshold_from": str(thresholds), "model": name,
             **{f"{k}_from": _SETTING_FROM.get(k, "results/decisions.md") for k, v in given.items() if v is not None}}
    save_model(model, out, extra, half=half)
    if name == PROTOCOL_WEIGHTS_NAME and out.resolve() == shipped.resolve():
        interim = named_weights(DEFAULT_WEIGHTS_NAME)
        if interim.is_file() and _is_interim_copy_of_protocol(interim):
            save_model(model, interim, {**extra, "model": DEFAULT_WEIGHTS_NAME, "copy_of": PROTOCOL_WEIGHTS_NAME})
    return t


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m training.eval.install", description=__doc__.split("\n\n")[0])
    p.add_argument("--weights", required=True, type=Path)
    level = p.add_mutually_exclusive_group(required=True)
    level.add_argument("--thresholds", type=Path, help="thresholds.json of 'genre eval' on seen-test views")
    level.add_argument("--threshold", type=float, help="the level itself (the product model: that of the weights it started from)")
    p.add_argument("--name", choices=list(WEIGHTS_NAMES), default=PROTOCOL_WEIGHTS_NAME,
                   help="which shipped weights these become: protocol (default: the research weights, seen classes only) "
                        "or default (the product model, trained on everything)")
    p.add_argument("--out", type=Path, default=None, help="write here instead of genre_backend/weights/NAME.safetensors")
    p.add_argument("--hole-closing", type=int, default=None, metavar="K",
                   help="store geometry.hole_closing = K (voxels; chosen by scripts/hole_closing.py on seen-test views); "
                        "default: the weights' own")
    p.add_argument("--sph-hit-probability", type=float, default=None, metavar="P",
                   help="store geometry.sph_hit_probability = P (the hit head's decision level, chosen by "
                        "scripts/stage_errors.py --hit-levels on seen-test views); default: the weights' own")
    p.add_argument("--silhouette-carve", action=argparse.BooleanOptionalAction, default=None,
                   help="store geometry.silhouette_carve (carve the output to the mask's outline; chosen on seen-test "
                        "views); default: the weights' own")
    p.add_argument("--visible-fusion", action=argparse.BooleanOptionalAction, default=None,
                   help="store geometry.visible_fusion (fill the holes in the visible face from the depth map; chosen by "
                        "scripts/visible_fusion.py on seen-test views); default: the weights' own")
    p.add_argument("--primitive-snap", type=float, default=None, metavar="TOL",
                   help="store geometry.primitive_snap = TOL (replace the mesh by a fitted box, cylinder, cone, torus or "
                        "ellipsoid within TOL of its size; 0: off; chosen by scripts/primitive_snap.py on training-split "
                        "views; default weights only); default: the weights' own")
    p.add_argument("--test-time-mirror", action=argparse.BooleanOptionalAction, default=None,
                   help="store geometry.test_time_mirror (average each view with its mirror image; twice the nets' "
                        "time; by the rule in results/decisions.md); default: the weights' own")
    p.add_argument("--pit-sealing", type=int, default=None, metavar="K",
                   help="store geometry.pit_sealing = K (voxels: seal the narrow pits in the visible front up to about 2K "
                        "across; 0: off; chosen by scripts/visible_fusion.py --pit-sealing); default: the weights' own")
    p.add_argument("--fp16", action="store_true",
                   help="store the weights as float16 (half the file; inference still computes in float32; check the "
                        "scores stay within 1e-3 CD of the float32 file's)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=JSON",
                   help="store another geometry setting, e.g. --set sph_keep_seen=true (repeatable)")
    args = p.parse_args(argv)
    settings = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        try:
            if not sep:
                raise ValueError("expected NAME=JSON")
            settings[key.strip()] = json.loads(value)
        except ValueError as exc:
            p.error(f"--set {item!r}: {exc}")
    out = args.out if args.out is not None else named_weights(args.name)
    interim = named_weights(DEFAULT_WEIGHTS_NAME)
    refresh = (args.name == PROTOCOL_WEIGHTS_NAME and out.resolve() == named_weights(PROTOCOL_WEIGHTS_NAME).resolve()
               and interim.is_file() and _is_interim_copy_of_protocol(interim))
    try:
        t = install(args.weights, args.thresholds if args.thresholds is not None else args.threshold, out, name=args.name,
                    hole_closing=args.hole_closing, sph_hit_probability=args.sph_hit_probability,
                    silhouette_carve=args.silhouette_carve, visible_fusion=args.visible_fusion,
                    primitive_snap=args.primitive_snap, test_time_mirror=args.test_time_mirror, half=args.fp16,
                    pit_sealing=args.pit_sealing, settings=settings)
    except (ValueError, WeightsError, OSError) as exc:
        print(f"install: {exc}", file=sys.stderr)
        return 1
    print(f"installed {args.weights} as {out} (weights '{args.name}', default threshold {t:.2f}"
          + (", chosen on seen-test views)" if args.thresholds is not None else ", as given)"))
    if refresh:
        print(f"also wrote {interim}: the interim 'default' weights stay a copy of 'protocol' until the product model is installed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
