"""Byte-level G-code lexer for the kernel: one line at a time, no ``str`` copies.

Numba compiles these functions into :func:`layerwatch.gcode.kernel.run_kernel`
(``inline="always"``), so this file is one of the kernel's cache keys
(:data:`layerwatch.gcode.jit_cache.KERNEL_SOURCES`).
"""

from __future__ import annotations

__all__ = ["lex_line", "parse_num", "count_g_lines"]

import math

import numba as nb
import numpy as np

# ---- byte codes
NL, CR, TAB, SPACE = 10, 13, 9, 32
SEMICOLON, LPAREN, RPAREN, ASTERISK = 59, 40, 41, 42
PLUS, MINUS, DOT, DIGIT_0, DIGIT_9 = 43, 45, 46, 48, 57
UPPER_A, UPPER_Z, LOWER_A, LOWER_Z, UNDERSCORE = 65, 90, 97, 122, 95
PRINTABLE_MIN, ASCII_END = 32, 128
CASE_BIT = 32
# ---- word letters, as offsets from 'A'
W_A, W_D, W_E, W_F, W_G, W_I, W_J = 0, 3, 4, 5, 6, 8, 9
W_M, W_R, W_S, W_T, W_X, W_Y, W_Z = 12, 17, 18, 19, 23, 24, 25
N_WORDS = 26
MAX_G = 4  # G words kept per line
# ---- what was wrong with a line (bit flags)
BAD_BYTES = 1  # non-text bytes
BAD_WORD = 2  # a malformed number or a stray character ('E1.2.3', 'X--1', '%')

_POW10 = np.array([10.0**k for k in range(309)])
#: first characters of ';' comments worth handing to the tag decoder
_TAG_FIRST = np.zeros(256, np.bool_)
for _c in b"LlZzTtFfCcBb'Ee":
    _TAG_FIRST[_c] = True


@nb.njit(cache=True, inline="always")
def _is_digit(c):
    return DIGIT_0 <= c <= DIGIT_9


@nb.njit(cache=True, inline="always")
def _is_letter(c):
    return (UPPER_A <= c <= UPPER_Z) or (LOWER_A <= c <= LOWER_Z)


@nb.njit(cache=True, inline="always")
def parse_num(buf, i, n):
    """Parse a decimal number at ``buf[i:]`` (no exponent: ``E`` is an axis); returns (value, next_i, ok).

    Digits accumulate in an integer mantissa (exact, one multiply-add per digit) scaled once
    by a power of ten; beyond 18 significant digits the rest only shift the exponent.
    """
    while i < n and (buf[i] == SPACE or buf[i] == TAB):
        i += 1
    neg = False
    if i < n and (buf[i] == MINUS or buf[i] == PLUS):
        neg = buf[i] == MINUS
        i += 1
    mant = 0
    nd = 0
    exp10 = 0
    i0 = i
    while i < n and _is_digit(buf[i]):
        if nd < 18:
            mant = mant * 10 + (buf[i] - DIGIT_0)
            nd += 1 if (mant > 0) else 0
        else:
            exp10 += 1
        i += 1
    ok = i > i0
    if i < n and buf[i] == DOT:
        i += 1
        while i < n and _is_digit(buf[i]):
            if nd < 18:
                mant = mant * 10 + (buf[i] - DIGIT_0)
                nd += 1 if (mant > 0) else 0
                exp10 -= 1
            i += 1
            ok = True
    val = float(mant)
    if exp10 < 0:
        val /= _POW10[min(-exp10, 308)]
    elif exp10 > 0:
        val *= _POW10[min(exp10, 308)]
    return -val if neg else val, i, ok


@nb.njit(cache=True, inline="always")
def _to_eol(buf, i, n):
    while i < n and buf[i] != NL:
        i += 1
    return i


@nb.njit(cache=True)
def count_g_lines(buf):
    """Lines whose first non-blank byte is ``G``/``g``: the segment capacity to start with."""
    cap = 16
    at_start = True
    for k in range(buf.shape[0]):
        c = buf[k]
        if c == NL:
            at_start = True
        elif at_start and c != SPACE and c != TAB:
            if c == UPPER_A + W_G or c == LOWER_A + W_G:
                cap += 1
            at_start = False
    return cap


@nb.njit(cache=True, inline="always")
def lex_line(buf, i, n, val, has, gcodes):
    """Lex one line from ``buf[i]`` into ``val``/``has`` (by letter) and ``gcodes``.

    Returns ``(i_at_newline, n_g, m_code, comment_at, bad, extended)``: the G
    words, the first M code (-1 none), the byte offset of a ``;`` comment
    that may be a tag (-1 none), ``BAD_*`` flags (non-text bytes, malformed
    words; what could not be read is ignored), and whether it was an extended
    (macro) command.
    """
    has[:] = False
    ng = 0
    mcode = -1
    cmt_at = -1
    bad = 0
    first = True
    while i < n and buf[i] != NL:
        c = buf[i]
        if c == SEMICOLON:
            j = i + 1
            while j < n and (buf[j] == SPACE or buf[j] == TAB):
                j += 1
            if j < n and _TAG_FIRST[buf[j]]:
                cmt_at = i
            return _to_eol(buf, i, n), ng, mcode, cmt_at, bad, False
        if c == LPAREN:  # '(' comment; Skeinforge nests them: '(<setting> Space_(mm): 2.0 </setting>)'
            depth = 0
            while i < n and buf[i] != NL:
                depth += 1 if buf[i] == LPAREN else (-1 if buf[i] == RPAREN else 0)
                i += 1
                if depth == 0:
                    break
            continue
        if c == SPACE or c == TAB or c == CR:
            i += 1
            continue
        if c == ASTERISK:  # checksum: rest of line
            return _to_eol(buf, i, n), ng, mcode, cmt_at, bad, False
        if _is_letter(c):
            if first and i + 1 < n and (_is_letter(buf[i + 1]) or buf[i + 1] == UNDERSCORE):
                return _to_eol(buf, i, n), 0, -1, cmt_at, bad, True  # Klipper macro ...: ignored
            first = False
            w = (c & ~CASE_BIT) - UPPER_A
            v, i, ok = parse_num(buf, i + 1, n)
            if w == W_G and ok:
                if ng < MAX_G:
                    gcodes[ng] = v
                    ng += 1
            elif w == W_M and ok:
                if mcode < 0:
                    mcode = int(v) if 0 <= v < 1e6 else 99999
                    if not (mcode == 82 or mcode == 83 or mcode == 101 or mcode == 103 or mcode == 200 or mcode == 221):
                        while i < n and buf[i] != NL and buf[i] != SEMICOLON:  # M117 text ...
                            i += 1
            else:
                has[w] = True
                val[w] = v if ok else math.nan  # a bare letter (G28 X) names the axis
            continue
        bad |= BAD_BYTES if (c >= ASCII_END or c < PRINTABLE_MIN) else BAD_WORD
        i += 1
    return i, ng, mcode, cmt_at, bad, False
