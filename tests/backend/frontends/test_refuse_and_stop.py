"""Fault injection for issue 43, parts 3 and 4: refusals before any work, and a clean stop on a signal.

Every case runs ``genre reconstruct`` or ``genre serve`` as a subprocess
(``sys.executable -m genre_backend.cli``) with the tiny trained weights and
checks the exit status, the line written, and the folder listing before and
after.  Signals are sent while a mesh file is being written: a small wrapper
(``_SLOW_WRITES``) makes every atomic write pause inside its temporary file
and say so, so the test knows the temporary exists when the signal goes.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from genre_backend.atomic import TMP_MARK
from support.faults import SLOW_WRITES as _SLOW_WRITES
from support.faults import all_lines as _all_lines
from support.faults import env as _env
from support.faults import job as _job
from support.faults import listing, server_with_env, temporaries
from support.faults import wait_for_mark as _wait_for_mark
from support.server import ServerProcess

def reconstruct(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "genre_backend.cli", "reconstruct", *args], cwd=cwd, env=_env(),
                          capture_output=True, text=True, timeout=600)


@pytest.fixture()
def photo(trained, tmp_path) -> Path:
    p = tmp_path / "photo.png"
    shutil.copy(trained[1] / "box" / "view_000.png", p)
    return p


def _refused(proc, code: str) -> str:
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr and f"[{code}]" in lines[-1], proc.stderr
    return lines[-1]


# ---- part 3: refuse before work (CLI) ------------------------------------------------------------
@pytest.mark.slow
def test_cli_refuses_intermediates_that_are_a_file_before_work(trained, photo, tmp_path):
    (tmp_path / "inter").write_text("a file")
    before = listing(tmp_path)
    proc = reconstruct(str(photo), "-o", "m.obj", "--save-intermediates", "inter", "--weights", str(trained[0]), cwd=tmp_path)
    line = _refused(proc, "output_unwritable")
    assert "inter" in line and "not a folder" in line
    assert listing(tmp_path) == before and (tmp_path / "inter").read_text() == "a file"  # no mesh written


def test_cli_refuses_intermediates_under_a_file_before_work(trained, photo, tmp_path):
    (tmp_path / "blocker").write_text("x")
    before = listing(tmp_path)
    proc = reconstruct(str(photo), "-o", "m.obj", "--save-intermediates", "blocker/a/b", "--weights", str(trained[0]), cwd=tmp_path)
    assert "is not a folder" in _refused(proc, "output_unwritable")
    assert listing(tmp_path) == before


def test_cli_refuses_a_preview_named_as_the_photo_before_work(trained, tmp_path):
    photo = tmp_path / "m_preview.png"
    shutil.copy(trained[1] / "box" / "view_000.png", photo)
    data = photo.read_bytes()
    before = listing(tmp_path)
    proc = reconstruct(str(photo), "-o", "m.obj", "--preview", "--weights", str(trained[0]), cwd=tmp_path)
    assert "input" in _refused(proc, "output_unwritable")
    assert listing(tmp_path) == before and photo.read_bytes() == data


@pytest.mark.slow
def test_cli_writes_a_mesh_with_a_name_at_the_limit_and_keeps_a_users_lookalike(trained, photo, tmp_path):
    name = "n" * 243 + ".obj"  # its texture's name, n…n_texture.png, is 255 bytes: the longest legal name
    dead = int(subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True).stdout)
    users = tmp_path / f".{name[:200]}.tmp-{dead}-x"  # a user's own file shaped like an old temporary
    users.write_text("mine")
    proc = reconstruct(str(photo), "-o", name, "--texture", "--weights", str(trained[0]), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / name).is_file() and (tmp_path / ("n" * 243 + ".mtl")).is_file()
    assert (tmp_path / ("n" * 243 + "_texture.png")).is_file()
    assert users.read_text() == "mine" and temporaries(tmp_path) == []


# ---- part 3: refuse before work (serve) ----------------------------------------------------------
@pytest.fixture()
def serve(trained, tmp_path):
    servers = []

    def start() -> ServerProcess:
        s = ServerProcess("--weights", str(trained[0]), cwd=tmp_path)
        ready = s.next(timeout=300)
        assert ready["type"] == "ready", ready
        servers.append(s)
        return s

    yield start
    for s in servers:
        if s.proc.poll() is None:
            s.proc.kill()
            s.proc.wait()


def _server_with_env(trained, cwd, env, script: str | None = None, prefix: list[str] | None = None) -> ServerProcess:
    return server_with_env(trained[0], cwd, env, script=script, prefix=prefix)


def test_serve_refuses_intermediates_it_cannot_fill_before_work(serve, photo, tmp_path):
    (tmp_path / "blocker").write_text("x")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "mask.png").mkdir()  # a folder where an intermediate image would go
    s = serve()
    before = listing(tmp_path)
    for rid, inter in (("file", "blocker"), ("under_file", "blocker/sub"), ("occupied", "full"), ("long", "i" * 300)):
        s.send(_job(rid, photo, f"{rid}.obj", save_intermediates=inter))
        ev = s.until(lambda e: e["type"] in ("error", "result"))[-1]
        assert ev["type"] == "error" and ev["id"] == rid and ev["code"] == "output_unwritable", ev
    assert listing(tmp_path) == before  # no mesh written
    s.send({"type": "shutdown", "id": "end"})
    assert s.until(lambda e: e["type"] == "bye")[-1] == {"type": "bye", "id": "end"} and s.close() == 0


def test_serve_refuses_a_format_that_disagrees_with_the_extension(serve, photo, tmp_path):
    s = serve()
    before = listing(tmp_path)
    s.send(_job("g", photo, "x.obj", format="glb"))
    ev = s.until(lambda e: e["type"] in ("error", "result"))[-1]
    assert ev["type"] == "error" and ev["code"] == "bad_field" and ".obj" in ev["message"], ev
    s.send(_job("ok", photo, "x.glb", format="glb"))  # agreeing: written
    assert s.until(lambda e: e["type"] in ("error", "result"))[-1]["type"] == "result"
    assert listing(tmp_path) == before | {"x.glb"}
    s.send({"type": "shutdown", "id": "end"})
    s.until(lambda e: e["type"] == "bye")
    assert s.close() == 0


@pytest.mark.slow
def test_serve_writes_names_at_the_limit_and_no_matplotlib_config(trained, photo, tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    env = _env(HOME=str(home))
    for key in ("MPLCONFIGDIR", "XDG_CONFIG_HOME", "XDG_CACHE_HOME"):
        env.pop(key, None)
    s = _server_with_env(trained, tmp_path, env)
    assert s.next(timeout=300)["type"] == "ready"
    names = [("a" * 251 + ".obj", False), ("\u00e9" * 125 + ".ply", True), ("b" * 243 + ".obj", True), ("c" * 251 + ".glb", True)]
    for i, (name, texture) in enumerate(names):  # 255, 254, 247 (its texture: 255) and 255 bytes
        s.send(_job(i, photo, name, texture=texture, save_intermediates="inter"))
        ev = s.until(lambda e: e["type"] in ("error", "result"))[-1]
        assert ev["type"] == "result", ev
        assert Path(ev["mesh"]).name == name and (tmp_path / name).is_file()
    assert (tmp_path / "inter" / "depth.png").is_file()
    s.send({"type": "shutdown", "id": "end"})
    s.until(lambda e: e["type"] == "bye")
    assert s.close() == 0
    assert listing(home) == set(), listing(home)  # no .config/matplotlib, no .cache/matplotlib
    assert temporaries(tmp_path) == []


# ---- part 4: a clean stop ------------------------------------------------------------------------
def _slow_cli(trained, photo, tmp_path, out: Path, *extra: str) -> tuple[subprocess.Popen, Path]:
    mark = tmp_path / "mark"
    mark.unlink(missing_ok=True)
    # (SIGINT restored to its default in the child: a suite started in the background of a non-interactive shell
    # hands its children SIGINT ignored, and Python then, rightly, leaves Ctrl-C ignored)
    proc = subprocess.Popen([sys.executable, "-c", _SLOW_WRITES, "reconstruct", str(photo), "-o", str(out / "m.obj"),
                             "--weights", str(trained[0]), *extra], cwd=tmp_path, env=_env(GENRE_TEST_MARK=str(mark)),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    return proc, mark


@pytest.mark.slow
@pytest.mark.parametrize("texture, at, sig", [(False, 1, signal.SIGINT), (False, 1, signal.SIGTERM)]
                         + [(True, at, sig) for at in (1, 2, 3) for sig in (signal.SIGINT, signal.SIGTERM)])
def test_cli_signal_during_a_write_prints_one_line_and_exits(trained, photo, tmp_path, texture, at, sig):
    out = tmp_path / "out"
    out.mkdir()
    proc, mark = _slow_cli(trained, photo, tmp_path, out, *(["--texture"] if texture else []))
    _wait_for_mark(mark, proc, writes=at)
    during = temporaries(out)
    assert len(during) == at and all(TMP_MARK in t for t in during), listing(out)  # the temporaries exist as the signal goes
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    status, word = (130, "interrupted") if sig == signal.SIGINT else (143, "terminated")
    assert proc.returncode == status, err
    assert err.strip().splitlines() == [f"genre reconstruct: {word}"], err
    assert listing(out) == set()  # no mesh, no .mtl, no texture (a textured OBJ is one unit), no temporary


@pytest.mark.slow
@pytest.mark.parametrize("at", [1, 2, 3])
def test_cli_sigkill_during_a_textured_write_leaves_no_final_file_and_the_next_run_cleans_up(trained, photo, tmp_path, at):
    out = tmp_path / "out"
    out.mkdir()
    proc, mark = _slow_cli(trained, photo, tmp_path, out, "--texture")
    _wait_for_mark(mark, proc, writes=at)
    proc.kill()
    proc.communicate(timeout=60)
    left = temporaries(out)
    assert len(left) == at and listing(out) == set(left)  # the unit's temporaries so far; no final file
    proc = reconstruct(str(photo), "-o", str(out / "m.obj"), "--texture", "--weights", str(trained[0]), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert listing(out) == {"m.obj", "m.mtl", "m_texture.png"}  # the dead run's temporaries removed


def _slow_writing_server(trained, tmp_path):
    """A ready ``genre serve`` whose writes wait at the mark file (``_SLOW_WRITES``): (server, output folder, mark)."""
    out = tmp_path / "out"
    out.mkdir()
    mark = tmp_path / "mark"
    s = _server_with_env(trained, tmp_path, _env(GENRE_TEST_MARK=str(mark)), script=_SLOW_WRITES)
    assert s.next(timeout=300)["type"] == "ready"
    return s, out, mark


@pytest.mark.slow
@pytest.mark.parametrize("sig, status, texture, at", [(signal.SIGTERM, 143, False, 1), (signal.SIGINT, 130, False, 1)]
                         + [(sig, status, True, at) for at in (1, 2, 3)
                            for sig, status in ((signal.SIGINT, 130), (signal.SIGTERM, 143))])
def test_serve_signal_during_a_write_finishes_it_says_bye_and_exits(trained, photo, tmp_path, sig, status, texture, at):
    s, out, mark = _slow_writing_server(trained, tmp_path)
    s.send(_job("j", photo, str(out / "m.obj"), texture=texture))
    s.send(_job("queued", photo, str(out / "q.obj")))
    _wait_for_mark(mark, s.proc, writes=at)
    assert len(temporaries(out)) == at and listing(out) == set(temporaries(out))
    s.proc.send_signal(sig)
    assert s.proc.wait(timeout=120) == status, s.proc.stderr.read()
    events = _all_lines(s)
    kinds = [(e["type"], e.get("id")) for e in events if e["type"] != "progress"]
    assert kinds == [("ready", None), ("cancelled", "queued"), ("result", "j"), ("bye", None)] or \
        kinds == [("ready", None), ("result", "j"), ("cancelled", "queued"), ("bye", None)], kinds
    assert events[-1] == {"type": "bye", "id": None, "reason": signal.Signals(sig).name}
    expected = {"m.obj", "m.mtl", "m_texture.png"} if texture else {"m.obj"}
    assert listing(out) == expected  # the job's files whole, no temporary, nothing of the queued job


def test_serve_sigterm_when_idle(trained, tmp_path):
    s = _server_with_env(trained, tmp_path, _env())
    assert s.next(timeout=300)["type"] == "ready"
    before = listing(tmp_path)
    s.proc.send_signal(signal.SIGTERM)
    assert s.proc.wait(timeout=60) == 143
    assert _all_lines(s)[-1] == {"type": "bye", "id": None, "reason": "SIGTERM"}
    assert listing(tmp_path) == before


@pytest.mark.slow
@pytest.mark.parametrize("at", [1, 2, 3])
def test_serve_sigkill_during_a_write_then_the_next_job_cleans_up(trained, photo, tmp_path, at):
    s, out, mark = _slow_writing_server(trained, tmp_path)
    s.send(_job("j", photo, str(out / "m.obj"), texture=True))
    _wait_for_mark(mark, s.proc, writes=at)
    s.proc.kill()
    s.proc.wait(timeout=60)
    assert len(temporaries(out)) == at and listing(out) == set(temporaries(out))  # no final file of the unit
    s = _server_with_env(trained, tmp_path, _env())
    assert s.next(timeout=300)["type"] == "ready"
    s.send(_job("again", photo, str(out / "m.obj"), texture=True))
    assert s.until(lambda e: e["type"] in ("error", "result"))[-1]["type"] == "result"
    s.send({"type": "shutdown", "id": "end"})
    s.until(lambda e: e["type"] == "bye")
    assert s.close() == 0
    assert listing(out) == {"m.obj", "m.mtl", "m_texture.png"}  # the dead server's temporaries removed


# serve whose weights take long to load: $GENRE_TEST_MARK is written as the load begins
_SLOW_LOAD = """
import os, sys, time
import genre_backend.inference.reconstruct as rec
_orig = rec.Reconstructor.__init__
def _slow(self, *args, **kwargs):
    open(os.environ["GENRE_TEST_MARK"], "w").write("loading\\n")
    time.sleep(30)
    _orig(self, *args, **kwargs)
rec.Reconstructor.__init__ = _slow
from genre_backend.cli import main
sys.exit(main(sys.argv[1:]))
"""


# serve whose worker thread is slow to begin: $GENRE_TEST_MARK is written as the new thread starts, which then
# waits 3 s before Thread.start may return (the window in which a signal once left the worker half started)
_SLOW_WORKER_START = """
import os, sys, time, threading
_orig = threading.Thread._bootstrap_inner
def _slow(self):
    if self.name == "genre-serve-worker":
        open(os.environ["GENRE_TEST_MARK"], "w").write("starting\\n")
        time.sleep(3)
    _orig(self)
threading.Thread._bootstrap_inner = _slow
from genre_backend.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.slow
@pytest.mark.parametrize("script", [_SLOW_LOAD, _SLOW_WORKER_START], ids=["weights_load", "worker_start"])
@pytest.mark.parametrize("sig, status", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_serve_signal_before_ready_says_bye_only(trained, tmp_path, script, sig, status):
    mark = tmp_path / "mark"
    before = listing(tmp_path)
    s = _server_with_env(trained, tmp_path, _env(GENRE_TEST_MARK=str(mark)), script=script)
    _wait_for_mark(mark, s.proc)
    s.proc.send_signal(sig)
    assert s.proc.wait(timeout=60) == status, s.proc.stderr.read()
    assert _all_lines(s) == [{"type": "bye", "id": None, "reason": signal.Signals(sig).name}]  # no `ready` before its worker runs
    assert "Traceback" not in s.proc.stderr.read()
    assert listing(tmp_path) == before | {"mark"}


# ---- part 4: a signal during a network stage ------------------------------------------------------
# The depth network slowed: on its first call it appends "network" to $GENRE_TEST_MARK, then sleeps
# $GENRE_TEST_SLEEP seconds (0: only marks, so a refusal test can tell that no network ran).
_SLOW_NET = """
import os, sys, time
import genre_backend.inference.reconstruct as rec
_orig = rec.Reconstructor._depth_net
def _slow(self, *args, **kwargs):
    with open(os.environ["GENRE_TEST_MARK"], "a") as m:
        m.write("network\\n")
    time.sleep(float(os.environ.get("GENRE_TEST_SLEEP", "30")))
    return _orig(self, *args, **kwargs)
rec.Reconstructor._depth_net = _slow
from genre_backend.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.slow
@pytest.mark.parametrize("sig, status, word", [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated")])
def test_cli_signal_during_a_network_stage_prints_one_line_and_writes_nothing(trained, photo, tmp_path, sig, status, word):
    out = tmp_path / "out"
    out.mkdir()
    mark = tmp_path / "mark"
    proc = subprocess.Popen([sys.executable, "-c", _SLOW_NET, "reconstruct", str(photo), "-o", str(out / "m.obj"), "--texture",
                             "--preview", "--save-intermediates", str(out / "inter"), "--weights", str(trained[0])],
                            cwd=tmp_path, env=_env(GENRE_TEST_MARK=str(mark)), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    _wait_for_mark(mark, proc)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == status, err
    assert err.strip().splitlines() == [f"genre reconstruct: {word}"], err
    assert listing(out) == set()


@pytest.mark.slow
@pytest.mark.parametrize("sig, status", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_serve_signal_during_a_network_stage_cancels_the_job_and_says_bye(trained, photo, tmp_path, sig, status):
    out = tmp_path / "out"
    out.mkdir()
    mark = tmp_path / "mark"
    s = _server_with_env(trained, tmp_path, _env(GENRE_TEST_MARK=str(mark), GENRE_TEST_SLEEP="5"), script=_SLOW_NET)
    assert s.next(timeout=300)["type"] == "ready"
    s.send(_job("j", photo, str(out / "m.obj"), texture=True, save_intermediates=str(out / "inter")))
    s.send(_job("queued", photo, str(out / "q.obj")))
    _wait_for_mark(mark, s.proc)
    s.proc.send_signal(sig)
    assert s.proc.wait(timeout=120) == status, s.proc.stderr.read()
    assert "Traceback" not in s.proc.stderr.read()
    events = _all_lines(s)
    kinds = sorted((e["type"], e.get("id")) for e in events if e["type"] not in ("progress", "ready", "bye"))
    assert kinds == [("cancelled", "j"), ("cancelled", "queued")], events  # the running job stops at its next stage
    assert events[-1] == {"type": "bye", "id": None, "reason": signal.Signals(sig).name}
    assert listing(out) == set()


# ---- part 4: a batch of textured photos -------------------------------------------------------------
def _batch(trained, tmp_path) -> tuple[list[str], Path]:
    """Two photos for one ``genre reconstruct`` call writing into ``out/``: a.obj, then b.obj (three files each)."""
    src = trained[1] / "box"
    for name, view in (("a.png", "view_000.png"), ("b.png", "view_001.png")):
        shutil.copy(src / view if (src / view).exists() else src / "view_000.png", tmp_path / name)
    out = tmp_path / "out"
    out.mkdir()
    return [str(tmp_path / "a.png"), str(tmp_path / "b.png"), "-o", str(out), "--texture", "--weights", str(trained[0])], out


_UNIT_A = {"a.obj", "a.mtl", "a_texture.png"}


@pytest.mark.slow
@pytest.mark.parametrize("at", range(1, 7))
@pytest.mark.parametrize("sig, status, word", [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated"),
                                               (signal.SIGKILL, -9, None)])
def test_signal_at_each_temporary_of_a_textured_batch(trained, tmp_path, at, sig, status, word):
    """A batch is written photo by photo, each textured OBJ as a unit: a signal at the ``at``-th temporary (1-3 the first
    photo's, 4-6 the second's) leaves the photos already written whole, and nothing of the one being written (after
    SIGKILL, only its temporaries, which the next run removes)."""
    args, out = _batch(trained, tmp_path)
    mark = tmp_path / "mark"
    proc = subprocess.Popen([sys.executable, "-c", _SLOW_WRITES, "reconstruct", *args], cwd=tmp_path,
                            env=_env(GENRE_TEST_MARK=str(mark), GENRE_TEST_SLEEP="1"), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    _wait_for_mark(mark, proc, writes=at)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == status, err
    done = _UNIT_A if at > 3 else set()
    if word is not None:
        assert err.strip().splitlines()[-1] == f"genre reconstruct: {word}", err
        assert "Traceback" not in err
        assert listing(out) == done
        return
    in_flight = (at - 1) % 3 + 1
    assert listing(out) - done == set(temporaries(out)) and len(temporaries(out)) == in_flight, listing(out)
    again = reconstruct(*args, cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    assert listing(out) == _UNIT_A | {"b.obj", "b.mtl", "b_texture.png"}  # the dead run's temporaries removed


# ---- part 3: refusals when the file system says no (permission bits) --------------------------------
def _without_override() -> list[str]:
    """A command prefix under which permission bits bind: as root, ``setpriv`` drops the capabilities that let root
    write anywhere (CAP_DAC_OVERRIDE, CAP_DAC_READ_SEARCH); as anyone else, none is needed."""
    if os.geteuid() != 0:
        return []
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("running as root without util-linux's setpriv: permission bits cannot bind")
    caps = "-dac_override,-dac_read_search"
    return [setpriv, f"--bounding-set={caps}", f"--inh-caps={caps}"]


@pytest.fixture()
def locked(trained, photo, tmp_path):
    """A read-only folder ``ro/`` (with ``ro/inside/``), an unreadable photo and unreadable weights."""
    ro = tmp_path / "ro"
    (ro / "inside").mkdir(parents=True)
    paths = {"ro": ro, "secret": tmp_path / "secret.png", "weights": tmp_path / "secret.safetensors"}
    shutil.copy(photo, paths["secret"])
    shutil.copy(trained[0], paths["weights"])
    for p, mode in ((ro / "inside", 0o555), (ro, 0o555), (paths["secret"], 0), (paths["weights"], 0)):
        p.chmod(mode)
    yield paths
    for p in (ro, ro / "inside"):  # (so that pytest can remove them)
        p.chmod(0o755)


@pytest.mark.slow
@pytest.mark.parametrize("case", ["output folder", "intermediates", "intermediates inside", "photo", "weights", "mask"])
def test_cli_refuses_what_permission_bits_forbid_before_any_network(trained, photo, locked, tmp_path, case):
    mark = tmp_path / "mark"
    weights = str(trained[0])
    args = {
        "output folder": [str(photo), "-o", "ro/m.obj", "--texture"],
        "intermediates": [str(photo), "-o", "m.obj", "--save-intermediates", "ro/inter"],
        "intermediates inside": [str(photo), "-o", "m.obj", "--save-intermediates", "ro/inside"],
        "photo": ["secret.png", "-o", "m.obj"],
        "weights": [str(photo), "-o", "m.obj"],
        "mask": [str(photo), "--mask", "secret.png", "-o", "m.obj"],
    }[case]
    if case == "weights":
        weights = str(locked["weights"])
    code = {"photo": "bad_image", "weights": "bad_weights", "mask": "bad_mask"}.get(case, "output_unwritable")
    before = listing(tmp_path)
    proc = subprocess.run([*_without_override(), sys.executable, "-c", _SLOW_NET, "reconstruct", *args, "--weights", weights],
                          cwd=tmp_path, env=_env(GENRE_TEST_MARK=str(mark), GENRE_TEST_SLEEP="0"), capture_output=True,
                          text=True, timeout=600)
    line = _refused(proc, code)
    assert "denied" in line or "not writable" in line or "not readable" in line, line
    assert not mark.exists(), "a network ran before the refusal"
    assert listing(tmp_path) == before


def test_serve_refuses_what_permission_bits_forbid_before_any_network(trained, photo, locked, tmp_path):
    mark = tmp_path / "mark"
    env = _env(GENRE_TEST_MARK=str(mark), GENRE_TEST_SLEEP="0")
    s = _server_with_env(trained, tmp_path, env, script=_SLOW_NET, prefix=_without_override())
    assert s.next(timeout=300)["type"] == "ready"
    before = listing(tmp_path)
    cases = [("out", _job("out", photo, "ro/m.obj", texture=True), "output_unwritable"),
             ("inter", _job("inter", photo, "m.obj", save_intermediates="ro/inside"), "output_unwritable"),
             ("photo", _job("photo", locked["secret"], "m.obj"), "bad_image"),
             ("mask", {**_job("mask", photo, "m.obj"), "mask": str(locked["secret"])}, "bad_mask")]
    for rid, job, code in cases:
        s.send(job)
        ev = s.until(lambda e: e["type"] in ("error", "result"))[-1]
        assert ev["type"] == "error" and ev["id"] == rid and ev["code"] == code, ev
        assert "denied" in ev["message"] or "not writable" in ev["message"] or "not readable" in ev["message"], ev
    assert not mark.exists(), "a network ran before a refusal"
    assert listing(tmp_path) == before
    s.send({"type": "shutdown", "id": "end"})
    s.until(lambda e: e["type"] == "bye")
    assert s.close() == 0
