"""The compiled scan of study 004's particle filters (filters/particle/kernel.py): its float32
functions against float64 numpy, one scan against the numpy loop (engine "numpy") from the same
particles and random numbers, its independence of chunks, threads and batch, and its cache."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from numba import njit

from filters.particle import kernel
from filters.particle import MultipleModelParticleFilter
from tests.helpers.filter_inputs import buoy_reports
from tests.helpers.processes import run_code

ROOT = Path(__file__).resolve().parents[1]


@njit
def _atan2(y, x, out):
    for i in range(y.size):
        out[i] = kernel.atan2_32(y[i], x[i])


@njit
def _exp_log(x, e, lg):
    for i in range(x.size):
        e[i] = kernel.exp32(-x[i])
        lg[i] = kernel.log32(x[i])


@njit
def _exp64(x, out):
    for i in range(x.size):
        out[i] = kernel.exp64(x[i])


def test_the_float32_functions_are_within_a_few_ulp_of_float64():
    rng = np.random.default_rng(0)
    y = (rng.standard_normal(200_000) * 10.0 ** rng.uniform(-3, 4, 200_000)).astype(np.float32)
    x = (rng.standard_normal(200_000) * 10.0 ** rng.uniform(-3, 4, 200_000)).astype(np.float32)
    y[:4], x[:4] = [0.0, 1.0, -1.0, 0.0], [1.0, 0.0, 0.0, -1.0]      # the axes
    got = np.empty_like(y)
    _atan2(y, x, got)
    exact = np.arctan2(y.astype(float), x.astype(float))
    assert np.max(np.abs(got - exact) / np.spacing(np.abs(exact).astype(np.float32) + np.float32(1e-30))) <= 4
    positive = rng.uniform(1e-6, 80.0, 200_000).astype(np.float32)
    e, lg = np.empty_like(positive), np.empty_like(positive)
    _exp_log(positive, e, lg)
    np.testing.assert_allclose(e, np.exp(-positive.astype(float)), rtol=4e-7)
    np.testing.assert_allclose(lg, np.log(positive.astype(float)), rtol=4e-7, atol=2e-7)
    wide = -rng.uniform(0.0, 700.0, 100_000)
    e64 = np.empty_like(wide)
    _exp64(wide, e64)
    np.testing.assert_allclose(e64, np.exp(wide), rtol=1e-15)


@pytest.mark.parametrize("auxiliary, lw_h, clutter, a_m", [(True, 0.3, True, 0.01), (False, 0.3, True, 0.01),
                                                          (True, 0.0, False, 0.01), (True, 0.3, True, 0.2)])
def test_a_scan_equals_the_numpy_loop_to_float32_rounding(auxiliary, lw_h, clutter, a_m):
    """From the same start and random numbers, scan 1's estimate, covariance, mode probabilities,
    ESS and NIS agree with the numpy loop's to float32 rounding (the bearings and likelihoods are
    float32 in both; the kernel's atan2/exp/log are its own polynomials). a_m = 0.2 m/s^2 turns
    by up to 2 rad a scan: the turns' sines from libm instead of the series."""
    _, reports = buoy_reports(runs=4, duration=10.0, clutter=clutter)
    fast, slow = (MultipleModelParticleFilter(particles=300, auxiliary=auxiliary, lw_h=lw_h, max_acceleration=a_m,
                                              snapshot_particles=20, engine=engine).run(reports)
                  for engine in ("numba", "numpy"))
    spread = np.sqrt(np.diagonal(slow.covariance[:, 1], axis1=-2, axis2=-1))
    assert np.max(np.abs(fast.state[:, 1] - slow.state[:, 1]) / spread) < 1e-5           # measured ~4e-7
    scale = spread[:, :, None] * spread[:, None, :]                  # covariances in correlation units
    assert np.max(np.abs(fast.covariance[:, 1] - slow.covariance[:, 1]) / scale) < 1e-5    # measured ~6e-7
    np.testing.assert_allclose(fast.extras["ess"][:, 1], slow.extras["ess"][:, 1], rtol=1e-6)
    np.testing.assert_allclose(fast.extras["mode_probabilities"][:, 1], slow.extras["mode_probabilities"][:, 1],
                               atol=1e-6)
    np.testing.assert_allclose(fast.extras["nis"][:, 1], slow.extras["nis"][:, 1], rtol=1e-5)
    np.testing.assert_array_equal(fast.extras["nis_dof"], slow.extras["nis_dof"])
    # the recorded particle clouds: every scan's (a bug once kept only the first and the last)
    assert np.isfinite(fast.extras["particles"]).all() and (fast.extras["particle_modes"] >= 0).all()
    np.testing.assert_array_equal(fast.extras["particle_modes"][:, 1], slow.extras["particle_modes"][:, 1])
    cloud_error = np.abs(fast.extras["particles"][:, 1] - slow.extras["particles"][:, 1]) / spread[:, None, :]
    assert np.max(cloud_error) < 1e-5


@pytest.mark.parametrize("auxiliary, lw_h", [(True, 0.3), (False, 0.0)])
def test_results_do_not_depend_on_chunks_threads_or_batch(auxiliary, lw_h):
    _, reports = buoy_reports(runs=5, duration=60.0, clutter=True)

    def run(**kwargs):
        return MultipleModelParticleFilter(particles=150, auxiliary=auxiliary, lw_h=lw_h, snapshot_particles=10,
                                           **kwargs).run(reports)

    base = run()
    for other in (run(chunk_runs=1, workers=2), run(chunk_runs=2, workers=1), run(chunk_runs=5, workers=3)):
        np.testing.assert_array_equal(other.state, base.state)
        np.testing.assert_array_equal(other.covariance, base.covariance)
        for name, value in base.extras.items():
            np.testing.assert_array_equal(other.extras[name], value, err_msg=name)
    alone = MultipleModelParticleFilter(particles=150, auxiliary=auxiliary, lw_h=lw_h, snapshot_particles=10
                                        ).run(reports.select([3]))
    np.testing.assert_array_equal(alone.state[0], base.state[3])
    np.testing.assert_array_equal(alone.extras["particles"][0], base.extras["particles"][3])


def test_the_compiled_scan_is_cached_where_it_can_be_written_and_a_new_process_loads_it():
    _, reports = buoy_reports(runs=1, duration=10.0)
    MultipleModelParticleFilter(particles=50).run(reports)
    MultipleModelParticleFilter(particles=50, auxiliary=False, lw_h=0.0).run(reports)
    # one compiled version serves both filters, the draws' check and any size: a second would be
    # a second compilation (~25 s) in every new process's cache
    assert len(kernel.scan.signatures) == 1, kernel.scan.signatures
    path = kernel.scan.stats.cache_path
    assert os.access(path, os.W_OK) and any(name.startswith("kernel.scan-") for name in os.listdir(path))
    code = ("from tests.helpers.filter_inputs import buoy_reports\n"
            "from filters.particle import MultipleModelParticleFilter\n"
            "from filters.particle import kernel\n"
            "MultipleModelParticleFilter(particles=50).run(buoy_reports(runs=1, duration=10.0)[1])\n"
            "print(sum(kernel.scan.stats.cache_hits.values()), sum(kernel.scan.stats.cache_misses.values()))\n")
    out = run_code(code, check=True, timeout=None).stdout.split()
    assert (int(out[-2]), int(out[-1])) == (1, 0), out          # loaded, not compiled again


def test_the_inline_draws_are_numpys_numbers_and_the_fallback_gives_the_same_results(monkeypatch):
    """The kernel draws each run's numbers from its PCG64 state itself (numpy's algorithms: the
    same numbers, the Generators left in the same state); with that switched off the Generators
    draw them (the fallback if numpy ever changed them): the estimates are bit-identical."""
    from filters.particle import reference as particle

    assert particle._inline_draws_match()
    _, reports = buoy_reports(runs=3, duration=60.0, clutter=True)
    for auxiliary in (True, False):
        inline = MultipleModelParticleFilter(particles=120, auxiliary=auxiliary).run(reports)
        monkeypatch.setattr(particle, "_inline_draws_match", lambda: False)
        drawn = MultipleModelParticleFilter(particles=120, auxiliary=auxiliary).run(reports)
        monkeypatch.undo()
        np.testing.assert_array_equal(inline.state, drawn.state)
        np.testing.assert_array_equal(inline.covariance, drawn.covariance)
    g, copy = np.random.default_rng(7), np.random.default_rng(7)
    state = particle._pcg64_state(copy)
    out = np.empty(50_001, dtype=np.float32)
    kernel._normals(state, out)
    np.testing.assert_array_equal(out, g.standard_normal(50_001, dtype=np.float32))
    assert kernel._uniform(state) == g.random()
    particle._set_pcg64_state(copy, state)
    assert copy.random() == g.random() and copy.standard_normal(dtype=np.float32) == g.standard_normal(dtype=np.float32)
