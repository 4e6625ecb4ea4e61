"""The layers of docs/design.md, enforced: who may import whom, and no import cycle anywhere.

Every ``import`` statement of the installed packages is read with ``ast`` (module level and inside
functions alike: a lazy import is still a dependency; ``if TYPE_CHECKING:`` blocks are not), each
resolved to the module it names (``from physcene.ctrc.grammar import X`` is an edge to
``physcene.ctrc.grammar``, ``from physcene.ctrc import grammar`` to the submodule when there is one).
"""

from __future__ import annotations

import ast
from collections.abc import Iterable
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# source folder -> the package it installs as (pyproject's package-dir)
PACKAGES = {"physcene": "physcene", "kernels": "physcene.kernels", "train": "physcene.train",
            "eval": "physcene.eval", "configs": "physcene.configs"}

# (importer prefix, forbidden imported prefixes, except these prefixes)
RULES = [
    ("physcene.kernels", ("physcene",), ("physcene.kernels",)),
    ("physcene.physics", ("physcene.ctrc", "physcene.reward", "physcene.tto"), ()),
    ("physcene.eval", ("physcene.train",), ()),
]


def module_sources(root: Path = ROOT) -> dict[str, Path]:
    """Every module of the packages: dotted name -> file."""
    modules = {}
    for folder, package in PACKAGES.items():
        for path in sorted((root / folder).rglob("*.py")):
            parts = path.relative_to(root / folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join((package, *parts))] = path
    return modules


def _type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def imported_modules(name: str, source: str, is_package: bool, known: Iterable[str]) -> set[str]:
    """The project modules that module ``name`` (with text ``source``) imports."""
    known = set(known)
    package = name if is_package else name.rpartition(".")[0]
    found: set[str] = set()

    def nearest(target: str) -> str | None:
        while target and target not in known:
            target = target.rpartition(".")[0]
        return target or None

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _type_checking(child):
                for stmt in child.orelse:
                    visit(stmt)
                continue
            if isinstance(child, ast.Import):
                for alias in child.names:
                    hit = nearest(alias.name)
                    if hit:
                        found.add(hit)
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    anchor = package.split(".")
                    anchor = anchor[: len(anchor) - (child.level - 1)]
                    base = ".".join([*anchor, *([base] if base else [])])
                for alias in child.names:
                    hit = nearest(f"{base}.{alias.name}") if base else None
                    if hit == f"{base}.{alias.name}":
                        found.add(hit)
                    else:
                        hit = nearest(base)
                        if hit:
                            found.add(hit)
            visit(child)

    visit(ast.parse(source))
    found.discard(name)
    return found


def import_graph(sources: dict[str, str], packages: set[str]) -> dict[str, set[str]]:
    """Module -> the project modules it imports, for ``sources`` (name -> text)."""
    return {name: imported_modules(name, text, name in packages, sources) for name, text in sources.items()}


def forbidden_imports(graph: dict[str, set[str]]) -> list[str]:
    """``importer -> imported`` for every edge a rule of :data:`RULES` forbids."""
    bad = []
    for importer, targets in graph.items():
        for prefix, banned, allowed in RULES:
            if not _under(importer, prefix):
                continue
            for target in sorted(targets):
                if any(_under(target, b) for b in banned) and not any(_under(target, a) for a in allowed):
                    bad.append(f"{importer} -> {target}")
    return sorted(bad)


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles = []
    counter = 0

    def strongconnect(v: str) -> None:
        nonlocal counter
        index[v] = low[v] = counter
        counter += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                strongconnect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            strongconnect(v)
    return cycles


def _under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    files = module_sources()
    packages = {name for name, path in files.items() if path.name == "__init__.py"}
    return import_graph({name: path.read_text() for name, path in files.items()}, packages)


def test_the_layers_hold(graph):
    assert forbidden_imports(graph) == []


def test_there_is_no_import_cycle(graph):
    assert import_cycles(graph) == []


def test_a_forbidden_import_or_a_cycle_is_caught():
    """The checker itself: a kernel importing the scene language, the engine importing the reward,
    eval importing train, and a two-module cycle are each reported."""
    sources = {
        "physcene.kernels.penetration": "import warp as wp\nfrom physcene.ctrc import MAX_ABS_CM\n",
        "physcene.kernels.launch": "from physcene.kernels import penetration\n",
        "physcene.physics.engine": "def f():\n    from physcene.reward import PhysicsReward\n",
        "physcene.eval.harness": "from physcene.train.generate import generate_with\n",
        "physcene.ctrc": "from physcene.ctrc.reader import parse\n",
        "physcene.ctrc.reader": "from physcene.scene import Scene\n",
        "physcene.scene": ("from typing import TYPE_CHECKING\n"
                           "if TYPE_CHECKING:\n    from physcene.ctrc import parse\n"),
        "physcene.reward": "from physcene.tto import repair\n",
        "physcene.tto": "from . import reward\n",
        "physcene.train.generate": "",
    }
    packages = {"physcene.ctrc"}
    graph = import_graph({**sources, "physcene": ""}, packages | {"physcene"})
    assert forbidden_imports(graph) == [
        "physcene.eval.harness -> physcene.train.generate",
        "physcene.kernels.penetration -> physcene.ctrc",
        "physcene.physics.engine -> physcene.reward",
    ]
    assert graph["physcene.ctrc"] == {"physcene.ctrc.reader"}
    assert graph["physcene.scene"] == set()  # a TYPE_CHECKING import is no dependency
    assert import_cycles(graph) == [["physcene.reward", "physcene.tto"]]


def test_every_package_is_installed():
    """pyproject's package list names every package folder (a non-editable install ships only those)."""
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    files = module_sources()
    packages = {name for name, path in files.items() if path.name == "__init__.py"}
    assert set(setuptools["packages"]) == packages
    mapped = {setuptools["package-dir"][p] for p in ("physcene.kernels", "physcene.train", "physcene.eval")}
    assert mapped == {"kernels", "train", "eval"}
