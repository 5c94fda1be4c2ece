"""PrusaSlicer binary G-code (``.bgcode``) container: read the G-code blocks.

G-code blocks may be stored raw, deflate- or heatshrink-compressed, plain or
MeatPack-encoded; all of these are decoded. Anything else is refused with a
message that names the fix (export ASCII G-code).
"""

from __future__ import annotations

import struct
import zlib

from layerwatch.errors import GcodeError

__all__ = ["decode_bgcode"]

_GCODE_BLOCK = 1
_COMPRESSION = {0: "none", 1: "deflate", 2: "heatshrink 11,4", 3: "heatshrink 12,4"}
_ENCODING = {0: "none", 1: "MeatPack", 2: "MeatPack with comments"}


def _decode_block(payload: bytes, comp: int, enc: int, usize: int) -> bytes | None:
    from layerwatch.gcode.bgcode_codecs import heatshrink_decode, meatpack_decode

    if comp == 0:
        raw = payload
    elif comp == 1:
        try:
            raw = zlib.decompress(payload)
        except zlib.error:
            return None
    elif comp in (2, 3):
        raw = heatshrink_decode(payload, usize, 11 if comp == 2 else 12, 4)
    else:
        return None
    if raw is None:
        return None
    if enc == 0:
        return raw
    if enc in (1, 2):
        return meatpack_decode(raw)
    return None


def decode_bgcode(data: bytes, name: str = "<memory>") -> bytes:
    """The concatenated G-code text of a ``.bgcode`` file, as bytes."""
    if len(data) < 10 or data[:4] != b"GCDE":
        raise GcodeError(f"{name}: not a binary G-code file (no GCDE header).")
    _version, checksum_type = struct.unpack_from("<IH", data, 4)
    crc = 4 if checksum_type == 1 else 0
    i, out, head, tail = 10, [], [], []
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
        if btype in (0, 2) and comp in (0, 1):  # file / slicer metadata (INI lines) as comments
            try:
                meta = zlib.decompress(payload) if comp else payload
            except zlib.error:
                meta = b""
            lines = [b"; " + ln for ln in meta.splitlines() if ln.strip()]
            (head if btype == 0 else tail).extend(lines)
        if btype != _GCODE_BLOCK:
            continue
        text = _decode_block(payload, comp, enc, usize)
        if text is None:
            raise GcodeError(
                f"{name}: binary G-code uses {_COMPRESSION.get(comp, comp)} compression and "
                f"{_ENCODING.get(enc, enc)} encoding, which layerwatch does not read; "
                "export ASCII G-code instead (PrusaSlicer: Printer Settings > General > Binary G-code off)."
            )
        out.append(text)
    if not out:
        raise GcodeError(f"{name}: binary G-code holds no G-code blocks; export the file again.")
    text = b"".join(out)
    if head:
        text = b"\n".join(head) + b"\n" + text
    if tail:
        text = text + (b"" if text.endswith(b"\n") else b"\n") + b"\n".join(tail) + b"\n"
    return text
