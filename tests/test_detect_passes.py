"""The local detector's compiled full-frame passes (kernels/detect_passes.py) against brute force in numpy."""

import numpy as np
import pytest

from dualsight.kernels.detect_background import tile_background


def test_tile_background_engines_agree_on_a_star_frame():
    """The compiled clipping gives the numpy path's tile levels and noises to float32 rounding (16-bit frame
    with stars, a gradient and 2-ADU noise), and both the truth's level within 0.1 sigma."""
    rng = np.random.default_rng(7)
    H, W = 192, 256
    yy, xx = np.mgrid[0:H, 0:W]
    sky = 300 + 0.2 * xx + 0.1 * yy
    img = sky + rng.normal(0, 2.0, (H, W))
    for cx, cy in rng.uniform(5, 180, (40, 2)):
        img += 800 * np.exp(-((xx + 0.5 - cx) ** 2 + (yy + 0.5 - cy) ** 2) / 2.0)
    img = np.rint(img).astype(np.uint16)
    a = tile_background(img, 32, 3.0, 3, 1, "numpy")
    b = tile_background(img, 32, 3.0, 3, 1, "taichi")
    np.testing.assert_allclose(b[0], a[0], rtol=0, atol=1e-3)
    np.testing.assert_allclose(b[1], a[1], rtol=1e-4)
    centre = sky.reshape(6, 32, 8, 32).mean((1, 3))
    assert np.abs(b[0] - centre).max() < 0.1 * 2.0 * 3      # tiles with stars: within a few tenths of sigma
    assert np.median(np.abs(b[0] - centre)) < 0.1 * 2.0


@pytest.mark.parametrize("connectivity", [8, 4])
def test_foreground_components_are_opencvs_and_the_maxima_a_dilations(connectivity):
    """The compiled pass's components are OpenCV's partition of the foreground (Z > threshold), numbered in the
    order of their first pixel in raster order; its peaks are the foreground pixels with Z >= the 3 x 3 grey
    dilation of Z (edge pixels replicated: outside the frame ignored).  Frames of blobs touching every edge."""
    import cv2

    from dualsight.kernels.detect_passes import foreground_components

    rng = np.random.default_rng([24, connectivity])
    for H, W in ((1, 7), (9, 1), (37, 53), (64, 48)):
        Z = (3 * cv2.GaussianBlur(rng.normal(0, 1, (H, W)).astype(np.float32), (0, 0), 1.0)).astype(np.float32)
        Z[rng.random((H, W)) < 0.02] = 9.0          # plateaus of equal maxima
        fg = Z > 0.4
        f = np.flatnonzero(fg)
        lab, peak = foreground_components(f, Z, connectivity)
        n, cvlab = cv2.connectedComponents(fg.astype(np.uint8), connectivity=connectivity, ltype=cv2.CV_32S)
        ref = cvlab.ravel()[f] - 1
        assert lab.max(initial=-1) + 1 == n - 1
        pairs = set(zip(lab.tolist(), ref.tolist()))
        assert len(pairs) == n - 1                   # one-to-one: the same partition
        first = np.unique(lab, return_index=True)[1]
        np.testing.assert_array_equal(lab[np.sort(first)], np.arange(n - 1))     # raster order of first pixels
        dil = cv2.dilate(Z, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
        np.testing.assert_array_equal(peak, (Z >= dil).ravel()[f])


def truncation_correction(c):
    """1 / sqrt(variance of a standard normal truncated to [-c, c]) = 1 / sqrt(1 - 2 c phi(c) / (2 Phi(c) - 1))."""
    import math

    phi = math.exp(-0.5 * c * c) / math.sqrt(2.0 * math.pi)
    return 1.0 / math.sqrt(1.0 - 2.0 * c * phi / math.erf(c / math.sqrt(2.0)))


@pytest.mark.parametrize("kind", ["wide", "tied", "clamped", "capped", "float", "stars"])
def test_sorted_clipped_stats_equal_the_numpy_clipping(kind):
    """The compiled clipping of sorted rows gives numpy's clipped_stats (searchsorted / reduceat over all rows,
    bisection for the MAD, lattice_start for tied medians) to float32 rounding, for 0, 2 and 3 windows: normal
    16-bit rows, rows whose noise spans 1-2 ADU (tied medians), 8-bit rows clamped at 0, rows capped at their top
    (a quantile's run of equal values reaching the row's end), float rows, rows with a bright tail; and a normal row's level and sigma are its mean and standard deviation within their errors."""
    import math

    from dualsight.kernels.detect_background import clipped_stats
    from dualsight.kernels.detect_passes import sorted_clipped_stats

    rng = np.random.default_rng([24, len(kind)])
    T, N = 300, 256
    s = {"wide": lambda: rng.normal(1000, 20, (T, N)).round().astype(np.uint16),
         "tied": lambda: np.clip(rng.normal(3, 1.2, (T, N)).round(), 0, None).astype(np.uint16),
         "clamped": lambda: np.clip(rng.normal(0.3, 1.0, (T, N)).round(), 0, None).astype(np.uint8),
         "capped": lambda: np.clip(rng.normal(3, 1.2, (T, N)).round(), 0, 4).astype(np.uint16),   # runs to the end
         "float": lambda: rng.normal(50, 3, (T, N)).astype(np.float32),
         "stars": lambda: np.concatenate([rng.normal(500, 5, (T, N - 26)), rng.uniform(500, 5000, (T, 26))],
                                         1).round().astype(np.uint16)}[kind]()
    s = np.sort(s, axis=1)
    corr = truncation_correction(3.0)
    for iters in (0, 2, 3):
        a = clipped_stats(s, 3.0, iters)
        b = sorted_clipped_stats(s, 3.0, iters, corr)
        scale = np.maximum(a[1], 1.0)
        np.testing.assert_allclose(b[0], a[0], rtol=0, atol=1e-4 * scale.max())
        np.testing.assert_allclose(b[1], a[1], rtol=1e-5, atol=1e-9)
        np.testing.assert_array_equal(b[2], a[2])
    if kind == "wide":         # mean 1000, sigma 20 (rounding adds 1/12 ADU^2): the level to ~3 x 20/sqrt(256)
        assert np.abs(b[0] - 1000).max() < 5 * 20 / math.sqrt(N) and abs(np.median(b[1]) - 20.0) < 0.5


def test_sorted_clipped_stats_mad_when_the_narrowest_run_is_the_last():
    """1.4826 MAD of [0, 1, 2, 3, 10, 11, 11, 11, 11] (median 10): |v - 10| sorted 0, 1, 1, 1, 1, 7, ... -> MAD 1, the
    run of the 5 largest values; written out, and numpy's."""
    import math

    from dualsight.kernels.detect_background import clipped_stats
    from dualsight.kernels.detect_passes import sorted_clipped_stats

    s = np.array([[0, 1, 2, 3, 10, 11, 11, 11, 11]], np.uint16)
    got = sorted_clipped_stats(s, 3.0, 0, truncation_correction(3.0))
    assert got[0][0] == 10.0 and got[1][0] == pytest.approx(1.4826)
    assert clipped_stats(s, 3.0, 0)[1][0] == pytest.approx(1.4826)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_the_row_sort_kind_changes_the_time_only(dtype, monkeypatch):
    """tile_background sorts the tiles' quarter samples with the kind row_sort_kind measured faster ("stable": radix,
    "quicksort": numpy's SIMD sort); the tile levels and noises are the same bits with either (a 16 / 8-bit frame with
    stars and a gradient, both engines)."""
    from dualsight.kernels import detect_background
    from dualsight.kernels.detect_background import row_sort_kind

    assert row_sort_kind(dtype) in ("stable", "quicksort")
    rng = np.random.default_rng([24, np.dtype(dtype).itemsize])
    H, W = 96, 160
    yy, xx = np.mgrid[0:H, 0:W]
    img = 40 + 0.1 * xx + rng.normal(0, 2.0, (H, W))
    img[rng.random((H, W)) < 0.01] = 250
    img = np.clip(np.rint(img), 0, 255).astype(dtype)
    for engine in ("numpy", "taichi"):
        got = []
        for kind in ("stable", "quicksort"):
            monkeypatch.setattr(detect_background, "row_sort_kind", lambda dt, kind=kind: kind)
            got.append(tile_background(img, 32, 3.0, 3, 3, engine))
        for a, b in zip(*got):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("connectivity", [8, 4])
def test_compiled_candidates_are_the_numpy_paths(connectivity):
    """find_candidates with the compiled pass (detect_passes.candidate_maxima: labelling, maxima, sort, deblending in
    one kernel) returns the numpy path's arrays in its order (sparse_components, a lexsort, the pairs' distance and
    dip tests): frames of blended blobs with several maxima (some closer than the deblending distance, some without a
    dip), plateaus of equal maxima (ties), blobs on every edge, and components over max_blob_pixels; for several
    deblending settings.  And a written-out case: two peaks 4 px apart with a dip are two stars, without it one."""
    import cv2

    from dualsight.kernels.detect_candidates import find_candidates
    from dualsight.kernels.detect_local import LocalDetectConfig

    rng = np.random.default_rng([24, connectivity, 1])
    n_multi = 0
    for H, W in ((1, 9), (7, 1), (40, 64), (96, 128)):
        Z = (4 * cv2.GaussianBlur(rng.normal(0, 1, (H, W)).astype(np.float32), (0, 0), 1.2)).astype(np.float32)
        for _ in range(H * W // 300):                 # bright blends: 2-3 Gaussians close together
            cy, cx = rng.uniform(0, H), rng.uniform(0, W)
            yy, xx = np.mgrid[0:H, 0:W]
            for _ in range(rng.integers(2, 4)):
                oy, ox = cy + rng.normal(0, 2.5), cx + rng.normal(0, 2.5)
                Z += rng.uniform(4, 30) * np.exp(-((yy - oy) ** 2 + (xx - ox) ** 2) / (2 * rng.uniform(0.6, 1.5) ** 2))
        Z[rng.random((H, W)) < 0.01] = 12.0            # plateaus of equal maxima
        Z = Z.astype(np.float32)
        for sep, contrast, maxpix in ((2.0, 0.2, 4096), (0.0, 0.0, 4096), (3.5, 0.5, 25), (1.0, 0.9, 4096)):
            want, got = [], []
            for engine, dst in (("numpy", want), ("taichi", got)):
                cfg = LocalDetectConfig(k_sigma=1.5, deblend_min_sep_px=sep, deblend_contrast=contrast,
                                        max_blob_pixels=maxpix, connectivity=connectivity, fit_engine=engine)
                dst.extend(find_candidates(Z, cfg))
            for a, b in zip(want[:3], got[:3]):
                np.testing.assert_array_equal(a, b)
            assert want[3] == got[3]
            n_multi += len(want[0]) - len(np.unique(want[2]))
    assert n_multi > 20                                  # components with more than one star were tested

    Z = np.zeros((9, 15), np.float32)
    Z[4, 3], Z[4, 7], Z[4, 4:7] = 10.0, 9.0, 6.0          # a dip to 6 < 0.8 x 9: two stars
    cfg = LocalDetectConfig(k_sigma=1.0, fit_engine="taichi")
    r, c, npix, n_large = find_candidates(Z, cfg)
    assert (r.tolist(), c.tolist(), npix.tolist(), n_large) == ([4, 4], [3, 7], [5, 5], 0)
    Z[4, 4:7] = 8.0                                      # 8 >= 0.8 x 9: one star
    assert find_candidates(Z, cfg)[1].tolist() == [3]
