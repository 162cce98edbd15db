"""The two test tiers, as pytest hooks (tests/conftest.py takes them from here).

Plain ``pytest`` is the developer's loop: unit and property tests and one reduced smoke run per study.
Tests marked ``full`` (paper-size targets, launchers and sweeps across processes, kills, load,
concurrency) run with ``--full`` (the README's test command and .ci/run) or when their file or node
id is named on the command line.
"""

from __future__ import annotations

from pathlib import Path

from tests.helpers.processes import ROOT

def pytest_addoption(parser):
    parser.addoption("--full", action="store_true", default=False,
                     help="also run the full tier: the tests marked 'full' (paper-size targets, launchers, "
                          "kills, load, concurrency), as CI does")


def _named_on_the_command_line(config) -> list[str]:
    """The command line's test paths and node ids that name less than the whole suite."""
    whole = {ROOT.resolve(), (ROOT / "tests").resolve()}
    named = []
    for arg in config.args:
        path = Path(arg.split("::")[0])
        path = (Path(config.invocation_params.dir) / path).resolve()
        if path not in whole:
            named.append(str(path) + ("::" + arg.split("::", 1)[1] if "::" in arg else ""))
    return named


def _explicitly_asked(item, named: list[str]) -> bool:
    here = str(Path(item.fspath).resolve())
    node = here + "::" + item.nodeid.split("::", 1)[1] if "::" in item.nodeid else here
    return any(node == n or node.startswith(n + "::") or node.startswith(n.rstrip("/") + "/") for n in named)


def pytest_collection_modifyitems(config, items):
    if config.getoption("--full") or config.getoption("-m"):
        return                                   # a marker expression chooses for itself
    named = _named_on_the_command_line(config)
    kept, deselected = [], []
    for item in items:
        if item.get_closest_marker("full") is None or _explicitly_asked(item, named):
            kept.append(item)
        else:
            deselected.append(item)
    if deselected:
        config.hook.pytest_deselected(items=deselected)
        items[:] = kept
        config._mtt_full_tier_left_out = len(deselected)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    left_out = getattr(config, "_mtt_full_tier_left_out", 0)
    if left_out:
        terminalreporter.write_line(f"fast tier: {left_out} tests of the full tier left out "
                                    f"(paper-size, launchers, kills, load); run them with: pytest --full -n auto")


def pytest_report_header(config):
    if not (config.getoption("--full") or config.getoption("-m")):
        return "tier: fast (the tests marked 'full' are left out unless named; pytest --full -n auto runs both tiers)"
    return None
