"""Compiled reader of canonical CTRC completions: UTF-8 bytes -> world poses, no Python per object.

The reward's fast path (physcene.reward.text_batch). All completions of a batch
are concatenated into one uint8 array with int32 offsets (text c = bytes[offsets[c]:offsets[c+1]]),
each text cut into its own CHUNK-byte chunks (chunk_start). Four launches and a cumsum, no sync
(stages in ``prescan``, ``entries``, ``walk``, the value readers in ``values``, the
constants in ``codes``; the launchers here):

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

from __future__ import annotations

import torch
import warp as wp

from physcene.kernels.ctrc_reader.codes import MAX_ENTRIES, ReaderLimits
from physcene.kernels.ctrc_reader.entries import entries
from physcene.kernels.ctrc_reader.prescan import emit, prescan
from physcene.kernels.ctrc_reader.walk import gather, walk
from physcene.kernels.launch import Launcher
from physcene.kernels.launch import torch_view as view

__all__ = ["launch_gather", "launch_scan", "scan_buffers"]


def launch_scan(*, text: torch.Tensor, offsets: torch.Tensor, chunk_start: torch.Tensor, n_text: int,
                n_chunks: int, words: dict[str, torch.Tensor], table: dict[str, torch.Tensor],
                limits: ReaderLimits, buffers: dict[str, torch.Tensor]) -> None:
    """prescan → cumsum → emit → entries → walk of ``n_text`` texts into ``buffers``; no sync.

    text (>= offsets[-1],) uint8; offsets (n_text + 1,) int32; chunk_start (n_text + 1,) int32:
    each text's first CHUNK-byte chunk (n_chunks = chunk_start[-1]); words: ``bytes``, ``start``
    of :func:`keyword_table`; table: ``key``, ``check`` (uint64 as int64), ``slot`` (int32),
    sorted by key as unsigned; ``limits``: the format's numeric limits. ``buffers``:
    :func:`scan_buffers` for >= n_text texts and >= n_chunks chunks.
    """
    launch = Launcher(text.device)
    b = buffers
    flags, marker = b["pre"][:n_text], b["pre"][n_text:2 * n_text]
    b["pre"][:2 * n_text].zero_()
    cand_count, cand_end = b["cand_count"][:n_chunks], b["cand_end"][:n_chunks]
    w_text, w_off, w_chunk = view(text, wp.uint8), view(offsets), view(chunk_start)
    w_flags, w_marker, w_count, w_end = view(flags), view(marker), view(cand_count), view(cand_end)
    w_pos = view(b["cand_pos"])
    launch(prescan, n_chunks, [w_text, w_off, w_chunk, n_text, w_flags, w_marker, w_count])
    torch.cumsum(cand_count, 0, out=cand_end)
    launch(emit, n_chunks, [w_text, w_off, w_chunk, n_text, w_count, w_end, w_pos])
    w_ent = [view(b["ent_f"]), view(b["ent_i"]), view(b["ent_h"], wp.uint64)]
    w_e = [view(b["e_stat"]), view(b["e_end"])]
    w_words = [view(words["bytes"], wp.uint8), view(words["start"])]
    n_table = int(table["key"].shape[0])
    max_abs, max_abs_pos, on_gap = limits.launch_values()
    launch(entries, n_text * MAX_ENTRIES, [
        w_text, w_off, w_chunk, w_flags, w_marker, w_count, w_end, w_pos, *w_words,
        view(table["key"], wp.uint64), view(table["check"], wp.uint64), view(table["slot"]), n_table, max_abs,
        *w_ent, view(b["arr"]), *w_e])
    launch(walk, n_text, [
        w_text, w_off, w_chunk, w_flags, w_marker, w_count, w_end, w_pos, *w_e, *w_words,
        max_abs, max_abs_pos, on_gap, *w_ent,
        view(b["pose"]), view(b["asset"]), view(b["zone"]), view(b["status"][:n_text]),
        view(b["n_read"][:n_text])])


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
    Launcher(poses.device)(gather, n_row * n_slot, [
        view(src), view(count), int(n_slot), view(buffers["pose"]), view(buffers["asset"]),
        view(poses.view(-1, 4)), view(sizes.view(-1, 3)), view(asset.view(-1))])
