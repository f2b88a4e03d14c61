"""Fixtures shared by several test files."""

import pytest

from tiny_data import make_tiny_views


@pytest.fixture(scope="module")
def tiny_views(tmp_path_factory):
    """Rendered views with targets of two tiny shapes (module scope: rendered once per file)."""
    return make_tiny_views(tmp_path_factory.mktemp("tiny"))
