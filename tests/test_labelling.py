"""The one connected-component labeller (kernels/labelling.py) against an independent one.

Truth: OpenCV's ``connectedComponentsWithStats`` (labels, areas, bounding boxes, centroids) on random
binary images, and brute-force numpy sums over OpenCV's labels for the moment sums.  Labels are compared
up to renumbering: the map from our labels to OpenCV's must be a bijection on the foreground.
Both kernel variants (serial and parallel, ``kernels.labelling._kernel``) are checked, and must agree bit for bit.
"""

import os
from contextlib import contextmanager

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from dualsight.kernels import labelling
from dualsight.kernels.labelling import NSTAT, label_frames, label_segments, native_threshold

_N = int(os.environ.get("DUALSIGHT_HYPOTHESIS_EXAMPLES", "0"))  # > 0: deeper runs (nightly, by hand)
HSET = settings(max_examples=_N or 25, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _opencv(binary, conn):
    """Per frame: (n, labels, stats, centroids) of OpenCV, background row dropped."""
    out = []
    for b in range(binary.shape[0]):
        n, lab, stats, cents = cv2.connectedComponentsWithStats(binary[b].astype(np.uint8), connectivity=conn)
        out.append((n - 1, lab, stats[1:], cents[1:]))
    return out


@contextmanager
def _kernels(serial: bool):
    """Force the serial (True) or the parallel (False) variant of every labelling kernel."""
    saved = labelling.SERIAL_MAX_PIXELS, labelling.SERIAL_MAX_RUNS
    labelling.SERIAL_MAX_PIXELS = labelling.SERIAL_MAX_RUNS = (1 << 62) if serial else -1
    try:
        yield
    finally:
        labelling.SERIAL_MAX_PIXELS, labelling.SERIAL_MAX_RUNS = saved


def _moments_np(lab, n, img, cov):
    """Brute-force (n, NSTAT) sums over the pixels of OpenCV's components 1..n (pixel centres at +0.5)."""
    yy, xx = np.nonzero(lab)
    k = lab[yy, xx] - 1
    x, y = xx + 0.5, yy + 0.5
    I, w = img[yy, xx].astype(np.float64), cov[yy, xx].astype(np.float64)
    cols = [np.ones_like(x), x, y, x * x, x * y, y * y, I, I * x, I * y, w, w * x, w * y, w * x * x, w * x * y,
            w * y * y]
    out = np.zeros((n, NSTAT))
    for j, c in enumerate(cols):
        np.add.at(out[:, j], k, c)
    return out


@HSET
@given(seed=st.integers(0, 2**32 - 1), p=st.floats(0.05, 0.95), conn=st.sampled_from([4, 8]),
       shape=st.tuples(st.integers(1, 3), st.integers(1, 40), st.integers(1, 40)),
       dtype=st.sampled_from([np.uint8, np.uint16, np.float32, np.float64]))
def test_labels_and_stats_match_opencv(seed, p, conn, shape, dtype):
    rs = np.random.default_rng(seed)
    binary = rs.random(shape) < p
    # foreground = value > 9.5 whatever the dtype; background values just below, foreground anywhere above
    img = np.where(binary, rs.integers(10, 200, shape), rs.integers(0, 10, shape)).astype(dtype)
    cov = rs.random(shape).astype(np.float32)
    ref = _opencv(binary, conn)
    got = []
    for serial in (True, False):           # both kernel variants, each against OpenCV, and equal bit for bit
        with _kernels(serial):
            got.append(_check_against_opencv(img, cov, conn, shape, ref))
    for a, b in zip(*got):
        np.testing.assert_array_equal(a, b)


def _check_against_opencv(img, cov, conn, shape, ref):
    comp = label_frames(img, 9.5, coverage=cov, connectivity=conn)
    assert comp.counts.tolist() == [r[0] for r in ref]
    labels = comp.label_image(shape)
    mom = comp.moments()
    for b, (n, lab, stats, cents) in enumerate(ref):
        s = slice(comp.offsets[b], comp.offsets[b + 1])
        # same partition: our label <-> OpenCV's label is one-to-one on the foreground
        fg = lab > 0
        assert np.array_equal(labels[b] > 0, fg)
        pairs = np.unique(np.stack([labels[b][fg], lab[fg]]), axis=1)
        assert pairs.shape[1] == n and np.unique(pairs[0]).size == n and np.unique(pairs[1]).size == n
        # stats, matched through that map (our label k+1 <-> OpenCV's label m)
        m = np.empty(n, np.int64)
        m[pairs[0] - 1] = pairs[1] - 1
        st_ = stats[m]
        np.testing.assert_array_equal(comp.npix[s], st_[:, cv2.CC_STAT_AREA])
        x0, y0 = st_[:, cv2.CC_STAT_LEFT], st_[:, cv2.CC_STAT_TOP]
        np.testing.assert_array_equal(comp.box[s], np.stack([x0, y0, x0 + st_[:, cv2.CC_STAT_WIDTH] - 1,
                                                             y0 + st_[:, cv2.CC_STAT_HEIGHT] - 1], 1))
        np.testing.assert_allclose(mom[s, 1] / mom[s, 0], cents[m, 0] + 0.5, rtol=0, atol=1e-9)
        np.testing.assert_allclose(mom[s, 2] / mom[s, 0], cents[m, 1] + 0.5, rtol=0, atol=1e-9)
        # every moment sum against brute force over OpenCV's components
        ref_m = _moments_np(lab, n, img[b], cov[b])[m]
        np.testing.assert_allclose(mom[s], ref_m, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(comp.seg_stats[b], ref_m.sum(0), rtol=1e-12, atol=1e-9)
    # a subset of components gives the very same sums (same runs, same order)
    pick = np.arange(len(comp))[::3]
    assert np.array_equal(comp.moments(pick), mom[pick])
    return comp.npix, comp.box, comp.seg, comp.offsets, comp.seg_stats, comp.run_label, comp.run_sums, mom


@HSET
@given(seed=st.integers(0, 2**32 - 1), p=st.floats(0.5, 0.98), conn=st.sampled_from([4, 8]),
       shape=st.tuples(st.integers(1, 2), st.integers(1, 12), st.integers(60, 300)),
       dtype=st.sampled_from([np.uint16, np.float32]))
def test_wide_rows_match_opencv(seed, p, conn, shape, dtype):
    """Rows wider than the second read's chunks (``labelling._CHUNK`` px), with long runs that cross the chunk
    boundaries, end on them or run to the row's end: both kernel variants against OpenCV."""
    rs = np.random.default_rng(seed)
    binary = rs.random(shape) < p
    img = np.where(binary, rs.integers(10, 200, shape), rs.integers(0, 10, shape)).astype(dtype)
    cov = rs.random(shape).astype(np.float32)
    ref = _opencv(binary, conn)
    for serial in (True, False):
        with _kernels(serial):
            _check_against_opencv(img, cov, conn, shape, ref)


@HSET
@given(seed=st.integers(0, 2**32 - 1), conn=st.sampled_from([4, 8]))
def test_segments_label_like_the_cropped_frames(seed, conn):
    # patches cut from frames, labelled as segments at their place: components and sums of each crop
    rs = np.random.default_rng(seed)
    frames = (rs.random((2, 30, 40)) < 0.4).astype(np.float32) * rs.uniform(1, 5, (2, 30, 40)).astype(np.float32)
    boxes = [(0, 3, 17, 5, 21), (1, 0, 40, 0, 9), (0, 20, 31, 11, 30), (1, 12, 13, 14, 15)]  # frame, c0, c1, r0, r1
    crops = [frames[f, r0:r1, c0:c1] for f, c0, c1, r0, r1 in boxes]
    flat = np.concatenate([c.ravel() for c in crops])
    start = np.cumsum([0] + [c.size for c in crops])[:-1]
    bx = np.array(boxes)
    comp = label_segments(flat, start, bx[:, 2] - bx[:, 1], bx[:, 4] - bx[:, 3], bx[:, 1], bx[:, 3], bx[:, 0],
                          np.array([0.5, 0.5]), offset=np.array([0.25, -1.0]), connectivity=conn)
    for g, (f, c0, c1, r0, r1) in enumerate(boxes):
        one = label_frames(crops[g][None], 0.5, offset=[0.25, -1.0][f], connectivity=conn)
        s = slice(comp.offsets[g], comp.offsets[g + 1])
        assert comp.counts[g] == len(one)
        np.testing.assert_array_equal(comp.npix[s], one.npix)
        np.testing.assert_array_equal(comp.box[s], one.box + [c0, r0, c0, r0])
        m, m1 = comp.moments(np.arange(s.start, s.stop)), one.moments()
        np.testing.assert_array_equal(m[:, 6], m1[:, 6])                                 # sum I
        np.testing.assert_allclose(m[:, 7] / m[:, 6], m1[:, 7] / m1[:, 6] + c0, rtol=0, atol=1e-12)
        np.testing.assert_allclose(m[:, 1] / m[:, 0], m1[:, 1] / m1[:, 0] + c0, rtol=0, atol=1e-12)
        np.testing.assert_allclose(m[:, 2] / m[:, 0], m1[:, 2] / m1[:, 0] + r0, rtol=0, atol=1e-12)


def test_threshold_is_exact_for_every_dtype():
    # value > t, decided exactly: t between two representable values, and t equal to one (float32(0.1) > 0.1)
    for dtype, t, vals in ((np.uint8, 99.5, [99, 100]), (np.uint16, 100.0, [100, 101]),
                           (np.float32, 0.1, [np.nextafter(np.float32(0.1), np.float32(0)), np.float32(0.1)]),
                           (np.float64, 0.1, [0.1, np.nextafter(0.1, 1.0)])):
        img = np.array(vals, dtype=dtype).reshape(1, 1, 2)
        comp = label_frames(img, t)
        assert comp.npix.tolist() == [1] and comp.box.tolist() == [[1, 0, 1, 0]], dtype
    assert native_threshold([99.5, -3.0, 1e9], np.uint8).tolist() == [99, -1, 255]


def test_empty_inputs():
    comp = label_frames(np.zeros((3, 4, 5), np.float32), 0.0)
    assert len(comp) == 0 and comp.counts.tolist() == [0, 0, 0] and comp.moments().shape == (0, NSTAT)
    assert np.all(comp.seg_stats == 0)
    with pytest.raises(ValueError, match="connectivity"):
        label_frames(np.zeros((1, 2, 2)), 0.0, connectivity=6)


@HSET
@given(seed=st.integers(0, 2**32 - 1), conn=st.sampled_from([4, 8]), block=st.sampled_from([8, 12, 15, 16]),
       shape=st.tuples(st.integers(1, 3), st.integers(5, 70), st.integers(5, 70)),
       dtype=st.sampled_from([np.uint16, np.float32]), serial=st.booleans())
def test_background_inside_the_labeller_matches_opencv_on_the_residual(seed, conn, block, shape, dtype, serial):
    """``label_frames(frames, background=model)`` (the smooth background evaluated per pixel in the row kernels)
    labels and sums exactly what OpenCV and a brute-force sum give on ``frames - background`` (float64, from
    ``Background.subtract``): a sloped sky with spots, frames not multiples of the block, both kernel variants."""
    from dualsight.kernels.background import background_model

    rng = np.random.default_rng(seed)
    B, H, W = shape
    yy, xx = np.mgrid[0:H, 0:W]
    # a steep sky, different in every frame: a background read one column or one frame off changes the runs
    f = (rng.normal(500.0, 6.0, (B, H, W)) + rng.uniform(0, 300, (B, 1, 1))
         + rng.uniform(-20, 20, (B, 1, 1)) * xx + rng.uniform(-20, 20, (B, 1, 1)) * yy)
    for _ in range(int(rng.integers(1, 12))):
        b, y0, x0 = rng.integers(0, B), rng.uniform(0, H), rng.uniform(0, W)
        f[b] += rng.uniform(50, 400) * np.exp(-((xx + 0.5 - x0) ** 2 + (yy + 0.5 - y0) ** 2) / 2.0)
    frames = np.clip(f, 0, 65535).astype(np.uint16).astype(dtype)
    model = background_model(frames, block)
    resid = model.subtract(frames, np.float64)
    thr = np.full(B, rng.uniform(8.0, 30.0))
    off = rng.uniform(-2.0, 2.0, B)
    with _kernels(serial):
        comp = label_frames(frames, thr, offset=off, connectivity=conn, background=model)
    want = _opencv(resid > thr[:, None, None], conn)
    assert comp.counts.tolist() == [r[0] for r in want]
    labels = comp.label_image(shape)
    ones = np.ones((H, W))
    for b in range(B):
        n, lab, stats, _ = want[b]
        fg = lab > 0
        assert np.array_equal(labels[b] > 0, fg)
        m = np.empty(n, np.int64)                        # our component k <-> OpenCV's label m[k] + 1
        m[labels[b][fg] - 1] = lab[fg] - 1
        s = slice(comp.offsets[b], comp.offsets[b + 1])
        np.testing.assert_array_equal(comp.npix[s], stats[m, cv2.CC_STAT_AREA])
        np.testing.assert_allclose(comp.moments()[s], _moments_np(lab, n, resid[b] - off[b], ones)[m],
                                   rtol=1e-12, atol=1e-9)


def test_detection_with_a_background_equals_detection_on_the_residual():
    """detect_stars(frames, background=model) gives the detections of detect_stars on the float64 residual, bit
    for bit (noise estimate from the same sample, same threshold, same sums), several frames in one call."""
    from dualsight.kernels.detect import DetectConfig, detect_stars
    from dualsight.kernels.background import background_model

    rng = np.random.default_rng(11)
    B, H, W = 3, 130, 170
    yy, xx = np.mgrid[0:H, 0:W]
    f = rng.normal(300.0, 8.0, (B, H, W)) + 0.3 * xx - 0.2 * yy
    for _ in range(40):
        b, y0, x0 = rng.integers(0, B), rng.uniform(0, H), rng.uniform(0, W)
        f[b] += rng.uniform(60, 600) * np.exp(-((xx + 0.5 - x0) ** 2 + (yy + 0.5 - y0) ** 2) / 2.0)
    frames = np.clip(f, 0, 65535).astype(np.uint16)
    model = background_model(frames, 32)
    got = detect_stars(frames, DetectConfig(), background=model)
    want = detect_stars(model.subtract(frames, np.float64), DetectConfig())
    assert got.offsets[-1] >= 25
    for name in ("case", "x", "y", "flux", "npix", "offsets", "background_adu", "threshold_adu"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)


@pytest.mark.parametrize("delta", [-1, 1])
def test_rows_counted_and_filled_differently_raise_instead_of_overrunning(monkeypatch, delta):
    """Should the two reads of a row ever disagree (a counting bug), the labeller stores nothing outside the row's
    slots and raises a clear error, instead of overrunning its run buffer."""
    img = np.zeros((1, 8, 200), np.float32)
    img[0, 3, 10:15] = img[0, 3, 70:90] = img[0, 5, 150:151] = 100.0
    real_get = labelling._KERNELS.get

    def get(name, dtype=None, serial=False):
        kern = real_get(name, dtype, serial=serial)
        if not name.startswith("count_runs"):
            return kern

        def miscount(*args):
            kern(*args)
            args[5][3] += delta                        # row 3 (two runs): one run more, or fewer, than it has
        return miscount

    monkeypatch.setattr(labelling._KERNELS, "get", get)
    with pytest.raises(RuntimeError, match="found other runs than the first counted"):
        label_frames(img, 50.0)
    monkeypatch.undo()
    assert len(label_frames(img, 50.0)) == 3
