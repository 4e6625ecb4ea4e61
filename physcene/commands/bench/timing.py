"""What every bench target shares: its registry entry and the timer (device synchronised, median)."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch

__all__ = ["BenchTarget", "Timing", "device_name", "timed"]


@dataclass(frozen=True)
class BenchTarget:
    """One ``physcene bench NAME`` target."""

    help: str
    add_arguments: Callable
    """add_arguments(parser): the target's own options."""
    run: Callable[..., dict]
    """run(args) -> a JSON-able dict of figures."""
    summary: Callable[[dict], str]
    """Human-readable lines of the figures."""
    repeat: tuple[int, int] = (20, 3)
    """Default ``--repeat`` on (CUDA, CPU)."""


@dataclass(frozen=True)
class Timing:
    """Medians of the timed calls of :func:`timed`."""

    seconds: float
    """Wall seconds."""
    cpu_seconds: float
    """Process CPU seconds: on a loaded CPU-only machine, the figure an idle machine would show for
    single-threaded work."""


def timed(fn: Callable[[], object], device: torch.device, repeat: int, warmup: int = 2) -> Timing:
    """Median wall and process CPU seconds of ``fn()`` with the device synchronised before and
    after each call."""

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    for _ in range(warmup):
        fn()
    sync()
    times, cpu = [], []
    for _ in range(max(1, repeat)):
        sync()
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        sync()
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return Timing(statistics.median(times), statistics.median(cpu))


def device_name(device: torch.device) -> str:
    """The device as the figures name it (the GPU's model, or the CPU's torch threads)."""
    if device.type == "cuda":
        return f"{device} ({torch.cuda.get_device_name(device)})"
    return f"cpu ({torch.get_num_threads()} torch threads)"
