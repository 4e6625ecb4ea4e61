"""The compiled reader of canonical CTRC completions (the reward's fast path): bytes -> world poses.

``scan`` holds the launchers and the data flow; the stages are ``prescan``, ``entries`` and
``walk``, the value readers ``values``, the constants and status codes ``codes``. The caller
gives the format's words (:func:`keyword_table`, in role order) and limits (:class:`ReaderLimits`).
"""

from physcene.kernels.ctrc_reader.codes import (
    CHUNK,
    ENTRY_ROLES,
    FNV_OFFSET,
    FNV_PRIME,
    MAX_ENTRIES,
    S_LONG,
    STATUS,
    TOP_ROLES,
    WORD_ROLES,
    ReaderLimits,
    category_hash,
    keyword_table,
)
from physcene.kernels.ctrc_reader.scan import launch_gather, launch_scan, scan_buffers

__all__ = [
    "CHUNK",
    "ENTRY_ROLES",
    "FNV_OFFSET",
    "FNV_PRIME",
    "MAX_ENTRIES",
    "STATUS",
    "S_LONG",
    "TOP_ROLES",
    "WORD_ROLES",
    "ReaderLimits",
    "category_hash",
    "keyword_table",
    "launch_gather",
    "launch_scan",
    "scan_buffers",
]
