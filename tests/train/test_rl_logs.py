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
