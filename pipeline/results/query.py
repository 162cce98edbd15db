"""Query the artifacts tree with SQL: ``python -m pipeline.query`` / ``mtt-query``.

These tables are registered, all lazy:

``summary``
    every ``summary.parquet`` of every single run (``<root>/runs/<experiment>/<timestamp>/``)
    and multirun job (``<root>/multirun/<timestamp>/<job_num>/``), failed jobs
    included (one row, ``status = 'failed'``). Config leaves are columns named by their dotted
    key (``"filters.vsimm.t1_mu"``). Different experiments carry different config columns and
    a swept key may be int in one job and float in another: the table is the union of all
    columns (missing ones are null) with each column at the common supertype (int + float ->
    float, anything + string -> string).
``metrics``
    every ``metrics.parquet`` (per-step series, fixed schema).
``runs``
    one row per run/job directory from its ``status.json`` (the ``list`` frame, plus
    ``finished_at`` and ``config_hash``).
``per_run``
    every ``per_run.parquet``: each Monte Carlo run's own value (column ``run``) of every summary
    statistic (variant x series x window), for distributions and per-run questions.
``comparisons``
    every ``comparisons.parquet``: each variant against its experiment's reference variant, paired
    over the runs (difference and ratio with their 95 % intervals, Wilcoxon p, ``resolved``).
``truth`` / ``estimates``
    the stage tables of every run folder (``truth.parquet``, ``estimates/<variant>.parquet``), with
    the folder's ``run_id`` and ``experiment`` (and the estimates' ``variant_key``) as columns;
    their columns differ by study (the union, null where a study has none). Large: read only when
    a query names them.

``mtt-query tables`` lists per experiment its run folders, n_runs and variants, and its metrics grouped
by the windows they have values in, then the tables' columns (the summary's config columns with
``--config``). After a query, every string literal compared with a name column (``metric``, ``series``,
``variant``, ``"window"``, ...: ``=``, ``<>``, ``IN (...)``, ``LIKE``) that none of the column's values in
the queried tables matches is warned about with the close values (difflib); an unknown column's error
names the close columns only.

Only files with those names (and ``status.json``) are read,
never hidden files or directories (the writers' ``.<name>.<random>.tmp`` temp files, ``.hydra``,
``.submitit``), never ``*.rejected`` and never ``<root>/cache``. A corrupt or truncated Parquet
file, or one whose rows do not match the content checksum stored when it was written
(pipeline.storage.store), is skipped with a warning naming it; it does not fail the query. So is a
table that is not the one its run folder's run wrote under that name (pipeline.storage.run_tables:
no checksum, another run's run_id or config hash, a stage table under another name's cache key).

Reading strategy: each file is read whole once and checked against its content checksum
(pipeline.storage.store; 1-2 ms to read a summary file, about 4 ms to check it), its schema goes into the
superset schema, then every file whose columns the scanner can cast to it goes into *one*
``pl.scan_parquet(files, schema=..., missing_columns="insert", cast_options=...)``. Files that
need a cast the scanner cannot do (int -> string, list -> JSON string) are scanned per distinct
schema and cast explicitly, then appended. Only the tables a query names are opened. Measured
on 300 summary files (2-core box, polars 2.1): collecting the whole summary takes 0.23 s this
way against 0.84 s for ``pl.concat([scan_parquet(f) ...], how="diagonal_relaxed")``, before the
checksums; with them, an ``sql`` over the 300 files' summary takes 2.2 s end to end against 0.41 s
without (median of 7, interpreter start and polars import included). ``mtt-query list`` reads no
Parquet file.

Python API::

    from pipeline.results.query import load_tables, query
    tables = load_tables(Path("artifacts"))                 # {"summary": LazyFrame, ...}
    df = query('SELECT variant, AVG(value) FROM summary GROUP BY ALL', root="artifacts")
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import polars as pl

__all__ = ["QueryError", "QueryWarning", "load_tables", "query", "runs_frame", "tables_overview", "check_literals",
           "main", "SUMMARY_COLUMNS", "METRICS_COLUMNS", "RUNS_COLUMNS", "LIST_COLUMNS"]

SUMMARY_FILE = "summary.parquet"
METRICS_FILE = "metrics.parquet"
STATUS_FILE = "status.json"
TABLE_FILES = {"summary": SUMMARY_FILE, "metrics": METRICS_FILE, "per_run": "per_run.parquet",
               "comparisons": "comparisons.parquet", "truth": "truth.parquet", "estimates": "estimates/*.parquet"}
#: The stage tables (one schema per study): each file gets the run folder's run_id and experiment (and
#: the estimates their variant_key) as columns, and the union of all files' columns is the table.
STAGE_TABLES = ("truth", "estimates")

#: Columns every summary has (in this order; null where an older file lacks one); the config
#: columns follow, sorted by name: every other column of the summary is a config leaf.
SUMMARY_COLUMNS: dict[str, pl.DataType] = {
    "run_id": pl.String(), "experiment": pl.String(), "status": pl.String(), "error": pl.String(),
    "variant": pl.String(), "variant_key": pl.String(), "metric": pl.String(), "component": pl.String(),
    "sensor": pl.Int32(), "target": pl.Int32(), "series": pl.String(), "window": pl.String(),
    "value": pl.Float64(), "unit": pl.String(), "n_runs": pl.Int32(), "n_valid_runs": pl.Int32(),
    "standard_error": pl.Float64(), "ci_low": pl.Float64(), "ci_high": pl.Float64(), "interval": pl.String(),
    "config_hash": pl.String(), "overrides": pl.String(), "sweep": pl.String(), "job_num": pl.Int32(),
    "estimates_from_cache": pl.Boolean(),
    # the compute rows' timing (pipeline.evaluation.timing)
    "compute_passes": pl.Int32(), "compute_cached": pl.Boolean(), "mixes_processes": pl.Boolean(),
}
METRICS_COLUMNS: dict[str, pl.DataType] = {
    "run_id": pl.String(), "experiment": pl.String(), "variant": pl.String(),
    "variant_key": pl.String(), "metric": pl.String(), "component": pl.String(), "sensor": pl.Int32(),
    "target": pl.Int32(), "series": pl.String(), "step": pl.Int32(), "time": pl.Float64(),
    "value": pl.Float64(), "n_runs": pl.Int32(),
}
PER_RUN_COLUMNS: dict[str, pl.DataType] = {
    "run_id": pl.String(), "experiment": pl.String(), "run": pl.Int32(), "variant": pl.String(),
    "variant_key": pl.String(), "metric": pl.String(), "component": pl.String(), "sensor": pl.Int32(),
    "target": pl.Int32(), "series": pl.String(), "window": pl.String(), "value": pl.Float64(),
}
COMPARISONS_COLUMNS: dict[str, pl.DataType] = {
    "run_id": pl.String(), "experiment": pl.String(), "variant_key": pl.String(), "reference_key": pl.String(),
    "metric": pl.String(), "component": pl.String(), "sensor": pl.Int32(), "target": pl.Int32(),
    "series": pl.String(), "window": pl.String(), "value": pl.Float64(), "reference_value": pl.Float64(),
    "n_paired_runs": pl.Int32(), "difference": pl.Float64(), "difference_low": pl.Float64(),
    "difference_high": pl.Float64(), "ratio": pl.Float64(), "ratio_low": pl.Float64(), "ratio_high": pl.Float64(),
    "wilcoxon_p": pl.Float64(), "resolved": pl.Boolean(),
}
STAGE_COLUMNS: dict[str, pl.DataType] = {"run_id": pl.String(), "experiment": pl.String()}
FIXED_COLUMNS = {"summary": SUMMARY_COLUMNS, "metrics": METRICS_COLUMNS, "per_run": PER_RUN_COLUMNS,
                 "comparisons": COMPARISONS_COLUMNS, "truth": STAGE_COLUMNS,
                 "estimates": {**STAGE_COLUMNS, "variant_key": pl.String()}}
#: The ``runs`` table.
RUNS_COLUMNS: dict[str, pl.DataType] = {
    "run_id": pl.String(), "experiment": pl.String(), "kind": pl.String(), "sweep": pl.String(),
    "job_num": pl.Int32(), "status": pl.String(), "started_at": pl.String(),
    "finished_at": pl.String(), "runs": pl.Int64(), "overrides": pl.String(),
    "error": pl.String(), "config_hash": pl.String(),
}
#: What ``list`` prints.
LIST_COLUMNS = ["run_id", "experiment", "kind", "sweep", "job_num", "status", "started_at",
                "runs", "overrides", "error"]
TABLE_NAMES = ("summary", "metrics", "runs", "per_run", "comparisons", "truth", "estimates")
#: Only the summary carries the run's config, one column per leaf (``"filters.vsimm.t1_mu"``).
CONFIG_TABLES = ("summary",)
#: The columns whose values name things (a typo in a literal compared with them matches no row):
#: the query warns when a literal is none of their values.
NAME_COLUMNS = ("experiment", "variant", "variant_key", "reference_key", "metric", "component", "series", "window")
#: What a query that names no table gets (the stage tables are large: read only when named).
DEFAULT_TABLES = ("summary", "metrics", "runs", "per_run", "comparisons")
ERROR_WIDTH = 120
DEFAULT_MAX_ROWS = 1000

Warn = Callable[[str], None]


class QueryError(ValueError):
    """Bad input (missing root, no runs, unknown table/column, SQL error). The message is
    meant for the user as is; the CLI prints it and exits with code 2."""


class QueryWarning(UserWarning):
    """A file was skipped (corrupt/truncated Parquet, unreadable status.json)."""


def _default_warn(msg: str) -> None:
    warnings.warn(msg, QueryWarning, stacklevel=3)


# ---- discovering run directories --------------------------------------------------------------
@dataclass(frozen=True)
class RunDir:
    path: Path       # absolute
    run_id: str      # relative to root, posix
    kind: str        # "run" | "multirun"


# depth below runs/ resp. multirun/ at which a run dir lacking status.json is still recognised
_EXPECTED_DEPTH = {"runs": 2, "multirun": 2}
_KIND = {"runs": "run", "multirun": "multirun"}


def _check_root(root: Path) -> Path:
    if not root.exists():
        raise QueryError(
            f"artifacts root '{root}' does not exist (working directory: {Path.cwd()}). "
            "Pass --root DIR pointing at the directory that holds runs/ and multirun/, "
            "i.e. the pipeline's artifacts directory.")
    if not root.is_dir():
        raise QueryError(f"artifacts root '{root}' is not a directory. Pass --root DIR pointing "
                         "at the directory that holds runs/ and multirun/.")
    return root


def discover_runs(root: Path) -> list[RunDir]:
    """Run/job directories under ``root/runs`` and ``root/multirun``, sorted by path.

    A directory is a run if it holds ``status.json``, or if it sits at the layout's depth
    (``runs/<exp>/<ts>``, ``multirun/<ts>/<job>``) and holds ``summary.parquet`` or
    ``metrics.parquet``. Hidden directories are never entered; run directories are not
    descended into (a sweep's aggregate ``summary.parquet`` next to its jobs is not a run).
    """
    found: list[RunDir] = []
    for top in ("runs", "multirun"):
        base = root / top
        if not base.is_dir():
            continue
        for dirpath, dirnames, filenames in os.walk(base):
            dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
            here = Path(dirpath)
            depth = len(here.relative_to(base).parts)
            names = set(filenames)
            if STATUS_FILE in names or (depth == _EXPECTED_DEPTH[top]
                                        and names & {SUMMARY_FILE, METRICS_FILE}):
                found.append(RunDir(here, here.relative_to(root).as_posix(), _KIND[top]))
                dirnames[:] = []
    found.sort(key=lambda r: r.run_id)
    return found


def _resolve_under_root(root: Path, d: Path | str, option: str) -> str:
    p = Path(d)
    candidates = [p] if p.is_absolute() else [root / p, Path.cwd() / p]
    for c in candidates:
        if c.is_dir():
            try:
                rel = c.resolve().relative_to(root.resolve()).as_posix()
            except ValueError:
                raise QueryError(f"{option} '{d}' is not inside the artifacts root '{root}'. "
                                 "Give it relative to the root (as in the run_id/sweep "
                                 "columns), relative to the working directory, or absolute.") from None
            return "" if rel == "." else rel
    raise QueryError(f"{option} '{d}': no such directory, neither under the artifacts root "
                     f"'{root}' nor relative to the working directory.")


def _sample(items: Sequence[str], n: int = 20) -> str:
    items = list(items)
    if not items:
        return "(none)"
    more = f", ... ({len(items) - n} more)" if len(items) > n else ""
    return ", ".join(items[:n]) + more


def _select_runs(root: Path, sweep: Path | str | None, run: Path | str | None) -> list[RunDir]:
    root = _check_root(Path(root))
    runs = discover_runs(root)
    if not runs:
        entries = sorted(p.name for p in root.iterdir() if not p.name.startswith("."))
        raise QueryError(
            f"no runs found under the artifacts root '{root}': expected "
            "runs/<experiment>/<timestamp>/status.json or "
            "multirun/<timestamp>/<job_num>/status.json. "
            f"The root holds: {_sample(entries)}. Pass --root DIR to point elsewhere.")
    if sweep is not None:
        s = _resolve_under_root(root, sweep, "--sweep")
        sel = [r for r in runs if s == "" or r.run_id.startswith(s + "/")]
        if not sel:
            sweeps = sorted({r.run_id.rsplit("/", 1)[0] for r in runs if r.kind == "multirun"})
            raise QueryError(f"--sweep '{sweep}' holds no runs or jobs. Sweeps under '{root}': "
                             f"{_sample(sweeps)}.")
        runs = sel
    if run is not None:
        r_id = _resolve_under_root(root, run, "--run")
        sel = [r for r in runs if r.run_id == r_id]
        if not sel:
            hint = (" It contains runs: use --sweep for a directory of jobs."
                    if any(r.run_id.startswith(r_id + "/") for r in runs) else "")
            raise QueryError(f"--run '{run}' is not a run or job directory.{hint} Runs: "
                             f"{_sample([r.run_id for r in runs])}.")
        runs = sel
    return runs


# ---- the runs table ---------------------------------------------------------------------------
def _one_line(text: object, width: int = ERROR_WIDTH) -> str | None:
    if text is None:
        return None
    lines = [ln.strip() for ln in str(text).strip().splitlines() if ln.strip()]
    if not lines:
        return None
    # a traceback's informative line is its last one; otherwise the first line says it
    line = lines[-1] if lines[0].startswith("Traceback") else lines[0]
    if len(lines) > 1 and line == lines[0]:
        line += " …"
    return line if len(line) <= width else line[: width - 1] + "…"


def _as_int(v: object) -> int | None:
    if isinstance(v, bool) or v is None:
        return None
    if isinstance(v, int):
        return v
    if isinstance(v, float) and v.is_integer():
        return int(v)
    if isinstance(v, str) and v.strip().lstrip("-").isdigit():
        return int(v)
    return None


def _status_row(r: RunDir, root: Path, warn: Warn) -> dict:
    parts = r.run_id.split("/")
    row: dict = {
        "run_id": r.run_id, "experiment": parts[1] if len(parts) > 1 else None, "kind": r.kind,
        "sweep": "/".join(parts[:-1]) if r.kind == "multirun" else None,
        "job_num": _as_int(parts[-1]) if r.kind == "multirun" else None,
        "status": None, "started_at": None, "finished_at": None, "runs": None,
        "overrides": None, "error": None, "config_hash": None,
    }
    path = r.path / STATUS_FILE
    if not path.is_file():
        row["status"] = "unknown"
        row["error"] = "no status.json"
        return row
    try:
        st = json.loads(path.read_text())
        if not isinstance(st, dict):
            raise ValueError("not a JSON object")
    except (OSError, ValueError) as e:
        warn(f"skipping unreadable {path}: {_one_line(e)}")
        row["status"] = "unknown"
        row["error"] = f"unreadable status.json: {_one_line(e)}"
        return row
    overrides = st.get("overrides")
    if isinstance(overrides, list):
        overrides = " ".join(str(o) for o in overrides)
    row.update({
        "experiment": st.get("experiment") or row["experiment"],
        "sweep": st.get("sweep", row["sweep"]),
        "job_num": _as_int(st.get("job_num", row["job_num"])),
        "status": st.get("status"), "started_at": st.get("started_at"),
        "finished_at": st.get("finished_at"), "runs": _as_int(st.get("runs")),
        "overrides": overrides if overrides is None else str(overrides),
        "error": _one_line(st.get("error")), "config_hash": st.get("config_hash"),
    })
    if row["status"] == "running":
        from pipeline.run.process import is_gone
        process = st.get("process")
        if is_gone(process):      # killed (SIGKILL, out of memory, power cut): it can no longer say so itself
            row["status"] = "interrupted"
            row["error"] = (f"its process (pid {process.get('pid')} on {process.get('host')}) ended without "
                            f"finishing the job; run the same command again to finish it from the cache")
    for k in ("experiment", "sweep", "status", "started_at", "finished_at", "config_hash"):
        if row[k] is not None:
            row[k] = str(row[k])
    return row


def _runs_frame(runs: Sequence[RunDir], root: Path, warn: Warn) -> pl.DataFrame:
    rows = [_status_row(r, root, warn) for r in runs]
    df = pl.DataFrame(rows, schema=RUNS_COLUMNS) if rows else pl.DataFrame(schema=RUNS_COLUMNS)
    return df.sort(["started_at", "run_id"], nulls_last=True)


def runs_frame(root: Path | str = "artifacts", sweep: Path | str | None = None,
               run: Path | str | None = None, *, warn: Warn | None = None) -> pl.DataFrame:
    """The ``runs`` table (eager): one row per run/job, sorted by ``started_at``."""
    root = Path(root)
    return _runs_frame(_select_runs(root, sweep, run), root, warn or _default_warn)


# ---- the Parquet tables -----------------------------------------------------------------------
_INT_BITS = {pl.Int8: 8, pl.Int16: 16, pl.Int32: 32, pl.Int64: 64, pl.Int128: 128,
             pl.UInt8: 8, pl.UInt16: 16, pl.UInt32: 32, pl.UInt64: 64}
_SIGNED = {pl.Int8, pl.Int16, pl.Int32, pl.Int64, pl.Int128}
_FLOATS = {pl.Float32, pl.Float64}


def _scan_castable(src: pl.DataType, dst: pl.DataType) -> bool:
    """Can ``scan_parquet(cast_options=_CAST)`` turn a file column of ``src`` into ``dst``?"""
    if src == dst or src == pl.Null:
        return True
    s, d = src.base_type(), dst.base_type()
    if s in _INT_BITS and d in _FLOATS:
        return True                                          # integer_cast="allow-float"
    if s in _INT_BITS and d in _INT_BITS:                    # integer_cast="upcast", lossless
        if (s in _SIGNED) == (d in _SIGNED):
            return _INT_BITS[s] <= _INT_BITS[d]
        return s not in _SIGNED and _INT_BITS[s] < _INT_BITS[d]
    return s == pl.Float32 and d == pl.Float64               # float_cast="upcast"


def _cast_options() -> pl.ScanCastOptions:
    with warnings.catch_warnings():          # "ScanCastOptions is considered unstable"
        warnings.simplefilter("ignore")
        return pl.ScanCastOptions(integer_cast=["upcast", "allow-float"], float_cast="upcast")


def _cast_to(name: str, src: pl.DataType, dst: pl.DataType) -> pl.Expr:
    col = pl.col(name)
    if src.is_nested() and dst == pl.String:       # a list config leaf -> JSON text
        text = (pl.struct(col.alias("v")).struct.json_encode()
                .str.strip_prefix('{"v":').str.strip_suffix("}"))
        return pl.when(col.is_null()).then(None).otherwise(text).alias(name)
    return col.cast(dst, strict=False)


@dataclass
class _ParquetTable:
    name: str
    files: list[Path] = field(default_factory=list)
    schemas: list[pl.Schema] = field(default_factory=list)
    constants: dict[Path, dict[str, str]] = field(default_factory=dict)   # a stage file's run_id, ...

    def add(self, path: Path, warn: Warn, constants: Mapping[str, str] | None = None,
            folder: RunDir | None = None, status: Mapping | None = None) -> None:
        from pipeline.storage.run_tables import TableRefused, check_run_table
        from pipeline.storage.store import TableDamaged, read_table
        try:
            # read whole and checked against the content checksum stored when it was written: a
            # file that still parses after damage must not answer a query (pipeline.storage.store);
            # and, in a run folder, against the folder: a checksum it has, this run's id, config
            # hash and cache keys (pipeline.storage.run_tables)
            df, meta = read_table(path)
            if folder is not None:
                check_run_table(path, df, meta, status, path.relative_to(folder.path).as_posix())
            schema = df.schema
            del df
        except TableRefused as e:
            warn(f"skipping {_one_line(e, 400)}")
            return
        except TableDamaged as e:
            warn(f"skipping damaged {_one_line(e)}")
            return
        except Exception as e:  # noqa: BLE001 - any unreadable file: skip the file, keep going
            warn(f"skipping corrupt or truncated {path}: {_one_line(e)}")
            return
        if constants:
            self.constants[path] = dict(constants)
            schema = pl.Schema({**{k: pl.String() for k in constants}, **schema})
        self.files.append(path)
        self.schemas.append(schema)

    def drop(self, bad: set[Path]) -> None:
        keep = [i for i, f in enumerate(self.files) if f not in bad]
        self.files = [self.files[i] for i in keep]
        self.schemas = [self.schemas[i] for i in keep]

    def target_schema(self, warn: Warn | None = None) -> pl.Schema:
        """The superset of all files' columns, each at the supertype of its dtypes. Files whose
        dtypes have no common supertype with the others (e.g. list vs float) are dropped."""
        fixed = FIXED_COLUMNS[self.name]
        union = pl.DataFrame(schema=fixed)
        distinct: dict[tuple, pl.Schema] = {}
        for s in self.schemas:
            distinct.setdefault(tuple(s.items()), s)
        bad: set[tuple] = set()
        for key, s in distinct.items():
            try:
                union = pl.concat([union, pl.DataFrame(schema=s)], how="diagonal_relaxed")
            except pl.exceptions.PolarsError as e:
                bad.add(key)
                for f, fs in zip(self.files, self.schemas):
                    if tuple(fs.items()) == key and warn is not None:
                        warn(f"skipping {f}: its column types clash with the other "
                             f"{self.name} files ({_first_paragraph(str(e))})")
        if bad:
            self.drop({f for f, fs in zip(self.files, self.schemas) if tuple(fs.items()) in bad})
        order = list(fixed) + sorted(c for c in union.columns if c not in fixed)
        return pl.Schema({c: union.schema[c] for c in order})

    def lazy(self, warn: Warn | None = None) -> pl.LazyFrame:
        target = self.target_schema(warn)
        if not self.files:
            return pl.LazyFrame(schema=target)
        if self.name in STAGE_TABLES:        # per file: its run folder's columns, then the union
            parts = [pl.scan_parquet(f, glob=False).select(
                        *[pl.lit(v, dtype=pl.String).alias(k) for k, v in self.constants.get(f, {}).items()], pl.all())
                     for f in self.files]
            return pl.concat(parts, how="diagonal_relaxed").select(
                [pl.col(c) if c in set().union(*[set(s) for s in self.schemas]) else pl.lit(None, dtype=dt).alias(c)
                 for c, dt in target.items()])
        fast: list[str] = []
        slow: dict[tuple, list[str]] = {}
        for f, s in zip(self.files, self.schemas):
            if all(_scan_castable(dt, target[c]) for c, dt in s.items()):
                fast.append(str(f))
            else:
                slow.setdefault(tuple(s.items()), []).append(str(f))
        parts: list[pl.LazyFrame] = []
        if fast:   # one scan for (nearly) everything: the fast path measured in the module doc
            parts.append(pl.scan_parquet(fast, schema=target, missing_columns="insert",
                                         cast_options=_cast_options(), glob=False,
                                         hidden_file_prefix="."))
        for key, files in slow.items():   # casts the scanner refuses (int -> str, list -> str)
            have = dict(key)
            lf = pl.scan_parquet(files, glob=False, hidden_file_prefix=".")
            parts.append(lf.select([_cast_to(c, have[c], dt) if c in have
                                    else pl.lit(None, dtype=dt).alias(c)
                                    for c, dt in target.items()]))
        return parts[0] if len(parts) == 1 else pl.concat(parts, how="vertical")

    def validate(self, warn: Warn) -> bool:
        """Read every file in full; drop (and warn about) those that fail. True if any failed."""
        bad = set()
        for f in self.files:
            try:
                pl.read_parquet(f)
            except FileNotFoundError:
                warn(f"skipping {f}: it was removed while the query read it")
                bad.add(f)
            except Exception as e:  # noqa: BLE001
                warn(f"skipping corrupt {f}: {_one_line(e)}")
                bad.add(f)
        self.drop(bad)
        return bool(bad)


@dataclass
class _Catalog:
    """The selected run dirs; each Parquet table's footers are read on first use only."""
    root: Path
    run_dirs: list[RunDir]
    warn: Warn
    runs: pl.DataFrame
    tables: dict[str, _ParquetTable] = field(default_factory=dict)

    def table(self, name: str) -> _ParquetTable:
        from pipeline.storage.run_tables import read_status
        if name not in self.tables:
            t = _ParquetTable(name)
            experiments = dict(zip(self.runs["run_id"].to_list(), self.runs["experiment"].to_list())) \
                if self.runs.height else {}
            for r in self.run_dirs:
                status = read_status(r.path)
                if name == "estimates":
                    folder = r.path / "estimates"
                    for p in sorted(folder.glob("*.parquet")) if folder.is_dir() else []:
                        if not p.name.startswith("."):
                            t.add(p, self.warn, {"run_id": r.run_id, "experiment": experiments.get(r.run_id),
                                                 "variant_key": p.stem}, r, status)
                    continue
                p = r.path / TABLE_FILES[name]
                if p.is_file():
                    t.add(p, self.warn, {"run_id": r.run_id, "experiment": experiments.get(r.run_id)}
                          if name in STAGE_TABLES else None, r, status)
            self.tables[name] = t
        return self.tables[name]

    def lazy(self, names: Iterable[str] = DEFAULT_TABLES) -> dict[str, pl.LazyFrame]:
        return {n: self.runs.lazy() if n == "runs" else self.table(n).lazy(self.warn)
                for n in names}


def _catalog(root: Path | str, sweep: Path | str | None, run: Path | str | None,
             warn: Warn) -> _Catalog:
    root = Path(root)
    runs = _select_runs(root, sweep, run)
    return _Catalog(root, runs, warn, _runs_frame(runs, root, warn))


def load_tables(root: Path | str = "artifacts", sweep: Path | str | None = None,
                run: Path | str | None = None, *, warn: Warn | None = None) -> dict[str, pl.LazyFrame]:
    """The tables ``summary``, ``metrics`` and ``runs`` as LazyFrames.

    :param root: the artifacts directory (holds ``runs/`` and ``multirun/``).
    :param sweep: restrict to the jobs of one sweep directory (relative to ``root``, to the
        working directory, or absolute).
    :param run: restrict to one run or job directory.
    :param warn: called with a message for each skipped file; default ``warnings.warn``
        with :class:`QueryWarning`.
    :raises QueryError: missing/empty root, unknown sweep/run.
    """
    return _catalog(root, sweep, run, warn or _default_warn).lazy()


# ---- SQL ----------------------------------------------------------------------------------------
QUOTING_HELP = (
    'Quote column names that contain dots or clash with SQL keywords in double quotes, e.g. '
    '"filters.vsimm.t1_mu", "mc.runs", "window"; string literals take single quotes: '
    "metric = 'position_rmse'.")


def _first_paragraph(msg: str) -> str:
    msg = str(msg).split("\n\nResolved plan")[0].split("\n\nThis error occurred")[0]
    msg = re.sub(r";\s*valid columns: \[.*?\]", "", msg, flags=re.DOTALL)   # we list them per table
    return " ".join(msg.split()).rstrip(".")


def _schemas(tables: Mapping[str, pl.LazyFrame]) -> dict[str, pl.Schema]:
    return {n: lf.collect_schema() for n, lf in tables.items()}


def is_config_column(table: str, column: str) -> bool:
    """A config leaf's column (only the summary has them: every column beyond SUMMARY_COLUMNS)."""
    return table in CONFIG_TABLES and column not in FIXED_COLUMNS[table]


def _quoted(column: str) -> str:
    return column if re.fullmatch(r"[a-z_][a-z0-9_]*", column) else f'"{column}"'


def _named_tables(tables: Mapping[str, pl.LazyFrame], sql: str) -> list[str]:
    return [n for n in tables if re.search(rf"\b{n}\b", sql, re.IGNORECASE)] or list(tables)


def close_names(name: str, candidates: Iterable[str], n: int = 6) -> list[str]:
    """The candidates closest to ``name`` (difflib, case-insensitive), those it is the last dotted part
    of (``t1_mu`` -> ``filters.vsimm.t1_mu``) and those it begins (``posit`` -> ``position_rmse``), in
    that order, at most ``n``."""
    import difflib

    by_lower: dict[str, list[str]] = {}
    for c in candidates:
        by_lower.setdefault(str(c).lower(), []).append(str(c))
    low = name.lower()
    found = [c for c in by_lower.get(low, [])]
    found += [c for k, cs in by_lower.items() if k != low and (k.endswith("." + low) or k.split(".")[-1] == low)
              for c in cs]
    found += [c for k in difflib.get_close_matches(low, list(by_lower), n=n, cutoff=0.6) for c in by_lower[k]]
    if len(low) >= 3:                            # a name cut short: 'posit' -> 'position_rmse'
        found += [c for k in sorted(by_lower) if k.startswith(low) for c in by_lower[k]]
    return list(dict.fromkeys(found))[:n]


def _column_hint(name: str, schemas: Mapping[str, pl.Schema], named: Sequence[str]) -> str:
    """Close column names of the named tables, or (none close) their columns without the config columns."""
    where: dict[str, list[str]] = {}
    for t in named:
        for c in close_names(name, schemas[t]):
            where.setdefault(c, []).append(t)
    more = "`mtt-query tables` lists every table's columns (`--config` with the config columns)"
    if where:
        ranked = close_names(name, list(where))
        return ("Close column names: " + ", ".join(f"{_quoted(c)} ({', '.join(where[c])})" for c in ranked)
                + f". Columns: {more}.")
    parts = []
    for t in named:
        shown = [c for c in schemas[t] if not is_config_column(t, c)]
        hidden = len(schemas[t]) - len(shown)
        parts.append(f"{t}: " + ", ".join(_quoted(c) for c in shown)
                     + (f" and {hidden} config columns" if hidden else ""))
    return f"No column is named like it. Columns: {'; '.join(parts)}. {more}."


_MISSING_COLUMN = (re.compile(r'unable to find column "([^"]+)"'), re.compile(r"no column named '([^']+)' found"))
_STRUCT = re.compile(r"no table or struct column named '([^']+)' found")


def _missing_name(msg: str, sql: str) -> str | None:
    for pattern in _MISSING_COLUMN:
        found = pattern.search(msg)
        if found:
            return found.group(1)
    found = _STRUCT.search(msg)
    if found:          # an unquoted dotted name: its first part is taken for a table; the whole name is meant
        prefix = re.escape(found.group(1))
        dotted = re.search(rf'(?<![\w."]){prefix}(?:\.[A-Za-z_]\w*)+', sql)
        return dotted.group(0) if dotted else found.group(1)
    return None


def _sql_error(e: Exception, sql: str, tables: Mapping[str, pl.LazyFrame]) -> QueryError:
    msg = _first_paragraph(str(e))
    msg = re.sub(r"\s*Did you mean [^?]*\?", "", msg).rstrip(". ")         # we say which ones, from every table
    low = msg.lower()
    names = ", ".join(TABLE_NAMES)
    if ("relation" in low and "not found" in low) or (
            "table" in low and "not found" in low and "column" not in low):
        return QueryError(f"SQL error: {msg}. The tables are: {', '.join(TABLE_NAMES)} "
                          "(`mtt-query tables` lists their columns).")
    if isinstance(e, pl.exceptions.ColumnNotFoundError) or ("column" in low and (
            "not found" in low or "unable to find" in low or "no column" in low
            or "struct column" in low)):
        dotted = " A dotted name must be double-quoted as a whole." if "struct column" in low else ""
        name = _missing_name(msg, sql)
        schemas = _schemas(tables)
        hint = _column_hint(name, schemas, _named_tables(tables, sql)) if name else \
            "Columns: `mtt-query tables` lists every table's columns (`--config` with the config columns)."
        return QueryError(f"SQL error: {msg}.{dotted} {hint} {QUOTING_HELP}")
    if "parser error" in low or isinstance(e, pl.exceptions.SQLSyntaxError):
        return QueryError(f"SQL syntax error: {msg}. {QUOTING_HELP} In a shell, wrap the query "
                          "in double quotes and escape the inner ones, or pass it on stdin "
                          "(`mtt-query sql -`) or from a file (`--file q.sql`). "
                          f"Tables: {names}.")
    return QueryError(f"query failed: {msg}. Tables: {names} (`mtt-query tables` lists their "
                      f"columns). {QUOTING_HELP}")


# ---- literals that name nothing -------------------------------------------------------------
_STRING = re.compile(r"'(?:[^']|'')*'")
_NAME_COLUMN = (r'(?<![\w."])(?:[A-Za-z_]\w*\.)?(?P<q>"?)(?P<col>' + "|".join(NAME_COLUMNS)
                + r')(?P=q)(?![\w."])')
_LITERAL = r"(?P<lit>'(?:[^']|'')*')"
_COMPARED = re.compile(_NAME_COLUMN + r"\s*(?P<op>==|=|<>|!=|(?:NOT\s+)?I?LIKE)\s*" + _LITERAL, re.IGNORECASE)
_REVERSED = re.compile(_LITERAL + r"\s*(?P<op>==|=|<>|!=)\s*" + _NAME_COLUMN, re.IGNORECASE)
_IN_LIST = re.compile(_NAME_COLUMN + r"\s+(?P<op>(?:NOT\s+)?IN)\s*\((?P<list>\s*'(?:[^']|'')*'(?:\s*,\s*'(?:[^']|'')*')*\s*)\)",
                      re.IGNORECASE)


@dataclass(frozen=True)
class _Compared:
    column: str
    op: str
    literal: str
    position: int = 0


def compared_literals(sql: str) -> list[_Compared]:
    """String literals compared with a name column (metric = 'x', 'x' = series, s."window" IN ('a', 'b'),
    variant LIKE 'AO%'), outside string literals."""
    spans = [m.span() for m in _STRING.finditer(sql)]

    def outside(pos: int) -> bool:
        return not any(a < pos < b for a, b in spans)

    out = []
    for pattern in (_COMPARED, _REVERSED):
        for m in pattern.finditer(sql):
            if outside(m.start()) and outside(m.start("col")):
                out.append(_Compared(m.group("col").lower(), " ".join(m.group("op").upper().split()),
                                     m.group("lit")[1:-1].replace("''", "'"), m.start("lit")))
    for m in _IN_LIST.finditer(sql):
        if outside(m.start()):
            op = " ".join(m.group("op").upper().split())
            out += [_Compared(m.group("col").lower(), op, lit.group(0)[1:-1].replace("''", "'"),
                              m.start("list") + lit.start()) for lit in _STRING.finditer(m.group("list"))]
    return sorted(out, key=lambda c: c.position)


def _like(pattern: str, insensitive: bool) -> re.Pattern[str]:
    parts = ["." if ch == "_" else ".*" if ch == "%" else re.escape(ch) for ch in pattern]
    return re.compile("".join(parts), re.IGNORECASE | re.DOTALL if insensitive else re.DOTALL)


def check_literals(sql: str, tables: Mapping[str, pl.LazyFrame], warn: Warn) -> None:
    """Warn, once per literal, where a string compared with a name column (metric, series, variant,
    window, ...) is none of that column's values in the tables the query reads: ``metric = 'pos_rmse'``
    silently matches no row. The warning names the close values (difflib) or, none close, some values."""
    compared = compared_literals(sql)
    if not compared:
        return
    named = _named_tables(tables, sql)
    schemas = _schemas({n: tables[n] for n in named})
    values: dict[str, tuple[list[str], list[str]]] = {}
    for column in dict.fromkeys(c.column for c in compared):
        having = [t for t in named if column in schemas[t]]
        if not having:
            continue
        frames = [tables[t].select(pl.col(column).cast(pl.String)).unique() for t in having]
        found = pl.concat(frames).unique().collect()[column].drop_nulls().sort().to_list()
        values[column] = (found, having)
    said = set()
    for c in compared:
        if c.column not in values or (c.column, c.literal) in said:
            continue
        present, having = values[c.column]
        if "LIKE" in c.op:
            matcher = _like(c.literal, c.op.endswith("ILIKE"))
            if any(matcher.fullmatch(v) for v in present):
                continue
            probe, what = c.literal.replace("%", ""), f"no {c.column} matches {c.op} '{c.literal}'"
        else:
            if c.literal in present:
                continue
            probe, what = c.literal, f"'{c.literal}' is no {c.column}"
        said.add((c.column, c.literal))
        effect = "excluding it excludes nothing" if c.op.startswith("NOT") or c.op in ("<>", "!=") \
            else "comparing with it matches no row"
        close = close_names(probe, present)
        listed = (f"close: {', '.join(repr(v) for v in close)}" if close
                  else f"its values: {_sample([repr(v) for v in present], 12)}")
        warn(f"{what} in {', '.join(having)} ({effect}); {listed}. "
             f"`mtt-query tables` lists each experiment's metrics, series and windows.")


def _execute(sql: str, tables: Mapping[str, pl.LazyFrame]) -> pl.DataFrame:
    ctx = pl.SQLContext(frames=dict(tables), eager=False)
    res = ctx.execute(sql, eager=False)
    return res.collect() if isinstance(res, pl.LazyFrame) else res


def _is_file_error(e: Exception) -> bool:
    return isinstance(e, (pl.exceptions.ComputeError, OSError)) and (
        "parquet" in str(e).lower() or isinstance(e, OSError))


# polars SQL's table functions read any file the user can (read_csv('/etc/passwd')): the query
# command and the report expose the project's tables only
FILE_FUNCTIONS = re.compile(r"\bread_(csv|parquet|json|ndjson|ipc|delta|excel|database)\s*\(", re.IGNORECASE)


def check_tables_only(sql: str) -> None:
    """Refuse SQL that reads files through a table function (read_csv, read_parquet, ...)."""
    found = FILE_FUNCTIONS.search(sql or "")
    if found:
        raise QueryError(f"{found.group(0).rstrip('(').strip()}(...): queries read the project's tables only "
                         f"({', '.join(TABLE_NAMES)} here; summary, metrics and wide in a report), not files; "
                         f"select from those tables instead.")


def _run_sql(sql: str, cat: _Catalog, warn: Warn) -> pl.DataFrame:
    if not sql or not sql.strip():
        raise QueryError(f"empty SQL query. Tables: {', '.join(TABLE_NAMES)}. {QUOTING_HELP}")
    check_tables_only(sql)
    # read the footers only of the tables the query names (all of them if it names none)
    names = [n for n in TABLE_NAMES if re.search(rf"\b{n}\b", sql, re.IGNORECASE)] or DEFAULT_TABLES
    tables = cat.lazy(names)
    try:
        result = _execute(sql, tables)
        check_literals(sql, tables, warn)
        return result
    except (pl.exceptions.PolarsError, OSError) as e:
        # A file whose footer reads fine but whose data pages are damaged fails only at
        # collect time, without a file name, and so does one removed since (a run folder deleted
        # while the query ran, polars' FileNotFoundError): find it, skip it, run again.
        if _is_file_error(e) and any([t.validate(warn) for t in cat.tables.values()]):
            tables = cat.lazy(names)
            try:
                return _execute(sql, tables)
            except (pl.exceptions.PolarsError, OSError) as e2:
                raise _sql_error(e2, sql, tables) from None
        raise _sql_error(e, sql, tables) from None


def query(sql: str, root: Path | str = "artifacts", sweep: Path | str | None = None,
          run: Path | str | None = None, *, warn: Warn | None = None) -> pl.DataFrame:
    """Run ``sql`` (polars SQL) over ``summary``, ``metrics`` and ``runs``; return a DataFrame.

    Example: ``query('SELECT variant, "filters.vsimm.t1_mu", AVG(value) FROM summary WHERE
    series = \\'acceleration_rmse_x\\' AND "window" = \\'all\\' GROUP BY ALL ORDER BY ALL')``.

    :raises QueryError: with a user-facing message for bad input or a failing query.
    """
    warn = warn or _default_warn
    return _run_sql(sql, _catalog(root, sweep, run, warn), warn)


def tables_frame(tables: Mapping[str, pl.LazyFrame], config: bool = True) -> pl.DataFrame:
    """table, column, dtype of every column; ``config=False`` leaves out the summary's config columns."""
    rows = [(n, c, str(dt)) for n, s in _schemas(tables).items() for c, dt in s.items()
            if config or not is_config_column(n, c)]
    return pl.DataFrame(rows, schema={"table": pl.String, "column": pl.String, "dtype": pl.String},
                        orient="row")


LIST_WIDTH = 8          # series listed per metric before "... (N more)"
WRAP = 100              # the overview's line width


def experiments_frame(tables: Mapping[str, pl.LazyFrame]) -> pl.DataFrame:
    """Per experiment: its run folders, their Monte Carlo sizes (n_runs) and its variants, from the summary."""
    df = tables["summary"].select("experiment", "run_id", "variant", "variant_key", "n_runs").collect()
    rows = []
    for (experiment,), part in df.group_by("experiment", maintain_order=True):
        named = part.drop_nulls("variant_key").unique(["variant", "variant_key"], maintain_order=True)
        rows.append((experiment, part["run_id"].n_unique(), sorted(part["n_runs"].drop_nulls().unique().to_list()),
                     named["variant"].to_list(), named["variant_key"].to_list()))
    return pl.DataFrame(rows, schema={"experiment": pl.String, "runs": pl.Int64, "n_runs": pl.List(pl.Int32),
                                      "variants": pl.List(pl.String), "variant_keys": pl.List(pl.String)},
                        orient="row").sort("experiment", nulls_last=True)


def metrics_overview_frame(tables: Mapping[str, pl.LazyFrame]) -> pl.DataFrame:
    """Per experiment and metric (the quantity): its series (the breakdowns), the summary's windows it has
    a value in (null: window-free, "window" IS NULL) and whether the metrics table has it per step."""
    metric = pl.coalesce("metric", "series").alias("metric")         # a summary from before the tidy columns: its series
    summary = tables["summary"].select("experiment", metric, "series", "window").drop_nulls(["metric"]).collect()
    per_step: set[tuple[str, str]] = set()
    if "metrics" in tables:
        steps = tables["metrics"].select("experiment", metric).unique().collect()
        per_step = set(zip(steps["experiment"].to_list(), steps["metric"].to_list()))
    rows = []
    for (experiment, metric), part in summary.group_by(["experiment", "metric"], maintain_order=True):
        rows.append((experiment, metric, part["series"].unique(maintain_order=True).to_list(),
                     part["window"].unique(maintain_order=True).to_list(), (experiment, metric) in per_step))
    return pl.DataFrame(rows, schema={"experiment": pl.String, "metric": pl.String, "series": pl.List(pl.String),
                                      "windows": pl.List(pl.String), "per_step": pl.Boolean},
                        orient="row").sort(["experiment", "metric"], nulls_last=True)


def tables_overview(root: Path | str = "artifacts", sweep: Path | str | None = None, run: Path | str | None = None,
                    *, config: bool = False, warn: Warn | None = None) -> dict[str, pl.DataFrame]:
    """What ``mtt-query tables`` prints: ``experiments`` (run folders, n_runs, variants), ``metrics`` (per
    experiment and metric its series, windows and whether it is per step) and ``columns`` (the tables'
    columns; the summary's config columns only with ``config``)."""
    cat = _catalog(root, sweep, run, warn or _default_warn)
    tables = cat.lazy()
    return {"experiments": experiments_frame(tables), "metrics": metrics_overview_frame(tables),
            "columns": tables_frame(tables, config)}


def _metric_names(part: pl.DataFrame) -> list[str]:
    """One group's metrics as listed: the series where they differ from the metric, a consistency band
    folded into its metric ("nees (+_lower,_upper)"), 4 or more of one family as "fault_runs_* (6)"."""
    series = dict(zip(part["metric"].to_list(), part["series"].to_list()))
    names = sorted(series)
    folded = {m for m in names for b in ("_lower", "_upper") if m.endswith(b) and m[: -len(b)] in series}
    family: dict[str, list[str]] = {}
    for m in names:
        if m not in folded and m.count("_") >= 2:
            family.setdefault("_".join(m.split("_")[:2]) + "_", []).append(m)
    families = {prefix: ms for prefix, ms in family.items() if len(ms) >= 4}
    in_family = {m for ms in families.values() for m in ms}
    out = []
    for m in names:
        if m in folded or m in in_family:
            continue
        text = m if series[m] == [m] else f"{m} (series {_sample(series[m], LIST_WIDTH)})"
        bands = [b for b in ("_lower", "_upper") if m + b in folded]
        out.append(text + (" (+" + ",".join(bands) + ")" if bands else ""))
    out += [f"{prefix}* ({len(ms)})" for prefix, ms in families.items()]
    return sorted(out)


def overview_text(frames: Mapping[str, pl.DataFrame], markdown: bool = False) -> str:
    """Per experiment: its runs, variants, and its metrics grouped by the windows they have values in."""
    import textwrap

    lines = ['What each experiment holds. summary, per_run and comparisons: one row per variant x series x '
             '"window" (metric = the quantity, series = its breakdown by axis, sensor, target); metrics: per step '
             '(where marked). Compare only rows of one experiment and one n_runs.', ""]
    metrics = frames["metrics"]
    for row in frames["experiments"].iter_rows(named=True):
        variants = ", ".join(f"{v} ({k})" if v != k else k for v, k in zip(row["variants"], row["variant_keys"]))
        head = (f"{row['experiment']}: {row['runs']} run folder{'s' if row['runs'] != 1 else ''} "
                f"(n_runs {', '.join(str(n) for n in row['n_runs'])}); variants {variants}")
        lines.append(f"### {head}" if markdown else textwrap.fill(head, WRAP, subsequent_indent="    "))
        mine = metrics.filter(pl.col("experiment") == row["experiment"]).with_columns(
            pl.col("windows").list.eval(pl.element().fill_null("<NULL>")).list.join(", ").alias("key"))
        groups = mine.group_by(["key", "per_step"], maintain_order=True).agg("metric", "series", "windows")
        groups = groups.with_columns(pl.col("metric").list.len().alias("n")).sort(
            [pl.col("key") == "<NULL>", pl.col("per_step").not_(), pl.col("n")], descending=[False, False, True])
        for g in groups.iter_rows(named=True):
            windows = [w for w in g["windows"][0] if w is not None]
            where = ('"window" IS NULL' if not windows else
                     '"window" ' + ", ".join(f"'{w}'" for w in windows) + (" or NULL" if None in g["windows"][0] else ""))
            where += "; per step in metrics too" if g["per_step"] else ""
            part = pl.DataFrame({"metric": g["metric"], "series": g["series"]})
            names = ", ".join(f"`{n}`" if markdown else n for n in _metric_names(part))
            if markdown:
                lines.append(f"- {where}: {names}")
            else:
                lines.append(textwrap.fill(where + ":", WRAP, initial_indent="  ", subsequent_indent="      "))
                lines.append(textwrap.fill(names.replace(" (+", "\0(+"), WRAP, initial_indent="      ",
                                           subsequent_indent="      ", break_on_hyphens=False).replace("\0", " "))
        lines.append("")
    return "\n".join(lines) + "\n"


def render_overview(frames: Mapping[str, pl.DataFrame], fmt: str, config: bool, hidden: int) -> str:
    """The ``tables`` command's output: the overview per experiment, then the columns (csv: the columns only)."""
    if fmt == "csv":
        return render(frames["columns"], fmt)
    title = "Columns"
    if not config and hidden:
        title += (f" ({hidden} config columns of summary left out, one per config leaf such as "
                  f"\"mc.runs\": `mtt-query tables --config` lists them)")
    heading = f"## {title}\n\n" if fmt == "markdown" else f"{title}:\n"
    return overview_text(frames, markdown=fmt == "markdown") + "\n" + heading + render(frames["columns"], fmt, max_rows=0)


# ---- output ---------------------------------------------------------------------------------
def _plain(df: pl.DataFrame) -> pl.DataFrame:
    """Nested columns (lists, structs, arrays) as JSON text, for csv/markdown."""
    nested = [c for c, dt in df.schema.items() if dt.is_nested() or dt == pl.Object]
    if not nested:
        return df
    return df.with_columns(pl.Series(c, [None if v is None else json.dumps(v, default=str)
                                         for v in df[c].to_list()], dtype=pl.String)
                           for c in nested)


def _md_cell(v: object) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        if not math.isfinite(v):
            return str(v)
        text = format(v, ".6g")
        return text + ".0" if v.is_integer() and text == str(int(v)) else text
    text = str(v)
    return text.replace("\\", "\\\\").replace("|", "\\|").replace("\r\n", "<br>").replace("\n", "<br>")


def to_markdown(df: pl.DataFrame) -> str:
    """A GitHub-flavoured Markdown table (``|`` escaped, newlines as ``<br>``, null empty,
    floats to 6 significant digits, numeric columns right-aligned)."""
    df = _plain(df)
    header = [_md_cell(c) for c in df.columns]
    rows = [[_md_cell(v) for v in row] for row in df.iter_rows()]
    widths = [max([3, len(h)] + [len(r[i]) for r in rows]) for i, h in enumerate(header)]
    numeric = [dt.is_numeric() for dt in df.dtypes]
    sep = ["-" * (w - 1) + ":" if num else "-" * w for w, num in zip(widths, numeric)]

    def line(cells: Iterable[str]) -> str:
        return "| " + " | ".join(c.rjust(w) if num else c.ljust(w)
                                 for c, w, num in zip(cells, widths, numeric)) + " |"
    return "\n".join([line(header), "| " + " | ".join(sep) + " |"] + [line(r) for r in rows]) + "\n"


def to_table(df: pl.DataFrame, max_rows: int | None = DEFAULT_MAX_ROWS) -> str:
    """polars' box table with every column shown in full and up to ``max_rows`` rows."""
    longest = max([8] + [len(c) for c in df.columns])      # headers are cut at this length too
    for c, dt in df.schema.items():
        if dt == pl.String and df.height:
            longest = max(longest, df[c].str.len_chars().max() or 0)
    with pl.Config(tbl_rows=-1 if not max_rows else max_rows, tbl_cols=-1,
                   fmt_str_lengths=min(longest, 10_000), fmt_table_cell_list_len=-1,
                   tbl_width_chars=65_000):     # must fit in u16, polars panics above
        return str(df)


def render(df: pl.DataFrame, fmt: str, max_rows: int | None = DEFAULT_MAX_ROWS) -> str:
    if fmt == "csv":
        return _plain(df).write_csv()
    if fmt == "markdown":
        return to_markdown(df)
    return to_table(df, max_rows) + "\n"


# ---- CLI ----------------------------------------------------------------------------------------
EXAMPLE_SQL = ('SELECT variant, "filters.vsimm.t1_mu", AVG(value) FROM summary '
               "WHERE series = 'acceleration_rmse_x' AND \"window\" = 'all' "
               "GROUP BY ALL ORDER BY ALL")

DESCRIPTION = """\
Query the pipeline's artifacts (runs/, multirun/ under --root) with SQL.

Tables: summary (every summary.parquet: one row per variant x metric x window, plus one
column per config leaf named by its dotted key), metrics (every metrics.parquet: per-step
series), runs (one row per run/job from status.json; the `list` frame), per_run, comparisons
(and truth, estimates when named). `mtt-query tables` lists each experiment's variants, metrics
and windows first. A string compared with a name column (metric = 'pos_rmse') that is none of its
values is warned about on stderr, with the close names.

Tracking (pipeline.results.tracking): `runs` lists runs with the code that made them (commit,
dirty flag, code hash), their tags and notes; `diff RUN_A RUN_B` shows what differs (config, code,
every metric's difference paired by Monte Carlo run where the data match); `tag`, `note`, `rm`;
`gc` frees unreferenced cache entries; `export-mlflow` writes runs into an MLflow store."""

SQL_EPILOG = """\
quoting:
  Column names with dots, or that are SQL keywords, go in double quotes: "filters.vsimm.t1_mu",
  "mc.runs", "window". String literals go in single quotes: series = 'position_rmse'.
  In a POSIX shell, wrap the whole query in double quotes and escape the inner double quotes:
    mtt-query sql "SELECT variant, \\"filters.vsimm.t1_mu\\", AVG(value) FROM summary
                   WHERE series = 'acceleration_rmse_x' AND \\"window\\" = 'all'
                   GROUP BY ALL ORDER BY ALL"
  or avoid shell quoting altogether with a here-document on stdin:
    mtt-query sql - <<'SQL'
    SELECT variant, "filters.vsimm.t1_mu", AVG(value) AS rmse FROM summary
    WHERE series = 'acceleration_rmse_x' AND "window" = 'all' GROUP BY ALL ORDER BY ALL
    SQL
  or put the query in a file: mtt-query sql --file q.sql

more examples:
  mtt-query sql --sweep multirun/2026-11-22_10-00-00_000000 "SELECT series, variant, \\
      AVG(value) FROM summary WHERE status = 'ok' GROUP BY ALL ORDER BY ALL"
  mtt-query sql "SELECT run_id, error FROM runs WHERE status = 'failed'"
  mtt-query sql --format csv "SELECT * FROM metrics WHERE series = 'position_rmse'" > pos.csv

The SQL dialect is polars' (PostgreSQL-like; GROUP BY ALL, ORDER BY ALL, QUALIFY, ...)."""


def _common(p: argparse.ArgumentParser, *, fmt: bool = True) -> None:
    p.add_argument("--root", type=Path, default=Path("artifacts"),
                   help="artifacts directory holding runs/ and multirun/ (default: artifacts)")
    p.add_argument("--sweep", metavar="DIR",
                   help="only the jobs of this sweep directory (relative to --root, e.g. "
                        "multirun/<timestamp>, or a path)")
    p.add_argument("--run", metavar="DIR",
                   help="only this run or job directory (relative to --root, or a path)")
    if fmt:
        p.add_argument("--format", choices=["table", "csv", "markdown"], default="table",
                       help="output format (default: table)")
        p.add_argument("--max-rows", type=int, default=DEFAULT_MAX_ROWS, metavar="N",
                       help=f"table format: rows shown before eliding the middle "
                            f"(default {DEFAULT_MAX_ROWS}; 0 = all). csv/markdown print all.")


def build_parser(more: Any = None) -> argparse.ArgumentParser:
    """``mtt-query``'s parser; ``more``: a module adding commands (``add_commands(subparsers)``;
    pipeline.results.cli passes the tracking commands)."""
    parser = argparse.ArgumentParser(prog="mtt-query", description=DESCRIPTION,
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=f"example:\n  mtt-query sql - <<'SQL'\n  {EXAMPLE_SQL}\n  SQL\n\n"
                                            "`mtt-query sql -h` explains quoting.")
    sub = parser.add_subparsers(dest="command", required=True,
                                metavar="{list,tables,sql,runs,diff,tag,note,rm,gc,export-mlflow}")
    p = sub.add_parser("list", help="runs and multirun jobs with their status (from status.json)",
                       description="One row per run/job: run_id, experiment, kind, sweep, job_num, "
                                   "status, started_at, runs, overrides, error (one line; the last "
                                   "line of a traceback). "
                                   "Sorted by started_at.")
    _common(p)
    p.add_argument("--experiment", metavar="NAME", help="only runs of this experiment")
    p = sub.add_parser("tables", help="each experiment's variants, metrics and windows; the tables' columns",
                       description="What the sql command can ask: per experiment its run folders, Monte Carlo "
                                   "sizes and variants; per experiment and metric its series and windows; then "
                                   "the tables' columns and dtypes, without the summary's config columns unless "
                                   "--config. --format csv prints the columns only.")
    _common(p)
    p.add_argument("--config", action="store_true",
                   help="also list the summary's config columns (one per config leaf: \"mc.runs\", ...)")
    p = sub.add_parser("sql", help="run a SQL query over summary, metrics and runs",
                       description="Run a polars SQL query over the tables summary, metrics "
                                   "and runs.",
                       epilog=SQL_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("query", nargs="?", help="the SQL query; '-' reads it from stdin")
    p.add_argument("--file", "-f", type=Path, help="read the SQL query from this file")
    _common(p)
    if more is not None:
        more.add_commands(sub)
    return parser


def _stderr_warn(msg: str) -> None:
    print(f"mtt-query: warning: {msg}", file=sys.stderr)


def _read_sql(args: argparse.Namespace) -> str:
    if args.file is not None:
        if args.query is not None:
            raise QueryError("give the SQL query either as an argument or with --file, not both.")
        try:
            return args.file.read_text()
        except OSError as e:
            raise QueryError(f"cannot read the SQL file '{args.file}': {e.strerror}.") from None
    if args.query is None:
        raise QueryError(f'no SQL query given. Example: mtt-query sql "{EXAMPLE_SQL}" '
                         "(see `mtt-query sql -h` for quoting).")
    return sys.stdin.read() if args.query == "-" else args.query


def _run(args: argparse.Namespace) -> pl.DataFrame:
    if args.command == "list":
        df = runs_frame(args.root, args.sweep, args.run, warn=_stderr_warn)
        if args.experiment is not None:
            names = sorted(set(df["experiment"].drop_nulls()))
            df = df.filter(pl.col("experiment") == args.experiment)
            if df.is_empty():
                raise QueryError(f"no runs of experiment '{args.experiment}' under "
                                 f"'{args.root}'. Experiments: {_sample(names)}.")
        return df.select(LIST_COLUMNS)
    if args.command == "tables":
        raise AssertionError("main() prints the tables command")
    sql = _read_sql(args)
    return _run_sql(sql, _catalog(args.root, args.sweep, args.run, _stderr_warn), _stderr_warn)


def main(argv: Sequence[str] | None = None, more: Any = None) -> int:
    """The query commands (``list``, ``tables``, ``sql``) and, with ``more`` (a module with
    ``add_commands``, ``COMMANDS`` and ``run_command``), its commands too: ``mtt-query`` is
    pipeline.results.cli's main, which passes the tracking commands. Returns the exit code: 0 on
    success, 2 on bad input (message on stderr, no traceback)."""
    args = build_parser(more).parse_args(argv)   # argparse itself exits 2 on bad options
    try:
        if more is not None and args.command in more.COMMANDS:
            return more.run_command(args)
        if args.command == "tables":
            frames = tables_overview(args.root, args.sweep, args.run, config=True, warn=_stderr_warn)
            shown = frames["columns"].filter(pl.col("table") == "summary")["column"]
            hidden = sum(is_config_column("summary", c) for c in shown)
            if not args.config:
                frames["columns"] = frames["columns"].filter(
                    ~pl.struct("table", "column").map_elements(lambda r: is_config_column(r["table"], r["column"]),
                                                               return_dtype=pl.Boolean))
            sys.stdout.write(render_overview(frames, args.format, args.config, hidden))
            sys.stdout.flush()
            return 0
        df = _run(args)
        sys.stdout.write(render(df, args.format, args.max_rows))
        sys.stdout.flush()
    except QueryError as e:
        print(f"mtt-query: error: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:                  # `mtt-query ... | head`
        try:
            sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - silence the flush at exit
        except OSError:
            pass
        return 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
