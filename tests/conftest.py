from __future__ import annotations

import copy
import functools
from pathlib import Path

import numpy as np
import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf

from filters.base import MeasurementSeries

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"


@pytest.fixture(scope="session")
def models13():
    return instantiate(OmegaConf.load(CONF / "models" / "acceleration13.yaml"), _convert_="all")


def scenario(name: str, **overrides):
    node = OmegaConf.load(CONF / "scenario" / f"{name}.yaml")
    return instantiate(OmegaConf.merge(node, overrides), _convert_="all")


def measurements(truth, seed: int, noise_std: float = 20.0) -> MeasurementSeries:
    from pipeline.studies.ao_vsimm.sensor import PositionSensor
    det = PositionSensor(noise_std).measure(truth, seed)
    return MeasurementSeries(det.time, det.z[:, :, 0], noise_std**2 * np.eye(2), det.detected[:, :, 0], det.sensor)


EXPERIMENTS = tuple(sorted(p.stem for p in (CONF / "experiment").glob("*.yaml")))


@functools.cache
def _composition(overrides: tuple[str, ...]):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        return compose("config", overrides=list(overrides))


def _composed(experiment: str, overrides: tuple[str, ...]):
    return _composition((f"experiment={experiment}", *overrides))


ARTIFACTS = "paths.artifacts="


def composed_config(*overrides: str):
    """conf/config.yaml composed with the overrides, unresolved: a copy of one composition per
    distinct overrides per process (a composition took 0.21 s on 2026-12-03, a copy 0.01 s; the
    collection of the test files alone asked for some 200, and every in-process run for one more).
    ``paths.artifacts=``, a fresh tmp_path in nearly every call, is set on the copy instead of
    being composed: it is a plain value that only other values interpolate."""
    cfg = copy.deepcopy(_composition(tuple(o for o in overrides if not o.startswith(ARTIFACTS))))
    for override in overrides:
        if override.startswith(ARTIFACTS):
            cfg.paths.artifacts = override[len(ARTIFACTS):]
    return cfg


def composed(experiment: str, *overrides: str):
    """``composed_config`` with ``experiment=<experiment>``."""
    return composed_config(f"experiment={experiment}", *overrides)


def smoke_experiments() -> list[tuple[str, list[str]]]:
    """(experiment, its ``smoke`` overrides) for every experiment that sets one (one per study, see
    conf/config.yaml): the tests that must cover every study parametrize over this, not a hand list."""
    found = []
    for name in EXPERIMENTS:
        smoke = _composed(name, ()).get("smoke")
        if smoke is not None:
            found.append((name, [str(o) for o in smoke]))
    return found


class SmokeRuns:
    """Each smoke experiment's run at ``mc.runs=2`` with its smoke overrides (the recording off),
    made on first use and kept for the session (one per xdist worker), every experiment's under
    one artifacts root ``root`` (``runs/<experiment>/run``, one stage cache): the metric registry,
    recompute and cached-stage determinism tests read the same run instead of making their own.
    A test may add runs under ``root``; it must not change what is there."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.overrides = dict(smoke_experiments())
        self._done: dict[str, tuple] = {}

    def __call__(self, experiment: str):
        """(RunOutcome, RunContext) of the experiment's smoke run."""
        if experiment not in self._done:
            from tests.test_pipeline import run_in_process
            self._done[experiment] = run_in_process(self.root, f"{experiment}/run", f"experiment={experiment}",
                                                    "mc.runs=2", *self.overrides[experiment])
        return self._done[experiment]


@pytest.fixture(scope="session")
def smoke_runs(tmp_path_factory) -> SmokeRuns:
    return SmokeRuns(tmp_path_factory.mktemp("smoke_runs"))


# ---- test tiers -------------------------------------------------------------------------------------
# Plain ``pytest`` is the developer's loop: unit and property tests and one reduced smoke run per study.
# Tests marked ``full`` (paper-size targets, launchers and sweeps across processes, kills, load,
# concurrency) run with ``--full`` (the README's test command and .ci/run) or when their file or node
# id is named on the command line.

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
