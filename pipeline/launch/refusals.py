"""Hydra's refusals of a command line (a key the config does not have, an option a config group does not
hold, an override it cannot parse) as one paragraph naming the override and the close names.

Hydra composes the config before any callback of ours runs, and prints its own text for these
(``Key 'noise_stdd' is not in struct`` with ``full_key`` and ``object_type``); ``entry`` in
pipeline.__main__ asks Hydra to raise them instead (``HYDRA_FULL_ERROR``) and prints ``explain``'s
paragraph. Only Hydra's public exception attributes are read: ``MissingConfigException``'s
``missing_cfg_file`` and ``options``, and the OmegaConf cause's ``full_key`` and ``parent_node``.
"""

from __future__ import annotations

import difflib
from typing import Any, Sequence


# The keys the code reads at the top level ("") and at the nodes of conf/config.yaml whose keys are fixed, in
# the config's order. A key added there with '+' is read by nothing: pipeline.run.config.check_added_keys
# refuses it, so a refusal of a key there does not suggest the '+'. Every other node is a ``_target_`` node
# (its constructor's parameters) or a mapping of entries the user names (filters, metrics.windows, ...).
FIXED_KEYS: dict[str, tuple[str, ...]] = {
    "": ("experiment_name", "description", "mc", "uncertainty", "timing", "record", "faults", "cache", "paths",
         "plugins", "variants", "objective", "paper_runs", "target_test_runs", "targets_tested_in", "smoke",
         "study", "scenario", "target_model", "sensors", "models", "filters", "bound", "metrics", "report"),
    "mc": ("runs", "seed", "chunk_runs", "max_memory_gb"),
    "uncertainty": ("confidence", "bootstrap_resamples"),
    "timing": ("passes", "budget_s"),
    "record": ("enabled", "runs"),
    "faults": ("symmetry_tolerance", "nees_bound", "divergence_factor"),
    "cache": ("enabled", "publish"),
    "paths": ("artifacts",),
    "plugins": ("packages",),
}


def close_names(name: str, options: Sequence[str], n: int = 3) -> list[str]:
    """Up to ``n`` of ``options`` close to ``name`` (difflib's ratio >= 0.6, or the options that contain
    it or that it contains, for a name typed short or long)."""
    found = difflib.get_close_matches(name, list(options), n=n, cutoff=0.6)
    found += [o for o in options if (name in o or o in name) and o not in found and len(o) > 1]
    return found[:n]


def _override_naming(argv: Sequence[str], key: str) -> str | None:
    """The command-line override that sets ``key`` (``sensors.noise_stdd=20``) or a key under it, if one does."""
    for exact in (True, False):      # filterz.a=1 is refused at its first unknown key, 'filterz'
        for arg in argv:
            name, eq, _ = arg.lstrip("+~").partition("=")
            if eq and (name == key if exact else name.startswith(f"{key}.")):
                return arg
    return None


def _suggest(close: list[str], what: str) -> str:
    return f"Did you mean {' or '.join(repr(c) for c in close)}?" if close else f"No {what} is close to it."


def explain(exc: BaseException, argv: Sequence[str]) -> str:
    """One paragraph for Hydra's refusal ``exc`` of the command line ``argv`` (without the program)."""
    missing = getattr(exc, "missing_cfg_file", None)
    options = getattr(exc, "options", None)
    if missing and options is not None:              # experiment=ao_vsim, +filter@filters.x=fsim
        group, _, name = str(missing).rpartition("/")
        if group:
            override = next((a for a in argv if a.partition("=")[2] == name
                             and a.lstrip("+~").partition("=")[0].partition("@")[0] == group), f"{group}={name}")
            return (f"{override}: conf/{group}/ has no option {name!r}. {_suggest(close_names(name, options), 'option')} "
                    f"The options of {group!r} are: {', '.join(options)} (Hydra: Could not find '{missing}').")
        return str(exc).strip()
    cause = exc.__cause__
    key = getattr(cause, "full_key", None)
    parent: Any = getattr(cause, "parent_node", None)
    if key and parent is not None and hasattr(parent, "keys") and "Could not override" in str(exc):
        where, _, leaf = str(key).rpartition(".")
        keys = [str(k) for k in parent.keys()]
        override = _override_naming(argv, str(key)) or f"{key}=..."
        node = f"{where!r}" if where else "the config's top level"
        add = (f"Its keys are fixed (a '+' key there is read by nothing)" if where in FIXED_KEYS and where
               else f"To add a new key, write +{override.lstrip('+~')}")
        return (f"{override}: {node} has no key {leaf!r}. {_suggest(close_names(leaf, keys), 'key')} "
                f"Its keys are: {', '.join(keys)}. {add} (Hydra: Could not override '{key}').")
    return " ".join(line.strip() for line in str(exc).strip().splitlines() if line.strip())
