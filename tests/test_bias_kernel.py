"""Study 002's compiled local-filter steps (filters/bias/kernel.py, ``engine="numba"``) against the
numpy steps of filters/bias/reference.py, their reference: the update bit for bit, the move to rounding, and
whole registrations of every method to rounding, a run filtered alone as in the batch."""

from __future__ import annotations

import numpy as np
import pytest

from filters.bias import EXXRegistration, LocalTracking, LocalTracks, PseudoBiasRegistration, predict_local, update_local
from tests.helpers.bias_reports import simulate


def _stack(seed: int = 0, runs: int = 7, targets: int = 5):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(runs, targets, 4, 4))
    P = A @ np.swapaxes(A, -1, -2) + 4.0 * np.eye(4)
    tracks = LocalTracks(rng.normal(size=(runs, targets, 4)) * 1e3, P, rng.normal(size=(runs, targets, 4, 4)))
    B = rng.normal(size=(runs, targets, 2, 2))
    noise = B @ np.swapaxes(B, -1, -2) + np.eye(2)
    return tracks, rng.normal(size=(runs, targets, 2)) * 1e3, noise, rng.normal(size=(runs, targets, 2, 4))


def test_the_compiled_update_is_the_numpy_update_bit_for_bit():
    tracks, z, noise, bias_columns = _stack()
    reference = update_local(tracks, z, noise, bias_columns, "numpy")
    compiled = update_local(tracks, z, noise, bias_columns, "numba")
    for name in ("state", "covariance", "bias_matrix", "nis"):
        assert np.array_equal(getattr(compiled, name), getattr(reference, name)), name
    np.testing.assert_array_equal(compiled.covariance, np.swapaxes(compiled.covariance, -1, -2))   # symmetrised


@pytest.mark.parametrize("dt", [1.0, 0.5, 1.7, 13.25])
def test_the_compiled_move_is_the_numpy_move_to_rounding(dt):
    tracks, *_ = _stack(seed=1)
    reference = predict_local(tracks, dt, 6.0, "numpy")
    compiled = predict_local(tracks, dt, 6.0, "numba")
    for name in ("state", "covariance", "bias_matrix"):
        want = getattr(reference, name)
        np.testing.assert_allclose(getattr(compiled, name), want, rtol=1e-13, atol=1e-13 * np.abs(want).max(),
                                   err_msg=name)
    no_bias = predict_local(LocalTracks(tracks.state, tracks.covariance, None), dt, 6.0, "numba")
    assert no_bias.bias_matrix is None
    np.testing.assert_array_equal(no_bias.covariance, compiled.covariance)


@pytest.mark.parametrize("method", [LocalTracking, PseudoBiasRegistration, EXXRegistration])
@pytest.mark.parametrize("start", ["truth", "two_point"])
def test_every_method_registers_the_same_with_either_engine(method, start):
    _, reports, _ = simulate(runs=3, targets=4, reports=50, q=1.0, seed=5)
    compiled = method(output_targets=None, start=start, engine="numba").run(reports)
    reference = method(output_targets=None, start=start, engine="numpy").run(reports)
    for name in ("bias", "bias_covariance", "track_state", "track_covariance", "compensated_state",
                 "compensated_covariance", "nis"):
        want = getattr(reference, name)
        np.testing.assert_allclose(getattr(compiled, name), want, rtol=1e-9,
                                   atol=1e-12 * np.nanmax(np.abs(want)) if np.isfinite(want).any() else 0,
                                   err_msg=name)


def test_a_run_registered_alone_equals_the_same_run_in_the_batch():
    _, reports, _ = simulate(runs=4, targets=3, reports=40, seed=6)
    batch = PseudoBiasRegistration(output_targets=None).run(reports)
    alone = PseudoBiasRegistration(output_targets=None).run(reports.select([2]))
    for name in ("bias", "track_state", "track_covariance", "compensated_state"):
        assert np.array_equal(getattr(alone, name)[0], getattr(batch, name)[2], equal_nan=True), name


def test_an_unknown_engine_is_refused_with_the_choices():
    with pytest.raises(ValueError, match=r"engine: 'cuda' must be one of \['numba', 'numpy'\]"):
        LocalTracking(engine="cuda")
