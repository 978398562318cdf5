"""The real-sensor detector's candidate screening, step 4 (``kernels/detect_hot_pixels.py``): each candidate's
brightest pixel, noise, saturation and hot-pixel test, checked against analytic truth (a lone spike on a flat frame,
a pixel-centred noise-free star, whose peak-to-4-neighbour ratio is the sharpness limit by construction) and the
compiled loop against the numpy stage on frames with spikes on the edges, saturated pixels and both filter
resolutions."""

import dataclasses
import math

import numpy as np
import pytest

from dualsight.kernels.detect_candidates import FilteredNoise
from dualsight.kernels.detect_hot_pixels import screen_candidates, screen_candidates_compiled
from dualsight.kernels.detect_local import LocalDetectConfig, BinnedView

CFG = LocalDetectConfig()


def _Phi(z):
    return 0.5 * (1.0 + math.erf(z / math.sqrt(2.0)))


def _flat_noise(H, W, inv_value, ratio=0.3):
    inv = np.full((H, W), inv_value, np.float32)
    return inv, FilteredNoise(inv, ratio, np.ones(0, np.float32), np.ones(0, np.float32))


def _both(R, inv, img, pr, pc, Z, nf, sat, s, cfg=CFG, b=1, spike_tap=None):
    """The numpy stage and the compiled loop on the same inputs (``b`` = 2: Z and its noise 2 x 2-binned)."""
    Zv, nv = (BinnedView(Z, Z.shape), BinnedView(nf, Z.shape)) if b == 2 else (Z, nf)
    ref = screen_candidates(R, inv, img, pr, pc, Zv, nv, sat, s, cfg, spike_tap)
    got = screen_candidates_compiled(R, inv, img, pr, pc, Z, nf.inv, nf.row, nf.col, nf.ratio, b, sat, s, cfg,
                                     spike_tap)
    return ref, got


def test_a_lone_spike_is_hot_and_a_pixel_centred_star_is_not():
    """A spike of 50 sigma on a flat, noise-free residual: t = R_p - r_max x 0 = 50 sigma > k sigma sqrt(1 + r_max^2
    / 4) (k = 5): hot, and with Z at the spike equal to its own excess times k00 / sigma_F it is dropped.  A noise-free
    pixel-integrated Gaussian star centred on a pixel: its peak over its 4-neighbour mean is the sharpness limit
    (the largest ratio a star gives), so t = R_p (1 - (1 + tolerance)) < 0: not hot, kept.  Each candidate sits one
    pixel off its brightest pixel, which the screen finds."""
    H, W, sigma, s = 64, 64, 2.0, 0.9
    R = np.zeros((H, W), np.float32)
    R[20, 30] = 50 * sigma                                  # the spike
    p = np.array([_Phi((i + 0.5) / s) - _Phi((i - 0.5) / s) for i in range(-4, 5)])
    R[36:45, 16:25] = 2000.0 * np.outer(p, p)              # the star, centred on pixel (40, 20)
    img = R + 100.0
    inv, nf = _flat_noise(H, W, 1.0 / sigma)
    Z = np.zeros((H, W), np.float32)
    tap = 0.17
    Z[20, 30] = 50 * sigma * tap / (nf.ratio / (1.0 / sigma))     # all of Z at the spike is the spike's excess
    Z[40, 20] = 100.0
    pr, pc = np.array([21, 39]), np.array([29, 21])
    for r0, c0, noise, is_sat, hot, keep in _both(R, inv, img, pr, pc, Z, nf, None, s, spike_tap=tap):
        assert list(r0) == [20, 40] and list(c0) == [30, 20]
        assert noise == pytest.approx([sigma, sigma])
        assert list(hot) == [True, False] and list(keep) == [False, True] and not is_sat.any()


def test_a_hot_pixel_on_a_bright_star_is_flagged_and_the_star_kept():
    """Z without the spike's excess stays far above k_sigma on a bright star: hot, kept (its fit gives the spike
    weight 0); and saturation at the peak is not a hot pixel."""
    H, W, sigma, s = 48, 48, 2.0, 0.9
    p = np.array([_Phi((i + 0.5) / s) - _Phi((i - 0.5) / s) for i in range(-4, 5)])
    R = np.zeros((H, W), np.float32)
    R[20:29, 20:29] = 5000.0 * np.outer(p, p)
    R[24, 24] += 3000.0                                           # a hot pixel on the star's peak
    R[10, 10] = 4000.0                                            # a saturated spike
    img = R + 100.0
    inv, nf = _flat_noise(H, W, 1.0 / sigma)
    Z = np.full((H, W), 5000.0, np.float32)
    for r0, c0, noise, is_sat, hot, keep in _both(R, inv, img, np.array([24, 10]), np.array([24, 10]), Z, nf,
                                                  4000.0, s):
        assert list(hot) == [True, False] and list(keep) == [True, True] and list(is_sat) == [False, True]


@pytest.mark.parametrize("b", [1, 2])
@pytest.mark.parametrize("sat", [None, 1500.0])
def test_the_compiled_screen_is_the_numpy_stage(b, sat):
    """On a noisy frame with spikes everywhere (edges and corners included), stars, saturated pixels, a noise map
    that varies and Z's noise with edge factors, every candidate (all the frame's edge pixels, the spikes and
    random pixels) gets the same brightest pixel, noise, flags and decision from both, bit for bit."""
    rng = np.random.default_rng(3)
    H, W = 97, 130
    sigma = rng.uniform(2.0, 6.0, (H, W)).astype(np.float32)
    R = (sigma * rng.standard_normal((H, W))).astype(np.float32)
    spikes = (rng.integers(0, H, 60), rng.integers(0, W, 60))
    R[spikes] += rng.uniform(5, 400, 60).astype(np.float32) * sigma[spikes]
    R[[0, 0, H - 1, H - 1], [0, W - 1, 0, W - 1]] += 300.0
    img = (R + 1000.0).astype(np.float32)
    inv = (1.0 / sigma).astype(np.float32)
    Hz, Wz = (H + 1) // b, (W + 1) // b
    invz = inv[:Hz * b:b, :Wz * b:b].copy() if b == 2 else inv
    Z = (rng.uniform(-1, 40, (invz.shape[0], invz.shape[1]))).astype(np.float32)
    edge = np.linspace(0.6, 0.95, 3).astype(np.float32)
    nf = FilteredNoise(invz, np.float32(0.31), edge, edge[::-1].copy())
    border = [(r, c) for r in range(H) for c in range(W) if r in (0, H - 1) or c in (0, W - 1)]
    pr = np.r_[[r for r, _ in border], spikes[0], rng.integers(0, H, 200)].astype(np.int64)
    pc = np.r_[[c for _, c in border], spikes[1], rng.integers(0, W, 200)].astype(np.int64)
    cfg = dataclasses.replace(CFG, k_sigma=5.0)
    ref, got = _both(R, inv, img, pr, pc, Z, nf, sat, 0.9, cfg, b=b, spike_tap=0.04 if b == 2 else None)
    for a, g in zip(ref, got):
        assert a.dtype.kind == g.dtype.kind and np.array_equal(a, g)
    hot, keep = ref[4], ref[5]
    assert 20 < hot.sum() and (hot & ~keep).any() and (hot & keep).any()      # the test exercises both branches
    if sat is not None:
        assert ref[3].any()


def test_without_the_hot_pixel_test_every_candidate_is_kept():
    H, W = 32, 32
    R = np.zeros((H, W), np.float32)
    R[5, 5] = 1e4
    inv, nf = _flat_noise(H, W, 1.0)
    cfg = dataclasses.replace(CFG, hot_pixel_k=0.0)
    for out in _both(R, inv, R, np.array([5]), np.array([5]), np.zeros((H, W), np.float32), nf, None, 0.9, cfg):
        assert list(out[4]) == [False] and list(out[5]) == [True]
