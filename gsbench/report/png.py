"""The report's PNG files: made small (a 256-colour palette, optionally scaled down) and able to say what they
show (a ``tEXt`` chunk named ``gsbench`` holding JSON, e.g. a surface picture's run id and seed).

A PNG is the 8-byte signature, then chunks: 4-byte big-endian length, 4-byte type, data, CRC-32 of type + data.
"""

from __future__ import annotations

import io
import json
import struct
import zlib

from PIL import Image

from gsbench.errors import GsbenchError

SIGNATURE = b"\x89PNG\r\n\x1a\n"
TEXT_KEY = b"gsbench"
COLOURS = 256


def compact(png: bytes, scale: float = 1.0) -> bytes:
    """``png`` scaled by ``scale`` (Lanczos) and stored with a palette of `COLOURS` colours, no dithering."""
    with Image.open(io.BytesIO(png)) as image:
        rgb = image.convert("RGB")
    if scale != 1.0:
        rgb = rgb.resize((max(1, round(rgb.width * scale)), max(1, round(rgb.height * scale))),
                         Image.Resampling.LANCZOS)
    buffer = io.BytesIO()
    rgb.quantize(COLOURS, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE).save(buffer, "PNG", optimize=True)
    return buffer.getvalue()


def _chunks(png: bytes, name: str):
    """(type, data) of each chunk of ``png``; a GsbenchError naming ``name`` when it is no PNG."""
    if not png.startswith(SIGNATURE):
        raise GsbenchError(f"{name}: not a PNG file; fix: delete it (the report draws it again where it can)")
    at = len(SIGNATURE)
    while at + 8 <= len(png):
        length, kind = struct.unpack(">I4s", png[at:at + 8])
        yield kind, png[at + 8:at + 8 + length]
        at += 12 + length


def size(png: bytes, name: str = "picture") -> tuple[int, int]:
    """(width, height) from the PNG's header."""
    kind, data = next(_chunks(png, name), (b"", b""))
    if kind != b"IHDR":
        raise GsbenchError(f"{name}: a PNG without its header; fix: delete it (the report draws it again where it can)")
    return struct.unpack(">II", data[:8])


def with_text(png: bytes, about: dict) -> bytes:
    """``png`` with ``about`` (JSON) in a ``gsbench`` text chunk right after the header; pixels unchanged."""
    data = TEXT_KEY + b"\0" + json.dumps(about, sort_keys=True).encode("latin-1")
    chunk = struct.pack(">I4s", len(data), b"tEXt") + data + struct.pack(">I", zlib.crc32(b"tEXt" + data))
    header_end = len(SIGNATURE) + 8 + 13 + 4  # the IHDR chunk is 13 bytes of data, always first
    return png[:header_end] + chunk + png[header_end:]


def text(png: bytes, name: str = "picture") -> dict:
    """What `with_text` wrote into ``png``; empty when it holds no ``gsbench`` chunk."""
    for kind, data in _chunks(png, name):
        if kind == b"tEXt" and data.startswith(TEXT_KEY + b"\0"):
            try:
                return json.loads(data[len(TEXT_KEY) + 1:].decode("latin-1"))
            except ValueError:
                return {}
    return {}
