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
Generators' draws are checked at run time instead (``filters.particle.reference._inline_draws_match``): a
different numpy changes no compiled code. The helpers are inlined by LLVM (``forceinline``): numba's own
inliner re-types each inlined body and made the first compilation ~128 s instead of ~23 s.
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

F32 = np.float32
_JIT = dict(nogil=True, cache=True, error_model="numpy", boundscheck=False)


# --------------------------------------------------------------------------------------------
# numpy's float32 ziggurat tables for the standard normal (Marsaglia & Tsang, 256 layers): its
# ki_float, wi_float, fi_float, ziggurat_nor_r_f and ziggurat_nor_inv_r_f
# (numpy/random/src/distributions/ziggurat_constants.h, BSD-3-Clause) as float32 bit patterns, so
# they are exact. Neither numpy nor numba exposes them publicly, so they are copied here rather
# than imported from a private module, and in this file because numba's cache checks only the
# file of the function it compiles. filters.particle.reference._inline_draws_match compares the draws with
# numpy's own once per process (falling back to numpy's calls); tests/test_particle_kernel.py too.
# --------------------------------------------------------------------------------------------

_KI = np.array([
    0x007799ec, 0x00000000, 0x006045f5, 0x006d1aa8, 0x00728fb4, 0x007592af, 0x00777a5c, 0x0078ca38,
    0x0079bf6b, 0x007a7a35, 0x007b0d2f, 0x007b83d4, 0x007be597, 0x007c3788, 0x007c7d33, 0x007cb926,
    0x007ced48, 0x007d1b08, 0x007d437f, 0x007d678b, 0x007d87db, 0x007da4fc, 0x007dbf61, 0x007dd767,
    0x007ded5d, 0x007e0183, 0x007e1411, 0x007e2534, 0x007e3515, 0x007e43d5, 0x007e5193, 0x007e5e67,
    0x007e6a69, 0x007e75aa, 0x007e803e, 0x007e8a32, 0x007e9395, 0x007e9c72, 0x007ea4d5, 0x007eacc6,
    0x007eb44e, 0x007ebb75, 0x007ec243, 0x007ec8bc, 0x007ecee8, 0x007ed4cc, 0x007eda6b, 0x007edfcb,
    0x007ee4ef, 0x007ee9dc, 0x007eee94, 0x007ef31b, 0x007ef774, 0x007efba0, 0x007effa3, 0x007f037f,
    0x007f0736, 0x007f0aca, 0x007f0e3c, 0x007f118f, 0x007f14c4, 0x007f17dc, 0x007f1ada, 0x007f1dbd,
    0x007f2087, 0x007f233a, 0x007f25d7, 0x007f285d, 0x007f2ad0, 0x007f2d2e, 0x007f2f7a, 0x007f31b3,
    0x007f33dc, 0x007f35f3, 0x007f37fb, 0x007f39f3, 0x007f3bdc, 0x007f3db7, 0x007f3f84, 0x007f4145,
    0x007f42f8, 0x007f449f, 0x007f463a, 0x007f47ca, 0x007f494e, 0x007f4ac8, 0x007f4c38, 0x007f4d9d,
    0x007f4ef9, 0x007f504c, 0x007f5195, 0x007f52d5, 0x007f540d, 0x007f553d, 0x007f5664, 0x007f5784,
    0x007f589c, 0x007f59ac, 0x007f5ab5, 0x007f5bb8, 0x007f5cb3, 0x007f5da8, 0x007f5e96, 0x007f5f7e,
    0x007f605f, 0x007f613b, 0x007f6210, 0x007f62e0, 0x007f63aa, 0x007f646f, 0x007f652e, 0x007f65e8,
    0x007f669c, 0x007f674c, 0x007f67f6, 0x007f689c, 0x007f693c, 0x007f69d9, 0x007f6a70, 0x007f6b03,
    0x007f6b91, 0x007f6c1b, 0x007f6ca0, 0x007f6d21, 0x007f6d9e, 0x007f6e17, 0x007f6e8c, 0x007f6efc,
    0x007f6f68, 0x007f6fd1, 0x007f7035, 0x007f7096, 0x007f70f3, 0x007f714c, 0x007f71a1, 0x007f71f2,
    0x007f723f, 0x007f7289, 0x007f72cf, 0x007f7312, 0x007f7350, 0x007f738b, 0x007f73c3, 0x007f73f6,
    0x007f7427, 0x007f7453, 0x007f747c, 0x007f74a1, 0x007f74c3, 0x007f74e0, 0x007f74fb, 0x007f7511,
    0x007f7524, 0x007f7533, 0x007f753f, 0x007f7546, 0x007f754a, 0x007f754b, 0x007f7547, 0x007f753f,
    0x007f7534, 0x007f7524, 0x007f7511, 0x007f74f9, 0x007f74de, 0x007f74be, 0x007f749a, 0x007f7472,
    0x007f7445, 0x007f7414, 0x007f73df, 0x007f73a5, 0x007f7366, 0x007f7323, 0x007f72da, 0x007f728d,
    0x007f723a, 0x007f71e3, 0x007f7186, 0x007f7123, 0x007f70bb, 0x007f704d, 0x007f6fd9, 0x007f6f5f,
    0x007f6edf, 0x007f6e58, 0x007f6dcb, 0x007f6d37, 0x007f6c9c, 0x007f6bf9, 0x007f6b4f, 0x007f6a9c,
    0x007f69e2, 0x007f691f, 0x007f6854, 0x007f677f, 0x007f66a1, 0x007f65b8, 0x007f64c6, 0x007f63c8,
    0x007f62c0, 0x007f61ab, 0x007f608a, 0x007f5f5d, 0x007f5e21, 0x007f5cd8, 0x007f5b7f, 0x007f5a17,
    0x007f589e, 0x007f5713, 0x007f5575, 0x007f53c4, 0x007f51fe, 0x007f5022, 0x007f4e2f, 0x007f4c22,
    0x007f49fa, 0x007f47b6, 0x007f4553, 0x007f42cf, 0x007f4028, 0x007f3d5a, 0x007f3a64, 0x007f3741,
    0x007f33ed, 0x007f3065, 0x007f2ca4, 0x007f28a4, 0x007f245f, 0x007f1fce, 0x007f1aea, 0x007f15a9,
    0x007f1000, 0x007f09e4, 0x007f0346, 0x007efc16, 0x007ef43e, 0x007eeba8, 0x007ee237, 0x007ed7c8,
    0x007ecc2f, 0x007ebf37, 0x007eb09d, 0x007ea00a, 0x007e8d0d, 0x007e7710, 0x007e5d47, 0x007e3e93,
    0x007e1959, 0x007deb2c, 0x007db036, 0x007d6203, 0x007cf4b9, 0x007c4fd2, 0x007b3630, 0x0078d2d2,
], dtype=np.uint32)

_WI = np.array([
    0x34fa49dc, 0x32dc685f, 0x3312857a, 0x332be5ca, 0x33400fe7, 0x33511861, 0x33600269, 0x336d617b,
    0x33799241, 0x33826991, 0x3387a82a, 0x338c9535, 0x33913d14, 0x3395a972, 0x3399e1fe, 0x339decf6,
    0x33a1cf7c, 0x33a58dda, 0x33a92bab, 0x33acac05, 0x33b0118e, 0x33b35e93, 0x33b69515, 0x33b9b6d7,
    0x33bcc569, 0x33bfc22d, 0x33c2ae63, 0x33c58b25, 0x33c85975, 0x33cb1a3c, 0x33cdce4c, 0x33d07667,
    0x33d3133b, 0x33d5a56b, 0x33d82d8b, 0x33daac24, 0x33dd21b4, 0x33df8eb1, 0x33e1f388, 0x33e4509d,
    0x33e6a650, 0x33e8f4f8, 0x33eb3ce9, 0x33ed7e70, 0x33efb9d5, 0x33f1ef5e, 0x33f41f4a, 0x33f649d6,
    0x33f86f3c, 0x33fa8fb3, 0x33fcab6d, 0x33fec29c, 0x34006ab7, 0x34017208, 0x34027755, 0x34037ab3,
    0x34047c35, 0x34057bec, 0x340679eb, 0x34077642, 0x34087102, 0x34096a38, 0x340a61f5, 0x340b5846,
    0x340c4d39, 0x340d40db, 0x340e3338, 0x340f245d, 0x34101455, 0x3411032c, 0x3411f0ec, 0x3412dda0,
    0x3413c953, 0x3414b40e, 0x34159ddb, 0x341686c3, 0x34176ecf, 0x34185608, 0x34193c77, 0x341a2224,
    0x341b0716, 0x341beb56, 0x341cceeb, 0x341db1de, 0x341e9435, 0x341f75f7, 0x3420572c, 0x342137d9,
    0x34221807, 0x3422f7bc, 0x3423d6fd, 0x3424b5d2, 0x34259440, 0x3426724d, 0x34275001, 0x34282d5f,
    0x34290a70, 0x3429e737, 0x342ac3ba, 0x342ba000, 0x342c7c0e, 0x342d57e9, 0x342e3397, 0x342f0f1c,
    0x342fea7e, 0x3430c5c3, 0x3431a0ef, 0x34327c08, 0x34335713, 0x34343214, 0x34350d11, 0x3435e80f,
    0x3436c313, 0x34379e22, 0x34387940, 0x34395473, 0x343a2fbf, 0x343b0b2a, 0x343be6b8, 0x343cc26e,
    0x343d9e52, 0x343e7a68, 0x343f56b4, 0x3440333d, 0x34411007, 0x3441ed16, 0x3442ca71, 0x3443a81b,
    0x3444861b, 0x34456475, 0x3446432d, 0x3447224b, 0x344801d1, 0x3448e1c7, 0x3449c231, 0x344aa314,
    0x344b8476, 0x344c665c, 0x344d48cd, 0x344e2bcc, 0x344f0f61, 0x344ff391, 0x3450d862, 0x3451bdd9,
    0x3452a3fd, 0x34538ad4, 0x34547263, 0x34555ab2, 0x345643c6, 0x34572da7, 0x3458185a, 0x345903e8,
    0x3459f055, 0x345addaa, 0x345bcbee, 0x345cbb28, 0x345dab5f, 0x345e9c9b, 0x345f8ee5, 0x34608243,
    0x346176bf, 0x34626c61, 0x34636330, 0x34645b37, 0x3465547e, 0x34664f0e, 0x34674af2, 0x34684832,
    0x346946d9, 0x346a46f1, 0x346b4885, 0x346c4ba0, 0x346d504d, 0x346e5698, 0x346f5e8d, 0x34706838,
    0x347173a6, 0x347280e5, 0x34739001, 0x3474a10a, 0x3475b40e, 0x3476c91c, 0x3477e043, 0x3478f994,
    0x347a1520, 0x347b32f9, 0x347c5330, 0x347d75d9, 0x347e9b07, 0x347fc2ce, 0x348076a2, 0x34810d40,
    0x3481a54c, 0x34823ed2, 0x3482d9e0, 0x34837681, 0x348414c4, 0x3484b4b8, 0x3485566c, 0x3485f9ef,
    0x34869f52, 0x348746a6, 0x3487efff, 0x34889b70, 0x3489490d, 0x3489f8eb, 0x348aab22, 0x348b5fca,
    0x348c16fc, 0x348cd0d3, 0x348d8d6c, 0x348e4ce5, 0x348f0f60, 0x348fd4fe, 0x34909de5, 0x34916a3c,
    0x34923a2d, 0x34930de6, 0x3493e598, 0x3494c176, 0x3495a1bb, 0x349686a2, 0x3497706e, 0x34985f67,
    0x349953db, 0x349a4e20, 0x349b4e94, 0x349c559d, 0x349d63ac, 0x349e793e, 0x349f96dd, 0x34a0bd25,
    0x34a1ecc1, 0x34a32672, 0x34a46b14, 0x34a5bb9d, 0x34a71928, 0x34a884fb, 0x34aa008b, 0x34ab8d8d,
    0x34ad2e04, 0x34aee451, 0x34b0b34e, 0x34b29e74, 0x34b4aa06, 0x34b6db5c, 0x34b93948, 0x34bbccab,
    0x34bea170, 0x34c1c818, 0x34c5587e, 0x34c97705, 0x34ce5f70, 0x34d47ee4, 0x34dcc0fa, 0x34e9dda4,
], dtype=np.uint32).view(np.float32)

_FI = np.array([
    0x3f800000, 0x3f7a2356, 0x3f75baa3, 0x3f71f88f, 0x3f6e9b7d, 0x3f6b8490, 0x3f68a24c, 0x3f65e99d,
    0x3f6352f6, 0x3f60d8e7, 0x3f5e775a, 0x3f5c2b2a, 0x3f59f1d4, 0x3f57c952, 0x3f55aff8, 0x3f53a45f,
    0x3f51a558, 0x3f4fb1df, 0x3f4dc914, 0x3f4bea33, 0x3f4a148e, 0x3f48478e, 0x3f4682aa, 0x3f44c56a,
    0x3f430f60, 0x3f416028, 0x3f3fb76a, 0x3f3e14d4, 0x3f3c781a, 0x3f3ae0f8, 0x3f394f30, 0x3f37c286,
    0x3f363ac5, 0x3f34b7bb, 0x3f333939, 0x3f31bf15, 0x3f304925, 0x3f2ed743, 0x3f2d694d, 0x3f2bff21,
    0x3f2a98a0, 0x3f2935ab, 0x3f27d627, 0x3f2679fa, 0x3f25210c, 0x3f23cb43, 0x3f22788a, 0x3f2128cc,
    0x3f1fdbf5, 0x3f1e91f1, 0x3f1d4aad, 0x3f1c0619, 0x3f1ac424, 0x3f1984be, 0x3f1847d8, 0x3f170d63,
    0x3f15d551, 0x3f149f94, 0x3f136c21, 0x3f123aeb, 0x3f110be5, 0x3f0fdf05, 0x3f0eb440, 0x3f0d8b8b,
    0x3f0c64dc, 0x3f0b4029, 0x3f0a1d69, 0x3f08fc92, 0x3f07dd9d, 0x3f06c081, 0x3f05a534, 0x3f048bb1,
    0x3f0373ee, 0x3f025de5, 0x3f01498f, 0x3f0036e4, 0x3efe4bbc, 0x3efc2ced, 0x3efa114e, 0x3ef7f8d4,
    0x3ef5e371, 0x3ef3d11b, 0x3ef1c1c7, 0x3eefb56a, 0x3eedabfa, 0x3eeba56b, 0x3ee9a1b5, 0x3ee7a0ce,
    0x3ee5a2ac, 0x3ee3a746, 0x3ee1ae93, 0x3edfb88c, 0x3eddc527, 0x3edbd45c, 0x3ed9e623, 0x3ed7fa75,
    0x3ed6114a, 0x3ed42a9a, 0x3ed2465f, 0x3ed06492, 0x3ece852b, 0x3ecca824, 0x3ecacd77, 0x3ec8f51d,
    0x3ec71f10, 0x3ec54b4a, 0x3ec379c5, 0x3ec1aa7c, 0x3ebfdd69, 0x3ebe1285, 0x3ebc49cd, 0x3eba833b,
    0x3eb8beca, 0x3eb6fc74, 0x3eb53c35, 0x3eb37e09, 0x3eb1c1ea, 0x3eb007d4, 0x3eae4fc2, 0x3eac99b1,
    0x3eaae59c, 0x3ea9337e, 0x3ea78354, 0x3ea5d51b, 0x3ea428cd, 0x3ea27e67, 0x3ea0d5e7, 0x3e9f2f47,
    0x3e9d8a84, 0x3e9be79b, 0x3e9a4689, 0x3e98a74a, 0x3e9709dc, 0x3e956e3a, 0x3e93d462, 0x3e923c51,
    0x3e90a604, 0x3e8f1178, 0x3e8d7eaa, 0x3e8bed97, 0x3e8a5e3e, 0x3e88d09a, 0x3e8744ab, 0x3e85ba6c,
    0x3e8431dc, 0x3e82aaf9, 0x3e8125c0, 0x3e7f445c, 0x3e7c4084, 0x3e793ff3, 0x3e7642a5, 0x3e734896,
    0x3e7051c1, 0x3e6d5e23, 0x3e6a6db8, 0x3e67807c, 0x3e64966d, 0x3e61af86, 0x3e5ecbc4, 0x3e5beb24,
    0x3e590da3, 0x3e56333d, 0x3e535bf0, 0x3e5087ba, 0x3e4db696, 0x3e4ae883, 0x3e481d7e, 0x3e455585,
    0x3e429094, 0x3e3fceab, 0x3e3d0fc7, 0x3e3a53e5, 0x3e379b04, 0x3e34e522, 0x3e32323d, 0x3e2f8254,
    0x3e2cd564, 0x3e2a2b6d, 0x3e27846d, 0x3e24e063, 0x3e223f4e, 0x3e1fa12c, 0x3e1d05fd, 0x3e1a6dc0,
    0x3e17d874, 0x3e154619, 0x3e12b6ad, 0x3e102a31, 0x3e0da0a5, 0x3e0b1a07, 0x3e089659, 0x3e06159a,
    0x3e0397ca, 0x3e011ceb, 0x3dfd49f6, 0x3df85ff9, 0x3df37be0, 0x3dee9dab, 0x3de9c55e, 0x3de4f2fa,
    0x3de02683, 0x3ddb5ffc, 0x3dd69f67, 0x3dd1e4ca, 0x3dcd3027, 0x3dc88184, 0x3dc3d8e5, 0x3dbf3650,
    0x3dba99cb, 0x3db6035c, 0x3db17309, 0x3dace8db, 0x3da864d8, 0x3da3e70a, 0x3d9f6f79, 0x3d9afe2f,
    0x3d969336, 0x3d922e9a, 0x3d8dd066, 0x3d8978a7, 0x3d852769, 0x3d80dcbd, 0x3d793161, 0x3d70b6aa,
    0x3d684978, 0x3d5fe9f0, 0x3d57983d, 0x3d4f5488, 0x3d471f01, 0x3d3ef7dc, 0x3d36df4e, 0x3d2ed592,
    0x3d26dae8, 0x3d1eef96, 0x3d1713e7, 0x3d0f482d, 0x3d078cc1, 0x3cffc40f, 0x3cf090d7, 0x3ce180cc,
    0x3cd294fa, 0x3cc3ce8e, 0x3cb52ed8, 0x3ca6b758, 0x3c9869c4, 0x3c8a481a, 0x3c78a952, 0x3c5d2469,
    0x3c420820, 0x3c275cb2, 0x3c0d2c91, 0x3be70b08, 0x3bb4f547, 0x3b8450f8, 0x3b2afcfa, 0x3aa5302e,
], dtype=np.uint32).view(np.float32)

_NOR_R = np.array([0x4069dda4], dtype=np.uint32).view(np.float32)[0]           # the base strip's edge, r
_NOR_INV_R = np.array([0x3e8c1d53], dtype=np.uint32).view(np.float32)[0]       # 1 / r


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
# on first use (``filters.particle.reference._inline_draws_match``); the numpy calls are the fallback.
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
