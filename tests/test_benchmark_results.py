"""The benchmarks' results files (benchmarks/results/): each states when, where and how it was measured,
and every time in it stands beside a ratio measured in the same run (docs/performance.md)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
HEADER = ("benchmark", "date", "commit", "machine", "load average at start", "command")


def _results() -> list[Path]:
    return sorted(RESULTS.glob("*.json"))


def test_there_are_results_and_each_json_has_its_markdown():
    assert _results(), "benchmarks/results/ holds no results"
    for path in _results():
        assert path.with_suffix(".md").is_file(), f"{path.name} has no .md beside it"


@pytest.mark.parametrize("path", _results(), ids=lambda p: p.stem)
def test_a_results_file_states_its_context_and_pairs_every_time_with_a_ratio(path):
    result = json.loads(path.read_text())
    for key in ("date", "commit", "machine", "command", "load_average_at_start"):
        assert result.get(key) not in (None, "", {}), f"{path.name}: no {key}"
    assert re.fullmatch(r"[0-9a-f]{7,40}", result["commit"]), result["commit"]
    assert result["machine"].get("cores"), f"{path.name}: the machine's cores"
    markdown = path.with_suffix(".md").read_text()
    for line in HEADER:
        assert f"- {line}:" in markdown, f"{path.with_suffix('.md').name}: no '- {line}:' line"
    timed = 0
    for table in result["tables"]:
        kinds = {c["key"]: c["kind"] for c in table["columns"]}
        times = [k for k, kind in kinds.items() if kind == "seconds"]
        ratios = [k for k, kind in kinds.items() if kind in ("ratio", "percent")]
        for row in table["rows"]:
            if any(row.get(k) is not None for k in times):
                timed += 1
                assert ratios and any(row.get(k) is not None for k in ratios), \
                    f"{path.name}: the row {row.get(table['columns'][0]['key'])!r} has a time and no ratio"
    assert timed, f"{path.name}: no timed row"


def test_the_readme_links_only_results_that_exist():
    readme = (ROOT / "README.md").read_text()
    linked = re.findall(r"\(benchmarks/results/([\w.-]+\.md)\)", readme)
    assert linked, "the README's Performance table links no results file"
    for name in linked:
        assert (RESULTS / name).is_file(), f"README links benchmarks/results/{name}, which does not exist"
