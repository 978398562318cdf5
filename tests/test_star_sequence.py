"""The sequence driver (nav/sequence.py): lost-in-space until a fix, tracking, fallback, re-acquisition.

Independent truths: a synthetic sequence whose attitude at every frame is the helpers' Rodrigues rotation of the
first one at a known constant rate (not the code's exponential map), whose detections are the catalog stars
projected through the camera model with Gaussian centroid noise of known sigma (so every detection's true catalog
row is known), with a blinded frame (only false stars) and a dropped frame (no image); lost-in-space run on the same
frames (``shadow_lis``) for the identities; the true rate for both rate estimates (within their stated sigmas).
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from dualsight.nav.tracking_config import TrackingConfig
from dualsight.nav.errors import axis_errors
from dualsight.nav.sequence import LOST_IN_SPACE, NO_FIX, NO_IMAGE, REASON_NAMES, TRACKING, run_sequence
from dualsight.nav.tracking import NO_PRIOR
from dualsight.nav.voting_config import VotingConfig
from dualsight.scene.attitude import euler123_to_dcm, random_euler123
from dualsight.scene.camera import Camera
from helpers import pair_catalog, rotation, sphere_catalog, unit

CAM = Camera(1024, 768, 4.65e-6, 3655.9, 3655.9, 512.0, 384.0, (-0.08, 0.02, 1e-4, -2e-4, 0.0))
SIGMA_PX = 0.2
ARCSEC = math.pi / 180 / 3600
FPS = 10.0
BLINDED, DROPPED = 12, 20


@pytest.fixture(scope="module")
def sky():
    cat = sphere_catalog(21, 3000)
    pi, pj, pa = pair_catalog(cat, CAM.fov_rad[2] * 1.05)
    return SimpleNamespace(cat=cat, pairs=SimpleNamespace(i=pi, j=pj, angle=pa))


def make_sequence(sky, seed, rate_deg_s, n_frames=30, n_false=1, events=True):
    """Truth and detections of a constant-rate sequence: (times, A_true (T, 3, 3), omega (3,), xy (K, 2),
    truth rows (K,), offsets (T + 1,), available (T,))."""
    rng = np.random.default_rng(seed)
    A0 = euler123_to_dcm(random_euler123(rng, 1))[0]
    w = unit(rng.normal(size=3)) * math.radians(rate_deg_s)
    t = np.arange(n_frames) / FPS
    # the camera turns by +|w| t about w: inertial vectors turn the other way in its frame (Rodrigues, transposed)
    A = np.stack([rotation(w, np.linalg.norm(w) * tk).T @ A0 for tk in t])
    xys, rows, counts = [], [], []
    for k in range(n_frames):
        if events and k == BLINDED:                              # saturated background: only false blobs
            xy, row = rng.uniform((0, 0), (CAM.width, CAM.height), (6, 2)), np.full(6, -1)
        else:
            px, front = CAM.project(sky.cat @ A[k].T)
            inn = np.flatnonzero(front & CAM.in_image(np.nan_to_num(px, nan=-1.0)))
            xy = px[inn] + rng.normal(scale=SIGMA_PX, size=(inn.size, 2))
            fxy = rng.uniform((0, 0), (CAM.width, CAM.height), (n_false, 2))
            xy, row = np.concatenate([xy, fxy]), np.concatenate([inn, np.full(n_false, -1)])
        xys.append(xy), rows.append(row), counts.append(len(xy))
    off = np.concatenate([[0], np.cumsum(counts)])
    avail = np.ones(n_frames, bool)
    if events:
        avail[DROPPED] = False
    return t, A, w, np.concatenate(xys), np.concatenate(rows), off, avail


def run(sky, seq, **kw):
    t, A, w, xy, truth, off, avail = seq
    return run_sequence(t, xy, np.full(len(xy), SIGMA_PX), off, CAM, sky.cat, sky.pairs, VotingConfig.robust(2e-4),
                        TrackingConfig(centroid_sigma_px=SIGMA_PX), available=avail, engine="numpy", **kw)


@pytest.mark.parametrize("seed, rate", [(1, 1.0), (2, 3.0)])
def test_tracking_holds_and_reacquires_after_a_blinded_frame(sky, seed, rate):
    seq = make_sequence(sky, seed, rate)
    t, A_true, w, xy, truth, off, avail = seq
    r = run(sky, seq, shadow_lis=True)
    mode = r.mode
    assert mode[0] == LOST_IN_SPACE and r.reason[0] == NO_PRIOR
    normal = np.ones(len(t), bool)
    normal[[0, 1, BLINDED, DROPPED]] = False
    # frame 1 has only a zero-rate prior (0.5 deg/s sigma): tracked at 1 deg/s, lost-in-space at 3 deg/s; every
    # later normal frame is tracked (the frames right after the events included)
    assert mode[1] == (TRACKING if rate < 2 else LOST_IN_SPACE)
    assert np.all(mode[normal] == TRACKING), [(k, int(m), REASON_NAMES[r.reason[k]]) for k, m in enumerate(mode)]
    assert mode[BLINDED] == NO_FIX and REASON_NAMES[r.reason[BLINDED]] != "locked"
    assert mode[DROPPED] == NO_FIX and r.reason[DROPPED] == NO_IMAGE
    # re-acquisition within 2 frames of the blinded frame
    assert (mode[BLINDED + 1: BLINDED + 3] != NO_FIX).any()
    # the attitude against the truth: within 4.5 of its stated sigmas on every axis (camera frame), and the
    # cross-boresight axes far inside the 100 arcsec limit
    fixed = mode != NO_FIX
    err = axis_errors(r.A[fixed], A_true[fixed], frame="camera")
    z = err / np.sqrt(np.diagonal(r.cov[fixed], axis1=1, axis2=2))
    assert np.abs(z).max() < 4.5, np.abs(z).max(axis=0)
    assert np.abs(err[:, :2]).max() < 15 * ARCSEC
    # identities: tracking's equal the truth and lost-in-space's on the same frames, wherever both answer
    frame_of = np.repeat(np.arange(len(t)), np.diff(off))
    trk = (mode[frame_of] == TRACKING) & (r.det_row >= 0)
    assert trk.sum() > 150
    assert np.array_equal(r.det_row[trk], truth[trk])
    both = trk & r.shadow_verified[frame_of] & (r.shadow_rows >= 0)
    assert both.sum() > 100
    assert np.array_equal(r.det_row[both], r.shadow_rows[both])
    assert np.all(r.det_row[truth < 0] == -1)                       # no false blob is given an identity


def test_rates_against_the_true_rate_within_their_sigmas(sky):
    seq = make_sequence(sky, 3, 2.0, n_frames=40)
    t, A_true, w, *_ = seq
    r = run(sky, seq)
    for est, cov in ((r.rate_att, r.rate_att_cov), (r.rate_star, r.rate_star_cov)):
        ok = np.all(np.isfinite(est), axis=1)
        assert ok.sum() >= 30
        z = (est[ok] - w) / np.sqrt(np.diagonal(cov[ok], axis1=1, axis2=2))
        assert np.mean(np.abs(z) <= 3) >= 0.97, np.abs(z).max()
        np.testing.assert_allclose(est[ok].mean(axis=0), w, atol=math.radians(0.02))
    # the star pairs behind rate_star: the frames with a fix after a fix one frame earlier see >= 5 common stars
    assert np.median(r.rate_pairs[r.rate_pairs > 0]) >= 5
    # latency recorded per stage where it ran
    trk = r.mode == TRACKING
    assert np.all(r.t_track_ns[trk] > 0) and np.all(r.t_predict_ns[trk] > 0) and np.all(r.t_lis_ns[trk] == -1)
    assert r.t_lis_ns[0] > 0 and np.all(r.t_total_ns[r.mode != NO_FIX] > 0)


def test_gyro_rate_carries_tracking_at_a_high_rate(sky):
    """At 6 deg/s (38 px between frames) a gyro's rate (noise 0.01 deg/s) keeps the lock from the second frame on;
    without it, the zero-rate prior of the first tracked frame (0.5 deg/s sigma) cannot follow, and the driver falls
    back to lost-in-space, which still fixes the frame."""
    seq = make_sequence(sky, 4, 6.0, n_frames=16, events=False)
    t, A_true, w, *_ = seq
    rng = np.random.default_rng(5)
    gyro = w[None] + rng.normal(scale=math.radians(0.01), size=(len(t), 3))
    r = run(sky, seq, gyro=gyro, gyro_sigma_rad_s=math.radians(0.01))
    normal = np.ones(len(t), bool)
    normal[0] = False
    assert np.all(r.mode[normal] == TRACKING)
    r0 = run(sky, seq)
    assert r0.mode[1] == LOST_IN_SPACE and REASON_NAMES[r0.reason[1]] != "locked"


@pytest.mark.parametrize("profile", [False, True])
def test_smear_weights_make_the_stated_covariance_hold_on_streaked_centroids(sky, profile):
    """Centroids of streaked stars scattered along the true streak by ``smear_sigma_per_px`` x its length and across
    it by ``smear_cross_per_px`` x its length (the model of nav/smear_weights.py), the detector stating a round
    0.08 px, detections shuffled, one false star per frame.  With the smear weights the tracked attitudes' roll is
    better than with the detector's sigmas alone (13 % in RMS through the filter over 6 turns and 3 mostly-roll
    sequences; none when the streaks are dropped from the fit), and their errors are within the stated covariance: mean NEES below the
    chi-square(3) mean's 3-sigma bound of the frame count (not overconfident), above 1.5 (the a posteriori variance
    factor leaves it at most 2x conservative).  Truth: each streak's direction and length from the camera model at
    the exposure's two ends (not the code's pixel Jacobian).  ``profile``: the scatter along a streak of L px is
    instead the detector's sigma times sqrt(1 + L^2 / (12 x 1.28^2)) (a 1.28 px profile blurred by the streak), across
    it the detector's, and the tracker states it with ``streak_psf_sigma_px``."""
    s0, along, cross, exposure = 0.08, 0.02, 0.003, 0.1
    if profile:
        along, cross = 0.0, 0.0
    nees, roll = {True: [], False: []}, {True: [], False: []}
    for seed in range(31, 40):
        rng = np.random.default_rng(seed)
        A0 = euler123_to_dcm(random_euler123(rng, 1))[0]
        w = unit(rng.normal(size=3)) * math.radians(1.2)
        if seed >= 37:                 # mostly a roll (camera frame): streak directions differ from star to star
            w = unit(np.array([0.2, -0.1, 1.0])) * math.radians(4.0)
        t = np.arange(30) / FPS
        att = lambda tk: rotation(w, np.linalg.norm(w) * tk).T @ A0          # noqa: E731
        xys, counts = [], []
        for tk in t:
            px, front = CAM.project(sky.cat @ att(tk).T)
            inn = np.flatnonzero(front & CAM.in_image(np.nan_to_num(px, nan=-1.0)))
            d = CAM.project(sky.cat[inn] @ att(tk + exposure / 2).T)[0] - CAM.project(sky.cat[inn] @ att(tk - exposure / 2).T)[0]
            length = np.hypot(d[:, 0], d[:, 1])
            u = d / length[:, None]
            n = np.stack([-u[:, 1], u[:, 0]], axis=1)
            sa, sc = np.hypot(s0, along * length), np.hypot(s0, cross * length)
            if profile:
                sa = s0 * np.sqrt(1.0 + length ** 2 / (12 * 1.28 ** 2))
            xy = px[inn] + u * (sa * rng.normal(size=inn.size))[:, None] + n * (sc * rng.normal(size=inn.size))[:, None]
            xy = rng.permutation(np.concatenate([xy, rng.uniform((0, 0), (CAM.width, CAM.height), (1, 2))]))
            xys.append(xy), counts.append(len(xy))
        xy = np.concatenate(xys)
        off = np.concatenate([[0], np.cumsum(counts)])
        A_true = np.stack([att(tk) for tk in t])
        for on in (True, False):
            cfg = TrackingConfig(centroid_sigma_px=s0, smear_sigma_per_px=along if on else 0.0,
                                 smear_cross_per_px=cross if on else 0.0,
                                 streak_psf_sigma_px=1.28 if on and profile else 0.0)
            r = run_sequence(t, xy, np.full(len(xy), s0), off, CAM, sky.cat, sky.pairs, VotingConfig.robust(2e-4),
                             cfg, engine="numpy", exposure_s=exposure)
            trk = np.flatnonzero(r.mode == TRACKING)
            assert len(trk) >= 25
            e = axis_errors(r.A[trk], A_true[trk], frame="camera")
            nees[on] += [float(x @ np.linalg.solve(P, x)) for x, P in zip(e, r.cov[trk])]
            roll[on] += list(e[:, 2])
    n = len(nees[True])
    assert 1.5 <= np.mean(nees[True]) <= 3 + 3 * math.sqrt(6 / n), np.mean(nees[True])
    assert np.sqrt(np.mean(np.square(roll[True]))) < 0.92 * np.sqrt(np.mean(np.square(roll[False])))


def test_a_lost_in_space_fix_that_contradicts_the_track_waits_for_the_next_frame(sky):
    """Frame 15 shows a false sky: the true stars turned 2 deg about the optical axis (a reflection, a mis-set
    image).  Tracking finds nothing in its windows, lost-in-space solves the false sky (verified: it is a real
    star pattern), 2 deg from the track.  That fix must not be output (mode none, reason ``unconfirmed``); an
    answer is back on the next frame, and no output frame is beyond 100 arcsec of the truth (the Rodrigues truth of
    :func:`make_sequence`)."""
    K = 15
    t, A, w, xy, truth, off, avail = make_sequence(sky, 7, 0.5, n_frames=30, events=False)
    roll = np.array([[math.cos(math.radians(2)), -math.sin(math.radians(2)), 0.0],
                     [math.sin(math.radians(2)), math.cos(math.radians(2)), 0.0], [0.0, 0.0, 1.0]])
    px, front = CAM.project(sky.cat @ (roll @ A[K]).T)
    inn = np.flatnonzero(front & CAM.in_image(np.nan_to_num(px, nan=-1.0)))
    xy = np.concatenate([xy[: off[K]], px[inn], xy[off[K + 1]:]])
    off = np.concatenate([off[: K + 1], off[K + 1:] - (off[K + 1] - off[K]) + len(inn)])
    r = run(sky, (t, A, w, xy, None, off, avail), shadow_lis=True)
    assert r.shadow_verified[K]                              # lost-in-space does solve the false sky ...
    assert r.mode[K] == NO_FIX and REASON_NAMES[r.reason[K]] == "unconfirmed"       # ... but it is not output
    # the next frame's lost-in-space fix contradicts the unconfirmed restart, a single fix: it is output, and the
    # filter restarts with the track's rate (not the 20 deg/s "rate" between the false fix and it), so frame K + 2
    # is tracked
    assert r.mode[K + 1] == LOST_IN_SPACE, [(k, REASON_NAMES[x]) for k, x in enumerate(r.reason)]
    assert np.all(r.mode[K + 2:] == TRACKING), [(k, REASON_NAMES[x]) for k, x in enumerate(r.reason)]
    fixed = r.mode != NO_FIX
    assert fixed.sum() >= 27
    assert np.degrees(np.abs(axis_errors(r.A[fixed], A[fixed], frame="camera"))).max() * 3600 < 100


def test_tracking_leaves_out_the_stars_whose_streak_the_edge_cuts(sky):
    """Streaks (1.5 deg/s, 100 ms: about 10 px) cut by the image's edge: the detector sees only the part inside,
    whose centroid is the midpoint of the visible segment (the streak clipped to the image box by its parameter
    range, a Liang-Barsky clip written here, not the code's bounding box).  Every detection of a cut streak stays
    unidentified in the tracked frames, while nearly every whole streak clear of the edge (by its length) is used;
    the tracked attitudes are within 4.5 stated sigmas of the truth."""
    exposure, s0 = 0.1, 0.08
    cut_seen = used_cut = clear_seen = clear_used = 0
    for seed in (41, 42, 43):
        rng = np.random.default_rng(seed)
        A0 = euler123_to_dcm(random_euler123(rng, 1))[0]
        w = unit(rng.normal(size=3)) * math.radians(1.5)
        t = np.arange(30) / FPS
        att = lambda tk: rotation(w, np.linalg.norm(w) * tk).T @ A0          # noqa: E731
        xys, cuts, counts = [], [], []
        for tk in t:
            p0, f0 = CAM.project(sky.cat @ att(tk - exposure / 2).T)
            p1, f1 = CAM.project(sky.cat @ att(tk + exposure / 2).T)
            ok = np.flatnonzero(f0 & f1 & np.isfinite(p0).all(axis=1) & np.isfinite(p1).all(axis=1))
            a, d = p0[ok], p1[ok] - p0[ok]
            lo, hi = np.zeros(len(ok)), np.ones(len(ok))
            for ax, size in ((0, CAM.width), (1, CAM.height)):      # a + s d in [0, size] for s in [lo, hi]
                with np.errstate(divide="ignore", invalid="ignore"):
                    s_a, s_b = (0.0 - a[:, ax]) / d[:, ax], (size - a[:, ax]) / d[:, ax]
                still = d[:, ax] == 0
                inside_still = (a[:, ax] >= 0) & (a[:, ax] <= size)
                lo = np.where(still, np.where(inside_still, lo, 2.0), np.maximum(lo, np.minimum(s_a, s_b)))
                hi = np.where(still, hi, np.minimum(hi, np.maximum(s_a, s_b)))
            vis = hi - lo > 0.05                                    # at least 5 % of the streak inside
            xy = a[vis] + d[vis] * (0.5 * (lo[vis] + hi[vis]))[:, None] + rng.normal(scale=s0, size=(vis.sum(), 2))
            cut = (hi[vis] - lo[vis]) < 1.0 - 1e-9
            ends = np.concatenate([a[vis], a[vis] + d[vis]], axis=1)
            reach = np.hypot(d[vis, 0], d[vis, 1]) + 3.0
            clear = ((ends[:, 0::2].min(axis=1) >= reach) & (ends[:, 0::2].max(axis=1) <= CAM.width - reach)
                     & (ends[:, 1::2].min(axis=1) >= reach) & (ends[:, 1::2].max(axis=1) <= CAM.height - reach))
            xys.append(xy), cuts.append(cut * 1 + clear * 2), counts.append(len(xy))
        xy, kind = np.concatenate(xys), np.concatenate(cuts)
        cut, clear = kind == 1, kind == 2
        off = np.concatenate([[0], np.cumsum(counts)])
        cfg = TrackingConfig(centroid_sigma_px=s0, smear_sigma_per_px=0.02, smear_cross_per_px=0.003)
        r = run_sequence(t, xy, np.full(len(xy), s0), off, CAM, sky.cat, sky.pairs, VotingConfig.robust(2e-4), cfg,
                         engine="numpy", exposure_s=exposure)
        trk = np.flatnonzero(r.mode == TRACKING)
        assert len(trk) >= 25
        in_trk = np.repeat(r.mode == TRACKING, np.diff(off))
        cut_seen += int((cut & in_trk).sum())
        used_cut += int((cut & in_trk & (r.det_row >= 0)).sum())
        clear_seen += int((clear & in_trk).sum())
        clear_used += int((clear & in_trk & (r.det_row >= 0)).sum())
        e = axis_errors(r.A[trk], np.stack([att(tk) for tk in t])[trk], frame="camera")
        z = e / np.sqrt(np.diagonal(r.cov[trk], axis1=1, axis2=2))
        assert np.abs(z).max() < 4.5, np.abs(z).max(axis=0)
    assert cut_seen >= 10 and used_cut == 0, (cut_seen, used_cut)
    assert clear_used >= 0.97 * clear_seen, (clear_used, clear_seen)
