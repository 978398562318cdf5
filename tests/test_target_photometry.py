"""Photometry of the target in the star field (scene/target_photometry.py) against independent truth: the analytic
magnitude of a Lambertian sphere, a finely tessellated sphere through the facet formula, a face-on plate, the
photocentre of a lit sphere by quadrature, and the 3U CubeSat's brightness on the star renderer's zero point."""

import math

import numpy as np
import pytest

from dualsight.kernels.sensor_config import SensorConfig, flux_from_magnitude
from dualsight.scene import target_photometry as tp
from dualsight.scene.satellite import ComponentConfig, load_satellite

M_SUN = -26.74          # V magnitude of the Sun (written here, not taken from the module)


def analytic_sphere_mag(R, A, alpha, d):
    """m = m_sun - 2.5 log10(p (R/d)^2 Phi(alpha)), p = 2/3 A (Lambert sphere), Phi = (sin a + (pi - a) cos a)/pi."""
    phi = (math.sin(alpha) + (math.pi - alpha) * math.cos(alpha)) / math.pi
    return M_SUN - 2.5 * math.log10(2.0 / 3.0 * A * (R / d) ** 2 * phi)


def sun_at_phase(alpha):
    """Camera at the origin, target on +z: the unit vector towards the Sun at phase angle alpha (in the x-z plane)."""
    return np.array([math.sin(alpha), 0.0, -math.cos(alpha)])


@pytest.mark.parametrize("alpha_deg", [0.0, 30.0, 60.0, 90.0, 135.0])
def test_sphere_component_magnitude_is_analytic(alpha_deg):
    R, A, d = 0.5, 0.3, 2000.0
    a = math.radians(alpha_deg)
    shape = tp.target_shape([ComponentConfig(shape="sphere", size=(2 * R,), k_l=A)])
    b = tp.apparent_brightness(shape, np.eye(3)[None], np.array([[0.0, 0.0, d]]), sun_at_phase(a)[None], 1.5e6)
    assert b.vmag[0] == pytest.approx(analytic_sphere_mag(R, A, a, d), abs=1e-9)
    assert b.phase_rad[0] == pytest.approx(a, abs=1e-12)
    assert b.e_per_s[0] == pytest.approx(1.5e6 * 10 ** (-0.4 * analytic_sphere_mag(R, A, a, d)), rel=1e-9)
    assert b.irradiance_w_m2[0] == pytest.approx(1361.0 * 10 ** (-0.4 * (analytic_sphere_mag(R, A, a, d) - M_SUN)),
                                                 rel=1e-9)


@pytest.mark.parametrize("alpha_deg", [0.0, 45.0, 100.0])
def test_tessellated_sphere_through_facets_matches_analytic(alpha_deg):
    """The facet formula over 200k equal-area facets of a sphere (Fibonacci lattice) gives the Lambert sphere."""
    R, A, d, n = 1.0, 0.5, 1e4, 200_000
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = math.pi * (1 + 5 ** 0.5) * k
    nrm = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], -1)
    a = math.radians(alpha_deg)
    ratio = tp.facet_flux_ratio(np.full(n, 4 * math.pi * R * R / n), nrm, np.full(n, A), sun_at_phase(a),
                                np.array([0.0, 0.0, -1.0]), d).sum()
    assert tp.magnitude_from_ratio(ratio) == pytest.approx(analytic_sphere_mag(R, A, a, d), abs=2e-3)


def test_face_on_plate_and_cuboid():
    """A cuboid with one face to the Sun and the camera (phase 0): rho a / (pi d^2); rotated 60 deg about x:
    cos i = cos e = 1/2 on that face plus the y face's sin^2."""
    lx, ly, lz, rho, d = 0.1, 0.1, 0.3, 0.8, 1e4
    shape = tp.target_shape([ComponentConfig(shape="cuboid", size=(lx, ly, lz), k_l=rho)])
    face = lx * ly    # the +-z faces; the camera looks along +z, so the -z face looks back at it
    b = tp.apparent_brightness(shape, np.eye(3)[None], np.array([[0.0, 0.0, d]]), np.array([[0.0, 0.0, -1.0]]), 1.0)
    assert b.ratio[0] == pytest.approx(rho * face / (math.pi * d * d), rel=1e-12)
    assert b.area_m2[0] == pytest.approx(face, rel=1e-12)
    t = math.radians(60)
    Rx = np.array([[1, 0, 0], [0, math.cos(t), -math.sin(t)], [0, math.sin(t), math.cos(t)]])
    b = tp.apparent_brightness(shape, Rx[None], np.array([[0.0, 0.0, d]]), np.array([[0.0, 0.0, -1.0]]), 1.0)
    expect = rho * (lx * ly * math.cos(t) ** 2 + lx * lz * math.sin(t) ** 2) / (math.pi * d * d)
    assert b.ratio[0] == pytest.approx(expect, rel=1e-12)


def test_cylinder_side_approaches_smooth_cylinder():
    """Side-on cylinder at phase 0 (caps edge-on): the smooth side gives rho / (pi d^2) times the integral over the
    visible half of cos i cos e dA = r L int_{-pi/2}^{pi/2} cos^2 phi dphi = r L pi / 2."""
    r, L, rho, d = 0.2, 1.0, 0.6, 1e3
    shape = tp.target_shape([ComponentConfig(shape="cylinder", size=(2 * r, L), k_l=rho)])
    Rx = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float)      # axis along camera y
    b = tp.apparent_brightness(shape, Rx[None], np.array([[0.0, 0.0, d]]), np.array([[0.0, 0.0, -1.0]]), 1.0)
    assert b.ratio[0] == pytest.approx(rho * r * L * (math.pi / 2) / (math.pi * d * d), rel=1e-3)


@pytest.mark.parametrize("alpha_deg", [10.0, 45.0, 90.0, 120.0])
def test_sphere_photocentre_against_quadrature(alpha_deg):
    """The brightness centroid of a lit Lambertian sphere, by a midpoint quadrature over (theta, phi), equals the
    closed form; and apparent_brightness puts the sphere's centre of brightness there, towards the Sun."""
    a = math.radians(alpha_deg)
    n = 1500
    th = (np.arange(n) + 0.5) / n * math.pi
    ph = (np.arange(2 * n) + 0.5) / (2 * n) * 2 * math.pi
    T, P = np.meshgrid(th, ph, indexing="ij")
    nx, nz = np.sin(T) * np.cos(P), np.cos(T)            # observer along +z here, Sun at (sin a, 0, cos a)
    w = np.clip(nx * math.sin(a) + nz * math.cos(a), 0, None) * np.clip(nz, 0, None) * np.sin(T)
    x_bar = (w * nx).sum() / w.sum()
    R = 2.0
    assert tp.sphere_photocentre_offset(R, a) == pytest.approx(R * x_bar, rel=1e-5)
    shape = tp.target_shape([ComponentConfig(shape="sphere", size=(2 * R,), k_l=0.5)])
    b = tp.apparent_brightness(shape, np.eye(3)[None], np.array([[0.0, 0.0, 500.0]]), sun_at_phase(a)[None], 1.0)
    assert b.cob_cam[0] == pytest.approx([R * x_bar, 0.0, 500.0], abs=1e-4)


def test_cubesat_magnitude_zero_at_10km_and_saturates_at_100m():
    """The paper's 3U CubeSat (examples/satellites/cubesat_3u.toml, k_l 0.8) at phase 0-90 deg over random
    orientations: about V 0 at 10 km (median within +-1.5 mag); at 100 m, on the paper sensor (0.1 s, 1.5e6
    e-/s at V 0, full well 20 ke-), even spread over its whole projected area in pixels it saturates them."""
    sat = load_satellite("examples/satellites/cubesat_3u.toml")
    shape = tp.target_shape(sat.components)
    rng = np.random.default_rng([23, 1])
    B = 2000
    q = rng.normal(size=(B, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    R = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                  2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                  2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(B, 3, 3)
    alpha = rng.uniform(0, math.pi / 2, B)
    psi = rng.uniform(0, 2 * math.pi, B)
    sun = np.stack([np.sin(alpha) * np.cos(psi), np.sin(alpha) * np.sin(psi), -np.cos(alpha)], -1)
    sensor = SensorConfig()
    for d in (1e4, 100.0):
        b = tp.apparent_brightness(shape, R, np.tile([0.0, 0.0, d], (B, 1)), sun, sensor.zero_mag_rate_e_per_s)
        if d == 1e4:
            assert -1.5 < np.median(b.vmag) < 1.5
            # the brightest a 0.1 x 0.3 m face can be at 10 km: rho a / (pi d^2)
            assert b.vmag.min() >= M_SUN - 2.5 * math.log10(0.8 * 0.03 / (math.pi * d * d)) - 1e-9
        else:
            e = flux_from_magnitude(b.vmag, sensor)                 # the stars' own conversion
            np.testing.assert_allclose(e, b.e_per_s * sensor.exposure_s, rtol=1e-12)
            ifov = 4.65e-6 / 17e-3                                  # the paper star camera, rad per pixel
            pixels = b.area_m2 / (d * ifov) ** 2
            assert np.all(e / np.maximum(pixels, 1.0) > sensor.full_well_e)
