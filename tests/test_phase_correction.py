"""The phase-angle correction of the target's centre of brightness (issue 23, point 3 / 6 (b)) against independent
truth: a lit Lambertian sphere's photocentre by a fine grid over its disc, a cuboid's photocentre for a known
attitude by a brute-force ray-cast image, the line-of-sight correction by the geometry of a target at a known range;
and the blob's centroid sigma by its formula written out."""

import math

import numpy as np
import pytest

from dualsight.nav import target_bearing as tb
from dualsight.scene import target_photometry as tp
from dualsight.scene.satellite import ComponentConfig


def basis(obs):
    """Two unit vectors across ``obs`` (the image plane of an orthographic camera looking along -obs)."""
    ref = np.array([1.0, 0.0, 0.0]) if abs(obs[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(obs, ref)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(obs, e1)


def rot(axis, ang):
    """Rodrigues' rotation matrix (written here)."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(ang) * K + (1 - math.cos(ang)) * K @ K


def disc_photocentre(alpha, n=2001):
    """A unit Lambertian sphere seen along -z (observer on +z), Sun at phase alpha in the x-z plane: the centroid
    (x, y) of its image on an n x n grid over the disc, each point's radiance max(0, N.s) (N = (x, y, sqrt(1 - x^2
    - y^2)); the projected area is the grid cell's, so no foreshortening factor)."""
    g = (np.arange(n) + 0.5) / n * 2 - 1
    X, Y = np.meshgrid(g, g, indexing="ij")
    inside = X * X + Y * Y < 1
    Z = np.sqrt(np.where(inside, 1 - X * X - Y * Y, 0.0))
    w = np.where(inside, np.clip(X * math.sin(alpha) + Z * math.cos(alpha), 0, None), 0.0)
    return (w * X).sum() / w.sum(), (w * Y).sum() / w.sum()


def raycast_cuboid_photocentre(half, R, sun, obs, n=900):
    """Brute force: an orthographic image (n x n rays along -obs) of the cuboid of half-sizes ``half`` turned by
    ``R`` (body -> frame); a ray's first hit (slab method) shines max(0, N.s) of the face it enters.  Returns the
    brightness centroid in the frame (its part across obs) about the body origin."""
    e1, e2 = basis(obs)
    L = float(np.linalg.norm(half)) * 1.05
    g = (np.arange(n) + 0.5) / n * 2 * L - L
    A, Bq = np.meshgrid(g, g, indexing="ij")
    P = A[..., None] * e1 + Bq[..., None] * e2 + 10.0 * obs            # ray origins, in front of the body
    o = P.reshape(-1, 3) @ R                                            # body frame (R^T p)
    d = -obs @ R
    with np.errstate(divide="ignore"):
        t1, t2 = (-half - o) / d, (half - o) / d
    tn, tf = np.minimum(t1, t2), np.maximum(t1, t2)
    t_near, t_far = tn.max(1), tf.min(1)
    hit = t_near < t_far
    axis = tn.argmax(1)
    n_body = np.zeros_like(o)
    n_body[np.arange(len(o)), axis] = -np.sign(d[axis])
    N = n_body @ R.T
    w = np.where(hit, np.clip(N @ sun, 0, None), 0.0)
    c = (w[:, None] * P.reshape(-1, 3)).sum(0) / w.sum()
    return c - (c @ obs) * obs


@pytest.mark.parametrize("alpha_deg", [0.0, 30.0, 60.0, 90.0])
def test_sphere_table_and_offset_against_a_fine_grid_over_the_disc(alpha_deg):
    a = math.radians(alpha_deg)
    x_bar, y_bar = disc_photocentre(a)
    R = 0.4
    assert abs(y_bar) < 1e-9
    assert tp.sphere_photocentre_offset(R, a) == pytest.approx(R * x_bar, abs=2e-4 * R)
    sphere = tp.target_shape([ComponentConfig(shape="sphere", size=(2 * R,), k_l=0.5)])
    alpha, mean, spread = tp.photocentre_table(sphere, n=20)
    i = int(np.argmin(abs(alpha - a)))
    assert alpha[i] == pytest.approx(a)
    assert mean[i] == pytest.approx(R * x_bar, abs=2e-4 * R)          # towards the Sun
    assert spread[i] == pytest.approx(0.0, abs=1e-9)                   # a sphere looks the same in every attitude


@pytest.mark.parametrize("case", range(6))
def test_cuboid_photocentre_of_a_known_attitude_against_a_raycast_image(case):
    rng = np.random.default_rng([23, 6, case])
    size = np.array([0.1, 0.1, 0.3])
    shape = tp.target_shape([ComponentConfig(shape="cuboid", size=tuple(size), k_l=0.8)])
    R = rot(rng.normal(size=3), rng.uniform(0, math.pi))
    obs = rng.normal(size=3)
    obs /= np.linalg.norm(obs)
    alpha = math.radians([0.0, 20.0, 45.0, 70.0, 90.0, 85.0][case])
    e1, _ = basis(obs)
    sun = math.cos(alpha) * obs + math.sin(alpha) * (math.cos(1.0 + case) * e1 + math.sin(1.0 + case)
                                                    * np.cross(obs, e1))
    want = raycast_cuboid_photocentre(0.5 * size, R, sun, obs)
    got = tp.photocentre_offset(shape, R[None], sun[None], obs[None])[0]
    assert abs(got @ obs) < 1e-12
    # 900 x 900 rays over ~0.35 m: cells of 0.4 mm; the centroid's error is well under a cell
    np.testing.assert_allclose(got, want, atol=1.5e-4)
    assert np.linalg.norm(want) > 1e-3 or alpha == 0.0                  # the test sees a real offset


def test_offset_correction_recovers_the_body_origin():
    rng = np.random.default_rng([23, 6, 99])
    B = 50
    u_body = rng.normal(size=(B, 3))
    u_body /= np.linalg.norm(u_body, axis=1, keepdims=True)
    r = rng.uniform(50.0, 5000.0, B)
    off = rng.normal(scale=0.05, size=(B, 3))                          # the photocentre about the origin (m)
    cob = u_body * r[:, None] + off
    u_cob = cob / np.linalg.norm(cob, axis=1, keepdims=True)
    u = tb.offset_correction(u_cob, off, r)
    # small-angle: exact to (|off| / r)^2
    assert tb.bearing_error(u, u_body).max() < 5 * (0.2 / 50.0) ** 2
    assert tb.bearing_error(u_cob, u_body).min() > 1e-6                 # there was something to correct


def test_blob_centroid_sigma_is_the_point_sigma_and_a_fraction_of_the_rms_radius():
    npix = np.array([2 * math.pi * 100.0, 2 * math.pi * 100.0, 2 * math.pi * 4.0])     # r_rms 10, 10, 2 px
    s = tb.blob_centroid_sigma(npix, np.array([0.3, 0.3, 0.05]), np.array([False, True, False]),
                               frac_point=0.02, frac_resolved=0.25)
    np.testing.assert_allclose(s, [math.hypot(0.3, 0.2), math.hypot(0.3, 2.5), math.hypot(0.05, 0.04)])
