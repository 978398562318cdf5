"""The star renderer's fused work (issue 24.3): the frame digest summed inside the render pass, and the sensor
pass reading the star-light scratch only in each row's span of star windows.

Truth: the digest from numpy's own splitmix64 over the returned frames (``kernels/digest.frame_digest``, an
independent implementation: a weight table built by numpy, one vectorised pass per frame); the pixel values of
noise-free frames from ``math.erf`` Gaussian integrals (``helpers.phi``), written out here; a sky-only frame is
exactly the sensor's empty-sky ADU value.
"""

import dataclasses

import numpy as np
import pytest

from dualsight.kernels.digest import frame_digest
from dualsight.kernels.sensor_config import SensorConfig
from dualsight.kernels.starfield import render_star_fields
from helpers import phi

PHI = np.vectorize(phi)

NOISY = SensorConfig(psf_sigma_px=0.9, shot_noise=True, read_noise_e=10.0, dark_current_e_per_s=20.0,
                     sky_background_e=50.0, gain_e_per_adu=5.0, hot_pixel_fraction=1e-3, false_stars_per_frame=2)
CONT = SensorConfig(quantize=False, gain_e_per_adu=1.0, full_well_e=1e12, bit_depth=24, psf_sigma_px=0.9)


def _stars(B, W, H, seed, S=6):
    """Stars anywhere, some across the frame's edges and corners, some touching each other."""
    rs = np.random.default_rng(seed)
    x = rs.uniform(-3.0, W + 3.0, (B, S))
    y = rs.uniform(-3.0, H + 3.0, (B, S))
    x[:, 0], y[:, 0] = 0.3, 0.6                 # a corner
    x[:, 1], y[:, 1] = W - 0.2, H * 0.5         # the right edge
    x[:, 2], y[:, 2] = x[:, 3] + 1.5, y[:, 3]   # two stars whose windows overlap
    f = rs.uniform(2e3, 5e4, (B, S))
    return x, y, f


@pytest.mark.parametrize("cfg,dtype", [(NOISY, np.uint16), (NOISY, np.float32), (SensorConfig(), np.uint16),
                                       (CONT, np.float32)])
def test_fused_digest_is_the_frame_digest(cfg, dtype):
    B, W, H = 5, 67, 41
    x, y, f = _stars(B, W, H, 3)
    seeds = np.arange(11, 11 + B, dtype=np.uint64)
    img, dig = render_star_fields(x, y, f, None, W, H, cfg, seeds, dtype=dtype, digest=True)
    sky = np.asarray(cfg.empty_pixel_adu()).astype(dtype)
    np.testing.assert_array_equal(dig, frame_digest(img, sky))
    # the same frames as without the digest, and a digest that sees every pixel: one ADU more anywhere changes it
    np.testing.assert_array_equal(img, render_star_fields(x, y, f, None, W, H, cfg, seeds, dtype=dtype))
    bumped = img.copy()
    bumped[2, H - 1, W - 1] += 1
    assert frame_digest(bumped, sky)[2] != dig[2]
    assert np.array_equal(frame_digest(bumped, sky)[[0, 1, 3, 4]], dig[[0, 1, 3, 4]])


def test_rows_read_in_their_spans_hold_every_star_pixel():
    """Noise-free continuous frames against the Gaussian integrals, stars across edges and overlapping; then a
    star-free batch through the same scratch: pure sky (the sensor pass cleared every pixel the splat wrote)."""
    B, W, H = 4, 53, 37
    x, y, f = _stars(B, W, H, 8)
    img = render_star_fields(x, y, f, None, W, H, CONT, dtype=np.float32).astype(np.float64)
    s = CONT.psf_sigma_px
    R = int(np.ceil(CONT.psf_window_sigma * s + 1.0))
    c = np.arange(W)[None, None, :]
    r = np.arange(H)[None, :, None]
    truth = np.zeros((B, H, W))
    for b in range(B):              # a test's brute force: every star, every pixel of its window
        for k in range(x.shape[1]):
            ci, ri = np.floor(x[b, k]), np.floor(y[b, k])
            win = (np.abs(c - ci) <= R) & (np.abs(r - ri) <= R)
            fx = PHI((c + 1 - x[b, k]) / s) - PHI((c - x[b, k]) / s)
            fy = PHI((r + 1 - y[b, k]) / s) - PHI((r - y[b, k]) / s)
            truth[b] += np.where(win, f[b, k] * fx * fy, 0.0)[0]
    np.testing.assert_allclose(img, truth, rtol=1e-5, atol=2e-3)
    empty = render_star_fields(np.zeros((B, 0)), np.zeros((B, 0)), np.zeros((B, 0)), None, W, H, CONT,
                               dtype=np.float32)
    assert np.all(empty == np.float32(CONT.empty_pixel_adu()))
    # noisy frames after a bright batch: the same pixels as in a fresh process would give (the sky statistics
    # hold: mean and variance of the sky pixels against the model, shot + read noise, in ADU)
    noisy = dataclasses.replace(NOISY, hot_pixel_fraction=0.0, false_stars_per_frame=0)
    sky = render_star_fields(np.zeros((64, 0)), np.zeros((64, 0)), np.zeros((64, 0)), None, W, H, noisy,
                             np.arange(64, dtype=np.uint64), dtype=np.float32).astype(np.float64)
    lam = noisy.base_e
    g = noisy.gain_e_per_adu
    mean, var = lam / g + noisy.bias_adu - 0.5, (lam + noisy.read_noise_e ** 2) / g ** 2 + 1.0 / 12.0
    n = sky.size
    assert abs(sky.mean() - mean) < 5 * np.sqrt(var / n)
    assert abs(sky.var() / var - 1.0) < 5 * np.sqrt(2.0 / n)


def _sky_reference(cfg, seed, H, W):
    """Each pixel's value if it were sky, from the numpy twins of the counter-based hash (kernels/rng.py) and
    ``np.searchsorted`` on the sky's tabulated ADU distribution: the smallest a with CDF(a) >= u, u from the
    pixel's 16 bits of the 64-bit word of its group of 4 (frame index // 4) plus, where a CDF step falls in that
    2^-16 cell, a further 53-bit uniform (a test's brute force: every pixel searched, no guide table)."""
    from dualsight.kernels import rng as krng
    from dualsight.kernels.sky_noise import sky_adu_table

    cdf, _, a0 = sky_adu_table(cfg)
    idx = np.arange(H * W, dtype=np.uint64)
    word = krng.hash_np(np.uint64(seed), krng.STREAM_SKY_ADU, 0, idx >> np.uint64(2))
    h16 = (word >> (np.uint64(48) - np.uint64(16) * (idx & np.uint64(3)))) & np.uint64(0xFFFF)
    lo = h16.astype(np.float64) / 65536.0
    k = np.searchsorted(cdf, lo, side="left")
    step_inside = cdf[np.minimum(k, cdf.size - 1)] < lo + 1.0 / 65536.0
    u = lo + krng.uniform_np(np.uint64(seed), krng.STREAM_SKY_ADU, 1, idx) / 65536.0
    k = np.where(step_inside, np.searchsorted(cdf, u, side="left"), k)
    return (a0 + k).reshape(H, W)


def _hot_reference(seed, H, W, p):
    """Hot columns of each row from the geometric gaps of their Bernoulli(p) process (kernels/starfield.py's
    sparse hot pixels), in numpy: column c_(n+1) = c_n + 1 + floor(ln u_n / ln(1 - p)), u_n the row's n-th draw."""
    from dualsight.kernels import rng as krng

    key = krng.stream_key_np(np.uint64(seed), krng.STREAM_HOT, 1)
    hot = np.zeros((H, W), bool)
    for r in range(H):                # a test's loop over rows (a few dozen)
        c, n = -1, 0
        while True:
            u = krng.u01_key_np(key, np.uint64((r << 32) | n))
            c = c + 1 + int(np.floor(np.log(u) / np.log1p(-p)))
            if c >= W:
                break
            hot[r, c] = True
            n += 1
    return hot


@pytest.mark.parametrize("W", [96, 94])       # a multiple of 4 (one hash word per 4 pixels of a row) or not
def test_two_pass_rows_equal_the_pixel_model(W):
    """Rows drawn sky-first then redrawn in their star spans and hot columns: every pixel outside the star
    windows and not hot is its sky draw; every hot pixel is where the numpy geometric process puts it and holds
    the hot charge; star windows hold the star light (the frame minus its sky draw sums to the stars' flux)."""
    H, B = 40, 3
    cfg = dataclasses.replace(NOISY, hot_pixel_fraction=0.01, hot_pixel_e=20000.0, false_stars_per_frame=0)
    rs = np.random.default_rng(5)
    x = np.stack([rs.uniform(8.0, W - 8.0, 4) for _ in range(B)])
    y = np.stack([rs.uniform(8.0, H - 8.0, 4) for _ in range(B)])
    f = np.full((B, 4), 3.0e4)            # peak pixel ~6 ke-: below the full well
    seeds = np.array([21, 22, 23], np.uint64)
    img = render_star_fields(x, y, f, None, W, H, cfg, seeds).astype(np.int64)
    R = int(np.ceil(cfg.psf_window_sigma * cfg.psf_sigma_px + 1.0))
    c = np.arange(W)[None, :]
    r = np.arange(H)[:, None]
    for b in range(B):
        win = np.zeros((H, W), bool)
        light = np.zeros((H, W))
        s = cfg.psf_sigma_px
        for k in range(4):
            wk = (np.abs(c - np.floor(x[b, k])) <= R) & (np.abs(r - np.floor(y[b, k])) <= R)
            win |= wk
            light += np.where(wk, f[b, k] * (PHI((c + 1 - x[b, k]) / s) - PHI((c - x[b, k]) / s))
                              * (PHI((r + 1 - y[b, k]) / s) - PHI((r - y[b, k]) / s)), 0.0)
        hot = _hot_reference(int(seeds[b]), H, W, cfg.hot_pixel_fraction)
        sky = _sky_reference(cfg, int(seeds[b]), H, W)
        plain = ~win & ~hot
        np.testing.assert_array_equal(img[b][plain], sky[plain])
        assert hot.sum() > 10 and (hot & ~win).any()
        hot_adu = cfg.hot_pixel_e / cfg.gain_e_per_adu
        assert np.all(img[b][hot & ~win] > sky[hot & ~win] + 0.8 * hot_adu)
        excess = ((img[b] - sky) * cfg.gain_e_per_adu)[win & ~hot].sum()
        truth = light[win & ~hot].sum()
        assert abs(excess - truth) < 0.02 * truth
