"""Set distances and track-level measures of multi-target estimates against the truth, batched over
runs and scans. Pure numpy (and scipy's assignment); nothing here knows about the pipeline.

Sets are padded arrays: estimates (R, K, M, d) and truths (R, K, N, d), NaN in empty slots (a slot
counts when all its d coordinates are finite, or where an explicit ``valid`` mask says so).

GOSPA (Rahmathullah, Garcia-Fernandez & Svensson, "Generalized optimal sub-pattern assignment
metric", FUSION 2017, eq. 1 and Proposition 1). For sets X = {x_1..x_m} (estimates) and
Y = {y_1..y_n} (truths), cut-off c > 0, order 1 <= p < inf and alpha = 2::

    d_p^(c,2)(X, Y) = ( min_gamma  sum_{(i,j) in gamma} d(x_i, y_j)^p  +  c^p / 2 (|X| + |Y| - 2 |gamma|) )^(1/p)

over partial assignments gamma whose pairs have d(x_i, y_j) < c (Proposition 1). Since
min(d, c)^p <= c^p = 2 c^p / 2, the minimum equals the optimal *complete* assignment of min(m, n)
pairs under the cut distance min(d, c)^p, with every pair at d >= c then read as one missed and
one false target. Its exact split (eq. 3 of the paper): ``localisation`` = sum of d^p over the
pairs with d < c, ``missed`` = c^p/2 x (truths left unassigned), ``false`` = c^p/2 x (estimates left
unassigned); distance = (localisation + missed + false)^(1/p). The three parts are given in those
d^p units, as Stone Soup's ``GOSPAMetric`` gives them.

OSPA (Schuhmacher, Vo & Vo, IEEE TSP 56(8), 2008, eq. 3) from the same assignment, for m <= n::

    d_p^(c)(X, Y) = ( (min_pi sum_{i<=m} min(d(x_i, y_pi(i)), c)^p + c^p (n - m)) / n )^(1/p)

(0 when both sets are empty, c when exactly one is). Cardinality error: |X| - |Y| per scan.

The assignment of each (run, scan) is scipy.optimize.linear_sum_assignment on the (m, n) matrix of
cut distances; a scan with an empty set needs none.

Track-level measures (``track_measures``) read the GOSPA assignment as "truth j is tracked by the
track whose estimate is paired with it at d < c" and count, per run: track switches (a truth's
track id changes from the last one it had), breaks (a truth tracked at its previous scan is not
tracked at this one although it still exists), false tracks (track ids never paired with any truth
during their life), confirmed-track purity (per track id, the share of its scans spent on its most
frequent truth; the mean over tracks) and the confirmation delay (seconds from a truth's first scan
to its first tracked one; NaN for a truth never tracked).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

__all__ = ["SetDistances", "set_distances", "gospa", "TrackMeasures", "track_measures", "cardinality_error"]


@dataclass(frozen=True)
class SetDistances:
    """Per (run, scan) distances between the estimated and the true set, each (R, K).

    gospa, and its parts localisation, missed and false (in d^p units: gospa^p is their sum);
    missed_count / false_count the truths / estimates left unpaired (pairs at d >= c count in
    both); ospa; cardinality_error = |X| - |Y|; pairing (R, K, N) int the estimate slot paired with
    each truth slot at d < c, -1 where none (or the truth slot is empty); p and c as given.
    """

    gospa: np.ndarray
    localisation: np.ndarray
    missed: np.ndarray
    false: np.ndarray
    missed_count: np.ndarray
    false_count: np.ndarray
    ospa: np.ndarray
    cardinality_error: np.ndarray
    pairing: np.ndarray
    p: float
    c: float


def _checked(c: float, p: float) -> tuple[float, float]:
    if not (isinstance(c, (int, float)) and np.isfinite(c) and c > 0):
        raise ValueError(f"c: {c!r} must be a finite cut-off distance > 0")
    if not (isinstance(p, (int, float)) and np.isfinite(p) and p >= 1):
        raise ValueError(f"p: {p!r} must be a finite order >= 1")
    return float(c), float(p)


def _valid(points: np.ndarray, valid: np.ndarray | None, what: str) -> np.ndarray:
    if points.ndim != 4:
        raise ValueError(f"{what}: shape {points.shape} must be (runs, scans, slots, d)")
    if valid is None:
        return np.isfinite(points).all(axis=-1)
    valid = np.asarray(valid, dtype=bool)
    if valid.shape != points.shape[:3]:
        raise ValueError(f"{what}_valid: shape {valid.shape} must be {points.shape[:3]}")
    return valid


def cardinality_error(estimate_valid: np.ndarray, truth_valid: np.ndarray) -> np.ndarray:
    """(R, K) |X| - |Y| from the slot masks (R, K, M) and (R, K, N)."""
    return estimate_valid.sum(axis=-1).astype(float) - truth_valid.sum(axis=-1)


def set_distances(estimates: np.ndarray, truths: np.ndarray, c: float, p: float = 2.0,
                  estimate_valid: np.ndarray | None = None, truth_valid: np.ndarray | None = None
                  ) -> SetDistances:
    """GOSPA (alpha = 2) with its split, OSPA and the cardinality error of every (run, scan).

    estimates (R, K, M, d), truths (R, K, N, d): positions (or any vectors in one metric space),
    NaN in empty slots unless ``*_valid`` (R, K, slots) masks are given. See the module docstring.
    """
    c, p = _checked(c, p)
    estimates = np.asarray(estimates, dtype=float)
    truths = np.asarray(truths, dtype=float)
    ev, tv = _valid(estimates, estimate_valid, "estimates"), _valid(truths, truth_valid, "truths")
    if estimates.shape[:2] != truths.shape[:2] or estimates.shape[-1] != truths.shape[-1]:
        raise ValueError(f"estimates {estimates.shape} and truths {truths.shape} must share runs, scans and d")
    R, K, M, _ = estimates.shape
    N = truths.shape[2]
    m, n = ev.sum(axis=-1), tv.sum(axis=-1)
    cp = c**p
    localisation = np.zeros((R, K))
    paired = np.zeros((R, K), dtype=np.int64)
    assigned_cost = np.zeros((R, K))
    pairing = np.full((R, K, N), -1, dtype=np.int64)
    both = np.argwhere((m > 0) & (n > 0))
    # filled slots first is not promised: index them per (run, scan)
    for r, k in both:
        ei, ti = np.flatnonzero(ev[r, k]), np.flatnonzero(tv[r, k])
        diff = estimates[r, k, ei][:, None, :] - truths[r, k, ti][None, :, :]
        distance = np.sqrt(np.einsum("ijd,ijd->ij", diff, diff))
        cost = np.minimum(distance, c) ** p
        rows, cols = linear_sum_assignment(cost)
        assigned_cost[r, k] = cost[rows, cols].sum()
        close = distance[rows, cols] < c
        localisation[r, k] = cost[rows, cols][close].sum()
        paired[r, k] = close.sum()
        pairing[r, k, ti[cols[close]]] = ei[rows[close]]
    missed_count, false_count = n - paired, m - paired
    missed, false = cp / 2.0 * missed_count, cp / 2.0 * false_count
    gospa_value = (localisation + missed + false) ** (1.0 / p)
    larger = np.maximum(m, n)
    with np.errstate(invalid="ignore", divide="ignore"):
        ospa = np.where(larger > 0, ((assigned_cost + cp * np.abs(m - n)) / np.where(larger > 0, larger, 1))
                        ** (1.0 / p), 0.0)
    return SetDistances(gospa_value, localisation, missed, false, missed_count, false_count, ospa,
                        (m - n).astype(float), pairing, p, c)


def gospa(estimates: np.ndarray, truths: np.ndarray, c: float, p: float = 2.0, **valid) -> np.ndarray:
    """(R, K) GOSPA distance (alpha = 2); ``set_distances`` gives its split."""
    return set_distances(estimates, truths, c, p, **valid).gospa


@dataclass(frozen=True)
class TrackMeasures:
    """Track-level measures (module docstring).

    switches (R, K) and breaks (R, K) counted at the scan where they happen; per run (R,):
    false_tracks, tracks (distinct track ids reported), purity (mean over track ids, NaN without
    tracks), mean_confirmation_delay [s] (over the truths ever tracked, NaN if none) and
    never_tracked (truths never paired); delay (R, T) per truth id 0..T-1 (NaN if never tracked or
    never present).
    """

    switches: np.ndarray
    breaks: np.ndarray
    false_tracks: np.ndarray
    tracks: np.ndarray
    purity: np.ndarray
    mean_confirmation_delay: np.ndarray
    never_tracked: np.ndarray
    delay: np.ndarray


def track_measures(time: np.ndarray, truths: np.ndarray, truth_id: np.ndarray, estimates: np.ndarray,
                   track_id: np.ndarray, c: float, p: float = 2.0,
                   distances: SetDistances | None = None) -> TrackMeasures:
    """Switches, breaks, false tracks, purity and confirmation delay of the tracks ``track_id``
    (R, K, M) at ``estimates`` (R, K, M, d) against truths (R, K, N, d) labelled ``truth_id``
    (R, K, N), ids >= 0 (-1 in empty slots). Pass only the tracks the tracker reports as targets
    (confirmed). ``distances``: the ``set_distances`` of the same sets, if already computed."""
    time = np.asarray(time, dtype=float)
    truth_id = np.asarray(truth_id, dtype=np.int64)
    track_id = np.asarray(track_id, dtype=np.int64)
    tv, ev = truth_id >= 0, track_id >= 0
    if distances is None:
        distances = set_distances(estimates, truths, c, p, estimate_valid=ev, truth_valid=tv)
    R, K, N = truth_id.shape
    slot = distances.pairing
    r_idx, k_idx, j_idx = np.nonzero(tv)
    truth = truth_id[r_idx, k_idx, j_idx]
    s = slot[r_idx, k_idx, j_idx]
    track = np.where(s >= 0, track_id[r_idx, k_idx, np.maximum(s, 0)], -1)
    order = np.lexsort((k_idx, truth, r_idx))                  # by run, truth, scan
    r_idx, k_idx, truth, track = r_idx[order], k_idx[order], truth[order], track[order]
    same = np.zeros(truth.size, dtype=bool)
    same[1:] = (r_idx[1:] == r_idx[:-1]) & (truth[1:] == truth[:-1])
    # breaks: tracked at the previous entry of this truth, present and untracked now
    breaks = np.zeros((R, K), dtype=np.int64)
    broken = np.zeros(truth.size, dtype=bool)
    broken[1:] = same[1:] & (track[:-1] >= 0) & (track[1:] < 0)
    np.add.at(breaks, (r_idx[broken], k_idx[broken]), 1)
    # switches: among the tracked entries of a truth, the track id differs from the last one
    switches = np.zeros((R, K), dtype=np.int64)
    on = track >= 0
    tr_r, tr_k, tr_t, tr_a = r_idx[on], k_idx[on], truth[on], track[on]
    switched = np.zeros(tr_a.size, dtype=bool)
    switched[1:] = (tr_r[1:] == tr_r[:-1]) & (tr_t[1:] == tr_t[:-1]) & (tr_a[1:] != tr_a[:-1])
    np.add.at(switches, (tr_r[switched], tr_k[switched]), 1)
    # confirmation delay per (run, truth id)
    T = int(truth_id.max()) + 1 if truth_id.size and truth_id.max() >= 0 else 0
    born = np.full((R, T), np.inf)
    first_tracked = np.full((R, T), np.inf)
    np.minimum.at(born, (r_idx, truth), time[k_idx])
    np.minimum.at(first_tracked, (tr_r, tr_t), time[tr_k])
    delay = np.where(np.isfinite(first_tracked), first_tracked - born, np.nan)
    present = np.isfinite(born)
    tracked = np.isfinite(delay)
    with np.errstate(invalid="ignore"):
        mean_delay = np.where(tracked.any(axis=1), np.nansum(np.where(tracked, delay, 0.0), axis=1)
                              / np.maximum(tracked.sum(axis=1), 1), np.nan)
    never = (present & ~tracked).sum(axis=1)
    # purity and false tracks per (run, track id)
    er, ek, em = np.nonzero(ev)
    eid = track_id[er, ek, em]
    partner = np.full(track_id.shape, -1, dtype=np.int64)      # truth id paired with each track slot
    rr, kk, jj = np.nonzero(tv & (slot >= 0))
    partner[rr, kk, slot[rr, kk, jj]] = truth_id[rr, kk, jj]
    ep = partner[er, ek, em]
    false_tracks = np.zeros(R, dtype=np.int64)
    tracks = np.zeros(R, dtype=np.int64)
    purity = np.full(R, np.nan)
    if eid.size:
        keys, life = np.unique(np.stack([er, eid]), axis=1, return_counts=True)      # (2, U) run, track id
        tracks = np.bincount(keys[0], minlength=R)
        hit = ep >= 0
        pair_keys, pair_counts = np.unique(np.stack([er[hit], eid[hit], ep[hit]]), axis=1, return_counts=True)
        best = np.zeros(keys.shape[1], dtype=np.int64)
        if pair_keys.size:
            where = _rows_of(keys, pair_keys[:2])
            np.maximum.at(best, where, pair_counts)
        false_tracks = np.bincount(keys[0], weights=(best == 0), minlength=R).astype(np.int64)
        share = best / life
        with np.errstate(invalid="ignore"):
            purity = np.where(tracks > 0, np.bincount(keys[0], weights=share, minlength=R) / np.maximum(tracks, 1),
                              np.nan)
    return TrackMeasures(switches, breaks, false_tracks, tracks, purity, mean_delay, never, delay)


def _rows_of(keys: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """Column index in ``keys`` (2, U), sorted lexicographically as np.unique leaves it, of each column of
    ``wanted`` (2, V), all of which are present."""
    span = int(max(keys[1].max(), wanted[1].max())) + 1
    flat = keys[0] * span + keys[1]
    return np.searchsorted(flat, wanted[0] * span + wanted[1])
