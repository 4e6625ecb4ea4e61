"""Compiled reader of canonical CTRC completions: UTF-8 bytes -> world poses, no Python per object.

The reward's fast path (physcene.physics.PhysicsEngine.pack_texts). All completions of a batch
are concatenated into one uint8 array with int32 offsets (text c = bytes[offsets[c]:offsets[c+1]]),
each text cut into its own CHUNK-byte chunks (chunk_start). Four launches and a cumsum, no sync:

1. ``prescan`` (one thread per chunk): flags every text containing something that would make
   :func:`physcene.ctrc.parse` look elsewhere for the JSON (a code fence ```` ``` ````, a
   ``<json>`` token, anything starting ``<j``, ``<J`` or ``</``), records the LAST
   ``Scene Layout`` (the parser reads from its ``rfind``) and counts entry candidates: '{' bytes
   whose previous non-blank byte is '[' or ','.
2. ``torch.cumsum`` of the counts, then ``emit`` (one thread per chunk) writes each text's first
   MAX_ENTRIES candidate positions, ascending.
3. ``entries`` (one thread per candidate): reads the JSON object at the candidate as a layered
   CTRC entry (keys in any order, the value rules of ``ctrc.decode``), speculatively: a '{'
   inside a description is a candidate too, and simply never gets used.
4. ``walk`` (one thread per text): from the first ``{`` after the marker, the strict reader of
   the top level ({"objects": [...], "item_placement_zone": [...]}); at each entry it takes the
   candidate that starts at that byte and continues after its end, so the chain it follows is
   exactly what a serial parse reads. Then ids, parents, relations, cycles, and the world pose of
   every object composed through its parent chain in float64 exactly as ``ctrc._absolute`` does;
   the category's engine asset slot comes from a sorted hash table (looked up in ``entries``).

The per-text serial work is the top level and the hierarchy; the bytes are read in parallel.
A text the scanner does not fully understand gets a negative ``status`` (the reason code) and is
left to the Python parser: the scanner never decides that a completion is unparsable. Numbers are
exact: the decimal mantissa is accumulated as an integer (at most 15 significant digits, so it is
exact in float64) and divided once by an exact power of ten (≤ 10^22), which is the correctly
rounded float64 that Python's float() returns. Exponents, escapes in ids/categories/parents,
unknown keys, duplicate keys and non-canonical values all fall back.
"""

# Warp needs typed constructors (int(0), wp.float64(0.0)) for variables a loop modifies.
# ruff: noqa: UP018

from __future__ import annotations

import numpy as np
import torch
import warp as wp
from physcene.kernels.penetration import _ct, _Launcher

wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
# Small CUDA blocks: the per-text ``walk`` is serial, latency-bound work (512 texts -> 128 blocks
# on an H100/H200's 132 SMs, where Warp's default of 256 would put them on two), and a text's
# entries share a warp. One block size for the whole module: Warp compiles a module per size.
wp.set_module_options({"enable_backward": False, "block_dim": 4})
wp.init()

__all__ = ["CHUNK", "ENTRY_KEYS", "FNV_OFFSET", "FNV_PRIME", "MAX_ENTRIES", "STATUS", "TOP_KEYS",
           "category_hash", "keyword_table", "launch_gather", "launch_scan"]

# Entries (the zone entry included) one text may hold on the fast path; more go to Python.
MAX_ENTRIES = 64
# Bytes per prescan thread.
CHUNK = wp.constant(256)
# |value| beyond this (cm) is refused by ctrc (MAX_ABS_CM); the absolute-position check uses a hair
# less so that a float64 ulp of difference with Python's libm never accepts what Python refuses.
_MAX_ABS = wp.constant(wp.float64(1.0e5))
_MAX_ABS_POS = wp.constant(wp.float64(1.0e5 * (1.0 - 1.0e-9)))
_DEG = wp.constant(wp.float64(np.pi / 180.0))  # math.radians multiplies by exactly this
_PI = wp.constant(wp.float64(np.pi))
_TWO_PI = wp.constant(wp.float64(2.0 * np.pi))

FNV_OFFSET = int(14695981039346656037)
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
            if p + 1 < stop:
                n = int(text[p + 1])
                if n == 106 or n == 74 or n == 47:  # j J /
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
            p = skip_ws(text, p + 1, end)
            if p < end and int(text[p]) == 93:
                p += 1
            else:
                while True:
                    p = skip_ws(text, p, end)
                    q, av, akind, st = scan_number(text, p, end)
                    if st != 0:
                        e_stat[s] = st
                        return
                    if an < 8:
                        arr[s, an] = av
                    an += 1
                    p = skip_ws(text, q, end)
                    if p >= end:
                        e_stat[s] = _S_SYNTAX
                        return
                    b = int(text[p])
                    p += 1
                    if b == 93:
                        break
                    if b != 44:
                        e_stat[s] = _S_SYNTAX
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
        p = skip_ws(text, p, end)
        if p >= end:
            e_stat[s] = _S_SYNTAX
            return
        b = int(text[p])
        p += 1
        if b == 125:
            break
        if b != 44:
            e_stat[s] = _S_SYNTAX
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


@wp.kernel
def walk(text: wp.array(dtype=wp.uint8), offsets: wp.array(dtype=wp.int32),
         chunk_start: wp.array(dtype=wp.int32), flags: wp.array(dtype=wp.int32),
         marker: wp.array(dtype=wp.int32), cand_count: wp.array(dtype=wp.int32),
         cand_end: wp.array(dtype=wp.int32), cand_pos: wp.array(dtype=wp.int32),
         e_stat: wp.array(dtype=wp.int32), e_end: wp.array(dtype=wp.int32),
         words: wp.array(dtype=wp.uint8), word_start: wp.array(dtype=wp.int32),
         ent_f: wp.array2d(dtype=wp.float64), ent_i: wp.array2d(dtype=wp.int32),
         ent_h: wp.array2d(dtype=wp.uint64),
         out_pose: wp.array2d(dtype=wp.float32), out_asset: wp.array(dtype=wp.int32),
         out_zone: wp.array2d(dtype=wp.float64), status: wp.array(dtype=wp.int32),
         n_read: wp.array(dtype=wp.int32)):
    """Text c -> status[c] (objects read, or a negative fallback code) and, per object slot k of
    c (row c * MAX_ENTRIES + k): out_pose [x, y, z, yaw, w, d, h, 0] (cm, rad), out_asset.

    Reads the top level serially and takes each entry from the ``entries`` kernel's candidate at
    its '{' (the chain of candidates it walks is exactly the serial parse), then checks the
    hierarchy and composes the world poses. Object rows (moved down to slots 0..n-1): ent_f [box
    (6), rotation deg, 0, world cx, cy, cz, w, d, h, yaw]; ent_i [parent slot, relation (0 in,
    1 on, 2 near), id start, id len, parent start, parent len, done, asset slot, category start,
    category len]; ent_h [id hash, parent hash, category hash, category check]. n_read[c]: the
    objects of an accepted text or of one with an unknown category (status -9).
    """
    c = wp.tid()
    if flags[c] != 0 or marker[c] == 0:
        status[c] = _S_MARKER
        return
    base = offsets[c]
    end = offsets[c + 1]
    row0 = c * MAX_ENTRIES
    n_cand = n_candidates(chunk_start, cand_count, cand_end, c)
    p = base + marker[c] - 1 + 12
    while p < end and int(text[p]) != 123:
        p += 1
    if p >= end:
        status[c] = _S_SYNTAX
        return
    p += 1
    n_obj = int(0)      # non-zone entries (object slots)
    n_ent = int(0)      # all entries
    top_seen = int(0)
    zone_src = int(0)   # 1 once item_placement_zone is read
    zone_entry_seen = int(0)
    entry_zone_ok = int(0)  # the first zone entry has a bbox of >= 4 numbers
    # Top-level object ---------------------------------------------------------------------------
    first_key = int(1)
    while True:
        p = skip_ws(text, p, end)
        if p >= end:
            status[c] = _S_SYNTAX
            return
        b = int(text[p])
        if b == 125 and first_key == 1:
            break  # {} has no "objects": Python searches further; the caller sees it below
        if b != 34:
            status[c] = _S_SYNTAX
            return
        q, kesc = scan_string(text, p, end)
        if q < 0 or kesc == 1:
            status[c] = _S_SYNTAX
            return
        key = match_word(text, p + 1, q - p - 2, words, word_start, K_OBJECTS, K_ZONE + 1)
        if key < 0 or (top_seen & (1 << (key - K_OBJECTS))) != 0:
            status[c] = _S_KEY
            return
        top_seen = top_seen | (1 << (key - K_OBJECTS))
        p = skip_ws(text, q, end)
        if p >= end or int(text[p]) != 58:
            status[c] = _S_SYNTAX
            return
        p = skip_ws(text, p + 1, end)
        if p >= end or int(text[p]) != 91:
            status[c] = _S_VALUE  # both top-level values must be arrays here
            return
        p += 1
        if key == K_ZONE:
            n = int(0)
            p = skip_ws(text, p, end)
            if p < end and int(text[p]) == 93:
                p += 1
            else:
                while True:
                    p = skip_ws(text, p, end)
                    q, v, kind, st = scan_number(text, p, end)
                    if st != 0:
                        status[c] = st
                        return
                    if n < 4:
                        out_zone[c, n] = v
                    n += 1
                    p = skip_ws(text, q, end)
                    if p >= end:
                        status[c] = _S_SYNTAX
                        return
                    b = int(text[p])
                    p += 1
                    if b == 93:
                        break
                    if b != 44:
                        status[c] = _S_SYNTAX
                        return
            if n != 4:
                status[c] = _S_ZONE
                return
            zone_src = int(1)
        else:
            # "objects": an array of entry objects
            p = skip_ws(text, p, end)
            empty = int(0)
            if p < end and int(text[p]) == 93:
                p += 1
                empty = int(1)
            while empty == 0:
                p = skip_ws(text, p, end)
                if p >= end or int(text[p]) != 123:
                    status[c] = _S_VALUE
                    return
                if n_ent >= MAX_ENTRIES:
                    status[c] = _S_MANY
                    return
                # the entries kernel read this entry: find it among the text's candidates
                e = find_candidate(cand_pos, row0, n_cand, p)
                if e < 0:
                    status[c] = _S_MANY  # more '{' candidates than MAX_ENTRIES before this one
                    return
                st = e_stat[e]
                if st < 0:
                    status[c] = st
                    return
                p = e_end[e]
                n_ent += 1
                if st == 1:
                    if zone_entry_seen == 0:  # ctrc._zone_from reads the FIRST zone entry only
                        zone_entry_seen = int(1)
                        if ent_i[e, 6] >= 4:
                            entry_zone_ok = int(1)
                            for k in range(4):
                                out_zone[c, 8 + k] = ent_f[e, 8 + k]
                else:
                    # objects move down to slots 0..n_obj-1 (slot <= e: nothing unread is overwritten)
                    slot = row0 + n_obj
                    if slot != e:
                        for k in range(7):
                            ent_f[slot, k] = ent_f[e, k]
                        for k in range(10):
                            ent_i[slot, k] = ent_i[e, k]
                        for k in range(4):
                            ent_h[slot, k] = ent_h[e, k]
                    ent_i[slot, 0] = -1
                    ent_i[slot, 6] = 0
                    n_obj += 1
                p = skip_ws(text, p, end)
                if p >= end:
                    status[c] = _S_SYNTAX
                    return
                b = int(text[p])
                p += 1
                if b == 93:
                    break
                if b != 44:
                    status[c] = _S_SYNTAX
                    return
        p = skip_ws(text, p, end)
        if p >= end:
            status[c] = _S_SYNTAX
            return
        b = int(text[p])
        p += 1
        first_key = int(0)
        if b == 125:
            break
        if b != 44:
            status[c] = _S_SYNTAX
            return
    if (top_seen & 1) == 0:
        status[c] = _S_KEY  # no "objects": Python keeps searching the text
        return
    if n_obj == 0:
        status[c] = _S_VALUE
        return
    # Zone: item_placement_zone, else the first zone entry's bbox[:4] (ctrc._zone_from) ------------
    zx0 = wp.float64(0.0)
    zx1 = wp.float64(0.0)
    zy0 = wp.float64(0.0)
    zy1 = wp.float64(0.0)
    if zone_src == 1:
        zx0 = out_zone[c, 0]
        zx1 = out_zone[c, 1]
        zy0 = out_zone[c, 2]
        zy1 = out_zone[c, 3]
    elif entry_zone_ok == 1:
        zx0 = out_zone[c, 8]
        zx1 = out_zone[c, 9]
        zy0 = out_zone[c, 10]
        zy1 = out_zone[c, 11]
    else:
        status[c] = _S_ZONE
        return
    if (wp.abs(zx0) > _MAX_ABS or wp.abs(zx1) > _MAX_ABS or wp.abs(zy0) > _MAX_ABS or wp.abs(zy1) > _MAX_ABS
            or not (zx1 > zx0 and zy1 > zy0)):
        status[c] = _S_ZONE
        return
    out_zone[c, 0] = zx0
    out_zone[c, 1] = zx1
    out_zone[c, 2] = zy0
    out_zone[c, 3] = zy1
    # Hierarchy: duplicate ids, parents by exact bytes ---------------------------------------------
    for i in range(n_obj):
        si = row0 + i
        for j in range(i + 1, n_obj):
            sj = row0 + j
            if (ent_h[si, 0] == ent_h[sj, 0] and ent_i[si, 3] == ent_i[sj, 3]
                    and same_bytes(text, ent_i[si, 2], ent_i[sj, 2], ent_i[si, 3]) == 1):
                status[c] = _S_TREE
                return
    for i in range(n_obj):
        si = row0 + i
        if ent_i[si, 4] >= 0:
            found = int(-1)
            for j in range(n_obj):
                sj = row0 + j
                if (found < 0 and ent_h[sj, 0] == ent_h[si, 1] and ent_i[sj, 3] == ent_i[si, 5]
                        and same_bytes(text, ent_i[sj, 2], ent_i[si, 4], ent_i[si, 5]) == 1):
                    found = j
            if found < 0:
                status[c] = _S_TREE
                return
            ent_i[si, 0] = found
    # World poses, parents first (ctrc._Frame / _absolute in float64); a cycle never resolves -----
    n_done = int(0)
    progress = int(1)
    while progress == 1 and n_done < n_obj:
        progress = int(0)
        for i in range(n_obj):
            si = row0 + i
            if ent_i[si, 6] == 0:
                par = ent_i[si, 0]
                ready = int(1)
                x0 = zx0
                y0 = zy0
                fyaw = wp.float64(0.0)
                zb = wp.float64(0.0)
                if par >= 0:
                    sp = row0 + par
                    if ent_i[sp, 6] == 0:
                        ready = int(0)
                    else:
                        fyaw = ent_f[sp, 14]
                        cp = wp.cos(fyaw)
                        spn = wp.sin(fyaw)
                        hw = wp.float64(0.5) * ent_f[sp, 11]
                        hd = wp.float64(0.5) * ent_f[sp, 12]
                        x0 = ent_f[sp, 8] - cp * hw + spn * hd
                        y0 = ent_f[sp, 9] - spn * hw - cp * hd
                        if ent_i[si, 1] == 0:
                            zb = ent_f[sp, 10] - wp.float64(0.5) * ent_f[sp, 13]
                        else:
                            zb = ent_f[sp, 10] + wp.float64(0.5) * ent_f[sp, 13]
                if ready == 1:
                    rx = wp.float64(0.5) * (ent_f[si, 0] + ent_f[si, 1])
                    ry = wp.float64(0.5) * (ent_f[si, 2] + ent_f[si, 3])
                    cf = wp.cos(fyaw)
                    sf = wp.sin(fyaw)
                    cx = x0 + cf * rx - sf * ry
                    cy = y0 + sf * rx + cf * ry
                    cz = zb + wp.float64(0.5) * (ent_f[si, 4] + ent_f[si, 5])
                    if wp.abs(cx) > _MAX_ABS_POS or wp.abs(cy) > _MAX_ABS_POS or wp.abs(cz) > _MAX_ABS_POS:
                        status[c] = _S_NUMBER
                        return
                    ent_f[si, 8] = cx
                    ent_f[si, 9] = cy
                    ent_f[si, 10] = cz
                    ent_f[si, 11] = ent_f[si, 1] - ent_f[si, 0]
                    ent_f[si, 12] = ent_f[si, 3] - ent_f[si, 2]
                    ent_f[si, 13] = ent_f[si, 5] - ent_f[si, 4]
                    ent_f[si, 14] = wrap_angle(fyaw + ent_f[si, 6] * _DEG)
                    ent_i[si, 6] = 1
                    n_done += 1
                    progress = int(1)
    if n_done < n_obj:
        status[c] = _S_TREE
        return
    unknown = int(0)
    for i in range(n_obj):
        si = row0 + i
        out_pose[si, 0] = wp.float32(ent_f[si, 8])
        out_pose[si, 1] = wp.float32(ent_f[si, 9])
        out_pose[si, 2] = wp.float32(ent_f[si, 10])
        out_pose[si, 3] = wp.float32(ent_f[si, 14])
        out_pose[si, 4] = wp.float32(ent_f[si, 11])
        out_pose[si, 5] = wp.float32(ent_f[si, 12])
        out_pose[si, 6] = wp.float32(ent_f[si, 13])
        out_pose[si, 7] = wp.float32(0.0)
        out_asset[si] = ent_i[si, 7]
        if ent_i[si, 7] < 0:
            unknown = int(1)
    n_read[c] = n_obj
    if unknown == 1:
        status[c] = _S_CATEGORY
        return
    status[c] = n_obj


@wp.kernel
def gather(src: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), n_slot: int,
           scan_pose: wp.array2d(dtype=wp.float32), scan_asset: wp.array(dtype=wp.int32),
           poses: wp.array2d(dtype=wp.float32), sizes: wp.array2d(dtype=wp.float32),
           asset: wp.array(dtype=wp.int32)):
    """Batch slot (row, i) <- scanned object i of text src[row] (padding: pose 0, size 1, asset 0)."""
    t = wp.tid()
    row = t // n_slot
    i = t - row * n_slot
    c = src[row]
    if c >= 0 and i < count[row]:
        s = c * MAX_ENTRIES + i
        for k in range(4):
            poses[t, k] = scan_pose[s, k]
        for k in range(3):
            sizes[t, k] = scan_pose[s, 4 + k]
        asset[t] = scan_asset[s]
    else:
        for k in range(4):
            poses[t, k] = 0.0
        for k in range(3):
            sizes[t, k] = 1.0
        asset[t] = 0


# Launchers --------------------------------------------------------------------------------------
def launch_scan(*, text: torch.Tensor, offsets: torch.Tensor, chunk_start: torch.Tensor, n_text: int,
                n_chunks: int, words: dict[str, torch.Tensor], table: dict[str, torch.Tensor],
                buffers: dict[str, torch.Tensor]) -> None:
    """prescan → cumsum → emit → entries → walk of ``n_text`` texts into ``buffers``; no sync.

    text (>= offsets[-1],) uint8; offsets (n_text + 1,) int32; chunk_start (n_text + 1,) int32:
    each text's first CHUNK-byte chunk (n_chunks = chunk_start[-1]); words: ``bytes``, ``start``
    of :func:`keyword_table`; table: ``key``, ``check`` (uint64 as int64), ``slot`` (int32),
    sorted by key as unsigned. ``buffers``: :func:`scan_buffers` for >= n_text texts and
    >= n_chunks chunks.
    """
    launch = _Launcher(text.device)
    b = buffers
    flags, marker = b["pre"][:n_text], b["pre"][n_text:2 * n_text]
    b["pre"][:2 * n_text].zero_()
    cand_count, cand_end = b["cand_count"][:n_chunks], b["cand_end"][:n_chunks]
    w_text, w_off, w_chunk = _ct(text, wp.uint8), _ct(offsets), _ct(chunk_start)
    w_flags, w_marker, w_count, w_end = _ct(flags), _ct(marker), _ct(cand_count), _ct(cand_end)
    w_pos = _ct(b["cand_pos"])
    launch(prescan, n_chunks, [w_text, w_off, w_chunk, n_text, w_flags, w_marker, w_count])
    torch.cumsum(cand_count, 0, out=cand_end)
    launch(emit, n_chunks, [w_text, w_off, w_chunk, n_text, w_count, w_end, w_pos])
    w_ent = [_ct(b["ent_f"]), _ct(b["ent_i"]), _ct(b["ent_h"], wp.uint64)]
    w_e = [_ct(b["e_stat"]), _ct(b["e_end"])]
    w_words = [_ct(words["bytes"], wp.uint8), _ct(words["start"])]
    n_table = int(table["key"].shape[0])
    launch(entries, n_text * MAX_ENTRIES, [
        w_text, w_off, w_chunk, w_flags, w_marker, w_count, w_end, w_pos, *w_words,
        _ct(table["key"], wp.uint64), _ct(table["check"], wp.uint64), _ct(table["slot"]), n_table,
        *w_ent, _ct(b["arr"]), *w_e])
    launch(walk, n_text, [
        w_text, w_off, w_chunk, w_flags, w_marker, w_count, w_end, w_pos, *w_e, *w_words, *w_ent,
        _ct(b["pose"]), _ct(b["asset"]), _ct(b["zone"]), _ct(b["status"][:n_text]),
        _ct(b["n_read"][:n_text])])


def scan_buffers(n_text: int, n_chunks: int, device: torch.device) -> dict[str, torch.Tensor]:
    """Scratch and output tensors of :func:`launch_scan` for up to ``n_text`` texts, ``n_chunks`` chunks."""
    rows = n_text * MAX_ENTRIES
    return {
        "pre": torch.zeros(2 * n_text, dtype=torch.int32, device=device),
        "cand_count": torch.empty(n_chunks, dtype=torch.int32, device=device),
        "cand_end": torch.empty(n_chunks, dtype=torch.int32, device=device),
        "cand_pos": torch.empty(rows, dtype=torch.int32, device=device),
        "e_stat": torch.empty(rows, dtype=torch.int32, device=device),
        "e_end": torch.empty(rows, dtype=torch.int32, device=device),
        "ent_f": torch.empty(rows, 16, dtype=torch.float64, device=device),
        "ent_i": torch.empty(rows, 10, dtype=torch.int32, device=device),
        "ent_h": torch.empty(rows, 4, dtype=torch.int64, device=device),
        "arr": torch.empty(rows, 8, dtype=torch.float64, device=device),
        "pose": torch.empty(rows, 8, dtype=torch.float32, device=device),
        "asset": torch.empty(rows, dtype=torch.int32, device=device),
        "zone": torch.empty(n_text, 12, dtype=torch.float64, device=device),
        "status": torch.empty(n_text, dtype=torch.int32, device=device),
        "n_read": torch.zeros(n_text, dtype=torch.int32, device=device),
    }


def launch_gather(*, src: torch.Tensor, count: torch.Tensor, n_slot: int, buffers: dict[str, torch.Tensor],
                  poses: torch.Tensor, sizes: torch.Tensor, asset: torch.Tensor) -> None:
    """Fill (R, n_slot) ``poses`` (4), ``sizes`` (3), ``asset`` from the scan of texts ``src`` (R,)."""
    n_row = int(src.shape[0])
    if n_row == 0:
        return
    _Launcher(poses.device)(gather, n_row * n_slot, [
        _ct(src), _ct(count), int(n_slot), _ct(buffers["pose"]), _ct(buffers["asset"]),
        _ct(poses.view(-1, 4)), _ct(sizes.view(-1, 3)), _ct(asset.view(-1))])
