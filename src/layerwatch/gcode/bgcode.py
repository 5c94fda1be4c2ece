"""PrusaSlicer binary G-code (``.bgcode``) container: read the G-code blocks.

Blocks stored uncompressed or deflate-compressed, unencoded, are decoded;
heatshrink compression or MeatPack encoding are refused with a message that
names the fix (export ASCII G-code).
"""

from __future__ import annotations

import struct
import zlib

from layerwatch.errors import GcodeError

__all__ = ["decode_bgcode"]

_GCODE_BLOCK = 1
_COMPRESSION = {0: "none", 1: "deflate", 2: "heatshrink 11,4", 3: "heatshrink 12,4"}
_ENCODING = {0: "none", 1: "MeatPack", 2: "MeatPack with comments"}


def decode_bgcode(data: bytes, name: str = "<memory>") -> bytes:
    """The concatenated G-code text of a ``.bgcode`` file, as bytes."""
    if len(data) < 10 or data[:4] != b"GCDE":
        raise GcodeError(f"{name}: not a binary G-code file (no GCDE header).")
    _version, checksum_type = struct.unpack_from("<IH", data, 4)
    crc = 4 if checksum_type == 1 else 0
    i, out = 10, []
    while i < len(data):
        if i + 8 > len(data):
            raise GcodeError(f"{name}: truncated binary G-code at byte {i}; export the file again.")
        btype, comp, usize = struct.unpack_from("<HHI", data, i)
        i += 8
        csize = usize
        if comp:
            csize = struct.unpack_from("<I", data, i)[0]
            i += 4
        plen = 6 if btype == 5 else 2
        enc = struct.unpack_from("<H", data, i)[0] if i + 2 <= len(data) else 0
        payload = data[i + plen : i + plen + csize]
        i += plen + csize + crc
        if btype != _GCODE_BLOCK:
            continue
        if comp not in (0, 1) or enc != 0:
            raise GcodeError(
                f"{name}: binary G-code uses {_COMPRESSION.get(comp, comp)} compression and "
                f"{_ENCODING.get(enc, enc)} encoding, which layerwatch does not read; "
                "export ASCII G-code instead (PrusaSlicer: Printer Settings > General > Binary G-code off)."
            )
        out.append(zlib.decompress(payload) if comp == 1 else payload)
    if not out:
        raise GcodeError(f"{name}: binary G-code holds no G-code blocks; export the file again.")
    return b"".join(out)
