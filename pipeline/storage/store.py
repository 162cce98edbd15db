"""Parquet I/O: atomic writes, the per-stage cache, and provenance metadata.

Writes go to a hidden temp file in the target directory (``.<name>.w<writer>.<random>.tmp``), are
fsync'ed, then renamed over the target: a reader sees the old file or the new one, never a
half-written one, and the temp name matches no ``*.parquet`` glob. ``<writer>`` names the process
that writes it (a hash of its host and boot, its pid and start time): a temp file left by a killed
job is removed from the cache by the next job that uses the stage (``remove_orphans``) once that
process is gone, and one of an unknown or another host's writer once untouched for a day.

The cache keeps one file per stage output under ``<artifacts>/cache/<stage>/<key>.parquet``.
The key hashes the stage's resolved config, its inputs' keys, the package version and the
source of every module in the import closure of the code that produces the stage's output
(pipeline.storage.fingerprint: user packages named by ``_target_`` included). A cached
file is trusted only if its metadata names the same table and key and its rows match the content checksum
stored when it was written (``content_checksum``); anything else (truncated, a flipped bit in a data
page, rows altered under copied metadata, foreign, another key) is reported, moved aside as ``*.rejected`` (nothing is deleted) and
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
- a cache hit is published (copied into the run folder) from the file that was opened and
  verified, so another job's rename over the name in between cannot change what the run gets.
Two jobs storing the same key both write complete files; the last rename wins, and the stages
are deterministic, so both hold the same table.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import re
import shutil
import tempfile
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Iterator, Mapping

import numpy as np
import polars as pl

try:
    import fcntl
except ImportError:    # not POSIX (Windows): renames are not serialised across processes there
    fcntl = None

from pipeline.errors import StorageError, cannot_write
from pipeline.storage.schemas import META_TABLE, META_VERSION, SCHEMA_VERSION

META_KEY = "mtt.cache_key"
META_CHECKSUM = "mtt.content_sha256"
# Every table's Parquet compression. lz4 over Parquet's usual zstd: the tables are mostly float64
# states and covariances, which no codec shrinks much; on study 003's 100-run estimates zstd wrote
# 126 MB in 1.49 s, lz4 139 MB in 0.61 s (ADS-B's: 44 MB in 1.01 s against 51 MB in 0.20 s), and
# lz4 reads them back faster too. The cache and the run folders pay 10-16 % more disk for it.
COMPRESSION = "lz4"
log = logging.getLogger("pipeline.storage.store")


class TableDamaged(Exception):
    """A table whose rows (or ``mtt.*`` metadata) are not what was written: its content checksum differs."""


def _is_plain(dtype: pl.DataType) -> bool:
    """Numbers, booleans and times, alone or in fixed-size arrays: their values are their machine bytes."""
    while isinstance(dtype, pl.Array):
        dtype = dtype.inner
    return dtype.is_numeric() or dtype == pl.Boolean or dtype.is_temporal()


# Rows of a text column hashed at a time: the byte streams are the same as the whole column's, but
# the joined text, its Python copy and its UTF-8 copy are one slice's, not the column's. A study 003
# job's metrics table (600 060 rows of names) had each name column joined whole, and that was where
# the job peaked: a 2-run job at 759 MB against 480 MB held (592 MB since), 100 runs at 1.61 GB
# (1.55 GB since).
HASH_ROWS = 1 << 16


def _slices(s: pl.Series) -> Iterator[pl.Series]:
    for offset in range(0, s.len(), HASH_ROWS):
        yield s.slice(offset, HASH_ROWS)


class _ColumnHash:
    """One column's canonical byte streams, fed chunk by chunk: the same digest however the rows are
    split (a table streamed in chunks of runs, read back whole), and whatever the buffers, chunking or
    polars version. Streams: the row numbers of nulls; the non-null values (numbers, booleans, times
    and fixed-size arrays of them as machine bytes; strings as UTF-8 bytes with a separate stream of
    their lengths; anything else as the repr of each value, which round-trips floats exactly)."""

    def __init__(self, name: str, dtype: pl.DataType) -> None:
        self.name, self.dtype = name, dtype
        self.nulls, self.values, self.lengths = hashlib.sha256(), hashlib.sha256(), hashlib.sha256()

    def update(self, s: pl.Series, first_row: int) -> None:
        dtype = s.dtype
        if s.null_count():
            self.nulls.update((np.flatnonzero(s.is_null().to_numpy()) + first_row).astype("<i8").tobytes())
            s = s.drop_nulls()
        if _is_plain(dtype):
            values = (s.to_physical() if dtype.is_temporal() else s).to_numpy()
            self.values.update(np.ascontiguousarray(values))      # hashlib reads the buffer: no copy
        elif dtype == pl.String or isinstance(dtype, (pl.Categorical, pl.Enum)):
            if s.len() <= 4096:                 # one Series call: a summary has ~90 small columns
                encoded = [v.encode() for v in s.cast(pl.String).to_list()]
                self.lengths.update(np.array([len(v) for v in encoded], dtype="<i8").tobytes())
                self.values.update(b"".join(encoded))
            else:
                for part in _slices(s):
                    part = part.cast(pl.String)
                    self.lengths.update(part.str.len_bytes().to_numpy().astype("<i8").tobytes())
                    self.values.update((part.str.join("").item() or "").encode())
        else:                                   # lists, structs, Null, Object, Binary, Decimal: each value's text
            for part in _slices(s):
                self.values.update("".join(f"{v!r}\x1e" for v in part.to_list()).encode())

    def digest(self) -> bytes:
        return hashlib.sha256(f"{self.name}\x1f{self.dtype}".encode() + self.nulls.digest() + self.values.digest()
                              + self.lengths.digest()).digest()


class TableChecksum:
    """The content checksum of a table fed in chunks of rows (``update``), then of its metadata
    (``hexdigest``): equal to ``content_checksum`` of the whole table."""

    def __init__(self) -> None:
        self.columns: dict[str, _ColumnHash] = {}
        self.rows = 0

    def update(self, df: pl.DataFrame) -> None:
        if not self.columns:
            self.columns = {name: _ColumnHash(name, dtype) for name, dtype in df.schema.items()}
        elif [(c.name, c.dtype) for c in self.columns.values()] != list(df.schema.items()):
            raise ValueError(f"TableChecksum: a chunk with columns {df.schema} after {[c.name for c in self.columns.values()]}")
        for column in df.get_columns():
            self.columns[column.name].update(column, self.rows)
        self.rows += df.height

    def hexdigest(self, metadata: Mapping[str, str]) -> str:
        h = hashlib.sha256()
        for key in sorted(k for k in metadata if k.startswith("mtt.") and k != META_CHECKSUM):
            h.update(f"{key}\x1f{metadata[key]}\x1e".encode())
        h.update(f"rows\x1f{self.rows}\x1e".encode())
        for column in self.columns.values():
            h.update(column.digest())
        return h.hexdigest()


def content_checksum(df: pl.DataFrame, metadata: Mapping[str, str]) -> str:
    """SHA-256 of a table's rows and of its ``mtt.*`` metadata (the checksum's own key aside).

    Stored in the file's metadata when written (``atomic_write_parquet``, ``TableStream``) and
    recomputed on every read (``read_table``, the cache, queries, reports): a Parquet file can still
    parse after a flipped bit or a zeroed block in a data page (its pages carry no checksum of their
    own), and a file with other rows under copied metadata parses too; neither may be handed out as
    the table that was written. About 1.3 GB/s: 0.125 s for a 100-run study 003 estimates table
    (169 MB), 0.28 s for its metrics table (600 060 rows, mostly names)."""
    checksum = TableChecksum()
    checksum.update(df)
    return checksum.hexdigest(metadata)


def verify_checksum(df: pl.DataFrame, metadata: Mapping[str, str], path: Path | str) -> None:
    """Raise TableDamaged unless ``df`` and ``metadata`` are what was written. A file of schema
    version 4 or later must carry a checksum (the cache accepts no other version); files without a
    version or of an older one were written before checksums and are taken as they are."""
    stored = metadata.get(META_CHECKSUM)
    if stored is None:
        version = metadata.get(META_VERSION)
        if version is None or not version.isdigit() or int(version) < 4:
            return
        raise TableDamaged(f"{path}: it carries no content checksum ({META_CHECKSUM}), which every table "
                           f"this version writes has")
    if content_checksum(df, metadata) != stored:
        raise TableDamaged(f"{path}: its content checksum does not match its rows (the file was altered or "
                           f"damaged after it was written)")


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


# A temp file whose writer this machine cannot check (written on another host, or before temp names
# named their writer) is an orphan once untouched this long: a live writer touches its file with every
# chunk it writes, and no table here takes a day between two chunks.
ORPHAN_GRACE_S = 24 * 3600.0
_WRITER = re.compile(r"\.w(?P<host>[0-9a-f]{6})(?P<boot>[0-9a-f]{6})-(?P<pid>\d+)-(?P<ticks>\d+|x)\.[^.]+(\.copy)?\.tmp$")


def _short_hash(text: object) -> str:
    return hashlib.sha256(str(text).encode()).hexdigest()[:6]


def writer_tag() -> str:
    """This process as a temp file names it: ``w<host hash><boot hash>-<pid>-<start ticks or x>``."""
    from pipeline.run.process import identity
    me = identity()
    ticks = me["start_ticks"] if me["start_ticks"] is not None else "x"
    return f"w{_short_hash(me['host'])}{_short_hash(me['boot_id'])}-{me['pid']}-{ticks}"


def orphaned(path: Path, now: float | None = None) -> bool:
    """Whether the hidden temp file ``path`` is left over by a writer that has ended: one named by a
    process of this host whose process is gone (or of an earlier boot), or, where its writer cannot be
    checked, one untouched for ``ORPHAN_GRACE_S``. A live writer's file is never orphaned."""
    from pipeline.run.process import identity, is_running
    try:
        age = (time.time() if now is None else now) - path.lstat().st_mtime
    except FileNotFoundError:
        return False
    found = _WRITER.search(path.name)
    me = identity()
    if found and found["host"] == _short_hash(me["host"]):
        if found["boot"] != _short_hash(me["boot_id"]):
            return True                   # written before this machine's last boot
        return not is_running(int(found["pid"]), None if found["ticks"] == "x" else int(found["ticks"]))
    return age > ORPHAN_GRACE_S


def remove_orphans(folder: Path) -> list[tuple[Path, int]]:
    """Remove the orphaned hidden temp files (``orphaned``) directly in ``folder``; (path, bytes) of each."""
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    now = time.time()
    for entry in entries:
        if not (entry.name.startswith(".") and entry.name.endswith(".tmp")) or not entry.is_file(follow_symlinks=False):
            continue
        path = Path(entry.path)
        if orphaned(path, now):
            with contextlib.suppress(OSError):
                size = entry.stat(follow_symlinks=False).st_size
                path.unlink()
                removed.append((path, size))
    return removed


def unlink_if_unchanged(path: Path, seen: os.stat_result) -> bool:
    """Remove ``path`` if it is still the file ``seen`` described (same inode, size and mtime), under
    its folder's rename lock: a store that renames a new file onto the name meanwhile keeps it
    (``mtt-query gc``). True if removed."""
    with _renames_locked(path.parent):
        try:
            now = os.stat(path)
        except FileNotFoundError:
            return False
        if (now.st_ino, now.st_size, now.st_mtime_ns) != (seen.st_ino, seen.st_size, seen.st_mtime_ns):
            return False
        os.unlink(path)
        return True


def _temp_beside(path: Path) -> tuple[int, str]:
    """(fd, name) of a new hidden temp file in ``path``'s folder (made if missing), which no
    ``*.parquet`` glob matches and which names its writer (``writer_tag``); an OSError becomes a
    StorageError naming the path."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        return tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.{writer_tag()}.", suffix=".tmp")
    except OSError as exc:
        raise cannot_write(path, exc) from None


def _os_error(exc: BaseException) -> OSError | None:
    """The OSError behind ``exc``: itself, or the one a polars writer reports in its text (polars
    raises ``ComputeError: parquet: ... underlying IO error: No space left on device (os error 28)``
    where Python would raise OSError); None for anything else."""
    if isinstance(exc, OSError):
        return exc
    if isinstance(exc, pl.exceptions.PolarsError):
        found = re.search(r"\(os error (\d+)\)", str(exc))
        if found:
            code = int(found.group(1))
            return OSError(code, os.strerror(code))
    return None


def _atomic_write(path: Path, write, binary: bool = True, locked: bool = False) -> None:
    """Write through a hidden temp file in the target directory, fsync, then rename over ``path``
    (with ``locked``, the rename alone runs under the directory's rename lock). An OSError (no such
    folder, no permission, no space, a folder in the way) becomes a StorageError naming the path."""
    fd, tmp = _temp_beside(path)
    try:
        with os.fdopen(fd, "wb" if binary else "w") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, FILE_MODE)
        with _renames_locked(path.parent) if locked else contextlib.nullcontext():
            os.replace(tmp, path)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        error = _os_error(exc)
        if error is not None:
            raise cannot_write(path, error) from None
        raise


def atomic_write_parquet(df: pl.DataFrame, path: Path, metadata: Mapping[str, str] | None = None,
                         *, locked: bool = False) -> None:
    """Write ``df`` atomically with ``metadata`` and the content checksum of both (``content_checksum``)."""
    metadata = {str(k): str(v) for k, v in (metadata or {}).items()}
    metadata[META_CHECKSUM] = content_checksum(df, metadata)
    _atomic_write(path, lambda f: df.write_parquet(f, compression=COMPRESSION, metadata=metadata), locked=locked)


def atomic_write_bytes(data: bytes, path: Path) -> None:
    _atomic_write(path, lambda f: f.write(data))


def atomic_write_text(text: str, path: Path) -> None:
    _atomic_write(path, lambda f: f.write(text), binary=False)


def read_yaml(path: Path | str) -> Any:
    """A YAML file written by this package (a job's config.yaml, Hydra's overrides.yaml) as plain
    Python objects. libyaml's safe loader where PyYAML has it: 7 ms instead of 41 ms for a job's
    18 kB config.yaml, the same objects; a sweep's aggregation reads one per job."""
    import yaml

    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    return yaml.load(Path(path).read_text(), Loader=loader)


class TableStream:
    """A table written chunk by chunk (one Parquet row group per chunk) to a hidden temp file beside
    ``path``; ``finish(metadata)`` adds the metadata with the content checksum of all chunks and
    renames the file into place (under the directory's rename lock with ``locked``), ``abort()``
    removes it. Only one chunk is in memory at a time: ``mc.chunk_runs`` bounds a track stage's
    memory by streaming each chunk of runs here instead of concatenating them first."""

    def __init__(self, path: Path, locked: bool = False) -> None:
        self.path, self.locked = Path(path), locked
        fd, tmp = _temp_beside(self.path)
        os.close(fd)
        self.tmp = Path(tmp)
        self.writer = None
        self.checksum = TableChecksum()

    def write(self, df: pl.DataFrame) -> None:
        import pyarrow.parquet as pq
        table = df.to_arrow()
        try:
            if self.writer is None:
                self.writer = pq.ParquetWriter(self.tmp, table.schema, compression=COMPRESSION)
            self.writer.write_table(table)
        except OSError as exc:
            self.abort()
            raise cannot_write(self.path, exc) from None
        self.checksum.update(df)

    def finish(self, metadata: Mapping[str, str]) -> Path:
        if self.writer is None:
            self.abort()
            raise ValueError(f"TableStream {self.path}: finish() before any chunk was written")
        metadata = {str(k): str(v) for k, v in metadata.items()}
        metadata[META_CHECKSUM] = self.checksum.hexdigest(metadata)
        try:
            self.writer.add_key_value_metadata(metadata)
            self.writer.close()
            with open(self.tmp, "rb+") as f:
                os.fsync(f.fileno())
            os.chmod(self.tmp, FILE_MODE)
            with _renames_locked(self.path.parent) if self.locked else contextlib.nullcontext():
                os.replace(self.tmp, self.path)
        except OSError as exc:
            self.abort()
            raise cannot_write(self.path, exc) from None
        return self.path

    def abort(self) -> None:
        with contextlib.suppress(Exception):
            if self.writer is not None:
                self.writer.close()
        self.tmp.unlink(missing_ok=True)


def read_table(path: Path | str) -> tuple[pl.DataFrame, dict[str, str]]:
    """(rows, metadata) of a table this project wrote, from one open file, its checksum verified
    (TableDamaged if it does not match)."""
    with open(path, "rb") as f:
        meta = pl.read_parquet_metadata(f)
        f.seek(0)
        df = pl.read_parquet(f)
    verify_checksum(df, meta, path)
    return df, meta


def inside(folder: Path, relative: Path | str) -> Path:
    """``folder / relative``, refused unless it resolves inside ``folder`` (a name from a config must
    never place a file elsewhere, e.g. a variant key '../../x')."""
    target = (Path(folder) / relative)
    if not target.resolve().is_relative_to(Path(folder).resolve()) or Path(relative).is_absolute():
        raise ValueError(f"{relative!s}: resolves outside {folder}; refused")
    return target


FICLONE = 0x40049409        # linux/fs.h: share the source's extents (btrfs, XFS, bcachefs); no data copied


def _clone_or_copy(source: BinaryIO, target: BinaryIO) -> None:
    """The whole of ``source`` into ``target``: a reflink where the file system has them, else a
    kernel-side copy (sendfile), else a plain one."""
    if fcntl is not None:
        try:
            fcntl.ioctl(target.fileno(), FICLONE, source.fileno())
            return
        except OSError:
            pass                 # ext4, tmpfs, NFS, another device: copy the bytes
    size, offset = os.fstat(source.fileno()).st_size, 0
    try:
        while offset < size:
            sent = os.sendfile(target.fileno(), source.fileno(), offset, size - offset)
            if sent == 0:
                break
            offset += sent
    except OSError:
        source.seek(offset)
        target.seek(offset)
        shutil.copyfileobj(source, target, 1 << 20)


def publish(src: Path | BinaryIO, dst: Path, link: bool = False) -> None:
    """Place a copy of a cached file (a path, or the file the cache opened and verified) into a run
    folder, atomically.

    A copy, not a hard link: with a link, the run's file *was* the cache file, so damage to one
    (a truncate, a dd, a bad disk block) changed every earlier run's published tables too. A
    copy is independent of the cache from the moment it is made; where the file system has
    reflinks (btrfs, XFS) it shares the data blocks copy-on-write and costs no space, elsewhere
    (ext4) each run folder holds its own bytes (see the README for the measured cost).

    ``link`` (config ``cache.publish=link``, for a user short of disk): a hard link to the cache file
    (a path), made read-only so that an accidental in-place write fails instead of reaching every
    run that shares it; where links are impossible, a copy.
    """
    try:
        dst.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise cannot_write(dst, exc) from None
    # unique per call (not per process): threads of one worker process never share a temp name
    tmp = dst.parent / f".{dst.name}.{writer_tag()}.{uuid.uuid4().hex[:8]}.copy.tmp"
    try:
        if link and isinstance(src, (str, Path)):
            try:
                os.chmod(src, FILE_MODE & 0o444)
                os.link(src, tmp)
                os.replace(tmp, dst)
                return
            except OSError:
                pass          # another file system, FAT, a name just renamed over: copy instead
        with (open(src, "rb") if isinstance(src, (str, Path)) else contextlib.nullcontext(src)) as source, \
                open(tmp, "wb") as target:
            _clone_or_copy(source, target)
            target.flush()
            os.fsync(target.fileno())
        os.chmod(tmp, FILE_MODE)
        os.replace(tmp, dst)
    except BaseException as exc:
        if os.path.lexists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError) and not isinstance(exc, FileNotFoundError):   # a missing source stays itself
            raise cannot_write(dst, exc) from None
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
        self._swept: set[str] = set()

    def path(self, stage: str, key: str) -> Path:
        return self.root / stage / f"{key}.parquet"

    def sweep(self, stage: str) -> None:
        """Once per stage folder and cache: remove the temp files killed jobs left there (``remove_orphans``)."""
        if stage in self._swept:
            return
        self._swept.add(stage)
        removed = remove_orphans(self.root / stage)
        if removed:
            log.info("cache/%s: removed %d temp file(s) of %.1f MB left by jobs that ended before renaming them "
                     "(killed): %s", stage, len(removed), sum(size for _, size in removed) / 1e6,
                     ", ".join(p.name for p, _ in removed[:3]) + (" ..." if len(removed) > 3 else ""))

    def load(self, stage: str, key: str, table: str, publish_to: Path | None = None
             ) -> tuple[pl.DataFrame, dict[str, str]] | None:
        """The cached table and its metadata, or None (a miss, or a file found bad and moved aside).
        With ``publish_to``, a hit is also copied there from the very file that was read and verified."""
        path = self.path(stage, key)
        self.sweep(stage)
        if not self.enabled:
            return None
        try:
            f = open(path, "rb")
        except FileNotFoundError:   # not cached yet, or another job has just moved it aside
            return None
        except OSError as exc:      # a folder where the file belongs, no permission: say which and why
            raise cannot_write(path, exc, "read the cache file") from None
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
                    verify_checksum(df, meta, path)
            except TableDamaged as exc:
                problem = str(exc).split(": ", 1)[1]
            except Exception as exc:  # unreadable: truncated, not Parquet, ...
                problem = f"it cannot be read ({type(exc).__name__}: {str(exc).splitlines()[0][:200]})"
            if problem is None:
                # read and verified: a copy that fails now (a full disk, no permission) is the run folder's
                # failure, raised as such (a StorageError naming it); the good cache file stays
                if publish_to is not None:
                    publish(f, publish_to)
                return df, meta
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
        try:
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
        except OSError as exc:     # a read-only cache: the file can be neither moved aside nor recomputed there
            raise StorageError(f"cache file {path} cannot be used: {problem}. It cannot be moved aside and the stage "
                               f"recomputed into the cache: {cannot_write(path.parent, exc, 'write in')}") from None
        log.warning("cache file %s was not used: %s. It was moved to %s and the stage is recomputed.",
                    path, problem, aside.name)

    def stream(self, stage: str, key: str) -> TableStream:
        """A TableStream onto the cache name of (stage, key); finish() with the metadata (the key is added)."""
        return _KeyedStream(self.path(stage, key), key)

    def store(self, stage: str, key: str, df: pl.DataFrame, metadata: Mapping[str, str]) -> Path:
        path = self.path(stage, key)
        atomic_write_parquet(df, path, {**metadata, META_KEY: key}, locked=True)
        return path


class _KeyedStream(TableStream):
    def __init__(self, path: Path, key: str) -> None:
        super().__init__(path, locked=True)
        self.key = key

    def finish(self, metadata: Mapping[str, str]) -> Path:
        return super().finish({**metadata, META_KEY: self.key})
