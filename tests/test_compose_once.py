"""pipeline.compose_once: under the basic launcher a sweep composes each job's config once (the
sweeper's validation), and the job gets the same config a second composition would give it."""

from __future__ import annotations

import inspect
import os
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf, open_dict

from pipeline.compose_once import BASIC_LAUNCHER, compose_each_job_once

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def sweep_loader(tmp_path):
    """Hydra's config loader and a multirun's config for this project's conf/, as `-m` builds them."""
    from hydra._internal.hydra import Hydra
    from hydra._internal.utils import create_config_search_path
    from hydra.core.global_hydra import GlobalHydra
    from hydra.types import RunMode

    compose_each_job_once()
    GlobalHydra.instance().clear()
    hydra = Hydra.create_main_hydra2(task_name="pipeline", config_search_path=create_config_search_path(str(ROOT / "conf")))
    master = hydra.compose_config("config", [f"paths.artifacts={tmp_path}"], run_mode=RunMode.MULTIRUN)
    loader = hydra.config_loader
    compositions = []
    compose = loader.load_configuration

    def counted(*args, **kwargs):
        compositions.append(kwargs.get("overrides"))
        return compose(*args, **kwargs)

    loader.load_configuration = counted       # this loader only: each call is one composition
    yield loader, master, compositions
    GlobalHydra.instance().clear()


def test_hydra_still_has_the_method_it_wraps():
    from hydra._internal.config_loader_impl import ConfigLoaderImpl
    compose_each_job_once()
    compose_each_job_once()                    # idempotent: wrapped once
    wrapped = ConfigLoaderImpl.load_sweep_config
    assert wrapped.composes_once and not getattr(wrapped.__wrapped__, "composes_once", False)
    assert list(inspect.signature(wrapped.__wrapped__).parameters) == ["self", "master_config", "sweep_overrides"]
    from hydra._internal.core_plugins.basic_launcher import BasicLauncher
    assert f"{BasicLauncher.__module__}.{BasicLauncher.__qualname__}" == BASIC_LAUNCHER


def test_the_second_request_for_a_job_reuses_the_first_composition(sweep_loader):
    loader, master, compositions = sweep_loader
    assert master.hydra.launcher._target_ == BASIC_LAUNCHER
    validated = loader.load_sweep_config(master, ["mc.seed=3", "mc.runs=2"])        # the sweeper's check
    as_validated = OmegaConf.to_yaml(validated)
    master._metadata.resolver_cache["now"] = {"%H": "12"}    # e.g. the sweep folder's ${now:} resolved since
    launched = loader.load_sweep_config(master, ["mc.seed=3", "mc.runs=2"])         # the launcher's request
    assert len(compositions) == 1
    assert launched is not validated and OmegaConf.to_yaml(launched) == OmegaConf.to_yaml(validated)
    assert launched.mc.seed == 3 and launched.mc.runs == 2
    assert OmegaConf.get_cache(launched) == {"now": {"%H": "12"}}           # copied at the launch, as Hydra does
    with open_dict(launched):
        launched.hydra.job.num = 7                       # the launcher writes into its copy only
    assert OmegaConf.to_yaml(validated) == as_validated

    fresh = loader.load_sweep_config(master, ["mc.seed=3", "mc.runs=2"])    # handed over once: composed again
    assert len(compositions) == 2
    assert OmegaConf.to_yaml(fresh) == OmegaConf.to_yaml(validated)
    assert OmegaConf.to_container(fresh.mc, resolve=True) == OmegaConf.to_container(launched.mc, resolve=True)


def test_other_launchers_compose_as_hydra_does(sweep_loader):
    loader, master, compositions = sweep_loader
    with open_dict(master):
        master.hydra.launcher._target_ = "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher"
    for _ in range(2):
        loader.load_sweep_config(master, ["mc.seed=4"])
    assert len(compositions) == 2 and not loader.__dict__.get("_pipeline_composed_once")


def test_a_sweep_composes_each_job_once(tmp_path):
    """`python -m pipeline -m`: Hydra composes the multirun's own config twice (to read its mode, then
    to run it), then here each job once: 5 compositions for 3 jobs (8 without compose_once)."""
    driver = ("import runpy, sys\n"
              "from hydra._internal.config_loader_impl import ConfigLoaderImpl\n"
              "compose = ConfigLoaderImpl.load_configuration\n"
              "calls = []\n"
              "def counted(self, *a, **k):\n"
              "    calls.append(1)\n"
              "    return compose(self, *a, **k)\n"
              "ConfigLoaderImpl.load_configuration = counted\n"
              "sys.argv = ['pipeline', *sys.argv[1:]]\n"
              "try:\n"
              "    runpy.run_module('pipeline', run_name='__main__', alter_sys=True)\n"
              "finally:\n"
              "    print('compositions', len(calls), file=sys.stderr)\n")
    env = {**os.environ, "HYDRA_FULL_ERROR": "0", "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-c", driver, "-m", f"paths.artifacts={tmp_path}", "mc.seed=1,2,3",
                           "mc.runs=2", "scenario.steps=20", "record.enabled=false"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "compositions 5" in proc.stderr, proc.stderr[-1000:]
    (sweep,) = (tmp_path / "multirun").iterdir()
    seeds = [OmegaConf.load(sweep / str(j) / ".hydra" / "config.yaml").mc.seed for j in range(3)]
    numbers = [OmegaConf.load(sweep / str(j) / ".hydra" / "hydra.yaml").hydra.job.num for j in range(3)]
    assert seeds == [1, 2, 3] and numbers == [0, 1, 2]
