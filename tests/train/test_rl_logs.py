"""physcene.train.analysis.rl_logs: an RL run's logged keys averaged over windows of steps."""

import json

import pytest

from physcene.train.analysis import rl_logs


def _log(steps, **keys):
    """A trainer log history as physcene train pada writes it: a step entry per optimiser step (with the
    reward) and a summary entry at the end (no reward)."""
    history = [{"step": s, "reward": 0.0, **{k: v(s) for k, v in keys.items()}} for s in steps]
    return history + [{"step": steps[-1], "train_runtime": 12.0}]


def test_windows_average_each_key_over_the_steps_that_logged_it(tmp_path):
    run = tmp_path / "grpo"
    run.mkdir()
    history = _log(range(1, 26), kl=lambda s: s / 100, step_time=lambda s: 4.0 if s <= 20 else 100.0)
    history[3].pop("kl")  # step 4 logged no kl
    (run / "train_log.json").write_text(json.dumps(history))
    keys = ("kl", "step_time", "constraint/overruled_frac")
    rows = rl_logs.windows(rl_logs.log_history(run), 10, keys=keys)
    assert [(r["steps"], r["n"]) for r in rows] == [([1, 10], 10), ([11, 20], 10), ([21, 30], 5)]
    assert rows[0]["kl"] == pytest.approx(sum(s for s in range(1, 11) if s != 4) / 9 / 100)
    assert [r["step_time"] for r in rows] == [4.0, 4.0, 100.0]
    assert rows[0]["constraint/overruled_frac"] is None
    with pytest.raises(ValueError, match="window must be >= 1 step, got 0"):
        rl_logs.windows([], 0)


def test_the_cli_reads_a_checkpoint_folder_and_names_a_folder_without_a_log(tmp_path, capsys):
    ckpt = tmp_path / "checkpoint-3"
    ckpt.mkdir()
    (ckpt / "trainer_state.json").write_text(json.dumps({"log_history": _log([3, 1, 2], kl=lambda s: 0.1)}))
    out = tmp_path / "w.json"
    assert rl_logs.main([f"pada={ckpt}", "--window", "2", "--keys", "kl", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["runs"]["pada"]["steps"] == 3
    assert [w["steps"] for w in result["runs"]["pada"]["windows"]] == [[1, 2], [3, 4]]
    assert "pada 1-2: kl 0.1" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        rl_logs.main([f"x={tmp_path / 'none'}"])
    assert "neither train_log.json nor trainer_state.json" in capsys.readouterr().err


def test_a_console_log_extends_a_run_past_its_last_save(tmp_path, capsys):
    """A killed run: its folder's log ends at the resumed checkpoint (step 4, 2 steps an epoch); the steps
    after it are read from the console lines the trainer printed, placed by their epoch."""
    run = tmp_path / "pada"
    run.mkdir()
    (run / "train_log.json").write_text(json.dumps(
        [{"step": s, "epoch": s / 2, "reward": 1.0, "kl": 0.1} for s in range(1, 5)]))

    def line(epoch, kl):
        return (f"{{'loss': '0.2', 'kl': '{kl}', 'reward': '3.5', 'constraint/overruled_frac': '0.4', "
                f"'epoch': '{epoch}'}}")
    console = "\r 40%|####| 4/10 [00:01<00:02]\r" + line(2.0, 0.5) + "\n\r 50%|" + line(2.5, 0.7) + "\r 60%|"
    console += "\n" + line(3.0, 0.9) + "\nTraceback (most recent call last):\n"
    console += "{'loss': '0.3', 'kl"  # a line cut short by the kill
    (tmp_path / "pada.log").write_text(console)
    history = rl_logs.run_history(f"{run},{tmp_path / 'pada.log'}")
    assert [e["step"] for e in history] == [1, 2, 3, 4, 5, 6]  # the console's step 4 is the folder's
    assert [e["kl"] for e in history[4:]] == [0.7, 0.9]
    assert history[-1]["constraint/overruled_frac"] == 0.4
    out = tmp_path / "w.json"
    assert rl_logs.main([f"pada={run},{tmp_path / 'pada.log'}", "--window", "3", "--keys", "kl",
                         "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["runs"]["pada"]["windows"]
    assert [r["steps"] for r in rows] == [[1, 3], [4, 6]]
    assert rows[1]["kl"] == pytest.approx((0.1 + 0.7 + 0.9) / 3)
    empty = tmp_path / "nolog"
    empty.mkdir()
    (empty / "train_log.json").write_text(json.dumps([{"step": 1, "reward": 0.0}]))
    with pytest.raises(SystemExit):
        rl_logs.main([f"x={empty},{tmp_path / 'pada.log'}"])
    assert "no logged step with an epoch" in capsys.readouterr().err
    with pytest.raises(ValueError, match="steps_per_epoch must be > 0"):
        rl_logs.console_history(tmp_path / "pada.log", 0)
