"""The markers of pyproject.toml and what tests/conftest.py does with them: a test not marked ``network`` cannot
download, in its own process or in the ones it starts; one marked ``network`` can."""

import os
import socket
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from support.offline import _CONNECT, DEAD_PROXY, PROXY_VARIABLES

ROOT = Path(__file__).resolve().parents[2]


def test_the_markers_are_registered():
    markers = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]["markers"]
    assert sorted(m.split(":")[0] for m in markers) == ["blender", "network", "slow"]


def test_a_test_not_marked_network_reaches_only_this_machine():
    with pytest.raises(OSError, match="not marked network"):
        socket.create_connection(("192.0.2.1", 80), timeout=5)  # TEST-NET-1: refused before any packet leaves
    with pytest.raises(OSError, match="not marked network"):
        socket.socket(socket.AF_INET6, socket.SOCK_STREAM).connect_ex(("2001:db8::1", 80))
    with socket.socket() as server:  # this machine stays reachable (the loopback interface)
        server.bind(("127.0.0.1", 0))
        server.listen()
        socket.create_connection(server.getsockname(), timeout=5).close()


def test_its_subprocesses_download_through_a_closed_port():
    assert all(os.environ[name] == DEAD_PROXY for name in PROXY_VARIABLES)
    done = subprocess.run([sys.executable, "-c", "import urllib.request; urllib.request.urlopen('http://deb.debian.org/', timeout=10)"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode != 0 and "Connection refused" in done.stderr, done.stderr


@pytest.mark.network
def test_a_test_marked_network_is_not_cut_off():
    assert socket.socket.connect is _CONNECT["connect"] and socket.socket.connect_ex is _CONNECT["connect_ex"]
    assert all(os.environ.get(name) != DEAD_PROXY for name in PROXY_VARIABLES)
