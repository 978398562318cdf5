"""The compiled PSF fit (``kernels/detect_psf_fit.py``, Taichi) against the numpy fit (``kernels/detect_psf.py``,
itself held to the Cramér-Rao bound and the least-squares minimum in tests/test_detect_real.py) and against the
true positions of noise-free stars (math.erf pixel integrals, independent of both)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dualsight.kernels.detect_psf import fit_psf
from dualsight.kernels.detect_psf_fit import fit_psf_compiled


def _Phi(z):
    return 0.5 * (1.0 + math.erf(z / math.sqrt(2.0)))


def _stamps(K, h, s, flux, noise, rng, bg=3.0):
    """(stamps, truth x, y, top-left r0, c0) of K stars (pixel-integrated Gaussians by math.erf) on (2h+1)^2 px."""
    n = 2 * h + 1
    r0 = rng.integers(100, 900, K)
    c0 = rng.integers(100, 900, K)
    x = c0 + h + rng.uniform(0, 1, K)
    y = r0 + h + rng.uniform(0, 1, K)
    st = np.empty((K, n, n))
    for k in range(K):
        px = np.array([_Phi((c0[k] + j + 1 - x[k]) / s[k]) - _Phi((c0[k] + j - x[k]) / s[k]) for j in range(n)])
        py = np.array([_Phi((r0[k] + i + 1 - y[k]) / s[k]) - _Phi((r0[k] + i - y[k]) / s[k]) for i in range(n)])
        st[k] = flux[k] * np.outer(py, px) + bg
    st += rng.normal(0, 1, st.shape) * noise[:, None, None]
    return st, x, y, r0, c0


@pytest.mark.parametrize("fit_sigma", [False, True])
@pytest.mark.parametrize("gain", [None, 2.0])
def test_compiled_fit_is_the_numpy_fit(fit_sigma, gain):
    """Noisy stars (SNR 5-300), some pixels unusable (weight 0), starts off by up to 0.4 px: the same converged
    positions, fluxes, backgrounds, widths (to 1e-9 px / relative 1e-9), the same ok flags, covariances to 1e-6."""
    rng = np.random.default_rng([4, int(fit_sigma), int(gain or 0)])
    K, h = 300, 3
    s = rng.uniform(0.6, 1.4, K)
    flux = np.exp(rng.uniform(math.log(30), math.log(3000), K))
    noise = rng.uniform(1.0, 4.0, K)
    st, x, y, r0, c0 = _stamps(K, h, s, flux, noise, rng)
    w0 = (rng.random(st.shape) > 0.05).astype(np.float64)
    x0, y0 = x + rng.uniform(-0.4, 0.4, K), y + rng.uniform(-0.4, 0.4, K)
    s0 = s * rng.uniform(0.8, 1.2, K) if fit_sigma else s
    a = fit_psf(st, w0, r0, c0, x0, y0, s0, noise, gain, fit_sigma=fit_sigma)
    b = fit_psf_compiled(st, w0, r0, c0, x0, y0, s0, noise, gain, fit_sigma=fit_sigma)
    assert np.array_equal(a[6], b[6]) and a[6].mean() > 0.9
    for i in range(5):
        np.testing.assert_allclose(b[i], a[i], rtol=1e-9, atol=1e-9)
    ok = a[6]
    np.testing.assert_allclose(b[5][ok], a[5][ok], rtol=1e-6, atol=1e-12)


def test_compiled_fit_finds_noise_free_stars_and_their_width():
    """Noise-free stars (math.erf pixel integrals, flat background): positions within 2e-3 px of the truth (the
    fit stops within ~1e-3 px of its minimum), the width within 1e-3 px when fitted, flux within 0.1 %."""
    rng = np.random.default_rng(9)
    K, h = 60, 3
    s = rng.uniform(0.6, 1.3, K)
    flux = rng.uniform(500, 5000, K)
    st, x, y, r0, c0 = _stamps(K, h, s, flux, np.zeros(K), rng)
    w0 = np.ones_like(st)
    for fit_sigma in (False, True):
        s0 = s if not fit_sigma else np.full(K, 1.0)
        xf, yf, A, b, sf, cov, ok = fit_psf_compiled(st, w0, r0, c0, x + 0.3, y - 0.2, s0, np.full(K, 1.0), None,
                                                     fit_sigma=fit_sigma)
        assert ok.all()
        assert np.abs(xf - x).max() < 2e-3 and np.abs(yf - y).max() < 2e-3
        assert np.abs(A / flux - 1).max() < 1e-3 and np.abs(b - 3.0).max() < 0.05
        if fit_sigma:
            assert np.abs(sf - s).max() < 1e-3


def test_large_stamps_go_to_the_numpy_fit():
    """Stamps over MAX_STAMP a side: the numpy fit's answer, bit for bit."""
    from dualsight.kernels.detect_psf_fit import MAX_STAMP

    rng = np.random.default_rng(2)
    h = MAX_STAMP // 2 + 1
    st, x, y, r0, c0 = _stamps(3, h, np.full(3, 3.0), np.full(3, 1e4), np.full(3, 2.0), rng)
    w0 = np.ones_like(st)
    args = (st, w0, r0, c0, x, y, np.full(3, 3.0), np.full(3, 2.0), None)
    a, b = fit_psf(*args), fit_psf_compiled(*args)
    for u, v in zip(a, b):
        np.testing.assert_array_equal(u, v)


def test_the_fit_engine_is_a_setting_and_numpy_starts_no_taichi():
    """fit_engine "numpy" starts no Taichi; "auto" (the default, run as "taichi" by the kernel) gives the same stars at positions within 1e-6 px,
    fluxes within 1e-6 relative, the same measured PSF width to 1e-6 px (the fits agree to ~1e-12 px; the tiles'
    last clipping window sums in float64 there, float32 in numpy: levels differ at float32 rounding, positions by
    ~1e-7 px).  (In a fresh process: the test process may run Taichi already.)"""
    import subprocess
    import sys

    code = (
        "import numpy as np\n"
        "from dualsight.kernels.detect_local import LocalDetectConfig, detect_real\n"
        "from dualsight.kernels.taichi_runtime import is_initialised\n"
        "rng = np.random.default_rng(3)\n"
        "img = rng.normal(100, 3, (256, 320))\n"
        "yy, xx = np.mgrid[0:256, 0:320]\n"
        "for cx, cy, f in zip(rng.uniform(10, 310, 40), rng.uniform(10, 246, 40), rng.uniform(300, 5000, 40)):\n"
        "    img += f * np.exp(-((xx + 0.5 - cx) ** 2 + (yy + 0.5 - cy) ** 2) / (2 * 0.8 ** 2)) / (2 * np.pi * 0.64)\n"
        "img = np.rint(img).astype(np.uint16)[None]\n"
        "a = detect_real(img, LocalDetectConfig(fit_engine='numpy'))\n"
        "started = is_initialised()\n"
        "b = detect_real(img, LocalDetectConfig())\n"
        "print(started, is_initialised(), LocalDetectConfig().engine, len(a), len(b), float(np.abs(a.x - b.x).max()),"
        " float(np.abs(a.y - b.y).max()), float(np.abs(a.flux / b.flux - 1).max()), float(a.psf_sigma_px[0]),"
        " float(b.psf_sigma_px[0]))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    started, started_b, default, na, nb, dx, dy, df, sa, sb = r.stdout.split()
    assert started == "False" and started_b == "True" and default == "taichi"
    assert na == nb and int(na) >= 30
    assert float(dx) < 1e-6 and float(dy) < 1e-6 and float(df) < 1e-6 and abs(float(sa) - float(sb)) < 1e-6


def _frame_with_stars(rng, H=96, W=128, K=40, s=0.9, sat=None):
    """A 16-bit-like float32 residual frame of K pixel-integrated Gaussian stars (math.erf; some within 2 px of the
    edges) on noise 2 ADU, their true positions, and the image (the residual + 100 ADU)."""
    x = np.concatenate([rng.uniform(0.6, 2.0, 4), rng.uniform(W - 2.0, W - 0.6, 4), rng.uniform(3, W - 3, K - 8)])
    y = np.concatenate([rng.uniform(3, H - 3, 8), rng.uniform(3, H - 3, K - 8)])
    y[:2] = rng.uniform(0.6, 2.0, 2)
    flux = rng.uniform(300, 5000, K)
    cols = np.arange(W + 1)
    rows = np.arange(H + 1)
    R = np.zeros((H, W))
    for k in range(K):
        px = np.diff([_Phi((c - x[k]) / s) for c in cols])
        py = np.diff([_Phi((r - y[k]) / s) for r in rows])
        R += flux[k] * np.outer(py, px)
    R = (R + rng.normal(0, 2.0, R.shape)).astype(np.float32)
    return R, (R + 100).astype(np.float32), x, y, flux


@pytest.mark.parametrize("fit_sigma", [False, True])
def test_frame_fit_is_the_stamp_cut_and_numpy_fit(fit_sigma):
    """fit_frame_compiled (stamps cut, start, fit and Fisher inverse in one kernel) against cut_stamps + the 3 x 3
    start + the numpy fit + numpy.linalg.inv, on a frame of stars near every edge, with hot centres (weight 0) and
    saturated pixels (weight 0): the same starts, ok flags, positions to 1e-9 px, variances to 1e-6; and the
    positions of the converged fits within 0.1 px of the truth (math.erf stars, 2 ADU noise)."""
    from dualsight.kernels.detect_psf import cut_stamps, fit_outcome
    from dualsight.kernels.detect_psf_fit import fit_frame_compiled

    rng = np.random.default_rng([24, int(fit_sigma)])
    s = 0.9
    R, img, x, y, flux = _frame_with_stars(rng, s=s)
    H, W = R.shape
    sat = float(np.quantile(img, 0.999))                  # the brightest pixels saturated
    r = np.clip(np.floor(y).astype(np.int64), 0, H - 1)
    c = np.clip(np.floor(x).astype(np.int64), 0, W - 1)
    K, h = r.size, 3
    hot = rng.random(K) < 0.2
    noise = np.full(K, 2.0)
    got = fit_frame_compiled(R, img, r, c, hot, h, sat, s, noise, None, fit_sigma=fit_sigma)
    st, w0, rr0, cc0 = cut_stamps(R, None, r, c, h, img=img, sat=sat)
    w0[hot, h, h] = 0.0
    box = (slice(None), slice(h - 1, h + 2), slice(h - 1, h + 2))
    cen = np.maximum(st[box].astype(np.float64), 0) * w0[box]
    tot = cen.sum((1, 2))
    x0 = c + 0.5 + (cen * np.array([-1, 0, 1])[None, None, :]).sum((1, 2)) / np.maximum(tot, 1e-12)
    y0 = r + 0.5 + (cen * np.array([-1, 0, 1])[None, :, None]).sum((1, 2)) / np.maximum(tot, 1e-12)
    np.testing.assert_allclose(got["x0"], x0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got["y0"], y0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got["tot"], tot, rtol=1e-12)
    xf, yf, A, b, sf, cov, ok = fit_psf(st, w0, rr0, cc0, x0, y0, np.full(K, s), noise, None, fit_sigma=fit_sigma)
    ok &= w0.reshape(K, -1).sum(1) >= 6
    assert np.array_equal(got["ok"], ok) and ok.sum() >= K - 4 and (~w0.astype(bool)).any(axis=(1, 2)).sum() >= 8
    for name, want in (("x", xf), ("y", yf), ("A", A), ("b", b), ("s", sf)):
        np.testing.assert_allclose(got[name][ok], want[ok], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(got["cxx"][ok], cov[ok, 0, 0], rtol=1e-6)
    np.testing.assert_allclose(got["cyy"][ok], cov[ok, 1, 1], rtol=1e-6)
    d = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :]) + np.eye(K) * 1e9
    alone = ok & (d.min(1) > 2 * h + 2)          # no other star's light on the stamp (PSF sigma 0.9 px)
    assert alone.sum() >= 10
    assert np.abs(got["x"][alone] - x[alone]).max() < 0.1 and np.abs(got["y"][alone] - y[alone]).max() < 0.1
    if fit_sigma:
        assert abs(np.median(got["s"][ok]) - s) < 0.02
