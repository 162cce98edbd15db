"""A run folder's tables read as input: each must be the table this folder's run wrote under that name.

A reader (``mtt-query``, the report, a sweep's aggregation) trusts a table of a run folder only when
it passes, in this order (each failure a ``TableRefused`` naming the file and what differs):

1. its content checksum (``pipeline.storage.store.verify_checksum``), and that it *has* one: a table
   without ``mtt.content_sha256`` (rewritten by another tool, which drops the metadata, or a "legacy"
   file) shows nothing that ties its rows to the run, so it is refused, not served unchecked;
2. a table the run computes itself (``summary``, ``metrics``, ``per_run``, ``comparisons``,
   ``resamples``) says it is that table (``mtt.table``) and names this run: its ``run_id`` column and
   its ``mtt.config_hash`` (and ``config_hash`` column) equal ``status.json``'s ``run_id`` and
   ``config_hash``; a summary copied from another run (seed 2 into seed 1's folder) names that run;
3. a stage table published from the cache (``truth``, ``detections``, ``estimates/<variant>``)
   carries the cache key (``mtt.cache_key``) that ``status.json`` records for that name
   (``stage_keys``, written when the job ends ok): ``estimates/fsimm.parquet`` and ``vsimm.parquet``
   swapped, or another seed's ``truth.parquet`` copied in, carry another key. A table the run wrote
   under no such name is refused too.

A folder whose ``status.json`` is missing, or records no ``stage_keys`` (a job that failed, or one
written before they were recorded), is held to the checks it has the records for.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

import polars as pl

from pipeline.storage.schemas import META_TABLE
from pipeline.storage.store import META_CHECKSUM, META_KEY, TableDamaged, read_table

__all__ = ["TableRefused", "RUN_TABLES", "STAGE_KEYS", "read_status", "check_run_table", "read_run_table"]

#: The tables a run computes itself, by file name: the name its metadata must carry.
RUN_TABLES = {"summary.parquet": "summary", "metrics.parquet": "metrics", "per_run.parquet": "per_run",
              "comparisons.parquet": "comparisons", "resamples.parquet": "resamples"}
#: status.json's record of each stage table's cache key, by its name in the run folder.
STAGE_KEYS = "stage_keys"
META_CONFIG_HASH = "mtt.config_hash"


class TableRefused(TableDamaged):
    """A run folder's table that is not (shown to be) the one its run wrote under that name."""


def read_status(run_dir: Path | str) -> dict[str, Any] | None:
    """The folder's status.json as a dict, or None (missing, unreadable, not an object)."""
    try:
        status = json.loads((Path(run_dir) / "status.json").read_text())
    except (OSError, ValueError):
        return None
    return status if isinstance(status, dict) else None


def _values(df: pl.DataFrame, column: str) -> set[str]:
    if column not in df.columns:
        return set()
    return {str(v) for v in df[column].drop_nulls().unique().to_list() if str(v)}


def check_run_table(path: Path | str, df: pl.DataFrame, meta: Mapping[str, str], status: Mapping[str, Any] | None,
                    name: str) -> None:
    """Raise TableRefused unless ``df`` (read from ``path``, checksum verified) is what this run folder's run
    wrote as ``name`` (relative to the folder: ``summary.parquet``, ``estimates/fsimm.parquet``)."""
    if META_CHECKSUM not in meta:
        raise TableRefused(
            f"{path}: it carries no content checksum ({META_CHECKSUM}), so nothing shows that its rows are the "
            f"ones the run wrote (a file rewritten by another tool loses the metadata; a file from before "
            f"checksums never had it); it is not served. Re-run the job to get checked tables")
    status = status or {}
    if name in RUN_TABLES:
        said = meta.get(META_TABLE)
        if said != RUN_TABLES[name]:
            raise TableRefused(f"{path}: it holds the table {said!r}, not {RUN_TABLES[name]!r} (a file renamed "
                               f"or copied over it); it is not served")
        run_id = str(status.get("run_id") or "")
        found = _values(df, "run_id")
        if run_id and found and found != {run_id}:
            raise TableRefused(
                f"{path}: its rows are run {', '.join(sorted(found))}'s (column run_id), but this folder's "
                f"status.json is run {run_id}'s: the table was copied from another run folder; it is not served")
        config_hash = str(status.get("config_hash") or "")
        stated = {meta[META_CONFIG_HASH]} if meta.get(META_CONFIG_HASH) else set()
        stated |= _values(df, "config_hash")
        if config_hash and stated and stated != {config_hash}:
            raise TableRefused(
                f"{path}: it was computed with config hash {', '.join(sorted(stated))}, but this folder's "
                f"status.json records {config_hash}: the table is another run's (another seed or config); "
                f"it is not served")
        return
    keys = status.get(STAGE_KEYS)
    if not isinstance(keys, Mapping):
        return
    if name not in keys:
        raise TableRefused(f"{path}: this folder's run wrote no table under that name (status.json's "
                           f"{STAGE_KEYS}: {', '.join(sorted(keys)) or 'none'}); it is not served")
    key = meta.get(META_KEY)
    if key != keys[name]:
        other = sorted(n for n, k in keys.items() if k == key)
        why = (f"it holds the table this run stored as {', '.join(other)} (the files were swapped or renamed)"
               if other else "it is not the table this run computed under that name (another run's, or another "
                             "seed's or config's)")
        raise TableRefused(f"{path}: {why}: its cache key is {key!r}, status.json records {keys[name]!r} for "
                           f"{name}; it is not served")


def read_run_table(run_dir: Path | str, name: str, status: Mapping[str, Any] | None = None
                   ) -> tuple[pl.DataFrame, dict[str, str]]:
    """(rows, metadata) of ``run_dir/name``, checksum verified and checked against the folder
    (``check_run_table``; ``status`` defaults to the folder's status.json). TableDamaged / TableRefused."""
    path = Path(run_dir) / name
    df, meta = read_table(path)
    check_run_table(path, df, meta, read_status(run_dir) if status is None else status, name)
    return df, meta
