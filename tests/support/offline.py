"""A test not marked ``network`` stays offline (tests/conftest.py turns this on for the whole run).

Its sockets reach only this machine, and the subprocesses it starts get a proxy on a closed local port.
"""

import ipaddress
import json
import os
import socket

# A download from a test not marked network goes through this proxy, on the discard port where nothing listens: it
# fails at once (pip, apt-get, curl and urllib read these variables).
DEAD_PROXY = "http://127.0.0.1:9"
PROXY_VARIABLES = ("http_proxy", "https_proxy", "HTTP_PROXY", "HTTPS_PROXY", "ALL_PROXY", "all_proxy")
_CONNECT = {"connect": socket.socket.connect, "connect_ex": socket.socket.connect_ex}
# the variables as the run found them; pytest-xdist's workers inherit the controller's offline ones, and read these
_SAVED = "GENRE_TESTS_ONLINE_PROXIES"
_ENVIRONMENT = json.loads(os.environ.setdefault(_SAVED, json.dumps(
    {name: os.environ.get(name) for name in PROXY_VARIABLES + ("no_proxy", "NO_PROXY")})))


def _is_local(address) -> bool:
    host = address[0] if isinstance(address, tuple) else address
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


def _offline(name: str):
    original = _CONNECT[name]

    def connect(self, address):
        if self.family in (socket.AF_INET, socket.AF_INET6) and not _is_local(address):
            raise OSError(f"{address}: a test not marked network reaches only this machine (tests/conftest.py)")
        return original(self, address)

    return connect


def offline(on: bool) -> None:
    """Cut this process and the subprocesses it starts from everything but this machine (``on``), or restore them."""
    for name, original in _CONNECT.items():
        setattr(socket.socket, name, _offline(name) if on else original)
    for name, value in _ENVIRONMENT.items():
        if on:
            os.environ[name] = DEAD_PROXY if name in PROXY_VARIABLES else "localhost,127.0.0.1,::1"
        elif value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value
