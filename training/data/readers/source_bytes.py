"""The one way the readers take their input: a file's path, or its bytes (a member read out of an archive)."""

from __future__ import annotations

from pathlib import Path

__all__ = ["source_bytes"]


def source_bytes(source: str | Path | bytes | bytearray | memoryview) -> tuple[bytes, str]:
    """``(data, label)``: the bytes to parse and the name to put in error messages (the path, or ``<bytes>``).

    Raises:
        ValueError: a path that is not a file.
    """
    if isinstance(source, (bytes, bytearray, memoryview)):
        return bytes(source), "<bytes>"
    path = Path(source)
    if not path.is_file():
        raise ValueError(f"{path}: no such file")
    return path.read_bytes(), str(path)
