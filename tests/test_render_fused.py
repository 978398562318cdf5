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
