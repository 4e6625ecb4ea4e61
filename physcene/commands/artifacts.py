"""``physcene artifacts list|add|pin|restore``: checkpoints kept in the repository's history
(docs/training.md, "Artifacts").

    physcene artifacts add small-sft runs/small/sft --exclude 'checkpoint-*' \\
        --made-by "physcene train sft --config small" --data data/train.jsonl
    git commit -m "artifact small-sft"        # add staged the files and artifacts.json (a file that a
                                              # pinned artifact keeps is referred to, not staged)
    physcene artifacts pin small-sft          # records HEAD, takes the files out of the index
    git commit -am "artifact small-sft: out of the tree"
    physcene artifacts restore small-sft      # -> artifacts/small-sft/ (ignored), sha256-checked
"""

from __future__ import annotations

from physcene.artifacts import (
    MANIFEST,
    add_artifact,
    is_restored,
    load_manifest,
    pin_artifact,
    referenced_from,
    repo_root,
    restore_artifact,
    restored_dir,
)
from physcene.commands import add_json, print_json

NAME = "artifacts"
HELP = "list, add, pin and restore checkpoints kept in the repository's history (artifacts.json)"


def add_arguments(parser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION")
    sub.required = True
    listing = sub.add_parser("list", help="the manifest's artifacts, pinned or not, restored or not")
    add_json(listing, "the manifest with each artifact's restored state")
    add = sub.add_parser("add", help="hash a checkpoint folder, write its manifest entry, stage both")
    add.add_argument("name", help="the artifact's name, e.g. small-sft")
    add.add_argument("path", help="the file or folder (inside the repository) to keep")
    add.add_argument("--made-by", required=True, help="the command that made it")
    add.add_argument("--data", action="append", default=[], help="data it was made from (repeatable)")
    add.add_argument("--base", help="the artifact it was trained from, by name")
    add.add_argument("--exclude", action="append", default=[], metavar="GLOB",
                     help="leave out files with a path component matching GLOB, e.g. 'checkpoint-*' "
                          "(repeatable)")
    add.add_argument("--no-reuse", dest="reuse", action="store_false",
                     help="stage every file, also those a pinned artifact already keeps (by default they are "
                          "referred to in the manifest, not committed again)")
    pin = sub.add_parser("pin", help="record the commit holding an artifact's files and take them out of "
                                     "the index (commit again afterwards)")
    pin.add_argument("name")
    pin.add_argument("--commit", default="HEAD", help="the commit holding the files (default: HEAD)")
    restore = sub.add_parser("restore", help="write an artifact from its commit, sha256-checked")
    restore.add_argument("name")
    restore.add_argument("--to", metavar="DIR", help="target folder (default: artifacts/NAME, ignored)")


def _size(files) -> int:
    return sum(f["size"] for f in files)


def _list(args) -> int:
    root = repo_root()
    artifacts = load_manifest(root)
    rows = {name: {**a.to_dict(), "restored": is_restored(restored_dir(root, name), a),
                   "size": _size(a.files), "own_size": _size(a.own_files),
                   "referenced_size": _size(a.referenced_files),
                   "referenced_from": {k: _size(v) for k, v in referenced_from(a, artifacts).items()}}
            for name, a in artifacts.items()}
    if getattr(args, "json", False):
        print_json({"manifest": str(root / MANIFEST), "artifacts": rows})
        return 0
    if not rows:
        print(f"no artifacts in {root / MANIFEST}")
    for name, row in rows.items():
        commit = (row["commit"] or "not pinned")[:12]
        state = "restored" if row["restored"] else "not restored"
        sources = f" from {', '.join(row['referenced_from'])}" if row["referenced_from"] else ""
        print(f"{name}: {len(row['files'])} file(s), {row['own_size'] / 2**20:.1f} MiB own, "
              f"{row['referenced_size'] / 2**20:.1f} MiB referenced{sources}, commit {commit}, {state}; "
              f"made by: {row['made_by']}" + (f"; base: {row['base']}" if row["base"] else ""))
    return 0


def _added(a, artifacts) -> str:
    """What ``add`` did: the files staged, those referred to and where they are kept."""
    staged, referenced = a.own_files, a.referenced_files
    mib = _size(staged) / 2**20
    line = (f"{a.name}: {len(a.files)} file(s), {_size(a.files) / 2**20:.1f} MiB under {a.root}, digest "
            f"{a.digest[:12]}; staged {len(staged)} file(s), {mib:.1f} MiB with {MANIFEST}")
    if referenced:
        line += (f"; referenced {len(referenced)} file(s), {_size(referenced) / 2**20:.1f} MiB kept by "
                 f"{', '.join(referenced_from(a, artifacts))}")
    return (line + f"; next: `git commit`, then `physcene artifacts pin {a.name}` (a push that adds and then "
            f"removes the staged files carries them twice: {2 * mib:.1f} MiB of diffs)")


def run(args) -> int:
    # ArtifactError is a ValueError: the CLI prints its one line, no traceback
    if args.action == "list":
        return _list(args)
    if args.action == "add":
        a = add_artifact(args.name, args.path, made_by=args.made_by, data=args.data, base=args.base,
                         exclude=args.exclude, reuse=args.reuse)
        print(_added(a, load_manifest(repo_root())))
    elif args.action == "pin":
        a = pin_artifact(args.name, args.commit)
        print(f"{a.name}: pinned at {a.commit[:12]}, its files are out of the index; next: "
              f"`git commit -am \"artifact {a.name}: out of the tree\"`")
    else:
        print(f"{args.name}: {restore_artifact(args.name, args.to)}")
    return 0
