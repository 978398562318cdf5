"""A camera's stated PSF width (camera file ``psf_sigma_px`` -> ``LocalDetectConfig.psf_sigma_stated_px``): the
matched filter's SNR efficiency against an independent evaluation (math.erf), the detector's one-pass path on frames
rendered with a known PSF (the measured width, completeness and centroids against the render's truth), the re-filter
when the stated width is wrong, and the camera file's field through to the ``hil star`` spec."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dualsight.errors import ConfigError
from dualsight.kernels import detect_local
from dualsight.kernels.detect_local import (LocalDetectConfig, STATED_WIDTH_MIN_EFFICIENCY, detect_real,
                                           frames_psf_width)
from dualsight.kernels.detect_psf import filter_efficiency
from dualsight.kernels.sensor_config import SensorConfig
from dualsight.kernels.starfield import render_star_fields
from dualsight.scene.camera import Camera

W, H = 512, 384


def _pixel_fractions(s, n=40):
    """Pixel fractions of a pixel-centred 1-D Gaussian of sigma ``s`` (math.erf, independent of the module)."""
    Phi = lambda z: 0.5 * (1.0 + math.erf(z / math.sqrt(2.0)))
    return [Phi((i + 0.5) / s) - Phi((i - 0.5) / s) for i in range(-n, n + 1)]


@settings(max_examples=40, deadline=None)
@given(st.floats(0.3, 5.0), st.floats(0.3, 5.0))
def test_filter_efficiency_is_the_normalised_correlation_of_the_two_psfs(a, b):
    """The fraction of the optimal SNR: (<k, p> / (|k| |p|))^2 of the 1-D pixel fractions (2-D separable), 1 at equal
    widths, symmetric, and for widths of 0.8 px and more within 0.2 % of the continuous Gaussians'
    2 a' b' / (a'^2 + b'^2), a'^2 = a^2 + 1/12 (the pixel's variance; a sharper pixel-centred star is not that
    Gaussian: 4 % off at 0.5 px)."""
    k, p = _pixel_fractions(a), _pixel_fractions(b)      # (the module's erf: Abramowitz & Stegun, 1.5e-7)
    dot = sum(x * y for x, y in zip(k, p))
    want = dot ** 2 / (sum(x * x for x in k) * sum(y * y for y in p))
    assert filter_efficiency(a, b) == pytest.approx(want, abs=2e-6)
    assert filter_efficiency(b, a) == pytest.approx(want, abs=2e-6)
    assert filter_efficiency(a, a) == pytest.approx(1.0, abs=1e-12)
    a2, b2 = a * a + 1 / 12, b * b + 1 / 12
    if min(a, b) >= 0.8:
        assert filter_efficiency(a, b) == pytest.approx(2 * math.sqrt(a2 * b2) / (a2 + b2), rel=2e-3)


def _frames(s, B=3, seed=5, hot=0):
    """Frames of a grid of stars (SNR ~20-200) rendered with PSF sigma ``s``, noise, optional hot pixels far from
    the stars; (frames, x, y, hot pixel rows, cols)."""
    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid(np.arange(24.0, W - 24, 40), np.arange(24.0, H - 24, 40))
    x = gx.ravel()[None] + rng.uniform(0, 1, (B, gx.size))
    y = gy.ravel()[None] + rng.uniform(0, 1, (B, gx.size))
    sensor = SensorConfig(psf_sigma_px=s, read_noise_e=10.0, sky_background_e=50.0, shot_noise=True)
    img = render_star_fields(x, y, rng.uniform(3e3, 3e4, x.shape), None, W, H, sensor,
                             np.arange(B, dtype=np.uint64) + seed)
    hr = (gy.ravel()[:hot, None] + 20).astype(int).T.repeat(B, 0)      # between the grid's rows: > 10 px from stars
    hc = (gx.ravel()[:hot, None] + 20).astype(int).T.repeat(B, 0)
    for b in range(B):
        img[b, hr[b], hc[b]] = np.minimum(img[b, hr[b], hc[b]].astype(np.int64) + 1500, 4095)
    return img, x, y, hr, hc


def _errors(det, x, y):
    """Per frame: (found fraction, RMS centroid error px) against the truth, nearest detection within 1.5 px."""
    out = []
    for b in range(x.shape[0]):
        s0, s1 = int(det.offsets[b]), int(det.offsets[b + 1])
        d = np.hypot(det.x[s0:s1, None] - x[b][None], det.y[s0:s1, None] - y[b][None])
        ok = d.min(0) <= 1.5
        out.append((ok.mean(), float(np.sqrt(np.mean(d.min(0)[ok] ** 2)))))
    return np.array(out)


def _count_filters(monkeypatch):
    calls = []
    real = detect_local.matched_filter

    def counting(R, inv, s, tail=False):
        calls.append((R.shape, s))
        return real(R, inv, s, tail)

    monkeypatch.setattr(detect_local, "matched_filter", counting)
    return calls


@pytest.mark.parametrize("engine", ["numpy", "taichi"])
def test_a_right_stated_width_filters_once_and_fits_the_measured_width(monkeypatch, engine):
    """Stated 1.0 px on frames rendered at 0.9 px (the filter keeps 99.5 % of the SNR): one full-resolution filter
    per frame, no binned first pass; the frame's width measured (0.9 within 3 %), every star found with the same
    centroid error as when the true width is given, and hot pixels 1500 ADU high rejected and counted."""
    assert filter_efficiency(1.0, 0.9) >= STATED_WIDTH_MIN_EFFICIENCY
    img, x, y, hr, hc = _frames(0.9, hot=6)
    calls = _count_filters(monkeypatch)
    det = detect_real(img, LocalDetectConfig(psf_sigma_stated_px=1.0, fit_engine=engine))
    assert calls == [((H, W), 1.0)] * img.shape[0]
    np.testing.assert_allclose(det.psf_sigma_px, 0.9, rtol=0.03)
    given_ = detect_real(img, LocalDetectConfig(psf_sigma_px=0.9, fit_engine=engine))
    e_stated, e_given = _errors(det, x, y), _errors(given_, x, y)
    assert (e_stated[:, 0] == 1.0).all()
    np.testing.assert_allclose(e_stated[:, 1], e_given[:, 1], rtol=0.05)
    for b in range(img.shape[0]):
        s0, s1 = int(det.offsets[b]), int(det.offsets[b + 1])
        d = np.hypot(det.x[s0:s1, None] - hc[b][None] - 0.5, det.y[s0:s1, None] - hr[b][None] - 0.5)
        assert not (d < 2.0).any()                                   # no hot pixel is a star
    assert (det.hot_pixels >= 6).all()


def test_a_wrong_stated_width_is_measured_and_the_frame_filtered_again(monkeypatch):
    """Stated 2.0 px on 0.9 px frames (the filter would keep 70 % of the SNR): the frame is filtered again at its
    measured width, and finds what the default (width measured in a binned first pass) finds."""
    assert filter_efficiency(2.0, 0.9) < STATED_WIDTH_MIN_EFFICIENCY
    img, x, y, _, _ = _frames(0.9, seed=8)
    calls = _count_filters(monkeypatch)
    det = detect_real(img, LocalDetectConfig(psf_sigma_stated_px=2.0))
    assert [c[1] for c in calls[:2]] == [2.0, pytest.approx(0.9, rel=0.03)] and len(calls) == 2 * img.shape[0]
    np.testing.assert_allclose(det.psf_sigma_px, 0.9, rtol=0.03)
    default = detect_real(img, LocalDetectConfig())
    np.testing.assert_allclose(_errors(det, x, y), _errors(default, x, y), rtol=0.05)


def test_the_camera_files_psf_width_reaches_the_hil_spec(tmp_path):
    """``psf_sigma_px`` in a camera file: read with its range checked (one line naming the file and the field),
    written back only when stated, and the ``hil star`` spec's detector gets it as the stated width unless the
    settings give a number."""
    from dualsight.jobs.kinds.hil_star_spec import settings_from_table, spec_from_dict

    base = "[camera]\nwidth = 64\nheight = 48\nfx = 100.0\nbit_depth = 12\n"
    good = tmp_path / "cam.toml"
    good.write_text(base + "psf_sigma_px = 0.75\n")
    cam = Camera.from_toml(good)
    assert cam.psf_sigma_px == 0.75 and cam.to_dict()["psf_sigma_px"] == 0.75
    assert "psf_sigma_px" not in dataclasses.replace(cam, psf_sigma_px=None).to_dict()
    bad = tmp_path / "bad.toml"
    bad.write_text(base + "psf_sigma_px = 0.1\n")
    with pytest.raises(ConfigError) as e:
        Camera.from_toml(bad)
    assert "camera.psf_sigma_px" in str(e.value) and str(bad) in str(e.value) and "0.2" in str(e.value)
    img = tmp_path / "a.png"
    img.write_bytes(b"")
    for table, want in ((None, 0.75), ({"detect_local": {"psf_sigma_stated_px": 1.2}}, 1.2)):
        st_ = settings_from_table(table)                      # completed without the camera, as the CLI does
        spec = spec_from_dict({"images": [{"path": str(img)}], "camera": cam.to_dict(),
                               "settings": st_.model_dump()})
        assert spec.settings.detect_local["psf_sigma_stated_px"] == want


def test_a_frame_without_bright_stars_keeps_the_stated_width(monkeypatch):
    """No star bright enough to measure a width (SNR ~8): the frame is filtered once, at the stated width (0.67 px,
    far from the first pass's 1.0 px), and that width is the one reported, not the first pass's."""
    rng = np.random.default_rng(3)
    x = rng.uniform(20, W - 20, (1, 30))
    y = rng.uniform(20, H - 20, (1, 30))
    sensor = SensorConfig(psf_sigma_px=0.67, read_noise_e=10.0, sky_background_e=50.0, shot_noise=True)
    img = render_star_fields(x, y, np.full(x.shape, 250.0), None, W, H, sensor, np.array([9], np.uint64))
    calls = _count_filters(monkeypatch)
    det = detect_real(img, LocalDetectConfig(psf_sigma_stated_px=0.67))
    assert calls == [((H, W), 0.67)]
    assert det.psf_sigma_px[0] == 0.67
    assert 0 < len(det) <= 30                                       # faint stars found, none measured


def test_frames_agree_on_a_width_only_when_enough_of_them_measure_a_close_one():
    """Three or more measured widths (NaN and None are not measured) whose 90th percentile is at most 1.15 x the 10th
    give their median (nearest-rank order statistics) and their count; fewer, or a wider spread, give None."""
    assert frames_psf_width([0.9, 0.9]) is None
    assert frames_psf_width([0.66, 0.68, float("nan"), None, 0.67]) == (0.67, 3)
    assert frames_psf_width([0.80, 0.90, 1.00]) is None                 # 1.00 / 0.80 = 1.25
    assert frames_psf_width([0.80, 0.85, 0.90, 0.91]) == (0.90, 4)      # 0.91 / 0.80 = 1.14; median rank 2 of 0-3
