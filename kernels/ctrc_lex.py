"""Lexing kernels of the compiled CTRC reader (kernels/ctrc_scan.py): prescan, emit, entries.

Byte-level pieces of the reward's fast path: ``prescan`` (patterns, marker, entry candidates per
chunk), ``emit`` (candidate positions) and ``entries`` (one layered entry per candidate, read
speculatively), with the JSON lexing helpers and constants ``ctrc_scan.walk`` shares. The design,
the fallback rule and the status codes are in kernels/ctrc_scan.py and docs/physics.md.
"""

# Warp needs typed constructors (int(0), wp.float64(0.0)) for variables a loop modifies.
# ruff: noqa: UP018

from __future__ import annotations

import numpy as np
import warp as wp

from physcene.ctrc import MAX_ABS_CM, ON_CONTACT_GAP_CM

wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
# Small CUDA blocks, as in ctrc_scan: a text's entries share a warp (few divergent paths). One
# block size per module: Warp compiles a module once per block size.
wp.set_module_options({"enable_backward": False, "block_dim": 4})
wp.init()

__all__ = ["CHUNK", "ENTRY_KEYS", "FNV_OFFSET", "FNV_PRIME", "MAX_ENTRIES", "STATUS", "TOP_KEYS",
           "category_hash", "emit", "entries", "keyword_table", "prescan"]

# Entries (the zone entry included) one text may hold on the fast path; more go to Python.
MAX_ENTRIES = 64
# Bytes per prescan thread.
CHUNK = wp.constant(256)
# |value| beyond this (cm) is refused by ctrc (MAX_ABS_CM); the absolute-position check uses a hair
# less so that a float64 ulp of difference with Python's libm never accepts what Python refuses.
_MAX_ABS = wp.constant(wp.float64(MAX_ABS_CM))
_MAX_ABS_POS = wp.constant(wp.float64(MAX_ABS_CM * (1.0 - 1.0e-9)))
_DEG = wp.constant(wp.float64(np.pi / 180.0))  # math.radians multiplies by exactly this
_ON_GAP = wp.constant(wp.float64(ON_CONTACT_GAP_CM))  # an on child's z base: its support's top + this
_PI = wp.constant(wp.float64(np.pi))
_TWO_PI = wp.constant(wp.float64(2.0 * np.pi))

FNV_OFFSET = 14695981039346656037
FNV_PRIME = 1099511628211
_FNV_OFFSET = wp.constant(wp.uint64(FNV_OFFSET))
_FNV_PRIME = wp.constant(wp.uint64(FNV_PRIME))

# Keys the scanner knows, in keyword-table order (their index is the key code below).
ENTRY_KEYS = ("layer", "instance_id", "category", "parent_id", "relation_type", "description",
              "relative_bbox", "relative_rotation_deg", "type", "bbox", "z_rotation")
TOP_KEYS = ("objects", "item_placement_zone")
K_LAYER, K_IID, K_CAT, K_PARENT, K_REL, K_DESC, K_BOX, K_ROT, K_TYPE, K_BBOX, K_ZROT = range(11)
K_OBJECTS, K_ZONE = 11, 12
# Constant strings compared by value.
_EXTRA_WORDS = ("root_zone", "zone", "in", "on", "near")
W_ROOT, W_ZONE, W_IN, W_ON, W_NEAR = 13, 14, 15, 16, 17

# status >= 0: objects read (the text is accepted). Negative: why it goes to the Python parser.
STATUS = {
    -1: "no 'Scene Layout' marker, or a code fence / <json> token elsewhere in the text",
    -2: "JSON outside the canonical subset (syntax, nesting, literal, escape in a name)",
    -3: "unknown or repeated key",
    -4: "number outside the exact subset (exponent, > 15 digits, magnitude)",
    -5: "value the layered decoder would refuse or reinterpret (type, relation, extent, blank id)",
    -6: "hierarchy the decoder would refuse (duplicate id, unknown parent, cycle)",
    -7: "more entries than MAX_ENTRIES",
    -8: "no zone (item_placement_zone or zone entry bbox) the decoder would accept",
    -9: "category not in the engine's table yet (resolved on the host, then rescanned)",
}
_S_MARKER, _S_SYNTAX, _S_KEY, _S_NUMBER, _S_VALUE, _S_TREE, _S_MANY, _S_ZONE, _S_CATEGORY = range(-1, -10, -1)
_E_NONE = wp.constant(-100)  # entries kernel: no candidate in this slot

# Value kinds of the generic value reader.
V_STRING, V_INT, V_FLOAT, V_NULL, V_BOOL, V_ARRAY = range(6)


def category_hash(data: bytes) -> tuple[int, int]:
    """(FNV-1a 64-bit hash, (len << 32) | 31-polynomial 32-bit hash) of ``data``, as the kernel."""
    h, h2 = FNV_OFFSET, 0
    for b in data:
        h = ((h ^ b) * FNV_PRIME) & 0xFFFFFFFFFFFFFFFF
        h2 = (h2 * 31 + b) & 0xFFFFFFFF
    return h, (len(data) << 32) | h2


def keyword_table() -> tuple[np.ndarray, np.ndarray]:
    """(bytes uint8, starts int32 (K+1,)) of every word the scanner compares against."""
    words = [w.encode() for w in (*ENTRY_KEYS, *TOP_KEYS, *_EXTRA_WORDS)]
    starts = np.concatenate([[0], np.cumsum([len(w) for w in words])]).astype(np.int32)
    return np.frombuffer(b"".join(words), np.uint8).copy(), starts


# Prescan ----------------------------------------------------------------------------------------
@wp.func
def text_of(offsets: wp.array(dtype=wp.int32), n_text: int, p: int):
    """The text index c with offsets[c] <= p < offsets[c+1] (binary search)."""
    lo = int(0)
    hi = n_text
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if offsets[mid] <= p:
            lo = mid
        else:
            hi = mid
    return lo


@wp.func
def ws_byte(b: int):
    return b == 32 or b == 10 or b == 13 or b == 9


@wp.func
def is_candidate(text: wp.array(dtype=wp.uint8), p: int, start: int):
    """1 if the '{' at p follows '[' or ',' (JSON whitespace between): where an entry can begin."""
    q = p - 1
    while q >= start and ws_byte(int(text[q])):
        q -= 1
    if q >= start:
        b = int(text[q])
        if b == 91 or b == 44:
            return 1
    return 0


@wp.func
def chunk_range(offsets: wp.array(dtype=wp.int32), chunk_start: wp.array(dtype=wp.int32), n_text: int,
                t: int):
    """(text c, first byte, end byte) of chunk t; every text has its own CHUNK-byte chunks."""
    c = text_of(chunk_start, n_text, t)
    p = offsets[c] + (t - chunk_start[c]) * CHUNK
    return c, p, wp.min(p + CHUNK, offsets[c + 1])


@wp.kernel
def prescan(text: wp.array(dtype=wp.uint8), offsets: wp.array(dtype=wp.int32),
            chunk_start: wp.array(dtype=wp.int32), n_text: int, flags: wp.array(dtype=wp.int32),
            marker: wp.array(dtype=wp.int32), cand_count: wp.array(dtype=wp.int32)):
    """Per chunk t: flags[c] = 1 if text c holds a fence or a <j / </ token, marker[c] = 1 + the
    last 'Scene Layout', cand_count[t] = entry candidates ('{' after '[' or ',') in the chunk."""
    t = wp.tid()
    c, p, end = chunk_range(offsets, chunk_start, n_text, t)
    start = offsets[c]
    stop = offsets[c + 1]
    count = int(0)
    while p < end:
        b = int(text[p])
        if b == 123:
            count += is_candidate(text, p, start)
        elif b == 96:
            if p + 2 < stop:
                if int(text[p + 1]) == 96 and int(text[p + 2]) == 96:
                    flags[c] = 1
        elif b == 60:
            # ctrc's </?json> token is re.I: '<' or '</' then j/J (no other character folds to j);
            # an end-of-text tag such as </s> stays on the fast path
            q = p + 1
            if q < stop and int(text[q]) == 47:
                q += 1
            if q < stop:
                n = int(text[q])
                if n == 106 or n == 74:
                    flags[c] = 1
        elif b == 83 and p + 12 <= stop:
            # "Scene Layout"
            if (int(text[p + 1]) == 99 and int(text[p + 2]) == 101 and int(text[p + 3]) == 110
                    and int(text[p + 4]) == 101 and int(text[p + 5]) == 32 and int(text[p + 6]) == 76
                    and int(text[p + 7]) == 97 and int(text[p + 8]) == 121 and int(text[p + 9]) == 111
                    and int(text[p + 10]) == 117 and int(text[p + 11]) == 116):
                wp.atomic_max(marker, c, p - start + 1)
        p += 1
    cand_count[t] = count


@wp.func
def first_candidate(chunk_start: wp.array(dtype=wp.int32), cand_count: wp.array(dtype=wp.int32),
                    cand_end: wp.array(dtype=wp.int32), c: int):
    """Global index of text c's first entry candidate (cand_end: inclusive cumsum of cand_count)."""
    t0 = chunk_start[c]
    return cand_end[t0] - cand_count[t0]


@wp.func
def n_candidates(chunk_start: wp.array(dtype=wp.int32), cand_count: wp.array(dtype=wp.int32),
                 cand_end: wp.array(dtype=wp.int32), c: int):
    """Entry candidates of text c kept (at most MAX_ENTRIES: later ones cannot be needed)."""
    n = cand_end[chunk_start[c + 1] - 1] - first_candidate(chunk_start, cand_count, cand_end, c)
    return wp.min(n, MAX_ENTRIES)


@wp.kernel
def emit(text: wp.array(dtype=wp.uint8), offsets: wp.array(dtype=wp.int32),
         chunk_start: wp.array(dtype=wp.int32), n_text: int, cand_count: wp.array(dtype=wp.int32),
         cand_end: wp.array(dtype=wp.int32), cand_pos: wp.array(dtype=wp.int32)):
    """cand_pos[c * MAX_ENTRIES + k] = byte position of text c's k-th entry candidate (ascending)."""
    t = wp.tid()
    c, p, end = chunk_range(offsets, chunk_start, n_text, t)
    start = offsets[c]
    k = cand_end[t] - cand_count[t] - first_candidate(chunk_start, cand_count, cand_end, c)
    while p < end and k < MAX_ENTRIES:
        if int(text[p]) == 123:
            if is_candidate(text, p, start) == 1:
                cand_pos[c * MAX_ENTRIES + k] = p
                k += 1
        p += 1


@wp.func
def find_candidate(cand_pos: wp.array(dtype=wp.int32), row0: int, n: int, p: int):
    """Row of the candidate at byte p among cand_pos[row0:row0+n] (ascending), or -1."""
    lo = int(0)
    hi = n
    while lo < hi:
        mid = (lo + hi) // 2
        if cand_pos[row0 + mid] < p:
            lo = mid + 1
        else:
            hi = mid
    if lo < n:
        if cand_pos[row0 + lo] == p:
            return row0 + lo
    return -1


# Lexing helpers ---------------------------------------------------------------------------------
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
                if not (hex_digit(int(text[q + 2])) and hex_digit(int(text[q + 3]))
                        and hex_digit(int(text[q + 4])) and hex_digit(int(text[q + 5]))):
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
    h = _FNV_OFFSET
    h2 = wp.uint32(0)
    for i in range(n):
        b = text[s + i]
        h = (h ^ wp.uint64(b)) * _FNV_PRIME
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
    scale = int(0)   # digits after the point
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
        return p, _S_SYNTAX
    b = int(text[p])
    p += 1
    if b == close:
        return p, int(1)
    if b != 44:
        return p, _S_SYNTAX
    return p, int(0)


@wp.func
def scan_number_array(text: wp.array(dtype=wp.uint8), p: int, end: int, out: wp.array2d(dtype=wp.float64),
                      row: int, cap: int):
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
    return p, n, _S_SYNTAX


@wp.func
def match_word(text: wp.array(dtype=wp.uint8), s: int, n: int, words: wp.array(dtype=wp.uint8),
               word_start: wp.array(dtype=wp.int32), first: int, last: int):
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
def is_word(text: wp.array(dtype=wp.uint8), s: int, n: int, words: wp.array(dtype=wp.uint8),
            word_start: wp.array(dtype=wp.int32), k: int):
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
    r = wp.mod(a + _PI, _TWO_PI)
    if r != wp.float64(0.0) and r < wp.float64(0.0):
        r = r + _TWO_PI
    return r - _PI


@wp.func
def lookup_slot(key: wp.uint64, check: wp.uint64, table_key: wp.array(dtype=wp.uint64),
                table_check: wp.array(dtype=wp.uint64), table_slot: wp.array(dtype=wp.int32), n_table: int):
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


# Scan -------------------------------------------------------------------------------------------
@wp.kernel
def entries(text: wp.array(dtype=wp.uint8), offsets: wp.array(dtype=wp.int32),
            chunk_start: wp.array(dtype=wp.int32), flags: wp.array(dtype=wp.int32),
            marker: wp.array(dtype=wp.int32), cand_count: wp.array(dtype=wp.int32),
            cand_end: wp.array(dtype=wp.int32), cand_pos: wp.array(dtype=wp.int32),
            words: wp.array(dtype=wp.uint8), word_start: wp.array(dtype=wp.int32),
            table_key: wp.array(dtype=wp.uint64), table_check: wp.array(dtype=wp.uint64),
            table_slot: wp.array(dtype=wp.int32), n_table: int,
            ent_f: wp.array2d(dtype=wp.float64), ent_i: wp.array2d(dtype=wp.int32),
            ent_h: wp.array2d(dtype=wp.uint64), arr: wp.array2d(dtype=wp.float64),
            e_stat: wp.array(dtype=wp.int32), e_end: wp.array(dtype=wp.int32)):
    """Candidate entry s = c * MAX_ENTRIES + k of text c, read on its own (speculatively).

    e_stat[s]: 0 an object entry ctrc.decode accepts (its fields in row s of ent_f / ent_i /
    ent_h, see ``walk``), 1 a zone entry (bbox[:4] in ent_f[s, 8:12], its length in ent_i[s, 6]),
    a negative STATUS code, or _E_NONE when there is no candidate; e_end[s] the position after
    its closing brace. Whether the candidate is really an entry is decided by ``walk``.
    """
    s = wp.tid()
    c = s // MAX_ENTRIES
    ke = s - c * MAX_ENTRIES
    e_stat[s] = _E_NONE
    if flags[c] != 0 or marker[c] == 0:
        return
    if ke >= n_candidates(chunk_start, cand_count, cand_end, c):
        return
    p = cand_pos[s]
    if p < offsets[c] + marker[c] - 1:
        return  # before the layout's marker: never part of it
    end = offsets[c + 1]
    p += 1
    seen = int(0)
    iid_s = int(-1)
    iid_n = int(0)
    iid_h = wp.uint64(0)
    iid_vis = int(0)
    cat_ok = int(0)
    cat_s = int(0)
    cat_n = int(0)
    cat_h = wp.uint64(0)
    cat_chk = wp.uint64(0)
    par_s = int(-1)
    par_n = int(0)
    par_h = wp.uint64(0)
    rel = int(-1)
    is_zone_type = int(0)
    bad = int(0)          # a value Python would refuse for an object entry
    box_ok = int(0)
    bbox_n = int(0)
    rot = wp.float64(0.0)
    slot = s
    efirst = int(1)
    while True:
        p = skip_ws(text, p, end)
        if p >= end:
            e_stat[s] = _S_SYNTAX
            return
        b = int(text[p])
        if b == 125 and efirst == 1:
            p += 1
            break
        efirst = int(0)
        if b != 34:
            e_stat[s] = _S_SYNTAX
            return
        q, kesc = scan_string(text, p, end)
        if q < 0 or kesc == 1:
            e_stat[s] = _S_SYNTAX
            return
        key = match_word(text, p + 1, q - p - 2, words, word_start, 0, K_ZROT + 1)
        if key < 0 or (seen & (1 << key)) != 0:
            e_stat[s] = _S_KEY
            return
        seen = seen | (1 << key)
        p = skip_ws(text, q, end)
        if p >= end or int(text[p]) != 58:
            e_stat[s] = _S_SYNTAX
            return
        p = skip_ws(text, p + 1, end)
        if p >= end:
            e_stat[s] = _S_SYNTAX
            return
        # generic value
        b = int(text[p])
        kind = int(-1)
        v = wp.float64(0.0)
        vs = int(0)
        vn = int(0)
        vesc = int(0)
        an = int(0)
        if b == 34:
            q, vesc = scan_string(text, p, end)
            if q < 0:
                e_stat[s] = _S_SYNTAX
                return
            kind = V_STRING
            vs = p + 1
            vn = q - p - 2
            p = q
        elif b == 91:
            kind = V_ARRAY
            p, an, st = scan_number_array(text, p + 1, end, arr, s, 8)
            if st != 0:
                e_stat[s] = st
                return
        elif b == 45 or (b >= 48 and b <= 57):
            q, v, kind, st = scan_number(text, p, end)
            if st != 0:
                e_stat[s] = st
                return
            p = q
        elif b == 110 and p + 4 <= end:
            if int(text[p + 1]) == 117 and int(text[p + 2]) == 108 and int(text[p + 3]) == 108:
                kind = V_NULL
                p += 4
        elif b == 116 and p + 4 <= end:
            if int(text[p + 1]) == 114 and int(text[p + 2]) == 117 and int(text[p + 3]) == 101:
                kind = V_BOOL
                p += 4
        elif b == 102 and p + 5 <= end:
            if (int(text[p + 1]) == 97 and int(text[p + 2]) == 108 and int(text[p + 3]) == 115
                    and int(text[p + 4]) == 101):
                kind = V_BOOL
                p += 5
        if kind < 0:
            e_stat[s] = _S_SYNTAX
            return
        # what the key makes of the value (object-entry rules; zone entries ignore them)
        if key == K_LAYER:
            if kind == V_INT:
                if v < wp.float64(0.0):
                    bad = int(1)
            elif kind != V_NULL:
                bad = int(1)
        elif key == K_IID:
            if kind != V_STRING or vesc == 1:
                e_stat[s] = _S_VALUE  # also decides zone-ness: must be readable
                return
            iid_s = vs
            iid_n = vn
            iid_h, iid_h2 = hash_span(text, vs, vn)
            iid_vis = visible_ascii(text, vs, vn)
        elif key == K_CAT:
            if kind == V_STRING and vesc == 0 and vn > 0:
                cat_ok = int(1)
                cat_s = vs
                cat_n = vn
                cat_h, cat_h2 = hash_span(text, vs, vn)
                cat_chk = (wp.uint64(vn) << wp.uint64(32)) | wp.uint64(cat_h2)
            else:
                bad = int(1)
        elif key == K_PARENT:
            if kind == V_STRING and vesc == 0:
                if is_word(text, vs, vn, words, word_start, W_ROOT) == 0:
                    par_s = vs
                    par_n = vn
                    par_h, par_h2 = hash_span(text, vs, vn)
            elif kind != V_NULL:
                bad = int(1)
        elif key == K_REL:
            if kind == V_STRING and vesc == 0:
                w = match_word(text, vs, vn, words, word_start, W_IN, W_NEAR + 1)
                if w < 0:
                    bad = 1  # an alias or an unknown relation: the Python parser decides
                else:
                    rel = w - W_IN
            elif kind != V_NULL:
                bad = int(1)
        elif key == K_DESC:
            if kind != V_STRING and kind != V_NULL:
                bad = int(1)
        elif key == K_BOX:
            if kind == V_ARRAY and an == 6:
                box_ok = int(1)
                for k in range(6):
                    ent_f[slot, k] = arr[s, k]
            else:
                bad = int(1)
        elif key == K_ROT:
            if kind == V_INT or kind == V_FLOAT:
                rot = v
            elif kind != V_NULL:
                bad = int(1)
        elif key == K_TYPE:
            if kind == V_STRING and vesc == 0:
                if is_word(text, vs, vn, words, word_start, W_ZONE) == 1:
                    is_zone_type = int(1)
        elif key == K_BBOX:
            if kind == V_ARRAY:
                bbox_n = an
                for k in range(4):
                    if k < an:
                        ent_f[s, 8 + k] = arr[s, k]
            else:
                bbox_n = int(-1)
        p, sep = after_value(text, p, end, 125)
        if sep == 1:
            break
        if sep < 0:
            e_stat[s] = sep
            return
    # end of entry: zone entry or object?
    e_end[s] = p
    is_root = int(0)
    if iid_s >= 0:
        if is_word(text, iid_s, iid_n, words, word_start, W_ROOT) == 1:
            is_root = int(1)
    if is_zone_type == 1 or is_root == 1:
        ent_i[s, 6] = bbox_n  # the walk reads the first zone entry's bbox (ctrc._zone_from)
        e_stat[s] = 1
        return
    else:
        if (seen & (1 << K_TYPE)) != 0:
            e_stat[s] = _S_KEY  # a "type" other than zone on an object: not canonical
            return
        if iid_s < 0 or iid_vis == 0 or cat_ok == 0 or box_ok == 0 or bad == 1:
            e_stat[s] = _S_VALUE
            return
        # relation rules of ctrc._relation
        if par_s < 0:
            if rel == 0:
                e_stat[s] = _S_VALUE
                return
            rel = int(2)
        else:
            if rel < 0 or rel == 2:
                e_stat[s] = _S_VALUE
                return
        for k in range(6):
            if wp.abs(ent_f[slot, k]) > _MAX_ABS:
                e_stat[s] = _S_NUMBER
                return
        if wp.abs(rot) > _MAX_ABS:
            e_stat[s] = _S_NUMBER
            return
        if not (ent_f[slot, 1] > ent_f[slot, 0] and ent_f[slot, 3] > ent_f[slot, 2]
                and ent_f[slot, 5] > ent_f[slot, 4]):
            e_stat[s] = _S_VALUE
            return
        ent_f[slot, 6] = rot
        ent_i[slot, 1] = rel
        ent_i[slot, 2] = iid_s
        ent_i[slot, 3] = iid_n
        ent_i[slot, 4] = par_s
        ent_i[slot, 5] = par_n
        ent_i[slot, 7] = lookup_slot(cat_h, cat_chk, table_key, table_check, table_slot, n_table)
        ent_i[slot, 8] = cat_s
        ent_i[slot, 9] = cat_n
        ent_h[slot, 0] = iid_h
        ent_h[slot, 1] = par_h
        ent_h[slot, 2] = cat_h
        ent_h[slot, 3] = cat_chk
        e_stat[s] = 0
