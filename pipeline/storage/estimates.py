"""How a job holds its variants' estimates: one variant in memory at a time.

A variant's estimate is as large as its track table (study 003 case 1: ~140 MB for 100 runs x
10 001 steps; an ADS-B flight with seven variants: ~60 MB each). Holding every variant from the
track stage to the recording made a job's peak grow with its number of variants. Instead:

- the evaluation measures each variant as soon as its track stage is done, then lets it go
  (``pipeline.run.runner.Evaluation``);
- a study's own summary rows of a variant come from ``Study.variant_summary``, called then too;
  its rows across variants (``Study.extra_summary``) get ``StoredEstimates``, which reads a
  variant's table again when asked and keeps only the last one read (the shipped studies keep
  what they need from ``variant_summary`` instead, and read nothing again);
- the recording gets ``recorded_runs`` of each estimate: the recorded runs' rows only, standing
  in for the whole arrays (``RecordedRuns``), made while the variant is in memory anyway.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np


class StoredEstimates(Mapping[str, Any]):
    """variant key -> its estimate, read from its track table (``tables[key]``) with ``from_frame``
    when asked, in the order of ``tables``. Only the last one read stays in memory, so iterate once
    (``for key, estimate in stored.items()``): each variant read is one table read."""

    def __init__(self, tables: Mapping[str, Path], from_frame: Callable[[Any, dict[str, str]], Any]) -> None:
        self.tables = dict(tables)
        self.from_frame = from_frame
        self._last: tuple[str, Any] | None = None

    def __getitem__(self, key: str) -> Any:
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        if key not in self.tables:
            raise KeyError(key)
        from pipeline.storage.store import read_table

        self._last = None                           # let the previous one go before reading the next
        df, meta = read_table(self.tables[key])
        value = self.from_frame(df, {k: str(v) for k, v in meta.items()})
        self._last = (key, value)
        return value

    def __iter__(self) -> Iterator[str]:
        return iter(self.tables)

    def __len__(self) -> int:
        return len(self.tables)

    def release(self) -> None:
        """Let the last estimate read go."""
        self._last = None


class RecordedRuns:
    """A few runs' rows of an (R, ...) array, standing in for the whole of it in a recording.

    ``shape``, ``ndim``, ``dtype`` and ``len`` are the whole array's; indexing with one of the kept
    runs (or a list of them) as the leading index gives their rows, as the whole array would. Any
    other run, or a use of the whole array, raises: a recording never shows a run it was not
    given."""

    def __init__(self, rows: np.ndarray, runs: Sequence[int], total_runs: int) -> None:
        rows = np.asarray(rows)
        if rows.shape[0] != len(runs):
            raise ValueError(f"RecordedRuns: {rows.shape[0]} rows for the {len(runs)} runs {list(runs)}")
        self.rows = rows
        self.runs = [int(r) for r in runs]
        self._row_of = {r: i for i, r in enumerate(self.runs)}
        self.shape = (int(total_runs), *rows.shape[1:])
        self.ndim = len(self.shape)
        self.dtype = rows.dtype
        self.size = int(np.prod(self.shape))

    def __len__(self) -> int:
        return self.shape[0]

    def _row(self, run: Any) -> int:
        run = int(run)
        if run < 0:
            run += self.shape[0]
        if run not in self._row_of:
            raise IndexError(f"run {run} is not among the recorded runs {self.runs}; only their rows are held")
        return self._row_of[run]

    def __getitem__(self, key: Any) -> np.ndarray:
        first, rest = (key[0], key[1:]) if isinstance(key, tuple) and key else (key, ())
        if isinstance(first, (int, np.integer)):
            index: Any = self._row(first)
        elif isinstance(first, (list, np.ndarray)) and np.asarray(first).dtype.kind in "iu":
            index = [self._row(r) for r in np.asarray(first).ravel()]
        else:
            raise IndexError(f"RecordedRuns: index {key!r}: the leading index must be a recorded run or a list of "
                             f"them ({self.runs}); the other runs are not held")
        return self.rows[(index, *rest)]

    def __iter__(self):
        # without it, Python would iterate through __getitem__ and stop silently at the first run not held
        raise TypeError(f"RecordedRuns: only the recorded runs {self.runs} of this {self.shape} array are held; "
                        f"index it by run (array[r]) instead of iterating over every run")

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        raise TypeError(f"RecordedRuns: only the recorded runs {self.runs} of this {self.shape} array are held; "
                        f"index it by run (array[r]) instead of reading it whole")

    def __repr__(self) -> str:
        return f"RecordedRuns(runs={self.runs}, shape={self.shape}, dtype={self.dtype})"


def _kept(value: Any, runs: list[int], total_runs: int) -> Any:
    if isinstance(value, Mapping):
        return {k: _kept(v, runs, total_runs) for k, v in value.items()}
    shape = getattr(value, "shape", None)
    # a per-run array is (R, K, ...): a (K,) time axis or a (T,) list of targets is kept whole
    if shape is None or len(shape) < 2 or shape[0] != total_runs:
        return value
    if isinstance(value, np.ndarray):
        return RecordedRuns(value[runs], runs, total_runs)
    # an array-like that unpacks a run at a time (pipeline.storage.schemas.PackedCovariance)
    return RecordedRuns(np.stack([np.asarray(value[r]) for r in runs]), runs, total_runs)


def recorded_runs(estimate: Any, runs: Sequence[int], total_runs: int) -> Any:
    """``estimate`` (a dataclass of (R, K, ...) arrays, extras included) with each per-run array
    replaced by its ``runs``' rows (``RecordedRuns``): what a recording of those runs draws, without
    holding the other runs."""
    runs = sorted({int(r) for r in runs})
    if not dataclasses.is_dataclass(estimate):
        raise TypeError(f"recorded_runs: {type(estimate).__name__} is not a dataclass of per-run arrays")
    changes = {f.name: _kept(getattr(estimate, f.name), runs, total_runs) for f in dataclasses.fields(estimate)
               if f.init}
    return dataclasses.replace(estimate, **changes)
