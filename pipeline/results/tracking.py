"""Experiment tracking over the artifacts tree: list runs with their code, tag, note, delete.

A run folder is the record (``status.json``: its config hash, stage keys, environment and
provenance, pipeline.run.provenance; ``config.yaml``; the tables). What a user adds to it lives
beside it in ``<run>/annotations.json`` (tags, a note, whether it is marked deleted), written under
a lock so two commands never lose each other's tag. The commands (``mtt-query <command> -h``):

- ``runs``: one row per run with its commit, dirty flag, code hash, tags and note; filters by
  experiment, status, tag, time; ``--only-changed`` keeps only the config keys and provenance
  fields that differ between the listed runs; ``--metric M --window W`` adds a column per variant
  (``value ± half-width`` of its interval);
- ``diff RUN_A RUN_B`` (pipeline.results.diff), ``gc`` (pipeline.results.gc), ``export-mlflow``
  (pipeline.results.mlflow_export);
- ``tag RUN NAME...`` (``--remove``), ``note RUN TEXT``, ``rm RUN`` (``--undo``): ``rm`` marks the
  run deleted (hidden from ``runs`` unless ``--include-deleted``); ``gc --apply`` removes it.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import polars as pl

from pipeline.results.query import QueryError, discover_runs, render
from pipeline.run.config import flatten
from pipeline.storage.run_tables import STAGE_KEYS
from pipeline.storage.store import META_KEY, atomic_write_text, read_yaml

try:
    import fcntl
except ImportError:                    # Windows: no cross-process lock, single-user use
    fcntl = None

ANNOTATIONS = "annotations.json"
STATUS = "status.json"
FORMATS = ("table", "markdown", "csv", "json")
# config keys that say where a job wrote, not what it computed: never a "change" between runs
LOCATION_KEYS = ("paths.", "hydra.")


@dataclass
class Run:
    """One run (or sweep job) folder as the tracking commands see it."""

    path: Path
    run_id: str
    status: dict[str, Any]
    annotations: dict[str, Any] = field(default_factory=dict)

    @property
    def provenance(self) -> dict[str, Any]:
        return self.status.get("provenance") or {}

    @property
    def git(self) -> dict[str, Any]:
        return self.provenance.get("git") or {}

    @property
    def deleted(self) -> bool:
        return bool(self.annotations.get("deleted"))

    @property
    def tags(self) -> list[str]:
        return list(self.annotations.get("tags") or [])

    def config(self) -> dict[str, Any]:
        """The run's resolved config, flattened to dotted keys (empty if it has none)."""
        path = self.path / "config.yaml"
        if not path.is_file():
            return {}
        try:
            loaded = read_yaml(path)
        except (OSError, ValueError) as exc:
            raise QueryError(f"{path}: cannot be read as YAML ({exc}); the run's config is damaged.") from None
        return flatten(loaded) if isinstance(loaded, dict) else {}

    def stage_keys(self) -> dict[str, str]:
        """Each stage table's cache key by its name in the folder (``truth.parquet``,
        ``estimates/fsimm.parquet``): status.json's, or for a run from before it recorded them, the
        published tables' own ``mtt.cache_key``."""
        keys = self.status.get(STAGE_KEYS)
        if isinstance(keys, dict) and keys:
            return {str(k): str(v) for k, v in keys.items()}
        found: dict[str, str] = {}
        tables = [self.path / "truth.parquet", self.path / "detections.parquet",
                  *sorted((self.path / "estimates").glob("*.parquet"))]
        for table in tables:
            try:
                key = pl.read_parquet_metadata(table).get(META_KEY)
            except (OSError, pl.exceptions.PolarsError):
                continue
            if key:
                found[table.relative_to(self.path).as_posix()] = key
        return found


# ---- reading and annotating runs --------------------------------------------------------------
def _read_json(path: Path) -> dict[str, Any]:
    try:
        loaded = json.loads(path.read_text())
    except FileNotFoundError:
        return {}
    except (OSError, ValueError):
        return {}
    return loaded if isinstance(loaded, dict) else {}


def load_runs(root: Path, sweep: str | Path | None = None) -> list[Run]:
    """Every run and job folder under ``root`` (runs/ and multirun/), with status and annotations."""
    root = Path(root)
    if not root.is_dir():
        raise QueryError(f"--root '{root}': no such directory; give the artifacts directory that holds runs/ "
                         f"and multirun/ (the pipeline's paths.artifacts, default artifacts).")
    found = [Run(r.path, r.run_id, _read_json(r.path / STATUS), _read_json(r.path / ANNOTATIONS))
             for r in discover_runs(root)]
    if sweep is not None:
        prefix = resolve_folder(root, sweep, "--sweep").relative_to(root.resolve()).as_posix()
        found = [r for r in found if r.run_id.startswith(prefix + "/")]
    return found


def resolve_folder(root: Path, given: str | Path, what: str) -> Path:
    """A run or sweep folder given as a path (absolute, or relative to the working directory) or as
    its run_id (relative to ``root``), resolved; refused unless it is inside ``root``."""
    given = Path(given)
    for candidate in ([given] if given.is_absolute() else [Path.cwd() / given, Path(root) / given]):
        if candidate.is_dir():
            resolved = candidate.resolve()
            if not resolved.is_relative_to(Path(root).resolve()):
                raise QueryError(f"{what} '{given}' is not inside the artifacts root '{root}'; the tracking "
                                 f"commands act only on folders the pipeline wrote there (give --root).")
            return resolved
    raise QueryError(f"{what} '{given}': no such folder, neither relative to the working directory nor to the "
                     f"artifacts root '{root}' (a run_id as `mtt-query runs` lists it, or a path).")


def resolve_run(root: Path, given: str | Path) -> Run:
    path = resolve_folder(root, given, "RUN")
    if not (path / STATUS).is_file():
        jobs = sorted(p.name for p in path.iterdir() if (p / STATUS).is_file()) if path.is_dir() else []
        hint = f" It holds the jobs {', '.join(jobs[:8])}: name one of them." if jobs else ""
        raise QueryError(f"RUN '{given}' is not a run folder (it has no {STATUS}).{hint}")
    run_id = path.relative_to(Path(root).resolve()).as_posix()
    return Run(path, run_id, _read_json(path / STATUS), _read_json(path / ANNOTATIONS))


@contextlib.contextmanager
def _annotations_locked(run: Run) -> Iterator[dict[str, Any]]:
    """The run's annotations, read and written back under an exclusive lock on ``.annotations.lock``."""
    fd = os.open(run.path / ".annotations.lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        if fcntl is not None:
            fcntl.flock(fd, fcntl.LOCK_EX)
        current = _read_json(run.path / ANNOTATIONS)
        yield current
        current["updated_at"] = dt.datetime.now().isoformat(timespec="seconds")
        atomic_write_text(json.dumps(current, indent=2, sort_keys=True) + "\n", run.path / ANNOTATIONS)
        run.annotations = current
    finally:
        os.close(fd)


def tag(run: Run, names: Sequence[str], remove: bool = False) -> list[str]:
    for name in names:
        if not name or any(c.isspace() for c in name) or "," in name:
            raise QueryError(f"tag {name!r}: a tag is one word without spaces or commas (e.g. baseline, "
                             f"after-fix).")
    with _annotations_locked(run) as notes:
        tags = [t for t in notes.get("tags", []) if not (remove and t in names)]
        if not remove:
            tags += [n for n in names if n not in tags]
        notes["tags"] = tags
    return tags


def note(run: Run, text: str) -> None:
    with _annotations_locked(run) as notes:
        notes["note"] = text


def mark_deleted(run: Run, undo: bool = False) -> None:
    with _annotations_locked(run) as notes:
        notes["deleted"] = not undo
        if not undo:
            notes["deleted_at"] = dt.datetime.now().isoformat(timespec="seconds")
        else:
            notes.pop("deleted_at", None)


# ---- the runs listing -------------------------------------------------------------------------
def _when(text: str, option: str) -> dt.datetime:
    try:
        return dt.datetime.fromisoformat(text)
    except ValueError:
        raise QueryError(f"{option} {text!r}: give a date or a time as ISO 8601, e.g. 2026-12-04 or "
                         f"2026-12-04T13:30.") from None


def select(runs: Sequence[Run], *, experiment: str | None = None, status: str | None = None,
           tags: Sequence[str] = (), since: str | None = None, until: str | None = None,
           include_deleted: bool = False) -> list[Run]:
    """The runs that pass every filter given (``tags``: all of them)."""
    first = _when(since, "--since") if since else None
    last = _when(until, "--until") if until else None
    kept = []
    for run in runs:
        if run.deleted and not include_deleted:
            continue
        if experiment and run.status.get("experiment") != experiment:
            continue
        if status and run.status.get("status") != status:
            continue
        if any(t not in run.tags for t in tags):
            continue
        started = run.status.get("started_at")
        try:
            started_at = dt.datetime.fromisoformat(started) if started else None
        except ValueError:
            started_at = None
        if (first or last) and started_at is None:
            continue
        if first and started_at < first or last and started_at > last:
            continue
        kept.append(run)
    return kept


def provenance_fields(run: Run) -> dict[str, Any]:
    git, env = run.git, run.status.get("environment") or {}
    packages = run.provenance.get("user_packages") or {}
    if not run.provenance:
        commit = "(not recorded)"          # a run from before provenance was recorded
    else:
        commit = (git.get("commit") or "")[:10] or None if git.get("available") else "(no git)"
    return {
        "commit": commit,
        "branch": git.get("branch"), "dirty": git.get("dirty"),
        "diff": (git.get("diff_sha256") or "")[:10] or None,
        "code": run.provenance.get("code"),
        "user_packages": ", ".join(f"{k}:{v.get('sha256', '')[:8]}" for k, v in sorted(packages.items())) or None,
        "environment": env.get("hash"), "host": run.provenance.get("host"),
    }


def metric_columns(runs: Sequence[Run], metric: str, window: str) -> dict[str, list[str | None]]:
    """Per variant, each run's ``value ± half-width`` of ``metric`` (a summary series) in ``window``."""
    per_run: list[dict[str, str]] = []
    variants: list[str] = []
    for run in runs:
        path = run.path / "summary.parquet"
        cells: dict[str, str] = {}
        if path.is_file():
            try:
                rows = (pl.read_parquet(path, columns=["variant", "series", "window", "value", "ci_low", "ci_high"])
                        .filter((pl.col("series") == metric) & (pl.col("window") == window)))
            except (OSError, pl.exceptions.PolarsError):
                rows = pl.DataFrame()
            for row in rows.iter_rows(named=True):
                cells[row["variant"]] = _value_pm(row["value"], row["ci_low"], row["ci_high"])
                if row["variant"] not in variants:
                    variants.append(row["variant"])
        per_run.append(cells)
    return {f"{v} {metric} [{window}]": [cells.get(v) for cells in per_run] for v in variants}


def _value_pm(value: float | None, low: float | None, high: float | None) -> str | None:
    if value is None:
        return None
    if low is None or high is None:
        return f"{value:.4g}"
    return f"{value:.4g} ± {max(high - value, value - low):.2g}"


def runs_table(runs: Sequence[Run], *, only_changed: bool = False, metric: str | None = None,
               window: str = "all") -> pl.DataFrame:
    rows = []
    configs = [r.config() for r in runs] if only_changed else []
    for run in runs:
        status = run.status
        rows.append({"run_id": run.run_id, "experiment": status.get("experiment"), "status": status.get("status"),
                     "started_at": status.get("started_at"), "runs": status.get("runs"),
                     "seed": (run.provenance.get("seed")), **provenance_fields(run),
                     "tags": ",".join(run.tags) or None, "note": run.annotations.get("note")})
    df = pl.DataFrame(rows, infer_schema_length=None) if rows else pl.DataFrame(schema={"run_id": pl.String})
    if only_changed and len(runs) > 1:
        fixed = {"run_id"}
        varying = [c for c in df.columns if c not in fixed and df[c].cast(pl.String).n_unique() > 1]
        keys = sorted({k for c in configs for k in c if not k.startswith(LOCATION_KEYS)})
        changed = [k for k in keys if len({json.dumps(c.get(k), default=str) for c in configs}) > 1]
        df = df.select(["run_id", *varying]).with_columns(
            pl.Series(k, [None if c.get(k) is None else str(c.get(k)) for c in configs], dtype=pl.String)
            for k in changed)
    if metric:
        for name, cells in metric_columns(runs, metric, window).items():
            df = df.with_columns(pl.Series(name, cells, dtype=pl.String))
    return df


WIDE_ONLY = ("diff", "user_packages", "environment", "host", "seed")


def emit(df: pl.DataFrame, fmt: str, extra: Mapping[str, Any] | None = None, wide: bool = True) -> str:
    """json and csv carry every column; a table or markdown leaves out, unless ``wide``, the
    provenance details that are the same in every row and every column that is empty."""
    if not wide and fmt in ("table", "markdown") and df.height:
        df = df.select([c for c in df.columns if df[c].null_count() < df.height and
                        not (c in WIDE_ONLY and df[c].cast(pl.String).n_unique() == 1)])
    if fmt == "json":
        return json.dumps({**(extra or {}), "rows": df.to_dicts()}, indent=2, default=str) + "\n"
    return render(df, fmt, max_rows=0)
