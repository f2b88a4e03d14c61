"""Fixtures shared by several test files."""

import pytest

from tiny_data import make_tiny_views


@pytest.fixture(scope="module")
def tiny_views(tmp_path_factory):
    """Rendered views with targets of two tiny shapes (module scope: rendered once per file)."""
    return make_tiny_views(tmp_path_factory.mktemp("tiny"))


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """(weights, views): the tiny model trained stage by stage, once per session (test_reconstruct.trained_weights),
    on one thread (tiny nets: faster, and far faster on a busy 2-core machine).  test_reconstruct and test_addon
    have their own."""
    import torch
    from test_reconstruct import trained_weights

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return trained_weights(tmp_path_factory)
    finally:
        torch.set_num_threads(threads)
