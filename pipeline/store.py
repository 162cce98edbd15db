"""Parquet I/O: atomic writes, the per-stage cache, and provenance metadata.

Writes go to a hidden temp file in the target directory (``.<name>.<random>.tmp``), are
fsync'ed, then renamed over the target: a reader sees the old file or the new one, never a
half-written one, and the temp name matches no ``*.parquet`` glob.

The cache keeps one file per stage output under ``<artifacts>/cache/<stage>/<key>.parquet``.
The key hashes the stage's resolved config, its inputs' keys, the package version and the
source of every module in the import closure of the code that produces the stage's output
(pipeline.fingerprint: user packages named by ``_target_`` included). A cached
file is trusted only if its metadata names the same table and key; anything else (truncated,
foreign, another key) is reported, moved aside as ``*.rejected`` (nothing is deleted) and
recomputed.

Concurrent jobs (sweep workers in separate processes, on one machine or on a shared file
system) share the cache; each may compute and store the same key. What keeps that correct:
- readers take no lock: a file appears under its name only whole (rename), and a reader opens it
  once and reads the metadata and the table from that one open file, so a rename over the name
  in between cannot pair one file's checked metadata with another file's rows;
- a reader that finds a file damaged moves aside only *that* file (same device and inode): if
  another job has already moved it aside, or has stored a good file in its place, nothing
  happens. The check and the rename, and every store's rename onto a cache name, happen under
  an exclusive ``flock`` on ``<stage>/.lock``, held for the rename only (microseconds); without
  it a job could move aside the good file another job had just stored (and that job's publish
  would then find no file).
- a file that vanishes before it is opened is a miss, not a damaged file;
- publishing (hard-linking) a cache file while another job renames its copy over the same name
  retries the link: Linux fails a link to an inode whose last name has just gone with ENOENT.
Two jobs storing the same key both write complete files; the last rename wins, and the stages
are deterministic, so both hold the same table.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
import tempfile
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Mapping

import polars as pl

try:
    import fcntl
except ImportError:    # not POSIX (Windows): renames are not serialised across processes there
    fcntl = None

from pipeline.schemas import META_TABLE, META_VERSION, SCHEMA_VERSION

META_KEY = "mtt.cache_key"
log = logging.getLogger("pipeline.store")


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


FILE_MODE = 0o666 & ~_umask()   # mkstemp creates 0600; published tables are ordinary files


def package_version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("mtt-experiments")
    except PackageNotFoundError:
        return "0+unknown"


def stable_hash(obj: Any, length: int = 16) -> str:
    text = json.dumps(obj, sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:length]


def stage_key(stage: str, config: Any, inputs: tuple[str, ...] = (), producers: tuple[str, ...] = ()) -> str:
    """The cache key of a stage output: its resolved config subtree, its inputs' keys, the package
    and schema versions, and the source of the import closure of ``producers`` (module names) and
    of every ``_target_`` in ``config`` (pipeline.fingerprint): editing any code that made the
    table, a user's package included, recomputes it; a researcher changing the math must never be
    handed estimates made by the old code."""
    from pipeline.fingerprint import producers as named_producers, source_fingerprint
    code = source_fingerprint(named_producers(config, *producers))
    return stable_hash({"stage": stage, "config": config, "inputs": list(inputs),
                        "version": package_version(), "schema": SCHEMA_VERSION, "code": code})


@contextlib.contextmanager
def _renames_locked(directory: Path) -> Iterator[None]:
    """Exclusive, cross-process: no other rename onto a cache name in ``directory`` meanwhile.

    ``flock`` on ``directory/.lock`` (created once, never removed; hidden, so no glob sees it).
    The lock goes with the file descriptor, so a killed process never leaves it held.
    """
    if fcntl is None:
        yield
        return
    fd = os.open(directory / ".lock", os.O_RDWR | os.O_CREAT, FILE_MODE)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def _atomic_write(path: Path, write, binary: bool = True, locked: bool = False) -> None:
    """Write through a hidden temp file in the target directory, fsync, then rename over ``path``
    (with ``locked``, the rename alone runs under the directory's rename lock)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb" if binary else "w") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, FILE_MODE)
        with _renames_locked(path.parent) if locked else contextlib.nullcontext():
            os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_parquet(df: pl.DataFrame, path: Path, metadata: Mapping[str, str] | None = None,
                         *, locked: bool = False) -> None:
    _atomic_write(path, lambda f: df.write_parquet(f, metadata=dict(metadata or {})), locked=locked)


def atomic_write_text(text: str, path: Path) -> None:
    _atomic_write(path, lambda f: f.write(text), binary=False)


def read_table(path: Path) -> tuple[pl.DataFrame, dict[str, str]]:
    return pl.read_parquet(path), pl.read_parquet_metadata(path)


def inside(folder: Path, relative: Path | str) -> Path:
    """``folder / relative``, refused unless it resolves inside ``folder`` (a name from a config must
    never place a file elsewhere, e.g. a variant key '../../x')."""
    target = (Path(folder) / relative)
    if not target.resolve().is_relative_to(Path(folder).resolve()) or Path(relative).is_absolute():
        raise ValueError(f"{relative!s}: resolves outside {folder}; refused")
    return target


def publish(src: Path, dst: Path) -> None:
    """Place a cached file into a run directory: hard link if possible (no copy), else copy; atomic."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    # unique per call (not per process): threads of one worker process never share a temp name
    tmp = dst.parent / f".{dst.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.link.tmp"
    try:
        for attempt in range(100):
            try:
                os.link(src, tmp)
                break
            except FileNotFoundError:
                # Linux refuses to link an inode whose last name went away between the lookup and
                # the link (ENOENT): another job has just renamed its copy of this stage output
                # over ``src``. The name holds that newer, equally complete file: link again.
                if attempt == 99 or not os.path.exists(src):
                    raise
            except OSError:         # no hard links here (another file system, FAT, ...): copy
                shutil.copyfile(src, tmp)
                break
        os.replace(tmp, dst)
    except BaseException:
        if os.path.lexists(tmp):
            os.unlink(tmp)
        raise


@dataclass
class CacheEvent:
    stage: str
    key: str
    path: Path
    reused: bool
    seconds: float = 0.0
    note: str = ""


class StageCache:
    """Per-stage Parquet cache. ``enabled=False`` still writes (so later runs can reuse) but never reads."""

    def __init__(self, root: Path, enabled: bool = True) -> None:
        self.root = Path(root)
        self.enabled = enabled
        self.events: list[CacheEvent] = []

    def path(self, stage: str, key: str) -> Path:
        return self.root / stage / f"{key}.parquet"

    def load(self, stage: str, key: str, table: str) -> tuple[pl.DataFrame, dict[str, str]] | None:
        path = self.path(stage, key)
        if not self.enabled:
            return None
        try:
            f = open(path, "rb")
        except FileNotFoundError:   # not cached yet, or another job has just moved it aside
            return None
        with f:   # metadata and rows from this one open file, whatever is renamed over the name meanwhile
            found = os.fstat(f.fileno())
            problem = None
            try:
                meta = pl.read_parquet_metadata(f)
                if meta.get(META_TABLE) != table:
                    problem = f"it holds table {meta.get(META_TABLE)!r}, expected {table!r}"
                elif meta.get(META_KEY) != key:
                    problem = f"its cache key is {meta.get(META_KEY)!r}, expected {key!r}"
                elif meta.get(META_VERSION) != SCHEMA_VERSION:
                    problem = f"its schema version is {meta.get(META_VERSION)!r}, expected {SCHEMA_VERSION!r}"
                else:
                    f.seek(0)
                    df = pl.read_parquet(f)
                    return df, meta
            except Exception as exc:  # unreadable: truncated, not Parquet, ...
                problem = f"it cannot be read ({type(exc).__name__}: {str(exc).splitlines()[0][:200]})"
            # still open: the inode cannot be reused by a new file before the identity check
            self.reject(path, problem, found)
        return None

    def reject(self, path: Path, problem: str, found: os.stat_result | None = None) -> None:
        """Move the file at ``path`` aside as ``*.rejected`` (never deleted).

        ``found``: the ``os.stat`` of the file that was read and found bad. Only that file is
        moved: if another job has moved it aside already, or stored a new file under the name,
        the name is left alone (the check and the rename under the stage's rename lock, which
        every store's rename also takes).
        """
        aside = path.with_name(f"{path.name}.{time.strftime('%Y%m%d-%H%M%S')}.{uuid.uuid4().hex[:6]}.rejected")
        with _renames_locked(path.parent):
            try:
                current = os.stat(path)
            except FileNotFoundError:
                current = None
            if current is None or (found is not None and not os.path.samestat(current, found)):
                log.warning("cache file %s was not used: %s. Another job has already moved it aside%s; "
                            "the stage is recomputed.", path, problem,
                            "" if current is None else " and stored a new one")
                return
            os.replace(path, aside)
        log.warning("cache file %s was not used: %s. It was moved to %s and the stage is recomputed.",
                    path, problem, aside.name)

    def store(self, stage: str, key: str, df: pl.DataFrame, metadata: Mapping[str, str]) -> Path:
        path = self.path(stage, key)
        atomic_write_parquet(df, path, {**metadata, META_KEY: key}, locked=True)
        return path
