"""Checkpoints kept in the repository's history, not its working tree: the artifact manifest.

A checkpoint that a later run needs (an SFT base with its tokenizer, anchors, an RL adapter with its
optimiser state) is committed in one commit and removed from the tree in the next, so the tree stays
small and the bytes stay reachable. ``artifacts.json`` at the repository root lists each one::

    {"artifacts": {"small-sft": {"commit": "<sha of the commit holding the files>", "root": "runs/small/sft",
                                 "files": [{"path": "model.safetensors", "sha256": "...", "size": 54525952}],
                                 "digest": "...", "made_by": "physcene train sft --config small",
                                 "data": ["data/train.jsonl"], "base": null},
                   "rl-s0-pada-300": {"commit": "...", "root": "runs/rl/s0/pada", "files": [
                                 {"path": "checkpoint-50/adapter_model.safetensors", "sha256": "...",
                                  "size": 8391352, "commit": "<sha of rl-s0-pada's commit>",
                                  "at": "runs/rl/s0/pada/checkpoint-50/adapter_model.safetensors"},
                                 ...], ...}}}

``add`` hashes the files, writes the entry (``commit`` null) and stages both; after the commit that
holds them, ``pin`` records that commit, checks every file in it against its hash and takes the files
out of the index (the next commit removes them from the tree). ``restore`` reads each file back from
the commit with ``git cat-file --batch`` (binary-safe), checks its sha256 and writes it atomically
under ``artifacts/NAME`` (ignored). Paths in the manifest are relative to the repository root (``root``,
``at``) and to the artifact's root (``path``). docs/training.md, "Artifacts", gives the workflow.

Reuse: a file whose sha256 equals a file of an artifact already pinned (a continued RL run's early
checkpoints) is not staged again; its entry names where that artifact keeps it, ``commit`` and ``at``
(its path in that commit), and ``pin`` and ``restore`` check and read it there. Bytes committed in one
commit and removed in the next count twice against what one push may carry, so the history keeps each
file's bytes once. Files without ``commit`` live in the artifact's own commit; ``digest`` covers all
files, kept or referred to.
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import os
import re
import subprocess
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from physcene.files import temp_path, write_atomic

__all__ = ["MANIFEST", "MAX_FILE_BYTES", "RESTORED", "Artifact", "ArtifactError", "add_artifact",
           "checkpoint_digest", "file_sha256", "is_restored", "load_manifest", "pin_artifact",
           "referenced_from", "repo_root", "resolve_generators", "resolve_model", "restore_artifact",
           "restored_dir"]

MANIFEST = "artifacts.json"
# Where ``restore`` writes an artifact by default (ignored by .gitignore), and the marker it leaves there.
RESTORED = "artifacts"
_MARKER = ".physcene-artifact.json"
# The files of a checkpoint directory that define the model a run starts from (weights, config,
# tokenizer): what :func:`checkpoint_digest` hashes. Logs, run info and checkpoint-N folders are not.
_MODEL_FILES = ("config.json", "generation_config.json", "tokenizer.json", "tokenizer_config.json",
                "special_tokens_map.json", "vocab.json", "merges.txt", "added_tokens.json",
                "chat_template.jinja", "chat_template.json", "adapter_config.json")
_WEIGHT_SUFFIXES = (".safetensors", ".bin")
# A file git hosts refuse (GitHub: 100 MiB); a checkpoint that large wants bf16 weights or fewer files.
MAX_FILE_BYTES = 100 * 2**20


class ArtifactError(ValueError):
    """An artifact cannot be added, pinned or restored: the message names it and what to do."""


@dataclass(frozen=True)
class Artifact:
    """One manifest entry (see the module docstring)."""

    name: str
    root: str
    """The artifact's folder, relative to the repository root, where it was added and committed."""
    files: tuple[dict, ...]
    """``{"path", "sha256", "size"}`` per file, ``path`` relative to ``root``, sorted by path; a file
    that an earlier artifact keeps adds ``{"commit", "at"}``: where it is read from."""
    made_by: str
    """The command that made it."""
    data: tuple[str, ...] = ()
    """The data it was made from (files, ``synth:SPLIT:N`` specs)."""
    base: str | None = None
    """The artifact it was trained from, by name."""
    commit: str | None = None
    """The commit that holds the files (null until ``pin``)."""
    digest: str = ""
    """sha256 over the sorted ``sha256  path`` lines: one hash for the whole artifact."""

    @property
    def own_files(self) -> tuple[dict, ...]:
        """The files kept in this artifact's own commit."""
        return tuple(f for f in self.files if "commit" not in f)

    @property
    def referenced_files(self) -> tuple[dict, ...]:
        """The files read from an earlier artifact's commit."""
        return tuple(f for f in self.files if "commit" in f)

    def to_dict(self) -> dict:
        return {"root": self.root, "commit": self.commit, "digest": self.digest, "made_by": self.made_by,
                "data": list(self.data), "base": self.base, "files": [dict(f) for f in self.files]}

    @classmethod
    def from_dict(cls, name: str, entry: dict, source: str) -> Artifact:
        try:
            files = tuple(_file_entry(f) for f in entry["files"])
            return cls(name=name, root=str(entry["root"]), files=files, made_by=str(entry.get("made_by", "")),
                       data=tuple(str(d) for d in entry.get("data") or ()), base=entry.get("base"),
                       commit=entry.get("commit"), digest=str(entry.get("digest", "")))
        except (KeyError, TypeError, ValueError) as exc:
            raise ArtifactError(f"{source}: artifact {name!r} is malformed ({exc!r})") from None


def _file_entry(f: dict) -> dict:
    entry = {"path": str(f["path"]), "sha256": str(f["sha256"]), "size": int(f["size"])}
    if "commit" in f or "at" in f:  # both or neither: a reference names a commit and a path in it
        entry.update(commit=str(f["commit"]), at=str(f["at"]))
    return entry


def _git(root: Path | None, *args: str, stdin: bytes | None = None, check: bool = True) -> bytes:
    """``git args`` in ``root``; its stdout. A failure is an ArtifactError quoting git's message."""
    try:
        done = subprocess.run(["git", *args], cwd=root, input=stdin, capture_output=True)
    except FileNotFoundError:
        raise ArtifactError("git is not installed: artifacts live in the repository's history") from None
    if check and done.returncode != 0:
        raise ArtifactError(f"git {' '.join(args)}: {done.stderr.decode(errors='replace').strip()}")
    return done.stdout


def repo_root(cwd: str | Path | None = None) -> Path:
    """The top of the git checkout holding ``cwd`` (default: the current directory)."""
    done = subprocess.run(["git", "rev-parse", "--show-toplevel"], cwd=cwd or ".", capture_output=True)
    if done.returncode != 0:
        where = Path(cwd or ".").resolve()
        raise ArtifactError(f"{where} is not inside a git checkout: artifacts are read from the "
                            "repository's history (clone the repository, not a copy of its files)")
    return Path(done.stdout.decode().strip())


def file_sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _digest(files: Iterable[dict]) -> str:
    lines = sorted(f"{f['sha256']}  {f['path']}\n" for f in files)
    return hashlib.sha256("".join(lines).encode()).hexdigest()


def checkpoint_digest(model_dir: str | Path) -> str:
    """sha256 over the weights, config and tokenizer files at the top of a checkpoint directory: what
    an RL run records of its base and what the ablation compares before re-scoring kept layouts. The
    same checkpoint gives the same digest wherever it lies: each file is hashed as bytes, except a PEFT
    adapter's ``adapter_config.json``, hashed as canonical JSON without ``base_model_name_or_path`` (the
    absolute path of the host it was trained on, which ``restore`` rewrites to the restored base's).
    Leaving it out loses nothing: the base's identity is its own digest, which the RL run records."""
    folder = Path(model_dir)
    files = [p for p in sorted(folder.iterdir()) if p.is_file()
             and (p.name in _MODEL_FILES or p.suffix in _WEIGHT_SUFFIXES)] if folder.is_dir() else []
    if not files:
        raise ArtifactError(f"{folder}: no model files to hash (config.json, *.safetensors ...)")
    return _digest({"path": p.name, "sha256": _model_file_sha256(p)} for p in files)


def _model_file_sha256(path: Path) -> str:
    if path.name != "adapter_config.json":
        return file_sha256(path)
    try:
        config = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ArtifactError(f"{path}: not an adapter config ({exc})") from None
    if not isinstance(config, dict):
        raise ArtifactError(f"{path}: not an adapter config (a JSON object)")
    config.pop("base_model_name_or_path", None)
    return hashlib.sha256(json.dumps(config, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def load_manifest(root: Path) -> dict[str, Artifact]:
    """The artifacts of ``root/artifacts.json`` by name (none when the file does not exist)."""
    path = root / MANIFEST
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        entries = data["artifacts"]
        return {name: Artifact.from_dict(name, entry, str(path)) for name, entry in entries.items()}
    except (json.JSONDecodeError, KeyError, TypeError, AttributeError) as exc:
        raise ArtifactError(f"{path}: not an artifact manifest ({exc!r})") from None


def _save_manifest(root: Path, artifacts: dict[str, Artifact]) -> None:
    body = {"artifacts": {name: artifacts[name].to_dict() for name in sorted(artifacts)}}
    write_atomic(root / MANIFEST, (json.dumps(body, indent=1) + "\n").encode())


def _entry(root: Path, name: str) -> Artifact:
    artifacts = load_manifest(root)
    if name not in artifacts:
        known = ", ".join(sorted(artifacts)) or "none"
        raise ArtifactError(f"no artifact {name!r} in {root / MANIFEST} (known: {known})")
    return artifacts[name]


def add_artifact(name: str, path: str | Path, *, made_by: str, data: Sequence[str] = (),
                 base: str | None = None, exclude: Sequence[str] = (), reuse: bool = True,
                 cwd: str | Path | None = None) -> Artifact:
    """Hash every file under ``path`` (a file or a folder inside the checkout) but those with a path
    component matching an ``exclude`` glob (``checkpoint-*``: an SFT base without its intermediate
    checkpoints), write the manifest entry ``name`` with no commit yet and stage those files and the
    manifest (``git add -f``: they may lie in an ignored folder such as ``runs/``), ready for the commit
    that holds them. With ``reuse`` a file whose sha256 equals a file of a pinned artifact is not
    staged: its entry refers to that artifact's commit (``commit``, ``at``), so the history keeps its
    bytes once. Re-adding a name is allowed until it is pinned."""
    root = repo_root(cwd)
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", name):
        raise ArtifactError(f"artifact name {name!r}: use letters, digits, '-', '_' and '.', starting with "
                            "a letter or digit")
    artifacts = load_manifest(root)
    if name in artifacts and artifacts[name].commit:
        raise ArtifactError(f"artifact {name!r} is pinned at {artifacts[name].commit[:12]}: pick a new name")
    if base is not None and base not in artifacts:
        raise ArtifactError(f"artifact {name}: --base {base!r} is not in {MANIFEST}")
    folder, paths = _files_under(root, name, path, exclude, cwd)
    files = tuple({"path": p.relative_to(folder).as_posix(), "sha256": file_sha256(p),
                   "size": p.stat().st_size} for p in paths)
    if reuse:
        files = _with_references(files, _kept_files(artifacts.values()))
    artifact = Artifact(name=name, root=folder.relative_to(root.resolve()).as_posix() or ".", files=files,
                        made_by=made_by, data=tuple(data), base=base, digest=_digest(files))
    artifacts[name] = artifact
    _save_manifest(root, artifacts)
    _git(root, "add", "-f", "--", *(_committed_path(artifact, f) for f in artifact.own_files), MANIFEST)
    return artifact


def _files_under(root: Path, name: str, path: str | Path, exclude: Sequence[str],
                 cwd: str | Path | None) -> tuple[Path, list[Path]]:
    """The artifact's folder and its files, none excluded, none too large for a git host."""
    target = (Path(cwd or ".") / path).resolve()
    if not target.exists():
        raise ArtifactError(f"artifact {name}: {path} does not exist")
    try:
        target.relative_to(root.resolve())
    except ValueError:
        raise ArtifactError(f"artifact {name}: {target} is outside the repository {root}") from None
    folder = target if target.is_dir() else target.parent
    paths = sorted(p for p in target.rglob("*") if p.is_file()) if target.is_dir() else [target]
    paths = [p for p in paths if not any(fnmatch.fnmatch(part, pattern) for pattern in exclude
                                         for part in p.relative_to(folder).parts)]
    if not paths:
        raise ArtifactError(f"artifact {name}: {path} holds no files")
    if large := [p for p in paths if p.stat().st_size > MAX_FILE_BYTES]:
        where, mib = large[0].relative_to(root.resolve()), large[0].stat().st_size / 2**20
        raise ArtifactError(f"artifact {name}: {where} has {mib:.1f} MiB, over the {MAX_FILE_BYTES // 2**20} "
                            "MiB a git host takes in one file: save the weights in bf16 or --exclude what a "
                            "later run does not read")
    return folder, paths


def _committed_path(artifact: Artifact, f: dict) -> str:
    return f["path"] if artifact.root in ("", ".") else f"{artifact.root}/{f['path']}"


def _source(artifact: Artifact, f: dict) -> tuple[str, str]:
    """The commit that keeps file ``f`` of a pinned artifact and its path there."""
    return (f["commit"], f["at"]) if "commit" in f else (artifact.commit, _committed_path(artifact, f))


def _kept_files(artifacts: Iterable[Artifact]) -> dict[str, tuple[str, str]]:
    """Where the pinned artifacts keep each sha256 they hold: (commit, path there). A reference leads
    to the commit that holds the bytes, not to the artifact that refers to them."""
    kept: dict[str, tuple[str, str]] = {}
    for artifact in sorted(artifacts, key=lambda a: a.name):
        if artifact.commit:
            for f in artifact.files:
                kept.setdefault(f["sha256"], _source(artifact, f))
    return kept


def _with_references(files: tuple[dict, ...], kept: dict[str, tuple[str, str]]) -> tuple[dict, ...]:
    return tuple({**f, "commit": kept[f["sha256"]][0], "at": kept[f["sha256"]][1]} if f["sha256"] in kept
                 else f for f in files)


def referenced_from(artifact: Artifact, artifacts: Mapping[str, Artifact]) -> dict[str, list[dict]]:
    """The files ``artifact`` refers to, by the pinned artifact that keeps them (by the commit's first
    12 digits where the manifest names none)."""
    keepers: dict[tuple[str, str], str] = {}
    for other in sorted(artifacts.values(), key=lambda a: a.name):
        for f in other.own_files if other.commit else ():
            keepers.setdefault(_source(other, f), other.name)
    by_keeper: dict[str, list[dict]] = {}
    for f in artifact.referenced_files:
        by_keeper.setdefault(keepers.get((f["commit"], f["at"]), f["commit"][:12]), []).append(f)
    return by_keeper


def _sources(artifact: Artifact) -> dict[str, list[tuple[dict, str]]]:
    """A pinned artifact's files by the commit that keeps them, each with its path in that commit."""
    groups: dict[str, list[tuple[dict, str]]] = {}
    for f in artifact.files:
        commit, path = _source(artifact, f)
        groups.setdefault(commit, []).append((f, path))
    return groups


def _read_sources(root: Path, groups: dict[str, list[tuple[dict, str]]],
                  temps: Mapping[str, Path] | None = None) -> Iterator[tuple[dict, str, str, str | None]]:
    """``(file, commit, path there, sha256)`` for every file of ``groups`` (:func:`_sources`), one
    ``git cat-file --batch`` per commit; with ``temps`` (by the file's ``path``) each blob is also
    written there. The sha256 is None where the commit holds no file at that path."""
    for commit, entries in groups.items():
        paths = [path for _, path in entries]
        sinks = [temps[f["path"]] for f, _ in entries] if temps is not None else None
        for (f, path), got in zip(entries, _blob_digests(root, commit, paths, sinks)):
            yield f, commit, path, got


def _blob_digests(root: Path, commit: str, paths: Sequence[str],
                  targets: Sequence[Path | None] | None = None) -> list[str | None]:
    """The sha256 of ``commit:path`` for each path, streamed through one ``git cat-file --batch``
    (binary-safe, a block at a time: a checkpoint of many GB never sits in memory); None where the
    commit holds no file at that path. With ``targets`` each blob is also written to its target."""
    targets = list(targets) if targets is not None else [None] * len(paths)
    try:
        proc = subprocess.Popen(["git", "cat-file", "--batch"], cwd=root, stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    except FileNotFoundError:
        raise ArtifactError("git is not installed: artifacts live in the repository's history") from None
    digests: list[str | None] = []
    try:
        for path, target in zip(paths, targets):
            proc.stdin.write(f"{commit}:{path}\n".encode())
            proc.stdin.flush()
            header = proc.stdout.readline().decode(errors="replace").split()
            if len(header) < 3:  # "<object> missing"
                digests.append(None)
                continue
            blob = header[1] == "blob"
            h = hashlib.sha256()
            sink = target if blob and target is not None else os.devnull  # devnull: only hashed
            with open(sink, "wb") as out:
                remaining = int(header[2])
                while remaining:
                    chunk = proc.stdout.read(min(remaining, 1 << 20))
                    if not chunk:
                        raise ArtifactError(f"git cat-file stopped inside {commit[:12]}:{path}")
                    h.update(chunk)
                    out.write(chunk)
                    remaining -= len(chunk)
            proc.stdout.read(1)  # the newline after the content
            digests.append(h.hexdigest() if blob else None)  # a folder at that path is no file
    finally:
        proc.stdin.close()
        proc.stdout.close()
        proc.wait()
    return digests


def _commit_present(root: Path, commit: str, name: str) -> None:
    done = subprocess.run(["git", "cat-file", "-e", f"{commit}^{{commit}}"], cwd=root, capture_output=True)
    if done.returncode == 0:
        return
    shallow = _git(root, "rev-parse", "--is-shallow-repository", check=False).decode().strip() == "true"
    hint = ("this clone is shallow: run `git fetch --unshallow`" if shallow else
            "fetch the branch that holds it (`git fetch origin`)")
    raise ArtifactError(f"artifact {name}: commit {commit} is not in this repository; {hint}")


def pin_artifact(name: str, commit: str = "HEAD", *, cwd: str | Path | None = None) -> Artifact:
    """Record ``commit`` as the one holding artifact ``name`` after checking each of its own files there,
    and each file it refers to in that file's commit, against the manifest's sha256; then take its own
    files out of the index (``git rm --cached``) and delete their working copies that git does not
    ignore, so that the next commit leaves the tree small."""
    root = repo_root(cwd)
    artifact = _entry(root, name)
    sha = _git(root, "rev-parse", "--verify", f"{commit}^{{commit}}").decode().strip()
    pinned = Artifact(**{**artifact.__dict__, "commit": sha})
    groups = _sources(pinned)
    for source in groups:
        _commit_present(root, source, name)
    for f, source, path, got in _read_sources(root, groups):
        if "commit" in f:
            _check_reference(name, f, source, path, got)
        elif got is None:
            raise ArtifactError(f"artifact {name}: commit {sha[:12]} does not hold {path}; commit the files "
                                f"first (`git add -f {artifact.root} {MANIFEST} && git commit`)")
        elif got != f["sha256"]:
            raise ArtifactError(f"artifact {name}: {path} in commit {sha[:12]} has sha256 {got}, the "
                                f"manifest says {f['sha256']} (add and commit it again)")
    _untrack(root, [_committed_path(pinned, f) for f in pinned.own_files])
    artifacts = load_manifest(root)
    artifacts[name] = pinned
    _save_manifest(root, artifacts)
    return pinned


def _check_reference(name: str, f: dict, commit: str, path: str, got: str | None) -> None:
    if got != f["sha256"]:
        held = "holds no such file" if got is None else f"has sha256 {got}, the manifest says {f['sha256']}"
        raise ArtifactError(f"artifact {name}: {f['path']} refers to {path} in commit {commit[:12]}, which "
                            f"{held}; add the artifact again (`--no-reuse` stages every file)")


def _untrack(root: Path, paths: Sequence[str]) -> None:
    """Take ``paths`` out of the index and delete the working copies that git does not ignore."""
    if not paths:  # an artifact whose files all live in earlier commits
        return
    _git(root, "rm", "-r", "-q", "--cached", "--ignore-unmatch", "--", *paths)
    ignored = set(_git(root, "check-ignore", "--no-index", "--", *paths, check=False).decode().splitlines())
    for path in paths:
        if path not in ignored:
            (root / path).unlink(missing_ok=True)


def restored_dir(root: Path, name: str) -> Path:
    return root / RESTORED / name


def is_restored(folder: Path, artifact: Artifact) -> bool:
    """Whether ``folder`` holds ``artifact`` as :func:`restore_artifact` wrote it (its marker names
    the same digest and every file has its size)."""
    try:
        marker = json.loads((folder / _MARKER).read_text())
    except (OSError, ValueError):
        return False
    if marker.get("digest") != artifact.digest:
        return False
    rewritten = set(marker.get("rewritten", ()))  # an adapter pointed at its restored base
    return all((folder / f["path"]).is_file() and
               (f["path"] in rewritten or (folder / f["path"]).stat().st_size == f["size"])
               for f in artifact.files)


def restore_artifact(name: str, to: str | Path | None = None, *, cwd: str | Path | None = None) -> Path:
    """Write artifact ``name`` into ``to`` (default ``<repo>/artifacts/NAME``), each file read from the
    commit that keeps it (its own, or an earlier artifact's for a reference) and checked against its
    sha256 before any is renamed into place: a mismatch writes nothing. Returns the folder; a folder that
    already holds it is left as it is."""
    root = repo_root(cwd)
    artifact = _entry(root, name)
    if not artifact.commit:
        raise ArtifactError(f"artifact {name} is not pinned yet: commit its files, then "
                            f"`physcene artifacts pin {name}`")
    folder = Path(cwd or ".", to).resolve() if to is not None else restored_dir(root, name)
    if is_restored(folder, artifact):
        return folder
    groups = _sources(artifact)
    for source in groups:
        _commit_present(root, source, name)
    temps = {f["path"]: temp_path(folder / f["path"]) for f in artifact.files}
    for p in temps.values():
        p.parent.mkdir(parents=True, exist_ok=True)
    try:  # every file checked before any is renamed into place: a mismatch writes nothing
        for f, source, path, got in _read_sources(root, groups, temps):
            if got is None:
                raise ArtifactError(f"artifact {name}: commit {source[:12]} does not hold {path}")
            if got != f["sha256"]:
                raise ArtifactError(f"artifact {name}: {path} at {source[:12]} has sha256 {got}, "
                                    f"the manifest says {f['sha256']}: refusing to restore it")
    except BaseException:
        for p in temps.values():
            p.unlink(missing_ok=True)
        raise
    for path, tmp in temps.items():
        os.replace(tmp, folder / path)
    write_atomic(folder / _MARKER, json.dumps({"name": name, "commit": artifact.commit,
                                                "digest": artifact.digest}).encode())
    if artifact.base is not None and any(f["path"].endswith("adapter_config.json") for f in artifact.files):
        _point_adapters_at(folder, restore_artifact(artifact.base, cwd=cwd))
    return folder


def resolve_model(target: str, *, cwd: str | Path | None = None) -> str:
    """The checkpoint folder of a ``model:`` generator's target: ``target`` itself when it is a folder,
    else the restored folder of the artifact of that name (restored now if it is not yet). ``NAME/PATH``
    is a folder inside the artifact (``rl-med-s1-pada-297/checkpoint-200``: a curve point it keeps). An
    RL run kept without its final adapter (byte for byte its newest checkpoint's, left out to halve the
    artifact) resolves to that newest checkpoint."""
    if Path(cwd or ".", target).is_dir():
        return target
    try:
        root = repo_root(cwd)
    except ArtifactError:
        return target  # outside a checkout a model:PATH stays a path (its generator names it missing)
    artifacts = load_manifest(root)
    name, _, inside = target.partition("/")
    if name not in artifacts:
        return target
    try:
        folder = restore_artifact(name, cwd=cwd)
    except ArtifactError as exc:
        raise ArtifactError(f"model:{target}: {exc} (restore it with `physcene artifacts restore "
                            f"{name}`)") from None
    if inside:
        if not (folder / inside).is_dir():
            kept = sorted(p.name for p in folder.iterdir() if p.is_dir())
            raise ArtifactError(f"model:{target}: artifact {name} has no folder {inside!r} (it has: "
                                f"{', '.join(kept) or 'none'})")
        return str(folder / inside)
    return str(_run_model(folder))


def _holds_model(folder: Path) -> bool:
    return (folder / "config.json").is_file() or (folder / "adapter_config.json").is_file()


def _run_model(folder: Path) -> Path:
    """``folder`` when it holds a model (a config or an adapter config), else its newest
    ``checkpoint-N`` that does (an RL run's final model), else ``folder`` (its loader names what is
    missing)."""
    if _holds_model(folder):
        return folder
    steps = [(int(p.name.split("-", 1)[1]), p) for p in folder.glob("checkpoint-*")
             if p.name.split("-", 1)[1].isdigit() and _holds_model(p)]
    return max(steps)[1] if steps else folder


def _point_adapters_at(folder: Path, base_folder: Path) -> None:
    """A LoRA adapter names its base by the absolute path it was trained from, which need not exist
    where the artifact is restored: point every adapter of the folder (the final one and each
    ``checkpoint-N``'s) at the restored base, noted in the marker."""
    rewritten = []
    for config_path in sorted(folder.rglob("adapter_config.json")):
        config = json.loads(config_path.read_text())
        if Path(str(config.get("base_model_name_or_path", ""))).is_dir():
            continue
        config["base_model_name_or_path"] = str(base_folder)
        write_atomic(config_path, json.dumps(config, indent=2).encode())
        rewritten.append(config_path.relative_to(folder).as_posix())
    if rewritten:
        marker = json.loads((folder / _MARKER).read_text())
        marker["rewritten"] = sorted({*marker.get("rewritten", ()), *rewritten})
        write_atomic(folder / _MARKER, json.dumps(marker).encode())


def resolve_generators(generators: str, *, cwd: str | Path | None = None) -> str:
    """A comma-separated ``--generator`` argument with every ``model:NAME`` that names an artifact (and
    no folder) replaced by ``model:<its restored folder>``; the others as given."""
    out = []
    for spec in generators.split(","):
        kind, _, target = spec.strip().partition(":")
        out.append(f"model:{resolve_model(target, cwd=cwd)}" if kind == "model" and target else spec)
    return ",".join(out)
