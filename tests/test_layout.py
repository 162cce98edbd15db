"""The layout holds its architecture: no import circle in pipeline/ or filters/, and the arrows run
one way: filters import nothing of pipeline; the shared pipeline modules import no particular study
(only the base they all extend, pipeline.studies.single_target); a study imports no other study.
Every import counts, a function's lazy one too: a circle through a lazy import is still a circle a
reader has to untangle. The tests are laid out the same way: what several test files share is in
tests/helpers/, and no file of tests/ reaches into a test file or conftest.py."""

from __future__ import annotations

import ast
import re
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


# ---- the tests' own layout ---------------------------------------------------------------------------
TEST_MODULE = re.compile(r"\btests\.(test_\w+|conftest)\b")


def reaches_into_test_modules(path: Path, tests: Path) -> list[str]:
    """What ``path`` takes from a test module or conftest that is not itself: an import (a lazy one
    too, and ``from tests import conftest``) or a dotted name in a string (a code string a child
    runs, a Hydra ``_target_``). A file may name its own module (its classes as ``_target_``)."""
    own = "tests." + path.relative_to(tests).with_suffix("").as_posix().replace("/", ".")
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            names = [node.module] + ([f"tests.{a.name}" for a in node.names] if node.module == "tests" else [])
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            names = [m.group(0) for m in TEST_MODULE.finditer(node.value)]
        for name in names:
            match = TEST_MODULE.match(name)
            if match and f"tests.{match.group(1)}" != own:
                found.append(f"{path.relative_to(tests.parent)}:{node.lineno}: {name}")
    return found


def test_no_file_of_tests_reaches_into_another_test_file_or_conftest():
    tests = ROOT / "tests"
    found = [hit for path in sorted(tests.rglob("*.py")) for hit in reaches_into_test_modules(path, tests)]
    assert found == [], "move what is shared into tests/helpers/:\n" + "\n".join(found)


def test_the_test_module_finder_finds_each_way_in(tmp_path):
    tests = tmp_path / "tests"
    tests.mkdir()
    t = "tests"                      # spelled apart: this file holds to the rule it tests
    (tests / "test_mine.py").write_text(
        f"from {t}.test_other import x\nimport {t}.conftest\nfrom {t} import conftest\n"
        f"def f():\n    from {t}.test_lazy import y\n"
        f"CODE = 'from {t}.test_child import z'\nTARGET = '{t}.test_mine.Mine'\n"
        f"from {t}.helpers.runs import run_in_process\n")
    assert [hit.split(": ")[1] for hit in reaches_into_test_modules(tests / "test_mine.py", tests)] == [
        f"{t}.{name}" for name in ("test_other", "conftest", "conftest", "test_lazy", "test_child")]
