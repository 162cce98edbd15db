"""filters.tracker.kernel.cv_ct_imm: the CV/CT IMM's compiled scan loop against the numpy cycle (the reference),
on turns, straight legs, missed scans, varying scan periods and both measurement kinds, and
read-only inputs (measurements read back from the stage cache) running the
signature warm_up compiled, not a new one inside the filter's clock. Batch independence, for both
engines: tests/test_turn.py."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from filters.tracker import kernel as kalman_kernel
from filters.turn import CVCTIMM
from tests.helpers.assertions import assert_same_to_rounding
from tests.helpers.filter_inputs import radar_series, turning_positions


def assert_engines_agree(m, ct_at_least: float = 0.9, **parameters):
    """``assert_same_to_rounding`` for the CV/CT IMM, and the CT mode reached ``ct_at_least``
    somewhere (both modes were exercised)."""
    compiled = CVCTIMM(engine="numba", **parameters).run(m)
    assert_same_to_rounding(compiled, CVCTIMM(engine="numpy", **parameters).run(m))
    assert np.nanmax(compiled.extras["mode_probabilities"][:, :, 1]) > ct_at_least
    return compiled


@pytest.mark.parametrize("varying", [False, True], ids=["2 s scans", "1-5 s scans"])
def test_on_turns_in_2d_the_compiled_loop_is_the_numpy_cycle(varying):
    assert_engines_agree(turning_positions(np.random.default_rng(21), varying=varying))


def test_on_radar_measurements_in_3d_with_misses_the_compiled_loop_is_the_numpy_cycle():
    m = radar_series(np.random.default_rng(4), R=10, K=80)
    # with an agile prior the CT mode takes over on these straight tracks at times: both modes matter
    assert_engines_agree(m, ct_at_least=0.5, sojourn_times=(10.0, 10.0), initial_mode_probabilities=(0.5, 0.5))


def test_a_mode_that_cannot_be_entered_is_mixed_with_its_own_probability_in_both_engines():
    """sojourn_times inf and mu_CT = 0: c_CT = 0, so mu_{i|CT} falls back to mu_i (filters.turn.mix)."""
    m = turning_positions(np.random.default_rng(2), R=3, K=40)
    ours = CVCTIMM(engine="numba", sojourn_times=(np.inf, np.inf), initial_mode_probabilities=(1.0, 0.0)).run(m)
    theirs = CVCTIMM(engine="numpy", sojourn_times=(np.inf, np.inf), initial_mode_probabilities=(1.0, 0.0)).run(m)
    np.testing.assert_array_equal(ours.extras["mode_probabilities"][:, 1:, 1], 0.0)
    np.testing.assert_allclose(ours.state, theirs.state, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(ours.extras["nis"], theirs.extras["nis"], rtol=1e-10)


def test_read_only_measurements_run_the_warmed_up_signature():
    """Measurements read back from the stage cache are read-only arrays, another numba type: passed
    as they were, the first such job on a machine compiled the loop again inside its clock (6.4 s
    of 'filtered in' on the horizontal ADS-B job, against 0.33 s)."""
    kalman_kernel.warm_up()
    signatures = len(kalman_kernel.cv_ct_imm.signatures)
    m = turning_positions(np.random.default_rng(3), R=2, K=20)
    z, detected = m.z.copy(), m.detected.copy()
    z.flags.writeable = detected.flags.writeable = False
    CVCTIMM(engine="numba").run(replace(m, z=z, detected=detected))
    assert len(kalman_kernel.cv_ct_imm.signatures) == signatures


def test_an_unknown_engine_is_refused_with_the_choices():
    with pytest.raises(ValueError, match=r"^engine: 'cuda' must be one of \['numba', 'numpy'\]"):
        CVCTIMM(engine="cuda")
