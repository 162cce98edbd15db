"""A stage output's cache key: what it was computed from, the code that computed it included."""

from __future__ import annotations

import math
from typing import Any

from pipeline.storage import fingerprint
from pipeline.storage.schemas import SCHEMA_VERSION
from pipeline.storage.store import package_version, stable_hash


def canonical_numbers(node: Any) -> Any:
    """``node`` (a resolved config subtree: mappings, lists, scalars) with every integral float written
    as the int it equals (``20.0`` -> ``20``), so that ``sensors.noise_std=20`` and ``=20.0``, one
    value, give one key. Booleans stay booleans; NaN, infinities and fractional floats stay as they
    are."""
    if isinstance(node, dict):
        return {key: canonical_numbers(value) for key, value in node.items()}
    if isinstance(node, (list, tuple)):
        return [canonical_numbers(value) for value in node]
    if isinstance(node, float) and math.isfinite(node) and node.is_integer():
        return int(node)
    return node


def stage_key(stage: str, config: Any, inputs: tuple[str, ...] = (), producers: tuple[str, ...] = ()) -> str:
    """The cache key of a stage output: its resolved config subtree (numbers canonical:
    ``canonical_numbers``), its inputs' keys, the package and schema versions, and the source of the
    import closure of ``producers`` (module names) and of every ``_target_`` in ``config``
    (pipeline.storage.fingerprint): editing any code that made the table, a user's package included,
    recomputes it; a researcher changing the math must never be handed estimates made by the old code."""
    code = fingerprint.source_fingerprint(fingerprint.producers(config, *producers))
    return stable_hash({"stage": stage, "config": canonical_numbers(config), "inputs": list(inputs),
                        "version": package_version(), "schema": SCHEMA_VERSION, "code": code})
