"""FlashForge ``.gx`` container (``xgcode 1.0``): a binary header, a BMP thumbnail, then G-code.

Layout (little-endian), as FlashPrint writes it::

    0   "xgcode 1.0\\n\\0"        12 bytes
    12  int32  0
    16  uint32 thumbnail offset   (58)
    20  uint32 G-code offset
    24  uint32 G-code offset      (again)
    28  uint32 print time, s
    32  uint32 filament used, right extruder, mm
    36  uint32 filament used, left extruder, mm
    40  uint16 multi-extruder type
    42  uint16 layer height, um
    44  uint16 (reserved), shells, print speed, bed temperature, nozzle temperatures ...
    58  BMP thumbnail, up to the G-code offset

The G-code that follows is ordinary text. :func:`decode_gx` returns it with the
header's statements appended as ``;`` comments (at the end, so that line
numbers stay those of the G-code).
"""

from __future__ import annotations

import struct

from layerwatch.errors import GcodeError

__all__ = ["MAGIC", "decode_gx"]

MAGIC = b"xgcode 1.0"
_HEADER = struct.Struct("<12sIIIIIIIHH")
_THUMB_AT = 58


def decode_gx(data: bytes, name: str = "<memory>") -> bytes:
    """The G-code text inside a ``.gx`` file, header statements appended as comments.

    Raises
    ------
    GcodeError
        Truncated header or a G-code offset outside the file.
    """
    if len(data) < _THUMB_AT:
        raise GcodeError(f"{name}: FlashForge .gx header truncated ({len(data)} bytes); export the file again.")
    (_magic, _zero, thumb_at, gcode_at, _gcode_at2, seconds, fil_right, fil_left, _multi,
     layer_um) = _HEADER.unpack_from(data, 0)
    if not (_THUMB_AT <= gcode_at <= len(data)) or thumb_at > gcode_at:
        raise GcodeError(
            f"{name}: FlashForge .gx header gives the G-code at byte {gcode_at} in a {len(data)}-byte file "
            "(damaged file); export it again from FlashPrint."
        )
    text = data[gcode_at:]
    notes = [
        "; xgcode header statements:",
        f"; filament used [mm] = {fil_right}, {fil_left}",
        f"; estimated printing time [s] = {seconds}",
    ]
    if layer_um:
        notes.append(f"; layer_height = {layer_um / 1000:g}")
    sep = b"" if text.endswith(b"\n") or not text else b"\n"
    return text + sep + "\n".join(notes).encode() + b"\n"
