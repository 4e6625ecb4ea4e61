"""The CTRC constraint's host check spread over worker processes (``constraint_workers``).

Under the constraint the fast decoder's host checks step t's tokens while the GPU runs step t + 1
(:class:`~physcene.train.decode.overlap.OverlappedConstraint`). The check is pure Python, about 20-35
µs per row and step, so at PADA's 128 rows it takes 3-4 ms a step where the GPU takes 1-2: the host,
not the GPU, sets the rollout's pace (the RL study's rounds: 3.9 of 4.8 s of generation in the
check). Threads would share one interpreter lock; :class:`ShardedConstraint` gives each of K worker
processes every K-th row, with a constraint of the same rules for those rows, and per step sends each
its rows' tokens and candidates and gathers the rows it repaired. A worker that needs a row's logits
(every copied candidate refused) asks for them and the main process reads them off the GPU.

The decisions are the single-process check's: the same rules, and a refused draw redrawn from a
generator seeded by (call, row, position), not by the order rows are checked in, so a seeded round
writes the same tokens with any number of workers (``tests/train/test_decode_shards.py``).

The workers are started once per (tokenizer, count) with ``spawn`` (the parent holds CUDA) and kept
for the process: a round only sends its prompts. Each holds one torch thread. As with any ``spawn``ed
process (a DataLoader's workers too), a script of one's own that trains with workers must start from an
``if __name__ == "__main__":`` block, or each worker runs the script again; the ``physcene`` commands do.
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import multiprocessing
import pickle
import time
import traceback
import weakref

import torch

from physcene.train.constrained import CTRCConstraint
from physcene.train.decode.overlap import OverlappedConstraint

__all__ = ["ConstraintPool", "ShardedConstraint", "constraint_pool"]

logger = logging.getLogger(__name__)

_POOLS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # tokenizer -> {workers: ConstraintPool}
_COUNTERS = ("masked_steps", "refused_draws", "vocabulary_scans", "scan_seconds", "indexed_scans",
             "trie_scans")


class ConstraintWorkerError(RuntimeError):
    """A constraint worker failed; the message carries its traceback."""


def _serve(conn, payload: bytes) -> None:
    """A worker: build a constraint for its rows on ``start``, check them on ``check``, hand back its
    tokens and counters on ``finish``; ``stop`` ends it."""
    torch.set_num_threads(1)
    tokenizer = pickle.loads(payload)
    check = None
    while True:
        message = conn.recv()
        kind = message[0]
        try:
            if kind == "stop":
                return
            if kind == "start":
                _, prompts, texts, settings, max_new_tokens, eos, seed, rows = message
                constraint = CTRCConstraint(tokenizer, prompts, **settings)
                constraint.texts = texts  # what the rows hold already (a completion's forced prefix)
                check = OverlappedConstraint(constraint, max_new_tokens=max_new_tokens, eos=eos,
                                             warpers=settings["warpers"], seed=seed, rows=rows)
                conn.send(("started",))
            elif kind == "check":
                _, tokens, candidates, skip = message

                def logits_row(b: int) -> torch.Tensor:
                    conn.send(("need", b))
                    return conn.recv()

                corrections = check.check(tokens, candidates, set(skip), logits_row)
                conn.send(("checked", corrections, check.open))
            elif kind == "finish":
                stats = check.constraint.stats
                conn.send(("finished", check.tokens(), stats.overruled,
                           {name: getattr(stats, name) for name in _COUNTERS}))
                check = None
        except Exception:  # noqa: BLE001 - every failure goes back to the main process, which raises it
            conn.send(("error", traceback.format_exc()))


class ConstraintPool:
    """``workers`` processes that check rows of a tokenizer's constraints (:func:`constraint_pool`)."""

    def __init__(self, tokenizer, workers: int):
        if workers < 1:
            raise ValueError(f"a constraint pool needs at least one worker, got {workers}")
        context = multiprocessing.get_context("spawn")
        payload = pickle.dumps(tokenizer)
        self.connections, self.processes = [], []
        for _ in range(workers):
            parent, child = context.Pipe()
            process = context.Process(target=_serve, args=(child, payload), daemon=True,
                                      name="physcene-constraint")
            process.start()
            child.close()
            self.connections.append(parent)
            self.processes.append(process)
        atexit.register(self.close)

    def __len__(self) -> int:
        return len(self.connections)

    def receive(self, worker: int):
        """The worker's next message; its traceback raised as :class:`ConstraintWorkerError`."""
        try:
            message = self.connections[worker].recv()
        except EOFError:
            raise ConstraintWorkerError(f"constraint worker {worker} exited "
                                        f"(code {self.processes[worker].exitcode})") from None
        if message[0] == "error":
            raise ConstraintWorkerError(f"constraint worker {worker} failed:\n{message[1]}")
        return message

    def close(self) -> None:
        for conn, process in zip(self.connections, self.processes):
            with contextlib.suppress(BrokenPipeError, OSError):  # a worker already gone: joined below
                conn.send(("stop",))
            process.join(timeout=5)
            if process.is_alive():
                process.kill()
        self.connections, self.processes = [], []


def constraint_pool(tokenizer, workers: int) -> ConstraintPool:
    """The pool of ``workers`` processes for ``tokenizer`` (started on first use, kept while the
    tokenizer lives)."""
    pools = _POOLS.setdefault(tokenizer, {})
    pool = pools.get(workers)
    if pool is None or not all(p.is_alive() for p in pool.processes):
        start = time.perf_counter()
        pool = pools[workers] = ConstraintPool(tokenizer, workers)
        logger.info("started %d constraint workers in %.1f s", workers, time.perf_counter() - start)
    return pool


class ShardedConstraint:
    """:class:`~physcene.train.decode.overlap.OverlappedConstraint`'s interface (``check``, ``done``,
    ``tokens``) over a pool's workers, each with every K-th row of ``constraint``. ``constraint``'s
    counters and per-row overruled positions are filled in when the tokens are taken."""

    def __init__(self, constraint: CTRCConstraint, *, max_new_tokens: int, eos: list[int], warpers=None,
                 seed: int = 0, pool: ConstraintPool):
        self.constraint = constraint
        rows = len(constraint.texts)
        count = min(len(pool), rows)
        self.pool = pool
        self.shards = [list(range(w, rows, count)) for w in range(count)]
        settings = {**constraint.settings(), "warpers": warpers}
        for w, shard in enumerate(self.shards):
            pool.connections[w].send(("start", [constraint.prompts[r] for r in shard],
                                      [constraint.texts[r] for r in shard], settings, int(max_new_tokens),
                                      list(eos), int(seed), shard))
        failure = None
        for w in range(count):  # every answer read, so a failure leaves no reply behind in the pool
            try:
                pool.receive(w)
            except ConstraintWorkerError as error:
                failure = failure or error
        if failure is not None:
            raise failure
        self.open = [len(shard) for shard in self.shards]
        self._tokens: list[list[int]] | None = None

    def done(self) -> bool:
        return sum(self.open) == 0

    def check(self, tokens: list[int], candidates: list[list[int]], skip: set[int],
              logits_row) -> dict[int, int]:
        """One step of every worker's rows (see ``OverlappedConstraint.check``); the rows repaired."""
        start = time.perf_counter()
        for w, shard in enumerate(self.shards):
            local_skip = [k for k, r in enumerate(shard) if r in skip] if skip else []
            self.pool.connections[w].send(("check", [tokens[r] for r in shard],
                                           [candidates[r] for r in shard], local_skip))
        corrections: dict[int, int] = {}
        failure = None
        for w, shard in enumerate(self.shards):
            while True:
                try:
                    message = self.pool.receive(w)
                except ConstraintWorkerError as error:
                    failure = failure or error
                    break
                if message[0] == "need":  # a row whose copied candidates were all refused
                    self.pool.connections[w].send(logits_row(shard[message[1]]).float().cpu())
                    continue
                _, repaired, self.open[w] = message
                corrections.update({shard[k]: t for k, t in repaired.items()})
                break
        if failure is not None:
            raise failure
        self.constraint.stats.seconds += time.perf_counter() - start
        return corrections

    def tokens(self) -> list[list[int]]:
        """Every row's accepted tokens (gathered from the workers once; their counters added to
        ``constraint.stats``)."""
        if self._tokens is None:
            rows = len(self.constraint.texts)
            out: list[list[int]] = [[] for _ in range(rows)]
            stats = self.constraint.stats
            for w, shard in enumerate(self.shards):
                self.pool.connections[w].send(("finish",))
                _, tokens, overruled, counters = self.pool.receive(w)
                for k, r in enumerate(shard):
                    out[r] = tokens[k]
                    stats.overruled[r] = overruled[k]
                    self.constraint.finished[r] = True
                for name, value in counters.items():
                    setattr(stats, name, getattr(stats, name) + value)
            self._tokens = out
        return [list(row) for row in self._tokens]
