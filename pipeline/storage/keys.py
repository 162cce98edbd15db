"""A stage output's cache key: what it was computed from, the code that computed it included."""

from __future__ import annotations

from typing import Any

from pipeline.storage import fingerprint
from pipeline.storage.schemas import SCHEMA_VERSION
from pipeline.storage.store import package_version, stable_hash


def stage_key(stage: str, config: Any, inputs: tuple[str, ...] = (), producers: tuple[str, ...] = ()) -> str:
    """The cache key of a stage output: its resolved config subtree, its inputs' keys, the package
    and schema versions, and the source of the import closure of ``producers`` (module names) and
    of every ``_target_`` in ``config`` (pipeline.storage.fingerprint): editing any code that made the
    table, a user's package included, recomputes it; a researcher changing the math must never be
    handed estimates made by the old code."""
    code = fingerprint.source_fingerprint(fingerprint.producers(config, *producers))
    return stable_hash({"stage": stage, "config": config, "inputs": list(inputs),
                        "version": package_version(), "schema": SCHEMA_VERSION, "code": code})
