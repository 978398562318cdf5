"""Counter-based hash random numbers for Taichi kernels (and a numpy twin).

Why: a case must render bit-identically whatever batch, position in the batch or thread
computes it (docs/architecture.md, Conventions: "Seeds").  ``ti.random`` keeps per-thread
state, so the numbers a pixel gets would depend on scheduling.  Here every random number is a
pure function of ``(seed, stream, draw, index)``:

    key   = mix64(seed ^ (((stream << 32) | draw) * K_STREAM + K_OFFSET))
    value = mix64(key + (index + 1) * GOLDEN)

``mix64`` is the SplitMix64 output finaliser (Steele, Lea & Flood, "Fast splittable
pseudorandom number generators", OOPSLA 2014; constants from Stafford's "Mix13"), a bijection
on 64-bit words with full avalanche.  For a fixed key, ``value`` over consecutive ``index`` is
exactly the SplitMix64 sequence started at ``key`` (which passes BigCrush); different
(seed, stream, draw) give different start points 2^64 apart in expectation, so two streams of
< 2^32 draws overlap with probability < 2^-30.

Conventions
-----------
seed   : uint64, one per case (``seeds[b]``).
stream : small uint32 naming *what* the number is for (see ``STREAM_*``), so that turning one
         sensor effect on or off never changes the numbers another effect draws.
draw   : uint32, the n-th number a consumer needs for the same (stream, index) (e.g. rejection-sampler retries).
index  : uint64 counter, usually the pixel index ``row * width + col`` inside the frame.

All functions decorated with ``@ti.func`` are meant to be called from kernels; the numpy
functions (``*_np``) compute the very same bits on arrays (used for the per-case false-star
lists and for tests).  Importing this module does not initialise Taichi.
"""


import math

import numpy as np
import taichi as ti

# ----------------------------------------------------------------------------- constants
_M1 = 0xBF58476D1CE4E5B9
_M2 = 0x94D049BB133111EB
GOLDEN = 0x9E3779B97F4A7C15
K_STREAM = 0xD1342543DE82EF95
K_OFFSET = 0x2545F4914F6CDD1D

# Stream ids used by the dualsight kernels (each effect has its own stream).
STREAM_SHOT = 1
STREAM_READ = 2
STREAM_HOT = 3
STREAM_FALSE_STAR = 4
STREAM_SKY_ADU = 5     # a sky pixel's ADU value in one draw (shot + read noise + ADC, kernels/starfield.sky_adu_table)
STREAM_PROX_READ = 0   # proximity renderer's read noise (Box-Muller pairs; kept at 0 for bit-identical replays)
STREAM_TEST = 99

_INV_2_53 = 1.0 / 9007199254740992.0  # 2^-53
_TWO_PI_F32 = float(np.float32(2.0 * math.pi))  # 6.2831854820251465


# Polynomial coefficients, highest power first (evaluated by :func:`_horner`, unrolled at compile time).
_AS241_A = (  # normal_icdf, central region, numerator
    2.5090809287301226727e3, 3.3430575583588128105e4, 6.7265770927008700853e4,
    4.5921953931549871457e4, 1.3731693765509461125e4, 1.9715909503065514427e3,
    1.3314166789178437745e2, 3.3871328727963666080e0)
_AS241_B = (  # normal_icdf, central region, denominator
    5.2264952788528545610e3, 2.8729085735721942674e4, 3.9307895800092710610e4,
    2.1213794301586595867e4, 5.3941960214247511077e3, 6.8718700749205790830e2,
    4.2313330701600911252e1, 1.0)
_AS241_C = (  # normal_icdf, tails r <= 5, numerator
    7.74545014278341407640e-4, 2.27238449892691845833e-2, 2.41780725177450611770e-1,
    1.27045825245236838258e0, 3.64784832476320460504e0, 5.76949722146069140550e0,
    4.63033784615654529590e0, 1.42343711074968357734e0)
_AS241_D = (  # normal_icdf, tails r <= 5, denominator
    1.05075007164441684324e-9, 5.47593808499534494600e-4, 1.51986665636164571966e-2,
    1.48103976427480074590e-1, 6.89767334985100004550e-1, 1.67638483018380384940e0,
    2.05319162663775882187e0, 1.0)
_AS241_E = (  # normal_icdf, far tails, numerator
    2.01033439929228813265e-7, 2.71155556874348757815e-5, 1.24266094738807843860e-3,
    2.65321895265761230930e-2, 2.96560571828504891230e-1, 1.78482653991729133580e0,
    5.46378491116411436990e0, 6.65790464350110377720e0)
_AS241_F = (  # normal_icdf, far tails, denominator
    2.04426310338993978564e-15, 1.42151175831644588870e-7, 1.84631831751005468180e-5,
    7.86869131145613259100e-4, 1.48753612908506148525e-2, 1.36929880922735805310e-1,
    5.99832206555887937690e-1, 1.0)
_LOGGAM = (  # log_gamma's Stirling series in 1/x^2
    -1.39243221690590e00, 1.796443723688307e-01, -2.955065359477124e-02,
    6.410256410256410e-03, -1.917526917526918e-03, 8.417508417508418e-04,
    -5.952380952380952e-04, 7.936507936507937e-04, -2.777777777777778e-03,
    8.333333333333333e-02)


# ----------------------------------------------------------------------------- Taichi funcs
@ti.func
def mix64(z):
    """SplitMix64 finaliser of a u64 (bijective, full avalanche)."""
    z = (z ^ ti.bit_shr(z, 30)) * ti.u64(_M1)
    z = (z ^ ti.bit_shr(z, 27)) * ti.u64(_M2)
    return z ^ ti.bit_shr(z, 31)


@ti.func
def stream_key(seed, stream, draw):
    """u64 key of (seed: u64, stream: int, draw: int); hoist it out of pixel loops."""
    sd = (ti.cast(stream, ti.u64) << ti.u64(32)) | ti.cast(draw, ti.u64)
    return mix64(seed ^ (sd * ti.u64(K_STREAM) + ti.u64(K_OFFSET)))


@ti.func
def hash_key(key, index):
    """u64 random word for counter ``index`` (u64) under ``key`` (from :func:`stream_key`)."""
    return mix64(key + (ti.cast(index, ti.u64) + ti.u64(1)) * ti.u64(GOLDEN))


@ti.func
def u01_key(key, index):
    """Uniform f64 in the open interval (0, 1): 53 random bits + 1/2 ulp."""
    h = hash_key(key, index)
    # via i64: the 53-bit value converts exactly either way, and x86-64 has no single u64 -> f64 instruction
    return (ti.cast(ti.cast(ti.bit_shr(h, 11), ti.i64), ti.f64) + ti.f64(0.5)) * ti.f64(_INV_2_53)


@ti.func
def uniform(seed, stream, draw, index):
    """Uniform f64 in (0, 1) for (seed, stream, draw, index)."""
    return u01_key(stream_key(seed, stream, draw), index)


@ti.func
def _horner(coeffs: ti.template(), r):
    """Polynomial with f64 coefficients ``coeffs`` (a tuple, highest power first) at f64 r, by Horner."""
    acc = ti.f64(coeffs[0])
    for i in ti.static(range(1, len(coeffs))):
        acc = acc * r + ti.f64(coeffs[i])
    return acc


@ti.func
def normal_icdf(p):
    """Standard normal quantile Phi^-1(p) for f64 p in (0, 1), relative accuracy ~1e-16.

    Wichura (1988), "Algorithm AS241: The percentage points of the normal distribution",
    Applied Statistics 37, 477-484 (PPND16; the coefficients CPython's statistics module uses).
    Central 85 % of p: one rational function, no transcendental call.
    """
    q = p - ti.f64(0.5)
    x = ti.f64(0.0)
    if ti.abs(q) <= ti.f64(0.425):
        r = ti.f64(0.180625) - q * q
        x = q * _horner(_AS241_A, r) / _horner(_AS241_B, r)
    else:
        r = p
        if q > ti.f64(0.0):
            r = ti.f64(1.0) - p
        r = ti.sqrt(-ti.log(r))
        num = ti.f64(0.0)
        den = ti.f64(1.0)
        if r <= ti.f64(5.0):
            r = r - ti.f64(1.6)
            num = _horner(_AS241_C, r)
            den = _horner(_AS241_D, r)
        else:
            r = r - ti.f64(5.0)
            num = _horner(_AS241_E, r)
            den = _horner(_AS241_F, r)
        x = num / den
        if q < ti.f64(0.0):
            x = -x
    return x


@ti.func
def normal_key(key, index):
    """Standard normal f64 by inversion of one keyed uniform (:func:`normal_icdf`)."""
    return normal_icdf(u01_key(key, index))


@ti.func
def normal(seed, stream, index):
    """Standard normal f64 for (seed, stream, index) (draw 0 of the stream)."""
    return normal_key(stream_key(seed, stream, 0), index)


@ti.func
def derived_key(key):
    """A second u64 key from ``key`` (a :func:`stream_key`): mix64(key ^ GOLDEN)."""
    return mix64(key ^ ti.u64(GOLDEN))


@ti.func
def normal_box_muller(key0, key1, index):
    """Standard normal f64 by Box-Muller (Box & Muller 1958, cosine branch) from the uniforms of
    (key0, index) and (key1, index): sqrt(-2 ln u1) cos(2 pi u2).

    The proximity renderer's read noise (STREAM_PROX_READ, key1 = :func:`derived_key` of key0).  2 pi is
    the float32-rounded constant that code has always used, so its frames replay bit-identically.
    """
    u1 = u01_key(key0, index)
    u2 = u01_key(key1, index)
    return ti.sqrt(ti.f64(-2.0) * ti.log(u1)) * ti.cos(ti.f64(_TWO_PI_F32) * u2)


@ti.func
def log_gamma(x):
    """ln Gamma(x) for f64 x >= 1: Stirling series with upward shift below 7.

    Same algorithm and coefficients as numpy's ``random_loggam`` (distributions.c),
    absolute error < 1e-14 for x >= 1.
    """
    result = ti.f64(0.0)
    if x != ti.f64(1.0) and x != ti.f64(2.0):
        n = 0
        if x < ti.f64(7.0):
            n = ti.cast(ti.f64(7.0) - x, ti.i32)
        x0 = x + ti.cast(n, ti.f64)
        x2 = (ti.f64(1.0) / x0) * (ti.f64(1.0) / x0)
        gl0 = _horner(_LOGGAM, x2)
        gl = gl0 / x0 + ti.f64(0.5 * 1.8378770664093453) + (x0 - ti.f64(0.5)) * ti.log(x0) - x0
        for _k in range(n):
            x0 -= ti.f64(1.0)
            gl -= ti.log(x0)
        result = gl
    return result


@ti.func
def poisson_consts(lam):
    """Per-lambda constants of :func:`poisson_keyed` (f64 vector of 7); cache them for repeated lambdas."""
    lam_c = ti.max(lam, ti.f64(10.0))  # the PTRS part is only used for lam >= 10
    slam = ti.sqrt(lam_c)
    b = ti.f64(0.931) + ti.f64(2.53) * slam
    return ti.Vector([ti.exp(-lam), slam, ti.log(lam_c), b, ti.f64(-0.059) + ti.f64(0.02483) * b,
                      ti.log(ti.f64(1.1239) + ti.f64(1.1328) / (b - ti.f64(3.4))),
                      ti.f64(0.9277) - ti.f64(3.6224) / (b - ti.f64(2.0))], dt=ti.f64)


@ti.func
def poisson_inversion(lam, p0, u, n_max: ti.template()):
    """Poisson(lam) by sequential inversion of the uniform u (f64 holding an integer): the smallest n with
    P(N <= n) >= u, summing the pmf p_n = p_(n-1) lam / n from p0 = exp(-lam) (passed in: it is often cached),
    n_max at the most.  For small lam (the search takes ~lam + 1 steps)."""
    p = p0
    cdf = p
    n = 0
    while u > cdf and n < n_max:
        n += 1
        p *= lam / ti.cast(n, ti.f64)
        cdf += p
    return ti.cast(n, ti.f64)


@ti.func
def poisson(lam, seed, stream, index):
    """Exact Poisson(lam) sample for (seed, stream, index); see :func:`poisson_keyed`."""
    return poisson_keyed(lam, poisson_consts(lam), stream_key(seed, stream, 0), stream_key(seed, stream, 1),
                         seed, stream, index)


@ti.func
def poisson_keyed(lam, cst, key0, key1, seed, stream, index):
    """Exact Poisson(lam) sample (f64 holding an integer) for f64 lam >= 0.

    lam < 10: inversion by sequential search (:func:`poisson_inversion`; one uniform, draw 0).
    lam >= 10: PTRS transformed rejection (Hörmann 1993, "The transformed rejection method for
    generating Poisson random variables", Insurance: Math. & Econ. 12, 39-45; the variant used by
    numpy), drawing uniform pairs (draws 2k, 2k+1) until acceptance (~1.1 pairs on average).
    cst = poisson_consts(lam); key0, key1 = stream_key(seed, stream, 0 / 1): both can be hoisted out
    of pixel loops by the caller (most pixels of a star field share the sky's lambda).
    """
    k = ti.f64(0.0)
    if lam <= ti.f64(0.0):
        k = ti.f64(0.0)
    elif lam < ti.f64(10.0):
        k = poisson_inversion(lam, cst[0], u01_key(key0, index), 200)
    else:
        loglam = cst[2]
        b = cst[3]
        a = cst[4]
        log_invalpha = cst[5]
        vr = cst[6]
        draw = 0
        done = False
        while not done and draw < 2000:
            ka = key0
            kb = key1
            if draw > 0:
                ka = stream_key(seed, stream, draw)
                kb = stream_key(seed, stream, draw + 1)
            U = u01_key(ka, index) - ti.f64(0.5)
            V = u01_key(kb, index)
            draw += 2
            us = ti.f64(0.5) - ti.abs(U)
            kk = ti.floor((ti.f64(2.0) * a / us + b) * U + lam + ti.f64(0.43))
            if us >= ti.f64(0.07) and V <= vr:
                k = kk
                done = True
            elif kk < ti.f64(0.0) or (us < ti.f64(0.013) and V > us):
                pass
            elif (ti.log(V) + log_invalpha - ti.log(a / (us * us) + b)
                  <= -lam + kk * loglam - log_gamma(kk + ti.f64(1.0))):
                k = kk
                done = True
        if not done:  # practically unreachable (p < 1e-1000); keep the mean
            k = ti.floor(lam + ti.f64(0.5))
    return k


@ti.func
def search_cdf(u, k0, cdf: ti.template(), o0, K):
    """The smallest local index k >= k0 of the tabulated CDF cdf[o0 : o0 + K] with cdf[o0 + k] >= u, by a forward
    search from k0 (a guide table's cell, so O(1) expected steps: Chen & Asau 1974); -1 when u lies beyond the
    table's last entry.  The search of every guided inversion (:func:`poisson_table`, :func:`inverse_table`,
    :func:`inverse_table_bits`)."""
    k = k0
    while k < K and cdf[o0 + k] < u:
        k += 1
    res = k
    if k >= K:
        res = -1
    return res


@ti.func
def poisson_table(u, cdf: ti.template(), guide: ti.template(), o0, o1):
    """Poisson sample by inversion of the tabulated CDF cdf[o0:o1] with its guide table guide[o0:o1] (local
    indices; each as :func:`poisson_table_np` gives them, K = o1 - o0 entries; a whole table is o0 = 0,
    o1 = its length, several tables one after another are cut by their offsets, as kernels/sky_noise.stray_tables):
    the smallest k with cdf[o0 + k] >= u, from guide cell floor(u K) (:func:`search_cdf`).  Returns -1.0 when u
    lies beyond the table's last entry (probability < 1e-15; the caller falls back).  Same result as the
    sequential-search inversion in :func:`poisson_keyed`, up to f64 rounding of the CDF.
    """
    K = ti.cast(o1 - o0, ti.i32)
    j = ti.min(ti.cast(u * ti.cast(K, ti.f64), ti.i32), K - 1)
    k = search_cdf(u, guide[o0 + j], cdf, o0, K)
    res = ti.f64(-1.0)
    if k >= 0:
        res = ti.cast(k, ti.f64)
    return res


@ti.func
def inverse_table(u, cdf: ti.template(), guide: ti.template()):
    """Index of the smallest cdf entry >= u (f64 u in (0, 1)), -1 beyond the last entry: inversion of a
    tabulated discrete CDF through the direct guide table of :func:`inverse_table_np` (M cells, a power of
    two, so the cell floor(u M) is exact).  A cell that holds no CDF step gives its answer in one load; the
    others (one in ~16) start their search (:func:`search_cdf`) there."""
    M = guide.shape[0]
    g = guide[ti.min(ti.cast(u * ti.cast(M, ti.f64), ti.i32), M - 1)]
    res = g
    if g < 0:
        res = search_cdf(u, -g - 1, cdf, 0, cdf.shape[0])
    return res


@ti.func
def inverse_table_bits(h, nbits: ti.template(), gshift, key, index, cdf: ti.template(), guide: ti.template()):
    """:func:`inverse_table` of u = (h + v) 2^-nbits from ``nbits`` random bits h (an integer < 2^nbits in a u64)
    and, only when a CDF step falls inside h's cell [h, h + 1) 2^-nbits (probability <= K 2^-nbits, K the table's
    entries), a further uniform v = :func:`u01_key` (key, index): exactly the distribution of inversion with a
    53-bit uniform, at a fraction of the hashing cost when one 64-bit hash serves 64 / nbits pixels
    (kernels/starfield.py).  Needs the guide table's cells M = 2^(nbits - gshift) <= 2^nbits (each h cell inside
    one guide cell, found by a shift)."""
    K = cdf.shape[0]
    w = ti.f64(1.0 / (1 << nbits))
    g = guide[ti.cast(h >> ti.cast(gshift, ti.u64), ti.i32)]    # cell floor(h / 2^gshift) = floor(u M), exact
    res = g
    if g < 0:
        ulo = ti.cast(ti.cast(h, ti.i64), ti.f64) * w
        res = search_cdf(ulo, -g - 1, cdf, 0, K)
        if res >= 0:
            if cdf[res] < ulo + w:    # a step inside h's cell: more bits decide
                res = search_cdf(ulo + u01_key(key, index) * w, res, cdf, 0, K)
    return res


# ----------------------------------------------------------------------------- numpy twins
_U = np.uint64


def mix64_np(z: np.ndarray) -> np.ndarray:
    """numpy twin of :func:`mix64` on uint64 arrays."""
    z = np.asarray(z, dtype=np.uint64)
    with np.errstate(over="ignore"):
        z = (z ^ (z >> _U(30))) * _U(_M1)
        z = (z ^ (z >> _U(27))) * _U(_M2)
    return z ^ (z >> _U(31))


def stream_key_np(seed, stream: int, draw: int) -> np.ndarray:
    """numpy twin of :func:`stream_key`; ``seed`` (...,) uint64."""
    sd = _U((int(stream) << 32) | int(draw))
    with np.errstate(over="ignore"):
        return mix64_np(np.asarray(seed, dtype=np.uint64) ^ (sd * _U(K_STREAM) + _U(K_OFFSET)))


def hash_key_np(key, index) -> np.ndarray:
    """numpy twin of :func:`hash_key`: uint64 words for broadcastable uint64 ``key`` and ``index`` arrays."""
    idx = np.asarray(index, dtype=np.uint64)
    with np.errstate(over="ignore"):
        return mix64_np(np.asarray(key, dtype=np.uint64) + (idx + _U(1)) * _U(GOLDEN))


def u01_key_np(key, index) -> np.ndarray:
    """numpy twin of :func:`u01_key`: uniform float64 in (0, 1)."""
    return ((hash_key_np(key, index) >> _U(11)).astype(np.float64) + 0.5) * _INV_2_53


def derived_key_np(key) -> np.ndarray:
    """numpy twin of :func:`derived_key`."""
    return mix64_np(np.asarray(key, dtype=np.uint64) ^ _U(GOLDEN))


def hash_np(seed, stream: int, draw: int, index) -> np.ndarray:
    """uint64 words for broadcastable ``seed`` and ``index`` arrays (twin of ``hash_key``)."""
    return hash_key_np(stream_key_np(seed, stream, draw), index)


def uniform_np(seed, stream: int, draw: int, index) -> np.ndarray:
    """Uniform float64 in (0, 1), bit-identical to :func:`uniform`."""
    return u01_key_np(stream_key_np(seed, stream, draw), index)


def as_seeds(seeds, n: int, name: str = "seeds") -> np.ndarray:
    """Validate per-case seeds: (n,) non-negative integers -> contiguous uint64."""
    a = np.asarray(seeds)
    if a.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},) (one seed per case), got {a.shape}")
    if a.dtype.kind not in "ui":
        raise ValueError(f"{name} must be integers (uint64), got dtype {a.dtype}")
    if a.dtype.kind == "i" and a.size and a.min() < 0:
        raise ValueError(f"{name} must be >= 0, got min {a.min()}")
    return np.ascontiguousarray(a.astype(np.uint64))


def poisson_table_np(lam: float) -> tuple[np.ndarray, np.ndarray]:
    """CDF and guide table of Poisson(lam) for :func:`poisson_table`: (cdf (K,) float64, guide (K,) int32).

    K = lam + 12 sqrt(lam) + 30 entries (the tail beyond holds < 1e-20 of the mass); pmf by the recurrence
    p_k = p_(k-1) lam / k in log space; guide[j] = smallest k with cdf[k] >= j / K.
    """
    lam = float(lam)
    K = int(lam + 12.0 * math.sqrt(lam) + 30.0)
    k = np.arange(K, dtype=np.float64)
    if lam > 0:
        logp = -lam + np.concatenate([[0.0], np.cumsum(math.log(lam) - np.log(k[1:]))])
    else:
        logp = np.where(k == 0, 0.0, -np.inf)
    cdf = np.cumsum(np.exp(logp))
    guide = np.searchsorted(cdf, np.arange(K, dtype=np.float64) / K, side="left").astype(np.int32)
    return np.ascontiguousarray(cdf), np.ascontiguousarray(np.minimum(guide, K - 1))


def inverse_table_np(cdf: np.ndarray, cells_per_entry: int = 16) -> np.ndarray:
    """Direct guide table of a discrete CDF for :func:`inverse_table`: (M,) int32, M the power of two >=
    max(1024, cells_per_entry * len(cdf)).  Cell j covers u in [j / M, (j + 1) / M); g = the smallest k with
    cdf[k] >= j / M; the entry is g when cdf[g] >= (j + 1) / M (every u of the cell inverts to g), else
    -(g + 1) (search from g)."""
    cdf = np.asarray(cdf, dtype=np.float64)
    K = cdf.size
    M = 1 << max(10, int(math.ceil(math.log2(max(1, cells_per_entry * K)))))
    j = np.arange(M, dtype=np.float64)
    g = np.minimum(np.searchsorted(cdf, j / M, side="left"), K - 1)
    resolved = cdf[g] >= (j + 1.0) / M
    return np.ascontiguousarray(np.where(resolved, g, -(g + 1)).astype(np.int32))
