"""``mtt-query gc``: free the cache entries no kept run refers to, and the runs marked deleted.

The stage cache (``<artifacts>/cache/<stage>/<key>.parquet``) is never evicted by a job: a sweep
re-uses what did not change, and a run folder holds its own copy of every table it published. So
an entry is only worth keeping while some kept run refers to it (its ``status.json`` ``stage_keys``,
or for an older run the ``mtt.cache_key`` of its published tables): a re-run of that run's command
then hits the cache instead of recomputing.

Removed (``--apply``; the default lists them with the bytes they hold):

- every cache entry whose key no kept run refers to, unless it is newer than ``grace_s`` or than the
  start of a job still running (whose later stages may be about to write or read it): a job running
  meanwhile loses nothing; at worst a job recomputes an entry that gc removed an instant before it
  looked (each removal re-checks, under the stage folder's rename lock, that the file is still the
  one listed, so an entry a job renames onto the name meanwhile is kept);
- the folders of runs marked deleted (``mtt-query rm``), and so the entries only they referred to.

Left alone: ``*.rejected`` files (damaged entries moved aside for inspection), hidden temporary
files (a writer's), anything outside ``cache/`` and the run folders.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import polars as pl

from pipeline.results.query import render as render_table
from pipeline.results.tracking import Run, load_runs
from pipeline.storage.store import unlink_if_unchanged


@dataclass
class Entry:
    kind: str                 # "cache" | "run"
    path: Path
    bytes: int
    age_s: float
    stat: os.stat_result | None = None
    removed: bool | None = None


@dataclass
class Plan:
    root: Path
    entries: list[Entry]
    kept_cache: int
    kept_bytes: int
    runs_kept: int
    live_jobs: int
    notes: list[str] = field(default_factory=list)

    @property
    def bytes(self) -> int:
        return sum(e.bytes for e in self.entries if e.removed is not False)


def _started(run: Run) -> float | None:
    text = run.status.get("started_at")
    try:
        return dt.datetime.fromisoformat(text).timestamp() if text else None
    except ValueError:
        return None


def _folder_bytes(path: Path) -> int:
    total = 0
    for folder, _, files in os.walk(path):
        for name in files:
            try:
                total += os.lstat(os.path.join(folder, name)).st_size
            except OSError:
                pass
    return total


def _live(run: Run) -> bool:
    if run.status.get("status") != "running":
        return False
    from pipeline.run.process import is_gone
    return not is_gone(run.status.get("process"))


def plan(root: Path, grace_s: float = 600.0) -> Plan:
    """What gc would remove under ``root``, computed from the run folders as they are now."""
    root = Path(root)
    runs = load_runs(root)
    kept = [r for r in runs if not r.deleted]
    referenced: set[str] = set()
    for run in kept:
        referenced.update(run.stage_keys().values())
    live = [r for r in kept if _live(r)]
    now = time.time()
    # a running job's entries are only known when it writes its status: keep what is newer than its start
    oldest_live = min((s for s in (_started(r) for r in live) if s is not None), default=None)
    newest_allowed = now - grace_s
    if oldest_live is not None:
        newest_allowed = min(newest_allowed, oldest_live - 1.0)   # started_at has a resolution of a second
    entries: list[Entry] = []
    kept_cache = kept_bytes = 0
    cache = root / "cache"
    if cache.is_dir():
        for stage in sorted(p for p in cache.iterdir() if p.is_dir() and not p.name.startswith(".")):
            with os.scandir(stage) as listing:
                for item in listing:
                    if item.name.startswith(".") or not item.name.endswith(".parquet") or not item.is_file():
                        continue
                    st = item.stat()
                    if item.name[:-len(".parquet")] in referenced or st.st_mtime > newest_allowed:
                        kept_cache += 1
                        kept_bytes += st.st_size
                        continue
                    entries.append(Entry("cache", Path(item.path), st.st_size, now - st.st_mtime, st))
    for run in runs:
        if run.deleted:
            entries.append(Entry("run", run.path, _folder_bytes(run.path), now - (_started(run) or now)))
    notes = []
    if live:
        notes.append(f"{len(live)} job(s) running: cache entries newer than the oldest one's start are kept")
    return Plan(root, sorted(entries, key=lambda e: (e.kind, str(e.path))), kept_cache, kept_bytes, len(kept),
                len(live), notes)


def apply(planned: Plan) -> Plan:
    """Remove what ``planned`` lists (each cache entry only if it is still the file listed)."""
    for entry in planned.entries:
        if entry.kind == "cache":
            try:
                entry.removed = unlink_if_unchanged(entry.path, entry.stat)
            except OSError:
                entry.removed = False
        else:
            status = entry.path / "status.json"
            try:
                still_deleted = json.loads((entry.path / "annotations.json").read_text()).get("deleted")
            except (OSError, ValueError):
                still_deleted = False
            if not still_deleted or not status.is_file():
                entry.removed = False          # un-marked meanwhile, or not a run folder any more
                continue
            shutil.rmtree(entry.path, ignore_errors=True)
            entry.removed = not entry.path.exists()
    return planned


def _size(n: int) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n} B"


def render(planned: Plan, fmt: str, applied: bool) -> str:
    rows = [{"kind": e.kind, "path": e.path.relative_to(planned.root).as_posix() if e.path.is_relative_to(planned.root)
             else str(e.path), "bytes": e.bytes, "age_h": round(e.age_s / 3600, 2),
             **({"removed": e.removed} if applied else {})} for e in planned.entries]
    df = pl.DataFrame(rows, schema={"kind": pl.String, "path": pl.String, "bytes": pl.Int64, "age_h": pl.Float64,
                                    **({"removed": pl.Boolean} if applied else {})})
    verb = "removed" if applied else "would remove"
    counts = df.group_by("kind").len() if df.height else None
    n_cache = int(counts.filter(pl.col("kind") == "cache")["len"].sum()) if counts is not None else 0
    n_runs = int(counts.filter(pl.col("kind") == "run")["len"].sum()) if counts is not None else 0
    summary = (f"gc {verb} {n_cache} unreferenced cache entries and {n_runs} deleted runs: {_size(planned.bytes)}; "
               f"kept {planned.kept_cache} cache entries ({_size(planned.kept_bytes)}) that {planned.runs_kept} kept "
               f"runs refer to or that are recent")
    if not applied and (n_cache or n_runs):
        summary += "; `mtt-query gc --apply` removes them"
    if fmt == "json":
        return json.dumps({"applied": applied, "bytes": planned.bytes, "kept_cache_entries": planned.kept_cache,
                           "notes": planned.notes, "entries": df.to_dicts()}, indent=2) + "\n"
    if fmt == "csv":
        return df.write_csv()
    body = render_table(df, fmt, max_rows=0) if df.height else ""
    return body + "\n".join([summary, *planned.notes]) + "\n"
