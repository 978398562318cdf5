"""Correctness of the speed work on the real-frame chain (issue 13, point 4; benchmarks/bench_hil_speed.py).

No timing is asserted here: each faster path is checked against the slower one it replaces.
  * the PSF fit stops each star on its own convergence, so a star's fit does not depend on the batch it is in
    (a batch equals the per-star fits to 1e-9);
  * the candidates found with OpenCV's connected components equal those of the project's labeller
    (kernels/labelling.py), maxima, component sizes and deblending included, for 8 and 4 connectivity;
  * the tile statistics' searchsorted counts (8/16-bit frames) equal the float32 comparisons (bit for bit);
  * the hil_star rows are the same with the numpy and the Taichi voting engine (ESA frames).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from dualsight.kernels import detect_local as dl
from dualsight.kernels.detect_background import clipped_stats
from dualsight.kernels.detect_candidates import find_candidates
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


def _candidates_with_project_labeller(Z, cfg):
    """The candidate search as it was with kernels.labelling.label_frames (the reference)."""
    from dualsight.kernels.labelling import label_frames

    H, W = Z.shape
    comp = label_frames(Z[None], cfg.k_sigma, connectivity=cfg.connectivity)
    if len(comp) == 0:
        e = np.zeros(0, np.int64)
        return e, e, e, 0
    lens = (comp.run_c1 - comp.run_c0).astype(np.int64)
    first = np.cumsum(lens) - lens
    pr = np.repeat(comp.run_row.astype(np.int64), lens)
    pc = np.repeat(comp.run_c0.astype(np.int64), lens) + (np.arange(int(lens.sum())) - np.repeat(first, lens))
    cid = np.repeat(comp.run_label.astype(np.int64), lens)
    z = Z[pr, pc]
    peak = np.ones(pr.size, bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                peak &= z >= Z[np.clip(pr + dr, 0, H - 1), np.clip(pc + dc, 0, W - 1)]
    pr, pc, cid = pr[peak], pc[peak], cid[peak]
    large = comp.npix > cfg.max_blob_pixels
    keep = ~large[cid]
    pr, pc, cid = pr[keep], pc[keep], cid[keep]
    z = Z[pr, pc]
    order = np.lexsort((pc, pr, -z, cid))
    pr, pc, cid, z = pr[order], pc[order], cid[order], z[order]
    first = np.ones(len(cid), bool)
    first[1:] = cid[1:] != cid[:-1]
    accept = first.copy()
    multi = np.flatnonzero(~first)
    if multi.size:
        start = np.searchsorted(cid, cid[multi], side="left")
        cnt = multi - start
        j = np.repeat(multi, cnt)
        i = np.repeat(start, cnt) + (np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt))
        dy, dx = (pr[j] - pr[i]).astype(np.float64), (pc[j] - pc[i]).astype(np.float64)
        far = np.hypot(dx, dy) >= cfg.deblend_min_sep_px
        dip = np.full(j.size, np.inf)
        for t in (0.25, 0.5, 0.75):
            dip = np.minimum(dip, Z[np.rint(pr[i] + t * dy).astype(np.int64), np.rint(pc[i] + t * dx).astype(np.int64)])
        sep = far & (dip < (1.0 - cfg.deblend_contrast) * z[j])
        bad = np.zeros(len(cid), bool)
        np.logical_or.at(bad, j, ~sep)
        accept[multi] = ~bad[multi]
    return pr[accept], pc[accept], comp.npix[cid[accept]].astype(np.int64), int(large.sum())


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
    got = find_candidates(Z, cfg)
    ref = _candidates_with_project_labeller(Z, cfg)
    assert got[3] == ref[3] and ref[3] >= 1
    og, orf = np.lexsort((got[1], got[0])), np.lexsort((ref[1], ref[0]))
    assert len(og) == len(orf) > 30
    for a, b in zip(got[:3], ref[:3]):
        np.testing.assert_array_equal(a[og], b[orf])


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
    from dualsight.scene.camera import Camera

    paths = sorted(ESA.glob("*.tiff"))[:3]
    settings = hs.settings_from_table(None, epoch_jyear=2019.6)
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
            "from dualsight.kernels._runtime import is_initialised\n"
            "n = hs.TAICHI_VOTING_MIN_FRAMES * (os.cpu_count() or 1)\n"
            "print(hs.voting_engine(1), is_initialised(), hs.voting_engine(n - 1), is_initialised(),"
            " hs.voting_engine(n), is_initialised(), hs.voting_engine(1))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split() == ["numpy", "False", "numpy", "False", "taichi", "True", "taichi"]
