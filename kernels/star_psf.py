"""Star-field rendering, stage 1: exact pixel-integrated Gaussian PSFs splatted into a float32 signal buffer.

Signal of pixel (r, c) of case b, in electrons (coordinates as docs/architecture.md: pixel (r, c) covers
[c, c+1) x [r, r+1), centre (c + 0.5, r + 0.5))::

    S = sum_s  F_s * [Phi((c+1-x_s)/sigma) - Phi((c-x_s)/sigma)] * [Phi((r+1-y_s)/sigma) - Phi((r-y_s)/sigma)]

The PSF is a circular Gaussian of standard deviation sigma integrated exactly over each pixel's area (Phi is
the standard normal CDF), evaluated in a window of half-width ``ceil(psf_window_sigma * sigma + 1)`` pixels
around the star's pixel.  Stars are added in star order, one case per thread (no atomics), so a case's float
sums do not depend on scheduling.  The sensor stage (:mod:`dualsight.kernels.starfield`) turns the signal into
ADU; the sparse detector (:func:`dualsight.kernels.detect.render_and_detect_ideal`) reuses
:func:`star_window` and :func:`splat_star` on small patches.
"""

import math

import numpy as np
import taichi as ti

from dualsight.kernels.taichi_runtime import KernelCache

__all__ = ["erfc", "phi", "star_window", "splat_star", "splat_stars"]

_INV_SQRT2 = 1.0 / math.sqrt(2.0)
_KERNELS = KernelCache()      # builders registered below


@ti.func
def erfc(x):
    """Complementary error function, f64, fractional error < 1.2e-7 everywhere.

    Chebyshev fit of Press et al., Numerical Recipes (2nd ed., section 6.2, ``erfcc``).
    """
    z = ti.abs(x)
    t = ti.f64(1.0) / (ti.f64(1.0) + ti.f64(0.5) * z)
    p = ti.f64(0.17087277)
    p = ti.f64(-0.82215223) + t * p
    p = ti.f64(1.48851587) + t * p
    p = ti.f64(-1.13520398) + t * p
    p = ti.f64(0.27886807) + t * p
    p = ti.f64(-0.18628806) + t * p
    p = ti.f64(0.09678418) + t * p
    p = ti.f64(0.37409196) + t * p
    p = ti.f64(1.00002368) + t * p
    ans = t * ti.exp(-z * z - ti.f64(1.26551223) + t * p)
    if x < ti.f64(0.0):
        ans = ti.f64(2.0) - ans
    return ans


@ti.func
def phi(z):
    """Standard normal CDF Phi(z) = erfc(-z / sqrt 2) / 2 (f64)."""
    return ti.f64(0.5) * erfc(-z * ti.f64(_INV_SQRT2))


@ti.func
def star_window(xc, yc, flux, ok, sigma, wsig, width, height):
    """Pixel window of one star: (c0, c1, r0, r1), half-open, clipped to the image.

    Half-width R = ceil(wsig * sigma + 1) around the star's pixel (floor(xc), floor(yc)).
    Returns an empty window (c1 <= c0) for invalid, non-finite, non-positive or off-image stars.
    """
    c0 = 0
    c1 = 0
    r0 = 0
    r1 = 0
    lim = ti.f64(1.0e7)
    # the comparisons are False for NaN, so NaN coordinates or fluxes give an empty window
    if ok != 0 and flux > ti.f64(0.0) and flux < ti.f64(1.0e300) and ti.abs(xc) < lim and ti.abs(yc) < lim:
        R = ti.cast(ti.ceil(wsig * sigma + ti.f64(1.0)), ti.i32)
        ci = ti.cast(ti.floor(xc), ti.i32)
        ri = ti.cast(ti.floor(yc), ti.i32)
        c0 = ti.max(ci - R, 0)
        c1 = ti.min(ci + R + 1, width)
        r0 = ti.max(ri - R, 0)
        r1 = ti.min(ri + R + 1, height)
        if c1 <= c0 or r1 <= r0:
            c0 = 0
            c1 = 0
            r0 = 0
            r1 = 0
    return c0, c1, r0, r1


@ti.func
def splat_star(buf: ti.template(), b, base, pitch, pr0, pc0, flat: ti.template(), xc, yc, flux, sigma,
               c0, c1, r0, r1):
    """Add one star's pixel-integrated Gaussian to ``buf`` over the window [c0,c1) x [r0,r1).

    flat=False: ``buf`` is (B, H, W) and pixel (r, c) is ``buf[b, r, c]``.
    flat=True: ``buf`` is 1-D and pixel (r, c) is ``buf[base + (r - pr0) * pitch + (c - pc0)]``.
    Each pixel gets f32(flux * fy * fx) with fx, fy erf differences in f64 (CDF carried between edges).
    Not atomic: the caller must own the frame/patch (one thread per case or per patch).
    """
    inv = ti.f64(1.0) / sigma
    py_lo = phi((ti.cast(r0, ti.f64) - yc) * inv)
    for r in range(r0, r1):
        py_hi = phi((ti.cast(r + 1, ti.f64) - yc) * inv)
        fy = flux * (py_hi - py_lo)
        py_lo = py_hi
        px_lo = phi((ti.cast(c0, ti.f64) - xc) * inv)
        for c in range(c0, c1):
            px_hi = phi((ti.cast(c + 1, ti.f64) - xc) * inv)
            v = ti.cast(fy * (px_hi - px_lo), ti.f32)
            px_lo = px_hi
            if ti.static(flat):
                i = base + (r - pr0) * pitch + (c - pc0)
                buf[i] = buf[i] + v
            else:
                buf[b, r, c] = buf[b, r, c] + v


def _build_splat(_dtype=None, spans: bool = False):
    """The splat kernel; ``spans=True``: the variant that also widens each row's span of written columns,
    ``span[b, r] = (min c0, max c1)`` over the windows covering row r (the caller sets it to (W, 0) first)."""
    @ti.kernel
    def splat(x: ti.types.ndarray(dtype=ti.f64, ndim=2), y: ti.types.ndarray(dtype=ti.f64, ndim=2),
              flux: ti.types.ndarray(dtype=ti.f64, ndim=2), ok: ti.types.ndarray(dtype=ti.u8, ndim=2),
              buf: ti.types.ndarray(dtype=ti.f32, ndim=3), sigma: ti.f64, wsig: ti.f64,
              span: ti.types.ndarray(dtype=ti.i32, ndim=3)):
        W = buf.shape[2]
        H = buf.shape[1]
        for b in range(x.shape[0]):  # parallel over cases; stars of a case in order (deterministic sums)
            for s in range(x.shape[1]):
                c0, c1, r0, r1 = star_window(x[b, s], y[b, s], flux[b, s], ti.cast(ok[b, s], ti.i32),
                                             sigma, wsig, W, H)
                if c1 > c0:
                    splat_star(buf, b, 0, 0, 0, 0, False, x[b, s], y[b, s], flux[b, s], sigma, c0, c1, r0, r1)
                    if ti.static(spans):    # one thread per case: no other thread touches span[b]
                        for r in range(r0, r1):
                            span[b, r, 0] = ti.min(span[b, r, 0], c0)
                            span[b, r, 1] = ti.max(span[b, r, 1], c1)
    return splat


_KERNELS.builders.update({"splat": _build_splat, "splat_spans": lambda dtype: _build_splat(dtype, spans=True)})


def splat_stars(x, y, flux, ok, buf, sigma_px: float, window_sigma: float, spans: np.ndarray | None = None) -> None:
    """Add the pixel-integrated Gaussian PSFs of B cases' stars to ``buf`` (in place).

    x, y : (B, S) float64 star positions (px, continuous coordinates from the image corner).
    flux : (B, S) float64 electrons per star.  ok : (B, S) uint8, 0 = skip the star.
    buf : (B, H, W) float32 signal (e-), C-contiguous.
    sigma_px : PSF standard deviation (px); window_sigma : window half-width in sigma (+1 px).
    spans : optional (B, H, 2) int32, C-contiguous: each row's columns [spans[b, r, 0], spans[b, r, 1]) are
        widened to cover every window written in that row (set them to (W, 0), empty, before the call): outside
        its span a row of ``buf`` is left as it was, so the sensor stage need not read it there.
    """
    if spans is None:
        _KERNELS.get("splat")(x, y, flux, ok, buf, float(sigma_px), float(window_sigma),
                              np.zeros((1, 1, 2), np.int32))
    else:
        _KERNELS.get("splat_spans")(x, y, flux, ok, buf, float(sigma_px), float(window_sigma), spans)
