"""The add-on in a real GUI Blender under Xvfb: the modal operator's timer runs a reconstruction end to end.

Uses the system's ``blender`` (Debian's 3.4.1 package here, with its own
Python 3.11) and ``xvfb-run``; skipped when either is missing.  The backend
is a real ``genre serve`` run by this project's Python with weights trained
in the test session (see ``tests/addon/conftest.py``).  About 1.5 minutes on a
2-core machine, most of it Blender starting under software OpenGL.  ``make
e2e`` runs the same with better-trained weights and keeps the screenshots in
``out/e2e/``.
"""

import importlib.util
import json
from pathlib import Path

import pytest

from support.addon import REPO

_spec = importlib.util.spec_from_file_location("run_gui_e2e", REPO / "tests" / "addon" / "e2e" / "run_gui_e2e.py")
run_gui_e2e = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(run_gui_e2e)

_missing = run_gui_e2e.missing_tools()


@pytest.mark.slow
@pytest.mark.blender
@pytest.mark.skipif(bool(_missing), reason=f"no GUI Blender here: {_missing}")
def test_gui_blender_runs_the_modal_operator_end_to_end(built, trained, tmp_path):
    weights, photo = trained
    result = run_gui_e2e.run(tmp_path / "e2e", weights, photo, built["legacy"], timeout=120)
    assert result["exit_code"] == 0, json.dumps(result, indent=2)
    assert result["invoke"] == ["RUNNING_MODAL"]  # the button starts a modal operator; the timer finishes it
    assert result["ticks"] >= 1
    assert result["press_to_mesh_s"] > 0 and result["warm_press_to_mesh_s"] > 0
    mesh = result["mesh"]
    assert mesh["name"] == "box.001" and mesh["camera"] == ["box.001 camera"]
    assert f"{mesh['vertices']:,} vertices, {mesh['faces']:,} faces" in result["message"]
    for key in ("screenshot", "camera_screenshot"):
        png = Path(result[key])
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000


@pytest.mark.slow
@pytest.mark.blender
@pytest.mark.skipif(bool(_missing), reason=f"no GUI Blender here: {_missing}")
def test_annotation_points_are_image_view_space_in_a_drawn_editor(tmp_path):
    """The Annotate tool in a drawn Image Editor stores points 0-1 over the image, y up: what the add-on assumes."""
    import os
    import subprocess

    args = {"photo": str(REPO / "examples" / "photos" / "robin.jpg"), "out": str(tmp_path / "out.json"),
            "annotations_py": str(REPO / "blender_addon" / "annotations.py")}
    (tmp_path / "args.json").write_text(json.dumps(args))
    env = {**os.environ, "BLENDER_USER_RESOURCES": str(tmp_path / "user"), "XDG_CACHE_HOME": str(tmp_path / "cache")}
    subprocess.run(["xvfb-run", "-a", "-s", "-screen 0 1280x800x24", "blender", "--factory-startup", "-noaudio", "--python",
                    str(REPO / "tests" / "addon" / "e2e" / "annotation_coords.py"), "--", str(tmp_path / "args.json")],
                   env=env, cwd=tmp_path, capture_output=True, timeout=240)
    r = json.loads((tmp_path / "out.json").read_text())
    assert "error" not in r, r["error"]
    assert r["op"] == ["FINISHED"] and r["size"] == [380, 254] and r["found_same"] is True
    (stroke,) = r["co"]
    # the ends where they were drawn (a region pixel is 1/zoom of an image pixel: within 0.01); the middle is smoothed
    assert stroke[0][:2] == pytest.approx([0.25, 0.3], abs=0.01) and stroke[-1][:2] == pytest.approx([0.7, 0.8], abs=0.01)
    (line,) = r["object_pixels"]  # the add-on's photo pixels: x right, y down
    assert line[0] == pytest.approx([0.25 * 380, 0.7 * 254], abs=4) and line[-1] == pytest.approx([0.7 * 380, 0.2 * 254], abs=4)


@pytest.mark.slow
@pytest.mark.network  # (the runtime's wheels, pip-downloaded once into the GenRe home)
@pytest.mark.skipif(bool(_missing), reason=f"no GUI Blender here: {_missing}")
def test_gui_blender_installs_the_backend_from_the_preferences(built, tmp_path):
    """From an empty home folder and the legacy zip alone: Install Backend pressed in Edit > Preferences (a folder of
    wheels stands in for the network; the system's Python 3.11, as Debian's Blender runs on it), then Reconstruct on
    the example photo with the installed backend and its shipped default weights."""
    from support.wheels import wheel_folder

    wheels = wheel_folder()
    if wheels is None:
        pytest.skip("no package index reachable to fill the wheel folder (set GENRE_RUNTIME_WHEELS)")
    if not Path("/usr/bin/python3.11").is_file():
        pytest.skip("no /usr/bin/python3.11 for the backend's environment")
    result = run_gui_e2e.run(tmp_path / "e2e", Path(), REPO / "examples" / "sofa.png", built["legacy"], timeout=300,
                             install={"python": "/usr/bin/python3.11", "wheels": str(wheels)})
    assert result["exit_code"] == 0, json.dumps(result, indent=2)
    assert result["install_invoke"] == ["RUNNING_MODAL"] and result["install_ok"] and result["backend_ok"]
    assert result["backend_command"].endswith("/config/genre/backend-env/bin/python")
    assert "/backend-env/lib/python3.11/site-packages/genre_backend/weights/default.safetensors" in result["backend_info"]
    steps = [s for s, _ in result["install_steps"]]
    assert {"Installing PyTorch (CPU)", "Installing the backend"} <= set(steps)
    fractions = [f for _, f in result["install_steps"]]
    assert fractions == sorted(fractions)
    assert result["mesh"]["name"] == "sofa.001" and result["message"].startswith("sofa: ")
    for key in ("install_screenshot", "installed_screenshot", "screenshot"):
        png = Path(result[key])
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
