"""Reader stages 1-2: ``prescan`` (patterns, the layout marker, entry candidates per chunk) and
``emit`` (each text's candidate positions), with the byte helpers they share."""

# Warp needs typed constructors (int(0), wp.float64(0.0)) for variables a loop modifies.
# ruff: noqa: UP018

from __future__ import annotations

import warp as wp

from physcene.kernels.ctrc_reader.codes import CHUNK, MAX_ENTRIES

# Small CUDA blocks: a text's work is serial, latency-bound (512 texts -> 128 blocks on an
# H100/H200's 132 SMs, where Warp's default of 256 would put them on two). One block size per
# module: Warp compiles a module once per block size.
wp.set_module_options({"enable_backward": False, "block_dim": 4})

__all__ = ["emit", "prescan"]


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
            chunk_start: wp.array(dtype=wp.int32), n_text: int, flags_out: wp.array(dtype=wp.int32),
            marker_out: wp.array(dtype=wp.int32), cand_count_out: wp.array(dtype=wp.int32)):
    """Per chunk t: flags_out[c] = 1 if text c holds a fence or a <j / </ token, marker_out[c] = 1 + the
    last 'Scene Layout', cand_count_out[t] = entry candidates ('{' after '[' or ',') in the chunk."""
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
                    flags_out[c] = 1
        elif b == 60:
            # ctrc's </?json> token is re.I: '<' or '</' then j/J (no other character folds to j);
            # an end-of-text tag such as </s> stays on the fast path
            q = p + 1
            if q < stop and int(text[q]) == 47:
                q += 1
            if q < stop:
                n = int(text[q])
                if n == 106 or n == 74:
                    flags_out[c] = 1
        elif b == 83 and p + 12 <= stop:
            # "Scene Layout"
            if (int(text[p + 1]) == 99 and int(text[p + 2]) == 101 and int(text[p + 3]) == 110
                    and int(text[p + 4]) == 101 and int(text[p + 5]) == 32 and int(text[p + 6]) == 76
                    and int(text[p + 7]) == 97 and int(text[p + 8]) == 121 and int(text[p + 9]) == 111
                    and int(text[p + 10]) == 117 and int(text[p + 11]) == 116):
                wp.atomic_max(marker_out, c, p - start + 1)
        p += 1
    cand_count_out[t] = count



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
         cand_end: wp.array(dtype=wp.int32), cand_pos_out: wp.array(dtype=wp.int32)):
    """cand_pos_out[c * MAX_ENTRIES + k] = byte position of text c's k-th entry candidate (ascending)."""
    t = wp.tid()
    c, p, end = chunk_range(offsets, chunk_start, n_text, t)
    start = offsets[c]
    k = cand_end[t] - cand_count[t] - first_candidate(chunk_start, cand_count, cand_end, c)
    while p < end and k < MAX_ENTRIES:
        if int(text[p]) == 123:
            if is_candidate(text, p, start) == 1:
                cand_pos_out[c * MAX_ENTRIES + k] = p
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
