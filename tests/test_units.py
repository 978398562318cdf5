"""scene.units: the angle constants and angle_between against exact constructions.

Truth: vectors built at a known angle t, (1, 0, 0) and (cos t, sin t, 0), then rotated and scaled;
the unit constants against their definitions (pi rad = 180 deg = 648,000 arcsec).
"""

from __future__ import annotations

import math

import numpy as np

from dualsight.scene.attitude import quat_to_dcm, random_quaternions
from dualsight.scene.units import ARCSEC, DEG, MAS, angle_between


def test_constants():
    assert math.isclose(180 * DEG, math.pi, rel_tol=1e-15)
    assert math.isclose(648_000 * ARCSEC, math.pi, rel_tol=1e-15)
    assert math.isclose(1000 * MAS, ARCSEC, rel_tol=1e-15)
    assert np.radians(7.3) == 7.3 * DEG                    # numpy's converter uses the same factor


def test_angle_between_exact_angles_at_every_scale():
    rng = np.random.default_rng(0)
    t = np.array([0.0, 1e-12, 1e-9, 1e-6 * ARCSEC, ARCSEC, 1e-3, 0.5, np.pi / 2, 2.0, np.pi - 1e-6,
                  np.pi - 1e-9, np.pi])
    a = np.broadcast_to([1.0, 0.0, 0.0], (t.size, 3))
    b = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=-1)
    np.testing.assert_allclose(angle_between(a, b), t, rtol=1e-15, atol=0)   # exact inputs: to rounding
    R = quat_to_dcm(random_quaternions(rng, t.size))                          # rotated: a few ulps of 1
    ar, br = np.einsum("bij,bj->bi", R, a), np.einsum("bij,bj->bi", R, b)
    scale = rng.uniform(0.1, 10.0, (2, t.size, 1))                            # lengths do not matter
    got = angle_between(ar * scale[0], br * scale[1])
    np.testing.assert_allclose(got, t, rtol=1e-14, atol=1e-15)
    assert np.all((got >= 0) & (got <= np.pi))
    # 1e-9 rad, where acos of the dot product (cos t rounds to 1.0) sees no angle at all
    assert np.arccos(a[2] @ b[2]) == 0.0 and math.isclose(angle_between(a[2], b[2]), 1e-9, rel_tol=1e-15)


def test_angle_between_broadcasts_and_is_symmetric():
    rng = np.random.default_rng(1)
    u = rng.normal(size=(5, 1, 3))
    v = rng.normal(size=(1, 7, 3))
    d = angle_between(u, v)
    assert d.shape == (5, 7)
    np.testing.assert_array_equal(d, angle_between(v, u))
    assert angle_between([0.0, 0.0, 2.0], [0.0, 3.0, 0.0]) == np.pi / 2
