"""Clohessy-Wiltshire relative motion (scene/relative_orbit.py, issue 23 point 4) against independent truth: the
CW ODE integrated by a hand-written RK4 (no scipy on this machine), the closed 2:1 ellipse, the Hill frame built
here from Keplerian elements by elementary rotations, two-body orbits integrated in the inertial frame, and a
delta-v changing the later state by exactly Phi applied to it."""

import math

import numpy as np

from dualsight.scene import relative_orbit as ro

ORBIT = ro.CircularOrbit(altitude_m=500e3, inclination_rad=math.radians(97.4), raan_rad=math.radians(40.0),
                         arg_lat_rad=math.radians(25.0))
N = ORBIT.mean_motion


def cw_rhs(x, n):
    """The CW equations written out (Curtis Eq. 7.36): x'' = 3n^2 x + 2n y', y'' = -2n x', z'' = -n^2 z."""
    return np.stack([x[..., 3], x[..., 4], x[..., 5], 3 * n * n * x[..., 0] + 2 * n * x[..., 4],
                     -2 * n * x[..., 3], -n * n * x[..., 2]], -1)


def rk4(f, x, t_end, steps):
    h = t_end / steps
    for _ in range(steps):
        k1 = f(x)
        k2 = f(x + h / 2 * k1)
        k3 = f(x + h / 2 * k2)
        k4 = f(x + h * k3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


def test_mean_motion_and_period():
    a = 6378137.0 + 500e3
    assert math.isclose(N, math.sqrt(3.986004418e14 / a ** 3), rel_tol=1e-15)
    assert 5660 < ORBIT.period_s < 5680            # 500 km LEO: 94.6 min


def test_stm_against_rk4_of_the_ode():
    # Phi(t) column by column: integrate the ODE from each unit state
    for t in (300.0, 2000.0, 7000.0):
        Phi_num = rk4(lambda x: cw_rhs(x, N), np.eye(6), t, int(t / 2))    # rows = propagated unit states
        Phi = ro.cw_stm(N, t)
        scale = np.maximum(np.abs(Phi_num.T), 1.0)
        assert np.max(np.abs(Phi - Phi_num.T) / scale) < 1e-9
    assert np.allclose(ro.cw_stm(N, 0.0), np.eye(6))
    # group property, backwards too
    assert np.allclose(ro.cw_stm(N, 1234.0) @ ro.cw_stm(N, -1234.0), np.eye(6), atol=1e-9)


def test_closed_2_to_1_ellipse():
    x0 = 150.0
    st = np.array([[x0, 0.0, 0.0, 0.0, -2 * N * x0, 0.0]])
    t = np.linspace(0, 3 * ORBIT.period_s, 601)
    traj = ro.propagate(st, t, N)[0]
    assert np.allclose(traj[:, 0], x0 * np.cos(N * t), atol=1e-6)        # analytic: x = x0 cos nt
    assert np.allclose(traj[:, 1], -2 * x0 * np.sin(N * t), atol=1e-6)   # y = -2 x0 sin nt: along-track extent 4 x0
    assert math.isclose(np.ptp(traj[:, 1]), 4 * x0, rel_tol=1e-4)
    assert np.allclose(traj[-1], st[0], atol=1e-6)                       # closed after whole orbits: no drift
    # without the matched vy0 the chaser drifts along-track by 6 (sin nt - nt) x0 = -12 pi x0 per orbit
    drift = ro.propagate(np.array([[x0, 0, 0, 0, 0, 0.0]]), [ORBIT.period_s], N)[0, 0, 1]
    assert math.isclose(drift, -12 * math.pi * x0, rel_tol=1e-9)


def test_delta_v_is_phi_applied_after():
    rng = np.random.default_rng([23, 40])
    st = rng.normal(size=(5, 6)) * np.array([100, 100, 100, 0.1, 0.1, 0.1])
    tm = np.array([700.0, 1900.0])
    dv = np.array([[0.05, -0.02, 0.01], [-0.03, 0.04, 0.0]])
    times = np.array([0.0, 699.0, 700.0, 1500.0, 1900.0, 4000.0])
    out = ro.propagate(st, times, N, dv_times=tm, dv=dv)
    plain = ro.propagate(st, times, N)
    # the difference is the impulse propagated by Phi from its instant (linear superposition)
    d = np.zeros((6, 6))
    for k, t in enumerate(times):
        for tk, dvk in zip(tm, dv):
            if t >= tk:
                d[k] += ro.cw_stm(N, t - tk) @ np.concatenate([[0, 0, 0], dvk])
    assert np.allclose(out - plain, d[None], atol=1e-9)
    assert np.allclose(out[:, 1], plain[:, 1])                           # before the first burn: unchanged
    assert np.allclose(out[:, 2, 3:] - plain[:, 2, 3:], dv[0], atol=1e-12)  # at its instant: the burn included


def elementary(axis, ang):
    c, s = math.cos(ang), math.sin(ang)
    if axis == 1:
        return np.array([[1, 0, 0], [0, c, s], [0, -s, c]])
    return np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])


def kepler_rv(orbit, t):
    """Circular orbit by the classical perifocal-to-inertial rotation R3(-O) R1(-i) R3(-u) (Vallado Eq. 2-98)."""
    a, n = orbit.radius_m, orbit.mean_motion
    u = orbit.arg_lat_rad + n * t
    M = elementary(3, -orbit.raan_rad) @ elementary(1, -orbit.inclination_rad) @ elementary(3, -u)
    return M @ np.array([a, 0, 0]), M @ np.array([0, a * n, 0])


def test_hill_frame_against_keplerian_elements():
    t = np.array([0.0, 800.0, 3100.0])
    R = ro.hill_to_icrs(ORBIT, t)
    for k, tk in enumerate(t):
        r, v = kepler_rv(ORBIT, tk)
        xh = r / np.linalg.norm(r)
        zh = np.cross(r, v) / np.linalg.norm(np.cross(r, v))
        assert np.allclose(R[k][:, 0], xh, atol=1e-12)
        assert np.allclose(R[k][:, 2], zh, atol=1e-12)
        assert np.allclose(R[k][:, 1], v / np.linalg.norm(v), atol=1e-12)  # circular: along-track = velocity
        assert np.allclose(R[k].T @ R[k], np.eye(3), atol=1e-12) and np.linalg.det(R[k]) > 0
    # the orbit normal's angle from the pole is the inclination
    assert math.isclose(math.degrees(math.acos(R[0][2, 2])), 97.4, abs_tol=1e-9)


def two_body(x):
    r = x[..., :3]
    return np.concatenate([x[..., 3:], -ro.MU_EARTH * r / np.linalg.norm(r, axis=-1, keepdims=True) ** 3], -1)


def test_cw_against_two_body_in_inertial_frame():
    # chaser 200 m off the target in each direction, drifting; both integrated as two-body orbits (RK4, 1 s)
    hill0 = np.array([[120.0, -200.0, 80.0, 0.05, -0.1, 0.02]])
    T = 1500.0
    r0, v0 = kepler_rv(ORBIT, 0.0)
    tgt0 = np.concatenate([r0, v0])
    chs0 = tgt0 + ro.hill_state_to_icrs(ORBIT, [0.0], hill0)[0]
    both = rk4(two_body, np.stack([tgt0, chs0]), T, 1500)
    rel_true = both[1] - both[0]
    rel_cw = ro.hill_state_to_icrs(ORBIT, [T], ro.propagate(hill0, [T], N)[0])[0]
    # linearisation error ~ rho^2 / a (~1e-2 m for 300 m at 6878 km) grows over the arc; 0.1 m and 0.1 mm/s bound
    assert np.linalg.norm(rel_true[:3] - rel_cw[:3]) < 0.1
    assert np.linalg.norm(rel_true[3:] - rel_cw[3:]) < 1e-4
    # and the difference between the two motions is large (the check is not vacuous)
    assert np.linalg.norm(rel_true[:3] - ro.hill_state_to_icrs(ORBIT, [0.0], hill0)[0, :3]) > 100
