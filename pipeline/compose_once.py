"""A sweep run by Hydra's basic launcher composes each job's config once instead of twice.

Hydra's sweepers (the basic one and Optuna's) compose every job of a batch before launching any
(``Sweeper.validate_batch_is_legal``: a bad override stops the sweep before its first job), and the
basic launcher then composes each job again as it runs it, from the same files and overrides. A
composition of this project's config takes ~0.3 s (~20 files read and merged by Hydra and OmegaConf;
measured in a 10-job sweep), about a third of a small job's own time, so the second one is the
largest per-job cost such a sweep pays besides the job.

``compose_each_job_once`` makes the validation's composition the one the job runs: Hydra's config
loader keeps each job's validated config (pickled, ~40-50 kB) until the launcher asks for it, and
hands it over as a fresh object, with the resolver cache copied from the sweep's config at that
moment, as Hydra's own ``load_sweep_config`` does (``${now:}`` gives every job the sweep folder's
time). The config a job runs is the one composed when its batch was validated, so a config file
edited while the sweep runs no longer changes its later jobs.

Only under the basic launcher, which composes in the process that validated: the other launchers
(joblib, isolated, Ray, SLURM) compose in their workers, where nothing validated is at hand, and
are left as Hydra runs them. ``load_sweep_config`` is a method of Hydra's internal config loader;
``hydra-core`` is pinned (pyproject.toml), and tests/test_compose_once.py checks the method it
wraps, that a sweep composes each job once, and that a job's config equals a fresh composition.
"""

from __future__ import annotations

import functools
import pickle
from typing import Any

from omegaconf import DictConfig, OmegaConf

BASIC_LAUNCHER = "hydra._internal.core_plugins.basic_launcher.BasicLauncher"
_HELD = "_pipeline_composed_once"        # the loader's attribute: overrides -> (sweep config, pickled job config)


def compose_each_job_once() -> None:
    """Wrap Hydra's ``ConfigLoaderImpl.load_sweep_config`` (once per process; see the module's doc)."""
    from hydra._internal.config_loader_impl import ConfigLoaderImpl

    compose = ConfigLoaderImpl.load_sweep_config
    if getattr(compose, "composes_once", False):
        return

    @functools.wraps(compose)
    def load_sweep_config(self: Any, master_config: DictConfig, sweep_overrides: list[str]) -> DictConfig:
        if OmegaConf.select(master_config, "hydra.launcher._target_") != BASIC_LAUNCHER:
            return compose(self, master_config, sweep_overrides)
        held: dict[tuple[str, ...], tuple[DictConfig, bytes]] = self.__dict__.setdefault(_HELD, {})
        key = tuple(sweep_overrides)
        kept = held.pop(key, None)
        if kept is not None and kept[0] is master_config:
            config = pickle.loads(kept[1])
            OmegaConf.copy_cache(from_config=master_config, to_config=config)   # as load_sweep_config does
            return config
        config = compose(self, master_config, sweep_overrides)
        try:
            held[key] = (master_config, pickle.dumps(config, protocol=pickle.HIGHEST_PROTOCOL))
        except (pickle.PicklingError, TypeError, AttributeError):
            pass                           # a value that does not pickle: the launcher composes again
        return config

    load_sweep_config.composes_once = True          # type: ignore[attr-defined]
    ConfigLoaderImpl.load_sweep_config = load_sweep_config
