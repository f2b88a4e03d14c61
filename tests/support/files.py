"""Hostile files for the decoding tests."""

import struct
import zlib


def huge_png(width: int, height: int, colour_type: int = 0) -> bytes:
    """A PNG whose header claims width×height 8-bit pixels (``colour_type`` 0 grey, 2 RGB); the pixel data is a few
    bytes (no decoder gets that far)."""

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, colour_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\x00" * 1024)) + chunk(b"IEND", b"")
