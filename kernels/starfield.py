"""Batched star-field rendering on the CPU (Taichi): exact pixel-integrated Gaussian PSFs plus sensor effects.

Coordinates (docs/architecture.md): continuous pixel coordinates (col, row) = (x, y) measured from the image's
top-left *corner*; pixel (r, c) covers [c, c+1) x [r, r+1) and has its centre at (c + 0.5, r + 0.5).

Signal model (electrons, per pixel (r, c) of case b)::

    S      = sum_s  F_s * [Phi((c+1-x_s)/sigma) - Phi((c-x_s)/sigma)] * [Phi((r+1-y_s)/sigma) - Phi((r-y_s)/sigma)]
             (or the PSF model, smear and bright objects of :mod:`dualsight.kernels.psf_models`)
    e      = S + dark_current * exposure + sky_background  (+ hot_pixel_e on hot pixels)
             + max(0, e0 + gx (c + 0.5 - W/2) + gy (r + 0.5 - H/2))      (stray light, stray_light_e = [e0, gx, gy])
    e      = Poisson(e)                       if shot_noise
    e      = min(e, full_well)
    e      = e + read_noise * N(0, 1)
    ADU    = clip(floor(e / gain + bias_adu + 1e-9), 0, 2^bit_depth - 1)   (no floor if not quantize)

Stage 1, the signal S (Gaussian PSFs of standard deviation ``psf_sigma_px`` integrated exactly over each
pixel, in a window of half-width ``ceil(psf_window_sigma * sigma + 1)`` px, so at most 2 * Phi(-psf_window_sigma)
of the flux (6.3e-5 for 4 sigma) falls outside per axis), is :mod:`dualsight.kernels.star_psf` (other PSF models,
smear and bright objects: :mod:`dualsight.kernels.psf_models`).  This module holds stage 2 (the ``finalize``
kernel: charge, noise, ADC) and :func:`render_star_fields`, which runs both; the sensor model is
:class:`dualsight.kernels.sensor_config.SensorConfig`, the noise tables :mod:`dualsight.kernels.sky_noise`.

Random numbers come from :mod:`dualsight.kernels.rng` (a counter-based hash of (case seed, stream,
pixel index)), never from ``ti.random``: a case renders bit-identically whatever batch, position or
thread computes it.  Sky pixels (no star light, not hot, no stray light: most of a star field) with
quantised ADU draw their final value in one uniform, by inversion of the tabulated exact CDF of shot noise +
read noise + ADC (:func:`dualsight.kernels.sky_noise.sky_adu_table`, through a direct guide table: no
transcendental call per pixel); one 64-bit hash serves 4 neighbouring pixels, 16 bits each, and a pixel whose
2^-16 cell holds a CDF step draws 53 more bits (``rng.inverse_table_bits``: the same distribution as a 53-bit
uniform; 7-10 % of the noisy preset's time per case, measured with benchmarks/bench_noise_path.py).
Rows with the sky table, Gaussian stars and sparse (or no) hot pixels are drawn in two passes: every pixel as
sky in a tight loop, then only the columns in the row's span of star windows (recorded by the splat) and the hot
columns are redrawn through the per-effect samplers; every pixel's value is a function of (case seed, pixel
index, its inputs) alone, so the frame is the one a single pass draws.  The frame digest
(:mod:`dualsight.kernels.digest`) can be summed in the same pass (``render_star_fields(..., digest=True)``).
Other pixels: shot noise is exact Poisson, by inversion of a tabulated CDF for pixels at the sky level,
otherwise sequential inversion below 10 e- and PTRS rejection (Hörmann 1993) above; read noise is N(0, 1) by
inversion (Wichura's AS241).  Without shot noise, dark current and sky background are their means only.
Hot pixels (fraction p <= HOT_GEOMETRIC_MAX) are drawn along each row by the geometric gaps of their
Bernoulli process (one draw per hot pixel), above that by one draw per pixel.

Magnitudes: :func:`dualsight.kernels.sensor_config.flux_from_magnitude` uses
``F = zero_mag_rate_e_per_s * 10^(-0.4 m) * exposure_s``.  The default zero point, 1.5e6 e-/s for a V = 0 star,
is a round figure for a ~1 cm^2 clear aperture (e.g. 17 mm f/1.4): about 1000 photons s^-1 cm^-2 A^-1 at V = 0
(Bessell, Castelli & Plez 1998, A&A 333, 231: 3.63e-9 erg s^-1 cm^-2 A^-1 at 550 nm) over a ~3000 A silicon pass
band at ~50 % quantum efficiency.  It is a config field; set it from your optics.

Noise-free frames never need to be materialised for detection: see
``dualsight.kernels.detect.render_and_detect_ideal`` (same pixels, only the patches around stars).

Taichi is initialised lazily (``dualsight.kernels.taichi_runtime.ensure_init``) on the first call.
"""


import math
import threading

import numpy as np
import taichi as ti

from dualsight.kernels import psf_models, rng, star_psf
from dualsight.kernels.digest import splitmix64
from dualsight.kernels.taichi_runtime import KernelCache
from dualsight.kernels.sensor_config import QUANT_EPS_ADU, SensorConfig
from dualsight.kernels.sky_noise import sky_adu_table, stray_tables

__all__ = ["render_star_fields", "false_star_lists", "append_false_stars", "release_scratch", "digest_weights"]

MAX_CHUNK_PIXELS = 1 << 26  # pixels per kernel call: 256 MB float32 scratch at most, indices fit in int32
_FRAC_DRAW = 4095  # STREAM_SHOT draw of the stray light's sub-grid Poisson part (PTRS uses draws < 2000)
HOT_GEOMETRIC_MAX = 0.02  # hot-pixel fractions up to this are drawn by geometric gaps (one draw per hot pixel)


# ============================================================================ Taichi funcs
@ti.func
def ideal_adu(s, base_e, full_well, gain, bias, max_adu, quantize):
    """ADU of a pixel holding f32 star signal ``s`` (e-) without random effects (f64 result)."""
    e = ti.min(ti.cast(s, ti.f64) + base_e, full_well)
    adu = e / gain + bias
    if quantize != 0:
        adu = ti.floor(adu + ti.f64(QUANT_EPS_ADU))
    return ti.min(ti.max(adu, ti.f64(0.0)), max_adu)


@ti.func
def _next_hot(c, W, log1m, u):
    """Column of the next hot pixel after column c (W: none in the row): c + 1 + G, G = floor(ln u / ln(1 - p))
    the geometric number of cool pixels before it, P(G >= g) = (1 - p)^g (log1m = ln(1 - p) < 0)."""
    g = ti.floor(ti.log(u) / log1m)
    nxt = W
    if g < ti.cast(W - c - 1, ti.f64):
        nxt = c + 1 + ti.cast(g, ti.i32)
    return nxt


# ============================================================================ kernels (built lazily)
_KERNELS = KernelCache()      # builders registered at the end of the module


def _get(name: str, dtype=None):
    return _KERNELS.get(name, dtype)


@ti.func
def sky_value(h16, idx, gshift, key, cdf: ti.template(), guide: ti.template(), value: ti.template(), adu0,
              tdt: ti.template()):
    """A sky pixel's ADU value (``tdt``) from its 16 random bits h16 (u64): the guide cell's value (``value``:
    adu0 + the guide's entry, -1 where a CDF step crosses the cell) in one load, else the inversion of
    :func:`dualsight.kernels.rng.inverse_table_bits` (more bits from ``key`` and the pixel index ``idx``)."""
    g = value[ti.cast(h16 >> ti.cast(gshift, ti.u64), ti.i32)]
    v = ti.cast(g, tdt)
    if g < 0:
        j = rng.inverse_table_bits(h16, 16, gshift, key, idx, cdf, guide)
        v = ti.cast(adu0 + ti.cast(j, ti.f64), tdt)
    return v


@ti.func
def value_bits(v, is_float: ti.template()):
    """A pixel value's unsigned bit pattern as u64 (the integer of a u16, the IEEE-754 pattern of an f32)."""
    b = ti.u64(0)
    if ti.static(is_float):
        b = ti.cast(ti.bit_cast(v, ti.u32), ti.u64)
    else:
        b = ti.cast(v, ti.u64)
    return b


@ti.func
def digest_term(v, idx, sky_bits, weights: ti.template(), is_float: ti.template()):
    """One pixel's term of the frame digest (:mod:`dualsight.kernels.digest`): (bits(v) - sky_bits) *
    splitmix64(idx) mod 2^64, v the pixel's value (u16, or f32 by its IEEE-754 pattern), idx (u64) its
    row-major index in the frame, splitmix64(idx) read from ``weights`` (:func:`digest_weights`: one load
    instead of the hash's two multiplications and three shifts; 0.2-0.4 ms instead of 0.8 per 1024 x 768 frame,
    one core)."""
    return (value_bits(v, is_float) - sky_bits) * weights[ti.cast(idx, ti.i64)]


def _build_finalize(dtype, digest: bool = False):
    """The stage-2 kernel (charge, noise, ADC) for ``dtype`` frames; ``digest=True``: the variant that also
    writes each row's digest sum (:func:`digest_term` over the row, mod 2^64) while the pixel is in a register,
    so the frame digest costs no second pass over the frame."""
    tdt = {np.dtype(np.uint16).str: ti.u16, np.dtype(np.float32).str: ti.f32}[np.dtype(dtype).str]
    is_float = np.dtype(dtype).kind == "f"

    @ti.kernel
    def finalize(buf: ti.types.ndarray(dtype=ti.f32, ndim=1), out: ti.types.ndarray(dtype=tdt, ndim=1),
                 dig: ti.types.ndarray(dtype=ti.u64, ndim=1), sky_bits: ti.u64,
                 wts: ti.types.ndarray(dtype=ti.u64, ndim=1), span: ti.types.ndarray(dtype=ti.i32, ndim=1),
                 use_span: ti.i32,
                 B: ti.i32, H: ti.i32, W: ti.i32,
                 seeds: ti.types.ndarray(dtype=ti.u64, ndim=1), hot_seed: ti.u64, use_hot_seed: ti.i32,
                 base_e: ti.f64, full_well: ti.f64, gain: ti.f64, bias: ti.f64, max_adu: ti.f64,
                 quantize: ti.i32, shot: ti.i32, read_e: ti.f64, hot_frac: ti.f64, hot_e: ti.f64,
                 cdf: ti.types.ndarray(dtype=ti.f64, ndim=1), guide: ti.types.ndarray(dtype=ti.i32, ndim=1),
                 use_table: ti.i32, stray: ti.i32, stray_e0: ti.f64, stray_gx: ti.f64, stray_gy: ti.f64,
                 tcdf: ti.types.ndarray(dtype=ti.f64, ndim=1), tguide: ti.types.ndarray(dtype=ti.i32, ndim=1),
                 toff: ti.types.ndarray(dtype=ti.i64, ndim=1), tm0: ti.i32, tinv: ti.f64,
                 acdf: ti.types.ndarray(dtype=ti.f64, ndim=1), aguide: ti.types.ndarray(dtype=ti.i32, ndim=1),
                 avalue: ti.types.ndarray(dtype=ti.i32, ndim=1),
                 use_adu: ti.i32, adu0: ti.f64, hot_log1m: ti.f64):
        # flat (B*H*W,) arrays: 3-D external-array stores cost ~2x more in Taichi 1.7 CPU code
        for b, r in ti.ndrange(B, H):  # (frame, row) outer loop, columns serial
            seed = seeds[b]
            hseed = seed
            if use_hot_seed != 0:
                hseed = hot_seed
            k_hot = rng.stream_key(hseed, rng.STREAM_HOT, 0)
            k_read = rng.stream_key(seed, rng.STREAM_READ, 0)
            k_shot0 = rng.stream_key(seed, rng.STREAM_SHOT, 0)
            k_shot1 = rng.stream_key(seed, rng.STREAM_SHOT, 1)
            k_frac = rng.stream_key(seed, rng.STREAM_SHOT, _FRAC_DRAW)
            k_sky = rng.stream_key(seed, rng.STREAM_SKY_ADU, 0)
            k_sky2 = rng.stream_key(seed, rng.STREAM_SKY_ADU, 1)
            gshift = 16                       # the guide table has 2^(16 - gshift) cells (a power of two)
            while (1 << (16 - gshift)) < aguide.shape[0]:
                gshift -= 1
            k_geo = rng.stream_key(hseed, rng.STREAM_HOT, 1)
            ntab = toff.shape[0] - 1
            row0 = ti.cast(r, ti.u64) * ti.cast(W, ti.u64)
            p0 = (b * H + r) * W
            # stray light of this row at column c: max(0, stray_row + stray_gx * (c + 0.5 - W/2))
            stray_row = stray_e0 + stray_gy * (ti.cast(r, ti.f64) + ti.f64(0.5) - ti.f64(0.5) * ti.cast(H, ti.f64))
            stray_x0 = ti.f64(0.5) - ti.f64(0.5) * ti.cast(W, ti.f64)
            acc = ti.u64(0)                   # the row's digest sum (digest variant)
            lo = 0                            # the row's star light lies in columns [lo, hi) (zero elsewhere:
            hi = W                            # the scratch is not read there)
            if use_span != 0:
                lo = span[2 * (b * H + r)]
                hi = span[2 * (b * H + r) + 1]
            if shot == 0 and read_e <= ti.f64(0.0) and hot_frac <= ti.f64(0.0) and stray == 0:
                # noise-free: empty pixels (most of a star field) take the precomputed sky value and
                # leave the scratch untouched; others go through the same ideal_adu arithmetic
                sky = ti.cast(ideal_adu(ti.f32(0.0), base_e, full_well, gain, bias, max_adu, quantize), tdt)
                for c in range(W):
                    s = ti.f32(0.0)
                    if c >= lo and c < hi:
                        s = buf[p0 + c]
                    v = sky
                    if s != ti.f32(0.0):
                        buf[p0 + c] = ti.f32(0.0)  # restore the all-zero scratch invariant
                        v = ti.cast(ideal_adu(s, base_e, full_well, gain, bias, max_adu, quantize), tdt)
                    out[p0 + c] = v
                    if ti.static(digest):
                        acc += digest_term(v, row0 + ti.cast(c, ti.u64), sky_bits, wts, is_float)
            else:
                lam_c = base_e  # Poisson constants cached for the last lambda (the sky's, mostly)
                cst = rng.poisson_consts(lam_c)
                # sparse hot pixels (hot_log1m < 0): the row's hot columns as a Bernoulli process drawn by its
                # geometric gaps, one draw per hot pixel (+ one per row) instead of one per pixel
                rkey = ti.cast(r, ti.u64) << ti.u64(32)
                n_hot = 0
                next_hot = W
                h_pair = ti.u64(0)            # the sky's 64-bit word of pixels 4m .. 4m + 3 (frame index)
                m_pair = ti.u64(0xFFFFFFFFFFFFFFFF)
                if hot_log1m < ti.f64(0.0):
                    next_hot = _next_hot(-1, W, hot_log1m, rng.u01_key(k_geo, rkey))
                # fast rows (the sky table, spans of star light, sparse or no hot pixels): pass 1 draws every pixel as sky in a tight
                # loop; pass 2 visits only the columns in the row's span of star light and the hot columns and
                # redraws those that are not sky (each pixel's value is a function of (seed, index) and its
                # inputs alone: the same frame as one pass).  Other rows: one pass over every column.
                fast = 0
                if use_adu != 0 and use_span != 0 and (hot_log1m < ti.f64(0.0) or hot_frac <= ti.f64(0.0)):
                    fast = 1
                c = 0
                if fast != 0:
                    if W % 4 == 0:                # rows start on a word's first pixel: one word per 4 pixels
                        for m4 in range(W // 4):
                            idx0 = row0 + ti.cast(4 * m4, ti.u64)
                            hw = rng.hash_key(k_sky, idx0 >> ti.u64(2))
                            for q in ti.static(range(4)):
                                idx = idx0 + ti.u64(q)
                                v = sky_value((hw >> ti.u64(48 - 16 * q)) & ti.u64(0xFFFF), idx, gshift, k_sky2,
                                              acdf, aguide, avalue, adu0, tdt)
                                out[p0 + 4 * m4 + q] = v
                                if ti.static(digest):
                                    acc += digest_term(v, idx, sky_bits, wts, is_float)
                    else:
                        for c1 in range(W):
                            idx = row0 + ti.cast(c1, ti.u64)
                            m = idx >> ti.u64(2)
                            if m != m_pair:
                                m_pair = m
                                h_pair = rng.hash_key(k_sky, m)
                            sh = ti.u64(48) - ti.u64(16) * (idx & ti.u64(3))
                            v = sky_value((h_pair >> sh) & ti.u64(0xFFFF), idx, gshift, k_sky2, acdf, aguide, avalue,
                                          adu0, tdt)
                            out[p0 + c1] = v
                            if ti.static(digest):
                                acc += digest_term(v, idx, sky_bits, wts, is_float)
                    c = ti.min(lo, next_hot)
                while c < W:
                    idx = row0 + ti.cast(c, ti.u64)
                    hot = 0
                    if hot_log1m < ti.f64(0.0):
                        if c == next_hot:
                            hot = 1
                            n_hot += 1
                            next_hot = _next_hot(c, W, hot_log1m, rng.u01_key(k_geo, rkey | ti.cast(n_hot, ti.u64)))
                    elif hot_frac > ti.f64(0.0):
                        if rng.u01_key(k_hot, idx) < hot_frac:
                            hot = 1
                    nxt = c + 1                   # pass 2 of a fast row: the next span or hot column
                    if fast != 0 and (nxt < lo or nxt >= hi):
                        nxt = next_hot
                        if c + 1 < lo:
                            nxt = ti.min(lo, next_hot)
                    s = ti.f32(0.0)
                    if c >= lo and c < hi:
                        s = buf[p0 + c]
                    if s != ti.f32(0.0):
                        buf[p0 + c] = ti.f32(0.0)
                    prev = sky_bits               # the digest term this pixel holds already (pass 1's, fast rows)
                    j = -1
                    if s == ti.f32(0.0) and hot == 0:
                        if fast != 0:
                            j = -2                # a sky pixel: pass 1 drew it
                        elif use_adu != 0:
                            # a sky pixel (no star light, not hot; use_adu implies no stray light): its ADU value
                            # by inversion of the tabulated CDF of shot + read noise + ADC (sky_adu_table)
                            # one 64-bit hash per 4 pixels (frame index 4m .. 4m + 3), 16 bits each, high bits
                            # first (rng.inverse_table_bits draws more bits in the rare cells a CDF step crosses)
                            m = idx >> ti.u64(2)
                            if m != m_pair:
                                m_pair = m
                                h_pair = rng.hash_key(k_sky, m)
                            sh = ti.u64(48) - ti.u64(16) * (idx & ti.u64(3))
                            h16 = (h_pair >> sh) & ti.u64(0xFFFF)
                            j = rng.inverse_table_bits(h16, 16, gshift, k_sky2, idx, acdf, aguide)
                    elif fast != 0 and ti.static(digest):
                        prev = value_bits(out[p0 + c], is_float)
                    if j >= 0:
                        v = ti.cast(adu0 + ti.cast(j, ti.f64), tdt)
                        out[p0 + c] = v
                        if ti.static(digest):
                            acc += digest_term(v, idx, sky_bits, wts, is_float)
                    elif j == -1:
                        e = ti.cast(s, ti.f64) + base_e
                        st = ti.f64(0.0)
                        sky_px = 0  # 1: only sky, dark current and stray light (for the stray tables)
                        if s == ti.f32(0.0):
                            sky_px = 1
                        if stray != 0:
                            st = ti.max(stray_row + stray_gx * (ti.cast(c, ti.f64) + stray_x0), ti.f64(0.0))
                            e += st
                        if hot != 0:
                            e += hot_e
                            sky_px = 0
                        if shot != 0:
                            k = ti.f64(-1.0)
                            if use_table != 0 and e == base_e:  # the sky's lambda: tabulated CDF
                                k = rng.poisson_table(rng.u01_key(k_shot0, idx), cdf, guide, 0, cdf.shape[0])
                            if k < ti.f64(0.0) and stray != 0 and sky_px != 0 and ntab > 0:
                                # stray light: Poisson(base + st) = Poisson(base + q step) (tabulated CDF of that
                                # grid value, q = floor(st / step)) + Poisson(st - q step) (inversion, its own draw;
                                # independent).  The remainder is < step (<= 1/16 e-): u <= 1 - d <= exp(-d) means 0
                                # without computing exp(-d), the same result as the full inversion.
                                q = ti.floor(st * tinv)
                                ti_ = ti.cast(q, ti.i32) - tm0
                                if ti_ >= 0 and ti_ < ntab:
                                    k = rng.poisson_table(rng.u01_key(k_shot0, idx), tcdf, tguide, toff[ti_], toff[ti_ + 1])
                                    d = st - q / tinv
                                    if k >= ti.f64(0.0) and d > ti.f64(0.0):
                                        u2 = rng.u01_key(k_frac, idx)
                                        if u2 > ti.f64(1.0) - d:
                                            k += rng.poisson_inversion(d, ti.exp(-d), u2, 60)
                            if k < ti.f64(0.0):
                                if e != lam_c:
                                    lam_c = e
                                    cst = rng.poisson_consts(e)
                                k = rng.poisson_keyed(e, cst, k_shot0, k_shot1, seed, rng.STREAM_SHOT, idx)
                            e = k
                        e = ti.min(e, full_well)
                        if read_e > ti.f64(0.0):
                            e += read_e * rng.normal_key(k_read, idx)
                        adu = e / gain + bias
                        if quantize != 0:
                            adu = ti.floor(adu + ti.f64(QUANT_EPS_ADU))
                        adu = ti.min(ti.max(adu, ti.f64(0.0)), max_adu)
                        v = ti.cast(adu, tdt)
                        out[p0 + c] = v
                        if ti.static(digest):
                            acc += digest_term(v, idx, prev, wts, is_float)
                    c = nxt
            if ti.static(digest):
                dig[b * H + r] = acc
    return finalize


_KERNELS.builders.update({"finalize": _build_finalize,
                          "finalize_digest": lambda dtype: _build_finalize(dtype, digest=True)})


_DIGEST_WEIGHTS: dict[int, np.ndarray] = {}


def digest_weights(n: int) -> np.ndarray:
    """splitmix64(0 .. n - 1) as (n,) uint64 (:func:`dualsight.kernels.digest.splitmix64`): the digest's pixel
    weights for frames of n pixels, read by the render kernel's digest variant; cached for the last two frame
    sizes (8 bytes per pixel: 6.3 MB for 1024 x 768)."""
    w = _DIGEST_WEIGHTS.get(n)
    if w is None:
        if len(_DIGEST_WEIGHTS) >= 2:
            _DIGEST_WEIGHTS.pop(next(iter(_DIGEST_WEIGHTS)))
        w = _DIGEST_WEIGHTS[n] = np.ascontiguousarray(splitmix64(np.arange(n, dtype=np.uint64)))
    return w


# ============================================================================ scratch buffer
class _Scratch:
    """One process-wide float32 signal buffer that is all zero between calls.

    The finalize pass zeroes every pixel right after reading it, so the buffer never needs a
    separate clearing pass and its pages stay mapped (no page faults on reuse).
    """

    def __init__(self):
        self.lock = threading.Lock()
        self.buf: np.ndarray | None = None

    def get(self, n: int) -> np.ndarray:
        if self.buf is None or self.buf.size < n:
            self.buf = None
            self.buf = np.zeros(n, dtype=np.float32)
        return self.buf[:n]

    def drop(self):
        self.buf = None


_scratch = _Scratch()


def release_scratch() -> None:
    """Free the cached float32 signal buffer (it is re-created on the next render)."""
    with _scratch.lock:
        _scratch.drop()


# ============================================================================ helpers
def check_star_arrays(x, y, flux_e, valid=None):
    """Validate and convert star lists: returns contiguous (x, y, flux float64, ok uint8), each (B, S).

    ``valid`` may be None (all valid) or a bool array broadcastable to (B, S).
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2:
        raise ValueError(f"x must have shape (B, S), got {x.shape}")
    y = np.asarray(y, dtype=np.float64)
    f = np.asarray(flux_e, dtype=np.float64)
    if y.shape != x.shape or f.shape != x.shape:
        raise ValueError(f"x, y, flux_e must share shape (B, S); got {x.shape}, {y.shape}, {f.shape}")
    if valid is None:
        ok = np.ones(x.shape, dtype=np.uint8)
    else:
        v = np.asarray(valid)
        if v.dtype != np.bool_:
            raise ValueError(f"valid must be a bool array, got dtype {v.dtype}")
        try:
            ok = np.broadcast_to(v, x.shape).astype(np.uint8)
        except ValueError:
            raise ValueError(f"valid must have shape {x.shape}, got {v.shape}") from None
    return (np.ascontiguousarray(x), np.ascontiguousarray(y), np.ascontiguousarray(f),
            np.ascontiguousarray(ok))


def false_star_lists(seeds: np.ndarray, width: int, height: int, cfg: SensorConfig):
    """The false stars of each case: (x, y, flux_e) each (B, F), F = cfg.false_stars_per_frame.

    Positions uniform over the frame, flux log-uniform in [false_star_flux_min_e, false_star_flux_max_e];
    drawn from the counter-based hash of (case seed, STREAM_FALSE_STAR, draw 0/1/2, star index).
    """
    n = cfg.false_stars_per_frame
    s = np.asarray(seeds, dtype=np.uint64)[:, None]
    k = np.arange(n, dtype=np.uint64)[None, :]
    fx = rng.uniform_np(s, rng.STREAM_FALSE_STAR, 0, k) * width
    fy = rng.uniform_np(s, rng.STREAM_FALSE_STAR, 1, k) * height
    lo, hi = math.log(cfg.false_star_flux_min_e), math.log(cfg.false_star_flux_max_e)
    ff = np.exp(lo + rng.uniform_np(s, rng.STREAM_FALSE_STAR, 2, k) * (hi - lo))
    return fx, fy, ff


def append_false_stars(x, y, f, ok, seeds, width, height, cfg: SensorConfig):
    """Star arrays with the case's false stars appended as extra columns (no-op if none)."""
    if cfg.false_stars_per_frame == 0:
        return x, y, f, ok
    fx, fy, ff = false_star_lists(seeds, width, height, cfg)
    cat = lambda a, b: np.ascontiguousarray(np.concatenate([a, b.astype(a.dtype)], axis=1))
    return cat(x, fx), cat(y, fy), cat(f, ff), cat(ok, np.ones(fx.shape, np.uint8))


def check_size(width, height):
    for name, v in (("width", width), ("height", height)):
        if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or not 1 <= int(v) <= 65536:
            raise ValueError(f"{name} must be an integer in [1, 65536], got {v!r}")
    if int(width) * int(height) > 1 << 30:
        raise ValueError(f"frame of {width} x {height} px is larger than 2^30 pixels")
    return int(width), int(height)


def prepare_stars(x, y, flux_e, valid, width, height, cfg, seeds):
    """Shared input handling of the renderers: validated arrays, false stars appended, uint64 seeds."""
    width, height = check_size(width, height)
    x, y, f, ok = check_star_arrays(x, y, flux_e, valid)
    B = x.shape[0]
    if seeds is None:
        if cfg.needs_seeds:
            raise ValueError("seeds (one uint64 per case) are required when noise or false stars are on")
        seeds = np.zeros(B, dtype=np.uint64)
    else:
        seeds = rng.as_seeds(seeds, B)
    x, y, f, ok = append_false_stars(x, y, f, ok, seeds, width, height, cfg)
    if x.shape[1] == 0:  # Taichi wants non-empty arrays: one invalid star
        x = np.zeros((B, 1)); y = np.zeros((B, 1)); f = np.zeros((B, 1)); ok = np.zeros((B, 1), np.uint8)
    return x, y, f, ok, seeds, width, height


# ============================================================================ public API
def render_star_fields(x, y, flux_e, valid, width: int, height: int, cfg: SensorConfig = SensorConfig(),
                       seeds=None, *, dtype=np.uint16, out: np.ndarray | None = None, camera=None,
                       attitude=None, psf: np.ndarray | None = None, digest: bool = False):
    """Render a batch of star-field frames (dense, full frame, all sensor effects).

    Parameters
    ----------
    x, y : (B, S) float, star positions in continuous pixel coordinates (col, row) from the top-left
        corner (the top-left pixel's centre is (0.5, 0.5)); stars may lie partly or fully off the image.
    flux_e : (B, S) float, total electrons of each star during the exposure
        (see :func:`~dualsight.kernels.sensor_config.flux_from_magnitude`).
    valid : (B, S) bool (or None = all); invalid, non-finite or non-positive-flux stars are skipped.
    width, height : frame size (px).
    cfg : :class:`~dualsight.kernels.sensor_config.SensorConfig`.
    seeds : (B,) uint64 per-case seeds; required when any random effect is on (else ignored).
    dtype : np.uint16 (default) or np.float32 output; both hold ADU (integers when cfg.quantize).
    out : optional preallocated (B, H, W) C-contiguous array of ``dtype`` to write into.
    camera : ``dualsight.scene.camera.Camera`` of the frames; needed when ``cfg.rate_deg_s`` (smear) or
        ``cfg.bright_objects`` is set (``cfg.needs_camera``), else ignored.
    attitude : (B, 3, 3) inertial -> camera rotation of each case; needed for ``cfg.bright_objects``.
    psf : the measured PSF, a (ny, nx) float64 array of unit sum (the fraction of a star's electrons per pixel,
        sampled on the sensor's pixels, odd sides <= 64 px, centred on its middle pixel); needed when
        ``cfg.psf_model == "image"`` (the scene layer reads the file: ``dualsight.scene.psf_file.sensor_psf``),
        else ignored.
    digest : also return each frame's 64-bit digest (:func:`dualsight.kernels.digest.frame_digest` with the
        sensor's empty-sky level ``cfg.empty_pixel_adu()`` in ``dtype`` as ``sky``), summed inside the render
        pass while each pixel is in a register (no second pass over the frames).

    Returns
    -------
    (B, H, W) images in ADU (see the module docstring for the pixel model); with ``digest``, the tuple
    (images, (B,) uint64 digests).

    Cost: one serial-per-case splat of each star's window plus one (frame, row) pass over every pixel
    (1024 x 768, one core: ~1 ms/frame noise-free, ~1.9 ms/frame CPU with shot and read noise, hot pixels and
    the digest on the two-pass tabulated sky path (noisy preset, 2-core VM under load 10-12), ~18 ms/frame with continuous ADU (``quantize=False``: per-effect samplers)).  Another PSF
    model or smear renders each star as several sub-sources (:mod:`dualsight.kernels.psf_models`), each
    within its own window: the defocus quadrature of the "realistic" preset (255 Gaussians per star) adds
    ~3 ms per frame of 13 stars, a smear multiplies that part by ~5 L (L px long).  Stray light is computed
    per pixel inside the same pass, its shot noise from tabulated CDFs (~3 ms/frame more).  For
    noise-free frames prefer ``dualsight.kernels.detect.render_and_detect_ideal``, which never touches
    the empty sky.  Memory: a process-wide float32 scratch of up to 2^26 pixels (256 MB) is kept zeroed
    between calls (batches are processed in chunks of that size); :func:`release_scratch` frees it.
    """
    x, y, f, ok, seeds, W, H = prepare_stars(x, y, flux_e, valid, width, height, cfg, seeds)
    dt = np.dtype(dtype)
    if dt not in (np.dtype(np.uint16), np.dtype(np.float32)):
        raise ValueError(f"dtype must be uint16 or float32, got {dt}")
    if dt == np.uint16 and cfg.bit_depth > 16:
        raise ValueError(f"uint16 output needs bit_depth <= 16, got {cfg.bit_depth}")
    B = x.shape[0]
    digests = np.zeros(B, np.uint64)
    if out is None:
        out = np.empty((B, H, W), dtype=dt)
    elif out.shape != (B, H, W) or out.dtype != dt or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous {dt} array of shape {(B, H, W)}, "
                         f"got {out.dtype} {out.shape}")
    if B == 0:
        return (out, digests) if digest else out
    fin = _get("finalize_digest" if digest else "finalize", dt)
    sky_bits = np.asarray(cfg.empty_pixel_adu()).astype(dt).reshape(1).view(np.uint32 if dt.kind == "f" else dt)
    sky_bits = np.uint64(sky_bits[0])
    hot_seed = cfg.hot_pixel_seed
    # Poisson CDF table of the sky level (dark + background), shared by most pixels; exact inversion
    use_table = cfg.shot_noise and 0.0 < cfg.base_e <= 1e6
    tcdf, tguide, toff, tm0, tinv = stray_tables(cfg, W, H)
    cdf, guide = rng.poisson_table_np(cfg.base_e) if use_table else (np.ones(1), np.zeros(1, np.int32))
    sky = None if cfg.has_stray_light else sky_adu_table(cfg)   # the sky pixels' ADU in one draw
    # hot pixels up to HOT_GEOMETRIC_MAX: by their geometric gaps along each row; above, one draw per pixel
    p_hot = cfg.hot_pixel_fraction
    hot_log1m = math.log1p(-p_hot) if 0.0 < p_hot <= HOT_GEOMETRIC_MAX else 0.0
    acdf, aguide, adu0 = sky if sky is not None else (np.ones(1), np.zeros(1, np.int32), 0.0)
    # the guide's resolved cells as ADU values (adu0 + entry: integers, quantised ADU), -1 where a step crosses
    avalue = np.ascontiguousarray(np.where(aguide >= 0, aguide + int(adu0), -1).astype(np.int32))
    src = None
    if cfg.psf_model != "gaussian" or cfg.needs_camera:  # sub-sources (psf_models); else the plain Gaussian splat
        src = psf_models.prepare_sources(x, y, f, ok, cfg, camera, attitude, psf)
    stray = (int(cfg.has_stray_light),) + tuple(float(v) for v in cfg.stray_light_e)
    chunk = max(1, min(B, MAX_CHUNK_PIXELS // (H * W)))  # frames per kernel call (bounded scratch, i32 indices)
    rows = np.zeros(chunk * H if digest else 1, np.uint64)   # the digest variant's row sums of a chunk
    wts = digest_weights(H * W) if digest else rows
    spans = np.empty((chunk if src is None else 1, H, 2), np.int32)
    with _scratch.lock:
        try:
            for b0 in range(0, B, chunk):  # loop over chunks of frames, not over pixels or stars
                sl = slice(b0, min(B, b0 + chunk))
                n = sl.stop - sl.start
                buf = _scratch.get(n * H * W)
                if src is None:   # Gaussian stars: each row's span of star light, the rest of the scratch unread
                    span = spans[:n]
                    span[:, :, 0], span[:, :, 1] = W, 0
                    star_psf.splat_stars(x[sl], y[sl], f[sl], ok[sl], buf.reshape(n, H, W), cfg.psf_sigma_px,
                                         cfg.psf_window_sigma, spans=span)
                else:
                    psf_models.splat_sources(src, sl, buf.reshape(n, H, W), cfg.psf_sigma_px)
                fin(buf, out[sl].reshape(-1), rows, sky_bits, wts, spans.reshape(-1), int(src is None), n, H, W,
                    seeds[sl], np.uint64(hot_seed or 0),
                    int(hot_seed is not None), float(cfg.base_e), float(cfg.full_well_e), float(cfg.gain_e_per_adu),
                    float(cfg.bias_adu), float(cfg.max_adu), int(cfg.quantize), int(cfg.shot_noise),
                    float(cfg.read_noise_e), float(cfg.hot_pixel_fraction), float(cfg.hot_pixel_e), cdf, guide,
                    int(use_table), *stray, tcdf, tguide, toff, tm0, tinv, acdf, aguide, avalue, int(sky is not None),
                    float(adu0), hot_log1m)
                if digest:
                    with np.errstate(over="ignore"):
                        digests[sl] = rows[:n * H].reshape(n, H).sum(axis=1, dtype=np.uint64)
        except BaseException:
            _scratch.drop()  # the zero invariant may be broken
            raise
    return (out, digests) if digest else out
