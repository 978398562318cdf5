"""The sensor-noise render path's samplers against their exact distributions (issue 13, point 2).

* Sky pixels draw their final ADU value in one uniform from a tabulated CDF of shot noise + read noise + ADC
  (``kernels/starfield.sky_adu_table``): the rendered histograms are compared by chi-square with the exact pmf,
  computed here independently (Poisson pmf by ``math.lgamma``, the normal CDF by ``math.erf``, the ADC floor
  and clips by hand), and with the per-effect samplers the other pixels still use.
* Sparse hot pixels are drawn by the geometric gaps of a Bernoulli process along each row: counts, gaps and
  columns against the exact binomial / geometric / uniform laws.
* ``rng.inverse_table`` equals ``numpy.searchsorted`` (exact inversion) bit for bit.

Chi-square limits: the Wilson-Hilferty approximation of the chi-square quantile at z = 5 (p ~ 3e-7).
"""

import dataclasses
import math

import numpy as np
import pytest

from dualsight.kernels import rng as krng
from dualsight.kernels import starfield as sf
from dualsight.kernels.sensor_config import SensorConfig
from dualsight.kernels.sky_noise import sky_adu_table
from dualsight.kernels.starfield import render_star_fields
from helpers import phi


def chi2_limit(dof: int, z: float = 5.0) -> float:
    return dof * (1.0 - 2.0 / (9.0 * dof) + z * math.sqrt(2.0 / (9.0 * dof))) ** 3


def chi2(obs: np.ndarray, expected: np.ndarray, min_expected: float = 5.0) -> tuple[float, int]:
    """Chi-square statistic and degrees of freedom, pooling the bins of expectation < min_expected into one."""
    obs = np.asarray(obs, np.float64)
    expected = np.asarray(expected, np.float64)
    big = expected >= min_expected
    o = np.append(obs[big], obs[~big].sum())
    e = np.append(expected[big], expected[~big].sum())
    if e[-1] < min_expected:   # the pooled bin too small: fold it into the largest
        i = np.argmax(e[:-1])
        o[i] += o[-1]
        e[i] += e[-1]
        o, e = o[:-1], e[:-1]
    return float(((o - e) ** 2 / e).sum()), int(o.size - 1)


def exact_sky_pmf(cfg: SensorConfig) -> dict[int, float]:
    """P(ADU = a) of a star-free, not-hot pixel: e = min(Poisson(base), full_well) (base without shot noise),
    y = (e + R z) / g + bias + 1e-9, ADU = clip(floor(y), 0, 2^bits - 1); summed term by term."""
    lam, g, R, b, top = cfg.base_e, cfg.gain_e_per_adu, cfg.read_noise_e, cfg.bias_adu, cfg.max_adu
    if cfg.shot_noise:
        ks = range(0, int(lam + 15 * math.sqrt(lam) + 40))
        pk = [(min(float(k), cfg.full_well_e), math.exp(-lam + k * math.log(lam) - math.lgamma(k + 1)))
              for k in ks]
    else:
        pk = [(min(lam, cfg.full_well_e), 1.0)]
    pmf: dict[int, float] = {}
    for e, p in pk:
        if R == 0:
            a = int(min(max(math.floor(e / g + b + 1e-9), 0), top))
            pmf[a] = pmf.get(a, 0.0) + p
            continue
        mid = e / g + b
        lo = max(0, int(mid - 15 * R / g) - 1)
        hi = min(top, int(mid + 15 * R / g) + 2)
        for a in range(lo, hi + 1):
            # y in [a, a + 1) <=> z in [((a - b - eps) g - e) / R, ((a + 1 - b - eps) g - e) / R)
            up = 1.0 if a >= top else phi(((a + 1 - b - 1e-9) * g - e) / R)
            dn = 0.0 if a <= 0 else phi(((a - b - 1e-9) * g - e) / R)
            pmf[a] = pmf.get(a, 0.0) + p * (up - dn)
    return pmf


def _sky(cfg: SensorConfig, B: int = 6, W: int = 400, H: int = 300, seed0: int = 1) -> np.ndarray:
    z = np.zeros((B, 0))
    return render_star_fields(z, z, z, None, W, H, cfg, np.arange(seed0, seed0 + B, dtype=np.uint64))


SKY_CONFIGS = {
    # the noisy_sensor example's sky: 52 e- (Poisson), 10 e- read noise, 5 e-/ADU, no bias (clip at 0 ADU)
    "noisy_sensor": SensorConfig(gain_e_per_adu=5.0, exposure_s=0.1, dark_current_e_per_s=20.0, sky_background_e=50.0,
                                 shot_noise=True, read_noise_e=10.0),
    "read_only": SensorConfig(gain_e_per_adu=2.0, read_noise_e=4.0, sky_background_e=200.0, bias_adu=10.0),
    "shot_only": SensorConfig(gain_e_per_adu=1.5, shot_noise=True, sky_background_e=7.3, bias_adu=3.0),
    # full well at 40 e- of a 35 e- sky, a 6-bit ADC with the bias near its top: both clips carry mass
    "clipped": SensorConfig(gain_e_per_adu=0.7, shot_noise=True, sky_background_e=35.0, read_noise_e=2.0,
                            full_well_e=40.0, bit_depth=6, bias_adu=6.0),
    "sub_adu_noise": SensorConfig(gain_e_per_adu=20.0, shot_noise=True, sky_background_e=3.0, read_noise_e=1.5,
                                  bias_adu=100.0),
}


@pytest.mark.parametrize("name", sorted(SKY_CONFIGS))
def test_sky_adu_table_is_the_exact_pmf(name):
    cfg = SKY_CONFIGS[name]
    cdf, guide, a0 = sky_adu_table(cfg)
    pmf = exact_sky_pmf(cfg)
    table = np.diff(np.concatenate([[0.0], cdf]))
    for a, p in pmf.items():
        j = a - int(a0)
        got = table[j] if 0 <= j < table.size else 0.0
        assert got == pytest.approx(p, abs=1e-13), (a, got, p)
    assert cdf[-1] == pytest.approx(1.0, abs=1e-13)
    assert guide.size >= 16 * cdf.size and guide.size & (guide.size - 1) == 0


@pytest.mark.parametrize("name", sorted(SKY_CONFIGS))
def test_rendered_sky_histogram_matches_the_exact_pmf(name):
    cfg = SKY_CONFIGS[name]
    assert sky_adu_table(cfg) is not None  # the tabulated path is what is tested
    v = _sky(cfg).astype(np.int64).ravel()
    n = v.size
    pmf = exact_sky_pmf(cfg)
    support = np.arange(0, cfg.max_adu + 1)
    exp_ = n * np.array([pmf.get(int(a), 0.0) for a in support])
    obs = np.bincount(v, minlength=support.size)[:support.size]
    assert obs.sum() == n
    stat, dof = chi2(obs, exp_)
    assert stat < chi2_limit(dof), (name, stat, dof)
    # and the first two moments (sharper for a shifted or widened distribution)
    mean = sum(a * p for a, p in pmf.items())
    var = sum(a * a * p for a, p in pmf.items()) - mean ** 2
    assert abs(v.mean() - mean) < 5 * math.sqrt(var / n)
    assert abs(v.var() - var) < 5 * var * math.sqrt(2.0 / n) + 1e-12


def test_table_and_per_effect_samplers_agree(monkeypatch):
    # the same sensor through the per-effect samplers (Poisson table / PTRS, AS241 normal, ADC in the kernel):
    # a two-sample chi-square between the histograms
    cfg = SKY_CONFIGS["noisy_sensor"]
    a = _sky(cfg, seed0=100).astype(np.int64).ravel()
    monkeypatch.setattr(sf, "sky_adu_table", lambda _cfg: None)
    b = _sky(cfg, seed0=100).astype(np.int64).ravel()
    assert not np.array_equal(a, b)  # really the other path
    m = max(a.max(), b.max()) + 1
    ha, hb = np.bincount(a, minlength=m).astype(float), np.bincount(b, minlength=m).astype(float)
    keep = ha + hb >= 10
    ha = np.append(ha[keep], ha[~keep].sum())
    hb = np.append(hb[keep], hb[~keep].sum())
    nz = ha + hb > 0
    stat = (((ha - hb) ** 2) / (ha + hb))[nz].sum()  # equal sample sizes
    assert stat < chi2_limit(int(nz.sum()) - 1), stat


def test_no_table_for_continuous_adu_or_stray_light():
    assert sky_adu_table(dataclasses.replace(SKY_CONFIGS["noisy_sensor"], quantize=False)) is None
    assert sky_adu_table(SensorConfig()) is None  # no random effect


def test_star_pixels_keep_their_signal_through_the_table_path():
    # a bright star on the tabulated sky: its flux (sum above the sky) within the shot + read noise
    cfg = dataclasses.replace(SKY_CONFIGS["noisy_sensor"], psf_sigma_px=1.0, bias_adu=20.0)
    F = 50000.0
    img = render_star_fields([[100.5]], [[80.5]], [[F]], None, 200, 160, cfg, np.array([5], np.uint64))
    sky = (cfg.base_e / cfg.gain_e_per_adu + cfg.bias_adu - 0.5)
    win = img[0, 70:91, 90:111].astype(np.float64) - sky
    sd = math.sqrt(F + win.size * (cfg.base_e + cfg.read_noise_e ** 2)) / cfg.gain_e_per_adu
    assert abs(win.sum() - F / cfg.gain_e_per_adu) < 5 * sd


# ----------------------------------------------------------------------------------------- hot pixels
def _hot_map(p: float, B: int, W: int, H: int, seed0: int = 1, **kw) -> np.ndarray:
    cfg = SensorConfig(gain_e_per_adu=1.0, hot_pixel_fraction=p, hot_pixel_e=3000.0, **kw)
    z = np.zeros((B, 0))
    return render_star_fields(z, z, z, None, W, H, cfg, np.arange(seed0, seed0 + B, dtype=np.uint64)) == 3000


@pytest.mark.parametrize("p", [1e-3, 0.015])
def test_sparse_hot_pixels_are_a_bernoulli_process(p):
    assert 0 < p <= sf.HOT_GEOMETRIC_MAX  # the geometric-gap sampler
    B, W, H = 8, 512, 400
    hot = _hot_map(p, B, W, H)
    n = hot.size
    assert abs(hot.sum() - p * n) < 5 * math.sqrt(p * (1 - p) * n)
    # hot pixels per row: Binomial(W, p)
    per_row = hot.sum(axis=2).ravel()
    kmax = int(W * p + 8 * math.sqrt(W * p) + 8)
    pmf = np.array([math.exp(math.lgamma(W + 1) - math.lgamma(k + 1) - math.lgamma(W - k + 1)
                             + k * math.log(p) + (W - k) * math.log1p(-p)) for k in range(kmax)])
    obs = np.bincount(per_row, minlength=kmax)[:kmax]
    stat, dof = chi2(obs, per_row.size * pmf)
    assert stat < chi2_limit(dof), ("per row", stat, dof)
    # gaps between consecutive hot pixels of a row: Geometric(p) (cool pixels between them), truncated by
    # the row: P(gap = g | both in the row) is p (1 - p)^g weighted by the W - 1 - g places it fits
    gaps = []
    for row in hot.reshape(-1, W):
        c = np.flatnonzero(row)
        gaps.append(np.diff(c) - 1)
    gaps = np.concatenate(gaps)
    gs = np.arange(W - 1)
    w = (1 - p) ** gs * (W - 1 - gs)
    band = np.minimum((np.cumsum(w) / w.sum() * 20).astype(np.int64), 19)  # 20 bins of ~equal probability
    stat, dof = chi2(np.bincount(band[gaps], minlength=20), gaps.size * np.bincount(band, weights=w / w.sum(),
                                                                                    minlength=20))
    assert stat < chi2_limit(dof), ("gaps", stat, dof)
    # columns: uniform (in 32 bands)
    cols = hot.sum(axis=(0, 1)).reshape(32, -1).sum(axis=1)
    stat, dof = chi2(cols, np.full(32, cols.sum() / 32))
    assert stat < chi2_limit(dof), ("columns", stat, dof)


def test_hot_pixel_maps_per_case_and_fixed():
    a = _hot_map(0.01, 3, 300, 200)
    assert not np.array_equal(a[0], a[1])
    fixed = _hot_map(0.01, 3, 300, 200, hot_pixel_seed=77)
    assert np.array_equal(fixed[0], fixed[1]) and np.array_equal(fixed[1], fixed[2])
    dense = _hot_map(0.3, 2, 300, 200)  # above HOT_GEOMETRIC_MAX: one draw per pixel
    assert abs(dense.mean() - 0.3) < 5 * math.sqrt(0.3 * 0.7 / dense.size)


# ----------------------------------------------------------------------------------------- inversion
def test_inverse_table_is_exact_inversion():
    ti = __import__("dualsight.kernels.taichi_runtime", fromlist=["ensure_init"]).ensure_init()

    @ti.kernel
    def inv(u: ti.types.ndarray(dtype=ti.f64, ndim=1), cdf: ti.types.ndarray(dtype=ti.f64, ndim=1),
            guide: ti.types.ndarray(dtype=ti.i32, ndim=1), out: ti.types.ndarray(dtype=ti.i32, ndim=1)):
        for i in range(u.shape[0]):
            out[i] = krng.inverse_table(u[i], cdf, guide)

    rs = np.random.default_rng(3)
    for p in (rs.dirichlet(np.full(40, 0.3)), np.array([1e-20, 0.5, 1e-12, 0.3, 0.2 - 1e-12])):
        cdf = np.cumsum(p)
        cdf[-1] = min(cdf[-1], 1.0)
        guide = krng.inverse_table_np(cdf)
        # random u, every CDF value, its neighbours and the cell edges
        edges = np.arange(guide.size + 1) / guide.size
        u = np.concatenate([rs.random(200_000), cdf, np.nextafter(cdf, 0), np.nextafter(cdf, 1), edges,
                            np.nextafter(edges, 1)])
        u = u[(u > 0) & (u < 1)]
        out = np.empty(u.size, np.int32)
        inv(u, cdf, guide, out)
        want = np.searchsorted(cdf, u, side="left")
        want[want >= cdf.size] = -1
        np.testing.assert_array_equal(out, want)


def test_sixteen_bit_draws_invert_like_the_composite_uniform():
    """``rng.inverse_table_bits`` with 16 bits h and the refinement v = u01_key(key, index): the index of the
    smallest cdf >= u for u = (h + v) / 2^16 (numpy.searchsorted), for every h of CDFs whose steps fall inside
    16-bit cells (steps 1e-20 and 1e-12 apart, a 2^-16 cell holding several steps), and its tail (-1)."""
    ti = __import__("dualsight.kernels.taichi_runtime", fromlist=["ensure_init"]).ensure_init()

    @ti.kernel
    def inv(h: ti.types.ndarray(dtype=ti.u64, ndim=1), key: ti.u64, cdf: ti.types.ndarray(dtype=ti.f64, ndim=1),
            guide: ti.types.ndarray(dtype=ti.i32, ndim=1), out: ti.types.ndarray(dtype=ti.i32, ndim=1)):
        for i in range(h.shape[0]):
            gshift = 16
            while (1 << (16 - gshift)) < guide.shape[0]:
                gshift -= 1
            out[i] = krng.inverse_table_bits(h[i], 16, gshift, key, ti.cast(i, ti.u64), cdf, guide)

    rs = np.random.default_rng(5)
    key = np.uint64(0x9E3779B97F4A7C15)
    for p in (rs.dirichlet(np.full(40, 0.3)), np.array([1e-20, 0.5, 1e-12, 0.3, 0.2 - 1e-12]),
              np.concatenate([np.full(30, 1e-6), [1.0 - 30e-6]]), rs.dirichlet(np.full(3000, 0.5))):
        cdf = np.cumsum(p)
        cdf[-1] = min(cdf[-1], 1.0)
        if p.size == 40:
            cdf[-1] = 1.0 - 3e-6              # a table that stops short: its tail gives -1
        guide = krng.inverse_table_np(cdf, min(16, 65536 // cdf.size))
        assert guide.size <= 65536
        h = np.tile(np.arange(65536, dtype=np.uint64), 3)
        out = np.empty(h.size, np.int32)
        inv(h, key, cdf, guide, out)
        v = krng.u01_key_np(key, np.arange(h.size, dtype=np.uint64))
        u = (h.astype(np.float64) + v) / 65536.0
        want = np.searchsorted(cdf, u, side="left")
        want[want >= cdf.size] = -1
        np.testing.assert_array_equal(out, want)
