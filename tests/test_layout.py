"""The layout holds its architecture: no import circle in pipeline/ or filters/, and the arrows run
one way: filters import nothing of pipeline; the shared pipeline modules import no particular study
(only the base they all extend, pipeline.studies.single_target); a study imports no other study.
Every import counts, a function's lazy one too: a circle through a lazy import is still a circle a
reader has to untangle."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "filters")
SHARED_STUDY_BASE = "pipeline.studies.single_target"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for package in PACKAGES for p in sorted((ROOT / package).rglob("*.py"))}


def imports(path: Path, known: set[str]) -> set[str]:
    """The project modules ``path`` imports (``from a import b`` counts a.b when that is a module)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    here = module_name(path)
    package = here if path.name == "__init__.py" else here.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else []))
            # ``from a import b``: the module a.b where there is one, else a name of a
            names = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base for alias in node.names]
        else:
            continue
        for name in names:
            while name and name not in known:
                name = name.rpartition(".")[0]
            if name and name != here:
                found.add(name)
    return found


def graph() -> dict[str, set[str]]:
    known = modules()
    names = set(known)
    return {name: imports(path, names) for name, path in known.items()}


def circles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
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
                found.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return found




def test_there_is_no_import_circle():
    assert circles(graph()) == []


def _study(module: str) -> str | None:
    parts = module.split(".")
    if module.startswith("pipeline.studies.") and module != SHARED_STUDY_BASE and len(parts) > 2:
        return parts[2]
    return None


def test_the_arrows_run_one_way():
    wrong = []
    for module, targets in graph().items():
        for target in targets:
            if module.startswith("filters") and target.startswith("pipeline"):
                wrong.append(f"{module} -> {target} (filters import nothing of pipeline)")
            elif _study(target) and not _study(module) and not module.startswith("pipeline.studies"):
                wrong.append(f"{module} -> {target} (a shared module imports no study)")
            elif _study(target) and _study(module) and _study(target) != _study(module):
                wrong.append(f"{module} -> {target} (a study imports no other study)")
    assert not wrong, "\n".join(sorted(wrong))


def test_the_top_level_stays_small():
    top = sorted(p.name for p in (ROOT / "pipeline").glob("*.py"))
    assert len(top) <= 12, top


def test_the_circle_finder_finds_a_circle():
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert circles({"a": {"b"}, "b": set()}) == []
