"""GOSPA, OSPA and the track-level measures of filters.multitarget.metrics: hand-worked cases and
agreement with Stone Soup's GOSPAMetric on random set pairs."""

from __future__ import annotations

import datetime
import itertools

import numpy as np
import pytest

from filters.multitarget.metrics import set_distances, track_measures


def padded(sets, d=2):
    """Ragged [[points of scan 0], ...] of one run as (1, K, width, d), NaN-padded."""
    width = max([len(s) for s in sets] + [1])
    out = np.full((1, len(sets), width, d), np.nan)
    for k, s in enumerate(sets):
        if len(s):
            out[0, k, : len(s)] = s
    return out


def test_gospa_hand_worked():
    # truths (0,0), (10,0); estimates (1,0) (paired, d = 1) and (100,100) (false); (10,0) missed
    # with c = 5, p = 2: localisation 1, missed 25/2, false 25/2 -> gospa = sqrt(26)
    est = padded([[(1.0, 0.0), (100.0, 100.0)]])
    tru = padded([[(0.0, 0.0), (10.0, 0.0)]])
    d = set_distances(est, tru, c=5.0, p=2.0)
    assert d.localisation[0, 0] == pytest.approx(1.0)
    assert d.missed[0, 0] == pytest.approx(12.5) and d.false[0, 0] == pytest.approx(12.5)
    assert d.gospa[0, 0] == pytest.approx(np.sqrt(26.0))
    assert (d.missed_count[0, 0], d.false_count[0, 0]) == (1, 1)
    # OSPA: 2 vs 2, best complete assignment (1,0)-(0,0) cost 1 and the other cut at c^2 = 25
    assert d.ospa[0, 0] == pytest.approx(np.sqrt((1.0 + 25.0) / 2.0))
    assert d.cardinality_error[0, 0] == 0
    assert list(d.pairing[0, 0]) == [0, -1]


def test_gospa_empty_sets_and_p1():
    est = padded([[], [(0.0, 0.0)], [], [(0.0, 0.0), (3.0, 4.0)]])
    tru = padded([[], [], [(1.0, 1.0)], [(0.0, 0.0)]])
    d = set_distances(est, tru, c=10.0, p=1.0)
    # p = 1: an unpaired point costs c/2
    np.testing.assert_allclose(d.gospa[0], [0.0, 5.0, 5.0, 5.0])
    np.testing.assert_allclose(d.ospa[0], [0.0, 10.0, 10.0, (0.0 + 10.0) / 2.0])
    np.testing.assert_allclose(d.cardinality_error[0], [0, 1, -1, 1])


def test_a_pair_at_the_cutoff_or_beyond_is_missed_and_false():
    d = set_distances(padded([[(0.0, 0.0)]]), padded([[(6.0, 8.0)]]), c=10.0, p=2.0)   # d = 10 = c
    assert d.localisation[0, 0] == 0 and d.missed_count[0, 0] == 1 and d.false_count[0, 0] == 1
    assert d.gospa[0, 0] == pytest.approx(10.0)


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="c: -1"):
        set_distances(padded([[]]), padded([[]]), c=-1)
    with pytest.raises(ValueError, match="p: 0.5"):
        set_distances(padded([[]]), padded([[]]), c=1, p=0.5)


def random_sets(rng, R, K, width, spread=30.0):
    pts = rng.uniform(0, spread, (R, K, width, 2))
    count = rng.integers(0, width + 1, (R, K))
    pts[np.arange(width)[None, None, :] >= count[..., None]] = np.nan
    return pts


def brute_force_ospa(X, Y, c, p):
    """OSPA by enumerating every assignment (Schuhmacher et al. 2008 eq. 3), for small sets."""
    X, Y = X[np.isfinite(X).all(-1)], Y[np.isfinite(Y).all(-1)]
    if len(X) > len(Y):
        X, Y = Y, X
    m, n = len(X), len(Y)
    if n == 0:
        return 0.0
    best = min(sum(min(np.linalg.norm(X[i] - Y[j]), c) ** p for i, j in enumerate(perm))
               for perm in itertools.permutations(range(n), m))
    return ((best + c**p * (n - m)) / n) ** (1 / p)


def test_gospa_agrees_with_stone_soup():
    pytest.importorskip("stonesoup")
    from stonesoup.metricgenerator.ospametric import GOSPAMetric, OSPAMetric
    from stonesoup.types.state import State

    rng = np.random.default_rng(7)
    R, K = 6, 10
    est, tru = random_sets(rng, R, K, 6), random_sets(rng, R, K, 5)
    t = datetime.datetime(2026, 1, 1)
    for p, c in ((2.0, 10.0), (1.0, 4.0), (3.0, 25.0)):
        ours = set_distances(est, tru, c=c, p=p)
        metric = GOSPAMetric(p=p, c=c)
        ospa = OSPAMetric(p=p, c=c)
        for r in range(R):
            for k in range(K):
                X = [State(v.reshape(2, 1), timestamp=t) for v in est[r, k] if np.isfinite(v).all()]
                Y = [State(v.reshape(2, 1), timestamp=t) for v in tru[r, k] if np.isfinite(v).all()]
                if not (X or Y):                # Stone Soup wants a timestamp from some state
                    assert ours.gospa[r, k] == 0 and ours.ospa[r, k] == 0
                    continue
                theirs = metric.compute_gospa_metric(X, Y)[0].value
                assert ours.gospa[r, k] == pytest.approx(theirs["distance"], abs=1e-9)
                assert ours.localisation[r, k] == pytest.approx(theirs["localisation"], abs=1e-9)
                assert ours.missed[r, k] == pytest.approx(theirs["missed"], abs=1e-9)
                assert ours.false[r, k] == pytest.approx(theirs["false"], abs=1e-9)
                their_ospa = ospa.compute_OSPA_distance(X, Y).value
                if p == 1.0:
                    assert ours.ospa[r, k] == pytest.approx(their_ospa, abs=1e-9)
                else:
                    # Stone Soup 1.9.1 assigns on min(d, c) and raises the sum to p afterwards,
                    # which is OSPA's optimum only for p = 1; ours minimises sum min(d, c)^p
                    assert ours.ospa[r, k] <= their_ospa + 1e-9
                    assert ours.ospa[r, k] == pytest.approx(brute_force_ospa(est[r, k], tru[r, k], c, p), abs=1e-9)


def test_gospa_is_a_metric_on_random_sets():
    rng = np.random.default_rng(3)
    A, B, C = (random_sets(rng, 4, 20, 4) for _ in range(3))
    ab, ba = set_distances(A, B, 8.0).gospa, set_distances(B, A, 8.0).gospa
    np.testing.assert_allclose(ab, ba, atol=1e-12)                      # symmetry
    assert (set_distances(A, A, 8.0).gospa < 1e-12).all()                # identity
    ac, cb = set_distances(A, C, 8.0).gospa, set_distances(C, B, 8.0).gospa
    assert (ab <= ac + cb + 1e-9).all()                                   # triangle inequality


def test_track_measures_hand_worked():
    # truth 0 at x = 0 for scans 0..5; truth 1 from scan 2 at x = 100
    # track 7 follows truth 0 on scans 1-2, track 8 takes over on 3-5 (one switch at 3);
    # truth 1 tracked by 9 on scan 3 only (break at 4); track 5 a false track far away
    K = 6
    time = np.arange(K) * 2.0
    truths = np.full((1, K, 2, 2), np.nan)
    truth_id = np.full((1, K, 2), -1)
    truths[0, :, 0] = (0.0, 0.0)
    truth_id[0, :, 0] = 0
    truths[0, 2:, 1] = (100.0, 0.0)
    truth_id[0, 2:, 1] = 1
    est = np.full((1, K, 3, 2), np.nan)
    tid = np.full((1, K, 3), -1)
    for k in (1, 2):
        est[0, k, 0], tid[0, k, 0] = (0.5, 0.0), 7
    for k in (3, 4, 5):
        est[0, k, 0], tid[0, k, 0] = (0.0, 0.5), 8
    est[0, 3, 1], tid[0, 3, 1] = (100.0, 1.0), 9
    est[0, 4, 1], tid[0, 4, 1] = (500.0, 500.0), 5
    est[0, 5, 1], tid[0, 5, 1] = (500.0, 500.0), 5
    m = track_measures(time, truths, truth_id, est, tid, c=10.0)
    assert list(m.switches[0]) == [0, 0, 0, 1, 0, 0]
    assert list(m.breaks[0]) == [0, 0, 0, 0, 1, 0]
    assert m.false_tracks[0] == 1 and m.tracks[0] == 4
    assert m.purity[0] == pytest.approx((1 + 1 + 1 + 0) / 4)
    np.testing.assert_allclose(m.delay[0], [2.0, 2.0])                    # truth 0: 0 -> 2 s; truth 1: 4 -> 6 s
    assert m.mean_confirmation_delay[0] == pytest.approx(2.0) and m.never_tracked[0] == 0


def test_track_purity_counts_a_track_that_wanders_between_truths():
    K = 4
    truths = np.zeros((1, K, 2, 2))
    truths[0, :, 1] = (50.0, 0.0)
    truth_id = np.tile([0, 1], (1, K, 1))
    est = np.full((1, K, 1, 2), np.nan)
    est[0, :2, 0] = (0.0, 0.0)
    est[0, 2:, 0] = (50.0, 0.0)
    tid = np.full((1, K, 1), 3)
    m = track_measures(np.arange(K, dtype=float), truths, truth_id, est, tid, c=5.0)
    assert m.purity[0] == pytest.approx(0.5)
    assert m.breaks[0].sum() == 1 and m.switches[0].sum() == 0
    np.testing.assert_allclose(m.delay[0], [0.0, 2.0])
