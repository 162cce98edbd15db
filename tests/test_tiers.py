"""The two test tiers (tests/helpers/tiers.py, conftest's hooks): plain pytest leaves the 'full' tests out unless they are named;
--full, a marker expression or naming the file keeps them; the README's test command (CI) runs both."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest

from tests.helpers import tiers

ROOT = Path(__file__).resolve().parents[1]


class _Item:
    def __init__(self, file: str, name: str, full: bool):
        self.fspath = ROOT / "tests" / file
        self.nodeid = f"tests/{file}::{name}"
        self._full = full

    def get_closest_marker(self, name):
        return object() if name == "full" and self._full else None


class _Config:
    def __init__(self, args, full=False, markexpr=""):
        self.args = args
        self.invocation_params = SimpleNamespace(dir=ROOT)
        self._options = {"--full": full, "-m": markexpr}
        self.deselected = []
        self.hook = SimpleNamespace(pytest_deselected=lambda items: self.deselected.extend(items))

    def getoption(self, name):
        return self._options[name]


def _items():
    return [_Item("test_a.py", "test_unit", False), _Item("test_a.py", "test_paper_size", True),
            _Item("test_b.py", "test_kill", True)]


def _kept(config) -> list[str]:
    items = _items()
    tiers.pytest_collection_modifyitems(config, items)
    return [i.nodeid.split("::")[1] for i in items]


def test_plain_pytest_leaves_the_full_tier_out_and_says_how_many():
    config = _Config(["tests"])
    assert _kept(config) == ["test_unit"]
    assert [i.nodeid.split("::")[1] for i in config.deselected] == ["test_paper_size", "test_kill"]
    assert config._mtt_full_tier_left_out == 2
    assert _kept(_Config([])) == ["test_unit"] and _kept(_Config(["."])) == ["test_unit"]


def test_full_or_a_marker_expression_keeps_everything():
    assert _kept(_Config(["tests"], full=True)) == ["test_unit", "test_paper_size", "test_kill"]
    assert _kept(_Config(["tests"], markexpr="smoke")) == ["test_unit", "test_paper_size", "test_kill"]


def test_a_full_test_named_on_the_command_line_runs():
    assert _kept(_Config(["tests/test_b.py"])) == ["test_unit", "test_kill"]
    assert _kept(_Config(["tests/test_a.py::test_paper_size"])) == ["test_unit", "test_paper_size"]
    assert _kept(_Config(["tests/test_a.py::test_unit"])) == ["test_unit"]


@pytest.mark.smoke
def test_the_readme_test_command_runs_both_tiers_and_names_the_fast_one():
    readme = (ROOT / "README.md").read_text()
    block = readme.split("<!-- test-command -->", 1)[1].split("```", 2)[1].strip().splitlines()
    ci_line, fast_line = block[1], block[2]          # block[0] is the fence's language
    assert "pytest --full" in ci_line, ci_line
    assert "pytest" in fast_line and "--full" not in fast_line, fast_line
