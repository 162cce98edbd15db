"""The project's configuration as the tests compose it in process (``conf/``, Hydra's compose API):
one composition per distinct overrides per process, copied for each caller, and the experiments
that declare a smoke run."""

from __future__ import annotations

import copy
import functools

from tests.helpers.processes import ROOT

CONF = ROOT / "conf"
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
