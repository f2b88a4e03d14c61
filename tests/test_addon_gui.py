"""The add-on in a real GUI Blender under Xvfb: the modal operator's timer runs a reconstruction end to end.

Uses the system's ``blender`` (Debian's 3.4.1 package here, with its own
Python 3.11) and ``xvfb-run``; skipped when either is missing.  The backend
is a real ``genre serve`` run by this project's Python with weights trained
in the test session (see ``test_addon.trained``).  About 1.5 minutes on a
2-core machine, most of it Blender starting under software OpenGL.  ``make
e2e`` runs the same with better-trained weights and keeps the screenshots in
``out/e2e/``.
"""

import importlib.util
import json
from pathlib import Path

import pytest

from test_addon import REPO, built, trained  # noqa: F401  (fixtures)

_spec = importlib.util.spec_from_file_location("run_gui_e2e", REPO / "tests" / "e2e" / "run_gui_e2e.py")
run_gui_e2e = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(run_gui_e2e)

_missing = run_gui_e2e.missing_tools()


@pytest.mark.slow
@pytest.mark.skipif(bool(_missing), reason=f"no GUI Blender here: {_missing}")
def test_gui_blender_runs_the_modal_operator_end_to_end(built, trained, tmp_path):  # noqa: F811
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
