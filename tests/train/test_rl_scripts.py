"""The RL study's shell scripts without a GPU: ``rl_ablation.sh`` in ``DRY=1`` mode (the commands it
would run, printed) for the runs RUNS names and the per-seed evaluation they imply, and
``rl_remote.sh pack`` on a fake run tree of small real checkpoint files."""

from __future__ import annotations

import io
import json
import os
import shlex
import subprocess
import tarfile
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from physcene.train.checkpoints import last_complete_checkpoint

SCRIPTS = Path(__file__).resolve().parents[2] / "train" / "scripts"


def _rl_ablation(tmp_path, **env: str) -> subprocess.CompletedProcess:
    """``rl_ablation.sh`` with DRY=1 and only ``env`` set (GPUS given: no torch to ask)."""
    base = {"PATH": os.environ["PATH"], "HOME": str(tmp_path), "DRY": "1", "GPUS": "2"}
    return subprocess.run(["bash", str(SCRIPTS / "rl_ablation.sh")], cwd=tmp_path, env={**base, **env},
                          capture_output=True, text=True, timeout=30)


def _commands(stdout: str) -> list[dict[str, str]]:
    """The printed ablation_small.sh commands: each one's NAME=value words, its log under ``>``."""
    found = []
    for line in stdout.splitlines():
        if not line.startswith("env "):
            continue
        words = shlex.split(line)
        assert words[0] == "env" and "train/scripts/ablation_small.sh" in words
        end = words.index("bash")
        command = dict(w.split("=", 1) for w in words[1:end])
        command["log"] = words[words.index(">") + 1] if ">" in words else ""
        found.append(command)
    return found


def _variants(command: dict[str, str]) -> list[str]:
    (listed,) = [w for w in command["EXTRA"].split() if w.startswith("ablation.variants=")]
    return listed.removeprefix("ablation.variants=[").removesuffix("]").split(",")


def test_runs_named_one_by_one_train_and_evaluate_only_those(tmp_path):
    done = _rl_ablation(tmp_path, RUNS="0:pada_star 1:pada 1:grpo", STAGES="rl eval", SEEDS="0 1 2")
    assert done.returncode == 0, done.stderr
    commands = _commands(done.stdout)
    rl = [c for c in commands if c["STAGES"] != "eval"]
    # slot k (GPU k % GPUS) takes runs k, k + GPUS, ...: 0:pada_star and 1:grpo on GPU 0, 1:pada on GPU 1
    assert [(c["RUN"], c["STAGES"], c["CUDA_VISIBLE_DEVICES"], c["log"]) for c in rl] == [
        ("runs/rl/s0", "pada_star", "0", "runs/rl/s0/pada_star.log"),
        ("runs/rl/s1", "grpo", "0", "runs/rl/s1/grpo.log"),
        ("runs/rl/s1", "pada", "1", "runs/rl/s1/pada.log")]
    assert [c["EXTRA"].split()[-1] for c in rl] == ["seed=0", "seed=1", "seed=1"]
    evals = [c for c in commands if c["STAGES"] == "eval"]
    assert [(c["RUN"], _variants(c)) for c in evals] == [("runs/rl/s0", ["pada_star"]),
                                                        ("runs/rl/s1", ["pada", "grpo"])]
    assert not list(tmp_path.iterdir())  # DRY=1 writes nothing


def test_without_runs_every_seed_has_every_variant(tmp_path):
    done = _rl_ablation(tmp_path, SEEDS="3 5", VARIANTS="pada grpo", STAGES="rl eval")
    assert done.returncode == 0, done.stderr
    commands = _commands(done.stdout)
    assert sorted((c["RUN"], c["STAGES"]) for c in commands if c["STAGES"] != "eval") == [
        ("runs/rl/s3", "grpo"), ("runs/rl/s3", "pada"), ("runs/rl/s5", "grpo"), ("runs/rl/s5", "pada")]
    assert [(c["RUN"], _variants(c)) for c in commands if c["STAGES"] == "eval"] == [
        ("runs/rl/s3", ["pada", "grpo"]), ("runs/rl/s5", ["pada", "grpo"])]


def test_a_seed_without_a_run_is_not_evaluated(tmp_path):
    done = _rl_ablation(tmp_path, RUNS="1:grpo", SEEDS="0 1", STAGES="eval")
    assert done.returncode == 0, done.stderr
    assert [(c["RUN"], _variants(c), c["CUDA_VISIBLE_DEVICES"]) for c in _commands(done.stdout)] == [
        ("runs/rl/s1", ["grpo"], "0")]


def test_decode_only_decodes_each_seeds_rows_per_gpu_at_once_into_the_table_folder(tmp_path):
    done = _rl_ablation(tmp_path, RUNS="0:pada 0:pada_star 1:pada", STAGES="decode", GPUS="1", PER_GPU="2")
    assert done.returncode == 0, done.stderr
    commands = _commands(done.stdout)
    assert [(c["RUN"], _variants(c), c["CUDA_VISIBLE_DEVICES"], c["log"]) for c in commands] == [
        ("runs/rl/s0", ["pada", "pada_star"], "0", "runs/rl/s0/decode.log"),
        ("runs/rl/s1", ["pada"], "0", "runs/rl/s1/decode.log")]
    for c in commands:  # the eval stage's command with decode_only: its layouts are the ones eval re-scores
        assert c["STAGES"] == "eval"
        assert c["EXTRA"].split()[-1] == "ablation.decode_only=true"
        assert f"ablation.layouts={c['RUN']}/layouts" in c["EXTRA"].split()
    # tables made at once on one host rendezvous on ports of their own, apart from the runs' ports
    ports = [int(c["PORT"]) for c in commands]
    assert len(set(ports)) == 2 and min(ports) >= 29600 + 10 * 3
    evals = _rl_ablation(tmp_path, RUNS="0:pada 0:pada_star 1:pada", STAGES="eval", GPUS="1")
    evals = _commands(evals.stdout)
    assert [c["EXTRA"].split()[:-1] for c in commands] == [c["EXTRA"].split() for c in evals]


def test_runs_stop_off_grammar_and_tables_take_the_checkpoints_named(tmp_path):
    """Every run and table carries pada.stop_overruled (STOP_OVERRULED, 0.2 unless set), and the tables
    take the kept checkpoints CHECKPOINTS names (all of them unless set)."""
    def words(**env):
        done = _rl_ablation(tmp_path, RUNS="0:pada 0:grpo", STAGES="rl decode", **env)
        assert done.returncode == 0, done.stderr
        return [c["EXTRA"].split() for c in _commands(done.stdout)]

    default = words()
    assert len(default) == 3 and all("pada.stop_overruled=0.2" in w for w in default)
    assert "ablation.checkpoints=true" in default[-1]
    chosen = words(STOP_OVERRULED="null", CHECKPOINTS="[100,200]")
    assert all("pada.stop_overruled=null" in w for w in chosen)
    assert "ablation.checkpoints=[100,200]" in chosen[-1]


def test_a_study_from_a_first_gpu_keeps_every_stage_on_its_own_gpus(tmp_path):
    done = _rl_ablation(tmp_path, RUNS="0:pada 1:grpo 2:pada", STAGES="anchors rl decode", FIRST_GPU="1",
                        GPUS="2")
    assert done.returncode == 0, done.stderr
    commands = _commands(done.stdout)
    anchors = [c for c in commands if c["STAGES"] == "anchors"]
    assert [(c["CUDA_VISIBLE_DEVICES"], c["NPROC"]) for c in anchors] == [("1,2", "2"), ("1,2", "2")]
    rl = [c for c in commands if c["STAGES"] in ("pada", "grpo")]
    assert [(c["RUN"], c["CUDA_VISIBLE_DEVICES"]) for c in rl] == [
        ("runs/rl/s0", "1"), ("runs/rl/s2", "1"), ("runs/rl/s1", "2")]
    decode = [c for c in commands if c["STAGES"] == "eval"]
    assert [(c["RUN"], c["CUDA_VISIBLE_DEVICES"]) for c in decode] == [
        ("runs/rl/s0", "1"), ("runs/rl/s1", "2"), ("runs/rl/s2", "1")]


@pytest.mark.parametrize("word", ["0-pada", "pada", "x:pada", "-1:pada", "0:pdaa", "0:", ":grpo",
                                  "0:pada:grpo"])
def test_a_malformed_run_is_one_error_line_before_anything_runs(tmp_path, word):
    done = _rl_ablation(tmp_path, RUNS=f"1:grpo {word} 0:pada")
    assert done.returncode == 2
    assert done.stdout == ""  # no stage started
    (line,) = done.stderr.splitlines()
    assert f"'{word}'" in line and "RUNS" in line


def test_a_run_named_twice_is_refused(tmp_path):
    done = _rl_ablation(tmp_path, RUNS="0:pada 1:pada 0:pada")
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.strip() == "rl_ablation.sh: RUNS: '0:pada' is named twice"


def _checkpoint(folder: Path, step: int, *, state: bool = True) -> None:
    """A checkpoint as the Trainer writes it (a LoRA adapter, optimizer, scheduler, RNG, its state
    last); ``state=False``: one still being written."""
    folder.mkdir(parents=True)
    save_file({"lora_A": torch.full((2, 3), float(step))}, folder / "adapter_model.safetensors")
    (folder / "adapter_config.json").write_text("{}")
    torch.save({"state": {}, "param_groups": []}, folder / "optimizer.pt")
    torch.save({"last_epoch": step}, folder / "scheduler.pt")
    torch.save({"python": step}, folder / "rng_state.pth")
    if state:
        (folder / "trainer_state.json").write_text(json.dumps({"global_step": step, "log_history": []}))


def test_pack_carries_the_newest_complete_checkpoint_whole_and_leaves_incomplete_ones(tmp_path):
    """``rl_remote.sh pack``: every run's newest complete checkpoint whole (the next host resumes from
    it), its older complete ones without optimizer, scheduler and RNG state, a checkpoint being written
    or cut short not at all, the run's other files beside them; unpacked elsewhere, the run resumes
    from the same checkpoint."""
    work = tmp_path / "work"
    rl = work / "runs" / "rl"
    pada, grpo = rl / "s0" / "pada", rl / "s0" / "grpo"
    for step in (4, 10):
        _checkpoint(pada / f"checkpoint-{step}", step)
    _checkpoint(pada / "checkpoint-12", 12, state=False)  # being written: no trainer_state.json yet
    _checkpoint(grpo / "checkpoint-2", 2)
    _checkpoint(grpo / "checkpoint-6", 6)
    cut = grpo / "checkpoint-6" / "adapter_model.safetensors"
    cut.write_bytes(cut.read_bytes()[:-4])
    (rl / "anchors.jsonl.gz").write_bytes(b"anchors")
    (rl / "s0" / "pada.log").write_text("step 10\n")
    (pada / "physcene_run.json").write_text("{}")
    (rl / "s0" / "eval.lock").write_text("")

    dest = tmp_path / "dest"
    env = {**os.environ, "WORK": str(work), "PACK": str(tmp_path / "pack"), "RUN": "runs/rl"}
    done = subprocess.run(["bash", str(SCRIPTS / "rl_remote.sh"), "pack", str(dest)], env=env,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    parts = sorted(dest.glob("rl_state.tar.xz.*"))
    assert parts and "send: 1 of 1 part(s)" in done.stdout
    home = tmp_path / "home"
    with tarfile.open(fileobj=io.BytesIO(b"".join(p.read_bytes() for p in parts)), mode="r:xz") as tar:
        tar.extractall(home, filter="data")
    packed = sorted(str(p.relative_to(home)) for p in home.rglob("*") if p.is_file())

    def files(run: str, step: int, *names: str) -> list[str]:
        return [f"runs/rl/s0/{run}/checkpoint-{step}/{n}" for n in names]

    whole = ("adapter_config.json", "adapter_model.safetensors", "optimizer.pt", "rng_state.pth",
             "scheduler.pt", "trainer_state.json")
    curve = ("adapter_config.json", "adapter_model.safetensors", "trainer_state.json")
    assert packed == sorted([
        "runs/rl/anchors.jsonl.gz", "runs/rl/s0/pada.log", "runs/rl/s0/pada/physcene_run.json",
        *files("pada", 10, *whole), *files("pada", 4, *curve), *files("grpo", 2, *whole)])
    for name in files("pada", 10, *whole):
        assert (home / name).read_bytes() == (work / name).read_bytes()
    assert last_complete_checkpoint(home / "runs/rl/s0/pada") == str(home / "runs/rl/s0/pada/checkpoint-10")


def test_remote_runs_the_script_it_is_given_detached_and_poll_sees_it_end(tmp_path):
    """``rl_remote.sh again`` with SCRIPT: that script runs detached in WORK with the caller's
    environment, DONE holds its exit status, and ``poll`` returns once it ended (an SFT base runs
    under the same start/poll as the RL study)."""
    work = tmp_path / "work"
    (work / "train").mkdir(parents=True)
    (work / "train" / "sft_stub.sh").write_text('echo "stub ran: CONFIG=$CONFIG"; exit 3\n')
    env = {"PATH": os.environ["PATH"], "HOME": str(tmp_path), "WORK": str(work),
           "SCRIPT": "train/sft_stub.sh", "RUN": "runs/medium", "CONFIG": "medium"}
    started = subprocess.run(["bash", str(SCRIPTS / "rl_remote.sh"), "again"], env=env, capture_output=True,
                             text=True, timeout=30)
    assert started.returncode == 0, started.stderr
    polled = subprocess.run(["bash", str(SCRIPTS / "rl_remote.sh"), "poll", "20"], env=env,
                            capture_output=True, text=True, timeout=60)
    assert (work / "DONE").read_text().strip() == "3"
    assert "stub ran: CONFIG=medium" in (work / "rl.log").read_text()
    assert "train/sft_stub.sh ended with status 3" in polled.stdout


def test_poll_on_a_host_where_nothing_was_started_stops_at_once(tmp_path):
    """A fresh host (the last one given back with its run) has no PID: ``poll`` says so and exits 3 at
    once instead of waiting its whole time on nothing."""
    env = {"PATH": os.environ["PATH"], "HOME": str(tmp_path), "WORK": str(tmp_path / "work")}
    polled = subprocess.run(["bash", str(SCRIPTS / "rl_remote.sh"), "poll", "60"], env=env,
                            capture_output=True, text=True, timeout=20)
    assert polled.returncode == 3
    assert "nothing was started" in polled.stderr


def test_poll_stops_when_the_run_is_gone_without_an_exit_status(tmp_path):
    """A run killed from outside writes no DONE: ``poll`` reports it gone instead of waiting it out."""
    work = tmp_path / "work"
    work.mkdir()
    gone = subprocess.Popen(["true"])
    gone.wait()
    (work / "PID").write_text(f"{gone.pid}\n")
    env = {"PATH": os.environ["PATH"], "HOME": str(tmp_path), "WORK": str(work), "SCRIPT": "train/x.sh"}
    polled = subprocess.run(["bash", str(SCRIPTS / "rl_remote.sh"), "poll", "60"], env=env,
                            capture_output=True, text=True, timeout=20)
    assert "train/x.sh (pid" in polled.stderr and "is gone without an exit status" in polled.stderr


def test_a_pada_run_that_fails_on_its_fast_cache_retries_with_a_config_the_dynamic_cache_accepts(tmp_path):
    """A run whose fast cache fails (an out-of-memory step) goes again on the dynamic cache; merged
    adapters, which an EXTRA may ask for, exist for the fast decoder only, so the retry overrules them
    instead of stopping on a configuration error."""
    from physcene.config import load_config
    from physcene.train.pada import pada_arguments

    calls = tmp_path / "calls.txt"
    launcher = tmp_path / "launch"  # records its arguments; fails unless it is given the dynamic cache
    launcher.write_text(f'#!/bin/bash\necho "$*" >> {calls}\n[[ " $* " == *" pada.cache=dynamic "* ]]\n')
    launcher.chmod(0o755)
    env = {"PATH": os.environ["PATH"], "HOME": str(tmp_path), "NPROC": "1", "LAUNCH": str(launcher),
           "STAGES": "pada", "CONFIG": "tiny", "PADA_CACHE": "fast+fused+cudnn",
           "EXTRA": "pada.merge_adapters=true pada.temperature=0.7"}
    done = subprocess.run(["bash", str(SCRIPTS / "ablation_small.sh")], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert "again with the dynamic cache" in done.stdout
    first, retry = calls.read_text().splitlines()
    assert "pada.cache=fast+fused+cudnn" in first.split()
    overrides = [w for w in retry.split() if "=" in w and not w.startswith("--")]
    cfg = load_config("train_tiny", [f"output_dir={tmp_path}", *overrides])
    args = pada_arguments(cfg, "pada")  # raised "pada.merge_adapters merges ..." before the fix
    assert not args.merge_adapters and cfg.pada.cache == "dynamic" and cfg.pada.temperature == 0.7
