"""Fixtures shared by several test files.

The tiny views are rendered once per session (Blender) and each file gets a copy; the tiny model is trained on
them once per session.  ``make test-fast`` skips the tests marked ``slow`` (pyproject.toml)."""

import pytest

from support.tiny_data import copy_tiny_views, make_tiny_views, train_tiny_weights


@pytest.fixture(scope="session")
def tiny_views_rendered(tmp_path_factory):
    """The tiny views, rendered once per session: never used in place (tests may add files to their views), see
    ``tiny_views``."""
    return make_tiny_views(tmp_path_factory.mktemp("tiny_rendered"))


@pytest.fixture(scope="module")
def tiny_views(tiny_views_rendered, tmp_path_factory):
    """Rendered views with targets of two tiny shapes: each file's own copy of the session's renders."""
    return copy_tiny_views(tiny_views_rendered, tmp_path_factory.mktemp("tiny"))


@pytest.fixture(scope="session")
def trained(tiny_views_rendered, tmp_path_factory):
    """(weights, views): the tiny model trained stage by stage (tiny_data.train_tiny_weights) on a copy of the
    tiny views, once per session."""
    root = tmp_path_factory.mktemp("genre_trained")
    views = copy_tiny_views(tiny_views_rendered, root)
    return train_tiny_weights(views, root / "run"), views
