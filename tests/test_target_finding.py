"""Finding the target without the truth (nav/target_finding.py, issue 23 point 3): a synthetic sequence of
star-camera frames with catalog stars, an uncatalogued faint star (fixed on the sky), a hot pixel (fixed on the
detector), a random false detection and the target (moving against the stars); the target is known by
construction and the false ones never become it.  The gate against the closed-form chi-square(2) quantile and a
brute-force Mahalanobis distance."""

import math

import numpy as np
import pytest

from dualsight.nav import target_finding as tfd
from dualsight.scene.camera import Camera

CAM = Camera.pinhole(1024, 768, 5.5e-6, 0.02)          # ~57 arcsec/px, 16 x 12 deg


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def look(z):
    """ICRS -> camera attitude with boresight z."""
    x = unit(np.cross([0.0, 0.0, 1.0], z))
    return np.stack([x, np.cross(z, x), z])


def sequence(T=12, seed=0):
    """Per frame: detections (frame, ICRS via the true attitude, pixel) of 30 catalog stars in view, one faint
    uncatalogued star, one hot pixel, one random false blob, and the target; the boresight turns 3 deg per frame
    with the target's line of sight (pointed at with 0.3 deg error)."""
    rng = np.random.default_rng([seed, 23])
    t = np.arange(T)
    los = np.stack([np.cos(np.radians(3 * t)), np.sin(np.radians(3 * t)), 0.1 * np.ones(T)], -1)
    los = unit(los)
    bore = unit(los + rng.normal(size=(T, 3)) * math.radians(0.3))
    cat = unit(rng.normal(size=(20000, 3)))
    uncat = unit(los[T // 2] + np.array([0.0, 0.0, 0.05]))    # in the field for several frames, no catalog entry
    hot = np.array([100.5, 600.5])
    fr, u, xy, kind = [], [], [], []
    for k in range(T):
        A = look(bore[k])
        def add(v_icrs, what):
            p, _ = CAM.project((A @ v_icrs)[None])
            if np.all(np.isfinite(p)) and CAM.in_image(p)[0] and (A @ v_icrs)[2] > 0:
                fr.append(k), u.append(v_icrs), xy.append(p[0]), kind.append(what)
        vis = cat[(cat @ bore[k]) > math.cos(math.radians(7))][:30]
        for v in vis:
            add(v, "star")
        add(uncat, "uncat")
        add(A.T @ CAM.backproject(hot), "hot")
        add(A.T @ CAM.backproject(rng.random(2) * [1024, 768]), "random")
        add(los[k], "target")
    return (np.array(fr), unit(np.array(u)), np.array(xy), np.array(kind), bore, cat, los)


def candidates(seq):
    fr, u, xy, kind, bore, cat, los = seq
    pix = 1.0 / CAM.fx
    keep = tfd.unmatched(fr, u, bore, cat, 2 * pix, 0.5 * CAM.fov_rad[2])
    keep &= ~tfd.repeats(fr, u, 2 * pix, min_frames=2)
    keep &= ~tfd.repeats(fr, xy, 1.5, min_frames=3)
    return keep


def test_fixed_false_detections_never_candidates_target_always():
    seq = sequence()
    fr, u, xy, kind = seq[:4]
    keep = candidates(seq)
    assert np.sum(kind == "uncat") >= 3 and np.sum(kind == "hot") >= 10
    assert not keep[kind == "star"].any()
    assert not keep[kind == "uncat"].any()          # fixed on the sky
    assert not keep[kind == "hot"].any()            # fixed on the detector
    assert keep[kind == "target"].all() and np.sum(kind == "target") == 12


def test_gate_picks_the_target_among_moving_candidates():
    """The prediction (a Hill state whose line of sight is the target's, 1 m position sigma at 1 km) picks the
    target over the random false blob in every frame; a prediction 20 sigma off gates everything out."""
    seq = sequence()
    fr, u, xy, kind, bore, cat, los = seq
    keep = candidates(seq)
    gate = tfd.chi2_gate_2dof(0.999)
    C = np.broadcast_to(np.eye(3) * (5e-6) ** 2, (len(fr), 3, 3))
    for k in range(12):
        idx = np.flatnonzero(keep & (fr == k))
        # Hill frame = ICRS (R = I): rho = -1000 m along the line of sight
        x = np.concatenate([-1000.0 * los[k], np.zeros(3)])[None]
        up, Cp = tfd.predicted_bearing(x, np.eye(6)[None], np.eye(3))
        np.testing.assert_allclose(up[0], los[k], atol=1e-12)
        j, code = tfd.pick(tfd.innovation_d2(u[idx], C[idx], up[0], Cp[0]), gate)
        assert code == 1 and kind[idx[j]] == "target"
        off = unit(los[k] + 0.02 * unit(np.cross(los[k], [0, 0, 1.0])))
        x_off = np.concatenate([-1000.0 * off, np.zeros(3)])[None]
        up, Cp = tfd.predicted_bearing(x_off, np.eye(6)[None], np.eye(3))
        assert tfd.pick(tfd.innovation_d2(u[idx], C[idx], up[0], Cp[0]), gate) == (-1, 2)
    assert tfd.pick(np.zeros(0), gate) == (-1, 0)


def test_gate_quantile_and_distance_against_closed_forms():
    # chi-square(2) CDF is 1 - exp(-x/2)
    assert 1 - math.exp(-tfd.chi2_gate_2dof(0.999) / 2) == pytest.approx(0.999, abs=1e-12)
    assert tfd.chi2_gate_2dof(0.95) == pytest.approx(5.991464547, rel=1e-9)
    # a candidate 3 sigma_a along one tangent axis and 2 sigma_b along the other: d2 = 9 + 4
    up = unit([0.2, 0.3, 0.9])
    e1 = unit(np.cross(up, [1.0, 0, 0]))
    e2 = np.cross(up, e1)
    sa, sb = 1e-4, 3e-4
    Cp = sa ** 2 * np.outer(e1, e1) + sb ** 2 * np.outer(e2, e2)
    v = unit(up + 3 * sa * e1 + 2 * sb * e2)
    d2 = tfd.innovation_d2(v[None], np.zeros((1, 3, 3)), up, Cp)
    assert d2[0] == pytest.approx(13.0, rel=1e-6)
    assert np.isinf(tfd.innovation_d2(-up[None], np.zeros((1, 3, 3)), up, Cp)[0])
    # the predicted bearing's covariance: J P J^T with J = -R (I - r r^T) / |r| by finite differences
    rng = np.random.default_rng(3)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    x = np.array([[30.0, -400.0, 12.0, 0, 0, 0]])
    P = np.diag([4.0, 100.0, 9.0, 1, 1, 1])[None]
    u0, Cu = tfd.predicted_bearing(x, P, R)
    J = np.empty((3, 3))
    for i in range(3):
        d = np.zeros((1, 6))
        d[0, i] = 1e-4
        J[:, i] = (tfd.predicted_bearing(x + d, P, R)[0][0] - tfd.predicted_bearing(x - d, P, R)[0][0]) / 2e-4
    np.testing.assert_allclose(u0[0], -R @ unit(x[0, :3]), atol=1e-15)
    np.testing.assert_allclose(Cu[0], J @ P[0, :3, :3] @ J.T, rtol=1e-6, atol=1e-14)


def test_repeats_counts_other_frames():
    """An object seen in exactly two frames is fixed with min_frames = 2, not with 3; two detections of one frame
    never make each other fixed."""
    fr = np.array([0, 1, 2, 2, 3])
    p = np.array([[0.0, 0.0], [0.5, 0.0], [50.0, 0.0], [50.4, 0.0], [99.0, 9.0]])
    np.testing.assert_array_equal(tfd.repeats(fr, p, 1.0, min_frames=2), [True, True, False, False, False])
    np.testing.assert_array_equal(tfd.repeats(fr, p, 1.0, min_frames=3), [False] * 5)
