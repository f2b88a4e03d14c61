#!/usr/bin/env python3
"""The add-on in a real GUI Blender: ``make e2e`` (or ``python tests/addon/e2e/run_gui_e2e.py``).

Builds the add-on zips, takes the shipped default weights and the bundled
example photo (or ``--weights``/``--photo``; without shipped weights it
trains tiny test weights with the project's own training code), then starts the
system's ``blender`` (Debian's 3.4.1 here) under ``xvfb-run`` with
``blender_gui_script.py``: the legacy zip is installed, Reconstruct is
pressed, the modal operator runs on its timer against a real ``genre serve``
(this project's ``.venv`` Python), and screenshots are saved.  Prints the
result (including the seconds from the button press to the mesh in the
scene) and exits non-zero on failure.  Outputs go to ``out/e2e/`` by default.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]
SCRIPT = Path(__file__).resolve().with_name("blender_gui_script.py")
# Training steps (depth, inpaint, refine) of the e2e weights: enough for the tiny box to look like a box.
E2E_STEPS = (40, 40, 80)


def missing_tools() -> str:
    """Why the GUI run cannot happen here ('' when it can)."""
    missing = [t for t in ("blender", "xvfb-run") if shutil.which(t) is None]
    if missing:
        return f"{' and '.join(missing)} not installed (Debian: apt-get install blender xvfb xauth)"
    return ""


def run(out: Path, weights: Path, photo: Path, zip_path: Path, timeout: float = 300.0, event_simulate: bool = True,
        mask: Path | None = None) -> dict:
    """One GUI Blender session; returns blender_gui_script.py's result (see result.json)."""
    out.mkdir(parents=True, exist_ok=True)
    for name in ("result.json", "viewport_with_panel.png", "through_camera.png", "side.png", "panel_while_running.png"):
        (out / name).unlink(missing_ok=True)
    with tempfile.TemporaryDirectory(prefix="genre-e2e-") as tmp:
        tmp = Path(tmp)
        args = {"out": str(out), "zip": str(zip_path), "weights": str(weights), "photo": str(photo),
                "backend_python": str(Path(sys.executable)), "timeout": timeout, "mask": str(mask) if mask else ""}
        args["event_simulate"] = event_simulate
        (tmp / "args.json").write_text(json.dumps(args))
        env = dict(os.environ)
        for var, sub in (("BLENDER_USER_CONFIG", "config"), ("BLENDER_USER_SCRIPTS", "scripts"),
                         ("BLENDER_USER_DATAFILES", "datafiles"), ("BLENDER_USER_RESOURCES", "resources"),
                         ("XDG_CACHE_HOME", "cache"), ("XDG_CONFIG_HOME", "xdg-config"), ("TMPDIR", "tmp")):
            env[var] = str(tmp / sub)
            (tmp / sub).mkdir()
        # A .blend given on the command line keeps the splash screen away; event simulation lets the
        # script switch the sidebar to the GenRe tab (Ctrl+Wheel), since Blender 3.4 has no API for it.
        blank = tmp / "blank.blend"
        subprocess.run(["blender", "-b", "--factory-startup", "-noaudio", "--python-expr",
                        f"import bpy; bpy.ops.wm.save_as_mainfile(filepath={str(blank)!r})"],
                       env=env, capture_output=True, check=True, timeout=120)
        cmd_extra = ["--enable-event-simulate"] if event_simulate else []
        cmd = ["xvfb-run", "-a", "-s", "-screen 0 1600x1000x24", "blender", "--factory-startup", "-noaudio", "--window-geometry", "0", "0", "1600", "1000", *cmd_extra, str(blank), "--python", str(SCRIPT), "--", str(tmp / "args.json")]
        t0 = time.monotonic()
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout + 120)
        wall = time.monotonic() - t0
        (out / "blender.log").write_text(proc.stdout + "\n--- stderr ---\n" + proc.stderr)
        result_file = out / "result.json"
        if not result_file.is_file():
            raise RuntimeError(f"Blender exited with {proc.returncode} without a result; see {out / 'blender.log'}:\n"
                               f"{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
        result = json.loads(result_file.read_text())
        result["blender_wall_s"] = round(wall, 2)
        result["blender_returncode"] = proc.returncode
        result_file.write_text(json.dumps(result, indent=2))
        return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(REPO / "out" / "e2e"))
    parser.add_argument("--weights", help="weights file (default: the shipped default weights, else tiny test weights trained now)")
    parser.add_argument("--photo", help="photo (default: examples/sofa.png with the shipped weights, else the tiny data's box)")
    parser.add_argument("--mask", help="mask file for the photo (white object on black)")
    parser.add_argument("--timeout", type=float, default=300.0)
    args = parser.parse_args(argv)
    why = missing_tools()
    if why:
        print(f"e2e: cannot run: {why}", file=sys.stderr)
        return 2
    t0 = time.monotonic()
    sys.path[:0] = [str(REPO), str(REPO / "tests")]
    import build_addon

    out = Path(args.out)
    built = build_addon.build(out / "dist")
    shipped = REPO / "genre_backend" / "weights" / "default.safetensors", REPO / "examples" / "sofa.png"
    if args.weights and args.photo:
        weights, photo = Path(args.weights), Path(args.photo)
    elif not args.weights and not args.photo and all(p.is_file() for p in shipped):
        weights, photo = shipped  # the shipped default weights on the bundled example photo
    else:
        from support.addon import make_photo, make_weights

        data = out / "weights"
        weights = data / "train" / "refine" / "final.safetensors"
        if not weights.is_file():
            print(f"e2e: training tiny test weights once, {E2E_STEPS} steps (a few minutes; cached in {data})…", flush=True)
            shutil.rmtree(data, ignore_errors=True)
            data.mkdir(parents=True)
            weights = make_weights(data, steps=E2E_STEPS, lr=3e-3)
        photo = Path(args.photo) if args.photo else make_photo(data)
    prepared = time.monotonic() - t0
    result = run(out, weights, photo, built["legacy"], args.timeout, mask=Path(args.mask) if args.mask else None)
    result["prepare_s"] = round(prepared, 2)
    (out / "result.json").write_text(json.dumps(result, indent=2))
    print(json.dumps({k: v for k, v in result.items() if k != "log"}, indent=2))
    ok = result.get("exit_code") == 0 and "press_to_mesh_s" in result
    print(f"e2e: {'OK' if ok else 'FAILED'}: button press to mesh in the scene {result.get('press_to_mesh_s')} s; "
          f"Blender run {result['blender_wall_s']} s; screenshot {result.get('screenshot')}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
