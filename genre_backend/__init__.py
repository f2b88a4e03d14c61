"""GenRe backend: geometry core, networks, inference and the subprocess server."""

__version__ = "0.1.0"
