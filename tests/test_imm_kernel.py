"""The compiled IMM cycle (filters/imm/kernel.py, ``engine="numba"``) against the numpy cycle
(``engine="numpy"``, the reference): the same estimates to rounding, for the three estimators of
study 001, with missed detections and per-run noise; and a run's numbers independent of its batch,
bit for bit (alone, in chunks, beside runs of other sizes of running sets)."""

from __future__ import annotations

import numpy as np
import pytest

from filters.base import MeasurementSeries
from filters.imm import AOVSIMM, FSIMM, VSIMM, LinearModelBank, ModeSet, imm_cycle
from tests.helpers.filter_inputs import measurements, scenario

EXTRAS = ("mode_probabilities", "acceleration", "nis")
DECISIONS = ("models_evaluated", "active_group", "candidate_group")
ESTIMATORS = [
    pytest.param(lambda m, e: FSIMM(m, engine=e), id="FSIMM"),
    pytest.param(lambda m, e: VSIMM(m, engine=e), id="VSIMM"),
    pytest.param(lambda m, e: VSIMM(m, ratio="new_old", engine=e), id="VSIMM-new_old"),
    pytest.param(lambda m, e: AOVSIMM(m, engine=e), id="AO-VSIMM"),
    pytest.param(lambda m, e: FSIMM(m, initial_mode_probabilities=[0.5, 0.3] + [0.2 / 11] * 11, engine=e),
                 id="FSIMM-mu0"),
]


@pytest.fixture(scope="module")
def models(models13):
    return models13


@pytest.fixture(scope="module")
def meas():
    """6 runs of S2 (group switches both ways), 90 steps, ~10 % of the scans from k = 3 missed."""
    m = measurements(scenario("ao_vsimm_s2", steps=90).generate(6, 5), 5)
    miss = np.random.default_rng(5).random(m.detected.shape) < 0.1
    miss[:, :3] = False
    detected = m.detected & ~miss
    return MeasurementSeries(m.time, np.where(detected[..., None], m.z, np.nan), m.noise_covariance, detected,
                             m.sensor)


def _per_run_noise(m: MeasurementSeries) -> MeasurementSeries:
    """Each run and scan its own R (scaled, correlated), as converted radar plots give (noise.ndim == 4)."""
    R, K = m.detected.shape
    rng = np.random.default_rng(9)
    scale = rng.uniform(0.5, 2.0, (R, K))[..., None, None]
    rho = rng.uniform(-0.5, 0.5, (R, K))
    base = np.stack([np.stack([np.ones_like(rho), rho], -1), np.stack([rho, np.ones_like(rho)], -1)], -2)
    return MeasurementSeries(m.time, m.z, 400.0 * scale * base, m.detected, m.sensor)


def _assert_agree(a, b):
    scale = np.abs(b.state[:, 1:]).max()
    assert np.abs(a.state[:, 1:] - b.state[:, 1:]).max() <= 1e-13 * scale
    cov_scale = np.abs(b.covariance[:, 1:]).max()
    assert np.abs(a.covariance[:, 1:] - b.covariance[:, 1:]).max() <= 1e-11 * cov_scale
    for name in EXTRAS:
        x, y = a.extras[name], b.extras[name]
        np.testing.assert_array_equal(np.isnan(x), np.isnan(y), err_msg=name)
        np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-9, err_msg=name)
    for name in DECISIONS:
        np.testing.assert_array_equal(a.extras[name], b.extras[name], err_msg=name)


def _assert_identical(a, b):
    np.testing.assert_array_equal(a.state, b.state)
    np.testing.assert_array_equal(a.covariance, b.covariance)
    for name in EXTRAS + DECISIONS:
        np.testing.assert_array_equal(a.extras[name], b.extras[name], err_msg=name)


def _runs(m: MeasurementSeries, rows) -> MeasurementSeries:
    noise = m.noise_covariance[rows] if m.noise_covariance.ndim == 4 else m.noise_covariance
    return MeasurementSeries(m.time, m.z[rows], noise, m.detected[rows], m.sensor)


def _concat(parts):
    first = parts[0]
    extras = {k: np.concatenate([p.extras[k] for p in parts]) for k in first.extras}
    return type(first)(first.time, np.concatenate([p.state for p in parts]),
                       np.concatenate([p.covariance for p in parts]), extras, 0.0)


@pytest.mark.parametrize("make", ESTIMATORS)
@pytest.mark.parametrize("noise", ["shared", "per_run"])
def test_compiled_engine_agrees_with_numpy_to_rounding(make, noise, models, meas):
    m = meas if noise == "shared" else _per_run_noise(meas)
    compiled, reference = make(models, "numba"), make(models, "numpy")
    assert compiled.engine == "numba" and reference.engine == "numpy"
    _assert_agree(compiled.run(m), reference.run(m))


@pytest.mark.parametrize("make", ESTIMATORS)
def test_compiled_run_does_not_depend_on_its_batch(make, models, meas):
    m = _per_run_noise(meas)
    est = make(models, "numba")
    whole = est.run(m)
    alone = _concat([est.run(_runs(m, [r])) for r in range(m.runs)])
    chunked = _concat([est.run(_runs(m, rows)) for rows in ([4, 0], [1, 2, 3, 5])])
    chunked = _runs_of(chunked, np.argsort([4, 0, 1, 2, 3, 5]))
    _assert_identical(alone, whole)
    _assert_identical(chunked, whole)


def _runs_of(estimate, rows):
    extras = {k: v[rows] for k, v in estimate.extras.items()}
    return type(estimate)(estimate.time, estimate.state[rows], estimate.covariance[rows], extras, 0.0)


def _random_prior(rng, R, A, M, valid):
    n = 4
    L = rng.normal(size=(R, A, n, n))
    P = L @ np.swapaxes(L, -1, -2) + n * np.eye(n)
    return ModeSet(
        np.where(valid, rng.permuted(np.tile(np.arange(M), (R, 1)), axis=1)[:, :A], -1),
        np.where(valid[..., None], rng.normal(0, 50, (R, A, n)), 0.0),
        np.where(valid[..., None, None], 0.5 * (P + np.swapaxes(P, -1, -2)), 0.0),
        np.where(valid, 0.0, -np.inf), np.where(valid, 0.0, -np.inf),
        np.where(valid, rng.normal(0, 3, (R, A)), -np.inf),
        np.zeros((R, A, n)), np.zeros((R, A, n, n)))


@pytest.mark.parametrize("bank_kind", ["constant_velocity", "general"])
def test_compiled_cycle_with_padding_and_general_models(bank_kind, models):
    """One cycle on ragged sets (empty prior slots anywhere, empty targets, an unreachable target,
    missed detections): the compiled cycle gives the numpy cycle's ModeSet to rounding, for the
    written-out constant-velocity case and for general per-model F, Q and a general H."""
    rng = np.random.default_rng(3)
    R, A, B, M = 7, 6, 5, models.n_models
    bank = LinearModelBank.from_model_set(models)
    if bank_kind == "general":
        F = bank.transition + rng.normal(0, 0.05, (M, 4, 4))
        G = rng.normal(0, 1, (M, 4, 4))
        H = np.array([[1.0, 0.1, 0.0, 0.0], [0.2, 0.0, 1.0, 0.3]])
        bank = LinearModelBank(F, G @ np.swapaxes(G, -1, -2), bank.offsets, bank.tpm, H)
        assert bank.kernel_arguments[5] is False
    else:
        assert bank.kernel_arguments[5] is True
    valid = rng.random((R, A)) < 0.7
    valid[:, 2] = True
    prior = _random_prior(rng, R, A, M, valid)
    targets = np.where(rng.random((R, B)) < 0.8, rng.integers(0, M, (R, B)), -1)
    targets[0] = [0, 12, -1, 7, 3]                   # the CV model, an outer one, padding
    targets[1] = -1                                  # a run with nothing to run
    z = rng.normal(0, 50, (R, 2))
    noise = np.array([[400.0, 30.0], [30.0, 300.0]])
    detected = np.array([True, True, False, True, True, False, True])
    got = imm_cycle(prior, targets, z, noise, bank, detected, engine="numba")
    want = imm_cycle(prior, targets, z, noise, bank, detected, engine="numpy")
    np.testing.assert_array_equal(got.model_index, want.model_index)
    for field in ("x", "P", "x_predicted", "P_predicted"):
        np.testing.assert_allclose(getattr(got, field), getattr(want, field), rtol=1e-12, atol=1e-9, err_msg=field)
    for field in ("log_predicted", "log_likelihood", "log_weight"):
        a, b = getattr(got, field), getattr(want, field)
        np.testing.assert_array_equal(np.isneginf(a), np.isneginf(b), err_msg=field)
        fin = np.isfinite(b)
        np.testing.assert_allclose(a[fin], b[fin], rtol=1e-12, atol=1e-12, err_msg=field)


def test_engine_is_checked(models):
    with pytest.raises(ValueError, match="engine"):
        FSIMM(models, engine="cuda")


def test_one_compilation_serves_every_estimator_and_bank(models, meas):
    """filters.imm hands the kernel one set of argument types (C-contiguous int64 / float64 / bool,
    shared or per-run noise, shared or per-model F and Q): a second signature would compile again
    (seconds) in the middle of a run."""
    from filters.imm import kernel as imm_kernel

    for make in (FSIMM, VSIMM, AOVSIMM):
        make(models).run(meas)
        make(models).run(_per_run_noise(meas))
    assert len(imm_kernel.cycle.signatures) == 1, imm_kernel.cycle.signatures
    assert len(imm_kernel.summary.signatures) == 1, imm_kernel.summary.signatures


@pytest.mark.parametrize("ratio", VSIMM.RATIOS)
def test_compiled_group_logic_agrees_with_numpy(ratio, models):
    """Activation and termination on ragged random sets (runs in and out of a union, padding slots,
    a -inf likelihood): the compiled statistics give numpy's decisions and log t^L to rounding."""
    from filters.imm import GroupState

    rng = np.random.default_rng(11)
    R, A, M = 40, 9, models.n_models
    old = rng.integers(0, len(models.group_names), R)
    new = np.where(rng.random(R) < 0.7, rng.integers(0, len(models.group_names), R), -1)
    new = np.where(new == old, -1, new)
    index = np.full((R, A), -1)
    for r in range(R):
        members = np.unique(np.concatenate([models.groups[g][models.groups[g] >= 0] for g in {old[r], new[r]} - {-1}]))
        index[r, :members.size] = rng.permutation(members)[:A]
    valid = index >= 0
    log_pred = np.where(valid, np.log(rng.dirichlet(np.ones(A), R)), -np.inf)
    log_lik = np.where(valid, rng.normal(-3, 2, (R, A)), -np.inf)
    log_lik[0, 0] = -np.inf
    zeros = np.zeros((R, A, 4)), np.broadcast_to(np.eye(4), (R, A, 4, 4)).copy()
    s = ModeSet(index, *zeros, log_pred, log_lik, log_pred + log_lik, *zeros)
    groups = GroupState(old=old, new=new, log_lr=rng.normal(0, 0.2, R))
    in_union = new >= 0
    compiled = VSIMM(models, ratio=ratio, activation_threshold=0.3, engine="numba")
    reference = VSIMM(models, ratio=ratio, activation_threshold=0.3, engine="numpy")
    np.testing.assert_array_equal(compiled._activation(s, old, ~in_union), reference._activation(s, old, ~in_union))
    assert (reference._activation(s, old, ~in_union) >= 0).any()
    kept, g1 = compiled._terminate(s, groups, in_union)
    want, g2 = reference._terminate(s, groups, in_union)
    np.testing.assert_array_equal(g1.old, g2.old)
    np.testing.assert_array_equal(g1.new, g2.new)
    np.testing.assert_allclose(g1.log_lr, g2.log_lr, rtol=1e-12, atol=1e-12)
    assert (g2.new < 0).sum() > (~in_union).sum()            # some unions ended
    np.testing.assert_array_equal(kept.model_index, want.model_index)
