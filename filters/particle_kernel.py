"""The compiled scan of study 004's particle filters (``filters.particle``): one numba function that
does a whole scan of the AMMPF or the SIR-MM for a chunk of runs, particle by particle, without
the (runs x particles x modes x bearings) temporaries of the numpy loop.

Per run and scan, fused: drawing the run's random numbers, the first stage (three modes'
predicted positions, the four buoys' bearings, the clutter-mixture likelihood; eq 16), the joint
systematic resampling of (parent, mode), the propagation (eq 15), the second stage's bearings,
likelihood and weights (eq 17), the NIS of the prediction, the output moments, the resampling
and the Liu-West regularisation. Particles are component-major (20, N) inside, so every particle
loop is straight-line code over contiguous rows and vectorises (AVX2/AVX-512).

What is kept from the numpy loop (``filters.particle.filter_jump_markov`` with ``SonobuoyModel``,
still there as the reference: ``engine="numpy"``):

- the random numbers: each run's own Generator (PCG64), drawn in the same order with the same
  algorithms (``_next64``, ``_normals``: numpy's PCG64 and float32 ziggurat), so the same
  numbers bit for bit and a run's numbers do not depend on the batch; checked against numpy
  once per process, with numpy's own calls as the fallback;
- the float32/float64 split: positions, moments, weights, resampling and the Cholesky factor in
  float64; bearings, their residuals and the per-component likelihood in float32 (bearings of
  ~10 km differences keep ~1e-7 rad, far below the 1.5-15 deg noise), summed over components in
  float64 in the same order; the Liu-West jitter in float32 (it only perturbs), added to the
  float64 particles;
- each run is computed on its own, in a fixed order, so results are bit-identical whatever the
  chunk of runs, the threads or the launcher.

What differs, at rounding level: float32 atan2, exp and log are polynomial (Cephes' atanf,
expf, logf: < 2 ulp; float64 exp of the weights Cephes' exp, < 1 ulp) instead of numpy's SIMD
library calls; the turns' sin and cos by their series (float64 rounding for |wT| <= 0.25, libm
beyond); |v| as sqrt(vx^2 + vy^2), not hypot; sums over particles (moments, covariances in 4 x 4
tiles) in vectorised partial sums instead of numpy's pairwise or BLAS order; the NIS moments in
float64 instead of float32; the second resampling uses the normalised weights directly instead
of exp(log(w) - max log w); systematic resampling searches each run's own cumulative weights (the
numpy loop offsets them by the run's index in the batch, which rounds them). One scan agrees
with the numpy loop's to ~4e-7 relative (tests/test_particle_kernel.py). A resampling decision
flips where a point falls within rounding of a boundary, so whole runs drift apart from the numpy
loop's over hundreds of scans while staying the same filter (the reproduction targets hold:
tests/test_reproduction_004.py, benchmarks/particle_limits.md).

Compiled with ``cache=True``: numba writes the machine code beside this file (``__pycache__``,
else a user cache folder when that is read-only, or ``NUMBA_CACHE_DIR``), one file per function
(named by its line), valid while the SHA-256 of this file's content is the one it was built
from, keyed by the argument types, the processor (target triple, CPU name and features), the
function's bytecode and numba's version. Every jitted function of the kernel lives in this one
file (numba does not track edits of other files), so editing any of it recompiles. The
Generators' draws are checked at run time instead (``filters.particle._inline_draws_match``): a
different numpy changes no compiled code. The helpers are inlined by LLVM (``forceinline``): numba's own
inliner re-types each inlined body and made the first compilation ~128 s instead of ~23 s.
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic
from numba.np.random._constants import fi_float as _FI, ki_float as _KI, wi_float as _WI
from numba.np.random._constants import ziggurat_nor_inv_r_f as _NOR_INV_R, ziggurat_nor_r_f as _NOR_R

F32 = np.float32
_JIT = dict(nogil=True, cache=True, error_model="numpy", boundscheck=False)


# --------------------------------------------------------------------------------------------
# float32 bit casts and polynomial transcendentals (branch-free, so particle loops vectorise)
# --------------------------------------------------------------------------------------------

@intrinsic
def _bits(typingctx, x):
    """float32 -> its int32 bit pattern."""
    if x != types.float32:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(32))
    return types.int32(types.float32), codegen


@intrinsic
def _from_bits(typingctx, i):
    """Integer bit pattern (its low 32 bits) -> float32."""
    if not isinstance(i, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        value = args[0]
        if i.bitwidth > 32:
            value = builder.trunc(value, ir.IntType(32))
        return builder.bitcast(value, ir.FloatType())
    return types.float32(i), codegen


_ROUNDER = F32(12582912.0)                      # 1.5 * 2^23: x + it - it rounds x to an integer (|x| < 2^22)
_ROUNDER_BITS = np.int32(0x4B400000)
_TWO_PI = F32(2.0 * np.pi)
_INV_TWO_PI = F32(1.0 / (2.0 * np.pi))
_PI = F32(np.pi)
_HALF_PI = F32(np.pi / 2)
_QUARTER_PI = F32(np.pi / 4)
_TAN_PI_8 = F32(0.4142135623730950)
_LOG2E = F32(1.44269504088896341)
_LN2_HI = F32(0.693359375)
_LN2_LO = F32(-2.12194440e-4)
_SQRT_HALF = F32(0.707106781186547524)
_ZERO = F32(0.0)
_ONE = F32(1.0)
_HALF = F32(0.5)
_EXP_LOW = F32(-87.0)
_EXP_HIGH = F32(88.0)


@njit(forceinline=True, **_JIT)
def rint32(x):
    """Round to the nearest integer, ties to even (as np.rint), for |x| < 2^22."""
    return (x + _ROUNDER) - _ROUNDER


@njit(forceinline=True, **_JIT)
def wrap32(e):
    """float32 angle into [-pi, pi], as ``filters.particle.wrap``."""
    return e - _TWO_PI * rint32(e * _INV_TWO_PI)


@njit(forceinline=True, **_JIT)
def atan2_32(y, x):
    """float32 atan2(y, x): Cephes atanf on [0, tan(pi/8)] after the octant reduction (< 2 ulp)."""
    ax, ay = abs(x), abs(y)
    big, small = max(ax, ay), min(ax, ay)
    t = small / max(big, F32(1e-30))
    far = t > _TAN_PI_8
    t = (t - _ONE) / (t + _ONE) if far else t
    z = t * t
    p = (((F32(8.05374449538e-2) * z - F32(1.38776856032e-1)) * z + F32(1.99777106478e-1)) * z
         - F32(3.33329491539e-1)) * z * t + t
    r = (_QUARTER_PI + p) if far else p
    r = (_HALF_PI - r) if ay > ax else r
    r = (_PI - r) if x < _ZERO else r
    return -r if y < _ZERO else r


@njit(forceinline=True, **_JIT)
def exp32(x):
    """float32 exp (Cephes expf, < 2 ulp); 0 below -87 (the smallest normal float32)."""
    c = min(max(x, _EXP_LOW), _EXP_HIGH)
    shifted = c * _LOG2E + _ROUNDER
    n = shifted - _ROUNDER
    r = (c - n * _LN2_HI) - n * _LN2_LO
    z = r * r
    p = (((((F32(1.9875691500e-4) * r + F32(1.3981999507e-3)) * r + F32(8.3334519073e-3)) * r
           + F32(4.1665795894e-2)) * r + F32(1.6666665459e-1)) * r + F32(5.0000001201e-1)) * z + r + _ONE
    scale = _from_bits((_bits(shifted) - _ROUNDER_BITS + np.int32(127)) << np.int32(23))
    return p * scale if x >= _EXP_LOW else _ZERO


@njit(forceinline=True, **_JIT)
def log32(x):
    """float32 natural log of a positive normal number (Cephes logf, < 2 ulp)."""
    bits = _bits(x)
    e = ((bits >> np.int32(23)) & np.int32(0xFF)) - np.int32(126)
    m = _from_bits((bits & np.int32(0x007FFFFF)) | np.int32(0x3F000000))         # [0.5, 1)
    low = m < _SQRT_HALF
    e = e - np.int32(1) if low else e
    m = (m + m - _ONE) if low else (m - _ONE)
    fe = F32(e)
    z = m * m
    y = ((((((((F32(7.0376836292e-2) * m - F32(1.1514610310e-1)) * m + F32(1.1676998740e-1)) * m
               - F32(1.2420140846e-1)) * m + F32(1.4249322787e-1)) * m - F32(1.6668057665e-1)) * m
            + F32(2.0000714765e-1)) * m - F32(2.4999993993e-1)) * m + F32(3.3333331174e-1)) * m * z
    y = y + _LN2_LO * fe
    y = y - _HALF * z
    return (m + y) + _LN2_HI * fe


# float64 exp for the weights (arguments <= 0): Cephes exp's Pade form, < 1 ulp
_LOG2E64 = 1.4426950408889634
_C1 = 6.93145751953125e-1
_C2 = 1.42860682030941723212e-6


@njit(forceinline=True, **_JIT)
def exp64(x):
    """float64 exp of x <= 0 (Cephes exp); 0 below -708."""
    c = max(x, -708.0)
    n = math.floor(c * _LOG2E64 + 0.5)
    r = (c - n * _C1) - n * _C2
    xx = r * r
    px = r * ((1.26177193074810590878e-4 * xx + 3.02994407707441961300e-2) * xx + 9.99999999999999999910e-1)
    q = (((3.00198505138664455042e-6 * xx + 2.52448340349684104192e-3) * xx + 2.27265548208155028766e-1) * xx
         + 2.00000000000000000009e0)
    y = 1.0 + 2.0 * (px / (q - px))
    return y * _pow2(n) if x >= -708.0 else 0.0


@njit(forceinline=True, **_JIT)
def _pow2(n):
    """2.0 ** n for an integral float64 n in [-1022, 1023]."""
    return _from_bits64((np.int64(n) + np.int64(1023)) << np.int64(52))


@intrinsic
def _from_bits64(typingctx, i):
    if i != types.int64:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())
    return types.float64(types.int64), codegen


# --------------------------------------------------------------------------------------------
# numpy's PCG64 and float32 normals, inline: the same numbers as Generator.random() and
# Generator.standard_normal(dtype=float32) from the same state, at about a third of the cost
# (numpy reaches the bit generator through a function pointer per number). Checked against numpy
# on first use (``filters.particle._inline_draws_match``); the numpy calls are the fallback.
# --------------------------------------------------------------------------------------------

_MULT_HI = np.uint64(0x2360ED051FC65DA4)         # PCG64's 128-bit multiplier (XSL-RR 128/64)
_MULT_LO = np.uint64(0x4385DF649FCCF645)
_U0, _U1, _U8, _U11, _U32, _U58, _U63, _U64 = (np.uint64(v) for v in (0, 1, 8, 11, 32, 58, 63, 64))
_LOW32 = np.uint64(0xFFFFFFFF)
_TO_DOUBLE = 1.0 / 9007199254740992.0
_TO_FLOAT = np.float32(1.0 / 16777216.0)


@intrinsic
def _mulhi64(typingctx, a, b):
    """The high 64 bits of the 128-bit product of two uint64."""
    if a != types.uint64 or b != types.uint64:
        return None

    def codegen(context, builder, signature, args):
        wide = ir.IntType(128)
        product = builder.mul(builder.zext(args[0], wide), builder.zext(args[1], wide))
        return builder.trunc(builder.lshr(product, ir.Constant(wide, 64)), ir.IntType(64))
    return types.uint64(types.uint64, types.uint64), codegen


@njit(inline="always", **_JIT)
def _next64(hi, lo, inc_hi, inc_lo):
    """PCG64: state = state * multiplier + increment (mod 2^128), then the XSL-RR output of the
    new state. Returns (output, hi, lo)."""
    new_lo = lo * _MULT_LO
    new_hi = _mulhi64(lo, _MULT_LO) + lo * _MULT_HI + hi * _MULT_LO
    low = new_lo + inc_lo
    new_hi = new_hi + inc_hi + (_U1 if low < new_lo else _U0)
    value = new_hi ^ low
    rot = new_hi >> _U58
    return (value >> rot) | (value << ((_U64 - rot) & _U63)), new_hi, low


@njit(inline="always", **_JIT)
def _next32(hi, lo, inc_hi, inc_lo, has, buffered):
    """numpy's pcg64_next32: the buffered upper half of the last 64-bit output, else a new one
    (its lower half returned, its upper half kept). Returns (value, hi, lo, has, buffered)."""
    if has:
        return buffered, hi, lo, _U0, buffered
    value, hi, lo = _next64(hi, lo, inc_hi, inc_lo)
    return value & _LOW32, hi, lo, _U1, value >> _U32


@njit(**_JIT)
def _uniforms(state, out):
    """Generator.random(out=...): (next64 >> 11) / 2^53 each; state (6,) uint64 updated."""
    hi, lo, inc_hi, inc_lo = state[0], state[1], state[2], state[3]
    for i in range(out.shape[0]):
        value, hi, lo = _next64(hi, lo, inc_hi, inc_lo)
        out[i] = (value >> _U11) * _TO_DOUBLE
    state[0], state[1] = hi, lo


@njit(**_JIT)
def _normals(state, out):
    """Generator.standard_normal(dtype=float32, out=...) on a flat float32 array: numpy's float32
    ziggurat (the tables and the wedge and tail tests as numba's port of it); state updated."""
    hi, lo, inc_hi, inc_lo, has, buffered = state[0], state[1], state[2], state[3], state[4], state[5]
    for i in range(out.shape[0]):
        while True:
            r, hi, lo, has, buffered = _next32(hi, lo, inc_hi, inc_lo, has, buffered)
            idx = np.int64(r & np.uint64(0xFF))
            rabs = (r >> np.uint64(9)) & np.uint64(0x007FFFFF)
            x = F32(F32(rabs) * _WI[idx])
            if (r >> _U8) & _U1:
                x = -x
            if rabs < _KI[idx]:
                break
            if idx == 0:
                while True:
                    u, hi, lo, has, buffered = _next32(hi, lo, inc_hi, inc_lo, has, buffered)
                    xx = F32(-_NOR_INV_R * np.log1p(F32(-F32(F32(u >> _U8) * _TO_FLOAT))))
                    u, hi, lo, has, buffered = _next32(hi, lo, inc_hi, inc_lo, has, buffered)
                    yy = F32(-np.log1p(F32(-F32(F32(u >> _U8) * _TO_FLOAT))))
                    if F32(yy + yy) > F32(xx * xx):
                        x = -F32(_NOR_R + xx) if (rabs >> _U8) & _U1 else F32(_NOR_R + xx)
                        break
                break
            u, hi, lo, has, buffered = _next32(hi, lo, inc_hi, inc_lo, has, buffered)
            if (_FI[idx - 1] - _FI[idx]) * F32(F32(u >> _U8) * _TO_FLOAT) + _FI[idx] < F32(np.exp(-F32(0.5) * x * x)):
                break
        out[i] = x
    state[0], state[1], state[4], state[5] = hi, lo, has, buffered


@njit(**_JIT)
def _uniform(state):
    one = np.empty(1)
    _uniforms(state, one)
    return one[0]


# --------------------------------------------------------------------------------------------
# The likelihood of one bearing
# --------------------------------------------------------------------------------------------

@njit(forceinline=True, **_JIT)
def _component(predicted, k, mixture):
    """float32 log p(z | predicted) of one component (``BearingLikelihood.log``), k its constants
    (``_constants``): the clutter mixture summed around the clutter term (one exp and a log), or
    the nominal Gaussian; 0 where the component was missed."""
    nominal_factor, clutter_factor, difference, clutter_scale, nominal_scale, nominal_log_scale, z, received = k
    e = wrap32(z - predicted)
    e2 = e * e
    if mixture:
        value = e2 * clutter_factor + log32(clutter_scale + nominal_scale * exp32(e2 * difference))
    else:
        value = e2 * nominal_factor + nominal_log_scale
    return value if received else _ZERO


@njit(forceinline=True, **_JIT)
def _constants(lik, z32, received, c):
    """Component c's likelihood constants, its bearing and whether it was received, as scalars (a
    tuple): the particle loops then read no array but the particles'."""
    return (lik[0, c], lik[1, c], lik[2, c], lik[3, c], lik[4, c], lik[5, c], z32[c], received[c])


# the likelihood constants' rows in ``lik`` (8 components each, float32)
NOMINAL_FACTOR, CLUTTER_FACTOR, DIFFERENCE, CLUTTER_SCALE, NOMINAL_SCALE, NOMINAL_LOG_SCALE = range(6)


# --------------------------------------------------------------------------------------------
# One scan for a chunk of runs
# --------------------------------------------------------------------------------------------

@njit(**_JIT)
def scan(X, X_out, modes, z, dt, log_tpm, tpm, lik, mixture, observer, a_m, sigma, gain, lw_h, auxiliary,
         first_offsets, uniforms, noise, second_offsets, normals, rng, draw, variance, k,
         states, covariances, mode_probability, ess, underflow, nis, nis_dof):
    """Scan ``k`` for every run r of the chunk. X (R, 20, N) float64: the resampled, regularised
    particles of scan k - 1, component-major (each state component's N values contiguous, so the
    particle loops vectorise); modes (R, N) int64 theirs. Leaves scan k's cloud in X_out (X is
    scratch) and its modes in ``modes``.

    z (R, 8) float64 scan k's bearings (NaN missed); log_tpm, tpm (3, 3); lik (6, 8) float32 the
    likelihood constants (rows above); mixture: p_c > 0; observer (2,); a_m; sigma (5,) process
    noise std (target, buoys); gain (4,) Gamma's nonzero entries (g, g, T, T); lw_h.
    Random numbers (each run's own, drawn in the numpy loop's order): first_offsets (R,) the
    first stage's resampling offsets (AMMPF), uniforms (R, N) the SIR-MM's mode draws, noise
    (R, N, 10) float32 process noise, second_offsets (R,), normals (R, N, 20) float32 Liu-West's;
    drawn here when ``draw`` from each run's PCG64 state rng (R, 6) uint64 (state high, low,
    increment high, low, has_uint32, uinteger; updated), else given. variance (8,) the components' noise variances (NIS). Outputs at [r, k]: states, covariances,
    mode_probability, ess, underflow (|=), nis, nis_dof.
    """
    R = X.shape[0]
    for r in range(R):
        if draw:                  # in filter_jump_markov's order: offset or uniforms, noise, offset, normals
            state = rng[r]
            if auxiliary:
                first_offsets[r] = _uniform(state)
            else:
                _uniforms(state, uniforms[r])
            _normals(state, noise[r].reshape(-1))
            second_offsets[r] = _uniform(state)
            if lw_h > 0:
                _normals(state, normals[r].reshape(-1))
        out = _scan_run(X[r], X_out[r], modes[r], z[r], dt, log_tpm, tpm, lik, mixture, observer, a_m, sigma,
                        gain, lw_h, auxiliary, first_offsets[r], uniforms[r], noise[r], second_offsets[r],
                        normals[r], variance, states[r, k], covariances[r, k], mode_probability[r, k])
        ess[r, k], lost, nis[r, k], nis_dof[r, k] = out
        underflow[r, k] |= lost


@njit(**_JIT)
def _scan_run(X, X_out, modes, z, dt, log_tpm, tpm, lik, mixture, observer, a_m, sigma, gain, lw_h, auxiliary,
              first_offset, uniforms, noise, second_offset, normals, variance, state, covariance, mode_probability):
    """One run's scan (``filter_jump_markov``'s loop body for ``SonobuoyModel``): returns (ess,
    underflowed, nis, nis_dof) and writes the moments and mode probabilities."""
    N = X.shape[1]
    z32 = np.zeros(8, np.float32)
    received = np.empty(8, np.bool_)
    for c in range(8):
        received[c] = not np.isnan(z[c])
        z32[c] = F32(z[c]) if received[c] else _ZERO
    ox, oy = F32(observer[0]), F32(observer[1])
    # every |Omega T| <= 2 a_m T (Omega = a_m / max(|v|, 0.5)): the turn's sines by their series
    series = 2.0 * a_m * dt <= 0.25
    lost = False

    parent = np.empty(N, np.int64)
    new_mode = np.empty(N, np.int64)
    first_at_pick = np.zeros(N)
    # ---------------- first stage (eq 16) and the joint systematic resampling of (parent, mode)
    if auxiliary:
        ta, tb = np.empty(N), np.empty(N)
        _turn_factors(X, a_m, dt, series, ta, tb)
        first = np.empty((3, N))
        _first_stage(X, ta, tb, z32, received, dt, ox, oy, lik, mixture, first)
        log_lambda = np.empty(3 * N)
        for i in range(N):
            row = modes[i]
            for m in range(3):
                log_lambda[3 * i + m] = log_tpm[row, m] + first[m, i]
        lost |= _systematic(log_lambda, first_offset, parent)
        for i in range(N):
            pick = parent[i]
            parent[i], new_mode[i] = pick // 3, pick % 3
            first_at_pick[i] = first[pick % 3, pick // 3]
    else:
        for i in range(N):
            parent[i] = i
            row = modes[i]
            c0 = tpm[row, 0]
            c1 = c0 + tpm[row, 1]
            c2 = c1 + tpm[row, 2]
            u = uniforms[i]
            new_mode[i] = min(np.int64(u > c0) + np.int64(u > c1) + np.int64(u > c2), 2)

    # ---------------- propagation (eq 15), second-stage bearings and likelihood (eq 17)
    turn = np.empty((4, N))
    _turn_terms_of(X, parent, new_mode, a_m, dt, series, turn)
    _propagate(X, parent, turn, noise, dt, sigma, gain, X_out)
    log_weights = np.empty(N)
    _second_stage(X_out, z32, received, ox, oy, lik, mixture, log_weights)
    for i in range(N):
        log_weights[i] -= first_at_pick[i]

    # ---------------- the NIS of the prediction: the propagated cloud weighted by 1 / p(z | mu)
    nis, nis_dof = _innovation_nis(X_out, ox, oy, first_at_pick, z, variance)

    # ---------------- weights (eq 17), output moments, mode probabilities, ESS
    weights = np.empty(N)
    lost |= _normalise(log_weights, weights)
    centred = np.empty((20, N))
    _weighted_moments(X_out, weights, state, covariance, centred)
    p0 = 0.0
    p1 = 0.0
    p2 = 0.0
    total = 0.0
    for i in range(N):
        w = weights[i]
        m = new_mode[i]
        p0 += w if m == 0 else 0.0
        p1 += w if m == 1 else 0.0
        p2 += w if m == 2 else 0.0
        total += w * w
    mode_probability[0], mode_probability[1], mode_probability[2] = p0, p1, p2

    # ---------------- resampling (every scan) and Liu-West regularisation
    keep = np.empty(N, np.int64)
    _systematic_normalised(weights, second_offset, keep)
    for c in range(20):
        for i in range(N):
            X[c, i] = X_out[c, keep[i]]
    for i in range(N):
        modes[i] = new_mode[keep[i]]
    if lw_h > 0:
        _liu_west(X, lw_h, normals, X_out, centred)
    else:
        X_out[:, :] = X
    return 1.0 / total, lost, nis, nis_dof


@njit(forceinline=True, **_JIT)
def _sines(wt, series):
    """(sin wT, 1 - cos wT) of a turn; the Taylor series (float64 rounding for |wT| <= 0.25)
    when ``series``, else libm."""
    if series:
        u = wt * wt
        s = wt * (1.0 - u / 6.0 * (1.0 - u / 20.0 * (1.0 - u / 42.0 * (1.0 - u / 72.0 * (1.0 - u / 110.0
                                                                                            * (1.0 - u / 156.0))))))
        one_minus_c = 0.5 * u * (1.0 - u / 12.0 * (1.0 - u / 30.0 * (1.0 - u / 56.0 * (1.0 - u / 90.0
                                                                                         * (1.0 - u / 132.0)))))
        return s, one_minus_c
    return math.sin(wt), 1.0 - math.cos(wt)


@njit(**_JIT)
def _turn_factors(X, a_m, dt, series, ta, tb):
    """Per particle, the counter-clockwise turn's sin(wT)/w and (1 - cos wT)/w (eq 4 with eq 5's
    w = a_m / max(|v|, 0.5); the clockwise turn's are a and -b); dt and 0 below w = 1e-9."""
    N = X.shape[1]
    if series:
        for i in range(N):
            ta[i], tb[i] = _turn_ab(X[2, i], X[3, i], a_m, dt, True)
    else:
        for i in range(N):
            ta[i], tb[i] = _turn_ab(X[2, i], X[3, i], a_m, dt, False)


@njit(forceinline=True, **_JIT)
def _turn_ab(vx, vy, a_m, dt, series):
    omega = a_m / max(math.sqrt(vx * vx + vy * vy), 0.5)
    s, one_minus_c = _sines(omega * dt, series)
    small = omega < 1e-9
    return (dt if small else s / omega), (0.0 if small else one_minus_c / omega)


@njit(**_JIT)
def _first_stage(X, ta, tb, z32, received, dt, ox, oy, lik, mixture, first):
    """log p(z | mu(i, m)) (3, N) of each particle's three noise-free predicted means
    (``SonobuoyModel.first_stage``): the buoys' CV predictions, the target's three positions
    (``predicted_positions``), its bearings as ``mode_bearings`` (the CV bearing plus the turns'
    first-order change), the mixture likelihood summed over the received components in order.
    The four buoys written out, so the particle loop is straight-line code and vectorises."""
    if mixture:          # a constant in each inlined copy: the loop has no branch on it
        _first_stage_loop(X, ta, tb, z32, received, dt, ox, oy, lik, True, first)
    else:
        _first_stage_loop(X, ta, tb, z32, received, dt, ox, oy, lik, False, first)


@njit(inline="always", **_JIT)
def _first_stage_loop(X, ta, tb, z32, received, dt, ox, oy, lik, mixture, first):
    N = X.shape[1]
    k0, k1, k2, k3 = (_constants(lik, z32, received, 0), _constants(lik, z32, received, 1),
                      _constants(lik, z32, received, 2), _constants(lik, z32, received, 3))
    k4, k5, k6, k7 = (_constants(lik, z32, received, 4), _constants(lik, z32, received, 5),
                      _constants(lik, z32, received, 6), _constants(lik, z32, received, 7))
    for i in range(N):
        px, py, vx, vy = X[0, i], X[1, i], X[2, i], X[3, i]
        a, b = ta[i], tb[i]
        cvx, cvy = px + dt * vx, py + dt * vy
        ax, ay, bx, by = a * vx, a * vy, b * vy, b * vx
        shift = (F32((px + ax - bx) - cvx), F32((py + by + ay) - cvy), F32((px + ax + bx) - cvx),
                 F32((py - by + ay) - cvy))
        tx, ty = F32(cvx), F32(cvy)
        t00, t01, t02, b0 = _first_stage_buoy(X, i, 0, dt, tx, ty, shift, ox, oy, k0, k4, mixture)
        t10, t11, t12, b1 = _first_stage_buoy(X, i, 1, dt, tx, ty, shift, ox, oy, k1, k5, mixture)
        t20, t21, t22, b2 = _first_stage_buoy(X, i, 2, dt, tx, ty, shift, ox, oy, k2, k6, mixture)
        t30, t31, t32, b3 = _first_stage_buoy(X, i, 3, dt, tx, ty, shift, ox, oy, k3, k7, mixture)
        buoy = _sum4(b0, b1, b2, b3)
        first[0, i] = _sum4(t00, t10, t20, t30) + buoy
        first[1, i] = _sum4(t01, t11, t21, t31) + buoy
        first[2, i] = _sum4(t02, t12, t22, t32) + buoy


@njit(forceinline=True, **_JIT)
def _sum4(a, b, c, d):
    """float32 terms summed in float64 in order (np.sum(..., dtype=float64) over 4 components)."""
    return ((float(a) + float(b)) + float(c)) + float(d)


@njit(forceinline=True, **_JIT)
def _first_stage_buoy(X, i, j, dt, tx, ty, shift, ox, oy, k_target, k_buoy, mixture):
    """Buoy j's part of the first stage: the three modes' target bearings' likelihoods and the
    buoy's own."""
    fx, fy = F32(X[4 + 4 * j, i] + dt * X[6 + 4 * j, i]), F32(X[5 + 4 * j, i] + dt * X[7 + 4 * j, i])
    dx, dy = tx - fx, ty - fy
    base = atan2_32(dx, dy)
    rho2 = dx * dx + dy * dy
    c1 = (dy * shift[0] - dx * shift[1]) / rho2
    c2 = (dy * shift[2] - dx * shift[3]) / rho2
    return (_component(base, k_target, mixture), _component(base + c1, k_target, mixture),
            _component(base + c2, k_target, mixture), _component(atan2_32(fx - ox, fy - oy), k_buoy, mixture))


@njit(**_JIT)
def _turn_terms_of(X, parent, mode, a_m, dt, series, turn):
    """Per new particle, its parent's turn under its drawn mode (``turn_rates``, ``coordinated_turn``)
    into turn (4, N): sin wT, cos wT, sin(wT)/w, (1 - cos wT)/w; CV (0, 1, T, 0) for mode 0 and
    below |w| = 1e-9. Branch-free with the series (the loop vectorises), libm otherwise."""
    if series:
        _turn_terms_loop(X, parent, mode, a_m, dt, True, turn)
    else:
        _turn_terms_loop(X, parent, mode, a_m, dt, False, turn)


@njit(inline="always", **_JIT)
def _turn_terms_loop(X, parent, mode, a_m, dt, series, turn):
    for i in range(parent.shape[0]):
        p = parent[i]
        vx, vy = X[2, p], X[3, p]
        omega = a_m / max(math.sqrt(vx * vx + vy * vy), 0.5)
        m = mode[i]
        s, one_minus_c = _sines(omega * dt, series)
        cv = m == 0 or omega < 1e-9
        sign = 1.0 if m == 1 else -1.0          # w < 0: sin wT and (1 - cos wT)/w change sign
        turn[0, i] = 0.0 if cv else sign * s
        turn[1, i] = 1.0 if cv else 1.0 - one_minus_c
        turn[2, i] = dt if cv else s / omega
        turn[3, i] = 0.0 if cv else sign * (one_minus_c / omega)


@njit(**_JIT)
def _propagate(X, parent, turn, noise, dt, sigma, gain, out):
    """Eq 15: each parent under its drawn mode (``coordinated_turn``) plus the process noise
    through Gamma (``SonobuoyModel.propagate``); the buoys move CV. One output row group per loop,
    so the loops vectorise (gathering the parents)."""
    N = parent.shape[0]
    g0, g1, g2, g3 = gain[0], gain[1], gain[2], gain[3]
    s0 = sigma[0]
    for i in range(N):
        p = parent[i]
        px, py, vx, vy = X[0, p], X[1, p], X[2, p], X[3, p]
        s, c, a, b = turn[0, i], turn[1, i], turn[2, i], turn[3, i]
        n0, n1 = noise[i, 0] * s0, noise[i, 1] * s0
        out[0, i] = (px + a * vx - b * vy) + n0 * g0
        out[1, i] = (py + b * vx + a * vy) + n1 * g1
        out[2, i] = (c * vx - s * vy) + n0 * g2
        out[3, i] = (s * vx + c * vy) + n1 * g3
    for j in range(4):
        _propagate_buoy(X, parent, noise, dt, sigma[1 + j], g0, g1, g2, g3, 4 + 4 * j, 2 + 2 * j, out)


@njit(**_JIT)
def _propagate_buoy(X, parent, noise, dt, sj, g0, g1, g2, g3, o, n, out):
    for i in range(parent.shape[0]):
        p = parent[i]
        m0, m1 = noise[i, n] * sj, noise[i, n + 1] * sj
        out[o, i] = (X[o, p] + dt * X[o + 2, p]) + m0 * g0
        out[o + 1, i] = (X[o + 1, p] + dt * X[o + 3, p]) + m1 * g1
        out[o + 2, i] = X[o + 2, p] + m0 * g2
        out[o + 3, i] = X[o + 3, p] + m1 * g3


@njit(**_JIT)
def _second_stage(X, z32, received, ox, oy, lik, mixture, log_likelihood):
    """log p(z | x) (N,) of the propagated particles (``predicted_measurements``, ``log_likelihood``):
    the target part summed over its received components, then the buoys'. Straight-line code per
    particle, so the loop vectorises."""
    if mixture:
        _second_stage_loop(X, z32, received, ox, oy, lik, True, log_likelihood)
    else:
        _second_stage_loop(X, z32, received, ox, oy, lik, False, log_likelihood)


@njit(inline="always", **_JIT)
def _second_stage_loop(X, z32, received, ox, oy, lik, mixture, log_likelihood):
    N = X.shape[1]
    k0, k1, k2, k3 = (_constants(lik, z32, received, 0), _constants(lik, z32, received, 1),
                      _constants(lik, z32, received, 2), _constants(lik, z32, received, 3))
    k4, k5, k6, k7 = (_constants(lik, z32, received, 4), _constants(lik, z32, received, 5),
                      _constants(lik, z32, received, 6), _constants(lik, z32, received, 7))
    for i in range(N):
        tx, ty = F32(X[0, i]), F32(X[1, i])
        t0, b0 = _second_stage_buoy(X, i, 0, tx, ty, ox, oy, k0, k4, mixture)
        t1, b1 = _second_stage_buoy(X, i, 1, tx, ty, ox, oy, k1, k5, mixture)
        t2, b2 = _second_stage_buoy(X, i, 2, tx, ty, ox, oy, k2, k6, mixture)
        t3, b3 = _second_stage_buoy(X, i, 3, tx, ty, ox, oy, k3, k7, mixture)
        log_likelihood[i] = _sum4(t0, t1, t2, t3) + _sum4(b0, b1, b2, b3)


@njit(forceinline=True, **_JIT)
def _second_stage_buoy(X, i, j, tx, ty, ox, oy, k_target, k_buoy, mixture):
    fx, fy = F32(X[4 + 4 * j, i]), F32(X[5 + 4 * j, i])
    return (_component(atan2_32(tx - fx, ty - fy), k_target, mixture),
            _component(atan2_32(fx - ox, fy - oy), k_buoy, mixture))


@njit(forceinline=True, **_JIT)
def _bearing(X, i, c, ox, oy):
    """float32 bearing c of particle i: the target from buoy c (c < 4), buoy c - 4 from the observer."""
    j = c % 4
    fx, fy = F32(X[4 + 4 * j, i]), F32(X[5 + 4 * j, i])
    if c < 4:
        return atan2_32(F32(X[0, i]) - fx, F32(X[1, i]) - fy)
    return atan2_32(fx - ox, fy - oy)


@njit(**_JIT)
def _exp_weights(log_weights, weights):
    """weights = exp(log_weights - max) (unnormalised); a run whose every log weight is -inf or
    NaN restarts from uniform weights (``_restart_if_underflowed``). Returns (lost, sum)."""
    N = log_weights.shape[0]
    top = -np.inf
    for i in range(N):
        v = log_weights[i]
        top = v if v > top else top                 # NaN is never greater: it counts as -inf
    lost = not np.isfinite(top)
    if lost:
        weights[:] = 1.0
        return True, float(N)
    for i in range(N):
        v = log_weights[i]
        weights[i] = 0.0 if np.isnan(v) else exp64(v - top)
    return False, _sum(weights)


@njit(**_JIT)
def _normalise(log_weights, weights):
    """Normalised weights from log weights (``normalise_log`` after ``_restart_if_underflowed``)."""
    lost, total = _exp_weights(log_weights, weights)
    for i in range(weights.shape[0]):
        weights[i] /= total
    return lost


@njit(**_JIT)
def _systematic(log_weights, offset, out):
    """Systematic resampling of len(out) indices from unnormalised log weights (``systematic_resample``
    for one run, after ``_restart_if_underflowed``); True when every weight had underflowed."""
    weights = np.empty(log_weights.shape[0])
    lost, _ = _exp_weights(log_weights, weights)
    _systematic_normalised(weights, offset, out)
    return lost


@njit(**_JIT)
def _systematic_normalised(weights, offset, out):
    """Systematic resampling from (unnormalised) weights: point (offset + d) / D falls in the first
    index whose cumulative weight (normalised, the last set to 1) exceeds it (searchsorted, side
    right). The cumulative sum is sequential, as np.cumsum."""
    M, D = weights.shape[0], out.shape[0]
    cumulative = np.empty(M)
    running = 0.0
    for j in range(M):
        running += weights[j]
        cumulative[j] = running
    for j in range(M):
        cumulative[j] /= running
    cumulative[M - 1] = 1.0
    j = 0
    for d in range(D):
        point = (offset + d) / D
        while j < M - 1 and cumulative[j] <= point:
            j += 1
        out[d] = j


# Sums over particles: vectorised with partial sums (reassociated), so their rounding differs from
# a sequential sum's at 1e-16 relative; fixed by N and the compiled code, not by the batch.
_REDUCE = dict(_JIT, fastmath={"reassoc", "contract"})


@njit(**_REDUCE)
def _sum(a):
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i]
    return s


@njit(**_REDUCE)
def _row_dot(A, j, B, q):
    """sum_i A[j, i] B[q, i]."""
    s = 0.0
    for i in range(A.shape[1]):
        s += A[j, i] * B[q, i]
    return s


@njit(**_REDUCE)
def _weighted_row_sum(A, j, w):
    s = 0.0
    for i in range(A.shape[1]):
        s += w[i] * A[j, i]
    return s


@njit(**_JIT)
def _covariance(centred, weighted, covariance, scale):
    """covariance[j, q] = scale * sum_i weighted[j, i] centred[q, i] for rows (n, N), n a multiple
    of 4, symmetric (the q <= j half computed): 4 x 4 tiles, each one pass over the particles
    with its 16 sums in registers (a quarter of the memory traffic of one pass per entry)."""
    n = centred.shape[0]
    tile = np.empty(16)
    for jb in range(0, n, 4):
        for qb in range(0, jb + 1, 4):
            _tile(weighted, jb, centred, qb, tile)
            for a in range(4):
                for b in range(4):
                    j, q = jb + a, qb + b
                    if q <= j:
                        v = scale * tile[4 * a + b]
                        covariance[j, q] = v
                        covariance[q, j] = v


@njit(**_REDUCE)
def _tile(A, j, B, q, out):
    """out[4 a + b] = sum_i A[j + a, i] B[q + b, i], a, b < 4: sixteen sums in one loop."""
    s00 = s01 = s02 = s03 = s10 = s11 = s12 = s13 = 0.0
    s20 = s21 = s22 = s23 = s30 = s31 = s32 = s33 = 0.0
    for i in range(A.shape[1]):
        a0, a1, a2, a3 = A[j, i], A[j + 1, i], A[j + 2, i], A[j + 3, i]
        b0, b1, b2, b3 = B[q, i], B[q + 1, i], B[q + 2, i], B[q + 3, i]
        s00 += a0 * b0
        s01 += a0 * b1
        s02 += a0 * b2
        s03 += a0 * b3
        s10 += a1 * b0
        s11 += a1 * b1
        s12 += a1 * b2
        s13 += a1 * b3
        s20 += a2 * b0
        s21 += a2 * b1
        s22 += a2 * b2
        s23 += a2 * b3
        s30 += a3 * b0
        s31 += a3 * b1
        s32 += a3 * b2
        s33 += a3 * b3
    out[0], out[1], out[2], out[3] = s00, s01, s02, s03
    out[4], out[5], out[6], out[7] = s10, s11, s12, s13
    out[8], out[9], out[10], out[11] = s20, s21, s22, s23
    out[12], out[13], out[14], out[15] = s30, s31, s32, s33


@njit(**_JIT)
def _weighted_moments(X, weights, mean, covariance, centred):
    """Weighted mean (20,) and covariance (20, 20) of X (20, N) (``weighted_moments``)."""
    n, N = X.shape
    for j in range(n):
        mean[j] = _weighted_row_sum(X, j, weights)
    weighted = np.empty((n, N))
    for j in range(n):
        m = mean[j]
        for i in range(N):
            c = X[j, i] - m
            centred[j, i] = c
            weighted[j, i] = c * weights[i]
    _covariance(centred, weighted, covariance, 1.0)


@njit(**_JIT)
def _cholesky(A, L):
    """Lower Cholesky factor of a positive-definite A (n, n) into L."""
    n = A.shape[0]
    L[:, :] = 0.0
    for j in range(n):
        s = A[j, j]
        for q in range(j):
            s -= L[j, q] * L[j, q]
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            s = A[i, j]
            for q in range(j):
                s -= L[i, q] * L[j, q]
            L[i, j] = s / d


@njit(**_JIT)
def _liu_west(X, h, normals, out, centred):
    """Liu-West kernel on equally weighted particles X (20, N) (``liu_west``): a X + (1 - a) mean
    + h L eps, a = sqrt(1 - h^2), L L' the particles' covariance with a 1e-9 relative jitter on
    its diagonal; the jitter h L eps + (1 - a) mean in float32, as there."""
    n, N = X.shape
    mean = np.empty(n)
    for j in range(n):
        m = _sum(X[j]) / N
        mean[j] = m
        for i in range(N):
            centred[j, i] = X[j, i] - m
    covariance = np.empty((n, n))
    _covariance(centred, centred, covariance, 1.0 / N)
    for j in range(n):
        covariance[j, j] += 1e-9 * max(covariance[j, j], 1e-12)
    L = np.empty((n, n))
    _cholesky(covariance, L)
    a = math.sqrt(1.0 - h * h)
    eps = np.empty((n, N), np.float32)                # the normals component-major
    for i in range(N):
        for q in range(n):
            eps[q, i] = normals[i, q]
    hL = np.zeros((n, n + 3), np.float32)              # h L in float32, zero-padded to whole blocks of 4
    for j in range(n):
        for q in range(j + 1):
            hL[j, q] = F32(h * L[j, q])
    acc = np.empty(N, np.float32)
    for j in range(n):
        acc[:] = _ZERO
        for q in range(0, j + 1, 4):                   # four normals per pass over the particles
            _jitter_block(eps, q, hL[j, q], hL[j, q + 1], hL[j, q + 2], hL[j, q + 3], acc)
        shift = F32((1.0 - a) * mean[j])
        for i in range(N):
            out[j, i] = a * X[j, i] + (acc[i] + shift)


@njit(**_JIT)
def _jitter_block(eps, q, f0, f1, f2, f3, acc):
    """acc += eps[q] f0 + eps[q + 1] f1 + eps[q + 2] f2 + eps[q + 3] f3 (float32; rows past the
    last have zero factors)."""
    n = eps.shape[0]
    q1, q2, q3 = min(q + 1, n - 1), min(q + 2, n - 1), min(q + 3, n - 1)
    for i in range(acc.shape[0]):
        acc[i] += ((eps[q, i] * f0 + eps[q1, i] * f1) + eps[q2, i] * f2) + eps[q3, i] * f3


@njit(**_JIT)
def _deviations(X, c, ox, oy, reference, out):
    """float32 wrap(bearing c - reference) of every particle (the particles' bearings again: cheaper
    than storing eight rows from the second stage's loop)."""
    for i in range(X.shape[1]):
        out[i] = wrap32(_bearing(X, i, c, ox, oy) - reference)


@njit(**_JIT)
def _innovation_nis(X, ox, oy, first_at_pick, z, variance):
    """NIS of the received bearings against the propagated cloud weighted by 1 / p(z | mu) (a
    sample of the prediction), its moments plus the noise variance (``SonobuoyModel.innovation_nis``):
    (nis, dof), NaN and 0 when nothing was received. The cloud's moments of the bearings' float32
    deviations from particle 0's are summed in float64."""
    N = X.shape[1]
    weights = np.empty(N)
    minus = np.empty(N)
    for i in range(N):
        minus[i] = -first_at_pick[i]
    _normalise(minus, weights)
    deviation = np.empty((8, N))
    mean = np.empty(8)
    reference = np.empty(8, np.float32)
    for c in range(8):
        reference[c] = _bearing(X, 0, c, ox, oy)
        _deviations(X, c, ox, oy, reference[c], deviation[c])
        mean[c] = _weighted_row_sum(deviation, c, weights)
    weighted = np.empty((8, N))
    for c in range(8):
        for i in range(N):
            deviation[c, i] -= mean[c]
            weighted[c, i] = deviation[c, i] * weights[i]
    S = np.empty((8, 8))
    _covariance(deviation, weighted, S, 1.0)
    nu = np.zeros(8)
    dof = 0
    for c in range(8):
        e = z[c] - float(reference[c]) - mean[c]
        e = e - 2.0 * np.pi * np.rint(e * (1.0 / (2.0 * np.pi)))
        if np.isfinite(e):                 # missed (NaN): decoupled with a unit variance (``_masked_nis``)
            nu[c] = e
            S[c, c] += variance[c]
            dof += 1
        else:
            for q in range(8):
                S[c, q] = 0.0
                S[q, c] = 0.0
            S[c, c] = 1.0
    if dof == 0:
        return np.nan, 0.0
    L = np.empty((8, 8))
    _cholesky(S, L)
    y = np.empty(8)
    total = 0.0
    for c in range(8):
        s = nu[c]
        for q in range(c):
            s -= L[c, q] * y[q]
        y[c] = s / L[c, c]
        total += y[c] * y[c]
    return total, float(dof)
