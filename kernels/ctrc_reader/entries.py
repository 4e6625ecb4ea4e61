"""Reader stage 3: ``entries`` reads each candidate '{' as a layered CTRC entry, speculatively."""

# Warp needs typed constructors (int(0), wp.float64(0.0)) for variables a loop modifies.
# ruff: noqa: UP018

from __future__ import annotations

import warp as wp

from physcene.kernels.ctrc_reader.codes import (
    E_NONE,
    K_BBOX,
    K_BOX,
    K_CAT,
    K_DESC,
    K_IID,
    K_LAYER,
    K_PARENT,
    K_REL,
    K_ROT,
    K_TYPE,
    K_ZROT,
    MAX_ENTRIES,
    S_KEY,
    S_NUMBER,
    S_SYNTAX,
    S_VALUE,
    V_ARRAY,
    V_BOOL,
    V_FLOAT,
    V_INT,
    V_NULL,
    V_STRING,
    W_IN,
    W_NEAR,
    W_ROOT,
    W_ZONE,
)
from physcene.kernels.ctrc_reader.prescan import n_candidates
from physcene.kernels.ctrc_reader.values import (
    after_value,
    hash_span,
    is_word,
    lookup_slot,
    match_word,
    scan_number,
    scan_number_array,
    scan_string,
    skip_ws,
    visible_ascii,
)

# Small CUDA blocks: a text's work is serial, latency-bound (512 texts -> 128 blocks on an
# H100/H200's 132 SMs, where Warp's default of 256 would put them on two). One block size per
# module: Warp compiles a module once per block size.
wp.set_module_options({"enable_backward": False, "block_dim": 4})

__all__ = ["entries"]


@wp.kernel
def entries(text: wp.array(dtype=wp.uint8), offsets: wp.array(dtype=wp.int32),
            chunk_start: wp.array(dtype=wp.int32), flags: wp.array(dtype=wp.int32),
            marker: wp.array(dtype=wp.int32), cand_count: wp.array(dtype=wp.int32),
            cand_end: wp.array(dtype=wp.int32), cand_pos: wp.array(dtype=wp.int32),
            words: wp.array(dtype=wp.uint8), word_start: wp.array(dtype=wp.int32),
            table_key: wp.array(dtype=wp.uint64), table_check: wp.array(dtype=wp.uint64),
            table_slot: wp.array(dtype=wp.int32), n_table: int,
            max_abs: wp.float64,
            ent_f_out: wp.array2d(dtype=wp.float64), ent_i_out: wp.array2d(dtype=wp.int32),
            ent_h_out: wp.array2d(dtype=wp.uint64), arr_out: wp.array2d(dtype=wp.float64),
            e_stat_out: wp.array(dtype=wp.int32), e_end_out: wp.array(dtype=wp.int32)):
    """Candidate entry s = c * MAX_ENTRIES + k of text c, read on its own (speculatively).

    e_stat_out[s]: 0 an object entry ctrc.decode accepts (its fields in row s of ent_f_out / ent_i_out /
    ent_h_out, see ``walk``), 1 a zone entry (bbox[:4] in ent_f_out[s, 8:12], its length in ent_i_out[s, 6]),
    a negative STATUS code, or E_NONE when there is no candidate; e_end_out[s] the position after
    its closing brace. Whether the candidate is really an entry is decided by ``walk``.
    """
    s = wp.tid()
    c = s // MAX_ENTRIES
    ke = s - c * MAX_ENTRIES
    e_stat_out[s] = E_NONE
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
            e_stat_out[s] = S_SYNTAX
            return
        b = int(text[p])
        if b == 125 and efirst == 1:
            p += 1
            break
        efirst = int(0)
        if b != 34:
            e_stat_out[s] = S_SYNTAX
            return
        q, kesc = scan_string(text, p, end)
        if q < 0 or kesc == 1:
            e_stat_out[s] = S_SYNTAX
            return
        key = match_word(text, p + 1, q - p - 2, words, word_start, 0, K_ZROT + 1)
        if key < 0 or (seen & (1 << key)) != 0:
            e_stat_out[s] = S_KEY
            return
        seen = seen | (1 << key)
        p = skip_ws(text, q, end)
        if p >= end or int(text[p]) != 58:
            e_stat_out[s] = S_SYNTAX
            return
        p = skip_ws(text, p + 1, end)
        if p >= end:
            e_stat_out[s] = S_SYNTAX
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
                e_stat_out[s] = S_SYNTAX
                return
            kind = V_STRING
            vs = p + 1
            vn = q - p - 2
            p = q
        elif b == 91:
            kind = V_ARRAY
            p, an, st = scan_number_array(text, p + 1, end, arr_out, s, 8)
            if st != 0:
                e_stat_out[s] = st
                return
        elif b == 45 or (b >= 48 and b <= 57):
            q, v, kind, st = scan_number(text, p, end)
            if st != 0:
                e_stat_out[s] = st
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
            e_stat_out[s] = S_SYNTAX
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
                e_stat_out[s] = S_VALUE  # also decides zone-ness: must be readable
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
                    ent_f_out[slot, k] = arr_out[s, k]
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
                        ent_f_out[s, 8 + k] = arr_out[s, k]
            else:
                bbox_n = int(-1)
        p, sep = after_value(text, p, end, 125)
        if sep == 1:
            break
        if sep < 0:
            e_stat_out[s] = sep
            return
    # end of entry: zone entry or object?
    e_end_out[s] = p
    is_root = int(0)
    if iid_s >= 0:
        if is_word(text, iid_s, iid_n, words, word_start, W_ROOT) == 1:
            is_root = int(1)
    if is_zone_type == 1 or is_root == 1:
        ent_i_out[s, 6] = bbox_n  # the walk reads the first zone entry's bbox (ctrc._zone_from)
        e_stat_out[s] = 1
        return
    else:
        if (seen & (1 << K_TYPE)) != 0:
            e_stat_out[s] = S_KEY  # a "type" other than zone on an object: not canonical
            return
        if iid_s < 0 or iid_vis == 0 or cat_ok == 0 or box_ok == 0 or bad == 1:
            e_stat_out[s] = S_VALUE
            return
        # relation rules of ctrc._relation
        if par_s < 0:
            if rel == 0:
                e_stat_out[s] = S_VALUE
                return
            rel = int(2)
        else:
            if rel < 0 or rel == 2:
                e_stat_out[s] = S_VALUE
                return
        for k in range(6):
            if wp.abs(ent_f_out[slot, k]) > max_abs:
                e_stat_out[s] = S_NUMBER
                return
        if wp.abs(rot) > max_abs:
            e_stat_out[s] = S_NUMBER
            return
        if not (ent_f_out[slot, 1] > ent_f_out[slot, 0] and ent_f_out[slot, 3] > ent_f_out[slot, 2]
                and ent_f_out[slot, 5] > ent_f_out[slot, 4]):
            e_stat_out[s] = S_VALUE
            return
        ent_f_out[slot, 6] = rot
        ent_i_out[slot, 1] = rel
        ent_i_out[slot, 2] = iid_s
        ent_i_out[slot, 3] = iid_n
        ent_i_out[slot, 4] = par_s
        ent_i_out[slot, 5] = par_n
        ent_i_out[slot, 7] = lookup_slot(cat_h, cat_chk, table_key, table_check, table_slot, n_table)
        ent_i_out[slot, 8] = cat_s
        ent_i_out[slot, 9] = cat_n
        ent_h_out[slot, 0] = iid_h
        ent_h_out[slot, 1] = par_h
        ent_h_out[slot, 2] = cat_h
        ent_h_out[slot, 3] = cat_chk
        e_stat_out[s] = 0
