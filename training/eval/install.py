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

from genre_backend.config import SETTINGS
from genre_backend.weights_file import DEFAULT_WEIGHTS_NAME, PROTOCOL_WEIGHTS_NAME, WEIGHTS_NAMES, named_weights
from genre_backend.nets.model import WeightsError, load_model, save_model
from genre_backend.arguments import add_out, add_storage, add_weights

__all__ = ["install", "main"]


def _is_interim_copy_of_protocol(path: Path) -> bool:
    try:
        extra = json.loads(path.with_suffix(".json").read_text()).get("extra") or {}
    except (OSError, ValueError, AttributeError):
        return False
    return extra.get("copy_of") == PROTOCOL_WEIGHTS_NAME


# how a setting that is no mesh option was chosen (a mesh option's own field says it: Option.chosen)
_SETTING_FROM = {"sph_hit_probability": "scripts/stage_errors.py --hit-levels on seen-test views"}


def _chosen(name: str) -> str:
    """How the stored setting ``name`` was chosen (the weights' ``extra.NAME_from``)."""
    spec = next((s for s in SETTINGS if s.weights == name), None)
    return (spec.chosen if spec is not None else "") or _SETTING_FROM.get(name, "results/decisions.md")


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
            storage: str = "float32", **settings) -> float:
    """Copy ``weights`` to ``out`` (default: the shipped weights ``name``) with the seen-test threshold of GenRe.

    ``thresholds``: a ``thresholds.json`` of ``genre eval`` on seen-test views, or the level itself
    (the product model keeps the level of the weights it started from: results/decisions.md).
    Returns that threshold.  ``name`` (``protocol`` or ``default``) is stored as ``extra.model``.
    ``settings``: ``geometry`` fields to store, by name (``hole_closing=2``, ``sph_keep_seen=True``; ``None``: the
    weights' own), checked by the config; each is stored with how it was chosen (``extra.NAME_from``: a mesh option's
    field says it).  ``sph_hit_probability`` needs hit-head weights; the protocol weights never snap to regular shapes.
    ``storage``: how the file stores the weights (``float16``: half the file; ``int8``: about a quarter;
    :func:`~genre_backend.nets.model.save_model`), read back into float32.
    """
    if name not in WEIGHTS_NAMES:
        raise ValueError(f"unknown weights name {name!r}: choose {' or '.join(WEIGHTS_NAMES)}")
    t = _threshold(thresholds)
    model = load_model(weights)
    config = model.config
    given = {k: v for k, v in settings.items() if v is not None}
    unknown = sorted(set(given) - {f.name for f in dataclasses.fields(config.geometry)})
    if unknown:
        raise ValueError(f"--set: unknown geometry settings {unknown}")
    snap = given.get("primitive_snap", 0)
    if name == PROTOCOL_WEIGHTS_NAME and not isinstance(snap, bool) and isinstance(snap, (int, float)) and snap > 0:
        raise ValueError("the protocol weights never snap to regular shapes: Table 1 is GenRe alone")
    if "sph_hit_probability" in given and config.network.inpaint_head != "hit":
        raise ValueError(f"{weights}: --sph-hit-probability needs hit-head weights (network.inpaint_head = 'hit'), "
                         f"these have {config.network.inpaint_head!r}")
    geometry = dataclasses.replace(config.geometry, default_threshold=t, **given)  # (validated by the config)
    model.config = dataclasses.replace(config, geometry=geometry)
    shipped = named_weights(name)
    out = Path(out) if out is not None else shipped
    out.parent.mkdir(parents=True, exist_ok=True)
    extra = {"source": str(weights), "threshold_from": str(thresholds), "model": name,
             **{f"{k}_from": _chosen(k) for k in given}}
    save_model(model, out, extra, storage=storage)
    if name == PROTOCOL_WEIGHTS_NAME and out.resolve() == shipped.resolve():
        interim = named_weights(DEFAULT_WEIGHTS_NAME)
        if interim.is_file() and _is_interim_copy_of_protocol(interim):
            save_model(model, interim, {**extra, "model": DEFAULT_WEIGHTS_NAME, "copy_of": PROTOCOL_WEIGHTS_NAME})
    return t


def _setting_flags(p: argparse.ArgumentParser) -> None:
    """A flag for each mesh option the weights store (``--hole-closing K``, ``--visible-fusion/--no-visible-fusion``
    …), made from its field in ``GeometryConfig``; the threshold is ``--thresholds``/``--threshold``'s."""
    for spec in SETTINGS:
        if spec.weights == "default_threshold":
            continue
        text = f"store geometry.{spec.weights} ({spec.help}; chosen: {spec.chosen}); default: the weights' own"
        flag = "--" + spec.weights.replace("_", "-")
        if spec.kind == "bool":
            p.add_argument(flag, action=argparse.BooleanOptionalAction, default=None, help=text.replace("%", "%%"))
        else:
            p.add_argument(flag, type=float if spec.kind == "float" else int, default=None, metavar=spec.metavar,
                           help=f"{text}; {spec.expected()}".replace("%", "%%"))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m training.eval.install", description=__doc__.split("\n\n")[0])
    add_weights(p, required=True, type=Path, help="the trained weights file to install")
    level = p.add_mutually_exclusive_group(required=True)
    level.add_argument("--thresholds", type=Path, help="thresholds.json of 'genre eval' on seen-test views")
    level.add_argument("--threshold", type=float, help="the level itself (the product model: that of the weights it started from)")
    p.add_argument("--name", choices=list(WEIGHTS_NAMES), default=PROTOCOL_WEIGHTS_NAME,
                   help="which shipped weights these become: protocol (default: the research weights, seen classes only) "
                        "or default (the product model, trained on everything)")
    add_out(p, type=Path, help="write here instead of genre_backend/weights/NAME.safetensors")
    _setting_flags(p)
    p.add_argument("--sph-hit-probability", type=float, default=None, metavar="P",
                   help="store geometry.sph_hit_probability = P (the hit head's decision level, chosen by "
                        "scripts/stage_errors.py --hit-levels on seen-test views); default: the weights' own")
    add_storage(p)  # (check the scores stay within 1e-3 CD of the float32 file's)
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
        given = {spec.weights: getattr(args, spec.weights) for spec in SETTINGS if spec.weights != "default_threshold"}
        t = install(args.weights, args.thresholds if args.thresholds is not None else args.threshold, out, name=args.name,
                    storage=args.storage, **{**given, "sph_hit_probability": args.sph_hit_probability, **settings})
    except (ValueError, WeightsError, OSError) as exc:
        print(f"install: {exc}", file=sys.stderr)
        return 1
    print(f"installed {args.weights} as {out} (weights '{args.name}', default threshold {t:.2f}"
          + (", chosen on seen-test views)" if args.thresholds is not None else ", as given)"))
    if refresh:
        print(f"also wrote {interim}: the interim 'default' weights stay a copy of 'protocol' until the product model is installed")
    if out.resolve() == interim.resolve() or refresh:  # the add-on shows the default's settings before its backend starts
        print("the add-on's blender_addon/options_schema.json holds the default weights' settings: "
              "run python build_addon.py --schema (the build refuses a stale one)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
