"""Tables of the star renderer's noise (:mod:`dualsight.kernels.starfield`): the Poisson CDFs of the
stray-light grid values, and the exact distribution of a sky pixel's ADU value (shot + read noise + ADC floor
and clips) that the render kernel inverts with one uniform draw.  Built once per sensor (cached), in numpy."""

import functools
import math

import numpy as np

from dualsight.kernels import rng
from dualsight.kernels.sensor_config import QUANT_EPS_ADU, SensorConfig

MAX_STRAY_TABLE_ENTRIES = 1 << 21  # Poisson CDF entries tabulated for stray light (24 MB at most)
MAX_SKY_ADU_WORK = 1 << 19  # (Poisson terms) x (ADU values) evaluated for the sky's ADU table (~0.1 s, once)
_SKY_ADU_SIGMAS = 12.0  # the sky ADU table spans the charge range +- 12 read-noise sigmas (Phi(-12) = 1.8e-33)


@functools.lru_cache(maxsize=8)
def _stray_tables_for(base_e: float, m0: int, m1: int, step: float):
    parts = [rng.poisson_table_np(base_e + m * step) for m in range(m0, m1 + 1)]  # per grid value, not per pixel
    off = np.zeros(len(parts) + 1, np.int64)
    np.cumsum([len(c) for c, _ in parts], out=off[1:])
    return (np.ascontiguousarray(np.concatenate([c for c, _ in parts])),
            np.ascontiguousarray(np.concatenate([g for _, g in parts])), off)


def stray_tables(cfg: SensorConfig, W: int, H: int):
    """Poisson CDF tables of the sky pixels' lambdas (e-) under stray light in a W x H px frame, on a grid
    lambda = base_e + m * step, m = m0 .. floor(max stray / step) over the stray plane's range in the frame:
    (cdf (N,) float64, guide (N,) int32: the tables one after another, each as
    :func:`dualsight.kernels.rng.poisson_table_np` gives it; offsets (M + 1,) int64: table m0 + j is
    [offsets[j], offsets[j + 1]); m0 int; 1 / step float, e-^-1), the stray-light tables of the render kernel
    (:func:`dualsight.kernels.starfield.render_star_fields`).  The step is the finest of 1/16, 1/4, 1 e- whose
    tables hold at most MAX_STRAY_TABLE_ENTRIES entries (finer grids cost more in cache misses than they save:
    measured on 1024 x 768 frames, 1/16 e- adds ~3 ms/frame to the plain sky's table sampler, 1/64 and 1 e- ~35);
    none (one dummy entry) when shot noise or stray light is off or even 1 e- is too fine (then every pixel takes
    the PTRS sampler)."""
    none = (np.ones(1), np.zeros(1, np.int32), np.zeros(1, np.int64), 0, 1.0)
    if not (cfg.shot_noise and cfg.has_stray_light):
        return none
    e0, gx, gy = cfg.stray_light_e
    corners = [max(0.0, e0 + gx * (cx - 0.5 * W) + gy * (ry - 0.5 * H)) for cx in (0.5, W - 0.5) for ry in (0.5, H - 0.5)]
    lam_hi = cfg.base_e + max(corners) + 1.0
    per_table = lam_hi + 12.0 * math.sqrt(lam_hi) + 31.0
    if lam_hi > 1e6:
        return none
    for inv_step in (16, 4, 1):
        m0, m1 = math.floor(min(corners) * inv_step), math.floor(max(corners) * inv_step)
        if (m1 - m0 + 1) * per_table <= MAX_STRAY_TABLE_ENTRIES:
            cdf, guide, off = _stray_tables_for(float(cfg.base_e), int(m0), int(m1), 1.0 / inv_step)
            return cdf, guide, off, int(m0), float(inv_step)
    return none


_erfc = np.frompyfunc(math.erfc, 1, 1)


SKY_U_CELLS = 1 << 16
"""The finalize kernel draws a sky pixel's uniform 16 bits at a time (kernels/starfield.py, rng.inverse_table_bits):
its guide table may have at most 2^16 cells, so a table has at most 2^16 entries (else no table)."""


@functools.lru_cache(maxsize=8)
def _sky_adu_table_for(base_e: float, shot: bool, read_e: float, full_well: float, gain: float, bias: float,
                       max_adu: float):
    """(cdf, guide, a0) of the ADU value of a sky pixel, or None when too costly; see :func:`sky_adu_table`."""
    if shot and base_e > 0.0:
        K = int(base_e + 12.0 * math.sqrt(base_e) + 30.0)   # as rng.poisson_table_np: tail beyond < 1e-20
        k = np.arange(K, dtype=np.float64)
        logp = -base_e + np.concatenate([[0.0], np.cumsum(math.log(base_e) - np.log(k[1:]))])
        p = np.exp(logp)
        keep = p > 0.0
        k, p = k[keep], p[keep]
    else:
        k, p = np.array([base_e if not shot else 0.0]), np.ones(1)
    e = np.minimum(k, full_well)                              # the kernel: e = min(e, full_well)
    if read_e <= 0.0:   # ADU a function of the charge: the kernel's own f64 arithmetic
        adu = np.minimum(np.maximum(np.floor(e / gain + bias + QUANT_EPS_ADU), 0.0), max_adu)
        a0 = float(adu.min())
        pa = np.bincount((adu - a0).astype(np.int64), weights=p)
        cdf = np.cumsum(pa)
    else:
        half = _SKY_ADU_SIGMAS * read_e / gain
        lo = max(0.0, math.floor(e.min() / gain + bias - half) - 1.0)
        hi = min(max_adu, math.ceil(e.max() / gain + bias + half) + 1.0)
        if lo > hi or (hi - lo + 1) * k.size > MAX_SKY_ADU_WORK:
            return None
        a = np.arange(lo, hi + 1.0)
        # P(ADU <= a) = P(e + R z < (a + 1 - bias - eps) g) = sum_k p_k Phi(((a + 1 - bias - eps) g - e_k) / R)
        # for a < max_adu (the clip at 0 ADU is included: every y < 1 floors to <= 0); 1 at max_adu
        zc = (e[None, :] - (a[:, None] + 1.0 - bias - QUANT_EPS_ADU) * gain) / (read_e * math.sqrt(2.0))
        cdf = (0.5 * _erfc(zc).astype(np.float64)) @ p         # Phi(x) = erfc(-x / sqrt 2) / 2
        cdf[a >= max_adu] = 1.0
        a0 = float(lo)
    # a direct guide table (Chen & Asau 1974) of 16 cells per entry: ~94 % of the cells hold no CDF step and give
    # the ADU in one load (rng.inverse_table_bits); at most 2^16 cells, as the kernel draws 16-bit uniforms
    if cdf.size > SKY_U_CELLS:
        return None
    return np.ascontiguousarray(cdf), rng.inverse_table_np(cdf, min(16, SKY_U_CELLS // cdf.size)), a0


def sky_adu_table(cfg: SensorConfig):
    """Tabulated CDF of the final ADU value of a sky pixel (no star light, not hot, no stray light):
    (cdf (A,) float64, guide (A,) int32, a0) with cdf[j] = P(ADU <= a0 + j), or None (no table: the pixel goes
    through the per-effect samplers).

    The pixel model of the module docstring with S = 0: e = min(Poisson(base_e), full_well) (base_e itself
    without shot noise), e + read_noise * N(0, 1), ADU = clip(floor(e / gain + bias + 1e-9), 0, max_adu).  Its
    distribution is exactly P(ADU <= a) = sum_k P(e = k) Phi(((a + 1 - bias - 1e-9) gain - k) / read_noise)
    (read noise on), or the ADU of each charge by the kernel's own arithmetic (read noise off): one uniform
    inverted through this table replaces the Poisson and the normal draw of every sky pixel (most of a star
    field), with no transcendental call per pixel.  The table spans the charges' range +- 12 read-noise
    sigmas (the mass beyond, Phi(-12) ~ 2e-33, is below the resolution of the 53-bit uniforms).  Only for
    quantised ADU (continuous ADU have no finite table) and when the table costs at most
    MAX_SKY_ADU_WORK normal-CDF evaluations; built once per sensor (cached).
    """
    if not cfg.quantize or not (cfg.shot_noise or cfg.read_noise_e > 0.0) or cfg.base_e > 1e6:
        return None
    return _sky_adu_table_for(float(cfg.base_e), bool(cfg.shot_noise), float(cfg.read_noise_e),
                              float(cfg.full_well_e), float(cfg.gain_e_per_adu), float(cfg.bias_adu),
                              float(cfg.max_adu))
