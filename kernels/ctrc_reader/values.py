"""The JSON value readers of the compiled CTRC reader: whitespace, strings, exact numbers, words."""

# Warp needs typed constructors (int(0), wp.float64(0.0)) for variables a loop modifies.
# ruff: noqa: UP018

from __future__ import annotations

import warp as wp

from physcene.kernels.ctrc_reader.codes import (
    FNV_OFFSET_U64,
    FNV_PRIME_U64,
    PI,
    S_SYNTAX,
    TWO_PI,
    V_FLOAT,
    V_INT,
)

# Small CUDA blocks: a text's work is serial, latency-bound (512 texts -> 128 blocks on an
# H100/H200's 132 SMs, where Warp's default of 256 would put them on two). One block size per
# module: Warp compiles a module once per block size.
wp.set_module_options({"enable_backward": False, "block_dim": 4})

__all__ = [
    "after_value",
    "hash_span",
    "hex_digit",
    "is_word",
    "lookup_slot",
    "match_word",
    "same_bytes",
    "scan_number",
    "scan_number_array",
    "scan_string",
    "skip_ws",
    "visible_ascii",
    "wrap_angle",
]


@wp.func
def skip_ws(text: wp.array(dtype=wp.uint8), p: int, end: int):
    """First position >= p that is not JSON whitespace (space, tab, LF, CR)."""
    q = p
    while q < end:
        b = int(text[q])
        if b == 32 or b == 10 or b == 13 or b == 9:
            q += 1
        else:
            return q
    return q


@wp.func
def hex_digit(b: int):
    return (b >= 48 and b <= 57) or (b >= 65 and b <= 70) or (b >= 97 and b <= 102)


@wp.func
def scan_string(text: wp.array(dtype=wp.uint8), p: int, end: int):
    """A JSON string at p (the opening quote): (position after it or -1, 1 if it holds escapes).

    strict=False JSON: raw control bytes are allowed; escapes are validated (\\uXXXX needs 4 hex
    digits) but not decoded, so a string with escapes is never compared or hashed by content.
    Nothing else per byte: strings whose content matters are hashed afterwards (hash_span).
    """
    escaped = int(0)
    q = p + 1
    while q < end:
        b = int(text[q])
        if b == 34:
            return q + 1, escaped
        if b == 92:
            escaped = int(1)
            if q + 1 >= end:
                return -1, escaped
            e = int(text[q + 1])
            if e == 117:
                if q + 5 >= end:
                    return -1, escaped
                if not (
                    hex_digit(int(text[q + 2]))
                    and hex_digit(int(text[q + 3]))
                    and hex_digit(int(text[q + 4]))
                    and hex_digit(int(text[q + 5]))
                ):
                    return -1, escaped
                q += 6
            elif e == 34 or e == 92 or e == 47 or e == 98 or e == 102 or e == 110 or e == 114 or e == 116:
                q += 2
            else:
                return -1, escaped
        else:
            q += 1
    return -1, escaped


@wp.func
def hash_span(text: wp.array(dtype=wp.uint8), s: int, n: int):
    """(FNV-1a 64-bit hash, 31-polynomial 32-bit hash) of text[s:s+n] (category_hash on the host)."""
    h = FNV_OFFSET_U64
    h2 = wp.uint32(0)
    for i in range(n):
        b = text[s + i]
        h = (h ^ wp.uint64(b)) * FNV_PRIME_U64
        h2 = h2 * wp.uint32(31) + wp.uint32(b)
    return h, h2


@wp.func
def visible_ascii(text: wp.array(dtype=wp.uint8), s: int, n: int):
    """1 if text[s:s+n] has a visible ASCII byte (then str.strip() cannot leave it empty)."""
    for i in range(n):
        b = int(text[s + i])
        if b > 32 and b < 127:
            return 1
    return 0


@wp.func
def scan_number(text: wp.array(dtype=wp.uint8), p: int, end: int):
    """A JSON number at p without exponent. Returns (position after it, value, kind, status):
    kind V_INT or V_FLOAT; status 0 or a negative code (-2 syntax, -4 outside the exact subset)."""
    q = p
    neg = int(0)
    if q < end and int(text[q]) == 45:
        neg = int(1)
        q += 1
    if q >= end:
        return q, wp.float64(0.0), V_INT, -2
    b = int(text[q])
    if b < 48 or b > 57:
        return q, wp.float64(0.0), V_INT, -2
    mant = wp.int64(0)
    digits = int(0)  # significant digits in mant
    scale = int(0)  # digits after the point
    if b == 48:
        q += 1  # a leading 0 stands alone; a digit after it is a syntax error caught by the caller
    else:
        while q < end:
            b = int(text[q])
            if b < 48 or b > 57:
                break
            mant = mant * wp.int64(10) + wp.int64(b - 48)
            digits += 1
            q += 1
            if digits > 15:
                return q, wp.float64(0.0), V_INT, -4
    kind = V_INT
    if q < end and int(text[q]) == 46:
        kind = V_FLOAT
        q += 1
        start = q
        while q < end:
            b = int(text[q])
            if b < 48 or b > 57:
                break
            mant = mant * wp.int64(10) + wp.int64(b - 48)
            if mant != wp.int64(0):
                digits += 1
            scale += 1
            q += 1
            if digits > 15 or scale > 22:
                return q, wp.float64(0.0), V_INT, -4
        if q == start:
            return q, wp.float64(0.0), V_INT, -2
    if q < end:
        b = int(text[q])
        if b == 101 or b == 69:
            return q, wp.float64(0.0), V_INT, -4
    p10 = wp.float64(1.0)
    for _k in range(scale):
        p10 = p10 * wp.float64(10.0)  # exact: 10^k is a float64 for k <= 22
    v = wp.float64(mant) / p10
    if neg == 1:
        v = -v
    return q, v, kind, 0


@wp.func
def after_value(text: wp.array(dtype=wp.uint8), p: int, end: int, close: int):
    """The step after a value inside a JSON array or object closed by byte ``close`` (93 ']',
    125 '}'): (position after the ',' or the close, 1 if it closed, 0 if a ',' follows, or
    -2 when neither comes)."""
    p = skip_ws(text, p, end)
    if p >= end:
        return p, S_SYNTAX
    b = int(text[p])
    p += 1
    if b == close:
        return p, int(1)
    if b != 44:
        return p, S_SYNTAX
    return p, int(0)


@wp.func
def scan_number_array(
    text: wp.array(dtype=wp.uint8), p: int, end: int, out: wp.array2d(dtype=wp.float64), row: int, cap: int
):
    """The numbers of a JSON array whose '[' is just before p: (position after its ']', count,
    status); the first ``cap`` values go to out[row, 0:cap]. Status 0, or a negative code
    (scan_number's, or -2 for a malformed array)."""
    n = int(0)
    p = skip_ws(text, p, end)
    if p < end and int(text[p]) == 93:
        return p + 1, n, int(0)
    while True:
        p = skip_ws(text, p, end)
        q, v, kind, st = scan_number(text, p, end)
        if st != 0:
            return p, n, st
        if n < cap:
            out[row, n] = v
        n += 1
        p, sep = after_value(text, q, end, 93)
        if sep == 1:
            return p, n, int(0)
        if sep < 0:
            return p, n, sep
    return p, n, S_SYNTAX


@wp.func
def match_word(
    text: wp.array(dtype=wp.uint8),
    s: int,
    n: int,
    words: wp.array(dtype=wp.uint8),
    word_start: wp.array(dtype=wp.int32),
    first: int,
    last: int,
):
    """Index in [first, last) of the known word equal to text[s:s+n] (length, then bytes), or -1."""
    for k in range(first, last):
        ws = word_start[k]
        if word_start[k + 1] - ws == n:
            same = int(1)
            for i in range(n):
                if text[s + i] != words[ws + i]:
                    same = int(0)
                    break
            if same == 1:
                return k
    return -1


@wp.func
def is_word(
    text: wp.array(dtype=wp.uint8),
    s: int,
    n: int,
    words: wp.array(dtype=wp.uint8),
    word_start: wp.array(dtype=wp.int32),
    k: int,
):
    """1 if text[s:s+n] is known word k."""
    return wp.where(match_word(text, s, n, words, word_start, k, k + 1) >= 0, 1, 0)


@wp.func
def same_bytes(text: wp.array(dtype=wp.uint8), a: int, b: int, n: int):
    for i in range(n):
        if text[a + i] != text[b + i]:
            return 0
    return 1


@wp.func
def wrap_angle(a: wp.float64):
    """Python's (a + pi) % (2 pi) - pi (the remainder takes the divisor's sign)."""
    r = wp.mod(a + PI, TWO_PI)
    if r != wp.float64(0.0) and r < wp.float64(0.0):
        r = r + TWO_PI
    return r - PI


@wp.func
def lookup_slot(
    key: wp.uint64,
    check: wp.uint64,
    table_key: wp.array(dtype=wp.uint64),
    table_check: wp.array(dtype=wp.uint64),
    table_slot: wp.array(dtype=wp.int32),
    n_table: int,
):
    """The asset slot of a category hash in the sorted table, or -1 (absent or check mismatch)."""
    lo = int(0)
    hi = n_table
    while lo < hi:
        mid = (lo + hi) // 2
        if table_key[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    if lo < n_table:
        if table_key[lo] == key and table_check[lo] == check:
            return table_slot[lo]
    return -1
