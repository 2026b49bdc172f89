"""No import climbs back up between the folders (and top-level modules) of ``src/crowdrl``: the package
graph is acyclic, so each layer (sim < envs < models < exploration < policies < evaluation < training <
export < agents, reproduction, viz < cli) can be read and tested without the ones above it."""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "crowdrl"


def package_imports(root: Path = SRC) -> dict[str, dict[str, set[str]]]:
    """``{package: {imported package: {files}}}`` over every import of ``crowdrl.*``, lazy ones included."""
    edges: dict[str, dict[str, set[str]]] = defaultdict(lambda: defaultdict(set))
    for path in root.rglob("*.py"):
        rel = path.relative_to(root)
        pkg = rel.parts[0] if len(rel.parts) > 1 else rel.stem
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            for name in names:
                parts = name.split(".")
                if parts[0] == "crowdrl" and len(parts) > 1 and parts[1] != pkg:
                    edges[pkg][parts[1]].add(str(rel))
    return edges


def cycles(edges: dict[str, dict[str, set[str]]]) -> list[str]:
    """Each import ``a -> b`` from which ``a`` can be reached again, with the files that make it."""
    def reach(start: str) -> set[str]:
        seen, todo = set(), [start]
        while todo:
            for nxt in edges.get(todo.pop(), {}):
                if nxt not in seen:
                    seen.add(nxt)
                    todo.append(nxt)
        return seen

    return [f"{a} -> {b} ({', '.join(sorted(files))})" for a in sorted(edges) for b, files in sorted(edges[a].items())
            if a in reach(b)]


def test_no_import_climbs_back_up_between_folders():
    found = cycles(package_imports())
    assert not found, "imports that climb back up:\n  " + "\n  ".join(found)


def test_the_check_finds_a_loop(tmp_path):
    (tmp_path / "low").mkdir()
    (tmp_path / "high").mkdir()
    (tmp_path / "low" / "a.py").write_text("def f():\n    from crowdrl.high.b import g\n")  # a lazy import counts too
    (tmp_path / "high" / "b.py").write_text("from crowdrl.low.a import f\n")
    assert cycles(package_imports(tmp_path)) == ["high -> low (high/b.py)", "low -> high (low/a.py)"]
