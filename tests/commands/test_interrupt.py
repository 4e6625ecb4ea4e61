"""Ctrl-C in the middle of ``physcene data synth`` / ``physcene eval``: one line, exit 130, no half
or temporary file left, and the same command run again writes exactly what an uninterrupted run
writes (compared byte for byte over the whole output folder).

The interrupt goes to the whole process group, as a terminal's Ctrl-C does (pool workers get it
too). It is timed from the moment the command's first progress bar appears (imports done) at a
fraction of how long the uninterrupted run took from there; a run that finishes before the signal
is tried again with an earlier one.
"""

from __future__ import annotations

import filecmp
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}


class _Run:
    """``python -m physcene.cli ARGS`` in ``cwd``, its stderr read as it comes."""

    def __init__(self, args: list[str], cwd: Path):
        cwd.mkdir(parents=True, exist_ok=True)
        # SIGINT back to its default in the command: a suite started in the background of a
        # non-interactive shell (`pytest &`) inherits it ignored, and Python keeps an ignored SIGINT
        self.proc = subprocess.Popen([sys.executable, "-m", "physcene.cli", *args], cwd=cwd, env=ENV,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                     start_new_session=True,
                                     preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        self.stderr = ""
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        for chunk in iter(lambda: self.proc.stderr.read(1), ""):
            self.stderr += chunk

    def wait_for(self, marker: str, timeout: float = 240.0) -> float:
        """Seconds until ``marker`` shows on stderr (the command is past its imports)."""
        t0 = time.monotonic()
        while marker not in self.stderr:
            if self.proc.poll() is not None or time.monotonic() - t0 > timeout:
                raise AssertionError(f"{marker!r} never came; stderr:\n{self.stderr[-2000:]}")
            time.sleep(0.02)
        return time.monotonic()

    def finish(self, timeout: float = 300.0) -> int:
        rc = self.proc.wait(timeout=timeout)
        self.reader.join(timeout=10)
        return rc


def _files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


def _same_tree(a: Path, b: Path) -> None:
    assert _files(a) == _files(b)
    _, mismatch, errors = filecmp.cmpfiles(a, b, _files(a), shallow=False)
    assert not mismatch and not errors, f"differ: {mismatch + errors}"


def _interrupt_then_rerun(tmp_path: Path, args: list[str], marker: str) -> None:
    reference = _Run(args, tmp_path / "reference")
    started = reference.wait_for(marker)
    assert reference.finish() == 0, reference.stderr[-2000:]
    work = time.monotonic() - started
    for fraction in (0.5, 0.25, 0.1, 0.03):
        run = _Run(args, tmp_path / "interrupted")
        time.sleep(max(0.0, run.wait_for(marker) + fraction * work - time.monotonic()))
        if run.proc.poll() is None:
            os.killpg(run.proc.pid, signal.SIGINT)
        rc = run.finish()
        if rc != 0:
            break
        _clear(tmp_path / "interrupted")  # finished before the signal: try an earlier one
    else:
        pytest.fail(f"the run always finished before the interrupt ({work:.1f} s of work)")
    assert rc == 130, run.stderr[-2000:]
    assert "Traceback" not in run.stderr, run.stderr[-4000:]
    assert run.stderr.strip().splitlines()[-1] == "physcene: interrupted"
    out = tmp_path / "interrupted"
    assert not [f for f in _files(out) if f.endswith(".tmp")]
    # what an interrupted run leaves is whole: each file as the uninterrupted run wrote it
    left = _files(out)
    _, mismatch, errors = filecmp.cmpfiles(out, tmp_path / "reference", left, shallow=False)
    assert not mismatch and not errors, f"half or stale files after the interrupt: {mismatch + errors}"
    again = _Run(args, out)
    assert again.finish() == 0, again.stderr[-2000:]
    _same_tree(out, tmp_path / "reference")


def _clear(folder: Path) -> None:
    for p in sorted(folder.rglob("*"), reverse=True):
        p.unlink() if p.is_file() else p.rmdir()


def test_interrupted_synth_then_rerun_writes_the_same_files(tmp_path):
    # 60 scenes in 2 worker processes (a few seconds); the engine's measurement is left out (it only
    # adds Warp's start-up before the same three writes)
    _interrupt_then_rerun(tmp_path, ["data", "synth", "--out", "out", "--split", "test", "--n", "60",
                                     "--workers", "2", "--measure", "no"], marker="synth test")


def test_interrupted_eval_then_rerun_writes_the_same_files(tmp_path):
    # relative out=: report.md quotes the command, which must read the same in both folders
    _interrupt_then_rerun(tmp_path, ["eval", "n=6", "render=1", "out=out"], marker="synthesise test")
