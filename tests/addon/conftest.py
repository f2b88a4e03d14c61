"""Fixtures of the add-on tests: the built add-on and the session's tiny model with a cut-out photo."""

import sys

import pytest
from filelock import FileLock

from support.addon import REPO, make_photo


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    sys.path.insert(0, str(REPO))
    try:
        import build_addon
    finally:
        sys.path.remove(str(REPO))
    return build_addon.build(tmp_path_factory.mktemp("dist"))


@pytest.fixture(scope="session")
def trained(trained):
    """(weights, photo): the session's tiny model (conftest.py's ``trained``, trained once) and a cut-out photo of
    one of its views; shared by every add-on test module of the session."""
    weights, views = trained
    with FileLock(str(views.parent / "box.png.lock")):  # the model's folder is shared by the xdist workers
        return weights, make_photo(views.parent)
