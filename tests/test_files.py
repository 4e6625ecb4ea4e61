"""physcene.files: a file appears whole or not at all, and an interrupted writer leaves no litter."""

import os
import stat

import pytest

from physcene.files import open_atomic, replace_dir, write_atomic, write_atomic_many


def _listing(folder):
    return sorted(p.name for p in folder.iterdir())


@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])
def test_failed_open_atomic_leaves_neither_target_nor_temp(tmp_path, error):
    target = tmp_path / "out.jsonl"
    with pytest.raises(error):
        with open_atomic(target) as fh:
            fh.write('{"a": 1}\n')
            raise error("stop")
    assert _listing(tmp_path) == []


def test_failed_open_atomic_keeps_the_previous_file(tmp_path):
    target = tmp_path / "out.json"
    target.write_text("old\n")
    with pytest.raises(KeyboardInterrupt):
        with open_atomic(target) as fh:
            fh.write("new, but only half")
            raise KeyboardInterrupt
    assert _listing(tmp_path) == ["out.json"]
    assert target.read_text() == "old\n"


def test_open_atomic_renames_when_complete(tmp_path):
    target = tmp_path / "sub" / "out.jsonl"
    with open_atomic(target) as fh:
        fh.write("one\n")
        assert not target.exists()  # nothing under the final name until the block ends
        assert [p.name.endswith(".tmp") for p in target.parent.iterdir()] == [True]
    assert target.read_bytes() == b"one\n"
    assert _listing(target.parent) == ["out.jsonl"]


def test_write_atomic_bytes_text_and_permissions(tmp_path):
    write_atomic(tmp_path / "a.bin", b"\x00\x01")
    write_atomic(tmp_path / "b.txt", "x\ny\n")
    assert (tmp_path / "a.bin").read_bytes() == b"\x00\x01"
    assert (tmp_path / "b.txt").read_bytes() == b"x\ny\n"
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE((tmp_path / "b.txt").stat().st_mode) == 0o666 & ~umask  # as open() would give


def test_open_atomic_rejects_other_modes(tmp_path):
    with pytest.raises(ValueError, match="mode"):
        with open_atomic(tmp_path / "x", "a"):
            pass


def test_write_atomic_many_removes_old_files_of_the_group(tmp_path, monkeypatch):
    (tmp_path / "train.jsonl").write_text("old\n")
    (tmp_path / "train_stats.json").write_text("old stats\n")
    renamed = []
    real_replace = os.replace

    def interrupted_replace(src, dst):  # Ctrl-C after the first of the two renames
        if renamed:
            raise KeyboardInterrupt
        renamed.append(dst)
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", interrupted_replace)
    with pytest.raises(KeyboardInterrupt):
        write_atomic_many({tmp_path / "train.jsonl": "new\n", tmp_path / "train_stats.json": "new stats\n"})
    # the new records, no stale stats beside them (a rerun writes them), no temp files
    assert _listing(tmp_path) == ["train.jsonl"]
    assert (tmp_path / "train.jsonl").read_text() == "new\n"
    monkeypatch.setattr(os, "replace", real_replace)
    write_atomic_many({tmp_path / "train.jsonl": "new\n", tmp_path / "train_stats.json": b"new stats\n"})
    assert _listing(tmp_path) == ["train.jsonl", "train_stats.json"]


def test_replace_dir(tmp_path):
    target = tmp_path / "tokenizer"
    with replace_dir(target) as tmp:
        (tmp / "tokenizer.json").write_text("{}")
    assert _listing(tmp_path) == ["tokenizer"] and _listing(target) == ["tokenizer.json"]
    with pytest.raises(KeyboardInterrupt):
        with replace_dir(target) as tmp:
            (tmp / "half.json").write_text("{")
            raise KeyboardInterrupt
    assert _listing(tmp_path) == ["tokenizer"] and _listing(target) == ["tokenizer.json"]
    with replace_dir(target) as tmp:
        (tmp / "vocab.json").write_text("{}")
    assert _listing(tmp_path) == ["tokenizer"] and _listing(target) == ["vocab.json"]
