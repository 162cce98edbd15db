"""Fixtures and the test tiers' hooks; the plain helpers the tests import are in tests/helpers/."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf

from tests.helpers.config import CONF, smoke_experiments
from tests.helpers.tiers import (  # noqa: F401 (pytest finds its hooks here by name)
    pytest_addoption, pytest_collection_modifyitems, pytest_report_header, pytest_terminal_summary,
)


@pytest.fixture(scope="session")
def models13():
    return instantiate(OmegaConf.load(CONF / "models" / "acceleration13.yaml"), _convert_="all")


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
            from tests.helpers.runs import run_in_process      # the runner, imported when a test asks
            self._done[experiment] = run_in_process(self.root, f"{experiment}/run", f"experiment={experiment}",
                                                    "mc.runs=2", *self.overrides[experiment])
        return self._done[experiment]


@pytest.fixture(scope="session")
def smoke_runs(tmp_path_factory) -> SmokeRuns:
    return SmokeRuns(tmp_path_factory.mktemp("smoke_runs"))
