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
    # the codecs are numba kernels (~0.3 s to import numba): only .bgcode files pay it, so a
    # cold `gcode info` of a text file starts without numba
    from layerwatch.gcode.bgcode_codecs import heatshrink_decode, meatpack_decode

    raw: bytes | None
    if comp == 0:
        raw = payload
    elif comp == 1:
        try:  # never more than the block says it holds (a damaged or hostile block cannot balloon)
            raw = zlib.decompressobj().decompress(payload, max(usize, 1))
        except zlib.error:
            return None
    elif comp in (2, 3):
        if usize > 8 * len(payload) + 64:  # heatshrink expands at most 8x (9 bits per literal byte)
            return None
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


def _u(fmt: str, data: bytes, at: int, name: str) -> tuple:
    """``struct.unpack_from`` that names a damaged container instead of raising ``struct.error``."""
    if at < 0 or at + struct.calcsize(fmt) > len(data):
        raise GcodeError(f"{name}: binary G-code truncated or damaged at byte {at}; export the file again.")
    return struct.unpack_from(fmt, data, at)


def _metadata_lines(payload: bytes, comp: int) -> list[bytes]:
    """INI-style ``key=value`` metadata as ``; key=value`` comment lines (unreadable blocks: none)."""
    try:
        meta = zlib.decompressobj().decompress(payload, 1 << 22) if comp else payload[: 1 << 22]
    except zlib.error:
        return []
    return [b"; " + ln for ln in meta.splitlines() if ln.strip()]


def decode_bgcode(data: bytes, name: str = "<memory>") -> bytes:
    """The concatenated G-code text of a ``.bgcode`` file, as bytes.

    The file, printer and print metadata blocks (types 0, 3, 4: producer, filament
    used, ...) come first as ``; key=value`` comments, the slicer's settings
    (type 2) last, as PrusaSlicer places them in its ASCII export.

    Raises
    ------
    GcodeError
        Not a ``.bgcode``, truncated or damaged blocks, or an encoding layerwatch
        does not read.
    """
    if len(data) < 10 or data[:4] != b"GCDE":
        raise GcodeError(f"{name}: not a binary G-code file (no GCDE header).")
    _version, checksum_type = _u("<IH", data, 4, name)
    crc = 4 if checksum_type == 1 else 0
    i = 10
    out: list[bytes] = []
    head: list[bytes] = []
    tail: list[bytes] = []
    while i < len(data):
        btype, comp, usize = _u("<HHI", data, i, name)
        i += 8
        csize = usize
        if comp:
            csize = _u("<I", data, i, name)[0]
            i += 4
        plen = 6 if btype == 5 else 2
        enc = _u("<H", data, i, name)[0] if btype == _GCODE_BLOCK else 0
        if i + plen + csize > len(data):
            raise GcodeError(f"{name}: binary G-code block at byte {i} runs past the end of the file "
                             "(truncated download?); export the file again.")
        payload = data[i + plen : i + plen + csize]
        i += plen + csize + crc
        if btype in (0, 2, 3, 4) and comp in (0, 1):
            (tail if btype == 2 else head).extend(_metadata_lines(payload, comp))
        if btype != _GCODE_BLOCK:
            continue
        text = _decode_block(payload, comp, enc, usize)
        if text is None:
            raise GcodeError(
                f"{name}: binary G-code uses {_COMPRESSION.get(comp, comp)} compression and "
                f"{_ENCODING.get(enc, enc)} encoding, which layerwatch does not read (or the block is damaged); "
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
