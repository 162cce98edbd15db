"""Config checks at the stage boundary, and instantiation with errors that name the config key.

Hydra itself rejects unknown config groups/options (listing the available ones); everything it
cannot know (value ranges, cross-key consistency, what a ``_target_`` constructor refuses) is
checked here before any stage runs.
"""

from __future__ import annotations

import collections.abc
import inspect
import json
import numbers
import re
import types
import typing
from pathlib import Path
from typing import Any

import numpy as np
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, ListConfig, OmegaConf

from pipeline.errors import ConfigError


SEED_MAX = 2**63 - 1       # mc.seed is an Int64 column of the summary and every config-keyed table


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


# a variant key names files (estimates/<key>.parquet) and recording paths: letters, digits, _ and -,
# starting with a letter or digit, so that no key can name a path outside the run folder
SAFE_KEY = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,63}")


def check_variant_keys(keys: list[str]) -> None:
    bad = [k for k in keys if not SAFE_KEY.fullmatch(str(k))]
    if bad:
        raise ConfigError(f"filters: variant key(s) {bad} are not allowed. A variant key names its files "
                          f"(estimates/<key>.parquet), so it must be 1-64 letters, digits, '_' or '-', starting "
                          f"with a letter or digit (e.g. filters.my_kf); the display name (filters.<key>.name) "
                          f"may be any text.")


def check_experiment_name(name: object) -> None:
    """``experiment_name`` names the run folder (``runs/<experiment_name>/<time>`` under paths.artifacts)
    and labels every table: the same characters as a variant key. ``''`` ran unlabelled, and
    ``../../escaped`` wrote outside paths.artifacts."""
    if isinstance(name, str) and SAFE_KEY.fullmatch(name):
        return
    why = ("'' leaves the run unlabelled" if name == "" else
           "a '/' or '..' places the run folder outside paths.artifacts" if isinstance(name, str) and
           ("/" in name or "\\" in name or ".." in name) else "it is not such a name")
    raise ConfigError(f"experiment_name: {name!r} is not allowed ({why}). It names the run folder "
                      f"(runs/<experiment_name>/<time> under paths.artifacts) and labels every table, so it must be "
                      f"1-64 letters, digits, '_' or '-', starting with a letter or digit (e.g. experiment_name=my_study).")


def selected_variants(cfg: DictConfig) -> list[str]:
    available = list(cfg.filters.keys()) if cfg.get("filters") else []
    check_variant_keys(available)
    wanted = cfg.get("variants")
    if wanted is None:
        return available
    if isinstance(wanted, str):
        wanted = [wanted]
    if len(wanted) == 0:
        raise ConfigError(f"variants: [] selects no variant, so there would be nothing to filter. Leave variants unset "
                          f"(null) to run all of {available}, or name some, e.g. variants=[{available[0] if available else 'KEY'}].")
    unknown = [v for v in wanted if v not in available]
    if unknown:
        raise ConfigError(
            f"variants: {list(wanted)} names unknown variant(s) {unknown}. The variants of experiment "
            f"'{cfg.get('experiment_name')}' are {available}; add one with +filter@filters.NAME=<file in conf/filter> "
            f"or leave variants unset (null) to run them all.")
    return list(wanted)


MIN_RESAMPLES = 100        # a 95 % BCa interval reads its ends 2.5 % in: below ~100 resamples that is a couple of draws


def check_uncertainty(cfg: DictConfig) -> None:
    """``uncertainty.confidence`` in (0, 1) and ``uncertainty.bootstrap_resamples`` an integer >= 100.
    A confidence of 0 made every interval a point and every paired difference resolved (the interval
    excluding its own estimate), 1 made them infinite, 1.5 was taken; 0 resamples failed in the
    bootstrap with a traceback after every track stage had run."""
    uncertainty = cfg.get("uncertainty") or {}
    confidence = uncertainty.get("confidence", 0.95)
    if isinstance(confidence, bool) or not isinstance(confidence, (int, float)) or not 0 < confidence < 1:
        raise ConfigError(f"uncertainty.confidence: {confidence!r} is not allowed; the confidence of every interval "
                          f"and paired comparison must be a number strictly between 0 and 1 (e.g. 0.95 for 95 %): "
                          f"0 would make every interval its point (and every difference 'resolved'), 1 would make "
                          f"every interval infinite.")
    resamples = uncertainty.get("bootstrap_resamples", 2000)
    if not _is_int(resamples) or resamples < MIN_RESAMPLES:
        raise ConfigError(f"uncertainty.bootstrap_resamples: {resamples!r} is not allowed; the number of bootstrap "
                          f"resamples of the runs must be an integer >= {MIN_RESAMPLES} (default 2000; a BCa "
                          f"interval reads its ends from the tails of the resamples, which fewer cannot resolve).")


def validate(cfg: DictConfig) -> None:
    """Reject bad values before any stage runs."""
    if not OmegaConf.is_missing(cfg, "experiment_name"):
        check_experiment_name(cfg.get("experiment_name"))
    check_targets(cfg)             # before anything imports a _target_ (the kind and type checks do)
    if cfg.get("filters") and cfg.get("sensors") is not None:
        check_measurement_kinds(cfg, selected_variants(cfg))
    resolved = check_interpolations(cfg)      # one resolution of the whole config serves the next two
    check_finite(resolved)
    missing = sorted(missing_keys(resolved))
    if missing:
        raise ConfigError(f"missing mandatory config value(s) {missing}: select an experiment with "
                          f"experiment=NAME (see conf/experiment/) or set them on the command line.")
    for key in ("record.enabled", "cache.enabled"):
        value = OmegaConf.select(cfg, key)
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: {value!r} is not allowed; it must be true or false (a quoted 'false' is a "
                              f"string, and any non-empty string or non-zero number used to count as true).")
    publish = OmegaConf.select(cfg, "cache.publish", default="copy")
    if publish not in ("copy", "link"):
        raise ConfigError(f"cache.publish: {publish!r} is not allowed; it must be 'copy' (each run folder holds "
                          f"its own copy of its stage tables; a reflink where the file system has them) or 'link' "
                          f"(hard links into the cache: no extra space, but damage to a cache file reaches "
                          f"every run that published it).")
    runs = cfg.mc.runs
    if not _is_int(runs) or runs < 1:
        raise ConfigError(f"mc.runs: {runs!r} is not allowed; the number of Monte Carlo runs must be an integer >= 1.")
    seed = cfg.mc.seed
    if not _is_int(seed) or not 0 <= seed <= SEED_MAX:
        raise ConfigError(f"mc.seed: {seed!r} is not allowed; the seed must be an integer from 0 to {SEED_MAX} "
                          f"(2**63 - 1: it is stored as a 64-bit column of every table).")
    check_uncertainty(cfg)
    chunk = cfg.mc.get("chunk_runs")
    if chunk is not None and (not _is_int(chunk) or chunk < 1):
        raise ConfigError(f"mc.chunk_runs: {chunk!r} is not allowed; it must be an integer >= 1 (runs filtered "
                          f"together) or null (all runs at once). Results do not depend on it.")
    timing = cfg.get("timing") or {}
    passes, budget = timing.get("passes", 1), timing.get("budget_s", 0.0)
    if not _is_int(passes) or passes < 1:
        raise ConfigError(f"timing.passes: {passes!r} is not allowed; it must be an integer >= 1 (the most filtering "
                          f"passes timed per variant for its compute time; the track stage's own pass counts).")
    if isinstance(budget, bool) or not isinstance(budget, (int, float)) or not budget >= 0:
        raise ConfigError(f"timing.budget_s: {budget!r} is not allowed; it must be a number of seconds >= 0 (the time "
                          f"a variant's timed passes may take; 0: no pass beyond the track stage's own).")
    if not cfg.get("filters"):
        raise ConfigError(f"filters: experiment '{cfg.experiment_name}' defines no filter variants; add at least "
                          f"one node with a _target_ under filters (e.g. +filter@filters.fsimm=fsimm).")
    for key, node in cfg.filters.items():
        if not isinstance(node, DictConfig) or "_target_" not in node:
            raise ConfigError(f"filters.{key}: {node!r} is not a variant node; each variant needs a _target_ "
                              f"naming its estimator class (see conf/filter/).")
    selected_variants(cfg)
    record = cfg.record
    record_runs = record.runs
    if isinstance(record_runs, int):
        record_runs = [record_runs]
    if not isinstance(record_runs, (list, ListConfig)) or not all(_is_int(r) for r in record_runs):
        raise ConfigError(f"record.runs: {record_runs!r} must be a list of run indices, e.g. [0] or [0,3].")
    bad = [r for r in record_runs if not 0 <= r < runs]
    if bad:
        raise ConfigError(f"record.runs: {list(record_runs)} holds run index(es) {bad} outside the {runs} Monte Carlo "
                          f"runs; allowed indices are 0..{runs - 1} (mc.runs={runs}).")
    twice = sorted({r for r in record_runs if list(record_runs).count(r) > 1})
    if twice:
        raise ConfigError(f"record.runs: {list(record_runs)} lists run(s) {twice} more than once; each recorded run "
                          f"is listed once, e.g. record.runs={sorted(set(record_runs))}.")
    windows = _check_windows(cfg, "windows")
    for name in _check_windows(cfg, "count_windows"):
        if name in windows:
            raise ConfigError(f"metrics.count_windows.{name}: the name is also a key of metrics.windows; give the "
                              f"count window another name (summary rows are keyed by window name).")
    reached = cfg.metrics.get("group_reached")
    if reached:
        groups = list(cfg.models.groups.keys()) if cfg.get("models") and "groups" in cfg.models else []
        if reached.get("group") not in groups:
            raise ConfigError(f"metrics.group_reached.group: {reached.get('group')!r} is not a model group of "
                              f"this experiment; groups are {groups} (or set metrics.group_reached=null).")
        if not _is_int(reached.get("by_step")) or reached.by_step < 0:
            raise ConfigError(f"metrics.group_reached.by_step: {reached.get('by_step')!r} must be a step index >= 0.")
    ref = cfg.metrics.get("reference_variant")
    if ref is not None and ref not in cfg.filters:
        raise ConfigError(f"metrics.reference_variant: {ref!r} is not a variant of this experiment; "
                          f"choose one of {list(cfg.filters.keys())} or null.")
    compute_ref = compute_reference(cfg)
    if compute_ref is not None and compute_ref not in cfg.filters:
        raise ConfigError(f"metrics.compute_reference: {compute_ref!r} is not a variant of this experiment; "
                          f"choose one of {list(cfg.filters.keys())}, or null to print compute seconds only.")


def compute_reference(cfg: DictConfig) -> str | None:
    """The variant whose compute time the others are given as % of: ``metrics.compute_reference`` where
    the experiment sets it (null: none, seconds only), else ``metrics.reference_variant``, the reference
    of the paired comparisons."""
    metrics = cfg.get("metrics") or {}
    if "compute_reference" in metrics:
        return metrics.get("compute_reference")
    return metrics.get("reference_variant")


OBJECTIVE_DIRECTIONS = ("minimize", "maximize")
OBJECTIVE_EXAMPLE = "e.g. objective={variant: vsimm, series: acceleration_rmse_x, window: after_switch, direction: minimize}"


def summary_windows(cfg: DictConfig) -> list[str]:
    """The window names the config gives the summary's rows: metrics.windows, metrics.count_windows and
    the group-reached row's '<group> by step <k>' (a study's own rows may add others)."""
    metrics = cfg.get("metrics") or {}
    names = [str(k) for k in (metrics.get("windows") or {})] + [str(k) for k in (metrics.get("count_windows") or {})]
    reached = metrics.get("group_reached")
    if reached:
        names.append(f"{reached.get('group')} by step {reached.get('by_step')}")
    return names


def check_objective(cfg: DictConfig, variants: list[str]) -> None:
    """``objective``: null, or the one summary value a parameter search optimises (the task function
    returns it). Checked once the study is built (its metric names are registered then), before any
    stage runs: a typo must not cost a whole search of failed trials."""
    from pipeline.evaluation.metrics import lookup, registered
    objective = cfg.get("objective")
    if objective is None:
        return
    if not isinstance(objective, DictConfig):
        raise ConfigError(f"objective: {objective!r} is not allowed; it must be null (no objective) or a mapping "
                          f"naming one value of the summary, {OBJECTIVE_EXAMPLE}.")
    unknown = sorted(set(objective.keys()) - {"variant", "series", "window", "direction"})
    if unknown:
        raise ConfigError(f"objective: key(s) {unknown} are not allowed; the objective takes variant, series, window "
                          f"and direction, {OBJECTIVE_EXAMPLE}.")
    variant = objective.get("variant")
    if variant not in variants:
        chosen = cfg.get("variants")
        chosen = "null" if chosen is None else list(chosen) if isinstance(chosen, ListConfig) else repr(chosen)
        raise ConfigError(f"objective.variant: {variant!r} is not allowed; it must be the key of a variant this job "
                          f"runs, one of {variants} (experiment '{cfg.get('experiment_name')}' with variants={chosen}).")
    series = objective.get("series")
    if not isinstance(series, str) or lookup(series) is None:
        names, patterns = registered()
        raise ConfigError(f"objective.series: {series!r} is not allowed; it must name a summary series of the metric "
                          f"registry (pipeline.evaluation.metrics): one of {names}" + (f", or a name matching one of the patterns "
                          f"{patterns}" if patterns else "") + ".")
    window = objective.get("window")
    windows = summary_windows(cfg)
    if window is not None and window not in windows:
        raise ConfigError(f"objective.window: {window!r} is not allowed; it must be one of the summary windows this "
                          f"config defines, {windows}, or null for a series summarised over no window (compute_seconds, "
                          f"the fault counts). Windows a study adds to its own rows (e.g. sonobuoy's 'final') cannot "
                          f"be checked before the run and are not objectives yet.")
    direction = objective.get("direction")
    if direction not in OBJECTIVE_DIRECTIONS:
        raise ConfigError(f"objective.direction: {direction!r} is not allowed; it must be one of "
                          f"{list(OBJECTIVE_DIRECTIONS)} (what the search does with the value; with hydra/sweeper=optuna "
                          f"the sweeper's direction follows it).")


def _check_windows(cfg: DictConfig, key: str) -> dict:
    """metrics.<key>: name -> [first_step, last_step] with 0 <= first_step <= last_step."""
    windows = cfg.metrics.get(key) or {}
    for name, bounds in windows.items():
        if (not isinstance(bounds, (list, ListConfig)) or len(bounds) != 2 or not all(_is_int(b) for b in bounds)
                or bounds[0] > bounds[1] or bounds[0] < 0):
            raise ConfigError(f"metrics.{key}.{name}: {bounds!r} must be [first_step, last_step] with "
                              f"0 <= first_step <= last_step.")
    return windows


def missing_keys(node: Any, key: str = "") -> list[str]:
    """The keys of every mandatory value left unset (``???``, OmegaConf's MISSING) in a resolved config,
    named as ``OmegaConf.missing_keys`` names them (``a.b``, ``a[0].b``), without its second walk of
    the config node by node (18 % of ``prepare`` under the profiler)."""
    if isinstance(node, dict):
        children = [(f"{key}.{k}" if key else str(k), v) for k, v in node.items()]
    elif isinstance(node, list):
        children = [(f"{key}[{i}]", v) for i, v in enumerate(node)]
    else:
        return []
    found = []
    for child_key, value in children:
        if isinstance(value, str) and value == "???":
            found.append(child_key)
        else:
            found += missing_keys(value, child_key)
    return found


def check_finite(resolved: dict) -> None:
    """Every number of an experiment is finite: a NaN initial state ran to the end with every estimate
    NaN and no fault flagged; an infinite noise or bound is no setting either (null says 'none').
    ``resolved``: the config resolved to plain containers (``check_interpolations`` returns it)."""
    def walk(node: Any, key: str) -> None:
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{key}.{k}" if key else str(k))
        elif isinstance(node, list):
            for i, v in enumerate(node):
                walk(v, f"{key}[{i}]")
        elif isinstance(node, float) and not np.isfinite(node):
            raise ConfigError(f"{key}: {node!r} is not allowed; every number of an experiment must be finite "
                              f"(use null where a setting takes 'none', e.g. faults.nees_bound=null).")
    walk(resolved, "")


def check_interpolations(cfg: DictConfig) -> dict:
    """An interpolation (``${models}``) whose key this experiment does not define: one paragraph
    naming the key, instead of OmegaConf's traceback from deep inside the first stage to read it.
    Returns the resolved config as plain containers."""
    from omegaconf.errors import InterpolationResolutionError

    try:
        return OmegaConf.to_container(cfg, resolve=True)
    except InterpolationResolutionError as exc:
        key = getattr(exc, "full_key", None) or "?"
        raw = OmegaConf.to_container(cfg, resolve=False)
        value: Any = raw
        for part in str(key).split("."):
            value = value.get(part) if isinstance(value, dict) else None
        reason = str(exc).strip().splitlines()[0]
        raise ConfigError(
            f"{key}: {value!r} cannot be resolved ({reason}). It refers to a config node this experiment does not "
            f"define: a config file written for another study may need that study's nodes (the IMMs' "
            f"'${{models}}' is the model set of conf/models/, e.g. +models=acceleration13), or set {key} on the "
            f"command line.") from None


PROJECT_PACKAGES = ("pipeline", "filters")
# Stone Soup's components (the [stonesoup] extra, pipeline/stonesoup): models, filters' predictors and
# updaters, initiators, resamplers, simulators and their types only build objects, so a config may name
# them without listing anything. Its readers, writers (a YAMLWriter opens its file when built), plotters
# and trackers stay out: list `stonesoup` in plugins.packages to allow every class of it.
COMPONENT_PACKAGES = ("stonesoup.models", "stonesoup.predictor", "stonesoup.updater", "stonesoup.initiator",
                      "stonesoup.resampler", "stonesoup.regulariser", "stonesoup.simulator", "stonesoup.types",
                      "stonesoup.measures", "stonesoup.hypothesiser", "stonesoup.dataassociator", "stonesoup.deleter",
                      "stonesoup.mixturereducer")
# the optional extra whose install provides a package a _target_ may name (for the message when it is missing)
EXTRA_OF_PACKAGE = {"stonesoup": "stonesoup"}
DOTTED_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)+")


def allowed_packages(cfg: DictConfig) -> tuple[str, ...]:
    """This project's packages, Stone Soup's component packages and those the user lists in
    ``plugins.packages`` (a package, or a dotted sub-package such as ``stonesoup.tracker``)."""
    listed = OmegaConf.select(cfg, "plugins.packages", default=None)
    if listed is None:
        return PROJECT_PACKAGES + COMPONENT_PACKAGES
    if not isinstance(listed, ListConfig) or not all(isinstance(p, str) and all(part.isidentifier() for part in
                                                                                 p.split(".")) for p in listed):
        raise ConfigError(f"plugins.packages: {listed!r} is not allowed; it must be a list of package names whose "
                          f"classes a config may name with _target_, e.g. plugins.packages=[mytrack].")
    return PROJECT_PACKAGES + COMPONENT_PACKAGES + tuple(str(p) for p in listed)


def _inside(target: str, packages: tuple[str, ...]) -> bool:
    return any(target == p or target.startswith(p + ".") for p in packages)


def _target_nodes(node: Any, key: str) -> typing.Iterator[tuple[str, Any]]:
    """(dotted key, value) of every ``_target_`` in a config tree, interpolations resolved."""
    if isinstance(node, DictConfig):
        for name in node.keys():
            child = node._get_node(name)
            if name == "_target_":
                yield f"{key}._target_" if key else "_target_", node.get(name)
            elif isinstance(child, (DictConfig, ListConfig)) or OmegaConf.is_interpolation(node, name):
                try:
                    value = node.get(name)
                except Exception:  # noqa: BLE001 - unresolvable: check_interpolations names it
                    continue
                yield from _target_nodes(value, f"{key}.{name}" if key else str(name))
    elif isinstance(node, ListConfig):
        for i, child in enumerate(node):
            yield from _target_nodes(child, f"{key}[{i}]")


# The project's contracts (pipeline.contract, filters.base, pipeline.views.tables, pipeline.evaluation.bounds),
# each told by the hook the runner calls on it: a class that has none of them is no component, whatever
# package defines it (pipeline.storage.store.TableStream makes a file beside any path it is given).
CONTRACT_HOOKS = (("track_input", "a study (pipeline.contract.Study)"),
                  ("run", "a filter or tracker (filters.base.Estimator, filters.multitarget.base.MultiTargetTracker)"),
                  ("generate", "a scenario (pipeline.contract.Scenario)"),
                  ("measure", "a sensor (pipeline.contract.Sensor)"),
                  ("render", "a report table (pipeline.views.tables.ReportTable)"),
                  ("position_bound", "a bound (pipeline.evaluation.bounds)"),
                  ("model_index", "a model set (filters.models.AccelerationModelSet)"))
CONTRACTS = ", ".join(what for _, what in CONTRACT_HOOKS) + ", a Hydra callback (under hydra.callbacks) or a " \
    "Stone Soup component (a stonesoup.base.Base, or one of its array types)"


def implemented_contract(cls: type) -> str | None:
    """The project contract ``cls`` implements (CONTRACT_HOOKS, a Hydra callback, a Stone Soup
    component), None for none."""
    from hydra.experimental.callback import Callback

    for hook, what in CONTRACT_HOOKS:
        if callable(getattr(cls, hook, None)):
            return what
    if issubclass(cls, Callback):
        return "a Hydra callback"
    stonesoup_base = any(c.__module__ == "stonesoup.base" and c.__name__ == "Base" for c in cls.__mro__)
    if stonesoup_base or (cls.__module__.startswith("stonesoup.types.") and issubclass(cls, np.ndarray)):
        return "a Stone Soup component"
    return None


def check_target(key: str, target: Any, allowed: tuple[str, ...], listed: list[str]) -> type:
    """The class one ``_target_`` names (``key`` its dotted key), or ConfigError: the name inside
    ``allowed`` before anything is imported; then the object a class (or a class's constructor
    method), *defined* inside ``allowed`` (its ``__module__``: a name reached through an allowed
    module, ``pipeline.run.runner.logging.FileHandler``, is the class of the module it comes from),
    implementing one of the project's contracts (``implemented_contract``)."""
    from hydra.utils import get_object      # resolves a dotted name as instantiate() does

    fix = (f"a _target_ must name a class of this project ({', '.join(PROJECT_PACKAGES)}), of Stone Soup's "
           f"components ({', '.join(COMPONENT_PACKAGES)}) or of a package you list in plugins.packages "
           f"(now {listed}), e.g. plugins.packages=[mytrack] for _target_: mytrack.cv.MyFilter")
    if not isinstance(target, str) or not DOTTED_NAME.fullmatch(target):
        raise ConfigError(f"{key}: {target!r} is not allowed; {fix}.")
    if not _inside(target, allowed):
        raise ConfigError(f"{key}: {target!r} is not allowed (nothing was imported); {fix}.")
    try:
        obj = get_object(target)
    except Exception as exc:  # noqa: BLE001 - any import failure: the user's name is wrong
        top = target.split(".", 1)[0]
        cause = exc.__cause__ if isinstance(exc.__cause__, ImportError) else exc
        missing = getattr(cause, "name", None) or ""
        if isinstance(exc, ImportError) and top in EXTRA_OF_PACKAGE and missing == top:
            extra = EXTRA_OF_PACKAGE[top]
            raise ConfigError(f"{key}: {target!r} cannot be imported: {top} is not installed; it comes with the "
                              f"[{extra}] extra: pip install -e '.[{extra}]'.") from None
        raise ConfigError(f"{key}: {target!r} cannot be imported ({type(exc).__name__}: "
                          f"{str(exc).splitlines()[0] if str(exc) else ''}); it must name a class, e.g. "
                          f"filters.imm.FSIMM.") from None
    constructor = inspect.ismethod(obj) and inspect.isclass(obj.__self__)
    if not (inspect.isclass(obj) or constructor):
        raise ConfigError(f"{key}: {target!r} is a {type(obj).__name__}, not a class; {fix}.")
    cls = obj.__self__ if constructor else obj
    defined = f"{cls.__module__}.{cls.__qualname__}"
    if not _inside(str(cls.__module__), allowed):
        raise ConfigError(f"{key}: {target!r} is not allowed: it is {defined}, defined outside the allowed packages "
                          f"and only reached through {target.rsplit('.', 1)[0]}; {fix}, named where it is defined.")
    if implemented_contract(cls) is None:
        raise ConfigError(f"{key}: {target!r} is not allowed: {defined} implements none of the project's contracts; "
                          f"a _target_ must name a component: {CONTRACTS}.")
    return cls


def check_targets(cfg: DictConfig) -> None:
    """Every ``_target_`` names a class (or a class's constructor method, like
    ``AccelerationModelSet.from_config``) of this project (pipeline, filters) or of a package listed in
    ``plugins.packages``; checked by name *before* anything is imported, then as the imported object:
    where it is defined and which contract it implements (``check_target``).

    instantiate() calls whatever a ``_target_`` names: ``builtins.open`` truncated a file, ``shutil.copyfile``
    wrote one, and even the type check imported a module (``this``) just to read its signature;
    ``pipeline.runner.logging.FileHandler`` and ``stonesoup.types.array.np.memmap`` passed the name
    check as modules' attributes. A config is data: it may only pick among the components that
    implement the project's contracts."""
    allowed = allowed_packages(cfg)
    listed = list(allowed[len(PROJECT_PACKAGES) + len(COMPONENT_PACKAGES):])
    for key, target in _target_nodes(cfg, ""):
        check_target(key, target, allowed, listed)


# What a sweep's launcher and sweeper nodes may name: Hydra builds a launcher or sweeper only from a plugin
# class it registered (hydra_plugins, its core plugins), and the nodes nested in one with it (instantiate is
# recursive): Optuna's sampler (conf/tune/) is the only such node this project's configs have.
HYDRA_PLUGIN_PACKAGES = ("hydra_plugins", "hydra._internal.core_plugins")
SWEEPER_COMPONENT_PACKAGES = ("optuna.samplers",)


def check_hydra_targets(cfg: DictConfig) -> None:
    """What Hydra itself builds from ``cfg.hydra`` before any job runs, checked as every other
    ``_target_`` is (``check_target``): each ``hydra.callbacks`` node a Hydra callback
    (``hydra.experimental.callback.Callback``) defined in this project or a package listed in
    ``plugins.packages``, the nodes nested in it components; ``hydra.launcher._target_`` and
    ``hydra.sweeper._target_`` a name under HYDRA_PLUGIN_PACKAGES (Hydra then takes only a plugin it
    registered under that name), the nodes nested in them Optuna's samplers.

    Hydra instantiates these when a run or sweep starts, before the task function:
    ``'+hydra.callbacks.evil={_target_: logging.FileHandler, filename: F, mode: w}'`` truncated F and the
    job ended 0."""
    from hydra.experimental.callback import Callback
    from hydra.utils import get_object

    hydra_node = cfg.get("hydra")
    if not isinstance(hydra_node, DictConfig):
        return
    allowed = allowed_packages(cfg)
    listed = list(allowed[len(PROJECT_PACKAGES) + len(COMPONENT_PACKAGES):])
    callbacks = hydra_node.get("callbacks")
    for name in (callbacks.keys() if isinstance(callbacks, DictConfig) else ()):
        key, node = f"hydra.callbacks.{name}", callbacks.get(name)
        if node is None:
            continue
        if not isinstance(node, DictConfig) or "_target_" not in node:
            raise ConfigError(f"{key}: {node!r} is not allowed; a callback is a node whose _target_ names a Hydra "
                              f"callback class (e.g. {{_target_: pipeline.launch.folders.OutputFolders}}).")
        for nested_key, target in _target_nodes(node, key):
            cls = check_target(nested_key, target, allowed, listed)
            if nested_key == f"{key}._target_" and not issubclass(cls, Callback):
                raise ConfigError(f"{nested_key}: {target!r} is not allowed: a callback must be a Hydra callback "
                                  f"(a subclass of hydra.experimental.callback.Callback) of this project "
                                  f"({', '.join(PROJECT_PACKAGES)}) or of a package you list in plugins.packages "
                                  f"(now {listed}).")
    for part in ("launcher", "sweeper"):
        node = hydra_node.get(part)
        for key, target in _target_nodes(node, f"hydra.{part}") if isinstance(node, DictConfig) else ():
            if key == f"hydra.{part}._target_":
                if not (isinstance(target, str) and DOTTED_NAME.fullmatch(target) and _inside(target, HYDRA_PLUGIN_PACKAGES)):
                    raise ConfigError(f"{key}: {target!r} is not allowed (nothing was imported); a {part} must be a "
                                      f"Hydra plugin, a class under {' or '.join(HYDRA_PLUGIN_PACKAGES)}: choose one "
                                      f"with hydra/{part}=NAME (e.g. hydra/launcher=isolated, tune=<file in conf/tune>).")
                continue
            if not (isinstance(target, str) and DOTTED_NAME.fullmatch(target)
                    and _inside(target, SWEEPER_COMPONENT_PACKAGES)):
                raise ConfigError(f"{key}: {target!r} is not allowed (nothing was imported); a node inside "
                                  f"hydra.{part} may name only a class of {', '.join(SWEEPER_COMPONENT_PACKAGES)} "
                                  f"(the Optuna sweeper's sampler, e.g. optuna.samplers.TPESampler).")
            try:
                obj = get_object(target)
            except Exception as exc:  # noqa: BLE001 - any import failure: the user's name is wrong
                raise ConfigError(f"{key}: {target!r} cannot be imported ({type(exc).__name__}); it must name a "
                                  f"sampler class, e.g. optuna.samplers.TPESampler (the [tune] extra).") from None
            if not inspect.isclass(obj) or not _inside(str(obj.__module__), SWEEPER_COMPONENT_PACKAGES):
                where = f"{obj.__module__}.{obj.__qualname__}" if inspect.isclass(obj) else f"a {type(obj).__name__}"
                raise ConfigError(f"{key}: {target!r} is not allowed: it is {where}, not a class defined in "
                                  f"{', '.join(SWEEPER_COMPONENT_PACKAGES)} (e.g. optuna.samplers.TPESampler).")


def filter_nodes_in_conf() -> dict[str, tuple[Any, DictConfig]]:
    """conf/filter/<name>.yaml -> (the class its ``_target_`` names, its node), following a file's defaults."""
    from hydra.utils import get_object

    folder = Path(__file__).resolve().parents[2] / "conf" / "filter"
    found = {}
    for path in sorted(folder.glob("*.yaml")):
        node, seen = OmegaConf.load(path), 0
        while "_target_" not in node and node.get("defaults") and seen < 5:
            base = next((d for d in node.defaults if isinstance(d, str) and d != "_self_"), None)
            if base is None:
                break
            node, seen = OmegaConf.load(folder / f"{base}.yaml"), seen + 1
        try:
            found[path.stem] = (get_object(str(node["_target_"])), node)
        except Exception:  # noqa: BLE001 - a broken file is reported when an experiment uses it
            continue
    return found


def filter_classes_in_conf() -> dict[str, Any]:
    """conf/filter/<name>.yaml -> the class its ``_target_`` names (following a file's defaults)."""
    return {name: cls for name, (cls, _) in filter_nodes_in_conf().items()}


def _kinds(filter_class: Any, node: Any) -> frozenset[str]:
    """accepted_kinds from the variant's node; a node the class cannot read counts as none given."""
    from filters.base import accepted_kinds
    try:
        return accepted_kinds(filter_class, node)
    except Exception:  # noqa: BLE001 - build() reports a bad node with its own message
        return accepted_kinds(filter_class)


def check_measurement_kinds(cfg: DictConfig, variants: list[str]) -> None:
    """Refuse, before anything is built or run, a variant whose filter does not take what the
    experiment's sensor produces (filters.base.MEASUREMENT_KINDS): one paragraph naming the variant,
    both kinds and the filters in conf/filter/ that would fit."""
    from hydra.utils import get_object

    from filters.base import MEASUREMENT_KINDS, produced_kind

    try:
        sensor_class = get_object(str(cfg.sensors.get("_target_")))
        produced = produced_kind(sensor_class, cfg.sensors)
    except Exception:  # noqa: BLE001 - build() reports an unknown _target_ or a bad node with its own message
        return
    if produced is None:             # a sensor that declares nothing: the filters find out themselves
        return
    for v in variants:
        target = cfg.filters[v].get("_target_")
        try:
            filter_class = get_object(str(target))
        except Exception:  # noqa: BLE001 - build() reports an unknown _target_ with its own message
            continue
        accepts = _kinds(filter_class, cfg.filters[v])
        if produced in accepts:
            continue
        fitting = sorted(name for name, (cls, node) in filter_nodes_in_conf().items() if produced in _kinds(cls, node))
        declared = "declares" if getattr(filter_class, "accepts", None) is not None else \
            "declares no 'accepts', so it is taken to take a MeasurementSeries:"
        raise ConfigError(
            f"filters.{v}: {target} {declared} {sorted(accepts)} measurements, but this experiment's sensor "
            f"({cfg.sensors.get('_target_')}) produces '{produced}' ({MEASUREMENT_KINDS.get(produced, 'undocumented')}). "
            f"Filters in conf/filter/ that take '{produced}': {fitting or 'none'} (e.g. +filter@filters.{v}="
            f"{fitting[0] if fitting else '<one of yours>'}); or run this filter in an experiment whose sensor produces "
            f"one of {sorted(accepts)}. A filter class says what it takes with a class attribute, e.g. "
            f"accepts = frozenset({{'{produced}'}}).")


def build(node: DictConfig, key: str) -> Any:
    """instantiate() a config node; a constructor's refusal becomes a ConfigError naming the key.

    Before anything is built, every value is checked against its constructor's type annotation
    (``check_types``), so a wrong type or an unknown key is refused with the leaf's dotted key,
    the value and what is allowed, instead of failing deep inside numpy.
    """
    check_types(node, key)
    try:
        return instantiate(node, _convert_="all")
    except InstantiationException as exc:
        cause = exc.__cause__ or exc
        while isinstance(cause, InstantiationException) and cause.__cause__ is not None:
            cause = cause.__cause__
        message = str(cause).strip().splitlines()[0] if str(cause).strip() else type(cause).__name__
        target = node.get("_target_")
        # a value this node takes from elsewhere (${models.process_noise_std}) is fixed where it is set
        sources = [(leaf, source) for leaf, source in interpolated_leaves(node, key)
                   if leaf.rsplit(".", 1)[-1] in message]
        where = " or ".join(source for _, source in sources) if sources else f"the value under '{key}'"
        via = "".join(f" {leaf} is ${{{source}}}: the value was set as {source}." for leaf, source in sources)
        raise ConfigError(f"{key}: {message} (while building {target}).{via} Fix {where} in the experiment "
                          f"config or on the command line.") from None


def interpolated_leaves(node: DictConfig, key: str) -> list[tuple[str, str]]:
    """(dotted leaf, the key it interpolates) for every leaf of ``node`` that is a plain ``${key}``."""
    leaves = flatten(OmegaConf.to_container(node, resolve=False))
    found = [(f"{key}.{leaf}", re.fullmatch(r"\$\{([A-Za-z0-9_.]+)\}", value.strip()))
             for leaf, value in leaves.items() if isinstance(value, str)]
    return [(leaf, match.group(1)) for leaf, match in found if match]


def check_types(node: Any, key: str) -> None:
    """Check a ``_target_`` node's keys and values against its constructor's signature (recursively
    into nested ``_target_`` nodes). Unannotated parameters and types other than numbers, bools,
    strings, Literals, None-unions, sequences and mappings are left to the constructor."""
    if not isinstance(node, DictConfig) or "_target_" not in node:
        return
    target = node.get("_target_")
    parameters, hints = _signature(target, key)
    if parameters is None:
        return
    values = OmegaConf.to_container(node, resolve=True)
    takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values())
    for name, value in values.items():
        if name in ("_partial_", "_recursive_") and not isinstance(value, bool):
            raise ConfigError(f"{key}.{name}: {_short(value)} is not allowed; it must be true or false (Hydra's "
                              f"{name} flag of {target}).")
        if name.startswith("_"):
            continue
        where = f"{key}.{name}"
        if name not in parameters:
            if takes_any:
                continue
            allowed = sorted(n for n, p in parameters.items() if p.kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                                                            inspect.Parameter.KEYWORD_ONLY))
            raise ConfigError(f"{where}: {value!r} is not a parameter of {target}; it takes {allowed}. Remove the "
                              f"key or fix its spelling.")
        if isinstance(node.get(name), DictConfig) and "_target_" in node.get(name):
            check_types(node.get(name), where)
            continue
        hint = hints.get(name)
        problem = None if hint is None else _type_problem(value, hint)
        if problem:
            raise ConfigError(f"{where}: {_short(value)} is not allowed; it must be {problem} (parameter "
                              f"'{name}' of {target}).")


def _signature(target: Any, key: str) -> tuple[dict[str, inspect.Parameter] | None, dict[str, Any]]:
    """The parameters and resolved annotations of a target, following ``**kwargs`` up a class's MRO."""
    from hydra.utils import get_object      # resolves a dotted name as instantiate() does
    try:
        obj = get_object(str(target))
    except Exception as exc:
        raise ConfigError(f"{key}._target_: {target!r} cannot be imported ({type(exc).__name__}); it must name a "
                          f"class or function, e.g. filters.imm.FSIMM.") from None
    functions = [c.__init__ for c in obj.__mro__ if "__init__" in vars(c)] if inspect.isclass(obj) else [obj]
    parameters: dict[str, inspect.Parameter] = {}
    hints: dict[str, Any] = {}
    closed = False
    for fn in functions:
        try:
            signature = inspect.signature(fn)
            resolved = typing.get_type_hints(fn)
        except (TypeError, ValueError, NameError):
            return None, {}
        params = [p for n, p in signature.parameters.items() if n != "self"]
        for p in params:
            if p.kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY):
                parameters.setdefault(p.name, p)
                if p.name in resolved:
                    hints.setdefault(p.name, resolved[p.name])
                elif p.annotation is not inspect.Parameter.empty and not isinstance(p.annotation, str):
                    # a signature built with its types (Stone Soup's components declare theirs so, not
                    # in __annotations__, which get_type_hints reads)
                    hints.setdefault(p.name, p.annotation)
        if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params):
            closed = True
            break
    if not closed:
        parameters["**"] = inspect.Parameter("kwargs", inspect.Parameter.VAR_KEYWORD)
    return parameters, hints


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _type_problem(value: Any, hint: Any) -> str | None:
    """None when ``value`` fits ``hint``; else what is allowed, in words."""
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if hint is Any or hint is inspect.Parameter.empty:
        return None
    if origin in (typing.Union, types.UnionType):
        problems = [_type_problem(value, a) for a in args]
        if any(p is None for p in problems):
            return None
        return " or ".join(dict.fromkeys(p for p in problems if p))
    if hint is type(None):
        return None if value is None else "null"
    if origin is typing.Literal:
        return None if value in args else f"one of {list(args)}"
    if hint is bool:
        return None if isinstance(value, bool) else "true or false"
    if hint is int:
        return None if _is_int(value) else "an integer"
    if hint is float:
        return None if isinstance(value, (int, float)) and not isinstance(value, bool) else "a number"
    if hint is str:
        return None if isinstance(value, str) else "a string"
    if isinstance(hint, type) and issubclass(hint, numbers.Real):       # e.g. Stone Soup's Probability
        return None if isinstance(value, (int, float)) and not isinstance(value, bool) else "a number"
    if origin in (list, tuple, collections.abc.Sequence) or hint in (list, tuple):
        if not isinstance(value, (list, tuple)):
            return f"a list{_of(args)}"
        item = args[0] if args else Any
        for element in value:
            problem = _type_problem(element, item)
            if problem:
                return f"a list{_of(args)} (an element {_short(element)} is not {problem})"
        return None
    if origin in (dict, collections.abc.Mapping) or hint in (dict,):
        return None if isinstance(value, dict) else "a mapping"
    return None                    # other types (arrays, dataclasses): the constructor checks them


def _of(args: tuple) -> str:
    if not args or args[0] is Any:
        return ""
    inner = args[0]
    if typing.get_origin(inner) in (list, tuple, collections.abc.Sequence):
        return " of lists"
    return {float: " of numbers", int: " of integers", str: " of strings", bool: " of true/false"}.get(inner, "")


def flatten(container: Any, prefix: str = "", skip: tuple[str, ...] = ()) -> dict[str, Any]:
    """Dotted-key scalars of a resolved config; lists become JSON strings."""
    out: dict[str, Any] = {}
    if isinstance(container, dict):
        for k, v in container.items():
            key = f"{prefix}.{k}" if prefix else str(k)
            if any(_match(key, s) for s in skip):
                continue
            out.update(flatten(v, key, skip))
    elif isinstance(container, list):
        out[prefix] = json.dumps(container)
    else:
        out[prefix] = container
    return out


def _match(key: str, pattern: str) -> bool:
    parts, pat = key.split("."), pattern.split(".")
    return len(parts) == len(pat) and all(p == "*" or p == k for k, p in zip(parts, pat))



def _interpolated_names(node: Any) -> str:
    """Every interpolation text of the unresolved config, joined (``${paths.artifacts}/cache`` ...)."""
    found: list[str] = []

    def walk(value: Any) -> None:
        if isinstance(value, dict):
            for v in value.values():
                walk(v)
        elif isinstance(value, list):
            for v in value:
                walk(v)
        elif isinstance(value, str) and "${" in value:
            found.append(value)
    walk(OmegaConf.to_container(node, resolve=False) if isinstance(node, (DictConfig, ListConfig)) else node)
    return "\n".join(found)


def _is_config_group(key: str) -> bool:
    """Whether ``key`` names a config group (conf/<group>/, or one Hydra chose an option of in this job)."""
    from hydra.core.hydra_config import HydraConfig
    if HydraConfig.initialized() and key in (HydraConfig.get().runtime.choices or {}):
        return True
    return (Path(__file__).resolve().parents[2] / "conf" / key.replace(".", "/")).is_dir()


def check_added_keys(cfg: DictConfig, overrides: list[str]) -> None:
    """Refuse a ``+key=value`` (or ``++key=value``) override that adds a key nothing reads (``+mc.rnus=5``,
    ``+record.enable=false``: Hydra suggests the '+' for a key it does not know, and the job then ran with
    the key ignored): one paragraph naming it, the keys read there and the close names, as
    pipeline.launch.refusals words Hydra's own refusals. Only the top level and the fixed nodes of
    conf/config.yaml (``FIXED_KEYS``) are checked: a '+' key under a ``_target_`` node is left to
    ``build`` (a constructor parameter, or refused), one under a mapping of entries the user names
    (filters, metrics.windows, report.tables ...) to the code that reads that mapping; a top-level key
    that another value interpolates (``+my_noise=15 sensors.noise_std=${my_noise}``) is read; ``hydra.*``
    is Hydra's; a group override (``+tune=x``, ``+filter@filters.k=fsimm``) names a config file, not a key."""
    from pipeline.launch.refusals import FIXED_KEYS, close_names
    interpolated = None
    for override in overrides:
        if not override.startswith("+"):
            continue
        key, eq, value = override.lstrip("+").partition("=")
        key = key.strip()
        if not eq or "@" in key or key == "hydra" or key.startswith("hydra."):
            continue
        head = next((node for node in FIXED_KEYS if node and (key == node or key.startswith(f"{node}."))), None)
        if head is not None:
            if key == head:
                continue                   # ++mc={...} replaces the node: its keys are checked where read
            parent, leaf = head, key[len(head) + 1:].split(".")[0]      # +mc.sub.x=1 adds mc.sub
        elif "." not in key:
            parent, leaf = "", key
        else:
            continue                       # under a _target_ node or a user-named mapping
        if leaf in FIXED_KEYS[parent]:
            continue
        if not parent:
            if _is_config_group(key):
                continue                   # a config group chosen with '+' (+tune=x): its file, not a key
            node = OmegaConf.select(cfg, key, default=None)
            if isinstance(node, DictConfig) and "_target_" in node:
                continue                   # a whole node added (+bound={_target_: ...}): build checks it
            interpolated = _interpolated_names(cfg) if interpolated is None else interpolated
            if re.search(r"\$\{\s*" + re.escape(key) + r"\s*[}.:\[]", interpolated):
                continue                   # another value reads it
        keys = list(FIXED_KEYS[parent])
        close = close_names(leaf, keys)
        where = f"{parent}." if parent else ""
        suggest = (f"Did you mean {' or '.join(repr(where + c) for c in close)}? " if close
                   else "No key read there is close to it. ")
        example = f" ({where}{close[0]}={value})" if close else ""
        node_name = repr(parent) if parent else "the config's top level"
        raise ConfigError(
            f"{override}: {node_name} has no key {leaf!r} that anything reads, so the job would run with it ignored. "
            f"{suggest}Its keys are: {', '.join(keys)}. Set one of them without the '+'{example}"
            + ("; a new top-level key is read only where another value interpolates it (${...})." if not parent
               else "."))
