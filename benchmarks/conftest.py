"""Shared pieces of the pytest-benchmark suites: devices to run on and synchronised timing.

Run with ``python -m pytest benchmarks/ --benchmark-enable`` (pyproject disables benchmarks by
default, so a plain run only checks that each case works once).
"""

from __future__ import annotations

import pytest
import torch

# CPU always; the first CUDA device when there is one.
BENCH_DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=BENCH_DEVICES)
def bench_device(request) -> torch.device:
    return torch.device(request.param)


def synchronized(fn, device: torch.device):
    """``fn`` followed by a device synchronisation, so a benchmark round times the GPU work too."""

    def call():
        result = fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        return result

    return call
