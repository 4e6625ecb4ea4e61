"""Files that appear whole or not at all: written under a temporary name, renamed when complete.

Every file a command writes for a later run to read (data splits and their stats, evaluation
results, repaired layouts, anchors, run info, exports, cached bakes) goes through this module. The
temporary file lives in the target's folder (``os.replace`` is atomic only within one file
system), is named ``.<name>.<random>.tmp`` and is removed when the writer fails or is interrupted,
so a Ctrl-C leaves either the previous file or the new one, never half of one, and no litter.

- :func:`write_atomic`: one file from bytes or text;
- :func:`open_atomic`: a context manager for streamed output (JSONL, ``savefig``, ``np.savez``);
- :func:`write_atomic_many`: files that belong together (a split and its stats): all are written
  first, then renamed, the last one named last, so a file of an older run never sits beside a
  newer one;
- :func:`replace_dir`: a folder written by a library (a tokenizer) that must appear complete.
"""

from __future__ import annotations

import os
import secrets
import shutil
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import IO

__all__ = ["TEMP_SUFFIX", "open_atomic", "replace_dir", "temp_path", "write_atomic", "write_atomic_many"]

TEMP_SUFFIX = ".tmp"
"""Ending of every temporary name this module makes (what a clean-up or a test looks for)."""


def temp_path(path: str | os.PathLike) -> Path:
    """A fresh temporary name beside ``path``: ``.<name>.<8 hex>.tmp`` (hidden, never a final name)."""
    path = Path(path)
    return path.with_name(f".{path.name}.{secrets.token_hex(4)}{TEMP_SUFFIX}")


@contextmanager
def open_atomic(path: str | os.PathLike, mode: str = "w", *, encoding: str | None = "utf-8",
                newline: str | None = "\n", fsync: bool = False) -> Iterator[IO]:
    """Open a temporary file beside ``path`` for writing; rename it to ``path`` when the block ends.

    ``mode`` is ``"w"`` (text, ``encoding``, ``newline``) or ``"wb"``. On any exception, a
    ``KeyboardInterrupt`` included, the temporary file is removed and ``path`` is left as it was.
    ``fsync`` flushes the data to the disk before the rename (a cache that must survive a power
    loss); an interrupted process needs only the rename. The folder is created when missing, and
    the file gets the permissions ``open()`` would give it (the umask's).
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"open_atomic: mode must be 'w' or 'wb', got {mode!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(path)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        text = {} if mode == "wb" else {"encoding": encoding, "newline": newline}
        with os.fdopen(fd, mode, **text) as fh:
            yield fh
            if fsync:
                fh.flush()
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_atomic(path: str | os.PathLike, data: bytes | str, *, fsync: bool = False) -> Path:
    """Write ``data`` (bytes, or text as UTF-8 with ``\\n`` line ends) to ``path`` atomically; returns
    ``path``."""
    with open_atomic(path, "wb" if isinstance(data, bytes) else "w", fsync=fsync) as fh:
        fh.write(data)
    return Path(path)


def write_atomic_many(files: Mapping[str | os.PathLike, bytes | str]) -> list[Path]:
    """Write files that belong together: every temporary file first (the slow part), then the old
    targets are removed, then the new ones renamed in the order given. An interruption on the way
    leaves a prefix of the new files and none of the old, so put the file that says "complete"
    (the stats of a split, the summary) or that later runs look for last."""
    staged: list[tuple[Path, Path]] = []
    try:
        for target, data in files.items():
            target = Path(target)
            target.parent.mkdir(parents=True, exist_ok=True)
            tmp = temp_path(target)
            staged.append((tmp, target))
            with open(tmp, "wb" if isinstance(data, bytes) else "w",
                      **({} if isinstance(data, bytes) else {"encoding": "utf-8", "newline": "\n"})) as fh:
                fh.write(data)
        for _, target in staged:
            target.unlink(missing_ok=True)
        for tmp, target in staged:
            os.replace(tmp, target)
    except BaseException:
        for tmp, _ in staged:
            tmp.unlink(missing_ok=True)
        raise
    return [target for _, target in staged]


@contextmanager
def replace_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary folder beside ``path`` to fill; when the block ends it replaces ``path``.

    For folders a library writes file by file (``tokenizer.save_pretrained``): a later run that
    finds ``path`` finds all of it. On an exception the temporary folder is removed and ``path``
    is left as it was. An existing ``path`` is moved aside, the new one renamed in, then the old
    one deleted (a folder cannot be renamed over a non-empty one).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(path)
    tmp.mkdir()
    try:
        yield tmp
        old = temp_path(path) if path.exists() else None
        if old is not None:
            os.replace(path, old)
        os.replace(tmp, path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
