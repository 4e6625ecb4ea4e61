"""The fast decoder: one prompt pass, then fixed-shape decoding steps over a static KV cache, each
step replayed as a CUDA graph (eager on CPU: the same code path, so the CPU tests exercise it).

A step reads only what it needs: the cache is read up to the smallest of a few fixed lengths
(``buckets``, one graph each) that covers every row's position, so the KV bytes read grow with the
text instead of always being the whole cache. Left padding is handled through per-row position
ids (``position - padding``) and a per-row mask of the columns written.

Under the CTRC constraint (:class:`~physcene.train.decode.overlap.OverlappedConstraint`) the host
checks step ``t``'s tokens while the GPU computes step ``t + 1`` with them (speculatively). A row
whose token is refused gets the constraint's token instead and stands still for one step: its next
step rewrites the same cache column with the right token, and its speculative output is discarded;
the other rows go on. The host's grammar work thus leaves the GPU's critical path except for the
rows it repairs (one extra step each).
"""

from __future__ import annotations

import contextlib
import inspect
import logging
import time
from dataclasses import dataclass, field

import torch

from physcene.train.decode.attention import register_folded_attention
from physcene.train.decode.cache import StaticKV
from physcene.train.decode.fuse import fused_layers

__all__ = ["DecodeResult", "FastDecoder", "cut_at_eos", "text_model"]

logger = logging.getLogger(__name__)

_COPIED_CANDIDATES = 8  # candidates per row copied to the host each step (the constraint's first checks)


@dataclass
class DecodeResult:
    """What one :meth:`FastDecoder.generate` call produced."""

    tokens: list[list[int]]
    """Each row's completion token ids (up to and with its EOS; no padding)."""
    steps: int = 0
    """Decoding steps run (the prompt pass not counted)."""
    graphs: bool = False
    """Whether the steps were replayed CUDA graphs (else eager)."""
    fallback_reason: str | None = None
    """Why CUDA graphs were not used where they were asked for (None: they were, or not asked)."""
    repairs: int = 0
    """Rows x steps the constraint repaired (each a row standing still for one step)."""
    seconds: dict = field(default_factory=dict)
    """Wall time by part: prefill, decode, host_check (the constraint's host work), capture."""
    kv_bytes_read: int = 0
    """KV-cache bytes the decoding steps read (bucketed read lengths x rows x column bytes)."""
    merged_projections: int = 0
    """LoRA projections decoded with their adapters merged (:mod:`~physcene.train.decode.merge`)."""


def text_model(model: torch.nn.Module) -> torch.nn.Module:
    """The transformers model whose config holds the text attention (Qwen3: the model itself; Qwen3-VL:
    its language model), through a PEFT wrapper."""
    base = model.get_base_model() if hasattr(model, "get_base_model") else model
    inner = getattr(base, "model", base)
    return getattr(inner, "language_model", base)


def _cache_keyword(model: torch.nn.Module) -> str:
    """``cache`` (transformers >= 5.2x) or ``past_key_values`` (earlier 5.x): the model's KV-cache keyword."""
    base = model.get_base_model() if hasattr(model, "get_base_model") else model
    return "cache" if "cache" in inspect.signature(base.forward).parameters else "past_key_values"


class FastDecoder:
    """Decode ``batch`` rows with a static cache of ``length`` columns (longest prompt + new tokens).

    One decoder serves every call of that shape (PADA's rounds, eval's batches): the CUDA graphs are
    captured once (``graphs``: on CUDA; a failure falls back to eager steps with the reason logged and
    kept in :attr:`fallback_reason`). ``buckets``: how many read lengths (graphs) the cache is cut into.
    """

    reads_stream = True
    """Under the constraint on a GPU: a row's logits are read on a stream of their own (False: on the
    decoding stream, behind the next step: ``benchmarks/constraint_replay.py streams`` compares them)."""

    def __init__(self, model: torch.nn.Module, *, batch: int, length: int, graphs: bool = True,
                 buckets: int = 16, attention: str = "sdpa", fuse: bool = False):
        if batch < 1 or length < 2:
            raise ValueError(f"FastDecoder: batch {batch} and length {length} must be >= 1 and >= 2")
        self.model = model
        self.batch, self.length = int(batch), int(length)
        text = text_model(model)
        config = text.config
        param = next(model.parameters())
        self.device, self.dtype = param.device, param.dtype
        self.vocab = int(model.get_output_embeddings().weight.shape[0])
        heads = int(config.num_attention_heads)
        kv_heads = int(getattr(config, "num_key_value_heads", None) or heads)
        head_dim = int(getattr(config, "head_dim", None) or config.hidden_size // heads)
        self.cache_keyword = _cache_keyword(model)
        b, dev = self.batch, self.device
        self.positions = torch.zeros(b, dtype=torch.long, device=dev)  # column each row writes next
        self.cache = StaticKV(int(config.num_hidden_layers), b, kv_heads, self.length, head_dim,
                              dtype=self.dtype, device=dev, positions=self.positions)
        self.padding = torch.zeros(b, dtype=torch.long, device=dev)
        self.prompt_length = torch.zeros((), dtype=torch.long, device=dev)
        self.written = torch.zeros(b, self.length, dtype=torch.bool, device=dev)  # the attention mask
        self.token = torch.zeros(b, dtype=torch.long, device=dev)  # each row's last token (next input)
        self.finished = torch.zeros(b, dtype=torch.bool, device=dev)
        self.candidates = torch.zeros(b, _COPIED_CANDIDATES, dtype=torch.long, device=dev)
        self.logits = torch.zeros(2, b, self.vocab, dtype=torch.float32, device=dev)  # last two steps'
        self.step = torch.zeros((), dtype=torch.long, device=dev)
        self.out: torch.Tensor | None = None
        # per-call settings read by the step (tensors, so the captured graphs see them)
        self.min_new = torch.zeros((), dtype=torch.long, device=dev)
        self.eos = torch.zeros(1, dtype=torch.long, device=dev)
        self.pad_id = torch.zeros((), dtype=torch.long, device=dev)
        self.sampling = False
        self.warpers = None
        self._settings: tuple = ()
        chunk = -(-self.length // max(int(buckets), 1))
        chunk = -(-chunk // 64) * 64
        self.bounds = sorted({min(self.length, chunk * k) for k in range(1, -(-self.length // chunk) + 1)})
        self.want_graphs = bool(graphs) and self.device.type == "cuda"
        self.graphs: dict[tuple, torch.cuda.CUDAGraph] = {}
        self.fallback_reason: str | None = None
        self.capture_seconds = 0.0
        self.warmups = 0  # captures tried: each ran the step for real first (its writes restored after)
        self.attention = attention
        register_folded_attention(attention)
        self.fuse = bool(fuse)
        self.text = text

    # --- one step -------------------------------------------------------------------------------------
    def _choose(self, logits: torch.Tensor) -> None:
        """Pick each row's token from ``logits`` [B, V] (float32) into :attr:`token`; candidates for the
        constraint into :attr:`candidates`; the logits into this step's slot of :attr:`logits`."""
        produced = (self.positions - self.prompt_length + 1).clamp(min=0)  # index of the token chosen
        blocked = (produced < self.min_new)[:, None]  # min_new_tokens: no EOS yet (index ops: no host sync)
        logits.index_copy_(1, self.eos, torch.where(blocked, float("-inf"), logits.index_select(1, self.eos)))
        if self.out is None:  # under the constraint: what the host may need to repair a row
            self.logits.index_copy_(0, (self.step % 2).view(1), logits[None])
        if self.sampling:
            warped = self.warpers(None, logits) if self.warpers is not None else logits
            uniform = torch.rand_like(warped).clamp_(min=torch.finfo(warped.dtype).tiny)
            values, order = (warped - (-uniform.log()).log()).topk(_COPIED_CANDIDATES, dim=-1)
            token = order[:, 0]
        else:
            token = logits.argmax(dim=-1)
            if self.out is None:
                values, order = logits.topk(_COPIED_CANDIDATES, dim=-1)
        if self.out is None:
            self.candidates.copy_(torch.where(torch.isfinite(values), order, -1))
        token = torch.where(self.finished, self.pad_id, token)
        self.finished |= (token[:, None] == self.eos[None]).any(dim=-1)
        self.token.copy_(token)
        if self.out is not None:
            self.out.scatter_(1, produced.clamp(max=self.out.shape[1] - 1)[:, None], token[:, None])
        self.step.add_(1)

    def _forward_step(self, read_length: int) -> None:
        """One decoding step: feed :attr:`token` at :attr:`positions`, choose the next tokens."""
        self.cache.read_length = read_length
        self.written.scatter_(1, self.positions[:, None], True)
        mask = self.written[:, None, None, :read_length]
        position_ids = (self.positions - self.padding)[:, None]
        out = self.model(input_ids=self.token[:, None], attention_mask=mask, position_ids=position_ids,
                         use_cache=True, **{self.cache_keyword: self.cache})
        self._choose(out.logits[:, -1].float())
        self.positions.add_(1).clamp_(max=self.length - 1)

    def _key(self, read_length: int) -> tuple:
        return (read_length, *self._settings)

    def _capture(self, read_length: int) -> torch.cuda.CUDAGraph | None:
        """The step's CUDA graph for ``read_length`` (captured on first use; state saved around the
        warm-up, which runs the step for real); None after a failure (eager from then on)."""
        key = self._key(read_length)
        graph = self.graphs.get(key)
        if graph is not None or self.fallback_reason is not None:
            return graph
        start = time.perf_counter()
        self.warmups += 1
        state = [t.clone() for t in self._state()]
        rng = torch.cuda.get_rng_state(self.device)  # warm-up draws must not shift a seeded run
        try:
            stream = torch.cuda.Stream(self.device)
            stream.wait_stream(torch.cuda.current_stream(self.device))
            with torch.cuda.stream(stream):  # warm-up off the capture: lazy inits, cuBLAS workspaces
                for _ in range(2):
                    self._forward_step(read_length)
            torch.cuda.current_stream(self.device).wait_stream(stream)
            graph = torch.cuda.CUDAGraph()
            pool = next(iter(self.graphs.values())).pool() if self.graphs else None
            # thread_local: work another thread puts on the device meanwhile does not void the capture
            with torch.cuda.graph(graph, pool=pool, capture_error_mode="thread_local"):
                self._forward_step(read_length)
            self.graphs[key] = graph
        except Exception as error:  # noqa: BLE001 - any capture failure: eager steps, reason kept
            self.fallback_reason = f"CUDA graph capture failed ({type(error).__name__}: {error})"
            logger.warning("fast decoding runs eager steps: %s", self.fallback_reason)
            graph = None
            try:
                torch.cuda.synchronize(self.device)
            except RuntimeError as sync_error:  # noqa: PERF203 - logged, the eager steps will tell
                logger.warning("after the failed capture: %s", sync_error)
        for t, saved in zip(self._state(), state):
            t.copy_(saved)
        torch.cuda.set_rng_state(rng, self.device)
        self.capture_seconds += time.perf_counter() - start
        return graph

    def _state(self) -> list[torch.Tensor]:
        """Every buffer a step writes (restored after a warm-up), the cache apart: the warm-up writes
        its columns at the rows' current positions, which the next real step rewrites."""
        tensors = [self.positions, self.written, self.token, self.finished, self.candidates, self.step,
                   self.logits]
        return tensors + ([self.out] if self.out is not None else [])

    def run_step(self) -> None:
        """One decoding step, its graph replayed when there is one."""
        read_length = self._read_length()
        if self.want_graphs:
            graph = self._capture(read_length)
            if graph is not None:
                graph.replay()
                return
        self._forward_step(read_length)

    def _read_length(self) -> int:
        furthest = self._furthest + 1
        self._furthest += 1
        for bound in self.bounds:
            if bound >= furthest:
                return bound
        return self.length

    # --- a call ----------------------------------------------------------------------------------------
    def prefill(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> None:
        """The prompt pass over left-padded ``input_ids`` [B, P]: fills cache columns ``[0, P)`` and
        chooses every row's first token."""
        b, p = input_ids.shape
        if b != self.batch or p >= self.length:
            raise ValueError(f"FastDecoder for {self.batch} rows x {self.length} columns got prompts "
                             f"{b} x {p}")
        mask2 = attention_mask.to(self.device).bool()
        if not bool(mask2[:, -1].all()):
            raise ValueError("FastDecoder needs left-padded prompts (a row ends in padding)")
        self.padding.copy_((~mask2).sum(dim=1))
        self.prompt_length.fill_(p)
        self.written.zero_()
        self.written[:, :p] = mask2
        self.finished.zero_()
        self.step.zero_()
        self.positions.fill_(p - 1)  # _choose reads it: the first token's index is 0
        self.cache.read_length = p
        causal = torch.ones(p, p, dtype=torch.bool, device=self.device).tril()
        mask4 = causal[None, None] & mask2[:, None, None, :]
        # padding rows attend to everything (finite, never read), as transformers' sdpa mask does
        mask4 |= ~mask4.any(dim=-1, keepdim=True)
        position_ids = (mask2.long().cumsum(-1) - 1).clamp(min=0)
        out = self.model(input_ids=input_ids.to(self.device), attention_mask=mask4, position_ids=position_ids,
                         use_cache=True, logits_to_keep=1, **{self.cache_keyword: self.cache})
        self._choose(out.logits[:, -1].float())
        self.positions.fill_(p)
        self._furthest = p

    def _parameters_moved(self) -> bool:
        """Whether a parameter's storage changed since the graphs were captured (a graph reads the
        addresses it was captured with: a model moved or re-wrapped would be read stale)."""
        now = tuple(p.data_ptr() for p in self.model.parameters())
        moved, self._addresses = getattr(self, "_addresses", now) != now, now
        return moved

    def configure(self, *, max_new_tokens: int, min_new_tokens: int, eos: list[int], pad: int,
                  sampling: bool, warpers, keep_output: bool) -> None:
        """Per-call settings (the graphs of other settings stay captured)."""
        if self._parameters_moved() and self.graphs:
            logger.warning("model parameters moved since the decoding graphs were captured: recapturing")
            self.graphs.clear()
        self.min_new.fill_(int(min_new_tokens))
        eos_ids = torch.tensor(sorted(set(eos)), dtype=torch.long, device=self.device)
        if eos_ids.shape != self.eos.shape or not torch.equal(eos_ids, self.eos):
            self.eos = eos_ids
            self.graphs.clear()
        self.pad_id.fill_(int(pad))
        self.sampling = bool(sampling)
        self.warpers = warpers if sampling else None
        width = int(max_new_tokens)
        if keep_output:
            if self.out is None or self.out.shape[1] != width:
                self.out = torch.full((self.batch, width), int(pad), dtype=torch.long, device=self.device)
                self.graphs = {k: g for k, g in self.graphs.items() if not k[3]}
            self.out.fill_(int(pad))
        else:
            self.out = None
        # what a captured graph bakes in besides its read length
        self._settings = (self.sampling, _warper_key(self.warpers), self.out is not None)

    def generate(self, input_ids: torch.Tensor, attention_mask: torch.Tensor, *, max_new_tokens: int,
                 eos: list[int], pad: int, min_new_tokens: int = 0, sampling: bool = False, warpers=None,
                 constraint=None) -> DecodeResult:
        """Completions of the left-padded prompts (``constraint``: an
        :class:`~physcene.train.decode.overlap.OverlappedConstraint`, else unconstrained)."""
        if input_ids.shape[1] + max_new_tokens > self.length:
            raise ValueError(f"prompts of {input_ids.shape[1]} tokens + {max_new_tokens} new exceed the "
                             f"decoder's {self.length} columns")
        timing = {"prefill": 0.0, "decode": 0.0, "host_check": 0.0, "capture": 0.0}
        captured = self.capture_seconds
        self.configure(max_new_tokens=max_new_tokens, min_new_tokens=min_new_tokens, eos=eos, pad=pad,
                       sampling=sampling, warpers=warpers, keep_output=constraint is None)
        start = time.perf_counter()
        allocations = self.cache.allocations
        self.prefill(input_ids, attention_mask)
        if self.cache.allocations != allocations and allocations:
            self.graphs.clear()  # captured on cache buffers the prompt pass has replaced
        timing["prefill"] = time.perf_counter() - start
        start = time.perf_counter()
        with fused_layers(self.text) if self.fuse else contextlib.nullcontext():
            if constraint is None:
                tokens, steps, repairs, read = self._decode_free(max_new_tokens)
            else:
                tokens, steps, repairs, read = self._decode_constrained(max_new_tokens, constraint, timing)
        timing["capture"] = self.capture_seconds - captured
        timing["decode"] = time.perf_counter() - start - timing["capture"]
        return DecodeResult(tokens=tokens, steps=steps, graphs=self.want_graphs and not self.fallback_reason,
                            fallback_reason=self.fallback_reason, repairs=repairs, seconds=timing,
                            kv_bytes_read=read * self.batch * self.cache.bytes_per_column())

    def _decode_free(self, max_new_tokens: int) -> tuple[list[list[int]], int, int, int]:
        """Unconstrained: steps until every row has its EOS (checked every 16 steps without waiting:
        the flag's copy of 16 steps ago) or ``max_new_tokens`` tokens."""
        cuda = self.device.type == "cuda"
        done_flag = torch.zeros((), dtype=torch.bool, pin_memory=cuda)
        pending = None
        steps, read = 0, 0
        while steps < max_new_tokens - 1:
            if steps % 16 == 0:
                if pending is not None and pending.query() and bool(done_flag):
                    break
                done_flag.copy_(self.finished.all(), non_blocking=cuda)
                if cuda:
                    pending = torch.cuda.Event()
                    pending.record()
                elif bool(done_flag):
                    break
            read += self._read_length_peek()
            self.run_step()
            steps += 1
        rows = self.out.tolist()
        eos = set(self.eos.tolist())
        return [cut_at_eos(row, eos) for row in rows], steps, 0, read

    def _read_length_peek(self) -> int:
        furthest = self._furthest + 1
        return next((bound for bound in self.bounds if bound >= furthest), self.length)

    def _decode_constrained(self, max_new_tokens: int, constraint, timing: dict):
        """Under the constraint: the host checks step t while the GPU runs step t + 1 (module docstring)."""
        cuda = self.device.type == "cuda"
        slots = [(torch.zeros(self.batch, dtype=torch.long, pin_memory=cuda),
                  torch.zeros(self.batch, _COPIED_CANDIDATES, dtype=torch.long, pin_memory=cuda))
                 for _ in range(2)]
        events: list = [None, None]

        def fetch(slot: int) -> None:
            slots[slot][0].copy_(self.token, non_blocking=cuda)
            slots[slot][1].copy_(self.candidates, non_blocking=cuda)
            if cuda:
                events[slot] = torch.cuda.Event()
                events[slot].record()

        # A row whose candidates are all refused has its logits read (and scanned) during the check. On
        # the step's stream that read would queue behind step t + 1, already launched, and the host would
        # wait for the whole step at every such check; on a stream of its own it waits only for step t,
        # whose event the check has already waited for. The same kernels run, so the same tokens come out.
        # Except where launching step t + 1 captured a graph: the capture's warm-up runs the step for real,
        # writing both logits slots, and restores them after; a read on its own stream would race those
        # writes (on an H200 shared by four decodes: torch's topk assert, `writeIndex < outputSliceSize`),
        # so the reads of that check wait for the step (one wait per read length, 8 a call at most).
        reads = torch.cuda.Stream(self.device) if cuda and self.reads_stream else None

        def launch() -> None:
            warmups = self.warmups
            self.run_step()
            if reads is not None and self.warmups != warmups:
                reads.wait_stream(torch.cuda.current_stream(self.device))

        def check(slot: int, skip: set[int]) -> dict[int, int]:
            if events[slot] is not None:
                events[slot].synchronize()
            start = time.perf_counter()
            tokens, candidates = slots[slot][0].tolist(), slots[slot][1].tolist()
            with torch.cuda.stream(reads) if reads is not None else contextlib.nullcontext():
                corrections = constraint.check(tokens, candidates, skip, lambda row: self.logits[slot, row])
            if reads is not None:  # step t + 2 rewrites this slot's logits: not before the reads are done
                torch.cuda.current_stream(self.device).wait_stream(reads)
            timing["host_check"] += time.perf_counter() - start
            return corrections

        def repair(corrections: dict[int, int], rewind: bool) -> None:
            rows = torch.tensor(list(corrections), dtype=torch.long)
            tokens = torch.tensor(list(corrections.values()), dtype=torch.long)
            rows, tokens = rows.to(self.device, non_blocking=cuda), tokens.to(self.device, non_blocking=cuda)
            self.token.index_copy_(0, rows, tokens)
            self.finished.index_copy_(0, rows, (tokens[:, None] == self.eos[None]).any(dim=-1))
            if rewind:  # the row's next step rewrites the column its discarded step wrote
                self.positions.index_add_(0, rows, torch.full_like(rows, -1))

        fetch(0)
        corrections = check(0, set())  # the prompt pass's tokens: nothing speculative launched yet
        if corrections:
            repair(corrections, rewind=False)
        steps, read, repairs = 0, 0, 0
        limit = 2 * max_new_tokens + 8  # repairs add steps; a row repaired at every step is cut here
        skip: set[int] = set()
        if not constraint.done():
            read += self._read_length_peek()
            launch()
            steps += 1
            fetch(steps % 2)
        while not constraint.done() and steps < limit:
            read += self._read_length_peek()
            launch()  # speculative: step t + 1 with step t's tokens, before they are checked
            steps += 1
            fetch(steps % 2)
            corrections = check((steps - 1) % 2, skip)
            skip = set(corrections)
            repairs += len(corrections)
            if corrections:
                repair(corrections, rewind=True)
            # a repaired row's rows stay behind by one: the read length covers the furthest row anyway
        if not constraint.done():  # the last launched step's tokens
            check(steps % 2, skip)
        return constraint.tokens(), steps, repairs, read


def _warper_key(warpers) -> tuple:
    """The warpers' types and settings: a graph captured with them bakes their values in."""
    if warpers is None:
        return ()
    return tuple((type(w).__name__, tuple(sorted((k, v) for k, v in vars(w).items()
                                                 if isinstance(v, (int, float, str, bool)))))
                 for w in warpers)


def cut_at_eos(row: list[int], eos: set[int]) -> list[int]:
    """``row`` up to and with its first token of ``eos`` (the whole row when none)."""
    for i, t in enumerate(row):
        if t in eos:
            return row[:i + 1]
    return row
