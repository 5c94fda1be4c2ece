"""Decoders used by PrusaSlicer binary G-code: heatshrink (LZSS) and MeatPack.

Both are small state machines over bytes, written from the formats'
public descriptions (heatshrink: tag bit, 8-bit literal or W-bit index +
L-bit count back-reference, MSB-first; MeatPack: two 4-bit characters per
byte from the table ``0123456789. \\nGX``, nibble ``0xF`` = a full byte
follows, ``0xFF 0xFF <cmd>`` signals).
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["heatshrink_decode", "meatpack_decode"]


@nb.njit(cache=True)
def _heatshrink(src, out_size, window_bits, count_bits):
    out = np.empty(out_size, np.uint8)
    n_out = 0
    nbits = src.shape[0] * 8
    pos = 0  # bit position
    while n_out < out_size:
        if pos + 1 > nbits:
            break
        tag = (src[pos >> 3] >> (7 - (pos & 7))) & 1
        pos += 1
        if tag == 1:
            if pos + 8 > nbits:
                break
            v = 0
            for _ in range(8):
                v = (v << 1) | ((src[pos >> 3] >> (7 - (pos & 7))) & 1)
                pos += 1
            out[n_out] = v
            n_out += 1
        else:
            if pos + window_bits + count_bits > nbits:
                break
            idx = 0
            for _ in range(window_bits):
                idx = (idx << 1) | ((src[pos >> 3] >> (7 - (pos & 7))) & 1)
                pos += 1
            cnt = 0
            for _ in range(count_bits):
                cnt = (cnt << 1) | ((src[pos >> 3] >> (7 - (pos & 7))) & 1)
                pos += 1
            idx += 1
            cnt += 1
            if idx > n_out:
                return out[:0], False
            for _ in range(cnt):
                if n_out >= out_size:
                    break
                out[n_out] = out[n_out - idx]
                n_out += 1
    return out[:n_out], n_out == out_size


def heatshrink_decode(src: bytes, out_size: int, window_bits: int, count_bits: int) -> bytes | None:
    """Decompress heatshrink data; ``None`` when the stream is corrupt or short."""
    out, ok = _heatshrink(np.frombuffer(src, np.uint8), out_size, window_bits, count_bits)
    return out.tobytes() if ok else None


_TABLE = np.frombuffer(b"0123456789. \nGX", np.uint8)


@nb.njit(cache=True, inline="always")
def _meatpack_command(c, packing, nospace):
    """``(packing, nospace)`` after the command byte ``c`` of a ``0xFF 0xFF <c>`` signal."""
    if c == 251:
        packing = True
    elif c == 250 or c == 249:
        packing = False
    elif c == 247:
        nospace = True
    elif c == 246:
        nospace = False
    return packing, nospace


@nb.njit(cache=True, inline="always")
def _meatpack_chars(c, nospace, table):
    """The two characters of packed byte ``c``, low nibble first: ``(c0, c1, first_full,
    second_full)``; nibble ``0xF`` means a full byte follows instead (its character is 0)."""
    lo = c & 15
    hi = (c >> 4) & 15
    first_full = lo == 15
    second_full = hi == 15
    c0 = table[lo] if not first_full else 0
    c1 = table[hi] if not second_full else 0
    if nospace:
        if lo == 11:
            c0 = 69
        if hi == 11:
            c1 = 69
    return c0, c1, first_full, second_full


@nb.njit(cache=True)
def _meatpack(src, table):
    out = np.empty(src.shape[0] * 2 + 16, np.uint8)
    n = 0
    packing = False
    nospace = False
    cmd_count = 0
    cmd_active = False
    full_queue = 0
    char_buf = 0
    for k in range(src.shape[0] + 1):
        # a trailing lone 0xFF is data: flushed by the sentinel pass k == len
        if k == src.shape[0]:
            if cmd_count > 0 and not cmd_active:
                c = 255
                cmd_count = 0
            else:
                break
        else:
            c = src[k]
            if c == 255:
                if cmd_count > 0:
                    cmd_active = True
                    cmd_count = 0
                else:
                    cmd_count += 1
                continue
            if cmd_active:
                packing, nospace = _meatpack_command(c, packing, nospace)
                cmd_active = False
                continue
            if cmd_count > 0:  # a single 0xFF was data: decode it before c
                cmd_count = 0
                if not packing:
                    out[n] = 255
                    n += 1
                elif full_queue > 0:
                    out[n] = 255
                    n += 1
                    if char_buf > 0:
                        out[n] = char_buf
                        n += 1
                        char_buf = 0
                    full_queue -= 1
                else:
                    full_queue += 2  # 0xFF = both nibbles full bytes
        if not packing:
            out[n] = c
            n += 1
            continue
        if full_queue > 0:
            out[n] = c
            n += 1
            if char_buf > 0:
                out[n] = char_buf
                n += 1
                char_buf = 0
            full_queue -= 1
            continue
        c0, c1, first_full, second_full = _meatpack_chars(c, nospace, table)
        if first_full:
            full_queue += 1
            if second_full:
                full_queue += 1
            else:
                char_buf = c1
        else:
            out[n] = c0
            n += 1
            if c0 != 10:
                if second_full:
                    full_queue += 1
                else:
                    out[n] = c1
                    n += 1
        if n + 4 >= out.shape[0]:
            grown = np.empty(out.shape[0] * 2, np.uint8)
            grown[:n] = out[:n]
            out = grown
    return out[:n]


def meatpack_decode(src: bytes) -> bytes:
    """Expand MeatPack-encoded G-code (spaces between words may be missing)."""
    return _meatpack(np.frombuffer(src, np.uint8), _TABLE).tobytes()
