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
