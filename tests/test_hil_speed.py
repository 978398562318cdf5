"""Correctness of the speed work on the real-frame chain (issue 13, point 4; benchmarks/bench_hil_speed.py).

No timing is asserted here: each faster path is checked against the slower one it replaces.
  * the PSF fit stops each star on its own convergence, so a star's fit does not depend on the batch it is in
    (a batch equals the per-star fits to 1e-9);
  * the candidate search (kernels/detect_candidates.py) labels with OpenCV's connected components: they equal the
    project's labeller's (kernels/labelling.py: foreground, count, partition), and the search given the
    labeller's components instead finds the same candidates (maxima, component sizes and deblending included),
    for 8 and 4 connectivity;
  * the tile statistics' searchsorted counts (8/16-bit frames) equal the float32 comparisons (bit for bit);
  * the hil_star rows are the same with the numpy and the Taichi voting engine (ESA frames).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from dualsight.kernels import detect_local as dl
from dualsight.kernels.detect_background import clipped_stats
from dualsight.kernels.detect_candidates import find_candidates, sparse_components
from dualsight.kernels.detect_psf import fit_psf, psf_profiles
from helpers import ROOT, shared_real

ESA = shared_real() / "esa_tetra3"


def _stars(K, s, seed, n=7, noise=3.0):
    """K noisy stamps (n x n) of pixel-integrated Gaussian stars (flux 200-5000 ADU, background 0-5 ADU)."""
    rng = np.random.default_rng(seed)
    h = n // 2
    r0 = rng.integers(10, 500, K)
    c0 = rng.integers(10, 500, K)
    x = c0 + h + 0.5 + rng.uniform(-0.5, 0.5, K)
    y = r0 + h + 0.5 + rng.uniform(-0.5, 0.5, K)
    F = rng.uniform(200, 5000, K)
    b = rng.uniform(0, 5, K)
    px, _, _ = psf_profiles(x, c0, n, np.full(K, s))
    py, _, _ = psf_profiles(y, r0, n, np.full(K, s))
    st = F[:, None, None] * py[:, :, None] * px[:, None, :] + b[:, None, None] + rng.normal(0, noise, (K, n, n))
    w0 = np.ones((K, n, n))
    w0[rng.random((K, n, n)) < 0.03] = 0.0                      # a few excluded pixels
    x0 = np.round(x - 0.5) + 0.5 + rng.uniform(-0.3, 0.3, K)
    y0 = np.round(y - 0.5) + 0.5 + rng.uniform(-0.3, 0.3, K)
    return st.astype(np.float32), w0, r0, c0, x0, y0, np.full(K, noise)


@pytest.mark.parametrize("fit_sigma", [False, True])
@pytest.mark.parametrize("gain", [None, 2.0])
def test_batched_psf_fit_equals_the_per_star_fits(fit_sigma, gain):
    s = 0.9
    st, w0, r0, c0, x0, y0, noise = _stars(40, s, seed=7 + fit_sigma)
    batch = fit_psf(st, w0, r0, c0, x0, y0, np.full(40, s), noise, gain, fit_sigma=fit_sigma)
    assert batch[-1].sum() >= 35                                   # the fits converge
    for k in range(40):
        one = fit_psf(st[k:k + 1], w0[k:k + 1], r0[k:k + 1], c0[k:k + 1], x0[k:k + 1], y0[k:k + 1],
                      np.full(1, s), noise[k:k + 1], gain, fit_sigma=fit_sigma)
        for a, b in zip(batch, one):
            np.testing.assert_allclose(a[k:k + 1], b, rtol=1e-9, atol=1e-9, equal_nan=True)


def _labeller_components(Z, k_sigma, connectivity):
    """What ``cv2.connectedComponents`` returns for the foreground Z > k_sigma, made by the project's labeller
    (kernels/labelling.py) instead: (number of labels with the background's, (H, W) int32 labels, 0 = background)."""
    from dualsight.kernels.labelling import label_frames

    comp = label_frames(Z[None], k_sigma, connectivity=connectivity)
    lab = np.zeros((1, *Z.shape), np.int32)
    if len(comp):
        comp.paint(lab, np.ones(len(comp.run_label), bool), comp.run_label.astype(np.int32) + 1)
    return len(comp) + 1, lab[0]


@pytest.mark.parametrize("connectivity", [8, 4])
@pytest.mark.parametrize("k_sigma", [3.0, 5.0, 5.1])
def test_candidates_equal_the_project_labellers(connectivity, k_sigma):
    import cv2

    rng = np.random.default_rng(11)
    H, W = 200, 300
    Z = rng.normal(0, 1.2, (H, W)).astype(np.float32)
    Z = cv2.GaussianBlur(Z, (5, 5), 1.0) * 3                   # correlated noise: blobs of many shapes
    yy, xx = np.mgrid[0:H, 0:W]
    for _ in range(40):                                        # stars, close pairs, one glare
        cy, cx, a, sg = rng.uniform(0, H), rng.uniform(0, W), rng.uniform(4, 60), rng.uniform(0.6, 2.0)
        Z += (a * np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * sg * sg))).astype(np.float32)
    Z[150:190, 20:80] += 30.0
    Z[0, :] = 9.0                                              # foreground along the frame's edges
    Z[:, -1] = 9.0
    cfg = dl.LocalDetectConfig(k_sigma=k_sigma, connectivity=connectivity, max_blob_pixels=500)
    n_ref, lab_ref = _labeller_components(Z, k_sigma, connectivity)

    # the production search's components (sparse_components over the foreground pixels) are the labeller's and
    # OpenCV's: the same partition of the same foreground (the float32 threshold)
    t = np.float32(k_sigma)
    if float(t) > k_sigma:
        t = np.nextafter(t, np.float32(-np.inf))
    f = np.flatnonzero(Z > t)
    assert np.array_equal(f, np.flatnonzero(lab_ref > 0))
    lab = sparse_components(f, H, W, connectivity)
    n_cv, lab_cv = cv2.connectedComponents((Z > t).view(np.uint8), connectivity=connectivity, ltype=cv2.CV_32S)
    assert n_ref == n_cv == lab.max() + 2 > 30
    for other in (lab_ref.ravel()[f], lab_cv.ravel()[f]):
        pairs = np.unique(np.stack([lab, other]), axis=1)
        assert pairs.shape[1] == n_ref - 1
    # numbered by each component's first pixel in raster order
    assert np.array_equal(np.unique(lab, return_index=True)[1], np.sort(np.unique(lab, return_index=True)[1]))

    # the candidates: each one's npix is its component's size (the labeller's), large components counted
    pr, pc, npix, n_large = find_candidates(Z, cfg)
    sizes = np.bincount(lab_ref.ravel())
    assert len(pr) > 30 and np.array_equal(npix, sizes[lab_ref[pr, pc]])
    assert n_large == int((sizes[1:] > cfg.max_blob_pixels).sum()) >= 1
    assert (Z[pr, pc] > k_sigma).all()


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_tile_statistics_counts_equal_the_float32_comparisons(dtype):
    rng = np.random.default_rng(5)
    top = np.iinfo(dtype).max
    rows = []
    for _ in range(60):
        v = rng.normal(rng.uniform(3, top * 0.6), rng.uniform(0.2, 40), 1024)
        v[rng.random(1024) < 0.05] = top                       # saturated / bright tail
        rows.append(v)
    rows.append(np.full(1024, 7.0))                            # a constant tile
    s = np.sort(np.clip(np.array(rows), 0, top).astype(dtype), axis=1, kind="stable")
    fast = clipped_stats(s, 3.0, 3)
    ref = clipped_stats(s.astype(np.float32), 3.0, 3)     # float path: float32 comparisons
    for a, b in zip(fast, ref):
        np.testing.assert_array_equal(a, b)


@pytest.mark.skipif(not (ESA / "truth.json").exists(), reason=f"ESA tetra3 frames not found at {ESA}")
def test_numpy_and_taichi_voting_give_the_same_rows(monkeypatch):
    from dualsight.jobs.kinds import hil_star as hs
    from dualsight.jobs.kinds.hil_star_spec import settings_from_table
    from dualsight.scene.camera import Camera

    paths = sorted(ESA.glob("*.tiff"))[:3]
    settings = settings_from_table(None, epoch_jyear=2019.6)
    spec = hs.spec_from_dict(hs.build_spec(paths, Camera.from_toml(ROOT / "examples/cameras/esa_tetra3.toml"),
                                           settings))
    ctx = hs.make_context(spec)
    out = {}
    for engine in ("numpy", "taichi"):
        monkeypatch.setattr(hs, "voting_engine", lambda n_images=0, e=engine: e)
        t = hs.compute_shard(spec, np.arange(len(paths)), ctx)
        out[engine] = {k: v.drop_columns([c for c in hs.TIMING_COLUMNS if c in v.column_names]).to_pylist()
                       for k, v in t.items()}
    assert sum(r["identified"] for r in out["numpy"]["hil_star"]) == len(paths)
    assert out["numpy"] == out["taichi"]
    assert not math.isnan(out["numpy"]["hil_star"][0]["ra_rad"])


def test_voting_engine_starts_taichi_only_for_long_runs():
    # in a fresh process (Taichi not started): a short run votes with numpy and never starts Taichi (a one-image
    # `hil star` pays no Taichi start); a run of TAICHI_VOTING_MIN_FRAMES images per core starts it
    import subprocess
    import sys

    code = ("import os\n"
            "from dualsight.jobs.kinds import hil_star as hs\n"
            "from dualsight.kernels.taichi_runtime import is_initialised\n"
            "n = hs.TAICHI_VOTING_MIN_FRAMES * (os.cpu_count() or 1)\n"
            "print(hs.voting_engine(1), is_initialised(), hs.voting_engine(n - 1), is_initialised(),"
            " hs.voting_engine(n), is_initialised(), hs.voting_engine(1))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split() == ["numpy", "False", "numpy", "False", "taichi", "True", "taichi"]


@pytest.mark.parametrize("connectivity", [8, 4])
@pytest.mark.parametrize("density", [0.1, 0.35, 0.6])
def test_sparse_components_are_opencvs_on_random_masks(connectivity, density):
    """sparse_components on random masks (every neighbour configuration, the frame's edges, one-pixel-wide frames):
    the partition of cv2.connectedComponents, numbered in raster order of the components' first pixels."""
    import cv2

    rng = np.random.default_rng([int(density * 100), connectivity])
    for H, W in ((60, 80), (1, 50), (50, 1), (7, 7)):
        m = rng.random((H, W)) < density
        f = np.flatnonzero(m)
        lab = sparse_components(f, H, W, connectivity)
        n_cv, lab_cv = cv2.connectedComponents(m.astype(np.uint8), connectivity=connectivity, ltype=cv2.CV_32S)
        assert lab.size == f.size and (f.size == 0 or lab.max() + 2 == n_cv)
        pairs = np.unique(np.stack([lab, lab_cv.ravel()[f]]), axis=1)
        assert pairs.shape[1] == n_cv - 1
        first = np.unique(lab, return_index=True)[1]
        assert np.all(np.diff(first) > 0)
