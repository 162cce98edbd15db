"""Compiled (numba) parts of the multi-target trackers whose work is ragged per run:

- ``jpda_marginals``: JPDA's exact association marginals of one run's tracks, cluster by cluster
  (Fortmann, Bar-Shalom & Scheffe 1983; Bar-Shalom, Willett & Tian 2011, 6.2). Tracks t and
  detections i with gated likelihood ratios g[t, i] > 0 split into clusters (connected components
  of the gating graph). A joint event theta of a cluster gives each track one gated detection or
  none, no detection to two tracks; its weight is prod_{t assigned i} g[t, i] x prod_{t missed}
  miss[t], with g = P_D N(z_i; H x_t, S_t) / kappa and miss = 1 - P_D P_G (the clutter density
  kappa cancelling with a Poisson clutter model). beta[t, i] = sum of the weights of the events
  with t -> i over the sum of all, beta0[t] the same for "t missed". Every event of the cluster is
  enumerated by depth-first search; a cluster whose event count bound prod_t (1 + its gated
  detections) exceeds ``max_events`` is left to the caller (``exact`` False for its tracks), which
  approximates it from Murty's k best events (filters.multitarget.association).
- ``merge_components``: GM-PHD pruning and merging of every run's Gaussian mixture (Vo & Ma 2006,
  Table II): drop w < T, then repeatedly take the heaviest component j left, merge every
  component i left with (m_i - m_j)' P_i^-1 (m_i - m_j) <= U into
  w = sum w_i, m = sum w_i m_i / w, P = sum w_i (P_i + (m - m_i)(m - m_i)') / w, and keep at most
  J_max of the merged components (the heaviest). The merged component keeps the label of its
  heaviest member (the caller's track identity of a PHD's peaks).

This module imports nothing from the project (numba's cache validates a compiled function by its own
file only; see filters/tracker/kernel.py). Compiled with ``cache=True``, without fastmath.
"""

from __future__ import annotations

import numpy as np
from numba import njit

_JIT = dict(nogil=True, cache=True, error_model="numpy", boundscheck=False)


@njit(**_JIT)
def _clusters(gated):
    """Connected components of the bipartite gating graph: (label per track, number of clusters);
    a track with no gated detection is its own cluster."""
    T, D = gated.shape
    label = np.full(T, -1, np.int64)
    stack = np.empty(T, np.int64)
    count = 0
    for seed in range(T):
        if label[seed] >= 0:
            continue
        label[seed] = count
        top = 0
        stack[top] = seed
        top += 1
        while top > 0:
            top -= 1
            t = stack[top]
            for i in range(D):
                if gated[t, i]:
                    for u in range(T):
                        if gated[u, i] and label[u] < 0:
                            label[u] = count
                            stack[top] = u
                            top += 1
        count += 1
    return label, count


@njit(**_JIT)
def jpda_marginals(g, miss, max_events):
    """Exact JPDA marginals of one run (module docstring). g (T, D) >= 0 (0: not gated), miss (T,).
    Returns beta (T, D), beta0 (T,), exact (T,) bool and the events enumerated per track's cluster
    (T,) float (0 where not exact)."""
    T, D = g.shape
    gated = g > 0.0
    beta = np.zeros((T, D))
    beta0 = np.zeros(T)
    exact = np.zeros(T, np.bool_)
    events = np.zeros(T)
    label, count = _clusters(gated)
    for c in range(count):
        members = np.flatnonzero(label == c)
        n = members.size
        bound = 1.0
        for a in range(n):
            bound *= 1.0 + gated[members[a]].sum()
        if bound > max_events:
            continue
        # options per member: detections gated with it, then -1 for "missed"
        width = 1
        for a in range(n):
            width = max(width, gated[members[a]].sum() + 1)
        option = np.full((n, width), -1, np.int64)
        n_option = np.zeros(n, np.int64)
        for a in range(n):
            k = 0
            for i in range(D):
                if gated[members[a], i]:
                    option[a, k] = i
                    k += 1
            option[a, k] = -1
            n_option[a] = k + 1
        used = np.zeros(D, np.bool_)
        choice = np.full(n, -1, np.int64)
        partial = np.ones(n + 1)
        acc = np.zeros((n, width))
        total = 0.0
        enumerated = 0.0
        level = 0
        while level >= 0:
            choice[level] += 1
            if choice[level] >= n_option[level]:
                choice[level] = -1
                level -= 1
                if level >= 0:
                    i_prev = option[level, choice[level]]
                    if i_prev >= 0:
                        used[i_prev] = False
                continue
            i = option[level, choice[level]]
            if i >= 0 and used[i]:
                continue
            t = members[level]
            partial[level + 1] = partial[level] * (g[t, i] if i >= 0 else miss[t])
            if level == n - 1:
                w = partial[n]
                total += w
                enumerated += 1.0
                for a in range(n):
                    acc[a, choice[a]] += w
                continue
            if i >= 0:
                used[i] = True
            level += 1
        for a in range(n):
            t = members[a]
            exact[t] = True
            events[t] = enumerated
            if total > 0.0:
                for k in range(n_option[a]):
                    i = option[a, k]
                    if i >= 0:
                        beta[t, i] = acc[a, k] / total
                    else:
                        beta0[t] = acc[a, k] / total
            else:
                beta0[t] = 1.0
    return beta, beta0, exact, events


@njit(**_JIT)
def merge_components(w, m, P, label, count, prune_below, merge_within, max_components,
                     out_w, out_m, out_P, out_label):
    """Prune, merge and cap every run's mixture (module docstring). w (R, J), m (R, J, n),
    P (R, J, n, n), label (R, J) int64, count (R,) filled slots; writes out_* (R, J_max, ...) (zero
    weight, label -1 in unused slots) and returns the number kept per run (R,)."""
    R, J, n = m.shape
    kept_count = np.zeros(R, np.int64)
    left = np.zeros(J, np.bool_)
    merged_w = np.empty(J)
    merged_m = np.empty((J, n))
    merged_P = np.empty((J, n, n))
    merged_label = np.empty(J, np.int64)
    P_inv = np.empty((J, n, n))
    for r in range(R):
        for j in range(count[r]):
            left[j] = w[r, j] >= prune_below
            if left[j]:
                P_inv[j] = np.linalg.inv(P[r, j])
        for j in range(count[r], J):
            left[j] = False
        kept = 0
        while True:
            best = -1
            top = -1.0
            for j in range(count[r]):
                if left[j] and w[r, j] > top:
                    top = w[r, j]
                    best = j
            if best < 0:
                break
            total = 0.0
            mean = np.zeros(n)
            for i in range(count[r]):
                if not left[i]:
                    continue
                d = m[r, i] - m[r, best]
                q = 0.0
                for a in range(n):
                    for b in range(n):
                        q += d[a] * P_inv[i, a, b] * d[b]
                if q <= merge_within:
                    total += w[r, i]
                    mean += w[r, i] * m[r, i]
            mean /= total
            cov = np.zeros((n, n))
            for i in range(count[r]):
                if not left[i]:
                    continue
                d = m[r, i] - m[r, best]
                q = 0.0
                for a in range(n):
                    for b in range(n):
                        q += d[a] * P_inv[i, a, b] * d[b]
                if q <= merge_within:
                    e = mean - m[r, i]
                    for a in range(n):
                        for b in range(n):
                            cov[a, b] += w[r, i] * (P[r, i, a, b] + e[a] * e[b])
                    left[i] = False
            merged_w[kept] = total
            merged_m[kept] = mean
            merged_P[kept] = cov / total
            merged_label[kept] = label[r, best]
            kept += 1
        order = np.argsort(-merged_w[:kept], kind="mergesort")
        keep = min(kept, max_components)
        for a in range(keep):
            j = order[a]
            out_w[r, a] = merged_w[j]
            out_m[r, a] = merged_m[j]
            out_P[r, a] = merged_P[j]
            out_label[r, a] = merged_label[j]
        for a in range(keep, out_w.shape[1]):
            out_w[r, a] = 0.0
            out_label[r, a] = -1
        kept_count[r] = keep
    return kept_count


_warm = False


def warm_up() -> None:
    """Load (or compile, the first time on a machine) both functions before a tracker's clock starts."""
    global _warm
    if _warm:
        return
    jpda_marginals(np.array([[1.0, 0.5], [0.2, 0.0]]), np.array([0.1, 0.1]), 100.0)
    R, J, n = 1, 2, 4
    P = np.broadcast_to(np.eye(n), (R, J, n, n)).copy()
    merge_components(np.ones((R, J)), np.zeros((R, J, n)), P, np.zeros((R, J), np.int64), np.full(R, J, np.int64),
                     1e-5, 4.0, 100, np.zeros((R, 3)), np.zeros((R, 3, n)), np.zeros((R, 3, n, n)),
                     np.zeros((R, 3), np.int64))
    _warm = True
