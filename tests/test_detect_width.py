"""The per-frame PSF width of the local detector (kernels/detect_local.py, psf_sigma_px None): measured on isolated
stars only, so that a field of close pairs (each star's stamp holding its neighbour's light) does not widen it.
Stars rendered here by math.erf pixel integrals (independent of the module's Abramowitz-Stegun erf)."""

from __future__ import annotations

import math

import numpy as np

from dualsight.kernels.detect_local import LocalDetectConfig, detect_real


def _Phi(z):
    return 0.5 * (1.0 + math.erf(z / math.sqrt(2.0)))


def _render(H, W, xs, ys, flux, widths, noise, rng):
    img = np.zeros((H, W))
    for x, y, f, s in zip(xs, ys, flux, np.broadcast_to(widths, np.shape(xs))):
        c0, r0 = int(x) - 6, int(y) - 6
        px = np.array([_Phi((c0 + j + 1 - x) / s) - _Phi((c0 + j - x) / s) for j in range(13)])
        py = np.array([_Phi((r0 + i + 1 - y) / s) - _Phi((r0 + i - y) / s) for i in range(13)])
        img[r0:r0 + 13, c0:c0 + 13] += f * np.outer(py, px)
    return np.rint(200.0 + img + rng.normal(0, noise, img.shape)).astype(np.uint16)


def test_the_width_comes_from_isolated_stars_not_from_close_pairs():
    """6 isolated stars of PSF sigma 0.8 px and 12 brighter close pairs of sigma 1.2 px sources (6 px apart: two
    candidates each, within the isolation radius 3 x max(2, ceil(2.5 s)) = 9 px at the initial width 1 px): the
    measured width is the isolated stars' 0.8 px within 0.02 px (the pairs' members would pull the median of the 25
    brightest to ~1.2), and the pairs are found; the pairs alone (no 3 isolated stars) leave the initial width."""
    rng = np.random.default_rng(24)
    H, W, s = 200, 320, 0.8
    iso_x = np.array([30.3, 90.6, 150.2, 210.7, 270.4, 300.1])
    iso_y = np.array([30.5, 40.2, 35.8, 30.1, 45.6, 170.3])
    gx, gy = np.meshgrid(np.arange(4) * 70 + 30.4, np.arange(3) * 40 + 90.7)
    px = np.concatenate([gx.ravel(), gx.ravel() + 6.0])
    py = np.concatenate([gy.ravel(), gy.ravel() + 0.2])
    img = _render(H, W, np.concatenate([iso_x, px]), np.concatenate([iso_y, py]),
                  np.concatenate([np.full(6, 3000.0), np.full(24, 9000.0)]),
                  np.concatenate([np.full(6, s), np.full(24, 1.2)]), 3.0, rng)
    for engine in ("numpy", "taichi"):
        det = detect_real(img[None], LocalDetectConfig(fit_engine=engine))
        assert abs(det.psf_sigma_px[0] - s) < 0.02, (engine, det.psf_sigma_px[0])
        d = np.hypot(det.x[:, None] - px[None], det.y[:, None] - py[None]).min(0)
        assert (d < 0.5).all()
    img_pairs = _render(H, W, px, py, np.full(24, 9000.0), 1.2, 3.0, rng)
    assert detect_real(img_pairs[None], LocalDetectConfig()).psf_sigma_px[0] == 1.0


def test_a_sparse_field_measures_its_width_from_the_stars_it_has():
    """Two isolated stars of PSF sigma 1.5 px (a sparse field, or a smeared frame's streaks fitted as round stars):
    the width is theirs, 1.5 px within 0.03, not the initial 1.0 px (which made the filter and the fit too
    narrow, and the stated centroid sigma half the error along a streak)."""
    rng = np.random.default_rng(25)
    img = _render(160, 240, np.array([60.3, 170.6]), np.array([50.4, 110.2]), np.array([6000.0, 4000.0]), 1.5, 3.0,
                  rng)
    for engine in ("numpy", "taichi"):
        det = detect_real(img[None], LocalDetectConfig(fit_engine=engine))
        assert abs(det.psf_sigma_px[0] - 1.5) < 0.03, (engine, det.psf_sigma_px[0])
        assert len(det.x) == 2
