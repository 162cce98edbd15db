"""The multi-target trackers of filters.multitarget: hand-worked scenes (one target, two targets,
clutter only, GM-PHD's cardinality), the association's parts against brute force, and invariants."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from filters.multitarget import association, kernel
from filters.multitarget.base import DetectionSets
from filters.multitarget.gmphd import GMPHD
from filters.multitarget.metrics import set_distances
from filters.multitarget.trackers import GNN, IMMGNN, IMMJPDA, JPDA, TrackManagement

TRACKERS = (GNN, JPDA, IMMGNN, IMMJPDA)


def scene(starts, runs=4, scans=30, clutter=0.0, detection_probability=1.0, seed=0, noise_std=10.0,
          half_width=1000.0):
    """Straight-line targets (x, vx, y, vy) seen in Poisson clutter uniform on the square of
    ``half_width``; returns truth (R, K, T, 4) and the DetectionSets (time step 1 s)."""
    rng = np.random.default_rng(seed)
    starts = np.asarray(starts, dtype=float).reshape(-1, 4)
    T = len(starts)
    t = np.arange(scans, dtype=float)
    truth = np.broadcast_to(starts[None, None], (runs, scans, T, 4)).copy()
    truth[..., 0] += t[None, :, None] * starts[:, 1]
    truth[..., 2] += t[None, :, None] * starts[:, 3]
    seen = rng.random((runs, scans, T)) < detection_probability
    n_clutter = rng.poisson(clutter, (runs, scans))
    D = max(int((seen.sum(-1) + n_clutter).max()), 1)
    z = np.full((runs, scans, D, 2), np.nan)
    count = np.zeros((runs, scans), np.int64)
    for r in range(runs):
        for k in range(scans):
            points = truth[r, k, seen[r, k]][:, [0, 2]] + rng.normal(0, noise_std, (seen[r, k].sum(), 2))
            points = np.concatenate([points, rng.uniform(-half_width, half_width, (n_clutter[r, k], 2))])
            z[r, k, : len(points)] = rng.permutation(points)
            count[r, k] = len(points)
    return truth, DetectionSets(t, z, count, noise_std**2 * np.eye(2), ("x", "vx", "y", "vy"), (0, 2))


def confirmed_positions(tracks):
    return np.where(tracks.confirmed[..., None], tracks.state[..., [0, 2]], np.nan)


@pytest.mark.parametrize("tracker", TRACKERS, ids=lambda c: c.__name__)
def test_one_target_without_clutter_is_followed_by_one_track(tracker):
    truth, detections = scene([(0.0, 10.0, 0.0, -5.0)])
    tracks = tracker().run(detections)
    confirmed = tracks.confirmed
    assert (confirmed.sum(axis=2)[:, 4:] == 1).all()          # confirmed at the 4th hit (4 of 5), from scan 3 on
    assert not confirmed[:, :3].any()
    ids = np.unique(tracks.track_id[confirmed])
    assert ids.tolist() == [0]
    error = np.linalg.norm(confirmed_positions(tracks)[:, 10:, 0] - truth[:, 10:, 0, [0, 2]], axis=-1)
    assert error.mean() < 10.0 and error.max() < 35.0           # sigma = 10 m per axis measurements
    assert tracks.compute_seconds > 0


@pytest.mark.parametrize("tracker", TRACKERS, ids=lambda c: c.__name__)
def test_two_separated_targets_get_two_tracks(tracker):
    truth, detections = scene([(-400.0, 8.0, 0.0, 0.0), (400.0, -8.0, 300.0, 2.0)], detection_probability=0.95, seed=2)
    tracks = tracker().run(detections)
    d = set_distances(confirmed_positions(tracks), truth[..., [0, 2]], c=50.0)
    assert (d.cardinality_error[:, 10:] == 0).mean() > 0.95
    assert d.localisation[:, 10:].mean() < 2 * 2 * 10.0**2
    for r in range(tracks.runs):
        assert np.unique(tracks.track_id[r][tracks.confirmed[r]]).size == 2


@pytest.mark.parametrize("tracker", TRACKERS, ids=lambda c: c.__name__)
def test_clutter_alone_confirms_no_track(tracker):
    _, detections = scene(np.zeros((0, 4)), runs=5, scans=30, clutter=3.0, seed=4)
    tracks = tracker(clutter_density=3.0 / 2000.0**2).run(detections)
    assert not tracks.confirmed.any()
    assert tracks.extras["tracks_tentative"].max() > 0           # clutter did start tentative tracks


def test_track_ids_are_unique_per_scan_and_slots_padded():
    _, detections = scene([(-400.0, 8.0, 0.0, 0.0), (400.0, -8.0, 300.0, 2.0)], clutter=5.0, seed=5)
    for tracker in (GNN(report_tentative=True), JPDA(report_tentative=True)):
        tracks = tracker.run(detections)
        for r, k in itertools.product(range(tracks.runs), range(len(tracks.time))):
            ids = tracks.track_id[r, k]
            assert np.unique(ids[ids >= 0]).size == (ids >= 0).sum()
            assert np.isnan(tracks.state[r, k][ids < 0]).all()
            assert not tracks.confirmed[r, k][ids < 0].any()
        assert (~tracks.confirmed[tracks.track_id >= 0]).any()          # tentative tracks reported too


def test_a_run_does_not_depend_on_the_runs_batched_with_it():
    _, detections = scene([(-400.0, 8.0, 0.0, 0.0), (0.0, 0.0, 0.0, 10.0)], runs=4, clutter=5.0, seed=6)
    alone = DetectionSets(detections.time, detections.z[2:3], detections.count[2:3], detections.noise_covariance,
                          detections.state_names, detections.position_index)
    for tracker in (GNN(), JPDA(), IMMGNN(), GMPHD()):
        batch, single = tracker.run(detections), tracker.run(alone)
        M = single.state.shape[2]
        np.testing.assert_allclose(batch.state[2:3, :, :M], single.state, atol=1e-9, equal_nan=True)
        np.testing.assert_array_equal(batch.track_id[2:3, :, :M], single.track_id)
        assert (batch.track_id[2:3, :, M:] == -1).all()


def test_management_m_of_n():
    manage = TrackManagement(confirm_hits=2, confirm_window=3, delete_misses=2)
    alive, confirmed = np.ones((1, 3), bool), np.zeros((1, 3), bool)
    hits, age, misses = np.ones((1, 3), np.int64), np.ones((1, 3), np.int64), np.zeros((1, 3), np.int64)
    # track 0 hit at its 2nd scan: confirmed; track 1 missed twice: deleted at its 3rd; 2 hit at its 3rd
    for hit in ([True, False, False], [False, False, True]):
        alive, confirmed, hits, age, misses = manage.step(np.array([hit]), alive, confirmed, hits, age, misses)
    assert alive.tolist() == [[True, False, True]] and confirmed.tolist() == [[True, False, True]]
    for _ in range(2):                       # two misses delete a confirmed track
        alive, confirmed, hits, age, misses = manage.step(np.array([[False, False, True]]), alive, confirmed,
                                                          hits, age, misses)
    assert alive.tolist() == [[False, False, True]]
    with pytest.raises(ValueError, match="confirm_hits: 4 must be <= confirm_window"):
        TrackManagement(confirm_hits=4, confirm_window=3)
    with pytest.raises(ValueError, match="gate_probability: 1"):
        GNN(gate_probability=1)


def brute_force_marginals(g, miss):
    T, D = g.shape
    beta, beta0, total = np.zeros((T, D)), np.zeros(T), 0.0
    for event in itertools.product(*[[-1] + list(np.flatnonzero(g[t] > 0)) for t in range(T)]):
        chosen = [i for i in event if i >= 0]
        if len(chosen) != len(set(chosen)):
            continue
        w = np.prod([g[t, i] if i >= 0 else miss[t] for t, i in enumerate(event)])
        total += w
        for t, i in enumerate(event):
            if i >= 0:
                beta[t, i] += w
            else:
                beta0[t] += w
    return beta / total, beta0 / total, total


def random_cluster(seed, T=4, D=5):
    rng = np.random.default_rng(seed)
    g = rng.exponential(5.0, (T, D)) * (rng.random((T, D)) < 0.6)
    return g, rng.uniform(0.01, 0.2, T)


def test_jpda_marginals_equal_brute_force():
    for seed in range(5):
        g, miss = random_cluster(seed)
        beta, beta0, exact, _ = kernel.jpda_marginals(g, miss, 1e9)
        want, want0, _ = brute_force_marginals(g, miss)
        assert exact.all()
        np.testing.assert_allclose(beta, want, atol=1e-12)
        np.testing.assert_allclose(beta0, want0, atol=1e-12)
        np.testing.assert_allclose(beta.sum(1) + beta0, 1.0)


def test_murty_gives_the_k_best_events_and_the_marginals_when_k_covers_all():
    g, miss = random_cluster(11, T=3, D=3)
    beta, beta0 = association.murty_marginals(g, miss, k=10_000)
    want, want0, _ = brute_force_marginals(g, miss)
    np.testing.assert_allclose(beta, want, atol=1e-12)
    np.testing.assert_allclose(beta0, want0, atol=1e-12)
    # the k best in order
    with np.errstate(divide="ignore"):
        cost = np.full((3, 6), np.inf)
        cost[:, :3] = np.where(g > 0, -np.log(np.where(g > 0, g, 1)), np.inf)
        cost[np.arange(3), 3 + np.arange(3)] = -np.log(miss)
    totals = sorted(cost[np.arange(3), list(p)].sum() for p in itertools.permutations(range(6), 3)
                    if np.isfinite(cost[np.arange(3), list(p)].sum()))
    best = association.murty(cost, 5)
    np.testing.assert_allclose([t for t, _ in best], totals[:5])


def test_a_wide_cluster_falls_back_to_murty():
    g, miss = random_cluster(3, T=4, D=5)
    beta, beta0, counts = association.jpda_weights(g[None], float(miss[0]), max_events=5.0, k_best=10_000)
    want, want0, _ = brute_force_marginals(g, np.full(4, miss[0]))
    coupled = (g > 0).sum(axis=0) > 1
    assert counts["approximated_clusters"][0] >= 1
    rows = ((g > 0) & coupled).any(axis=1)
    np.testing.assert_allclose(beta[0][rows], want[rows], atol=1e-12)


def test_gnn_assignment_is_the_best_with_most_pairs():
    rng = np.random.default_rng(1)
    for _ in range(10):
        cost = rng.uniform(0, 10, (1, 4, 5))
        gated = rng.random((1, 4, 5)) < 0.5
        got = association.gnn_assign(cost, gated)[0]
        best = None
        for event in itertools.product(*[[-1] + list(np.flatnonzero(gated[0, t])) for t in range(4)]):
            chosen = [i for i in event if i >= 0]
            if len(chosen) != len(set(chosen)):
                continue
            key = (-len(chosen), sum(cost[0, t, i] for t, i in enumerate(event) if i >= 0))
            best = key if best is None or key < best else best
        mine = (-(got >= 0).sum(), sum(cost[0, t, i] for t, i in enumerate(got) if i >= 0))
        assert mine[0] == best[0] and mine[1] == pytest.approx(best[1])


def test_gmphd_cardinality_follows_the_truth():
    births = [(-400.0, 0.0, 0.0, 0.0), (400.0, 0.0, 300.0, 0.0)]
    truth, detections = scene([(-400.0, 8.0, 0.0, 0.0), (400.0, -8.0, 300.0, 2.0)], scans=25, clutter=5.0,
                              detection_probability=0.98, seed=8)
    tracks = GMPHD(birth_means=births, birth_std=(10.0, 10.0, 10.0, 10.0), clutter_density=5.0 / 2000.0**2).run(detections)
    cardinality = tracks.extras["cardinality"]
    assert abs(cardinality[:, 8:].mean() - 2.0) < 0.1
    d = set_distances(confirmed_positions(tracks), truth[..., [0, 2]], c=50.0)
    assert (d.cardinality_error[:, 8:] == 0).mean() > 0.85          # a PHD dips at a missed detection
    assert (tracks.extras["components"] <= 100).all()
    # the extracted estimates keep their identity: two ids (one per target) carry the settled scans
    for r in range(tracks.runs):
        _, uses = np.unique(tracks.track_id[r, 8:][tracks.confirmed[r, 8:]], return_counts=True)
        assert np.sort(uses)[-2:].sum() >= 0.9 * uses.sum()


def test_gmphd_without_targets_has_a_small_cardinality():
    _, detections = scene(np.zeros((0, 4)), scans=20, clutter=5.0, seed=9)
    tracks = GMPHD(clutter_density=5.0 / 2000.0**2).run(detections)
    assert tracks.extras["cardinality"][:, 5:].mean() < 0.3


def test_merge_kernel_merges_close_components_and_caps():
    w = np.array([[0.6, 0.3, 0.2, 1e-7]])
    m = np.zeros((1, 4, 4))
    m[0, 2, 0] = 1000.0
    P = np.broadcast_to(np.eye(4), (1, 4, 4, 4)).copy()
    out = (np.zeros((1, 2)), np.zeros((1, 2, 4)), np.zeros((1, 2, 4, 4)), np.zeros((1, 2), np.int64))
    kept = kernel.merge_components(w, m, P, np.array([[5, 6, 7, 8]]), np.array([4]), 1e-5, 4.0, 2, *out)
    assert kept[0] == 2
    np.testing.assert_allclose(out[0][0], [0.9, 0.2])
    assert out[3][0].tolist() == [5, 7]                       # the heaviest member's label


def test_gnn_agrees_with_stone_soup_on_one_target():
    """Stone Soup's GNN (benchmarks/multitarget.py: the same CV model, gate and single-point start,
    MultiMeasurementInitiator with 4 points) on the same detections: the same track, to rounding
    once both have confirmed it."""
    pytest.importorskip("stonesoup")
    from benchmarks.multitarget import stonesoup_gnn

    truth, detections = scene([(0.0, 10.0, 0.0, -5.0)], runs=1, scans=15)
    tracker = GNN()
    ours = confirmed_positions(tracker.run(detections))[0]
    theirs = stonesoup_gnn(detections, 0, tracker.threshold)
    assert theirs.shape[1] == 1 and ours.shape[1] == 1
    np.testing.assert_allclose(ours[4:, 0], theirs[4:, 0], atol=1e-6)


def test_gmphd_agrees_with_stone_soup_on_two_targets():
    """Stone Soup's PHDUpdater and GaussianMixtureReducer on the same detections and births: the same
    extracted estimates and expected count, up to its two departures from Vo & Ma (pruned weight
    spread over the components left; a merged weight capped at 1)."""
    pytest.importorskip("stonesoup")
    from benchmarks.multitarget import stonesoup_gmphd

    births = [(-400.0, 0.0, 0.0, 0.0), (400.0, 0.0, 300.0, 0.0)]
    truth, detections = scene([(-400.0, 8.0, 0.0, 0.0), (400.0, -8.0, 300.0, 2.0)], runs=1, scans=12, clutter=2.0,
                              seed=12)
    kappa = 2.0 / 2000.0**2
    tracks = GMPHD(birth_means=births, clutter_density=kappa).run(detections)
    theirs, cardinality = stonesoup_gmphd(detections, 0, kappa, births)
    np.testing.assert_allclose(tracks.extras["cardinality"][0], cardinality, atol=0.05)
    ours = confirmed_positions(tracks)[0]
    for k in range(3, 12):
        a, b = ours[k][np.isfinite(ours[k, :, 0])], theirs[k][np.isfinite(theirs[k, :, 0])]
        assert len(a) == len(b)
        np.testing.assert_allclose(np.sort(a, axis=0), np.sort(b, axis=0), atol=0.05)    # 7 mm seen


def test_detections_without_planar_positions_are_refused_by_name():
    _, detections = scene([(0.0, 1.0, 0.0, 1.0)], runs=1, scans=3)
    odd = DetectionSets(detections.time, detections.z, detections.count, detections.noise_covariance,
                        ("north", "east"), (0, 1))
    for tracker in (GNN(), GMPHD()):
        with pytest.raises(ValueError, match=r"lack \['x', 'y'\]"):
            tracker.run(odd)


def test_the_benchmark_writes_its_results(tmp_path):
    import json

    from benchmarks.multitarget import main

    assert main(["--runs", "2", "--stonesoup-runs", "0", "--results-dir", str(tmp_path)]) == 0
    record = json.loads((tmp_path / "multitarget.json").read_text())
    rows = record["tables"][0]["rows"]
    assert [r["tracker"] for r in rows] == ["GNN", "JPDA", "IMM-GNN", "IMM-JPDA", "GM-PHD"]
    assert all(r["ours"] > 0 and r["gospa"] > 0 for r in rows)


def test_jpda_weights_are_the_posterior_of_two_targets_and_a_clutter_point():
    """Hand-worked: two tracks (predicted at (0, 0) and (30, 0) m, S = 200 I m^2) and three detections, all in
    both gates. The event posterior from the generative model itself, each track detected in its gate with
    P_D P_G and then spread as N(z; zhat, S) / P_G, a Poisson(lambda) number of clutter points uniform over
    V (their nc! orders), must equal gate -> likelihood_ratios -> jpda_weights (miss = 1 - P_D P_G)."""
    import math

    from scipy.stats import chi2, multivariate_normal, poisson

    pd, pg, lam, V = 0.9, 0.99, 2.0, 1000.0**2
    zhat = np.array([[[0.0, 0.0], [30.0, 0.0]]])
    S = np.broadcast_to(200.0 * np.eye(2), (1, 2, 2, 2)).copy()
    z = np.array([[[5.0, 0.0], [25.0, 3.0], [15.0, 10.0]]])
    d2, gated, logdet = association.gate(zhat, S, z, np.ones((1, 3), bool), np.ones((1, 2), bool), chi2.ppf(pg, 2))
    assert gated.all()
    g = association.likelihood_ratios(d2, logdet, gated, pd, lam / V)
    beta, beta0, _ = association.jpda_weights(g, 1.0 - pd * pg, 1e5, 50)
    want, want0, total = np.zeros((2, 3)), np.zeros(2), 0.0
    for event in itertools.product([-1, 0, 1, 2], repeat=2):
        chosen = [i for i in event if i >= 0]
        if len(chosen) != len(set(chosen)):
            continue
        w = 1.0
        for t, i in enumerate(event):
            w *= pd * pg * multivariate_normal(zhat[0, t], S[0, t]).pdf(z[0, i]) / pg if i >= 0 else 1.0 - pd * pg
        clutter = 3 - len(chosen)
        w *= poisson.pmf(clutter, lam) * math.factorial(clutter) / V**clutter
        total += w
        for t, i in enumerate(event):
            if i >= 0:
                want[t, i] += w
            else:
                want0[t] += w
    np.testing.assert_allclose(beta[0], want / total, atol=1e-12)
    np.testing.assert_allclose(beta0[0], want0 / total, atol=1e-12)
    assert beta[0, 0, 0] > 0.6 and beta[0, 1, 1] > 0.6 and 0.2 < beta[0, 0, 2] < 0.3   # the clutter point shared


def test_jpda_soft_updates_confirm_clutter_tracks_that_gnn_does_not():
    """docs/studies/multitarget.md, why JPDA's GOSPA is above GNN's on the Vo-Vo run: on clutter alone
    (10 points a scan on the Vo-Vo region, 20 runs x 40 scans), single-point starts with a 30 m/s velocity
    spread (the experiment's) have wide first gates; GNN's hard update on a clutter point shrinks the gate
    to ~10 m and the track dies, JPDA's soft update (beta < 1, the spread term) keeps it wide, collects more
    clutter (beta_0 < 1/2: a hit) and confirms it. With 15 m/s (the trackers' default) both confirm few.
    Measured 2026-12-04: JPDA 75 confirmed clutter tracks at 30 m/s (median position std 36 m when
    confirmed), GNN 1 (8 m); at 15 m/s JPDA 2, GNN 1."""
    _, detections = scene(np.zeros((0, 4)), runs=20, scans=40, clutter=10.0, seed=4)
    kappa = 10.0 / 2000.0**2

    def confirmed_clutter_tracks(tracker):
        tracks = tracker.run(detections)
        count, spread = 0, []
        for r in range(tracks.runs):
            for t in np.unique(tracks.track_id[r][tracks.confirmed[r]]):
                k, s = np.nonzero((tracks.track_id[r] == t) & tracks.confirmed[r])
                count += 1
                spread.append(np.sqrt(tracks.covariance[r, k[0], s[0], 0, 0]))
        return count, np.median(spread) if spread else 0.0

    jpda, jpda_spread = confirmed_clutter_tracks(JPDA(clutter_density=kappa, initial_velocity_std=30.0))
    gnn, gnn_spread = confirmed_clutter_tracks(GNN(clutter_density=kappa, initial_velocity_std=30.0))
    assert jpda >= 30 and gnn <= 5, (jpda, gnn)
    assert jpda_spread > 20.0 and gnn_spread < 15.0, (jpda_spread, gnn_spread)
    jpda15, _ = confirmed_clutter_tracks(JPDA(clutter_density=kappa, initial_velocity_std=15.0))
    assert jpda15 <= 10, jpda15
