"""GenRe backend: the geometry core, the networks, the photo going in, the pipeline, what it writes and its front ends (the command line, the subprocess server)."""

__version__ = "0.1.0"
