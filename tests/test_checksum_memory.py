"""The content checksum hashes long text columns a slice of rows at a time: the same digest as the
whole column's (so every table written before still verifies), without the whole column's joined
text and its two copies in memory at once (that transient was a 100-run study 003 job's peak)."""

from __future__ import annotations

import hashlib
import textwrap

import numpy as np
import polars as pl

from pipeline.storage import store
from tests.helpers.processes import run_code


def reference_digest(df: pl.DataFrame, metadata: dict[str, str]) -> str:
    """The checksum written out from its definition (pipeline.storage.store._ColumnHash), whole columns."""
    h = hashlib.sha256()
    for key in sorted(k for k in metadata if k.startswith("mtt.") and k != store.META_CHECKSUM):
        h.update(f"{key}\x1f{metadata[key]}\x1e".encode())
    h.update(f"rows\x1f{df.height}\x1e".encode())
    for s in df.get_columns():
        nulls, values, lengths = hashlib.sha256(), hashlib.sha256(), hashlib.sha256()
        if s.null_count():
            nulls.update(np.flatnonzero(s.is_null().to_numpy()).astype("<i8").tobytes())
        kept = s.drop_nulls()
        if s.dtype in (pl.Float64, pl.Int64) or isinstance(s.dtype, pl.Array):
            values.update(np.ascontiguousarray(kept.to_numpy()).tobytes())
        elif s.dtype == pl.String or isinstance(s.dtype, pl.Categorical):
            text = kept.cast(pl.String).to_list()
            lengths.update(np.array([len(v.encode()) for v in text], dtype="<i8").tobytes())
            values.update("".join(text).encode())
        else:
            values.update("".join(f"{v!r}\x1e" for v in kept.to_list()).encode())
        h.update(hashlib.sha256(f"{s.name}\x1f{s.dtype}".encode() + nulls.digest() + values.digest()
                                + lengths.digest()).digest())
    return h.hexdigest()


def test_a_column_hashed_in_slices_has_the_whole_columns_digest(monkeypatch):
    monkeypatch.setattr(store, "HASH_ROWS", 1000)          # many slices on a small table, ragged last one
    n = 10_500
    rng = np.random.default_rng(3)
    df = pl.DataFrame({
        "name": [None if i % 11 == 0 else f"värde-{i}" * (i % 4) for i in range(n)],   # UTF-8, empty strings
        "kind": pl.Series([f"k{i % 7}" for i in range(n)], dtype=pl.Categorical),
        "pairs": [[i, -i] if i % 5 else None for i in range(n)],
        "x": rng.normal(size=n),
        "P": pl.Series(rng.normal(size=(n, 3)), dtype=pl.Array(pl.Float64, 3)),
    })
    meta = {"mtt.table": "t", "mtt.units": "{}"}
    assert store.content_checksum(df, meta) == reference_digest(df, meta)


SCRIPT = textwrap.dedent("""
    import polars as pl
    from pipeline.run.memory import own_peak_rss_mb
    from pipeline.storage.store import content_checksum

    # 3M names of 30 characters, made by polars (no Python strings): ~90 MB of text
    df = pl.select(pl.int_range(0, 3_000_000).cast(pl.String).str.zfill(30).alias("name"))
    before = own_peak_rss_mb()      # not ru_maxrss: that starts at the (larger) pytest worker's peak
    content_checksum(df, {"mtt.table": "t"})
    print(int(own_peak_rss_mb() - before))
""")


def test_hashing_a_long_text_column_does_not_hold_its_joined_copies():
    grown_mb = int(run_code(SCRIPT, check=True, timeout=None).stdout.strip())
    # whole: the joined text, its Python str and its UTF-8 bytes, ~90 MB each, above the frame's own peak
    assert grown_mb < 40, f"the checksum raised the process's peak by {grown_mb} MB"
