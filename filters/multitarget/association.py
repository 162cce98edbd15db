"""Gating and data association of every run's tracks and detections.

Gating (batched over runs, tracks and detections): d2[r, t, i] = nu' S_t^-1 nu with
nu = z_i - H x_t^-, S_t = H P_t^- H' + R; detection i is in track t's gate when d2 < gamma,
gamma = chi2_m^-1(P_G) (the gate probability P_G of a chi-square with m = 2 degrees of freedom).

GNN (``gnn_assign``; Blackman & Popoli 1999, 6.4): per run, the 2-D assignment of tracks to
detections that makes the most gated pairs and, among those, has the least total cost
sum (d2 + ln |S_t|) (the generalised statistical distance, which does not favour a wide gate),
solved by scipy.optimize.linear_sum_assignment on the gated tracks and detections only. Every
gated pair's cost is shifted down by a constant larger than any sum of costs, and a pair outside
the gate costs 0 = "not assigned", so one rectangular assignment solves the problem with misses.

JPDA (``jpda_weights``): exact marginals per cluster (filters.multitarget.kernel.jpda_marginals).
A track whose gated detections are gated with no other track is its own cluster; its marginals
are the PDA closed form beta_i = g_i / (miss + sum g), beta0 = miss / (miss + sum g), computed for
all such tracks at once. The tracks left go to the compiled per-run enumeration; a cluster with
more than ``max_events`` joint events (the bound prod_t (1 + gated detections of t)) is
approximated by Murty's k best joint events (``murty``; Murty 1968, Miller, Stone & Cox 1997),
its marginals normalised over those ``k_best`` events.
"""

from __future__ import annotations

import heapq

import numpy as np
from scipy.optimize import linear_sum_assignment

from filters.kalman import LOG_2PI, inverse_and_logdet


def gate(zhat: np.ndarray, S: np.ndarray, z: np.ndarray, valid: np.ndarray, alive: np.ndarray, threshold: float
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """d2 (R, M, D) (inf where a slot is empty), gated (R, M, D) and each track's log|S| (R, M)."""
    S_inv, logdet = inverse_and_logdet(S)
    nu = np.nan_to_num(z[:, None, :, :] - zhat[:, :, None, :])
    d2 = np.einsum("rtdm,rtmk,rtdk->rtd", nu, S_inv, nu)
    pair = alive[:, :, None] & valid[:, None, :]
    d2 = np.where(pair, d2, np.inf)
    return d2, pair & (d2 < threshold), logdet


def gnn_assign(cost: np.ndarray, gated: np.ndarray) -> np.ndarray:
    """(R, M) the detection assigned to each track slot, -1 for none (module docstring)."""
    R, M, D = gated.shape
    per_track, per_detection = gated.sum(axis=2), gated.sum(axis=1)
    # a run where no track gates two detections and no detection is gated by two tracks has nothing
    # to decide: every gated pair is assigned, for all such runs at once
    plain = (per_track <= 1).all(axis=1) & (per_detection <= 1).all(axis=1)
    assigned = np.where(plain[:, None] & (per_track == 1), np.argmax(gated, axis=2), -1).astype(np.int64)
    for r in np.flatnonzero(~plain):                       # the ragged step: one assignment per run
        rows = np.flatnonzero(per_track[r])
        cols = np.flatnonzero(per_detection[r])
        sub_gated = gated[r][np.ix_(rows, cols)]
        c = cost[r][np.ix_(rows, cols)]
        shift = np.abs(c[sub_gated]).sum() + 1.0
        matrix = np.where(sub_gated, c - shift, 0.0)
        t, i = linear_sum_assignment(matrix)
        good = sub_gated[t, i]
        assigned[r, rows[t[good]]] = cols[i[good]]
    return assigned


def likelihood_ratios(d2: np.ndarray, logdet: np.ndarray, gated: np.ndarray, detection_probability: float,
                      clutter_density: float) -> np.ndarray:
    """g (R, M, D) = P_D N(z_i; H x_t, S_t) / kappa on gated pairs, 0 elsewhere."""
    m = 2
    log_g = np.log(detection_probability) - 0.5 * (d2 + logdet[..., None] + m * LOG_2PI) - np.log(clutter_density)
    return np.where(gated, np.exp(np.where(gated, log_g, 0.0)), 0.0)


def jpda_weights(g: np.ndarray, miss: float, max_events: float, k_best: int
                 ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """beta (R, M, D), beta0 (R, M) and per run counts (``approximated_clusters``, ``events``)."""
    R, M, D = g.shape
    gated = g > 0
    shared_detection = gated.sum(axis=1) > 1                          # (R, D) gated by 2+ tracks
    coupled = (gated & shared_detection[:, None, :]).any(axis=2)      # (R, M) track in a multi-track cluster
    total = miss + g.sum(axis=2)
    beta = np.where(coupled[..., None], 0.0, g / total[..., None])
    beta0 = np.where(coupled, 0.0, miss / total)
    approximated = np.zeros(R, dtype=np.int64)
    events = np.zeros(R)
    from filters.multitarget import kernel          # numba, only where a cluster needs it

    for r in np.flatnonzero(coupled.any(axis=1)):                    # the ragged step
        tracks = np.flatnonzero(coupled[r])
        cols = np.flatnonzero(gated[r][tracks].any(axis=0))
        sub = np.ascontiguousarray(g[r][np.ix_(tracks, cols)])
        b, b0, exact, counted = kernel.jpda_marginals(sub, np.full(len(tracks), miss), float(max_events))
        events[r] = counted.sum()
        if not exact.all():
            label = _labels(sub > 0)
            for cluster in np.unique(label[~exact]):
                members = np.flatnonzero(label == cluster)
                mb, mb0 = murty_marginals(sub[members], np.full(len(members), miss), k_best)
                b[members], b0[members] = mb, mb0
                approximated[r] += 1
        beta[r][np.ix_(tracks, cols)] = b
        beta0[r, tracks] = b0
    return beta, beta0, {"approximated_clusters": approximated, "events": events}


def _labels(gated: np.ndarray) -> np.ndarray:
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    T, D = gated.shape
    graph = np.zeros((T + D, T + D), dtype=bool)
    graph[:T, T:] = gated
    _, label = connected_components(csr_matrix(graph), directed=False)
    return label[:T]


def murty(cost: np.ndarray, k: int) -> list[tuple[float, np.ndarray]]:
    """The k cheapest complete assignments of the rows of ``cost`` (T, C) (inf: forbidden), best first,
    by Murty's partitioning (Murty 1968): each solution's space is split into subproblems that fix
    its first a pairs and forbid its (a+1)-th. Returns (total cost, column per row) pairs."""
    def solve(matrix):
        try:
            rows, cols = linear_sum_assignment(matrix)
        except ValueError:                          # infeasible
            return None
        total = matrix[rows, cols].sum()
        return (total, cols) if np.isfinite(total) else None

    first = solve(cost)
    if first is None:
        return []
    found: list[tuple[float, np.ndarray]] = []
    queue = [(first[0], 0, first[1], cost)]
    counter = 1
    while queue and len(found) < k:
        total, _, cols, matrix = heapq.heappop(queue)
        found.append((total, cols))
        constrained = matrix.copy()
        for row in range(len(cols)):
            sub = constrained.copy()
            sub[row, cols[row]] = np.inf              # forbid this pair ...
            answer = solve(sub)
            if answer is not None:
                heapq.heappush(queue, (answer[0], counter, answer[1], sub))
                counter += 1
            keep = constrained[row, cols[row]]        # ... having fixed the ones before it
            constrained[row, :] = np.inf
            constrained[:, cols[row]] = np.inf
            constrained[row, cols[row]] = keep
    return found


def murty_marginals(g: np.ndarray, miss: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Approximate JPDA marginals of one cluster from its k best joint events: the assignment of
    tracks (T) to detections (D) or to their own "missed" column, cost -ln g or -ln miss."""
    T, D = g.shape
    with np.errstate(divide="ignore"):
        cost = np.full((T, D + T), np.inf)
        cost[:, :D] = np.where(g > 0, -np.log(np.where(g > 0, g, 1.0)), np.inf)
        cost[np.arange(T), D + np.arange(T)] = -np.log(miss)
    best = murty(cost, k)
    totals = np.array([t for t, _ in best])
    weights = np.exp(-(totals - totals.min()))
    beta = np.zeros((T, D))
    beta0 = np.zeros(T)
    for w, (_, cols) in zip(weights, best):
        hit = cols < D
        beta[np.arange(T)[hit], cols[hit]] += w
        beta0[~hit] += w
    s = weights.sum()
    return beta / s, beta0 / s
