"""The one way a benchmark records its figures: ``benchmarks/results/<name>.md`` and a ``.json`` beside it.

Every results file states when and where it was measured, so that a figure never outlives its
context: the date (UTC), the git commit and whether the work tree differed from it (the results
files themselves excepted), the machine (CPU model, cores, Python, numpy and numba versions) and the
load average when the benchmark started, and the command that made it. A shared machine drifts by
1.45x between days, so a speed figure means something only beside a figure measured in the same run:
every table row with a time (a column of kind ``seconds``) carries its ratio to the peer or the
reference (a column of kind ``ratio``), and ``write_result`` refuses a row without one.

Use::

    context = start("benchmarks/bench_study003.py", argv)   # first thing in main(): the load at start
    ...                                                 # measure
    write_result("study003", "Study 003: ...", [Table(columns, rows)], notes, context=context,
                 parameters={"runs": 100}, directory=args.results_dir)

Markdown headers carry the column's kind: ``(s)`` a time in seconds, ``(×)`` or ``(%)`` a ratio
(``tests/test_benchmark_results.py`` reads them back). The ``.json`` holds the same values unrounded.
"""

from __future__ import annotations

import datetime
import json
import math
import os
import platform
import shlex
import subprocess
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS_DIR = ROOT / "benchmarks" / "results"
KINDS = ("text", "number", "seconds", "ratio", "percent")
SUFFIX = {"seconds": " (s)", "ratio": " (×)", "percent": " (%)"}
ABSOLUTE_TIMES = ("Absolute times are on this {cores}-core machine, today (the load above): compare the ratios, "
                  "each measured in the same run as its partner.")


@dataclass(frozen=True)
class Column:
    """One column: ``key`` into the rows, its ``header`` (the kind's unit is appended), its ``kind``
    (``seconds``, ``ratio``, ``percent``, ``number`` or ``text``) and a format spec for numbers."""

    key: str
    header: str
    kind: str = "text"
    format: str = ".3g"

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"Column {self.key!r}: kind {self.kind!r} is not one of {', '.join(KINDS)}")

    @property
    def title(self) -> str:
        return self.header + SUFFIX.get(self.kind, "")

    def cell(self, value: Any) -> str:
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return ""
        if isinstance(value, str) or self.kind == "text":
            return str(value)
        return format(value, self.format)


@dataclass
class Table:
    """Rows (mappings from column keys to values; a missing key is an empty cell) under ``columns``."""

    columns: Sequence[Column]
    rows: Sequence[Mapping[str, Any]]
    caption: str = ""

    def check(self, name: str) -> None:
        """Every row with a time has a ratio in the same row (its partner measured in the same run)."""
        timed = [c.key for c in self.columns if c.kind == "seconds"]
        ratios = [c.key for c in self.columns if c.kind in ("ratio", "percent")]
        for i, row in enumerate(self.rows):
            has = lambda keys: any(row.get(k) is not None and not (isinstance(row.get(k), float)  # noqa: E731
                                                                    and math.isnan(row[k])) for k in keys)
            if has(timed) and not has(ratios):
                raise ValueError(f"results {name!r}: table {self.caption or '(untitled)'!r} row {i + 1} has a time "
                                 f"but no ratio to a peer or reference measured in the same run; add a column "
                                 f"of kind 'ratio' (allowed kinds: {', '.join(KINDS)})")

    def markdown(self) -> str:
        lines = [f"{self.caption}\n" if self.caption else ""]
        lines.append("| " + " | ".join(c.title for c in self.columns) + " |")
        lines.append("|" + "|".join("---" if c.kind == "text" else "---:" for c in self.columns) + "|")
        lines += ["| " + " | ".join(c.cell(row.get(c.key)) for c in self.columns) + " |" for row in self.rows]
        return "\n".join(line for line in lines if line != "") + "\n"


@dataclass(frozen=True)
class Context:
    """Where and when a benchmark ran; taken by :func:`start` before it measures anything."""

    date: str
    commit: str
    dirty: bool
    machine: dict[str, Any]
    load_average: float
    script: str
    command: str

    def header_lines(self) -> list[str]:
        m = self.machine
        return [f"- date: {self.date}",
                f"- commit: {self.commit}" + (" (dirty: the work tree differed from it)" if self.dirty else " (clean)"),
                f"- machine: {m['cpu']}, {m['cores']} cores ({m['usable_cores']} usable), {m['system']}, "
                f"Python {m['python']}, numpy {m['numpy']}, numba {m['numba']}",
                f"- load average at start: {self.load_average:.2f} (1 min; the machine is shared)",
                f"- command: `{self.command}`"]


def _git(*args: str) -> str | None:
    try:
        done = subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _version(name: str) -> str:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


def start(script: str, argv: Sequence[str] | None = None) -> Context:
    """The context of the benchmark ``script`` (its path in the repository, ``benchmarks/bench_x.py``)
    starting now with ``argv`` (default: this process's arguments): call it before measuring (it
    reads the load average)."""
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    commit = _git("rev-parse", "--short=12", "HEAD") or "unknown (not a git checkout)"
    # the results files are the record, not the code: writing one does not make the next run dirty
    status = _git("status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)benchmarks/results")
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    machine = {"cpu": _cpu_model(), "cores": os.cpu_count(), "usable_cores": usable,
               "system": f"{platform.system()} {platform.machine()}", "python": platform.python_version(),
               "numpy": _version("numpy"), "numba": _version("numba")}
    arguments = list(sys.argv[1:] if argv is None else argv)
    return Context(date=datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
                   commit=commit, dirty=bool(status), machine=machine, load_average=load,
                   script=script, command=shlex.join(["python", script, *arguments]))


def write_result(name: str, title: str, tables: Sequence[Table], notes: Sequence[str], *, context: Context,
                 parameters: Mapping[str, Any] | None = None,
                 directory: Path | None = None) -> Path:
    """Write ``<directory>/<name>.md`` (and ``.json``): the header of ``context``, ``parameters`` (the
    job's size), the tables and the notes; return the Markdown file's path.
    Raises ValueError, before writing anything, when a row has a time but no ratio."""
    if not name or any(ch in name for ch in "/\\ ") or name.startswith("."):
        raise ValueError(f"results name {name!r}: use a plain file stem (letters, digits, '_', '-')")
    for table in tables:
        table.check(name)
    directory = RESULTS_DIR if directory is None else Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    lines = [f"# {title}", "", f"- benchmark: `{context.script}`", *context.header_lines()]
    if parameters:
        lines.append("- size: " + ", ".join(f"{k} {v}" for k, v in parameters.items()))
    lines.append("")
    for table in tables:
        lines += [table.markdown()]
    usable = context.machine["usable_cores"]
    lines += [f"- {note}" for note in [*notes, ABSOLUTE_TIMES.format(cores=usable)]]
    path = directory / f"{name}.md"
    path.write_text("\n".join(lines).rstrip() + "\n")
    record = {"name": name, "title": title, "benchmark": context.script, "date": context.date, "commit": context.commit,
              "dirty": context.dirty, "machine": context.machine, "load_average_at_start": context.load_average,
              "command": context.command, "parameters": dict(parameters or {}),
              "tables": [{"caption": t.caption,
                          "columns": [{"key": c.key, "header": c.header, "kind": c.kind} for c in t.columns],
                          "rows": [dict(r) for r in t.rows]} for t in tables],
              "notes": list(notes)}
    (directory / f"{name}.json").write_text(json.dumps(record, indent=2, default=_plain) + "\n")
    print(f"results: {path}")
    return path


def _plain(value: Any) -> Any:
    """numpy scalars and arrays in the JSON as plain numbers and lists."""
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def add_results_argument(parser) -> None:
    """``--results-dir`` (default ``benchmarks/results``, the committed record; tests pass a temporary one)."""
    parser.add_argument("--results-dir", type=Path, default=RESULTS_DIR,
                        help="where the results file goes (default: benchmarks/results, the committed record)")
