"""Fixtures shared by several test files.

The tiny views are rendered once per session (Blender) and each file gets a copy; the tiny model is trained on
them once per session.  ``make test-fast`` skips the tests marked ``slow`` (pyproject.toml).

Under pytest-xdist (``make test`` and ``make test-fast`` run two workers, ``-n 2``) "once per session" means once
for all the workers: the first worker to ask renders or trains under a file lock in the run's shared temporary
folder, the others wait and use its files (read-only: every test takes a copy or writes elsewhere).  Each process
of the run uses one torch thread (``pytest_configure``): two workers on two cores, and tiny nets, which one
thread runs fastest; subprocesses inherit ``OMP_NUM_THREADS=1``.

Markers (pyproject.toml): a test marked ``blender`` is skipped where no ``blender`` program is on PATH; a test not
marked ``network`` cannot download (``offline``: its sockets reach only this machine, and its subprocesses get a
proxy on a closed local port).
"""

import json
import os
import shutil
from pathlib import Path

import pytest
from filelock import FileLock

from support.offline import offline
from support.tiny_data import copy_tiny_views, make_tiny_views, train_tiny_weights


def pytest_configure(config):
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))
    offline(True)


def pytest_collection_modifyitems(config, items):
    if shutil.which("blender") is None:
        skip = pytest.mark.skip(reason="no Blender program on PATH (Debian: apt-get install blender; scripts/setup.sh --test does)")
        for item in items:
            if item.get_closest_marker("blender"):
                item.add_marker(skip)


@pytest.fixture(autouse=True)
def _network_only_when_marked(request):
    """A test marked network may download; every other test stays offline."""
    if request.node.get_closest_marker("network") is None:
        yield
        return
    offline(False)
    try:
        yield
    finally:
        offline(True)


def once_per_run(tmp_path_factory, worker_id: str, name: str, make):
    """``make(folder)``'s JSON-able result, computed once per test run: once per session without xdist, once for all
    the workers with it (the first one makes it under a lock, the others read the result it left)."""
    if worker_id == "master":
        return make(tmp_path_factory.mktemp(name))
    shared = tmp_path_factory.getbasetemp().parent / f"shared_{name}"
    done = shared / "result.json"
    with FileLock(str(shared) + ".lock"):
        if not done.is_file():
            shared.mkdir(exist_ok=True)
            done.write_text(json.dumps(make(shared)))
    return json.loads(done.read_text())


@pytest.fixture(scope="session")
def tiny_views_rendered(tmp_path_factory, worker_id):
    """The tiny views, rendered once per session: never used in place (tests may add files to their views), see
    ``tiny_views``."""
    return Path(once_per_run(tmp_path_factory, worker_id, "tiny_rendered", lambda root: str(make_tiny_views(root))))


@pytest.fixture(scope="module")
def tiny_views(tiny_views_rendered, tmp_path_factory):
    """Rendered views with targets of two tiny shapes: each file's own copy of the session's renders."""
    return copy_tiny_views(tiny_views_rendered, tmp_path_factory.mktemp("tiny"))


@pytest.fixture(scope="session")
def trained(tiny_views_rendered, tmp_path_factory, worker_id):
    """(weights, views): the tiny model trained stage by stage (tiny_data.train_tiny_weights) on a copy of the
    tiny views, once per session."""

    def make(root):
        views = copy_tiny_views(tiny_views_rendered, root)
        return [str(train_tiny_weights(views, root / "run")), str(views)]

    weights, views = once_per_run(tmp_path_factory, worker_id, "genre_trained", make)
    return Path(weights), Path(views)
