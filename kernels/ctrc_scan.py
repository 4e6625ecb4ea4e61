"""Compiled reader of canonical CTRC completions: UTF-8 bytes -> world poses, no Python per object.

The reward's fast path (physcene.physics.PhysicsEngine.pack_texts). All completions of a batch
are concatenated into one uint8 array with int32 offsets (text c = bytes[offsets[c]:offsets[c+1]]),
each text cut into its own CHUNK-byte chunks (chunk_start). Four launches and a cumsum, no sync
(kernels 1-3 and the lexing helpers are in kernels/ctrc_lex.py; ``walk`` and the launchers here):

1. ``prescan`` (one thread per chunk): flags every text containing something that would make
   :func:`physcene.ctrc.parse` look elsewhere for the JSON (a code fence ```` ``` ````, a
   ``<json>`` token, anything starting ``<j``, ``<J``, ``</j`` or ``</J``), records the LAST
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

import torch
import warp as wp
from physcene.kernels.ctrc_lex import (
    _DEG,
    _MAX_ABS,
    _MAX_ABS_POS,
    _ON_GAP,
    _S_CATEGORY,
    _S_KEY,
    _S_MANY,
    _S_MARKER,
    _S_NUMBER,
    _S_SYNTAX,
    _S_TREE,
    _S_VALUE,
    _S_ZONE,
    CHUNK,
    ENTRY_KEYS,
    FNV_OFFSET,
    FNV_PRIME,
    K_OBJECTS,
    K_ZONE,
    MAX_ENTRIES,
    STATUS,
    TOP_KEYS,
    after_value,
    category_hash,
    emit,
    entries,
    find_candidate,
    keyword_table,
    match_word,
    n_candidates,
    prescan,
    same_bytes,
    scan_number_array,
    scan_string,
    skip_ws,
    wrap_angle,
)
from physcene.kernels.penetration import _ct, _Launcher

wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
# Small CUDA blocks: the per-text ``walk`` is serial, latency-bound work (512 texts -> 128 blocks
# on an H100/H200's 132 SMs, where Warp's default of 256 would put them on two). One block size
# per module: Warp compiles a module once per block size.
wp.set_module_options({"enable_backward": False, "block_dim": 4})
wp.init()

__all__ = ["CHUNK", "ENTRY_KEYS", "FNV_OFFSET", "FNV_PRIME", "MAX_ENTRIES", "STATUS", "TOP_KEYS",
           "category_hash", "keyword_table", "launch_gather", "launch_scan", "scan_buffers"]


# Walk -------------------------------------------------------------------------------------------
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
            p, n, st = scan_number_array(text, p, end, out_zone, c, 4)
            if st != 0:
                status[c] = st
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
                p, sep = after_value(text, p, end, 93)
                if sep == 1:
                    break
                if sep < 0:
                    status[c] = sep
                    return
        p, sep = after_value(text, p, end, 125)
        first_key = int(0)
        if sep == 1:
            break
        if sep < 0:
            status[c] = sep
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
                        else:  # on (and near an object): from the top, ctrc.ON_CONTACT_GAP_CM above it
                            zb = ent_f[sp, 10] + wp.float64(0.5) * ent_f[sp, 13] + _ON_GAP
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
