"""Completion texts -> the engine's :class:`~physcene.physics.SceneBatch` without Python per object.

The reward's fast path (:class:`TextPacker`, one per engine: ``TextPacker(engine).pack(texts)``).
The engine knows nothing of text; this module reads text for it. Per call, on the host: one join + encode
of all texts, one offsets array, one copy into a staging buffer (pinned on CUDA) and one upload;
on the device: the compiled CTRC reader of :mod:`physcene.kernels.ctrc_reader` (prescan + scan);
one device -> host copy of the per-text status; then one small upload (row sources, counts, CSR
pair offsets) and one gather kernel into the padded batch.

Texts the scanner does not fully understand (status < 0) go to the Python parser
(:func:`physcene.ctrc.parse`), which keeps every decision it makes today (including which
completions are unparsable); their Scenes are packed by ``PhysicsEngine.pack`` and written into
the same batch, so the engine is still called once. Categories are hashed in the kernel and looked
up in a sorted device table; a category not in the table yet is resolved on the host through the
engine's resolver (once per new category: a few dozen per training run), then the batch is
rescanned.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from physcene.ctrc import MAX_ABS_CM, MAX_CHARS, ON_CONTACT_GAP_CM, ParseError, grammar, parse
from physcene.kernels.ctrc_reader import (
    CHUNK,
    MAX_ENTRIES,
    S_LONG,
    STATUS,
    ReaderLimits,
    category_hash,
    keyword_table,
    launch_gather,
    launch_scan,
    scan_buffers,
)
from physcene.physics import PhysicsEngine, SceneBatch
from physcene.scene import Scene

__all__ = ["STATUS", "TextPack", "TextPacker"]

# The words the compiled reader compares against, in its role order (kernels.ctrc_reader: ENTRY_ROLES,
# TOP_ROLES, WORD_ROLES), and the limits it applies: the grammar's, given to the reader here.
ENTRY_KEYS = (*grammar.ENTRY_KEYS, grammar.TYPE, grammar.ZONE_BBOX, grammar.ZONE_ROTATION)
TOP_KEYS = grammar.TOP_KEYS
RELATIONS = (*grammar.CHILD_RELATIONS, grammar.TABLE_RELATION)  # the reader's order: in, on, near
ZONE_WORDS = (grammar.TABLE, grammar.ZONE_TYPE)  # the root entry's id and type
READER_LIMITS = ReaderLimits(max_abs_cm=MAX_ABS_CM, on_contact_gap_cm=ON_CONTACT_GAP_CM)

# Offsets are int32 (Warp indexes with int): larger batches are read by the Python parser.
_MAX_BYTES = 2**31 - 1
_UNKNOWN_CATEGORY = -9


@dataclass
class TextPack:
    """The result of :meth:`TextPacker.pack`."""

    batch: object | None
    """SceneBatch of every completion that parsed (rows in input order), None if none did."""
    row: np.ndarray
    """(n_text,) int64: batch row of each completion, -1 when it did not parse."""
    errors: list[str | None]
    """Per completion, the ParseError reason, or None when it parsed."""
    status: np.ndarray
    """(n_text,) int32: scanner status, objects read (>= 0, fast path) or a STATUS code (< 0)."""

    @property
    def fast(self) -> np.ndarray:
        """(n_text,) bool: read by the compiled scanner (the rest went to the Python parser)."""
        return self.status >= 0


class _LazyIds(Sequence):
    """Instance ids per batch row, decoded from the scanned byte spans on first access."""

    def __init__(self, data: bytes, spans: torch.Tensor, counts: np.ndarray, fast_rows: np.ndarray,
                 scene_ids: dict[int, list[str]]):
        self._data, self._spans, self._counts = data, spans, counts
        self._fast_rows, self._scene_ids = fast_rows, scene_ids
        self._ids: list[list[str]] | None = None

    def _materialise(self) -> list[list[str]]:
        if self._ids is None:
            spans = self._spans.cpu().numpy()  # (n_fast, N, 2) byte start, length
            ids: list[list[str]] = [[] for _ in range(len(self._counts))]
            for k, r in enumerate(self._fast_rows.tolist()):
                ids[r] = [self._data[s:s + n].decode("utf-8", "surrogatepass")
                          for s, n in spans[k, :self._counts[r]].tolist()]
            for r, names in self._scene_ids.items():
                ids[r] = names
            self._ids = ids
        return self._ids

    def __getitem__(self, k):
        return self._materialise()[k]

    def __len__(self) -> int:
        return len(self._counts)

    def __eq__(self, other) -> bool:
        return list(self._materialise()) == list(other)


class TextPacker:
    """Per-engine state of the fast path: staging/scan buffers and the category table."""

    def __init__(self, engine: PhysicsEngine):
        self.engine = engine
        self.device = engine.device
        words, starts = keyword_table(ENTRY_KEYS, TOP_KEYS, (*ZONE_WORDS, *RELATIONS))
        self._words = {"bytes": torch.from_numpy(words).to(self.device),
                       "start": torch.from_numpy(starts).to(self.device)}
        self._categories: dict[int, tuple[int, int, str]] = {}  # FNV hash -> (check, slot, name)
        self._table = self._upload_table()
        self._staging: torch.Tensor | None = None  # host (pinned on CUDA)
        self._device_bytes: torch.Tensor | None = None
        self._buffers: dict[str, torch.Tensor] | None = None
        self._capacity = (0, 0)  # texts, chunks

    # Buffers -----------------------------------------------------------------------------------
    def _upload_table(self) -> dict[str, torch.Tensor]:
        keys = np.array(sorted(self._categories), dtype=np.uint64)
        check = np.array([self._categories[int(k)][0] for k in keys], dtype=np.uint64)
        slot = np.array([self._categories[int(k)][1] for k in keys], dtype=np.int32)
        return {"key": torch.from_numpy(keys.view(np.int64)).to(self.device),
                "check": torch.from_numpy(check.view(np.int64)).to(self.device),
                "slot": torch.from_numpy(slot).to(self.device)}

    def _stage(self, data: bytes, offsets: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """(text bytes, int32 header) on the device through one staging buffer and one copy."""
        n_off = 4 * offsets.size
        head = (n_off + 15) // 16 * 16
        size = head + len(data)
        if self._staging is None or self._staging.numel() < size:
            cap = max(size, int(1.25 * (self._staging.numel() if self._staging is not None else 0)))
            pin = self.device.type == "cuda"
            self._staging = torch.empty(cap, dtype=torch.uint8, pin_memory=pin)
            self._device_bytes = (torch.empty(cap, dtype=torch.uint8, device=self.device) if pin
                                  else self._staging)
        host = self._staging.numpy()
        host[:n_off].view(np.int32)[:] = offsets
        host[head:size] = np.frombuffer(data, np.uint8)
        dev = self._device_bytes
        if dev is not self._staging:
            dev[:size].copy_(self._staging[:size], non_blocking=True)
        return dev[head:size], dev[:n_off].view(torch.int32)

    def _scan_buffers(self, n_text: int, n_chunks: int) -> dict[str, torch.Tensor]:
        if self._buffers is None or self._capacity[0] < n_text or self._capacity[1] < n_chunks:
            self._capacity = (max(n_text, int(1.25 * self._capacity[0])),
                              max(n_chunks, int(1.25 * self._capacity[1])))
            self._buffers = scan_buffers(*self._capacity, self.device)
        return self._buffers

    # Categories --------------------------------------------------------------------------------
    def _learn_categories(self, data: bytes, texts: np.ndarray, n_read: np.ndarray) -> bool:
        """Resolve the categories of texts whose scan met unknown ones; True if the table grew."""
        b = self._buffers
        rows = (texts[:, None] * MAX_ENTRIES + np.arange(MAX_ENTRIES)[None, :]).reshape(-1)
        rows_t = torch.from_numpy(rows).to(self.device)
        info = b["ent_i"].index_select(0, rows_t)[:, 7:10].cpu().numpy().reshape(len(texts), MAX_ENTRIES, 3)
        names: set[bytes] = set()
        for k, n in enumerate(n_read.tolist()):
            for slot, start, length in info[k, :n].tolist():
                if slot < 0:
                    names.add(data[start:start + length])
        grew = False
        for raw in sorted(names):
            key, check = category_hash(raw)
            if key in self._categories:
                continue  # a 64-bit hash collision with another name: those texts use Python
            name = raw.decode("utf-8", "surrogatepass")
            slot = self.engine.resolve(name, None)[0]
            self._categories[key] = (check, slot, name)
            grew = True
        if grew:
            self._table = self._upload_table()
        return grew

    # Packing -----------------------------------------------------------------------------------
    def _encode(self, texts: Sequence[str]) -> tuple[bytes, np.ndarray] | None:
        """(bytes, int32 header [offsets (n+1), chunk_start (n+1)]) of the texts, None if too big."""
        n = len(texts)
        joined = "".join(texts)
        if joined.isascii():  # O(1) in CPython: the string's kind
            data = joined.encode("ascii")
            lengths = np.fromiter(map(len, texts), np.int64, count=n)
        else:
            parts = [t.encode("utf-8", "surrogatepass") for t in texts]
            data = b"".join(parts)
            lengths = np.fromiter(map(len, parts), np.int64, count=n)
        if len(data) > _MAX_BYTES:
            return None
        header = np.zeros(2 * (n + 1), np.int32)
        np.cumsum(lengths, out=header[1:n + 1])
        np.cumsum(np.maximum(1, -(-lengths // CHUNK)), out=header[n + 2:])  # each text's own chunks
        return data, header

    def scan(self, texts: Sequence[str]) -> tuple[np.ndarray, bytes | None]:
        """Scanner status per text ((n,) int32, objects read or a negative STATUS code), and the bytes.

        The poses stay in the scan buffers for :meth:`pack`. Non-string items get status -2.
        """
        n = len(texts)
        if n == 0:
            return np.zeros(0, np.int32), b""
        strings = set(map(type, texts)) == {str}
        encoded = self._encode(texts) if strings else None
        if encoded is None:
            return np.full(n, -2, np.int32), None
        data, header = encoded
        n_chunks = int(header[-1])
        buffers = self._scan_buffers(n, n_chunks)
        text_t, header_t = self._stage(data, header)
        for attempt in range(2):
            launch_scan(text=text_t, offsets=header_t[:n + 1], chunk_start=header_t[n + 1:], n_text=n,
                        n_chunks=n_chunks, words=self._words, table=self._table, limits=READER_LIMITS,
                        buffers=buffers)
            both = torch.cat([buffers["status"][:n], buffers["n_read"][:n]]).cpu().numpy()  # one sync
            status, n_read = both[:n], both[n:]
            unknown = np.nonzero(status == _UNKNOWN_CATEGORY)[0]
            if attempt == 1 or unknown.size == 0:
                break
            if not self._learn_categories(data, unknown, n_read[unknown]):
                break
        status = status.copy()
        # the parser refuses a text over the grammar's length limit: leave it to the parser
        status[np.array([len(t) > MAX_CHARS for t in texts])] = S_LONG
        return status, data

    def pack(self, texts: Sequence[str], fallback: Callable | None = None) -> TextPack:
        """Completion texts → a :class:`TextPack` (batch, row per text, errors).

        Canonical CTRC (what ``ctrc.completion_text`` writes, keys in any order) is read by the
        compiled scanner straight into the batch; every other text goes to ``fallback`` (default
        :func:`physcene.ctrc.parse`), whose Scenes are packed into the same batch and whose
        ParseErrors are the texts that do not parse. Rows follow the input order.
        """
        fallback = fallback or parse
        engine, device = self.engine, self.device
        n = len(texts)
        status, data = self.scan(texts)
        fast = status >= 0
        slow = np.nonzero(~fast)[0]
        parsed = {int(k): fallback(texts[k]) for k in slow.tolist()}
        scenes = {k: p for k, p in parsed.items() if isinstance(p, Scene)}
        errors: list[str | None] = [None] * n
        for k, p in parsed.items():
            if isinstance(p, ParseError):
                errors[k] = p.reason
            elif not isinstance(p, Scene):
                errors[k] = f"fallback parser returned {type(p).__name__}"
        ok = fast.copy()
        ok[list(scenes)] = True
        row = np.full(n, -1, np.int64)
        ok_idx = np.nonzero(ok)[0]
        row[ok_idx] = np.arange(ok_idx.size)
        if ok_idx.size == 0:
            return TextPack(None, row, errors, status)
        counts = np.where(fast, status, 0).astype(np.int64)
        for k, s in scenes.items():
            counts[k] = len(s.objects)
        counts = counts[ok_idx]
        n_row, n_slot = ok_idx.size, max(1, int(counts.max()))
        pairs = counts * (counts - 1) // 2
        pair_start = np.concatenate([[0], np.cumsum(pairs)])
        if pair_start[-1] >= 2**31 // 64:
            raise ValueError(f"batch has {pair_start[-1]} object pairs; split it into smaller batches")
        src = np.where(fast[ok_idx], ok_idx, -1)
        fast_idx = np.nonzero(fast)[0]
        fast_rows = row[fast_idx]
        # one upload: row sources, counts, CSR pair offsets, scanned texts (for the lazy ids and the
        # zones) and their batch rows
        ints = np.concatenate([src, counts, pair_start, fast_idx, fast_rows]).astype(np.int32)
        ints = torch.from_numpy(ints).to(device)
        src_t, count_t = ints[:n_row], ints[n_row:2 * n_row]
        pair_start_t = ints[2 * n_row:3 * n_row + 1]
        fast_src = ints[3 * n_row + 1:3 * n_row + 1 + fast_idx.size]
        fast_rows_t = ints[3 * n_row + 1 + fast_idx.size:].long()
        poses_t = torch.empty(n_row, n_slot, 4, dtype=torch.float32, device=device)
        sizes_t = torch.empty(n_row, n_slot, 3, dtype=torch.float32, device=device)
        asset_t = torch.empty(n_row, n_slot, dtype=torch.int32, device=device)
        zones_t = torch.zeros(n_row, 4, dtype=torch.float32, device=device)
        if fast_idx.size:  # every slot: scanned objects, padding elsewhere
            launch_gather(src=src_t, count=count_t, n_slot=n_slot, buffers=self._buffers, poses=poses_t,
                          sizes=sizes_t, asset=asset_t)
            scanned_zones = self._buffers["zone"].index_select(0, fast_src.long())[:, :4]
            zones_t.index_copy_(0, fast_rows_t, scanned_zones.float())
        else:  # nothing scanned (no scan buffers yet, maybe): padding, the fallback rows below
            poses_t.zero_()
            sizes_t.fill_(1.0)
            asset_t.zero_()
        scene_ids: dict[int, list[str]] = {}
        if scenes:
            fb_rows = row[list(scenes)]
            slow_batch = engine.pack(list(scenes.values()))
            rows_t = torch.from_numpy(fb_rows).to(device)
            width = slow_batch.poses.shape[1]
            poses_t[:, :width].index_copy_(0, rows_t, slow_batch.poses)
            sizes_t[:, :width].index_copy_(0, rows_t, slow_batch.sizes)
            asset_t[:, :width].index_copy_(0, rows_t, slow_batch.asset_index)
            zones_t.index_copy_(0, rows_t, slow_batch.zones.to(device))
            scene_ids = {int(r): s.ids() for r, s in zip(fb_rows.tolist(), scenes.values())}
        spans = torch.zeros(0, n_slot, 2, dtype=torch.int32, device=device)
        if fast_idx.size:
            # a copy (the scan buffers are reused by the next call); index_select, not advanced
            # indexing, which is ~100x slower on CPU tensors here
            entry_ints = self._buffers["ent_i"].view(-1, MAX_ENTRIES, 10)
            spans = entry_ints[:, :n_slot, 2:4].index_select(0, fast_src.long())
        ids = _LazyIds(data or b"", spans, counts, fast_rows, scene_ids)
        batch = SceneBatch(
            poses=poses_t, sizes=sizes_t,
            mask=torch.arange(n_slot, device=device)[None, :] < count_t[:, None],
            ids=ids, asset_index=asset_t, count=count_t, pair_start=pair_start_t,
            n_pairs=int(pair_start[-1]), zones=zones_t)
        return TextPack(batch, row, errors, status)
