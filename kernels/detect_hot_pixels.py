"""Step 4 of the real-sensor detector (:mod:`dualsight.kernels.detect_local`, its docstring): each candidate's
brightest pixel, the hot-pixel / cosmic-ray test there, its noise and saturation flag, and whether it is kept.

:func:`screen_candidates` is the numpy stage (the reference); :func:`screen_candidates_compiled` the same as one
serial Taichi loop over the candidates (``fit_engine`` "taichi", the default): a frame has tens to hundreds of
candidates, so the numpy stage is ~40 calls of a few microseconds on small arrays (~0.1-0.2 ms per pass), the
loop a few microseconds of work after one launch.  Both read the same values and do the same float64 / float32
operations in the same order; they agree on every candidate of the test frames (tests/test_detect_hot_pixels.py).

Per candidate at pixel (r, c) of the matched-filtered SNR image (``Z``, its noise ``sig_f``; either at full
resolution or 2 x 2-binned, read at (min(r // b, Hz - 1), min(c // b, Wz - 1)) for bin size b):

* p = (r0, c0): the brightest pixel of the residual R in the candidate's 3 x 3 neighbourhood (within the frame;
  the first in raster order on a tie);
* peak R_p, m4 = the mean of p's in-frame 4-neighbours, the pixel noise sigma = max(1 / inv_p, noise floor);
* saturated when img_p >= sat;
* hot when t = R_p - r_max m4 > hot_pixel_k sigma sqrt(1 + r_max^2 / 4) and not saturated, with r_max = (1 +
  sharpness_tolerance) x :func:`~dualsight.kernels.detect_psf.sharpness_limit` (s) (the largest peak-to-4-neighbour
  ratio a pixel-integrated Gaussian of sigma s px gives);
* kept unless hot and Z at p without the spike's excess, Z_p - (R_p - m4) k00 / sigma_F,p, is at most
  ``k_sigma`` (k00: the filter kernel's centre tap, squared; a binned filter's divided by 4).
"""

import math

import numpy as np

from dualsight.kernels.detect_passes import pixel_type_name
from dualsight.kernels.detect_psf import psf_kernel_1d, sharpness_limit
from dualsight.kernels.taichi_runtime import KernelCache

__all__ = ["screen_candidates", "screen_candidates_compiled", "hot_test_constants"]

_OFF = np.array([(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1)])
"""The 3 x 3 neighbourhood's offsets (row, column), raster order."""


def hot_test_constants(s: float, cfg, spike_tap: float | None = None) -> tuple[float, float, float]:
    """(r_max, sqrt(1 + r_max^2 / 4), k00) of the hot-pixel test for PSF sigma ``s`` (px) and ``cfg`` (its
    ``sharpness_tolerance``); k00 = ``spike_tap`` when given (a binned filter's), else the squared centre tap of the
    matched filter of width s (:func:`~dualsight.kernels.detect_psf.psf_kernel_1d`)."""
    rmax = (1.0 + cfg.sharpness_tolerance) * sharpness_limit(s)
    if spike_tap is None:
        k0 = psf_kernel_1d(s)
        spike_tap = float(k0[len(k0) // 2] ** 2)
    return rmax, math.sqrt(1.0 + rmax * rmax / 4.0), float(spike_tap)


def screen_candidates(R, inv, img, pr, pc, Z, sig_f, sat, s, cfg, spike_tap=None):
    """The candidates' screening (module docstring), numpy.

    R, inv : (H, W) float32 residual (ADU) and inverse pixel noise (1/ADU); img : (H, W) the frame (ADU);
    pr, pc : (K,) int64 candidate pixels; Z, sig_f : indexable by (rows, cols) arrays at full-resolution pixel
    indices (float32 values; a binned image through a view that maps the indices); sat : saturation level (ADU)
    or None; s : PSF sigma (px); cfg : the detector's settings (``hot_pixel_k``, ``sharpness_tolerance``,
    ``noise_floor_adu``, ``k_sigma``).

    Returns (r0, c0) (K,) int64, noise (K,) float64 (ADU), saturated (K,) bool, hot (K,) bool, keep (K,) bool,
    in the candidates' order."""
    H, W = R.shape
    K = pr.size
    rr, cc = pr[:, None] + _OFF[:, 0], pc[:, None] + _OFF[:, 1]
    inside = (rr >= 0) & (rr < H) & (cc >= 0) & (cc < W)
    vals = np.where(inside, R[np.clip(rr, 0, H - 1), np.clip(cc, 0, W - 1)], -np.inf)
    best = vals.argmax(1)
    r0, c0 = pr + _OFF[best, 0], pc + _OFF[best, 1]
    at = lambda dr, dc: R[np.clip(r0 + dr, 0, H - 1), np.clip(c0 + dc, 0, W - 1)].astype(np.float64)
    peak = at(0, 0)
    # mean of the in-frame 4-neighbours (at an edge the clipped index would be the spike itself)
    n4 = ((r0 > 0).astype(np.float64) + (r0 < H - 1) + (c0 > 0) + (c0 < W - 1))
    m4 = (at(-1, 0) * (r0 > 0) + at(1, 0) * (r0 < H - 1) + at(0, -1) * (c0 > 0) + at(0, 1) * (c0 < W - 1)) / n4
    noise = np.maximum(1.0 / inv[r0, c0].astype(np.float64), cfg.noise_floor_adu)
    is_sat = img[r0, c0] >= sat if sat is not None else np.zeros(K, bool)     # saturation: at pixels, no map
    hot = np.zeros(K, bool)
    keep = np.ones(K, bool)
    if cfg.hot_pixel_k > 0:
        rmax, t_scale, k00 = hot_test_constants(s, cfg, spike_tap)
        stat = peak - rmax * m4
        hot = (stat > cfg.hot_pixel_k * noise * t_scale) & ~is_sat
        z_wo = Z[r0, c0] - (peak - m4) * k00 / sig_f[r0, c0]          # Z at the spike without its excess
        keep = ~hot | (z_wo > cfg.k_sigma)
    return r0, c0, noise, is_sat, hot, keep


def _build_screen(dtype):
    import taichi as ti   # here, not at import: the CLI imports this module without any kernel to run

    f64, f32 = ti.f64, ti.f32
    pt = getattr(ti, pixel_type_name(dtype))

    @ti.kernel
    def screen(R: ti.types.ndarray(dtype=f32, ndim=2), inv: ti.types.ndarray(dtype=f32, ndim=2),
               img: ti.types.ndarray(dtype=pt, ndim=2), pr: ti.types.ndarray(dtype=ti.i64, ndim=1),
               pc: ti.types.ndarray(dtype=ti.i64, ndim=1), Z: ti.types.ndarray(dtype=f32, ndim=2),
               invz: ti.types.ndarray(dtype=f32, ndim=2), row: ti.types.ndarray(dtype=f32, ndim=1),
               col: ti.types.ndarray(dtype=f32, ndim=1), ratio: f32, b: ti.i32, sat: f64, floor: f64, hot_k: f64,
               rmax: f64, t_scale: f64, k00: f64, k_sigma: f64, pos: ti.types.ndarray(dtype=ti.i64, ndim=2),
               noise: ti.types.ndarray(dtype=f64, ndim=1), flags: ti.types.ndarray(dtype=ti.u8, ndim=2)):
        H, W = R.shape[0], R.shape[1]
        Hz, Wz = Z.shape[0], Z.shape[1]
        ti.loop_config(serialize=True)
        for k in range(pr.shape[0]):
            r = ti.cast(pr[k], ti.i32)
            c = ti.cast(pc[k], ti.i32)
            best = -f64(math.inf)
            r0, c0 = r, c
            first = 1
            for dr in ti.static(range(-1, 2)):          # raster order; the first maximum wins (numpy argmax)
                for dc in ti.static(range(-1, 2)):
                    rr = r + dr
                    cc = c + dc
                    v = -f64(math.inf)
                    if 0 <= rr < H and 0 <= cc < W:
                        v = ti.cast(R[rr, cc], f64)
                    if first == 1 or v > best:
                        best = v
                        r0 = rr
                        c0 = cc
                        first = 0
            up = ti.cast(r0 > 0, f64)
            dn = ti.cast(r0 < H - 1, f64)
            lf = ti.cast(c0 > 0, f64)
            rt = ti.cast(c0 < W - 1, f64)
            peak = ti.cast(R[r0, c0], f64)
            n4 = up + dn + lf + rt
            m4 = (ti.cast(R[ti.max(r0 - 1, 0), c0], f64) * up + ti.cast(R[ti.min(r0 + 1, H - 1), c0], f64) * dn
                  + ti.cast(R[r0, ti.max(c0 - 1, 0)], f64) * lf + ti.cast(R[r0, ti.min(c0 + 1, W - 1)], f64) * rt) / n4
            sig = ti.max(f64(1.0) / ti.cast(inv[r0, c0], f64), floor)
            is_sat = ti.cast(img[r0, c0], f64) >= sat
            hot = 0
            keep = 1
            if hot_k > 0:
                stat = peak - rmax * m4
                if stat > hot_k * sig * t_scale and not is_sat:
                    hot = 1
                    rz = ti.min(r0 // b, Hz - 1)
                    cz = ti.min(c0 // b, Wz - 1)
                    sf = ratio * row[rz] * col[cz] / invz[rz, cz]          # Z's noise at p, float32
                    z_wo = ti.cast(Z[rz, cz], f64) - (peak - m4) * k00 / ti.cast(sf, f64)
                    if not z_wo > k_sigma:
                        keep = 0
            pos[k, 0] = r0
            pos[k, 1] = c0
            noise[k] = sig
            flags[k, 0] = ti.cast(is_sat, ti.u8)
            flags[k, 1] = ti.cast(hot, ti.u8)
            flags[k, 2] = ti.cast(keep, ti.u8)

    return screen


_KERNELS = KernelCache({"screen": _build_screen})      # built on first use


def screen_candidates_compiled(R, inv, img, pr, pc, Z, invz, row, col, ratio, b, sat, s, cfg, spike_tap=None):
    """:func:`screen_candidates` as one compiled loop (same returns).  ``Z`` ((Hz, Wz) float32) is the filtered
    SNR image at full resolution (``b`` = 1) or 2 x 2-binned (``b`` = 2), read at (min(r // b, Hz - 1),
    min(c // b, Wz - 1)); its noise there is ``ratio`` x ``row``[rz] x ``col``[cz] / ``invz``[rz, cz] (float32:
    :class:`~dualsight.kernels.detect_candidates.FilteredNoise`'s fields).  ``img`` of a dtype the kernels read
    (:func:`~dualsight.kernels.detect_passes.pixel_dtype_supported`; the caller checks)."""
    K = int(pr.size)
    pos = np.empty((K, 2), np.int64)
    noise = np.empty(K)
    flags = np.zeros((K, 3), np.uint8)
    if K:
        rmax, t_scale, k00 = hot_test_constants(s, cfg, spike_tap) if cfg.hot_pixel_k > 0 else (0.0, 0.0, 0.0)
        _KERNELS.get("screen", img.dtype)(
            np.ascontiguousarray(R, np.float32), np.ascontiguousarray(inv, np.float32), np.ascontiguousarray(img),
            np.ascontiguousarray(pr, np.int64), np.ascontiguousarray(pc, np.int64), np.ascontiguousarray(Z, np.float32),
            np.ascontiguousarray(invz, np.float32), np.ascontiguousarray(row, np.float32),
            np.ascontiguousarray(col, np.float32), float(ratio), int(b), math.inf if sat is None else float(sat),
            float(cfg.noise_floor_adu), float(cfg.hot_pixel_k), float(rmax), float(t_scale), float(k00),
            float(cfg.k_sigma), pos, noise, flags)
    f = flags.view(bool)
    return pos[:, 0], pos[:, 1], noise, f[:, 0], f[:, 1], f[:, 2]

