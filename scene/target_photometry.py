"""Photometry of a sunlit spacecraft seen by the star camera: apparent V magnitude, electrons per second on the
star renderer's zero point, and the centre of brightness (issue 23, point 1).

The target is the union of a satellite file's components (``scene/satellite.py``): cuboids and cylinders as flat
Lambertian facets, spheres analytically.  With the Sun at 1 au (irradiance ``E_sun`` = 1361 W/m^2, apparent
magnitude ``M_SUN_V`` = -26.74 V) and the camera at range d >> the target's size, the irradiance a facet of area
a, diffuse reflectance rho (the file's ``k_l``), unit normal n puts at the camera is (Lambert's law: radiance
rho E_sun / pi, projected area a cos e)::

    E = E_sun * rho * a * max(0, n.s) * max(0, n.o) / (pi d^2)        s: unit vector to the Sun, o: to the camera

and a Lambertian sphere of radius R (geometric albedo p = 2/3 rho, phase angle alpha between s and o)::

    E = E_sun * p * (R / d)^2 * Phi(alpha),   Phi(alpha) = [sin(alpha) + (pi - alpha) cos(alpha)] / pi

(Russell 1916, ApJ 43, 173; the phase integral of a Lambert sphere is q = 3/2).  The apparent magnitude is
``m = M_SUN_V - 2.5 log10(E / E_sun)``; the star renderer's zero point turns it into electrons exactly as it does
for stars (``kernels/sensor_config.flux_from_magnitude``: ``zero_mag_rate_e_per_s * 10^(-0.4 m)``).

The centre of brightness: a flat facet under a distant Sun and camera has uniform radiance, so its light comes
from its centre; a Lambertian sphere's photocentre is displaced from its centre towards the Sun's side, in the
plane of the sky, by (derived by integrating I ~ (n.s)(n.o) over the lit visible cap; ``tests/test_target_photometry.py``
checks it against a fine quadrature of the sphere)::

    delta(alpha) = (3 pi / 16) R sin(alpha) (1 + cos(alpha)) / (sin(alpha) + (pi - alpha) cos(alpha))

Phase-angle correction (issue 23, point 3): the centre of brightness is moved back to the body origin by

* :func:`sphere_photocentre_offset` for a sphere (the formula above: no attitude needed);
* :func:`photocentre_offset` for a target of KNOWN attitude and Sun direction: the exact Lambertian photocentre of
  its lit, visible facets (a flat facet's light comes from its centre, weighted by its flux ``facet_flux_ratio``;
  exact for one convex body, e.g. a cuboid, where no facet shadows or hides another);
* :func:`photocentre_table` for an UNKNOWN attitude: the mean offset towards the Sun over attitudes uniform on
  SO(3) per phase angle, and its spread (what the correction cannot remove).

Ignored (stated): mutual shadowing and occlusion between components (exact for one convex component), the specular
term (``k_s``), Earth shine and the target's thermal glow; the Sun's colour equals a V-band star's.
Units: metres, radians; vectors in one common frame (the camera frame in the star job).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dualsight.scene.attitude import quat_to_dcm, quaternions_from_uniforms
from dualsight.scene.motion import euler_deg_to_local_to_parent

__all__ = ["M_SUN_V", "SOLAR_IRRADIANCE_W_M2", "CYLINDER_STRIPS", "lambert_sphere_phase", "sphere_flux_ratio",
           "sphere_photocentre_offset", "facet_flux_ratio", "magnitude_from_ratio", "electrons_per_s",
           "TargetShape", "target_shape", "TargetBrightness", "apparent_brightness", "photocentre_offset",
           "PHASE_GRID_DEG", "PHOTOCENTRE_SAMPLES", "photocentre_table"]

M_SUN_V = -26.74
"""Apparent V magnitude of the Sun at 1 au (Allen's Astrophysical Quantities, 4th ed., Table 14.7: -26.74)."""
SOLAR_IRRADIANCE_W_M2 = 1361.0
"""Total solar irradiance at 1 au (W/m^2; Kopp & Lean 2011, GRL 38, L01706)."""
CYLINDER_STRIPS = 64
"""Flat strips that stand for a cylinder's side (the flux of 64 strips is within 0.1 % of the smooth side's)."""


def lambert_sphere_phase(alpha) -> np.ndarray:
    """Phase function of a Lambertian sphere, 1 at opposition: [sin a + (pi - a) cos a] / pi; alpha (rad) any shape."""
    a = np.asarray(alpha, dtype=np.float64)
    return (np.sin(a) + (np.pi - a) * np.cos(a)) / np.pi


def sphere_flux_ratio(radius, albedo, alpha, range_m) -> np.ndarray:
    """E / E_sun of a Lambertian sphere (radius m, diffuse reflectance ``albedo``) at phase ``alpha`` (rad) and
    ``range_m``: (2/3) albedo (R/d)^2 Phi(alpha) (module doc); broadcast over the inputs."""
    R, d = np.asarray(radius, np.float64), np.asarray(range_m, np.float64)
    return (2.0 / 3.0) * np.asarray(albedo, np.float64) * (R / d) ** 2 * lambert_sphere_phase(alpha)


def sphere_photocentre_offset(radius, alpha) -> np.ndarray:
    """Displacement (m) of a Lambertian sphere's centre of brightness from its centre, in the plane of the sky
    towards the Sun: (3 pi/16) R sin a (1 + cos a) / (sin a + (pi - a) cos a) (module doc); 0 at a = 0."""
    a = np.asarray(alpha, dtype=np.float64)
    den = np.sin(a) + (np.pi - a) * np.cos(a)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (3.0 * np.pi / 16.0) * np.asarray(radius, np.float64) * np.sin(a) * (1.0 + np.cos(a)) / den
    return np.where(den > 0, out, np.asarray(radius, np.float64) * np.ones_like(a))   # alpha -> pi: the limb


def facet_flux_ratio(area, normal, albedo, sun, obs, range_m) -> np.ndarray:
    """E / E_sun of flat Lambertian facets: albedo a max(0, n.s) max(0, n.o) / (pi d^2), per facet.

    area, albedo : (..., F); normal : (..., F, 3) unit; sun, obs : (..., 3) unit vectors from the target towards
    the Sun and towards the camera; range_m : (...) m.  Returns (..., F)."""
    n = np.asarray(normal, np.float64)
    ci = np.clip(np.einsum("...fk,...k->...f", n, np.asarray(sun, np.float64)), 0.0, None)
    ce = np.clip(np.einsum("...fk,...k->...f", n, np.asarray(obs, np.float64)), 0.0, None)
    d = np.asarray(range_m, np.float64)[..., None]
    return np.asarray(albedo, np.float64) * np.asarray(area, np.float64) * ci * ce / (np.pi * d * d)


def magnitude_from_ratio(ratio) -> np.ndarray:
    """Apparent V magnitude of an object giving ``ratio`` = E / E_sun: M_SUN_V - 2.5 log10(ratio) (+inf at 0)."""
    r = np.asarray(ratio, np.float64)
    with np.errstate(divide="ignore"):
        return np.where(r > 0, M_SUN_V - 2.5 * np.log10(np.where(r > 0, r, 1.0)), np.inf)


def electrons_per_s(vmag, zero_mag_rate_e_per_s: float) -> np.ndarray:
    """Electrons per second of a source of V magnitude ``vmag`` on the star renderer's zero point (the same
    formula as ``kernels/sensor_config.flux_from_magnitude`` without the exposure)."""
    return zero_mag_rate_e_per_s * np.power(10.0, -0.4 * np.asarray(vmag, np.float64))


@dataclass(frozen=True)
class TargetShape:
    """A target as photometric elements in its body frame.

    area (F,) m^2, normal (F, 3) unit outward, centre (F, 3) m, albedo (F,): flat facets (cuboid faces, cylinder
    caps and side strips); sphere_centre (P, 3) m, sphere_radius (P,) m, sphere_albedo (P,): spheres;
    bounding_radius : m about the body origin.
    """

    area: np.ndarray
    normal: np.ndarray
    centre: np.ndarray
    albedo: np.ndarray
    sphere_centre: np.ndarray
    sphere_radius: np.ndarray
    sphere_albedo: np.ndarray
    bounding_radius: float


def _component_facets(comp):
    """(area, normal, centre) of one component's flat facets in its own frame (none for a sphere)."""
    if comp.shape == "cuboid":
        lx, ly, lz = comp.size
        ax = np.eye(3)
        area = np.array([ly * lz, lx * lz, lx * ly] * 2)
        normal = np.concatenate([ax, -ax])
        half = 0.5 * np.array([lx, ly, lz])
        return area, normal, normal * np.concatenate([half, half])[:, None]
    if comp.shape == "cylinder":
        r, length = 0.5 * comp.size[0], comp.size[1]
        phi = (np.arange(CYLINDER_STRIPS) + 0.5) * 2 * np.pi / CYLINDER_STRIPS
        side = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], -1)
        caps = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
        area = np.concatenate([np.full(CYLINDER_STRIPS, 2 * np.pi * r * length / CYLINDER_STRIPS),
                               np.full(2, np.pi * r * r)])
        return area, np.concatenate([side, caps]), np.concatenate([side * r, caps * 0.5 * length])
    return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))


def target_shape(components) -> TargetShape:
    """The photometric elements of a satellite file's components (``SatelliteConfig.components``) at their
    frame-0 poses in the body frame (position, 1-2-3 ``orientation_deg``; ``k_l`` = diffuse reflectance)."""
    area, normal, centre, albedo, sc, sr, sa = [], [], [], [], [], [], []
    for comp in components:
        Q = euler_deg_to_local_to_parent(np.asarray(comp.orientation_deg, np.float64))
        q = np.asarray(comp.position, np.float64)
        if comp.shape == "sphere":
            sc.append(q)
            sr.append(0.5 * comp.size[0])
            sa.append(comp.k_l)
            continue
        a, n, c = _component_facets(comp)
        area.append(a)
        normal.append(n @ Q.T)
        centre.append(c @ Q.T + q)
        albedo.append(np.full(len(a), comp.k_l))
    cat = lambda xs, shape: np.concatenate(xs) if xs else np.zeros(shape)  # noqa: E731
    return TargetShape(cat(area, (0,)), cat(normal, (0, 3)), cat(centre, (0, 3)), cat(albedo, (0,)),
                       np.asarray(sc, np.float64).reshape(-1, 3), np.asarray(sr, np.float64),
                       np.asarray(sa, np.float64),
                       float(max(c.bounding_radius + float(np.linalg.norm(c.position)) for c in components)))


@dataclass(frozen=True)
class TargetBrightness:
    """Per case: ratio (B,) E / E_sun at the camera; irradiance_w_m2 (B,); vmag (B,) apparent V magnitude;
    e_per_s (B,) electrons per second on the zero point; phase_rad (B,); cob_cam (B, 3) the centre of brightness
    (m, the frame of the inputs; the body origin where the target is dark); area_m2 (B,) projected area of the
    elements facing the camera (m^2, self-occlusion ignored)."""

    ratio: np.ndarray
    irradiance_w_m2: np.ndarray
    vmag: np.ndarray
    e_per_s: np.ndarray
    phase_rad: np.ndarray
    cob_cam: np.ndarray
    area_m2: np.ndarray


def apparent_brightness(shape: TargetShape, R_body, pos, sun, zero_mag_rate_e_per_s: float) -> TargetBrightness:
    """Brightness of the target seen from the origin (the camera).

    R_body : (B, 3, 3) body -> camera rotation; pos : (B, 3) body origin (m); sun : (B, 3) unit vector towards
    the Sun (same frame); zero_mag_rate_e_per_s : electrons per second of a V = 0 star (``SensorConfig``).
    The range and the direction to the camera are the body origin's (d >> size).
    """
    R_body, pos = np.asarray(R_body, np.float64), np.asarray(pos, np.float64)
    sun = np.asarray(sun, np.float64)
    d = np.linalg.norm(pos, axis=-1)
    obs = -pos / d[:, None]
    phase = np.arccos(np.clip(np.einsum("bk,bk->b", sun, obs), -1.0, 1.0))
    n = np.einsum("bij,fj->bfi", R_body, shape.normal)                      # (B, F, 3)
    c = np.einsum("bij,fj->bfi", R_body, shape.centre) + pos[:, None]       # (B, F, 3)
    f_facet = facet_flux_ratio(shape.area, n, shape.albedo, sun, obs, d)   # (B, F)
    sc = np.einsum("bij,pj->bpi", R_body, shape.sphere_centre) + pos[:, None]   # (B, P, 3)
    f_sph = sphere_flux_ratio(shape.sphere_radius, shape.sphere_albedo, phase[:, None], d[:, None])  # (B, P)
    # sphere photocentres: towards the Sun's direction projected on the plane of the sky (normal obs)
    s_perp = sun - np.einsum("bk,bk->b", sun, obs)[:, None] * obs
    s_norm = np.linalg.norm(s_perp, axis=-1, keepdims=True)
    s_perp = np.divide(s_perp, s_norm, out=np.zeros_like(s_perp), where=s_norm > 0)
    off = sphere_photocentre_offset(shape.sphere_radius, phase[:, None])       # (B, P)
    sc = sc + off[..., None] * s_perp[:, None]
    total = f_facet.sum(-1) + f_sph.sum(-1)
    wsum = np.einsum("bf,bfk->bk", f_facet, c) + np.einsum("bp,bpk->bk", f_sph, sc)
    cob = np.where(total[:, None] > 0, wsum / np.where(total > 0, total, 1.0)[:, None], pos)
    area = (shape.area * np.clip(np.einsum("bfk,bk->bf", n, obs), 0.0, None)).sum(-1) \
        + np.pi * (shape.sphere_radius ** 2).sum()
    vmag = magnitude_from_ratio(total)
    return TargetBrightness(total, total * SOLAR_IRRADIANCE_W_M2, vmag, electrons_per_s(vmag, zero_mag_rate_e_per_s),
                            phase, cob, area)


def photocentre_offset(shape: TargetShape, R_body, sun, obs) -> np.ndarray:
    """(B, 3) offset (m) of a target's centre of brightness from its body origin, seen from far along ``obs``.

    R_body : (B, 3, 3) body -> frame rotation (the target's KNOWN attitude); sun, obs : (B, 3) unit vectors from
    the target towards the Sun and towards the camera, same frame.  Each lit (n.s > 0), visible (n.o > 0) flat
    facet shines from its centre with weight ``facet_flux_ratio`` (uniform radiance of a flat Lambertian facet
    under a distant Sun and camera), each sphere from its centre moved by :func:`sphere_photocentre_offset`
    towards the Sun in the plane of the sky; the offset is the flux-weighted mean minus the origin, projected on
    the plane of the sky (normal ``obs``).  Exact for one convex component (no mutual shadowing or occlusion).
    Zero where nothing lit faces the camera."""
    obs = np.asarray(obs, np.float64)
    d = 1e6                                              # far: the direction to every facet is obs
    pos = -d * obs
    br = apparent_brightness(shape, R_body, pos, sun, 1.0)
    off = br.cob_cam - pos
    return off - np.einsum("bk,bk->b", off, obs)[:, None] * obs


PHASE_GRID_DEG = np.arange(0.0, 180.1, 5.0)
"""Phase angles (deg) of :func:`photocentre_table`."""
PHOTOCENTRE_SAMPLES = 4000
"""Random attitudes per phase angle of :func:`photocentre_table`."""


def photocentre_table(shape: TargetShape, n: int = PHOTOCENTRE_SAMPLES, seed: int = 0
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The target's centre of brightness about its body origin over ``n`` attitudes uniform on SO(3) (drawn from
    ``default_rng([seed, 23, 5])``, the same for every run), at each phase angle of :data:`PHASE_GRID_DEG`, seen
    from far (:func:`apparent_brightness`: Lambertian facets and spheres): (alpha (A,) rad, mean offset towards
    the Sun in the plane of the sky (A,) m, spread (A,) m = sqrt of the mean of the two variances across the line
    of sight).  The correction for an unknown attitude (the mean) and what it leaves (the spread).  Where no
    attitude is lit (alpha -> 180 deg) the mean is 0 and the spread the bounding radius."""
    rng = np.random.default_rng([seed, 23, 5])
    u = rng.random((3, n))
    R = quat_to_dcm(quaternions_from_uniforms(u[0], u[1], u[2]))
    d = 1e4
    pos = np.tile([0.0, 0.0, d], (n, 1))
    alpha = np.radians(PHASE_GRID_DEG)
    mean, spread = np.zeros(alpha.size), np.full(alpha.size, float(shape.bounding_radius))
    for i, a in enumerate(alpha):                     # a few dozen angles, each over all attitudes at once
        sun = np.tile([np.sin(a), 0.0, -np.cos(a)], (n, 1))              # observer at -z from the target
        br = apparent_brightness(shape, R, pos, sun, 1.0)
        lit = br.ratio > 0
        if lit.sum() > 1:
            off = br.cob_cam[lit] - pos[lit]
            mean[i] = float(np.mean(off[:, 0]))
            spread[i] = float(np.sqrt(0.5 * (np.var(off[:, 0]) + np.var(off[:, 1]))))
    return alpha, mean, spread
