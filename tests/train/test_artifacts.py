"""Artifacts kept in the repository's history: add -> commit -> pin -> commit -> restore, sha256-checked;
an RL run refuses to resume on a base whose digest differs from the one it recorded."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
from pathlib import Path

import pytest

from physcene.artifacts import (
    Artifact,
    ArtifactError,
    add_artifact,
    checkpoint_digest,
    is_restored,
    load_manifest,
    pin_artifact,
    resolve_generators,
    resolve_model,
    restore_artifact,
)
from physcene.cli import main
from physcene.train.models import RUN_INFO, TrainingSetupError, base_checked, read_run_info


def git(repo, *args):
    return subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True, text=True).stdout


@pytest.fixture
def repo(tmp_path):
    root = tmp_path / "repo"
    root.mkdir()
    git(root, "init", "-q")
    git(root, "config", "user.email", "test@example.org")
    git(root, "config", "user.name", "test")
    (root / ".gitignore").write_text("/artifacts/\n/runs/\n")
    (root / "README.md").write_text("repo\n")
    git(root, "add", "-A")
    git(root, "commit", "-qm", "start")
    sft = root / "runs" / "sft"
    (sft / "tokenizer").mkdir(parents=True)
    (sft / "model.safetensors").write_bytes(bytes(range(256)) * 40 + b"\r\n\x00")  # binary, CR LF kept
    (sft / "config.json").write_text('{"model_type": "qwen3"}\n')
    (sft / "tokenizer" / "tokenizer.json").write_text('{"vocab": {}}')
    return root


def committed_and_pinned(root, name="small-sft"):
    (root / "runs/sft/checkpoint-2").mkdir()
    (root / "runs/sft/checkpoint-2/optimizer.pt").write_bytes(b"left out")
    add_artifact(name, "runs/sft", made_by="physcene train sft --config tiny", data=["synth:train:16"],
                 exclude=["checkpoint-*"], cwd=root)
    staged = git(root, "diff", "--cached", "--name-only").split()
    assert staged == ["artifacts.json", "runs/sft/config.json", "runs/sft/model.safetensors",
                      "runs/sft/tokenizer/tokenizer.json"]  # not the excluded checkpoint
    git(root, "commit", "-qm", f"artifact {name}")
    pin_artifact(name, cwd=root)
    git(root, "commit", "-qam", f"artifact {name}: out of the tree")
    return load_manifest(root)[name]


def test_add_commit_pin_remove_restore_gives_the_same_bytes(repo):
    original = {p.relative_to(repo / "runs/sft").as_posix(): p.read_bytes()
                for p in (repo / "runs/sft").rglob("*") if p.is_file()}
    artifact = committed_and_pinned(repo)
    assert (repo / "runs/sft/model.safetensors").is_file()  # an ignored working copy stays
    assert artifact.commit == git(repo, "rev-parse", "HEAD~1").strip()
    assert {f["path"] for f in artifact.files} == set(original)
    assert git(repo, "ls-files", "runs") == ""  # out of the tree; the history holds it
    assert git(repo, "ls-tree", "-r", "--name-only", "HEAD~1", "runs/sft").split() == \
        sorted(f"runs/sft/{p}" for p in original)
    manifest = json.loads((repo / "artifacts.json").read_text())["artifacts"]["small-sft"]
    assert manifest["made_by"] == "physcene train sft --config tiny"
    assert manifest["data"] == ["synth:train:16"]
    subdir = repo / "docs"
    subdir.mkdir()
    folder = restore_artifact("small-sft", cwd=subdir)  # any directory inside the checkout
    assert folder == repo / "artifacts" / "small-sft"
    for path, data in original.items():
        assert (folder / path).read_bytes() == data
        assert hashlib.sha256((folder / path).read_bytes()).hexdigest() == \
            next(f["sha256"] for f in artifact.files if f["path"] == path)
    assert checkpoint_digest(folder) == checkpoint_digest(repo / "runs/sft")
    assert resolve_model("small-sft", cwd=repo) == str(folder)
    other = restore_artifact("small-sft", "elsewhere", cwd=repo)
    assert other == repo / "elsewhere" and (other / "config.json").is_file()


def test_the_cli_lists_and_restores(repo, monkeypatch, capsys):
    committed_and_pinned(repo)
    monkeypatch.chdir(repo)
    assert main(["artifacts", "list"]) == 0
    listed = capsys.readouterr().out
    assert "small-sft: 3 file(s)" in listed and "not restored" in listed
    assert main(["artifacts", "restore", "small-sft"]) == 0
    assert main(["artifacts", "list", "--json"]) == 0
    assert json.loads(capsys.readouterr().out.split("\n", 1)[1])["artifacts"]["small-sft"]["restored"] is True
    assert main(["artifacts", "restore", "no-such"]) == 2
    assert "no artifact 'no-such'" in capsys.readouterr().err


def test_a_corrupted_blob_is_refused(repo):
    add_artifact("sft", "runs/sft", made_by="x", cwd=repo)
    manifest = json.loads((repo / "artifacts.json").read_text())
    (repo / "runs/sft/config.json").write_text('{"model_type": "other"}\n')  # differs from its hash
    git(repo, "add", "-f", "runs/sft", "artifacts.json")
    git(repo, "commit", "-qm", "artifact")
    with pytest.raises(ArtifactError, match="config.json in commit .* has sha256"):
        pin_artifact("sft", cwd=repo)
    manifest["artifacts"]["sft"]["commit"] = git(repo, "rev-parse", "HEAD").strip()  # pinned regardless
    (repo / "artifacts.json").write_text(json.dumps(manifest))
    with pytest.raises(ArtifactError, match="refusing to restore"):
        restore_artifact("sft", cwd=repo)
    assert not (repo / "artifacts" / "sft" / "config.json").exists()


def test_clear_errors_outside_a_checkout_and_for_a_missing_commit(repo, tmp_path):
    outside = tmp_path / "plain"
    outside.mkdir()
    with pytest.raises(ArtifactError, match="not inside a git checkout"):
        restore_artifact("small-sft", cwd=outside)
    committed_and_pinned(repo)
    manifest = json.loads((repo / "artifacts.json").read_text())
    manifest["artifacts"]["small-sft"]["commit"] = "0" * 40
    (repo / "artifacts.json").write_text(json.dumps(manifest))
    with pytest.raises(ArtifactError, match="commit 0{40} is not in this repository; fetch"):
        restore_artifact("small-sft", cwd=repo)
    with pytest.raises(ArtifactError, match="restore it with `physcene artifacts restore small-sft`"):
        resolve_model("small-sft", cwd=repo)
    add_artifact("again", "README.md", made_by="x", cwd=repo)
    with pytest.raises(ArtifactError, match="not pinned yet"):
        restore_artifact("again", cwd=repo)


def test_a_shallow_clone_is_told_to_unshallow(repo, tmp_path):
    committed_and_pinned(repo)  # the files live in HEAD~1, which a depth-1 clone lacks
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", "--depth", "1", f"file://{repo}", str(clone)], check=True)
    with pytest.raises(ArtifactError, match=r"is not in this repository; this clone is shallow: run "
                                            r"`git fetch --unshallow`"):
        restore_artifact("small-sft", cwd=clone)


def test_a_resume_on_another_base_is_refused(repo, tmp_path):
    out = tmp_path / "pada"
    digest = base_checked(out, repo / "runs/sft", stage="pada")
    info = json.loads((out / RUN_INFO).read_text())
    assert info["base_sha256"] == digest and info["complete"] is False
    with pytest.raises(TrainingSetupError, match="has not finished"):  # no model saved yet: not loadable
        read_run_info(out)
    assert base_checked(out, repo / "runs/sft") == digest  # the same base resumes
    (repo / "runs/sft/model.safetensors").write_bytes(b"other weights")
    with pytest.raises(TrainingSetupError, match=f"trained from a base with sha256 {digest}"):
        base_checked(out, repo / "runs/sft")


def test_a_generator_names_an_artifact_and_an_adapter_finds_its_restored_base(repo):
    committed_and_pinned(repo)
    pada = repo / "runs" / "pada"
    pada.mkdir()
    (pada / "adapter_config.json").write_text(json.dumps({"base_model_name_or_path": "/gone/runs/sft"}))
    (pada / "adapter_model.safetensors").write_bytes(b"\x00lora\x01")
    (pada / "checkpoint-50").mkdir()  # a curve point: an adapter of its own, trained from the same base
    (pada / "checkpoint-50" / "adapter_config.json").write_text((pada / "adapter_config.json").read_text())
    add_artifact("small-pada", "runs/pada", made_by="physcene train pada --config tiny", base="small-sft",
                 cwd=repo)
    git(repo, "commit", "-qm", "artifact small-pada")
    pin_artifact("small-pada", cwd=repo)
    git(repo, "commit", "-qam", "out of the tree")
    spec = resolve_generators("reference,model:small-pada,model:runs", cwd=repo)
    folder = repo / "artifacts" / "small-pada"
    assert spec == f"reference,model:{folder},model:runs"  # a folder stays a folder
    config = json.loads((folder / "adapter_config.json").read_text())
    assert config["base_model_name_or_path"] == str(repo / "artifacts" / "small-sft")
    assert (repo / "artifacts" / "small-sft" / "model.safetensors").is_file()
    assert is_restored(folder, load_manifest(repo)["small-pada"])  # the rewrite is not a corruption
    # a plain restore (physcene artifacts restore) points every adapter, the checkpoints' too
    elsewhere = restore_artifact("small-pada", repo / "elsewhere", cwd=repo)
    for config_path in (elsewhere / "adapter_config.json", elsewhere / "checkpoint-50/adapter_config.json"):
        base = json.loads(config_path.read_text())["base_model_name_or_path"]
        assert base == str(repo / "artifacts/small-sft")
    assert is_restored(elsewhere, load_manifest(repo)["small-pada"])
    assert checkpoint_digest(elsewhere) == checkpoint_digest(pada)  # pointed at another base: one digest
    with pytest.raises(ArtifactError, match="--base 'nope' is not in"):
        add_artifact("x", "README.md", made_by="x", base="nope", cwd=repo)


def test_a_file_too_large_for_a_git_host_is_refused_before_anything_is_staged(repo, monkeypatch):
    import physcene.artifacts as artifacts

    monkeypatch.setattr(artifacts, "MAX_FILE_BYTES", 1024)  # the fixture's weights: 10,243 bytes
    with pytest.raises(ArtifactError, match=r"runs/sft/model.safetensors has 0.0 MiB, over the 0 MiB .*bf16"):
        add_artifact("small-sft", "runs/sft", made_by="x", cwd=repo)
    assert git(repo, "diff", "--cached", "--name-only") == "" and not (repo / "artifacts.json").exists()
    add_artifact("small-sft", "runs/sft", made_by="x", exclude=["model.safetensors"], cwd=repo)


def adapter(folder, base, r=8, weights=b"\x00lora\x01"):
    folder.mkdir(parents=True)
    config = {"base_model_name_or_path": base, "peft_type": "LORA", "r": r, "lora_alpha": 16,
              "target_modules": ["q_proj", "v_proj"]}
    (folder / "adapter_config.json").write_text(json.dumps(config))
    (folder / "adapter_model.safetensors").write_bytes(weights)
    return folder


def test_an_adapter_has_one_digest_wherever_its_base_lay(tmp_path):
    here = adapter(tmp_path / "host-a" / "pada", "/host-a/runs/sft")
    there = tmp_path / "host-b" / "pada"
    shutil.copytree(here, there)
    config = json.loads((there / "adapter_config.json").read_text())
    config["base_model_name_or_path"] = "/host-b/artifacts/small-sft"
    (there / "adapter_config.json").write_text(json.dumps(config, indent=2))  # as restore rewrites it
    assert checkpoint_digest(here) == checkpoint_digest(there)
    assert checkpoint_digest(adapter(tmp_path / "r16", "/host-a/runs/sft", r=16)) != checkpoint_digest(here)
    assert checkpoint_digest(adapter(tmp_path / "w", "/host-a/runs/sft", weights=b"other")) != \
        checkpoint_digest(here)


def test_a_checkpoint_without_an_adapter_keeps_its_bytes_digest(repo):
    sft = repo / "runs/sft"  # config.json and model.safetensors at the top; tokenizer/ is a folder
    lines = sorted(f"{hashlib.sha256((sft / n).read_bytes()).hexdigest()}  {n}\n"
                   for n in ("config.json", "model.safetensors"))
    assert checkpoint_digest(sft) == hashlib.sha256("".join(lines).encode()).hexdigest()


def pinned_run(repo):
    """An RL run kept as artifact pada-50: a final adapter and the checkpoint it resumes from."""
    run = adapter(repo / "runs/rl/pada", "/host-a/runs/sft")
    shutil.copytree(run, run / "checkpoint-50")
    (run / "checkpoint-50/optimizer.pt").write_bytes(b"adam state at 50" * 64)
    add_artifact("pada-50", "runs/rl/pada", made_by="physcene train pada", cwd=repo)
    git(repo, "commit", "-qm", "artifact pada-50")
    pin_artifact("pada-50", cwd=repo)
    git(repo, "commit", "-qam", "out of the tree")
    return load_manifest(repo)["pada-50"]


def continued_run(repo):
    """The same run continued to step 100 in another folder: pada-50's files and new ones."""
    run = repo / "runs/rl/pada-100"
    shutil.copytree(repo / "runs/rl/pada", run)
    shutil.copytree(run / "checkpoint-50", run / "checkpoint-100")
    (run / "checkpoint-100/adapter_model.safetensors").write_bytes(b"\x00lora at 100")
    (run / "checkpoint-100/optimizer.pt").write_bytes(b"adam state at 100" * 64)
    (run / "adapter_model.safetensors").write_bytes(b"\x00lora at 100")
    return {p.relative_to(run).as_posix(): p.read_bytes() for p in run.rglob("*") if p.is_file()}


def test_a_continued_run_refers_to_the_files_an_earlier_artifact_keeps(repo, monkeypatch, capsys):
    first = pinned_run(repo)
    original = continued_run(repo)
    monkeypatch.chdir(repo)
    assert main(["artifacts", "add", "pada-100", "runs/rl/pada-100", "--made-by", "physcene train pada"]) == 0
    added = capsys.readouterr().out
    assert "staged 3 file(s)" in added and "referenced 5 file(s)" in added and "kept by pada-50" in added
    new = [f"runs/rl/pada-100/{p}" for p in ("adapter_model.safetensors",
                                             "checkpoint-100/adapter_model.safetensors",
                                             "checkpoint-100/optimizer.pt")]
    assert git(repo, "diff", "--cached", "--name-only").split() == ["artifacts.json", *new]
    referenced = {f["path"]: f for f in load_manifest(repo)["pada-100"].referenced_files}
    shared = {"adapter_config.json", "checkpoint-50/adapter_config.json",
              "checkpoint-100/adapter_config.json", "checkpoint-50/adapter_model.safetensors",
              "checkpoint-50/optimizer.pt"}
    assert set(referenced) == shared
    for path, f in referenced.items():  # A's commit holds the same bytes at "at"
        assert f["commit"] == first.commit and f["at"].startswith("runs/rl/pada/")
        kept = subprocess.run(["git", "show", f"{f['commit']}:{f['at']}"], cwd=repo, check=True,
                              capture_output=True).stdout
        assert kept == original[path]
    assert referenced["checkpoint-100/adapter_config.json"]["at"] == "runs/rl/pada/adapter_config.json"
    git(repo, "commit", "-qm", "artifact pada-100")
    assert git(repo, "ls-tree", "-r", "--name-only", "HEAD", "runs").split() == new  # the new bytes only
    pin_artifact("pada-100", cwd=repo)
    assert git(repo, "diff", "--cached", "--name-only").split() == new  # only its own files leave the index
    git(repo, "commit", "-qam", "out of the tree")
    assert main(["artifacts", "list", "--json"]) == 0
    row = json.loads(capsys.readouterr().out)["artifacts"]["pada-100"]
    assert row["own_size"] == sum(len(original[p[len("runs/rl/pada-100/"):]]) for p in new)
    assert row["referenced_size"] == sum(len(original[p]) for p in shared)
    assert row["referenced_from"] == {"pada-50": row["referenced_size"]}
    assert main(["artifacts", "list"]) == 0
    assert "MiB referenced from pada-50, commit" in capsys.readouterr().out
    shutil.rmtree(repo / "runs/rl")  # no working copy left: every byte comes from the history
    folder = restore_artifact("pada-100", repo / "fresh", cwd=repo)
    assert {p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*")
            if p.is_file() and p.name != ".physcene-artifact.json"} == original
    assert is_restored(folder, load_manifest(repo)["pada-100"])


def test_a_wrong_reference_is_refused_by_pin_and_restore(repo):
    pinned_run(repo)
    continued_run(repo)
    add_artifact("pada-100", "runs/rl/pada-100", made_by="x", cwd=repo)
    git(repo, "commit", "-qm", "artifact pada-100")
    good = (repo / "artifacts.json").read_text()
    manifest = json.loads(good)
    entry = next(f for f in manifest["artifacts"]["pada-100"]["files"] if "commit" in f)
    entry["sha256"] = "0" * 64
    (repo / "artifacts.json").write_text(json.dumps(manifest))
    with pytest.raises(ArtifactError, match=f"{entry['path']} refers to {entry['at']} in commit .*, which "
                                            "has sha256"):
        pin_artifact("pada-100", cwd=repo)
    (repo / "artifacts.json").write_text(good)
    pin_artifact("pada-100", cwd=repo)
    manifest = json.loads((repo / "artifacts.json").read_text())
    next(f for f in manifest["artifacts"]["pada-100"]["files"] if "commit" in f)["sha256"] = "0" * 64
    (repo / "artifacts.json").write_text(json.dumps(manifest))
    with pytest.raises(ArtifactError, match="refusing to restore"):
        restore_artifact("pada-100", repo / "fresh", cwd=repo)
    assert not [p for p in (repo / "fresh").rglob("*") if p.is_file()]  # all or nothing


def test_no_reuse_stages_every_file(repo, monkeypatch):
    pinned_run(repo)
    original = continued_run(repo)
    monkeypatch.chdir(repo)
    assert main(["artifacts", "add", "pada-100", "runs/rl/pada-100", "--made-by", "x", "--no-reuse"]) == 0
    assert git(repo, "diff", "--cached", "--name-only").split() == \
        ["artifacts.json", *sorted(f"runs/rl/pada-100/{p}" for p in original)]
    assert not load_manifest(repo)["pada-100"].referenced_files


def test_the_manifest_round_trips_references_and_loads_entries_without_them(repo):
    plain = {"root": "runs/sft", "commit": "a" * 40, "files": [{"path": "x", "sha256": "0" * 64, "size": 1}]}
    referenced = {**plain, "files": [{"path": "x", "sha256": "0" * 64, "size": 1, "commit": "b" * 40,
                                      "at": "runs/old/x"}]}
    for entry in (plain, referenced):
        artifact = Artifact.from_dict("a", entry, "test")
        assert Artifact.from_dict("a", artifact.to_dict(), "test") == artifact
        assert artifact.to_dict()["files"] == entry["files"]
    with pytest.raises(ArtifactError, match="artifact 'a' is malformed"):
        Artifact.from_dict("a", {**plain, "files": [{**plain["files"][0], "commit": "b" * 40}]}, "test")
    project = load_manifest(Path(__file__).resolve().parents[2])  # the repository's own artifacts.json
    assert any(not a.referenced_files for a in project.values())  # entries from before reuse load
    kept = {(a.commit, f"{a.root}/{f['path']}"): f["sha256"] for a in project.values() for f in a.files
            if "commit" not in f}
    for a in project.values():  # every file referred to is one an artifact keeps, byte for byte
        assert all(kept.get((f["commit"], f["at"])) == f["sha256"] for f in a.referenced_files), a.name


def test_a_run_kept_without_its_final_adapter_generates_from_its_newest_checkpoint(repo):
    """An RL artifact keeps the checkpoint it resumes from whole and leaves out the final adapter (its
    bytes are that checkpoint's): ``model:NAME`` is that checkpoint, ``model:NAME/checkpoint-N`` a curve
    point it keeps, and a folder it does not keep is named."""
    committed_and_pinned(repo)
    run = repo / "runs" / "rl"
    for step in (50, 200, 297):
        (run / f"checkpoint-{step}").mkdir(parents=True)
        (run / f"checkpoint-{step}" / "adapter_config.json").write_text(
            json.dumps({"base_model_name_or_path": "/gone/runs/sft"}))
    (run / "checkpoint-400").mkdir()  # being written when the run stopped: no model in it
    (run / "checkpoint-400" / "trainer_state.json").write_text("{}")
    (run / "physcene_run.json").write_text("{}")
    add_artifact("med-pada", "runs/rl", made_by="physcene train pada", base="small-sft", cwd=repo)
    git(repo, "commit", "-qm", "artifact med-pada")
    pin_artifact("med-pada", cwd=repo)
    git(repo, "commit", "-qam", "out of the tree")
    folder = repo / "artifacts" / "med-pada"
    assert resolve_model("med-pada", cwd=repo) == str(folder / "checkpoint-297")
    assert resolve_model("med-pada/checkpoint-200", cwd=repo) == str(folder / "checkpoint-200")
    with pytest.raises(ArtifactError, match="has no folder 'checkpoint-9'.*checkpoint-200"):
        resolve_model("med-pada/checkpoint-9", cwd=repo)
    assert resolve_model("other/checkpoint-9", cwd=repo) == "other/checkpoint-9"  # not an artifact: a path
