"""Streaks (nav/smear_weights.py) and the attitude weighted along and across them (nav/tracking.py
solve_reprojection, centroid_whitening) against closed forms and a Monte Carlo.

Truth: a pinhole with square pixels turning about its optical axis at w moves a star at radius rho px from the principal point at
rho * w px/s, tangentially; turning about its x axis at w moves the star at the principal point at fy * w px/s along
the image y axis (the interaction matrix's rotational part, Chaumette & Hutchinson 2006, Eq. 11).  The weighted
least-squares attitude with the true 2 x 2 centroid covariances has the stated covariance equal to the scatter of
its answers over noise draws, and a smaller roll scatter than the isotropically weighted SVD answer.
"""

from __future__ import annotations

import math

import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from dualsight.nav.angular_rate import log_rotation
from dualsight.nav.smear_weights import smear_axes, streak_inside
from dualsight.nav.tracking import centroid_whitening, pixel_jacobian, solve_pairs, solve_reprojection
from dualsight.scene.attitude import euler123_to_dcm, random_euler123
from dualsight.scene.camera import Camera
from dualsight.scene.rotation_vector import frame_rotation

PINHOLE = Camera(1024, 768, 4.65e-6, 3655.9, 3600.0, 512.0, 384.0, (0.0, 0.0, 0.0, 0.0, 0.0))
SQUARE = Camera(1024, 768, 4.65e-6, 3600.0, 3600.0, 512.0, 384.0, (0.0, 0.0, 0.0, 0.0, 0.0))   # fx = fy


def test_streaks_of_a_roll_and_a_cross_boresight_turn_are_the_closed_forms():
    w = math.radians(0.8)
    xy = np.array([[512.0 + 300.0, 384.0], [512.0, 384.0 - 200.0], [512.0 - 150.0, 384.0 + 150.0]])
    rho = np.hypot(xy[:, 0] - 512.0, xy[:, 1] - 384.0)
    G = pixel_jacobian(SQUARE.backproject(xy), SQUARE)
    u, length = smear_axes(G, np.array([0.0, 0.0, w]), 0.1)
    np.testing.assert_allclose(length, rho * w * 0.1, rtol=1e-9)
    radial = (xy - (512.0, 384.0)) / rho[:, None]
    np.testing.assert_allclose(np.abs(np.sum(u * radial, axis=1)), 0.0, atol=1e-9)     # tangential
    centre = np.array([[512.0, 384.0]])
    u0, l0 = smear_axes(pixel_jacobian(PINHOLE.backproject(centre), PINHOLE), np.array([w, 0.0, 0.0]), 0.1)
    np.testing.assert_allclose(l0, 3600.0 * w * 0.1, rtol=1e-9)
    np.testing.assert_allclose(np.abs(u0), [[0.0, 1.0]], atol=1e-12)


def _sky(rng, n=10):
    A = euler123_to_dcm(random_euler123(rng, 1))[0]
    xy = np.column_stack([rng.uniform(60, 964, n), rng.uniform(60, 708, n)])
    v = PINHOLE.backproject(xy)
    return A, xy, v @ A                                  # r = A^T v: the stars' ICRS directions


def test_noise_free_stars_give_the_attitude_back_from_a_nearby_start():
    rng = np.random.default_rng(3)
    A, xy, r = _sky(rng)
    u = np.tile([1.0, 0.0], (len(xy), 1))
    A0 = frame_rotation(np.array([3e-6, -2e-6, 5e-5])) @ A          # an SVD answer's few arcsec off
    L = centroid_whitening(np.zeros(len(xy)), u, np.full(len(xy), 0.09), np.full(len(xy), 0.01))
    A1, cov, e, ok = solve_reprojection(A0, r, xy, L, PINHOLE)
    assert ok and np.abs(log_rotation(A1 @ A.T)).max() < 1e-8 and float((e * e).sum()) < 1e-6


def test_stated_covariance_is_the_scatter_and_beats_isotropic_weights_in_roll():
    rng = np.random.default_rng(4)
    A, xy, r = _sky(rng, 9)
    w = np.array([0.3, 0.5, 0.0])                      # a cross-boresight turn: parallel streaks
    w = w / np.linalg.norm(w) * math.radians(0.9)
    u, length = smear_axes(pixel_jacobian(r @ A.T, PINHOLE), w, 0.1)
    s_al, s_cr = 0.25, 0.05
    n = np.stack([-u[:, 1], u[:, 0]], axis=1)
    errs, errs_iso, covs = [], [], []
    f = 0.5 * (PINHOLE.fx + PINHOLE.fy)
    for _ in range(400):
        d = xy + u * rng.normal(size=(len(xy), 1)) * s_al + n * rng.normal(size=(len(xy), 1)) * s_cr
        b = PINHOLE.backproject(d)
        A_iso, ok, _ = solve_pairs(b, r, np.full(len(xy), (f / math.hypot(s_al, s_cr)) ** 2))
        L = centroid_whitening(np.zeros(len(xy)), u, np.full(len(xy), s_al ** 2), np.full(len(xy), s_cr ** 2))
        A2, cov, _, _ = solve_reprojection(A_iso, r, d, L, PINHOLE)
        errs.append(log_rotation(A2 @ A.T))
        errs_iso.append(log_rotation(A_iso @ A.T))
        covs.append(cov)
    errs, errs_iso = np.array(errs), np.array(errs_iso)
    emp = np.cov(errs.T)
    stated = np.mean(covs, axis=0)
    np.testing.assert_allclose(np.diag(emp), np.diag(stated), rtol=0.2)
    assert np.var(errs[:, 2]) < 0.7 * np.var(errs_iso[:, 2])


def test_a_star_that_does_not_move_gets_the_fallback_direction():
    """A roll about the optical axis leaves the star at the principal point in place: its direction is (1, 0) and
    its length 0, beside a moving star (length rho w t); no rate at all: every star (1, 0), length 0."""
    w = math.radians(0.8)
    xy = np.array([[512.0, 384.0], [512.0 + 300.0, 384.0]])
    G = pixel_jacobian(SQUARE.backproject(xy), SQUARE)
    u, length = smear_axes(G, np.array([0.0, 0.0, w]), 0.1)
    np.testing.assert_allclose(u[0], [1.0, 0.0], atol=0)
    np.testing.assert_allclose(length, [0.0, 300.0 * w * 0.1], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.abs(u[1]), [0.0, 1.0], atol=1e-9)
    u, length = smear_axes(G, np.zeros(3), 0.1)
    np.testing.assert_array_equal(u, [[1.0, 0.0], [1.0, 0.0]])
    np.testing.assert_array_equal(length, [0.0, 0.0])


@settings(max_examples=300, deadline=None)
@given(x=st.floats(-5, 70), y=st.floats(-5, 50), ang=st.floats(0, 2 * math.pi), length=st.floats(0, 40),
       margin=st.floats(0, 6))
def test_a_streak_is_inside_exactly_when_every_point_of_it_is_margin_inside(x, y, ang, length, margin):
    """Truth: 401 points sampled along the streak, each with a square of half-side ``margin`` around it, all in the
    64 x 48 image box (a brute force over the segment, not the bounding-box formula); points within 1e-6 px of the
    boundary are not judged."""
    u = np.array([[math.cos(ang), math.sin(ang)]])
    s = np.linspace(-0.5, 0.5, 401)[:, None] * length
    pts = np.array([x, y]) + s * u
    slack = np.array([(pts[:, 0] - margin).min(), (pts[:, 1] - margin).min(),
                      64 - (pts[:, 0] + margin).max(), 48 - (pts[:, 1] + margin).max()])
    assume(np.abs(slack).min() > 1e-6)
    got = streak_inside(np.array([[x, y]]), u, np.array([length]), margin, 64, 48)
    assert got.shape == (1,) and bool(got[0]) == bool((slack >= 0).all())


@settings(max_examples=200, deadline=None)
@given(x=st.floats(-5, 70), y=st.floats(-5, 50), margin=st.floats(0, 6))
def test_a_still_star_is_inside_when_its_margin_square_is(x, y, margin):
    """No streak (``u`` and ``length`` None): the star's square of half-side ``margin`` in the 64 x 48 box, written
    out; points within 1e-6 px of the boundary are not judged."""
    slack = np.array([x - margin, y - margin, 64 - x - margin, 48 - y - margin])
    assume(np.abs(slack).min() > 1e-6)
    got = streak_inside(np.array([[x, y]]), None, None, margin, 64, 48)
    assert got.shape == (1,) and bool(got[0]) == bool((slack >= 0).all())
