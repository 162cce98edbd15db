"""A stored run's config.yaml, read as input: the classes it names under the names they had when it ran.

Modules move (issue 39 put the pipeline's modules into sub-packages); a stored run keeps the
``_target_`` names of its day. ``stored_config`` reads a run folder's config.yaml and maps every
moved module path to where it is now, logging one line per name it maps, so old runs stay
readable (``python -m pipeline.recompute``, ``python -m pipeline.report``). Filter families moved
too (``filters/imm.py`` -> ``filters/imm/``), but each family's package keeps the old names
(``filters.imm.FSIMM``), so they need no entry here.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Sequence

from omegaconf import DictConfig, ListConfig, OmegaConf

log = logging.getLogger("pipeline")

# old module -> its module now
MOVED_MODULES = {
    "pipeline.blueprint_parts": "pipeline.views.blueprints",
    "pipeline.bounds": "pipeline.evaluation.bounds",
    "pipeline.checks": "pipeline.run.checks",
    "pipeline.colours": "pipeline.views.colours",
    "pipeline.config": "pipeline.run.config",
    "pipeline.environment": "pipeline.run.environment",
    "pipeline.estimates": "pipeline.storage.estimates",
    "pipeline.evaluate": "pipeline.evaluation.evaluate",
    "pipeline.faults": "pipeline.evaluation.faults",
    "pipeline.fingerprint": "pipeline.storage.fingerprint",
    "pipeline.folders": "pipeline.launch.folders",
    "pipeline.kernels": "pipeline.evaluation.kernels",
    "pipeline.logs": "pipeline.launch.logs",
    "pipeline.memory": "pipeline.run.memory",
    "pipeline.metrics": "pipeline.evaluation.metrics",
    "pipeline.objective": "pipeline.launch.objective",
    "pipeline.process": "pipeline.run.process",
    "pipeline.progress": "pipeline.run.progress",
    "pipeline.recording": "pipeline.views.recording",
    "pipeline.runner": "pipeline.run.runner",
    "pipeline.schemas": "pipeline.storage.schemas",
    "pipeline.seeding": "pipeline.run.seeding",
    "pipeline.stages": "pipeline.run.stages",
    "pipeline.store": "pipeline.storage.store",
    "pipeline.studies.mie_los.sensor": "pipeline.sensors",
    "pipeline.sweep_recording": "pipeline.views.sweep_recording",
    "pipeline.tables": "pipeline.views.tables",
    "pipeline.track": "pipeline.studies.single_target",
    "pipeline.uncertainty": "pipeline.evaluation.uncertainty",
}


def current_target(target: str) -> str:
    """``target`` under today's module names (unchanged when its module did not move)."""
    for old in sorted(MOVED_MODULES, key=len, reverse=True):
        if target == old or target.startswith(old + "."):
            return MOVED_MODULES[old] + target[len(old):]
    return target


def upgrade_targets(node: Any, where: str = "") -> list[tuple[str, str, str]]:
    """Rewrite, in place, every ``_target_`` under ``node`` whose module moved; (key, old, new) each."""
    changed: list[tuple[str, str, str]] = []
    if isinstance(node, DictConfig):
        for key in list(node.keys()):
            value = node._get_node(key)._value() if key == "_target_" else node.get(key)   # no interpolation
            path = f"{where}.{key}" if where else str(key)
            if key == "_target_" and isinstance(value, str):
                new = current_target(value)
                if new != value:
                    node[key] = new
                    changed.append((path, value, new))
            elif isinstance(value, (DictConfig, ListConfig)):
                changed += upgrade_targets(value, path)
    elif isinstance(node, ListConfig):
        for i, item in enumerate(node):
            if isinstance(item, (DictConfig, ListConfig)):
                changed += upgrade_targets(item, f"{where}[{i}]")
    return changed


def stored_config(run_dir: Path) -> DictConfig:
    """``run_dir/config.yaml`` with moved classes under their current names (one log line each)."""
    cfg = OmegaConf.load(Path(run_dir) / "config.yaml")
    for key, old, new in upgrade_targets(cfg):
        log.info("%s: %s names %s, which is %s now", Path(run_dir) / "config.yaml", key, old, new)
    return cfg


def check_stored_packages(cfg: DictConfig, run_dir: Path, trusted: Sequence[str], how: str) -> None:
    """Refuse (ConfigError) a stored config whose ``plugins.packages`` lists a package the command did
    not name itself (``trusted``; ``how`` says how to name them, its ``{packages}`` replaced by those
    left, e.g. ``--plugins {packages}``).

    A stored run folder is input: its config.yaml can be edited or come from elsewhere, and a package
    it lists would let any class of that package be built (``plugins.packages: [logging]`` with a
    ``report.tables`` node of ``logging.FileHandler`` truncated a file under ``python -m
    pipeline.recompute``). What it may build without a word from the user is what any config may:
    this project's classes and Stone Soup's components (pipeline.run.config.check_targets)."""
    from pipeline.errors import ConfigError

    listed = OmegaConf.select(cfg, "plugins.packages", default=None)
    if listed is None:
        return
    names = [str(p) for p in listed] if isinstance(listed, ListConfig) else None
    untrusted = [p for p in names if p not in set(trusted)] if names is not None else None
    if untrusted == []:
        return
    shown = names if names is not None else listed
    raise ConfigError(f"{Path(run_dir) / 'config.yaml'}: plugins.packages: {shown!r} is not taken from a stored run "
                      f"folder: the folder is input, and a package its config lists could have any of its classes "
                      f"built. Without your word a stored run builds only this project's classes and Stone Soup's "
                      f"components; if you trust the package(s) {untrusted if untrusted is not None else shown!r} "
                      f"(your own filters, say), name them: "
                      f"{how.replace('{packages}', ' '.join(untrusted if untrusted is not None else []))}.")
