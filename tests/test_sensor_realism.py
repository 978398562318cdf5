"""Sensor realism of the dense star renderer (issue 11, point 5), checked against analytic statistics.

Every expected value here is derived in the test from the physics, not from the code: Poisson + Gaussian
variances, second moments of pixel-integrated shapes (a shape's own variance plus 1/12 px^2 for the pixel's
box, Sheppard's correction), the smear of a rotating camera (|w x u| T f px, a roll turns the image about the
principal point), a least-squares plane, the area of a disk and an ADC's full scale.
"""

import dataclasses
import hashlib
import math

import numpy as np
import pytest

from dualsight.errors import ConfigError
from dualsight.kernels.detect import render_and_detect_ideal
from dualsight.jobs.engine.specs import deep_merge
from dualsight.jobs.kinds.star import PRESETS as STAR_PRESETS, spec_from_dict as star_spec_from_dict
from dualsight.kernels.sensor_config import SensorConfig
from dualsight.kernels.starfield import render_star_fields
from dualsight.scene.camera import Camera
from dualsight.scene.psf_file import sensor_psf, with_psf_digest

CONT = SensorConfig(quantize=False, gain_e_per_adu=1.0, full_well_e=1e12, bit_depth=24, psf_window_sigma=8.0)
CAM = Camera.pinhole(256, 256, 5e-6, 5e-3)          # f = 1000 px, principal point (128, 128)


def _render(x, y, f, cfg, W, H, **kw):
    x, y, f = (np.atleast_2d(np.asarray(a, np.float64)) for a in (x, y, f))
    return render_star_fields(x, y, f, None, W, H, cfg, dtype=np.float32, **kw).astype(np.float64)


def _cell_moments(img, cell):
    """Moments of each (cell x cell) block of a (H, W) frame holding one source: flux, mean (x, y) and the
    covariance (xx, yy, xy), with pixel (r, c) at its centre (c + 0.5, r + 0.5)."""
    H, W = img.shape
    blk = img.reshape(H // cell, cell, W // cell, cell).transpose(0, 2, 1, 3).reshape(-1, cell, cell)
    oy, ox = np.divmod(np.arange(blk.shape[0]), W // cell)
    yy, xx = np.mgrid[0:cell, 0:cell] + 0.5
    F = blk.sum((1, 2))
    mx = (blk * xx).sum((1, 2)) / F
    my = (blk * yy).sum((1, 2)) / F
    vxx = (blk * (xx - mx[:, None, None]) ** 2).sum((1, 2)) / F
    vyy = (blk * (yy - my[:, None, None]) ** 2).sum((1, 2)) / F
    vxy = (blk * (xx - mx[:, None, None]) * (yy - my[:, None, None])).sum((1, 2)) / F
    return F, mx + ox * cell, my + oy * cell, vxx, vyy, vxy


def _mu4(img, cell, x, y):
    """Fourth moments (x, y) of each (cell x cell) block about the true source positions x, y (n,)."""
    H, W = img.shape
    blk = img.reshape(H // cell, cell, W // cell, cell).transpose(0, 2, 1, 3).reshape(-1, cell, cell)
    oy, ox = np.divmod(np.arange(blk.shape[0]), W // cell)
    yy, xx = np.mgrid[0:cell, 0:cell] + 0.5
    dx = xx[None] + (ox * cell - x)[:, None, None]
    dy = yy[None] + (oy * cell - y)[:, None, None]
    F = blk.sum((1, 2))
    return (blk * dx ** 4).sum((1, 2)) / F, (blk * dy ** 4).sum((1, 2)) / F


def _grid(rs, n, cell):
    """One source per cell near the cell's centre: x, y each (n*n,).  rs: a numpy Generator (uniformly
    random sub-pixel phases) or None (stratified: the n x n phases ((i + 1/2) / n, (j + 1/2) / n), whose
    averages are midpoint-rule integrals over the phase)."""
    c = (np.arange(n) * cell + cell / 2.0)
    gx, gy = np.meshgrid(c, c)
    if rs is None:
        ph = (np.arange(n) + 0.5) / n - 0.5
        px, py = np.meshgrid(ph, ph)
        return gx.ravel() + px.ravel(), gy.ravel() + py.ravel()
    return gx.ravel() + rs.uniform(-0.5, 0.5, n * n), gy.ravel() + rs.uniform(-0.5, 0.5, n * n)


# ----------------------------------------------------------------------------------------- noise
def test_pixel_noise_variance_is_shot_dark_read_and_quantisation():
    # var = (S + D t + R^2) / g^2 + 1/12 ADU^2 (Poisson mean = variance; the floor's step adds 1/12) and
    # mean = (S + D t) / g + bias - 1/2 (the floor takes half a step on average).  S = 37.3 e- of flat stray
    # light.  N = 480 000 pixels: the sample variance's standard error is var sqrt(2 / N) = 0.2 %; tolerance 5
    # of them (1 %).  Adding the stray light after the shot noise drops var by 40 %.
    for S, g, R, D, t in ((37.3, 2.0, 6.0, 40.0, 0.5), (0.0, 1.5, 4.0, 300.0, 0.1)):
        cfg = SensorConfig(gain_e_per_adu=g, read_noise_e=R, dark_current_e_per_s=D, exposure_s=t, shot_noise=True,
                           stray_light_e=(S, 0.0, 0.0), bias_adu=50.0, bit_depth=16, full_well_e=1e6)
        z = np.zeros((4, 0))
        img = render_star_fields(z, z, z, None, 400, 300, cfg, np.arange(4, dtype=np.uint64) + 11).astype(np.float64)
        var = (S + D * t + R * R) / g ** 2 + 1.0 / 12.0
        n = img.size
        assert abs(img.var(ddof=1) - var) < 5 * var * math.sqrt(2.0 / n), (S, img.var(ddof=1), var)
        mean = (S + D * t) / g + 50.0 - 0.5
        assert abs(img.mean() - mean) < 5 * math.sqrt(var / n), (S, img.mean(), mean)


def test_stray_light_shot_noise_is_poisson():
    # sky pixels under stray light draw Poisson(dark + stray) as a tabulated part on a 1/16 e- grid plus the
    # remainder's own Poisson draw: the counts must be Poisson(lambda) with lambda = 13.3 + 20.06 = 33.36 e-.
    # N = 2.4e6 pixels: mean to 5 sqrt(lambda / N) = 0.019 e- (dropping the 0.06 e- remainder fails by 15
    # standard errors), variance to 5 lambda sqrt(2 / N + 1 / (lambda N)), histogram chi^2 over k = 10..65
    # (56 bins; its 1 - 1e-7 quantile is ~120, measured 59).  A stray-light gradient: the fitted-plane test.
    lam = 13.3 + 20.06
    cfg = SensorConfig(gain_e_per_adu=1.0, quantize=False, shot_noise=True, dark_current_e_per_s=133.0,
                       exposure_s=0.1, stray_light_e=(20.06, 0.0, 0.0), bit_depth=16, full_well_e=1e6)
    z = np.zeros((20, 0))
    k = render_star_fields(z, z, z, None, 400, 300, cfg, np.arange(20, dtype=np.uint64) + 500,
                           dtype=np.float32).astype(np.float64).ravel()
    n = k.size
    assert np.all(k == np.round(k))
    assert abs(k.mean() - lam) < 5 * math.sqrt(lam / n), (k.mean(), lam)
    assert abs(k.var() - lam) < 5 * lam * math.sqrt(2 / n + 1 / (lam * n)), (k.var(), lam)
    ks = np.arange(10, 66)
    pmf = np.exp(-lam + ks * math.log(lam) - np.array([math.lgamma(v + 1) for v in ks]))
    obs = np.bincount(k.astype(np.int64), minlength=70)[10:66]
    chi2 = ((obs - n * pmf) ** 2 / (n * pmf)).sum()
    assert chi2 < 120, chi2


# ----------------------------------------------------------------------------------------- PSF models
def test_gaussian_psf_second_moment_is_sigma2_plus_one_twelfth():
    rs = np.random.default_rng(1)
    sigma, cell = 0.9, 24
    x, y = _grid(rs, 8, cell)
    img = _render(x, y, np.full(x.size, 1e5), dataclasses.replace(CONT, psf_sigma_px=sigma), 8 * cell, 8 * cell)[0]
    F, mx, my, vxx, vyy, vxy = _cell_moments(img, cell)
    # Sheppard's correction is exact up to exp(-2 pi^2 sigma^2) = 1e-7 for sigma 0.9: per star, 1e-4 (f32 sums)
    assert np.allclose(vxx, sigma ** 2 + 1 / 12, rtol=1e-4) and np.allclose(vyy, sigma ** 2 + 1 / 12, rtol=1e-4)
    assert np.allclose(mx, x, atol=1e-4) and np.allclose(my, y, atol=1e-4) and np.allclose(F, 1e5, rtol=1e-5)


def test_defocus_disk_moments_are_r2_over_4_plus_one_twelfth():
    # a uniform disk of radius R has variance R^2/4 per axis; integrated over pixels at a uniformly random
    # sub-pixel phase the binned second moment gains exactly 1/12 on average.  Per star it wobbles with the
    # phase (up to ~0.04 px^2: the disk's edge is sharp); averaged over a 16 x 16 grid of phases it is good
    # to ~1e-4.  Rendering R as the diameter, or a disk of the wrong area normalisation, fails by far.
    R, cell = 3.0, 16
    x, y = _grid(None, 16, cell)
    cfg = dataclasses.replace(CONT, psf_model="defocus", defocus_radius_px=R)
    img = _render(x, y, np.full(x.size, 1e5), cfg, 16 * cell, 16 * cell)[0]
    F, mx, my, vxx, vyy, vxy = _cell_moments(img, cell)
    assert np.allclose(F, 1e5, rtol=1e-5)                        # exact pixel areas sum to the disk's
    truth = R * R / 4 + 1 / 12
    assert abs(vxx.mean() - truth) < 5e-4 and abs(vyy.mean() - truth) < 5e-4, (vxx.mean(), vyy.mean(), truth)
    assert np.all(np.abs(vxx - truth) < 0.06) and abs(vxy.mean()) < 5e-4
    assert abs((mx - x).mean()) < 5e-4 and abs((my - y).mean()) < 5e-4
    # the shape: E (X + U)^4 with X the disk's marginal (E X^4 = R^4 / 8) and U the pixel's box (1/80)
    m4x, m4y = _mu4(img, cell, x, y)
    m4 = R ** 4 / 8 + 6 * (R * R / 4) / 12 + 1 / 80
    assert abs(m4x.mean() - m4) < 2e-3 * m4 and abs(m4y.mean() - m4) < 2e-3 * m4, (m4x.mean(), m4y.mean(), m4)
    # fully covered pixels hold F / (pi R^2) (the disk's surface brightness)
    c = img[8 * cell + 8, 8 * cell + 8 - 1: 8 * cell + 8 + 1]   # two pixels next to a star's centre
    assert np.allclose(c, 1e5 / (math.pi * R * R), rtol=1e-5)


def test_defocus_disk_convolved_with_gaussian_moments():
    # disk (+ R^2/4) convolved with a Gaussian (+ sigma^2), integrated over pixels (+ 1/12): variances add,
    # and the fourth moment is E (D + G + U)^4 of independent disk, Gaussian and box marginals.  Per star
    # to 1e-3 (the Gaussian smooths the pixel phase away): the ring quadrature must reproduce the disk's
    # moments up to order 4 (rings at the annuli's mid radius miss R^2/4 by ~1 %, a single ring of
    # points misses R^4/8 by 25 %).
    rs = np.random.default_rng(3)
    R, sigma, cell = 2.5, 0.7, 24
    x, y = _grid(rs, 6, cell)
    cfg = dataclasses.replace(CONT, psf_model="defocus", defocus_radius_px=R, defocus_gaussian=True, psf_sigma_px=sigma)
    F, mx, my, vxx, vyy, vxy = _cell_moments(_render(x, y, np.full(x.size, 1e5), cfg, 6 * cell, 6 * cell)[0], cell)
    truth = R * R / 4 + sigma ** 2 + 1 / 12
    assert np.allclose(vxx, truth, rtol=1e-3) and np.allclose(vyy, truth, rtol=1e-3), (vxx, vyy, truth)
    assert np.allclose(vxy, 0.0, atol=2e-3) and np.allclose(F, 1e5, rtol=1e-5)
    assert np.allclose(mx, x, atol=1e-3) and np.allclose(my, y, atol=1e-3)
    m4x, m4y = _mu4(_render(x, y, np.full(x.size, 1e5), cfg, 6 * cell, 6 * cell)[0], cell, x, y)
    m4 = R ** 4 / 8 + 3 * sigma ** 4 + 1 / 80 + 6 * (R * R / 4 * sigma ** 2 + R * R / 4 / 12 + sigma ** 2 / 12)
    assert np.allclose(m4x, m4, rtol=1e-3) and np.allclose(m4y, m4, rtol=1e-3), (m4x, m4y, m4)
    # every pixel: the disk as 40 Gauss-Legendre nodes in r^2 x 256 angles (converged to 1e-14), each an exact
    # pixel-integrated Gaussian (math.erf); to 1e-3 of the peak (measured 3e-4; one annulus of rings: 0.1)
    xc, yc = 12.37, 11.81
    s, ws = np.polynomial.legendre.leggauss(40)
    r = np.sqrt((s + 1) / 2 * R * R)
    th = 2 * np.pi * (np.arange(256) + 0.5) / 256
    px, py = (xc + r[:, None] * np.cos(th)).ravel(), (yc + r[:, None] * np.sin(th)).ravel()
    w = np.repeat(ws / 2 / 256, 256)
    cdf = np.frompyfunc(lambda z: 0.5 * (1.0 + math.erf(z / (sigma * math.sqrt(2.0)))), 1, 1)
    fx = np.diff(cdf(np.arange(25.0)[None] - px[:, None]).astype(float), axis=1)
    fy = np.diff(cdf(np.arange(25.0)[None] - py[:, None]).astype(float), axis=1)
    ref = 1e5 * np.einsum("k,kr,kc->rc", w, fy, fx)
    img = _render([xc], [yc], [1e5], cfg, 24, 24)[0]
    assert np.abs(img - ref).max() < 1e-3 * ref.max(), np.abs(img - ref).max() / ref.max()


def _measured_psf():
    """An asymmetric 9 x 13 PSF (rows x columns): a tilted elliptical core plus a side lobe."""
    j, i = np.mgrid[0:9, 0:13].astype(float)
    u, v = i - 6.3, j - 3.8
    core = np.exp(-0.5 * ((0.9 * u + 0.3 * v) ** 2 / 1.7 ** 2 + (-0.3 * u + 0.9 * v) ** 2 / 1.0 ** 2))
    return core + 0.25 * np.exp(-0.5 * ((i - 9.5) ** 2 + (j - 1.5) ** 2) / 0.6 ** 2)


def _own_moments(P):
    j, i = np.mgrid[0:P.shape[0], 0:P.shape[1]].astype(float)
    p = P / P.sum()
    mx, my = (p * (i - P.shape[1] // 2)).sum(), (p * (j - P.shape[0] // 2)).sum()
    return mx, my, (p * (i - P.shape[1] // 2 - mx) ** 2).sum(), (p * (j - P.shape[0] // 2 - my) ** 2).sum(), \
        (p * (i - P.shape[1] // 2 - mx) * (j - P.shape[0] // 2 - my)).sum()


def test_measured_psf_image_keeps_its_own_moments(tmp_path):
    # The image is sampled on the sensor's pixels.  A star at (x, y) gets it bilinearly resampled: the
    # centroid moves with the star exactly (x + the image's own mean offset), the second moment is the image's
    # own plus phi (1 - phi) per axis (the 2-tap linear-interpolation kernel's variance), phi = frac(0.5 - x),
    # and 0 at integer phase (a star at a pixel centre gets the image itself).
    P = _measured_psf()
    path = tmp_path / "psf.npy"
    np.save(path, P)
    cfg = dataclasses.replace(CONT, psf_model="image", psf_image=str(path))
    rs = np.random.default_rng(4)
    cell = 32
    x, y = _grid(rs, 6, cell)
    x[0], y[0] = 16.5, 16.5                                                # integer phase
    psf = sensor_psf(cfg)                                                  # the file, read by the scene layer
    F, mx, my, vxx, vyy, vxy = _cell_moments(_render(x, y, np.full(x.size, 1e5), cfg, 6 * cell, 6 * cell, psf=psf)[0],
                                             cell)
    ox, oy, pxx, pyy, pxy = _own_moments(P)
    fx, fy = np.mod(0.5 - x, 1.0), np.mod(0.5 - y, 1.0)
    assert np.allclose(F, 1e5, rtol=1e-5)
    assert np.allclose(mx, x + ox, atol=1e-4) and np.allclose(my, y + oy, atol=1e-4)
    assert np.allclose(vxx, pxx + fx * (1 - fx), atol=1e-4) and np.allclose(vyy, pyy + fy * (1 - fy), atol=1e-4)
    assert np.allclose(vxy, pxy, atol=1e-4)
    img = _render([16.5], [16.5], [1e5], cfg, 32, 32, psf=psf)[0]
    assert np.allclose(img[16 - 4:16 + 5, 16 - 6:16 + 7], 1e5 * P / P.sum(), rtol=1e-5, atol=1e-3)


def test_psf_image_from_png_and_one_line_errors(tmp_path):
    import cv2

    P = _measured_psf()
    q = np.round(P / P.max() * 60000).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "psf.png"), q)
    np.save(tmp_path / "q.npy", q.astype(np.float64))
    ca, cb = (dataclasses.replace(CONT, psf_model="image", psf_image=str(tmp_path / n)) for n in ("psf.png", "q.npy"))
    a = _render([20.3], [17.8], [1e5], ca, 40, 40, psf=sensor_psf(ca))
    b = _render([20.3], [17.8], [1e5], cb, 40, 40, psf=sensor_psf(cb))
    assert np.array_equal(a, b)
    # the renderer reads no file: it takes the PSF as a (ny, nx) float64 unit-sum array, one-line errors else
    for psf, what in ((None, "needs the measured PSF"), (np.ones((3, 3)), "unit sum"),
                      (np.ones((4, 3)) / 12, "odd sides"), (np.ones((3, 3), np.float32) / 9, "float64")):
        with pytest.raises(ValueError, match=what) as e:
            _render([20.3], [17.8], [1e5], cb, 40, 40, psf=psf)
        assert "\n" not in str(e.value)
    assert np.array_equal(_render([20.3], [17.8], [1e5], CONT, 40, 40, psf=sensor_psf(cb)),
                          _render([20.3], [17.8], [1e5], CONT, 40, 40))            # ignored by the other models
    bad = {"even.npy": np.ones((8, 9)), "neg.npy": -np.ones((3, 3)), "nan.npy": np.full((3, 3), np.nan),
           "big.npy": np.ones((65, 65)), "flat.npy": np.ones(9), "zero.npy": np.zeros((3, 3))}
    for name, arr in {**bad, "missing.npy": None}.items():
        if arr is not None:
            np.save(tmp_path / name, arr)
        cfg = SensorConfig(psf_model="image", psf_image=str(tmp_path / name))     # the constructor reads nothing
        with pytest.raises(ValueError) as e:
            with_psf_digest(cfg)
        msg = str(e.value)
        assert "psf_image" in msg and name in msg and "\n" not in msg, msg
        table = deep_merge(STAR_PRESETS["paper"], {"sensor": {"psf_model": "image", "psf_image": str(tmp_path / name)}})
        with pytest.raises(ConfigError) as e:
            star_spec_from_dict(table, source="spec.toml")
        assert "spec.toml" in str(e.value) and name in str(e.value) and "\n" not in str(e.value)
    good = with_psf_digest(SensorConfig(psf_model="image", psf_image=str(tmp_path / "q.npy")))
    unit = np.load(tmp_path / "q.npy") / np.load(tmp_path / "q.npy").sum()     # the spec hashes the unit-sum PSF
    want = hashlib.sha256(f"{unit.shape[0]}x{unit.shape[1]}:".encode() + unit.astype("<f8").tobytes()).hexdigest()
    assert good.psf_image_sha256 == want
    assert with_psf_digest(dataclasses.replace(good, psf_image=str(tmp_path / "psf.png"))) is not None  # same PSF
    np.save(tmp_path / "q.npy", q.astype(np.float64) + np.eye(*q.shape))                # the file changed under it
    with pytest.raises(ValueError, match="not the one this spec was made with"):
        with_psf_digest(good)
    with pytest.raises(ValueError, match="psf_image"):
        SensorConfig(psf_model="image")
    with pytest.raises(ValueError, match="psf_image"):
        SensorConfig(psf_image=str(tmp_path / "q.npy"))


# ----------------------------------------------------------------------------------------- smear
def test_smear_moves_stars_by_w_cross_u_t_f():
    # A camera turning at w (camera frame) sees a fixed direction u move as du/dt = -w x u: in T a star near the
    # boresight sweeps L = |w x u| T f px along -(w x u).  The rendered image is the static PSF convolved with
    # a segment of length L through the star's (mid-exposure) position: its covariance grows by L^2/12 along
    # the segment, not across it, and its centroid stays.  A wrong axis or sign of one rate component turns the
    # segment (fails the direction); a wrong length fails the L^2/12.
    T = 0.2
    w = np.radians([3.0, -4.0, 0.0])
    x0, y0 = 140.3, 117.6
    cfg = dataclasses.replace(CONT, exposure_s=T, psf_sigma_px=0.8)
    static = _cell_moments(_render([x0], [y0], [1e5], cfg, 256, 256)[0], 256)
    moving = _cell_moments(_render([x0], [y0], [1e5], dataclasses.replace(cfg, rate_deg_s=(3.0, -4.0, 0.0)),
                                   256, 256, camera=CAM)[0], 256)
    u = np.array([(x0 - 128) / 1000.0, (y0 - 128) / 1000.0, 1.0])
    u /= np.linalg.norm(u)
    v = -np.cross(w, u)
    L = np.linalg.norm(np.cross(w, u)) * T * 1000.0                       # ~17.45 px
    d = v[:2] / np.linalg.norm(v[:2])
    dcov = np.array([[moving[3] - static[3], moving[5] - static[5]], [moving[5] - static[5], moving[4] - static[4]]])[..., 0]
    along, across = d @ dcov @ d, np.array([-d[1], d[0]]) @ dcov @ np.array([-d[1], d[0]])
    assert along == pytest.approx(L * L / 12, rel=3e-3), (along, L * L / 12)
    assert abs(across) < 2e-3 * L * L / 12
    assert abs(moving[1][0] - x0) < 2e-3 and abs(moving[2][0] - y0) < 2e-3
    assert moving[0][0] == pytest.approx(1e5, rel=1e-5)


def test_roll_smears_each_star_by_its_own_arc():
    # a roll wz about the boresight turns a pinhole image rigidly about the principal point: a star at radius
    # r sweeps a chord of 2 r sin(wz T / 2) px, tangentially (three stars: three lengths).
    wz, T = 20.0, 0.1
    r = np.array([20.0, 50.0, 90.0])
    ang = np.array([0.3, 2.0, 4.0])
    x, y = 128 + r * np.cos(ang), 128 + r * np.sin(ang)
    cfg = dataclasses.replace(CONT, exposure_s=T, psf_sigma_px=0.8)
    stat = _render(x[:, None], y[:, None], np.full((3, 1), 1e5), cfg, 256, 256)
    mov = _render(x[:, None], y[:, None], np.full((3, 1), 1e5), dataclasses.replace(cfg, rate_deg_s=(0.0, 0.0, wz)),
                  256, 256, camera=CAM)
    L = 2 * r * np.sin(math.radians(wz) * T / 2)
    for b in range(3):
        s, m = _cell_moments(stat[b], 256), _cell_moments(mov[b], 256)
        dcov = np.array([[m[3] - s[3], m[5] - s[5]], [m[5] - s[5], m[4] - s[4]]])[..., 0]
        t = np.array([-math.sin(ang[b]), math.cos(ang[b])])              # tangential
        n = np.array([math.cos(ang[b]), math.sin(ang[b])])               # radial
        assert t @ dcov @ t == pytest.approx(L[b] ** 2 / 12, rel=5e-3), (b, t @ dcov @ t, L[b] ** 2 / 12)
        assert abs(n @ dcov @ n) < 5e-3 * L[b] ** 2 / 12 + 1e-5


def test_new_effects_take_the_dense_path():
    # the sparse noise-free detector renders Gaussian windows over a constant sky only
    for kw in ({"psf_model": "defocus"}, {"rate_deg_s": (0.0, 0.1, 0.0)}, {"stray_light_e": (5.0, 0.0, 0.0)},
               {"bright_objects": ({"ra_deg": 1.0, "dec_deg": 2.0, "vmag": -3.0, "radius_px": 0.0},)}):
        cfg = SensorConfig(**kw)
        assert not cfg.is_ideal and cfg.has_pixel_noise and not cfg.needs_seeds, kw
        with pytest.raises(ValueError, match="noise-free"):
            render_and_detect_ideal([[10.0]], [[10.0]], [[1e4]], None, 32, 32, cfg)
    assert SensorConfig().is_ideal and not SensorConfig().has_pixel_noise
    with pytest.raises(ValueError, match="camera"):
        render_star_fields([[10.0]], [[10.0]], [[1e4]], None, 32, 32, SensorConfig(rate_deg_s=(0.0, 1.0, 0.0)))


def test_realistic_frames_are_bit_identical_across_batches():
    rs = np.random.default_rng(6)
    B, S = 3, 12
    x, y, f = rs.uniform(0, 256, (B, S)), rs.uniform(0, 256, (B, S)), rs.uniform(1e3, 1e5, (B, S))
    cfg = SensorConfig(psf_model="defocus", defocus_gaussian=True, psf_sigma_px=0.5, rate_deg_s=(0.5, -0.3, 2.0),
                       stray_light_e=(30.0, 0.05, -0.02), shot_noise=True, read_noise_e=5.0, hot_pixel_fraction=1e-3)
    seeds = np.array([5, 2 ** 63 + 1, 77], np.uint64)
    full = render_star_fields(x, y, f, None, 256, 256, cfg, seeds, camera=CAM)
    for b in range(B):
        one = render_star_fields(x[b:b + 1], y[b:b + 1], f[b:b + 1], None, 256, 256, cfg, seeds[b:b + 1], camera=CAM)
        assert np.array_equal(one[0], full[b])


# ----------------------------------------------------------------------------------------- stray light
def test_stray_light_gradient_is_the_fitted_plane():
    # least-squares plane through the pixels of noisy star-free frames, at pixel centres relative to the frame
    # centre: a = e0 / g + bias - 1/2 (floor), slopes gx / g and gy / g.  Slope standard error
    # sigma / sqrt(sum dx^2) ~ 2e-5 ADU/px here; tolerance 5 of them.  The residual variance of each half of
    # the frame follows the local stray light (shot noise): (mean stray + R^2) / g^2 + 1/12.
    e0, gx, gy, g, R = 400.0, 0.8, -0.5, 2.0, 5.0
    cfg = SensorConfig(gain_e_per_adu=g, read_noise_e=R, shot_noise=True, stray_light_e=(e0, gx, gy), bias_adu=20.0,
                       bit_depth=16, full_well_e=1e6)
    B, W, H = 4, 400, 300
    z = np.zeros((B, 0))
    img = render_star_fields(z, z, z, None, W, H, cfg, np.arange(B, dtype=np.uint64)).astype(np.float64)
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    dx, dy = xx - W / 2, yy - H / 2
    A = np.stack([np.ones(H * W), dx.ravel(), dy.ravel()], 1)
    coef, *_ = np.linalg.lstsq(A, img.mean(0).ravel(), rcond=None)
    sig = math.sqrt((e0 + R * R) / g ** 2)
    se = sig / math.sqrt(B * (dx ** 2).sum())
    assert abs(coef[1] - gx / g) < 5 * se and abs(coef[2] - gy / g) < 5 * se * math.sqrt(W ** 2 / H ** 2), coef
    assert abs(coef[0] - (e0 / g + 20.0 - 0.5)) < 5 * sig / math.sqrt(img.size), coef
    res = img - (A @ coef).reshape(H, W)
    for half, mean_dx in ((slice(0, W // 2), -W / 4), (slice(W // 2, W), W / 4)):
        var = (e0 + gx * mean_dx + R * R) / g ** 2 + 1 / 12
        v = res[:, :, half].var()
        assert abs(v - var) < 5 * var * math.sqrt(2 / res[:, :, half].size), (v, var)


def test_stray_light_plane_is_clipped_at_zero_electrons():
    cfg = dataclasses.replace(CONT, stray_light_e=(10.0, 1.0, 0.0), bias_adu=100.0)
    img = _render(np.zeros((1, 0)), np.zeros((1, 0)), np.zeros((1, 0)), cfg, 40, 4)[0]
    c = np.arange(40) + 0.5 - 20
    assert np.allclose(img, 100.0 + np.maximum(0.0, 10.0 + c)[None, :], rtol=0, atol=1e-9)


# ----------------------------------------------------------------------------------------- bright objects
def _looking_at(ra_deg, dec_deg):
    """(1, 3, 3) inertial -> camera rotation with the boresight (+z) at (ra, dec), +x towards east."""
    ra, dec = math.radians(ra_deg), math.radians(dec_deg)
    z = np.array([math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec)])
    x = np.array([-math.sin(ra), math.cos(ra), 0.0])
    return np.stack([x, np.cross(z, x), z])[None]


def test_moon_disk_area_flux_and_saturation():
    R, vmag = 20.3, -2.0
    A = _looking_at(83.0, 21.0)
    moon = {"ra_deg": 83.5, "dec_deg": 21.3, "vmag": vmag, "radius_px": R}
    ra, dec = math.radians(83.5), math.radians(21.3)
    v = A[0] @ np.array([math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec)])
    px, py = 128 + 1000 * v[0] / v[2], 128 + 1000 * v[1] / v[2]        # pinhole projection
    cfg = dataclasses.replace(CONT, bright_objects=(moon,))
    img = _render(np.zeros((1, 0)), np.zeros((1, 0)), np.zeros((1, 0)), cfg, 256, 256, camera=CAM, attitude=A)[0]
    F = cfg.zero_mag_rate_e_per_s * 10 ** (-0.4 * vmag) * cfg.exposure_s
    dens = F / (math.pi * R * R)                                           # surface brightness, e-/px
    # pixels whose four corners lie inside the disk, and those the disk touches at all
    yy, xx = np.mgrid[0:256, 0:256].astype(float)
    far = np.max([np.hypot(xx + a - px, yy + b - py) for a in (0, 1) for b in (0, 1)], axis=0)
    near = np.hypot(np.clip(px, xx, xx + 1) - px, np.clip(py, yy, yy + 1) - py)
    inside, touched = far < R, near < R
    assert np.allclose(img[inside], dens, rtol=1e-5) and np.all(img[~touched] == 0)
    assert img.sum() / dens == pytest.approx(math.pi * R * R, rel=1e-5)   # area in px
    assert inside.sum() < math.pi * R * R < touched.sum()
    m = _cell_moments(img, 256)
    assert abs(m[1][0] - px) < 1e-3 and abs(m[2][0] - py) < 1e-3
    # the full Moon (V -12.7) on a 13.5 ke-, 3.3 e-/ADU, 12-bit sensor: every touched pixel but the thinnest
    # slivers of the limb saturates the ADC (4095); none beyond it lights up
    sat = SensorConfig(full_well_e=13500.0, gain_e_per_adu=3.3, bit_depth=12, bias_adu=32.0,
                       bright_objects=({**moon, "vmag": -12.7},))
    a = render_star_fields(np.zeros((1, 0)), np.zeros((1, 0)), np.zeros((1, 0)), None, 256, 256, sat,
                           camera=CAM, attitude=A)[0]
    n_sat = int((a == 4095).sum())
    assert inside.sum() <= n_sat <= touched.sum() and np.all(a[~touched] == 32)
    assert abs(n_sat - math.pi * R * R) < 2 * math.pi * R                  # pi R^2 within the limb's pixels


def test_bright_point_saturates_and_is_not_cut():
    # Venus (V -4.6) as a point: its core clips at the full well; its wings reach beyond the 4-sigma star
    # window without a step (the 10-sigma bright-object window)
    A = _looking_at(10.0, 5.0)
    cfg = dataclasses.replace(CONT, full_well_e=2e5, psf_sigma_px=0.8, psf_window_sigma=4.0,
                              bright_objects=({"ra_deg": 10.0, "dec_deg": 5.0, "vmag": -4.6, "radius_px": 0.0},))
    img = _render(np.zeros((1, 0)), np.zeros((1, 0)), np.zeros((1, 0)), cfg, 256, 256, camera=CAM, attitude=A)[0]
    assert img.max() == 2e5 and (img == 2e5).sum() >= 4
    row = img[128, 128:]
    assert row[6] > 0                     # 6 px = 7.5 sigma: beyond the stars' ceil(4 * 0.8 + 1) = 5 px window


# ----------------------------------------------------------------------------------------- ADC
@pytest.mark.parametrize("bits", [8, 12, 16])
def test_adc_full_scale_and_full_well_clip(bits):
    full = 2 ** bits - 1
    x, y = np.array([[10.3, 30.7]]), np.array([[10.6, 20.2]])
    # the ADC clips first: the star core sits at 2^b - 1, never above; the sky at the bias
    cfg = SensorConfig(gain_e_per_adu=1.0, full_well_e=1e12, bit_depth=bits, bias_adu=3.0, psf_sigma_px=1.0,
                       read_noise_e=0.4, shot_noise=True)
    img = render_star_fields(x, y, np.array([[1e7, 10.0]]), None, 40, 32, cfg, np.array([9], np.uint64))[0]
    assert img.max() == full and (img == full).sum() >= 9 and img.dtype == np.uint16
    assert np.all(img <= full) and np.median(img) in (2, 3)
    # the well clips first: saturated pixels hold floor(full_well / g + bias), noise-free and (less 0.1 e- of
    # read noise, added after the well) with shot and read noise
    g = 2.0 ** (bits - 8)
    well = 100.0 * g
    cfg = SensorConfig(gain_e_per_adu=g, full_well_e=well, bit_depth=bits, bias_adu=7.0, psf_sigma_px=1.0)
    img = render_star_fields(x, y, np.array([[1e4 * g, 1.0]]), None, 40, 32, cfg)[0]
    assert img.max() == math.floor(well / g + 7.0) == 107 and (img == 107).sum() >= 4
    noisy = dataclasses.replace(cfg, shot_noise=True, read_noise_e=0.1)
    img = render_star_fields(x, y, np.array([[1e4 * g, 1.0]]), None, 40, 32, noisy, np.array([3], np.uint64))[0]
    assert img.max() == 107 and (img >= 106).sum() >= 4


# ----------------------------------------------------------------------------------------- presets
def test_presets_and_example_resolve_and_run():
    from pathlib import Path

    from dualsight.jobs.kinds import star

    spec, _ = star.resolve("realistic", None)
    s = spec.sensor
    assert (s.psf_model, s.full_well_e, s.read_noise_e, s.bit_depth) == ("defocus", 13500.0, 13.0, 12)
    assert not s.is_ideal and not s.needs_camera
    ideal, _ = star.resolve("ideal", None)
    assert ideal.sensor.is_ideal and ideal.sensor.full_well_e == 1e12
    example = Path(__file__).resolve().parents[1] / "examples" / "star" / "realistic_sensor.toml"
    ex, _ = star.resolve(None, example)
    assert ex.sensor == dataclasses.replace(s, stray_light_e=(20.0, 0.02, 0.01), rate_deg_s=(0.0, 0.1, 0.05),
                                            bright_objects=ex.sensor.bright_objects)
    assert len(ex.sensor.bright_objects) == 1
    assert star.spec_from_dict(ex.to_dict()) == ex
    out = star.compute_batch(ex, star.make_context(ex), np.arange(4))
    assert out["rendered"].t_detect_ns is not None                         # dense path
    st = out["tables"]["star_cases"].column("status").to_pylist()
    assert st.count("success") >= 3, st


def test_a_star_job_smears_its_stars_by_its_rate():
    """The job passes the camera and each case's attitude to the renderer: with a rate of 3 deg/s about the
    camera's y axis for 0.1 s, a star near the centre moves L = w t fx ~ 19 px along x, so its image's
    second moment along x grows by L^2/12 (uniform motion), and not along y."""
    from dualsight.jobs.kinds import star

    base, _ = star.resolve("ideal", None, seed=3, cases=8)
    smeared = dataclasses.replace(base, sensor=dataclasses.replace(base.sensor, rate_deg_s=(0.0, 3.0, 0.0)))
    L = math.radians(3.0) * base.sensor.exposure_s * base.camera.fx
    grew = []
    for case in range(8):
        moments = []
        for spec in (base, smeared):
            out = star.compute_batch(spec, star.make_context(spec), np.array([case]), keep_images=True)
            f = out["field"]
            img = out["rendered"].images[0].astype(np.float64) - float(spec.sensor.empty_pixel_adu())
            d = np.hypot(f.x[0][:, None] - f.x[0][None, :], f.y[0][:, None] - f.y[0][None, :])
            lonely = (np.where(f.valid[0][None, :], d, np.inf) + np.diag(np.full(len(d), np.inf))).min(1) > 60
            ok = (f.inside[0] & lonely & (np.abs(f.x[0] - base.camera.cx) < 300)
                  & (np.abs(f.y[0] - base.camera.cy) < 250))
            if not ok.any():
                break
            k = int(np.argmax(np.where(ok, f.flux_e[0], -1)))
            x0, y0 = int(f.x[0, k]), int(f.y[0, k])
            win = img[y0 - 25:y0 + 26, x0 - 25:x0 + 26]
            yy, xx = np.mgrid[y0 - 25:y0 + 26, x0 - 25:x0 + 26] + 0.5
            w = win.sum()
            mx, my = (win * xx).sum() / w, (win * yy).sum() / w
            moments.append(((win * (xx - mx) ** 2).sum() / w, (win * (yy - my) ** 2).sum() / w))
        if len(moments) == 2:
            grew.append((moments[1][0] - moments[0][0], moments[1][1] - moments[0][1]))
    assert len(grew) >= 2
    for gx, gy in grew:      # quantisation of the faint smeared pixels and the field angle: 10 %
        assert gx == pytest.approx(L ** 2 / 12, rel=0.1) and abs(gy) < 0.05 * L ** 2 / 12, (gx, gy, L)


def test_a_runs_identity_covers_the_psf_images_content(tmp_path):
    """The spec stores the measured PSF's content hash (``psf_image_sha256``), not only its path: the same path with
    other content is another run (another spec hash), and a stored spec (a run being resumed or replayed) whose
    file has changed since fails in one line naming the file, before the lake is touched."""
    from dualsight.errors import ConfigError as CfgErr
    from dualsight.errors import InputError
    from dualsight.jobs.kinds import star
    from dualsight.jobs.engine.runner import run_job, spec_hash
    from dualsight.warehouse.lake import Lake

    path = tmp_path / "psf.npy"
    np.save(path, _measured_psf())
    d, _ = star.resolve_spec("ideal", None, cases=4)
    d["sensor"].update(psf_model="image", psf_image=str(path))
    d["batch_size"] = 4
    first = star.spec_from_dict(d).to_dict()
    assert len(first["sensor"]["psf_image_sha256"]) == 64
    lake = Lake(tmp_path / "lake")
    run_job("star", first, n_cases=4, lake=lake, run_id="psf", progress=False)
    files = lambda: sorted((p.name, p.stat().st_size) for p in (tmp_path / "lake").rglob("*") if p.is_file())
    before = files()
    np.save(path, _measured_psf()[::-1].copy())                 # the same file name, another PSF
    second = star.spec_from_dict(d).to_dict()                    # the TOML again: a new content hash
    assert second["sensor"]["psf_image_sha256"] != first["sensor"]["psf_image_sha256"]
    assert spec_hash("star", second, 4) != spec_hash("star", first, 4)
    with pytest.raises(CfgErr, match="psf_image_sha256.*psf.npy.*not the one"):
        run_job("star", first, n_cases=8, lake=lake, run_id="psf", progress=False)    # resume the stored spec
    with pytest.raises(InputError, match=r"other settings \(spec keys sensor\)"):
        run_job("star", second, n_cases=4, lake=lake, run_id="psf", progress=False)   # not mixed into that run
    assert files() == before                                     # the lake untouched by either refusal
