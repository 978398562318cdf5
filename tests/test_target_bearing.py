"""The target's inertial bearing (nav/target_bearing.py, issue 23 point 3) against independent truth: a direction
projected through a known attitude and a distorted camera comes back; Monte Carlo scatter of attitude and centroid
errors against the stated covariance; the phase-angle correction of a lit sphere against its centroid by
quadrature."""

import math

import numpy as np
import pytest

from dualsight.nav import target_bearing as tb
from dualsight.scene.camera import Camera
from dualsight.scene.target_photometry import sphere_photocentre_offset

CAM = Camera(width=1024, height=768, pixel_pitch_m=4.65e-6, fx=3656.0, fy=3650.0, cx=515.3, cy=380.2,
             distortion=(-0.05, 0.01, 1e-4, -2e-4, 0.0))


def rot(axis, ang):
    """Rodrigues' rotation matrix (written here)."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(ang) * K + (1 - math.cos(ang)) * K @ K


def test_round_trip_through_attitude_and_distortion():
    rng = np.random.default_rng([23, 3])
    A = np.stack([rot(rng.normal(size=3), rng.uniform(0, math.pi)) for _ in range(20)])
    xy = np.stack([rng.uniform(20, 1000, 20), rng.uniform(20, 740, 20)], -1)
    # the truth: a pixel's ray by inverting the camera model numerically (project, Newton on the pixel residual)
    v = np.stack([(xy[:, 0] - CAM.cx) / CAM.fx, (xy[:, 1] - CAM.cy) / CAM.fy, np.ones(20)], -1)
    for _ in range(50):
        p = CAM.project(v)[0]
        v[:, 0] -= (p[:, 0] - xy[:, 0]) / CAM.fx
        v[:, 1] -= (p[:, 1] - xy[:, 1]) / CAM.fy
    u_true = np.einsum("bji,bj->bi", A, v / np.linalg.norm(v, axis=1, keepdims=True))
    u, cov = tb.inertial_bearing(A, np.zeros((20, 3, 3)), xy, 0.1, CAM)
    assert tb.bearing_error(u, u_true).max() < 1e-10
    # centroid-only covariance: sigma_px / f per axis across the line of sight (pinhole, near the centre)
    ev = np.linalg.eigvalsh(cov)
    assert np.all(ev[:, 0] < 1e-20)
    assert np.sqrt(ev[:, 1:]).min() > 0.1 / 3656 * 0.95 and np.sqrt(ev[:, 1:]).max() < 0.1 / 3650 * 1.1


def test_covariance_holds_under_monte_carlo():
    """Draw attitude errors dtheta ~ N(0, P) (A_true = (I + [dtheta x]) A_est) and centroid errors ~ N(0, s^2):
    the stated covariance matches the scatter (each entry within 5 %) and 99.73 % +- 0.1 fall inside 3 sigma."""
    rng = np.random.default_rng([23, 4])
    n = 100_000
    A_est = rot([0.3, -0.2, 0.9], 1.1)
    L = np.array([[3e-5, 0, 0], [1e-5, 2e-5, 0], [0, 0, 2e-4]])      # roll weak, as a narrow field's
    P = L @ L.T
    xy_true = np.array([800.0, 150.0])
    s = 0.3
    # truth: the target's direction in ICRS, imaged through the true attitude
    u_I = np.einsum("ji,j->i", A_est, CAM.backproject(xy_true))
    dth = rng.normal(size=(n, 3)) @ L.T
    A_true = (np.eye(3) + tb.skew(dth)) @ A_est
    A_true = np.linalg.qr(A_true)[0] * np.sign(np.diagonal(np.linalg.qr(A_true)[1], axis1=1, axis2=2))[:, None, :]
    xy_meas = CAM.project(np.einsum("bij,j->bi", A_true, u_I))[0] + rng.normal(0, s, (n, 2))
    u, cov = tb.inertial_bearing(np.broadcast_to(A_est, (n, 3, 3)), np.broadcast_to(P, (n, 3, 3)), xy_meas, s, CAM)
    e = u - u_I
    emp = e.T @ e / n
    scale = np.sqrt(np.outer(np.diag(cov[0]), np.diag(cov[0])))
    assert np.abs(emp - cov[0]).max() < 0.05 * scale.max()
    nees = tb.bearing_nees(u, np.broadcast_to(u_I, (n, 3)), cov)
    assert np.mean(nees < 11.83) == pytest.approx(0.9973, abs=1e-3)
    assert np.mean(nees) == pytest.approx(2.0, rel=0.02)


@pytest.mark.parametrize("alpha_deg", [20.0, 60.0, 90.0])
def test_phase_correction_of_a_lit_sphere(alpha_deg):
    """A sphere of radius 1 m at 2 km: its brightness centroid (quadrature over the sphere, projected through the
    pinhole) is the measured line of sight; the correction brings it to the centre, removing >= 99 % of the bias."""
    a = math.radians(alpha_deg)
    R, d = 1.0, 2000.0
    centre = np.array([0.0, 0.0, d])
    s = np.array([math.sin(a), 0.0, -math.cos(a)])          # towards the Sun; phase = angle(s, -z) = a
    n = 1200
    th = (np.arange(n) + 0.5) / n * math.pi
    ph = (np.arange(2 * n) + 0.5) / (2 * n) * 2 * math.pi
    T, Ph = np.meshgrid(th, ph, indexing="ij")
    nrm = np.stack([np.sin(T) * np.cos(Ph), np.sin(T) * np.sin(Ph), np.cos(T)], -1)
    o = -(centre + R * nrm)
    o /= np.linalg.norm(o, axis=-1, keepdims=True)
    w = np.clip(nrm @ s, 0, None) * np.clip(np.einsum("...k,...k", nrm, o), 0, None) * np.sin(T)
    pts = centre + R * nrm
    img = pts[..., :2] / pts[..., 2:]                      # normalised image coordinates (pinhole)
    c = (w[..., None] * img).sum((0, 1)) / w.sum()
    u_cob = np.array([[c[0], c[1], 1.0]]) / math.hypot(c[0], c[1], 1.0)
    bias = tb.bearing_error(u_cob, np.array([[0.0, 0.0, 1.0]]))[0]
    assert bias == pytest.approx(sphere_photocentre_offset(R, a) / d, rel=2e-3)
    u_corr = tb.sphere_phase_correction(u_cob, s[None], sphere_photocentre_offset(R, a), d)
    assert tb.bearing_error(u_corr, np.array([[0.0, 0.0, 1.0]]))[0] < 0.01 * bias


def test_attitude_covariance_scales_by_residuals():
    cu = np.tile(np.eye(3), (2, 1, 1))
    r = np.array([[1e-5, -1e-5, 1e-5, np.nan], [2e-5, 2e-5, np.nan, np.nan]])
    P = tb.attitude_covariance(cu, r, np.array([3, 2]), floor_rad=1e-6)
    assert P[0, 0, 0] == pytest.approx(3e-10 / 3)
    assert P[1, 1, 1] == pytest.approx(8e-10 / 1)
