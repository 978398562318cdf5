"""Star-field rendering, detection and centroiding kernels, checked against independent truth.

Truth here is analytic (Gaussian pixel integrals from ``math.erf``, Poisson/Gaussian moments, flux-
weighted means of the true star positions) or an independent implementation (OpenCV's labeller).
Kernels compile once per process; examples are kept few.
"""

import dataclasses
import hashlib
import math
import os
import subprocess
import sys
import textwrap

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from dualsight.kernels import rng as krng
from dualsight.kernels.detect import (DetectConfig, Detections, detect_stars, estimate_background,
                                      render_and_detect_ideal)
from dualsight.kernels.background import row_medians
from dualsight.kernels.sensor_config import SensorConfig, flux_from_magnitude
from dualsight.kernels.starfield import false_star_lists, render_star_fields
from helpers import phi

_N = int(os.environ.get("DUALSIGHT_HYPOTHESIS_EXAMPLES", "0"))  # > 0: deeper runs (nightly, by hand)
HSET = settings(max_examples=_N or 6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
CONT = SensorConfig(quantize=False, gain_e_per_adu=1.0, full_well_e=1e12, bit_depth=24)  # continuous, linear


def _grid_stars(rng, B, W, H, step=40, margin=20):
    """Well-separated stars on a grid with random sub-pixel offsets: (x, y) each (B, S)."""
    gx, gy = np.meshgrid(np.arange(margin, W - margin, step, dtype=float),
                         np.arange(margin, H - margin, step, dtype=float))
    S = gx.size
    return (gx.ravel()[None] + rng.uniform(0, 1, (B, S)), gy.ravel()[None] + rng.uniform(0, 1, (B, S)))


def _match_errors(det: Detections, x, y):
    """Distance from each detection to the nearest true star of its frame."""
    d = np.hypot(x[det.case] - det.x[:, None], y[det.case] - det.y[:, None])
    return d.min(axis=1)


# ----------------------------------------------------------------------------------------- rendering
def test_pixel_values_are_exact_gaussian_integrals():
    sigma, flux, xc, yc = 0.9, 10000.0, 10.5, 7.25
    cfg = dataclasses.replace(CONT, psf_sigma_px=sigma)
    img = render_star_fields([[xc]], [[yc]], [[flux]], None, 21, 15, cfg, dtype=np.float32)[0]
    for r, c in [(7, 10), (6, 10), (8, 11), (7, 13), (3, 10)]:
        truth = flux * ((phi((c + 1 - xc) / sigma) - phi((c - xc) / sigma))
                        * (phi((r + 1 - yc) / sigma) - phi((r - yc) / sigma)))
        assert img[r, c] == pytest.approx(truth, rel=2e-6, abs=1e-4)


@HSET
@given(sigma=st.floats(0.5, 2.5), seed=st.integers(0, 2**31))
def test_flux_is_conserved(sigma, seed):
    rs = np.random.default_rng(seed)
    B, W, H = 3, 64, 48
    x = rs.uniform(20, 44, (B, 1))
    y = rs.uniform(16, 32, (B, 1))
    f = rs.uniform(500, 50000, (B, 1))
    # continuous ADU: the window (>= 4 sigma + 1 px) loses < 2 * 2 * Phi(-4) = 1.3e-4 of the flux
    img = render_star_fields(x, y, f, None, W, H, dataclasses.replace(CONT, psf_sigma_px=sigma), dtype=np.float32)
    tot = img.astype(np.float64).sum(axis=(1, 2))
    np.testing.assert_allclose(tot, f[:, 0], rtol=1.3e-4)
    # 12-bit ADC, 3 e-/ADU: floor loses less than one ADU per lit pixel
    cfg = SensorConfig(psf_sigma_px=sigma, gain_e_per_adu=3.0, full_well_e=1e9, bit_depth=16)
    q = render_star_fields(x, y, f, None, W, H, cfg).astype(np.float64)
    lit = (img > 0).sum(axis=(1, 2))
    e = q.sum(axis=(1, 2)) * cfg.gain_e_per_adu
    assert np.all(e <= f[:, 0] + 1e-6) and np.all(e >= f[:, 0] * (1 - 1.3e-4) - cfg.gain_e_per_adu * lit)


def test_flux_from_magnitude_pogson():
    cfg = SensorConfig(zero_mag_rate_e_per_s=2.0e6, exposure_s=0.25)
    f = flux_from_magnitude(np.array([0.0, 5.0, 2.5]), cfg)
    np.testing.assert_allclose(f, [5.0e5, 5.0e3, 5.0e4], rtol=1e-12)


def test_saturation_and_adc_clip():
    cfg = SensorConfig(psf_sigma_px=0.6, gain_e_per_adu=2.0, full_well_e=5000.0, bit_depth=12)
    img = render_star_fields([[10.5]], [[10.5]], [[1e7]], None, 21, 21, cfg)
    assert img.max() == 2500  # full well 5000 e- / 2 e-/ADU, below the 4095 ADC limit
    cfg = dataclasses.replace(cfg, full_well_e=1e6)
    assert render_star_fields([[10.5]], [[10.5]], [[1e7]], None, 21, 21, cfg).max() == 4095


def test_invalid_and_offimage_stars_are_skipped():
    x = np.array([[5.5, np.nan, -100.0, 3.0]])
    y = np.array([[5.5, 4.0, 5.0, 3.0]])
    f = np.array([[1000.0, 1000.0, 1000.0, 1000.0]])
    valid = np.array([[True, True, True, False]])
    img = render_star_fields(x, y, f, valid, 12, 12, CONT, dtype=np.float32)
    ref = render_star_fields(x[:, :1], y[:, :1], f[:, :1], None, 12, 12, CONT, dtype=np.float32)
    assert np.array_equal(img, ref)
    # not vacuous: the one valid star is there, its flux on the 12 x 12 frame the Gaussian integral over it
    s = CONT.psf_sigma_px
    inside = (phi((12 - 5.5) / s) - phi(-5.5 / s)) ** 2
    assert float(ref.sum(dtype=np.float64)) == pytest.approx(1000.0 * inside, rel=1e-5)


# ----------------------------------------------------------------------------------------- centroids
@HSET
@given(sigma=st.floats(0.6, 1.5), seed=st.integers(0, 2**31))
def test_centroid_error_noiseless(sigma, seed):
    rs = np.random.default_rng(seed)
    B, W, H = 8, 400, 300
    x, y = _grid_stars(rs, B, W, H)
    # continuous ADU: only the pixel-sampling bias of the centroid remains (< 1e-3 px for sigma >= 0.6)
    cfg = dataclasses.replace(CONT, psf_sigma_px=sigma)
    f = flux_from_magnitude(rs.uniform(2.0, 6.0, x.shape), SensorConfig())
    for det in (render_and_detect_ideal(x, y, f, None, W, H, cfg, DetectConfig(), dtype=np.float32),
                detect_stars(render_star_fields(x, y, f, None, W, H, cfg, dtype=np.float32), DetectConfig())):
        assert len(det) == x.size
        assert _match_errors(det, x, y).max() < 2e-3
    # quantised 16-bit ADC at 1 e-/ADU, magnitudes 2-5 (1500-24000 e-): the floor and the threshold
    # drop the sub-ADU wings, still < 0.02 px (fainter or coarser-gain stars: see the benchmark)
    cfg = SensorConfig(psf_sigma_px=sigma, gain_e_per_adu=1.0, full_well_e=60000.0, bit_depth=16)
    f = flux_from_magnitude(rs.uniform(2.0, 5.0, x.shape), cfg)
    det = render_and_detect_ideal(x, y, f, None, W, H, cfg, DetectConfig())
    assert len(det) == x.size
    err = _match_errors(det, x, y)
    assert err.max() < 0.02


def test_overlapping_stars_merge_into_one_blob_at_flux_weighted_mean():
    rs = np.random.default_rng(7)
    B, W, H = 6, 80, 60
    sigma = 1.2
    x1 = rs.uniform(30, 40, B)
    y1 = rs.uniform(25, 35, B)
    ang = rs.uniform(0, 2 * np.pi, B)
    sep = rs.uniform(1.0, 2.0, B) * sigma  # PSFs overlap heavily
    x = np.stack([x1, x1 + sep * np.cos(ang)], 1)
    y = np.stack([y1, y1 + sep * np.sin(ang)], 1)
    f = np.stack([rs.uniform(2000, 8000, B), rs.uniform(2000, 8000, B)], 1)
    cfg = dataclasses.replace(CONT, psf_sigma_px=sigma)
    xm = (f * x).sum(1) / f.sum(1)
    ym = (f * y).sum(1) / f.sum(1)
    img = render_star_fields(x, y, f, None, W, H, cfg, dtype=np.float32)
    for det in (render_and_detect_ideal(x, y, f, None, W, H, cfg, DetectConfig(), dtype=np.float32),
                detect_stars(img, DetectConfig())):
        assert np.array_equal(det.counts, np.ones(B))
        np.testing.assert_allclose(det.x, xm, atol=2e-3)
        np.testing.assert_allclose(det.y, ym, atol=2e-3)
        np.testing.assert_allclose(det.flux, f.sum(1), rtol=2e-4)
    # the same pairs 25 px apart stay two blobs, each at its own star
    x[:, 1] = x[:, 0] + 25.0
    y[:, 1] = y[:, 0]
    det = render_and_detect_ideal(x, y, f, None, W, H, cfg, DetectConfig(), dtype=np.float32)
    assert np.array_equal(det.counts, np.full(B, 2))
    assert _match_errors(det, x, y).max() < 2e-3


def test_detections_are_sorted_and_capped():
    rs = np.random.default_rng(3)
    B, W, H = 4, 300, 200
    x, y = _grid_stars(rs, B, W, H, step=50)
    f = rs.uniform(1000, 20000, x.shape)
    cfg = SensorConfig()
    full = render_and_detect_ideal(x, y, f, None, W, H, cfg, DetectConfig())
    for b in range(B):
        fl = full.frame(b)["flux"]
        assert np.all(np.diff(fl) <= 0)
    assert np.all(np.diff(full.case) >= 0)
    capped = render_and_detect_ideal(x, y, f, None, W, H, cfg, DetectConfig(max_blobs_per_frame=3))
    assert np.array_equal(capped.counts, np.minimum(full.counts, 3))
    for b in range(B):
        np.testing.assert_array_equal(capped.frame(b)["flux"], full.frame(b)["flux"][:3])
    assert capped.offsets.shape == (B + 1,) and capped.offsets[-1] == len(capped)


# ----------------------------------------------------------------------------------------- labelling
@HSET
@given(seed=st.integers(0, 2**31), p=st.floats(0.15, 0.65), conn=st.sampled_from([4, 8]))
def test_labelling_matches_opencv(seed, p, conn):
    rs = np.random.default_rng(seed)
    B, H, W = 3, 53, 71
    binary = (rs.random((B, H, W)) < p).astype(np.uint8)
    cfg = DetectConfig(threshold_adu=0.5, k_sigma=0.0, background_adu=0.0, min_pixels=1,
                       max_blobs_per_frame=10**6, connectivity=conn)
    for imgs in (binary, binary.astype(np.float32) * 3.0):  # integer and float paths
        det = detect_stars(imgs, cfg)
        for b in range(B):
            n, _, stats, cents = cv2.connectedComponentsWithStats(binary[b], connectivity=conn)
            area = stats[1:, cv2.CC_STAT_AREA]
            mine = det.frame(b)
            assert len(mine["npix"]) == n - 1
            scale = 3.0 if imgs.dtype == np.float32 else 1.0
            np.testing.assert_allclose(mine["flux"], mine["npix"] * scale)
            # same components: compare (area, centroid) sets; OpenCV centres pixels on integers
            ref = np.stack([area, cents[1:, 0] + 0.5, cents[1:, 1] + 0.5], 1)
            got = np.stack([mine["npix"], mine["x"], mine["y"]], 1)
            ref = ref[np.lexsort(ref.T[::-1])]
            got = got[np.lexsort(got.T[::-1])]
            np.testing.assert_allclose(got, ref, atol=1e-9)


def test_min_pixels_and_empty_frames():
    img = np.zeros((3, 20, 30), np.uint16)
    img[0, 5, 5] = 100  # a single hot pixel
    img[0, 10:12, 10:12] = 50
    cfg = DetectConfig(background_adu=0.0, noise_sigma_adu=0.0, min_pixels=2)
    det = detect_stars(img, cfg)
    assert det.counts.tolist() == [1, 0, 0]
    assert det.npix.tolist() == [4] and det.x[0] == pytest.approx(11.0) and det.y[0] == pytest.approx(11.0)
    det1 = detect_stars(img, dataclasses.replace(cfg, min_pixels=1))
    assert det1.counts.tolist() == [2, 0, 0]


# ----------------------------------------------------------------------------------------- sparse == dense
@settings(max_examples=_N or 8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31), sigma=st.floats(0.5, 2.5), quantize=st.booleans(),
       sky=st.sampled_from([0.0, 37.3]), n_false=st.integers(0, 3), conn=st.sampled_from([4, 8]),
       min_pix=st.integers(1, 3), dtype=st.sampled_from([np.uint16, np.float32]),
       cap=st.sampled_from([3, 256]), thr=st.sampled_from([0.0, 2.5]))
def test_sparse_path_equals_dense_path(seed, sigma, quantize, sky, n_false, conn, min_pix, dtype, cap, thr):
    rs = np.random.default_rng(seed)
    B, S, W, H = 5, 24, 320, 240
    x = rs.uniform(-8, W + 8, (B, S))
    y = rs.uniform(-8, H + 8, (B, S))
    # clusters: stars 0.5-6 px from another star (merged or touching windows), plus chains of them
    for k in range(1, 10):
        j = rs.integers(0, k, B)
        d = rs.uniform(0.5, 6.0, B)
        a = rs.uniform(0, 2 * np.pi, B)
        x[:, k] = x[np.arange(B), j] + d * np.cos(a)
        y[:, k] = y[np.arange(B), j] + d * np.sin(a)
    x[:, 10] = rs.uniform(-1, 1.5, B)  # on the left edge
    f = flux_from_magnitude(rs.uniform(1.5, 7.0, (B, S)))
    valid = rs.random((B, S)) > 0.1
    x[0, 11] = np.nan
    cfg = SensorConfig(psf_sigma_px=sigma, quantize=quantize, sky_background_e=sky, dark_current_e_per_s=20.0,
                       false_stars_per_frame=n_false)
    seeds = rs.integers(0, 2**63, B, dtype=np.uint64)
    dc = DetectConfig(threshold_adu=thr, connectivity=conn, min_pixels=min_pix, max_blobs_per_frame=cap)
    sparse = render_and_detect_ideal(x, y, f, valid, W, H, cfg, dc, seeds, dtype=dtype)
    dense = detect_stars(render_star_fields(x, y, f, valid, W, H, cfg, seeds, dtype=dtype), dc)
    assert len(sparse) > 0
    for name in ("case", "npix", "offsets"):
        np.testing.assert_array_equal(getattr(sparse, name), getattr(dense, name), err_msg=name)
    np.testing.assert_array_equal(sparse.background_adu, dense.background_adu)
    np.testing.assert_array_equal(sparse.threshold_adu, dense.threshold_adu)
    for name in ("x", "y", "flux"):  # one labeller, the same runs and sums in the same order: bit for bit
        np.testing.assert_array_equal(getattr(sparse, name), getattr(dense, name), err_msg=name)


def test_sparse_path_rejects_noise():
    with pytest.raises(ValueError, match="noise-free"):
        render_and_detect_ideal([[1.0]], [[1.0]], [[1.0]], None, 8, 8, SensorConfig(read_noise_e=1.0))
    with pytest.raises(ValueError, match="below the empty-sky"):
        render_and_detect_ideal([[1.0]], [[1.0]], [[1.0]], None, 8, 8, SensorConfig(sky_background_e=100.0),
                                DetectConfig(background_adu=0.0, k_sigma=0.0))


# ----------------------------------------------------------------------------------------- noise
NOISY = SensorConfig(psf_sigma_px=1.0, read_noise_e=3.0, dark_current_e_per_s=50.0, sky_background_e=20.0,
                     shot_noise=True, hot_pixel_fraction=1e-3, false_stars_per_frame=2, bias_adu=10.0)


def test_rendering_is_bit_identical_across_batches():
    rs = np.random.default_rng(11)
    B, S, W, H = 5, 8, 96, 64
    x = rs.uniform(0, W, (B, S))
    y = rs.uniform(0, H, (B, S))
    f = rs.uniform(1000, 30000, (B, S))
    seeds = np.array([3, 2**64 - 1, 12345678901234567, 0, 2**63], np.uint64)
    full = render_star_fields(x, y, f, None, W, H, NOISY, seeds)
    assert full[0].std() > 1  # noise is on
    for b in range(B):
        alone = render_star_fields(x[b:b + 1], y[b:b + 1], f[b:b + 1], None, W, H, NOISY, seeds[b:b + 1])
        assert np.array_equal(alone[0], full[b])
    pair = render_star_fields(x[[3, 1]], y[[3, 1]], f[[3, 1]], None, W, H, NOISY, seeds[[3, 1]])
    assert np.array_equal(pair[0], full[3]) and np.array_equal(pair[1], full[1])
    assert not np.array_equal(full[0], render_star_fields(x[:1], y[:1], f[:1], None, W, H, NOISY,
                                                          np.array([4], np.uint64))[0])


_SUBPROC = textwrap.dedent("""
    import hashlib, sys, numpy as np
    sys.path.insert(0, {tests!r})
    from test_kernels_stars import _bit_identity_case
    print(_bit_identity_case())
""")


def _bit_identity_case():
    rs = np.random.default_rng(5)
    x = rs.uniform(0, 200, (4, 10))
    y = rs.uniform(0, 150, (4, 10))
    f = rs.uniform(1000, 30000, (4, 10))
    img = render_star_fields(x, y, f, None, 200, 150, NOISY, np.arange(4, dtype=np.uint64) * 977)
    return hashlib.sha256(img.tobytes()).hexdigest()


def test_rendering_is_bit_identical_across_thread_counts():
    here = _bit_identity_case()
    env = dict(os.environ, DUALSIGHT_TI_THREADS="1")
    code = _SUBPROC.format(tests=os.path.dirname(os.path.abspath(__file__)))
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == here


def _flat(cfg, B=2, W=320, H=256, seed0=1):
    z = np.zeros((B, 0))
    img = render_star_fields(z, z, z, None, W, H, cfg, np.arange(seed0, seed0 + B, dtype=np.uint64),
                             dtype=np.float32)
    return img.astype(np.float64).ravel()


@pytest.mark.parametrize("lam", [0.7, 3.7, 9.9, 55.5, 2500.0])
@pytest.mark.parametrize("sampler", ["sky_table", "direct"])
def test_shot_noise_is_poisson(lam, sampler):
    cfg = SensorConfig(gain_e_per_adu=1.0, shot_noise=True, full_well_e=1e6, bit_depth=16)
    if sampler == "sky_table":  # the sky's lambda: tabulated-CDF inversion
        cfg = dataclasses.replace(cfg, sky_background_e=lam)
    else:  # any other lambda (here: every pixel hot): sequential inversion below 10, PTRS above
        cfg = dataclasses.replace(cfg, hot_pixel_fraction=1.0, hot_pixel_e=lam)
    v = _flat(cfg)
    n = v.size
    assert np.all(v == np.round(v))  # integer electrons at 1 e-/ADU
    assert abs(v.mean() - lam) < 5 * math.sqrt(lam / n)
    assert v.var() == pytest.approx(lam, rel=0.02)
    # the distribution, not just its moments: P(k) at the mode against the Poisson pmf
    k = math.floor(lam)
    pk = math.exp(-lam + k * math.log(lam) - math.lgamma(k + 1))
    assert (v == k).mean() == pytest.approx(pk, rel=0.05)


def test_read_noise_dark_current_gain():
    # read noise only, 2 e-/ADU, quantised: ADU = floor((200 + 4 z) / 2 + 10)
    cfg = SensorConfig(gain_e_per_adu=2.0, read_noise_e=4.0, sky_background_e=200.0, bias_adu=10.0)
    v = _flat(cfg)
    assert v.mean() == pytest.approx(109.5, abs=0.02)
    assert v.var() == pytest.approx(4.0 + 1.0 / 12.0, rel=0.02)  # sigma^2 / g^2 + uniform quantisation
    # continuous ADU: dark current is Poisson with mean D t; everything scaled by 1/g
    cfg = SensorConfig(gain_e_per_adu=2.0, dark_current_e_per_s=40.0, exposure_s=0.5, shot_noise=True,
                       read_noise_e=3.0, quantize=False)
    v = _flat(cfg)
    assert v.mean() == pytest.approx(20.0 / 2.0, rel=0.01)
    assert v.var() == pytest.approx((20.0 + 9.0) / 4.0, rel=0.02)


def test_hot_pixels():
    cfg = SensorConfig(gain_e_per_adu=1.0, hot_pixel_fraction=0.01, hot_pixel_e=3000.0)
    z = np.zeros((3, 0))
    img = render_star_fields(z, z, z, None, 256, 200, cfg, np.array([1, 2, 3], np.uint64))
    hot = img == 3000
    n = hot[0].size
    assert np.all((img == 0) | hot)
    for b in range(3):
        assert abs(hot[b].sum() - 0.01 * n) < 5 * math.sqrt(0.01 * 0.99 * n)
    assert not np.array_equal(hot[0], hot[1])  # drawn per case by default
    fixed = render_star_fields(z, z, z, None, 256, 200, dataclasses.replace(cfg, hot_pixel_seed=99),
                               np.array([1, 2, 3], np.uint64))
    assert np.array_equal(fixed[0], fixed[1]) and np.array_equal(fixed[1], fixed[2])  # one sensor map


def test_false_stars_are_rendered_where_listed():
    cfg = SensorConfig(false_stars_per_frame=4, false_star_flux_min_e=5000.0, false_star_flux_max_e=20000.0)
    seeds = np.array([10, 20, 30], np.uint64)
    W, H = 400, 300
    fx, fy, ff = false_star_lists(seeds, W, H, cfg)
    assert fx.shape == (3, 4) and np.all((ff >= 5000) & (ff <= 20000))
    z = np.zeros((3, 0))
    det = detect_stars(render_star_fields(z, z, z, None, W, H, cfg, seeds), DetectConfig())
    ok = (fx > 8) & (fx < W - 8) & (fy > 8) & (fy < H - 8)
    d = np.hypot(fx[..., None] - det.x[None, None, :], fy[..., None] - det.y[None, None, :])
    d = np.where(np.arange(3)[:, None, None] == det.case[None, None, :], d, np.inf).min(-1)
    assert np.all(d[ok] < 0.05)


def test_rng_uniform_and_normal_moments():
    ti = __import__("dualsight.kernels.taichi_runtime", fromlist=["ensure_init"]).ensure_init()

    @ti.kernel
    def draw(u: ti.types.ndarray(dtype=ti.f64, ndim=1), z: ti.types.ndarray(dtype=ti.f64, ndim=1), seed: ti.u64):
        for i in range(u.shape[0]):
            u[i] = krng.uniform(seed, krng.STREAM_TEST, 0, i)
            z[i] = krng.normal(seed, krng.STREAM_TEST + 1, i)

    n = 400_000
    u = np.empty(n)
    z = np.empty(n)
    draw(u, z, 2**64 - 3)
    np.testing.assert_array_equal(u, krng.uniform_np(np.uint64(2**64 - 3), krng.STREAM_TEST, 0, np.arange(n)))
    assert u.min() > 0 and u.max() < 1
    assert u.mean() == pytest.approx(0.5, abs=5 / math.sqrt(12 * n))
    assert u.var() == pytest.approx(1 / 12, rel=0.01)
    assert abs(np.corrcoef(u[:-1], u[1:])[0, 1]) < 5 / math.sqrt(n)
    assert z.mean() == pytest.approx(0.0, abs=5 / math.sqrt(n))
    assert z.var() == pytest.approx(1.0, rel=0.01)
    assert (np.abs(z) > 1.959963985).mean() == pytest.approx(0.05, rel=0.04)
    assert (np.abs(z) > 3.0).mean() == pytest.approx(0.0026998, rel=0.15)


def _noise_sigma_adu(cfg: SensorConfig) -> float:
    """Noise sigma of an empty-sky pixel (ADU): shot noise of dark + sky (Poisson, variance = mean, e-) and read
    noise through the gain, plus the quantisation step's 1/12 ADU^2 (Sheppard's correction; its error is
    ~exp(-2 pi^2 sigma^2), nil for sigma ~ 1 ADU)."""
    var_e = (cfg.dark_current_e_per_s * cfg.exposure_s + cfg.sky_background_e if cfg.shot_noise else 0.0)
    var_e += cfg.read_noise_e ** 2
    return math.sqrt(var_e / cfg.gain_e_per_adu ** 2 + (1.0 / 12.0 if cfg.quantize else 0.0))


def test_noise_sigma_matches_the_sensor_model():
    # star-free frames: the sample standard deviation of N independent pixels has standard error
    # ~ sigma / sqrt(2 N) (Gaussian; the Poisson and quantisation parts change it by < 1 %).  N = 480 000:
    # 5 standard errors = 0.5 % of sigma, so a 5 % error in sigma fails, and so does 1.05 x the read noise
    # (sigma sqrt(25 + 9) / 5 -> sqrt(25 + 9.9225) / 5 with the 1/12 ADU^2 step: +1.3 %, 2.5x the tolerance)
    cfg = dataclasses.replace(NOISY, false_stars_per_frame=0, hot_pixel_fraction=0.0)
    B, W, H = 4, 400, 300
    z = np.zeros((B, 0))
    img = render_star_fields(z, z, z, None, W, H, cfg, np.arange(100, 100 + B, dtype=np.uint64)).astype(np.float64)
    sigma = _noise_sigma_adu(cfg)
    assert sigma == pytest.approx(math.sqrt((25 + 9) / 25 + 1 / 12))
    tol = 5 * sigma / math.sqrt(2 * img.size)
    assert abs(img.std(ddof=1) - sigma) < tol, (img.std(ddof=1), sigma, tol)
    # detect_stars' robust estimate (4-sigma MAD clip: bias < 0.1 %), every pixel of each frame
    _, sig = estimate_background(img, step=1)
    tol1 = 5 * sigma / math.sqrt(2 * W * H)
    assert np.all(np.abs(sig - sigma) < tol1), (sig, sigma, tol1)


# ----------------------------------------------------------------------------------------- noisy detection
def test_detection_on_noisy_frames_finds_bright_stars():
    rs = np.random.default_rng(2)
    B, W, H = 3, 400, 300
    x, y = _grid_stars(rs, B, W, H, step=60, margin=30)
    f = rs.uniform(20000, 40000, x.shape)
    cfg = dataclasses.replace(NOISY, false_stars_per_frame=0, hot_pixel_fraction=0.0)
    img = render_star_fields(x, y, f, None, W, H, cfg, np.arange(B, dtype=np.uint64))
    bg, sig = estimate_background(img)
    # sky: (20 + 50 * 0.1) e- / 5 e-/ADU + 10 ADU bias = 15 ADU
    np.testing.assert_allclose(bg, 15.0, atol=1.0)
    # the robust sigma among the stars, from a strided sample of n pixels per frame: within 5 standard errors
    # (sigma / sqrt(2 n), n = 475: 16 %); the precise check is test_noise_sigma_matches_the_sensor_model
    n = len(range(8, H, 16)) * len(range(8, W, 16))
    sigma = _noise_sigma_adu(cfg)
    assert np.all(np.abs(sig - sigma) < 5 * sigma / math.sqrt(2 * n)), (sig, sigma)
    det = detect_stars(img, DetectConfig(k_sigma=5.0, min_pixels=3))
    assert np.array_equal(det.counts, np.full(B, x.shape[1]))
    assert _match_errors(det, x, y).max() < 0.1


def test_chunked_batches_give_the_same_frames_and_detections(monkeypatch):
    import dualsight.kernels.starfield as sfm
    rs = np.random.default_rng(4)
    B, W, H = 5, 120, 90
    x = rs.uniform(0, W, (B, 6))
    y = rs.uniform(0, H, (B, 6))
    f = rs.uniform(2000, 20000, (B, 6))
    seeds = np.arange(B, dtype=np.uint64)
    whole = render_star_fields(x, y, f, None, W, H, NOISY, seeds)
    dw = detect_stars(whole)
    monkeypatch.setattr(sfm, "MAX_CHUNK_PIXELS", 2 * W * H)  # 2 frames per kernel call
    parts = render_star_fields(x, y, f, None, W, H, NOISY, seeds)
    dp = detect_stars(parts)
    assert np.array_equal(whole, parts)
    for name in ("case", "x", "y", "flux", "npix", "offsets", "background_adu", "threshold_adu"):
        np.testing.assert_array_equal(getattr(dw, name), getattr(dp, name), err_msg=name)


def test_config_validation():
    with pytest.raises(ValueError, match="psf_sigma_px"):
        SensorConfig(psf_sigma_px=0.0)
    with pytest.raises(ValueError, match="bit_depth"):
        SensorConfig(bit_depth=40)
    with pytest.raises(ValueError, match="connectivity"):
        DetectConfig(connectivity=6)
    with pytest.raises(ValueError, match="seeds"):
        render_star_fields([[1.0]], [[1.0]], [[1.0]], None, 8, 8, SensorConfig(read_noise_e=1.0))
    with pytest.raises(ValueError, match="shape"):
        render_star_fields([[1.0, 2.0]], [[1.0]], [[1.0]], None, 8, 8)


@settings(max_examples=300, deadline=None)
@given(rows=st.integers(1, 4), n=st.integers(1, 70), seed=st.integers(0, 2 ** 32 - 1),
       ties=st.booleans(), nan=st.booleans(), f32=st.booleans())
def test_row_medians_equal_numpy_median(rows, n, seed, ties, nan, f32):
    """row_medians (estimate_background's and subtract_background's medians) is np.median(axis=1) bit for bit,
    float64 and float32: odd and even lengths, repeated values, NaN rows, signed zeros."""
    rng = np.random.default_rng(seed)
    x = rng.integers(-3, 4, (rows, n)).astype(np.float64) if ties else rng.normal(0, 10, (rows, n))
    x = x.astype(np.float32 if f32 else np.float64)
    if ties:
        x[rng.random((rows, n)) < 0.1] = -0.0
    if nan:
        x[rng.integers(0, rows), rng.integers(0, n)] = np.nan
    got, want = row_medians(x), np.median(x, axis=1)
    assert got.dtype == want.dtype and np.array_equal(got, want, equal_nan=True)
    assert np.array_equal(np.signbit(got), np.signbit(want))
