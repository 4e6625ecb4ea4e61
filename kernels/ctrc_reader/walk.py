"""Reader stage 4: ``walk`` reads each text's top level and hierarchy into world poses; ``gather``
copies the scanned objects into the engine's padded batch."""

# Warp needs typed constructors (int(0), wp.float64(0.0)) for variables a loop modifies.
# ruff: noqa: UP018

from __future__ import annotations

import warp as wp

from physcene.kernels.ctrc_reader.codes import (
    DEG,
    K_OBJECTS,
    K_ZONE,
    MAX_ENTRIES,
    S_CATEGORY,
    S_KEY,
    S_MANY,
    S_MARKER,
    S_NUMBER,
    S_SYNTAX,
    S_TREE,
    S_VALUE,
    S_ZONE,
)
from physcene.kernels.ctrc_reader.prescan import find_candidate, n_candidates
from physcene.kernels.ctrc_reader.values import (
    after_value,
    match_word,
    same_bytes,
    scan_number_array,
    scan_string,
    skip_ws,
    wrap_angle,
)

# Small CUDA blocks: a text's work is serial, latency-bound (512 texts -> 128 blocks on an
# H100/H200's 132 SMs, where Warp's default of 256 would put them on two). One block size per
# module: Warp compiles a module once per block size.
wp.set_module_options({"enable_backward": False, "block_dim": 4})

__all__ = ["gather", "walk"]


@wp.kernel
def walk(text: wp.array(dtype=wp.uint8), offsets: wp.array(dtype=wp.int32),
         chunk_start: wp.array(dtype=wp.int32), flags: wp.array(dtype=wp.int32),
         marker: wp.array(dtype=wp.int32), cand_count: wp.array(dtype=wp.int32),
         cand_end: wp.array(dtype=wp.int32), cand_pos: wp.array(dtype=wp.int32),
         e_stat: wp.array(dtype=wp.int32), e_end: wp.array(dtype=wp.int32),
         words: wp.array(dtype=wp.uint8), word_start: wp.array(dtype=wp.int32),
         max_abs: wp.float64, max_abs_pos: wp.float64, on_gap: wp.float64,
         ent_f: wp.array2d(dtype=wp.float64), ent_i: wp.array2d(dtype=wp.int32),
         ent_h: wp.array2d(dtype=wp.uint64),
         pose_out: wp.array2d(dtype=wp.float32), asset_out: wp.array(dtype=wp.int32),
         zone_out: wp.array2d(dtype=wp.float64), status_out: wp.array(dtype=wp.int32),
         n_read_out: wp.array(dtype=wp.int32)):
    """Text c -> status_out[c] (objects read, or a negative fallback code) and, per object slot k of
    c (row c * MAX_ENTRIES + k): pose_out [x, y, z, yaw, w, d, h, 0] (cm, rad), asset_out.

    Reads the top level serially and takes each entry from the ``entries`` kernel's candidate at
    its '{' (the chain of candidates it walks is exactly the serial parse), then checks the
    hierarchy and composes the world poses. Object rows (moved down to slots 0..n-1): ent_f [box
    (6), rotation deg, 0, world cx, cy, cz, w, d, h, yaw]; ent_i [parent slot, relation (0 in,
    1 on, 2 near), id start, id len, parent start, parent len, done, asset slot, category start,
    category len]; ent_h [id hash, parent hash, category hash, category check]. n_read_out[c]: the
    objects of an accepted text or of one with an unknown category (status_out -9).
    """
    c = wp.tid()
    if flags[c] != 0 or marker[c] == 0:
        status_out[c] = S_MARKER
        return
    base = offsets[c]
    end = offsets[c + 1]
    row0 = c * MAX_ENTRIES
    n_cand = n_candidates(chunk_start, cand_count, cand_end, c)
    p = base + marker[c] - 1 + 12
    while p < end and int(text[p]) != 123:
        p += 1
    if p >= end:
        status_out[c] = S_SYNTAX
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
            status_out[c] = S_SYNTAX
            return
        b = int(text[p])
        if b == 125 and first_key == 1:
            break  # {} has no "objects": Python searches further; the caller sees it below
        if b != 34:
            status_out[c] = S_SYNTAX
            return
        q, kesc = scan_string(text, p, end)
        if q < 0 or kesc == 1:
            status_out[c] = S_SYNTAX
            return
        key = match_word(text, p + 1, q - p - 2, words, word_start, K_OBJECTS, K_ZONE + 1)
        if key < 0 or (top_seen & (1 << (key - K_OBJECTS))) != 0:
            status_out[c] = S_KEY
            return
        top_seen = top_seen | (1 << (key - K_OBJECTS))
        p = skip_ws(text, q, end)
        if p >= end or int(text[p]) != 58:
            status_out[c] = S_SYNTAX
            return
        p = skip_ws(text, p + 1, end)
        if p >= end or int(text[p]) != 91:
            status_out[c] = S_VALUE  # both top-level values must be arrays here
            return
        p += 1
        if key == K_ZONE:
            p, n, st = scan_number_array(text, p, end, zone_out, c, 4)
            if st != 0:
                status_out[c] = st
                return
            if n != 4:
                status_out[c] = S_ZONE
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
                    status_out[c] = S_VALUE
                    return
                if n_ent >= MAX_ENTRIES:
                    status_out[c] = S_MANY
                    return
                # the entries kernel read this entry: find it among the text's candidates
                e = find_candidate(cand_pos, row0, n_cand, p)
                if e < 0:
                    status_out[c] = S_MANY  # more '{' candidates than MAX_ENTRIES before this one
                    return
                st = e_stat[e]
                if st < 0:
                    status_out[c] = st
                    return
                p = e_end[e]
                n_ent += 1
                if st == 1:
                    if zone_entry_seen == 0:  # ctrc._zone_from reads the FIRST zone entry only
                        zone_entry_seen = int(1)
                        if ent_i[e, 6] >= 4:
                            entry_zone_ok = int(1)
                            for k in range(4):
                                zone_out[c, 8 + k] = ent_f[e, 8 + k]
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
                    status_out[c] = sep
                    return
        p, sep = after_value(text, p, end, 125)
        first_key = int(0)
        if sep == 1:
            break
        if sep < 0:
            status_out[c] = sep
            return
    if (top_seen & 1) == 0:
        status_out[c] = S_KEY  # no "objects": Python keeps searching the text
        return
    if n_obj == 0:
        status_out[c] = S_VALUE
        return
    # Zone: item_placement_zone, else the first zone entry's bbox[:4] (ctrc._zone_from) ------------
    zx0 = wp.float64(0.0)
    zx1 = wp.float64(0.0)
    zy0 = wp.float64(0.0)
    zy1 = wp.float64(0.0)
    if zone_src == 1:
        zx0 = zone_out[c, 0]
        zx1 = zone_out[c, 1]
        zy0 = zone_out[c, 2]
        zy1 = zone_out[c, 3]
    elif entry_zone_ok == 1:
        zx0 = zone_out[c, 8]
        zx1 = zone_out[c, 9]
        zy0 = zone_out[c, 10]
        zy1 = zone_out[c, 11]
    else:
        status_out[c] = S_ZONE
        return
    if (wp.abs(zx0) > max_abs or wp.abs(zx1) > max_abs or wp.abs(zy0) > max_abs or wp.abs(zy1) > max_abs
            or not (zx1 > zx0 and zy1 > zy0)):
        status_out[c] = S_ZONE
        return
    zone_out[c, 0] = zx0
    zone_out[c, 1] = zx1
    zone_out[c, 2] = zy0
    zone_out[c, 3] = zy1
    # Hierarchy: duplicate ids, parents by exact bytes ---------------------------------------------
    for i in range(n_obj):
        si = row0 + i
        for j in range(i + 1, n_obj):
            sj = row0 + j
            if (ent_h[si, 0] == ent_h[sj, 0] and ent_i[si, 3] == ent_i[sj, 3]
                    and same_bytes(text, ent_i[si, 2], ent_i[sj, 2], ent_i[si, 3]) == 1):
                status_out[c] = S_TREE
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
                status_out[c] = S_TREE
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
                            zb = ent_f[sp, 10] + wp.float64(0.5) * ent_f[sp, 13] + on_gap
                if ready == 1:
                    rx = wp.float64(0.5) * (ent_f[si, 0] + ent_f[si, 1])
                    ry = wp.float64(0.5) * (ent_f[si, 2] + ent_f[si, 3])
                    cf = wp.cos(fyaw)
                    sf = wp.sin(fyaw)
                    cx = x0 + cf * rx - sf * ry
                    cy = y0 + sf * rx + cf * ry
                    cz = zb + wp.float64(0.5) * (ent_f[si, 4] + ent_f[si, 5])
                    if wp.abs(cx) > max_abs_pos or wp.abs(cy) > max_abs_pos or wp.abs(cz) > max_abs_pos:
                        status_out[c] = S_NUMBER
                        return
                    ent_f[si, 8] = cx
                    ent_f[si, 9] = cy
                    ent_f[si, 10] = cz
                    ent_f[si, 11] = ent_f[si, 1] - ent_f[si, 0]
                    ent_f[si, 12] = ent_f[si, 3] - ent_f[si, 2]
                    ent_f[si, 13] = ent_f[si, 5] - ent_f[si, 4]
                    ent_f[si, 14] = wrap_angle(fyaw + ent_f[si, 6] * DEG)
                    ent_i[si, 6] = 1
                    n_done += 1
                    progress = int(1)
    if n_done < n_obj:
        status_out[c] = S_TREE
        return
    unknown = int(0)
    for i in range(n_obj):
        si = row0 + i
        pose_out[si, 0] = wp.float32(ent_f[si, 8])
        pose_out[si, 1] = wp.float32(ent_f[si, 9])
        pose_out[si, 2] = wp.float32(ent_f[si, 10])
        pose_out[si, 3] = wp.float32(ent_f[si, 14])
        pose_out[si, 4] = wp.float32(ent_f[si, 11])
        pose_out[si, 5] = wp.float32(ent_f[si, 12])
        pose_out[si, 6] = wp.float32(ent_f[si, 13])
        pose_out[si, 7] = wp.float32(0.0)
        asset_out[si] = ent_i[si, 7]
        if ent_i[si, 7] < 0:
            unknown = int(1)
    n_read_out[c] = n_obj
    if unknown == 1:
        status_out[c] = S_CATEGORY
        return
    status_out[c] = n_obj



@wp.kernel
def gather(src: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), n_slot: int,
           scan_pose: wp.array2d(dtype=wp.float32), scan_asset: wp.array(dtype=wp.int32),
           poses_out: wp.array2d(dtype=wp.float32), sizes_out: wp.array2d(dtype=wp.float32),
           asset_out: wp.array(dtype=wp.int32)):
    """Batch slot (row, i) <- scanned object i of text src[row] (padding: pose 0, size 1, asset 0)."""
    t = wp.tid()
    row = t // n_slot
    i = t - row * n_slot
    c = src[row]
    if c >= 0 and i < count[row]:
        s = c * MAX_ENTRIES + i
        for k in range(4):
            poses_out[t, k] = scan_pose[s, k]
        for k in range(3):
            sizes_out[t, k] = scan_pose[s, 4 + k]
        asset_out[t] = scan_asset[s]
    else:
        for k in range(4):
            poses_out[t, k] = 0.0
        for k in range(3):
            sizes_out[t, k] = 1.0
        asset_out[t] = 0
