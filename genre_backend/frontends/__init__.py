"""The ways in: ``genre reconstruct`` (the command line) and ``genre serve`` (the JSON-lines server)."""
