"""Atomic writes and table round trips."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

from pipeline.storage import schemas
from pipeline.storage.store import atomic_write_parquet
from tests.helpers.filter_inputs import scenario


def test_an_interrupted_write_leaves_the_previous_file_and_no_temp(tmp_path, monkeypatch):
    path = tmp_path / "truth.parquet"
    atomic_write_parquet(pl.DataFrame({"a": [1, 2]}), path)
    original = path.read_bytes()

    def dies_half_way(self, f, **kwargs):
        f.write(b"PAR1 half a file")
        raise KeyboardInterrupt   # the user pressed Ctrl-C during the write

    monkeypatch.setattr(pl.DataFrame, "write_parquet", dies_half_way)
    with pytest.raises(KeyboardInterrupt):
        atomic_write_parquet(pl.DataFrame({"a": [3]}), path)
    assert path.read_bytes() == original
    assert sorted(p.name for p in tmp_path.iterdir()) == ["truth.parquet"]


def test_truth_round_trips_through_its_table():
    truth = scenario("ao_vsimm_s2", steps=20).generate(3, 4)
    df, meta = schemas.truth_to_frame(truth)
    assert df.columns[:4] == ["run", "step", "time", "target"] and df.height == 3 * 21
    back = schemas.truth_from_frame(df, meta)
    np.testing.assert_array_equal(back.state, truth.state)
    np.testing.assert_array_equal(back.labels["acceleration"], truth.labels["acceleration"])
    assert back.state_names == truth.state_names


def test_a_table_with_missing_rows_is_refused():
    truth = scenario("ao_vsimm_s1", steps=10).generate(2, 1)
    df, meta = schemas.truth_to_frame(truth)
    with pytest.raises(schemas.TableError, match="do not fill the run x step x target grid"):
        schemas.truth_from_frame(df.filter(~((pl.col("run") == 1) & (pl.col("step") == 3))), meta)


def test_the_cache_key_changes_with_the_code_that_produces_the_output(monkeypatch):
    from pipeline.storage import keys, store
    key = keys.stage_key("track", {"filter": {"name": "B"}}, ("abc",))
    assert key == keys.stage_key("track", {"filter": {"name": "B"}}, ("abc",))
    from pipeline.storage import fingerprint
    monkeypatch.setattr(fingerprint, "source_fingerprint", lambda modules: "edited-filter")
    assert keys.stage_key("track", {"filter": {"name": "B"}}, ("abc",)) != key


@pytest.mark.parametrize("n", [1, 6, 20])
def test_a_packed_covariance_is_its_float32_upper_triangle_and_unpacks_symmetric(n):
    """estimate_to_frame(compact_covariance=True): P_upper holds float32(P[i, j]) for i <= j, row-major;
    estimate_from_frame gives back the symmetric float64 matrix of those values (NaN kept)."""
    from filters.base import TrackEstimate
    rng = np.random.default_rng(n)
    a = rng.normal(size=(3, 5, n, n))
    covariance = a @ np.swapaxes(a, -1, -2) * 1e3
    covariance[1, 2] = np.nan
    est = TrackEstimate(np.arange(5.0), rng.normal(size=(3, 5, n)), covariance, {}, 0.0)
    df, meta = schemas.estimate_to_frame(est, tuple(f"s{i}" for i in range(n)), compact_covariance=True)
    upper = np.triu_indices(n)
    packed = df["P_upper"].to_numpy().reshape(3, 5, -1)
    assert packed.dtype == np.float32
    np.testing.assert_array_equal(packed, covariance[..., upper[0], upper[1]].astype(np.float32))
    back = np.asarray(schemas.estimate_from_frame(df, meta).covariance)
    expected = covariance.astype(np.float32).astype(np.float64)
    np.testing.assert_array_equal(back[..., upper[0], upper[1]], expected[..., upper[0], upper[1]])
    np.testing.assert_array_equal(back, np.swapaxes(back, -1, -2))


def test_a_packed_covariance_indexes_like_the_unpacked_array():
    """PackedCovariance (what a compact estimate table gives back) holds float32 upper triangles;
    every index reads the same as the unpacked float64 array's, a run index unpacking that run only."""
    rng = np.random.default_rng(3)
    a = rng.normal(size=(4, 7, 5, 5))
    full = (a @ np.swapaxes(a, -1, -2)).astype(np.float32).astype(np.float64)
    upper = np.triu_indices(5)
    packed = schemas.PackedCovariance(full[..., upper[0], upper[1]].astype(np.float32), 5)
    assert packed.shape == full.shape and packed.ndim == 4 and len(packed) == 4 and packed.dtype == np.float64
    np.testing.assert_array_equal(np.asarray(packed), full)
    for key in (2, (2, 3), slice(1, 3), [0, 3], (slice(None), 4), (1, slice(None), slice(0, 2), slice(0, 2)),
                (Ellipsis, 0, 0), (Ellipsis, slice(0, 2), slice(0, 2)), np.array([True, False, True, False])):
        np.testing.assert_array_equal(packed[key], full[key], err_msg=str(key))
    with pytest.raises(ValueError, match="entries per matrix"):
        schemas.PackedCovariance(np.zeros((2, 3, 14), dtype=np.float32), 5)
