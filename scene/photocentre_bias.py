"""How the centre of brightness of a spinning target errs after the mean phase correction, and for how long:
the white part and the part correlated from frame to frame (issue 23, point 6 c).

``scene/target_photometry.photocentre_table`` gives, per phase angle alpha, the mean photocentre offset over
attitudes uniform on SO(3) (the correction) and its spread (what the correction leaves).  A target that spins
about a fixed axis at a rate omega, seen in frames far apart against its spin (omega dt spreading the spin
phases over the circle), does not draw a fresh uniform attitude per frame: its spin axis is fixed for the whole
approach, so the residual splits into

* the offset of the spin-averaged photocentre from the mean over all attitudes: the same in every frame while
  the viewing geometry holds -- a bias, different per approach (its spin axis and initial attitude), zero mean
  over approaches; its standard deviations ``sigma_sun`` along the Sun's direction in the plane of the sky and
  ``sigma_cross`` across it;
* the scatter about that spin average from frame to frame (the spin phase): white, ``white_sun`` and
  ``white_cross`` along the Sun's direction and across (``spread_white``: the root of the mean of the two
  variances, as ``photocentre_table``'s spread).

By the law of total variance (the variance over all attitudes = the variance of the spin means + the mean
variance within a spin) the two add up to the table's spread.  The bias changes as the camera sees the spinning
body from another direction: turning the observer about the Sun's direction (phase angle held) by an angle
psi, the correlation of the spin-averaged offset falls from 1; :func:`photocentre_statistics` returns the angle
``psi_c``, the integral of that correlation over half a turn (:func:`correlation_angle`: the correlation falls
and turns negative, so the integral is shorter than its 1/e point), so that a first-order Gauss-Markov model
``exp(-psi / psi_c)`` (Gelb 1974, Table 4.4-1) with the same integral stands for it in a filter
(``nav/relative_filter.py``): what a filter averaging many frames is sensitive to.  For a target that does not spin the whole
spread is the bias (``spread_white`` = 0).

The photocentre is the Lambertian facets' of ``scene/target_photometry.photocentre_offset`` (the star camera's
target), or with :func:`shaded_photocentre_offset` the proximity renderer's shading (``kernels/prox_shading.py``,
the reference's Eq. 3: ambient, diffuse and specular light per facet), whose ambient light, the same on every
visible facet, pulls the photocentre back towards the silhouette's centre.  The statistics then carry the mean
offset along the Sun too (``mean_sun``: the correction for an unknown attitude under that shading).

Everything is by Monte Carlo over spin axes (uniform on the sphere), initial attitudes (uniform on SO(3)) and
spin phases (uniform on the circle, an even grid) with the Lambertian facet photocentre of
``scene/target_photometry.photocentre_offset`` (exact for one convex component), from
``default_rng([seed, 23, 6])``: the same for every run.  Units: metres, radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dualsight.scene.attitude import quat_to_dcm, quaternions_from_uniforms
from dualsight.scene.rotation_vector import frame_rotation
from dualsight.scene.target_photometry import CYLINDER_STRIPS, TargetShape, photocentre_offset

__all__ = ["BIAS_PHASE_GRID_DEG", "facet_materials", "shaded_photocentre_offset", "BIAS_SPIN_AXES", "BIAS_SPIN_PHASES", "BIAS_TURN_DEG", "PhotocentreStatistics",
           "correlation_angle", "photocentre_statistics"]

BIAS_PHASE_GRID_DEG = np.arange(0.0, 180.1, 10.0)
"""Phase angles (deg) of :func:`photocentre_statistics`."""
BIAS_SPIN_AXES = 200
"""Spin axes (each with its own initial attitude) per phase angle."""
BIAS_SPIN_PHASES = 24
"""Spin phases per axis (an even grid over the circle)."""
BIAS_TURN_DEG = np.arange(0.0, 360.0, 15.0)
"""Turns (deg) of the observer about the Sun's direction, a full circle: the correlation at a lag is averaged over
every start on it."""


@dataclass(frozen=True)
class PhotocentreStatistics:
    """Per phase angle ``alpha`` (A,) rad: ``mean_sun`` (A,) m the mean offset towards the Sun in the plane of the
    sky over all attitudes (the correction); ``sigma_sun``, ``sigma_cross`` (A,) m the spin-averaged photocentre's
    standard deviations about the mean over all attitudes (along the Sun's direction in the plane of the sky and
    across it); ``spread_white`` (A,) m the frame-to-frame scatter about the spin average (root mean of the two
    variances; ``white_sun``, ``white_cross`` (A,) m each); ``psi_c`` (A, 2) rad the integral scale of the correlation of the bias along the Sun and across
    against the observer's turn about the Sun (:func:`correlation_angle`; ``inf``: it does not fall)."""

    alpha: np.ndarray
    mean_sun: np.ndarray
    sigma_sun: np.ndarray
    sigma_cross: np.ndarray
    spread_white: np.ndarray
    psi_c: np.ndarray
    white_sun: np.ndarray
    white_cross: np.ndarray

    def at(self, alpha):
        """(sigma_sun, sigma_cross, white_sun, white_cross, psi_c along the Sun, psi_c across) interpolated at
        phase angles alpha (rad)."""
        a = np.asarray(alpha, np.float64)
        return tuple(np.interp(a, self.alpha, v) for v in (self.sigma_sun, self.sigma_cross, self.white_sun,
                                                              self.white_cross, self.psi_c[:, 0], self.psi_c[:, 1]))


def facet_materials(components) -> np.ndarray:
    """(F, 4) [k_a, k_l, k_s, n] per flat facet of ``target_shape(components)`` (the same order: a cuboid's 6
    faces, a cylinder's 2 caps and :data:`CYLINDER_STRIPS` strips; spheres have none).  Raises ValueError for a
    shape without flat facets of its own (a sphere), whose shaded photocentre this module does not model."""
    rows = []
    for comp in components:
        if comp.shape == "cuboid":
            k = 6
        elif comp.shape == "cylinder":
            k = 2 + CYLINDER_STRIPS
        else:
            raise ValueError(f"shaded photocentre: component shape {comp.shape!r} not modelled (cuboid, cylinder)")
        rows.append(np.tile([comp.k_a, comp.k_l, comp.k_s, comp.n], (k, 1)))
    return np.concatenate(rows).astype(np.float64)


def shaded_photocentre_offset(shape: TargetShape, materials: np.ndarray, I_a: float, I_l: float, R_body, sun,
                              obs) -> np.ndarray:
    """(B, 3) offset (m) of the centre of brightness from the body origin under the proximity renderer's shading,
    seen from far along ``obs``, projected on the plane of the sky (normal ``obs``).

    A flat facet of area a and unit normal n under a distant light s and camera o has uniform radiance
    ``I = I_a k_a + I_l (k_l max(n.s, 0) + k_s max(r.o, 0)^n_s [n.s > 0])``, ``r.o = 2 (n.o)(n.s) - o.s``
    (``kernels/prox_shading.py``: the reference's Eqs. 2-3), so its image's light ``I a max(n.o, 0)`` comes from
    its centre; the photocentre is their flux-weighted mean (exact for one convex body).  materials (F, 4)
    (:func:`facet_materials`); R_body (B, 3, 3) body -> frame; sun, obs (B, 3) unit vectors from the target."""
    R_body = np.asarray(R_body, np.float64)
    sun, obs = np.asarray(sun, np.float64), np.asarray(obs, np.float64)
    n = np.einsum("bij,fj->bfi", R_body, shape.normal)                          # (B, F, 3)
    c = np.einsum("bij,fj->bfi", R_body, shape.centre)
    ns = np.einsum("bfk,bk->bf", n, sun)
    no = np.einsum("bfk,bk->bf", n, obs)
    ka, kl, ks, ne = (materials[:, i] for i in range(4))
    ro = 2.0 * no * ns - np.einsum("bk,bk->b", obs, sun)[:, None]
    spec = np.where(ns > 0, ks * np.clip(ro, 0.0, None) ** ne, 0.0)
    radiance = I_a * ka + I_l * (kl * np.clip(ns, 0.0, None) + spec)
    w = radiance * shape.area * np.clip(no, 0.0, None)
    tot = w.sum(-1)
    off = np.einsum("bf,bfk->bk", w, c) / np.where(tot > 0, tot, 1.0)[:, None]
    return off - np.einsum("bk,bk->b", off, obs)[:, None] * obs


def correlation_angle(psi: np.ndarray, corr: np.ndarray) -> float:
    """The integral scale ``int_0^psi_max corr(psi) dpsi`` (rad; trapezoid over the samples psi (L,) from 0 to
    half a turn, corr (L,) from 1), floored at the first step: the time constant of the first-order Gauss-Markov
    process whose average over a long arc has the same variance as the bias's (the variance of a mean over an arc
    L >> psi_c is ``2 sigma^2 psi_c / L`` for either; Bendat & Piersol, *Random Data*, 4th ed., 2010, Sec. 8.2.1).
    A correlation that never falls (a bias fixed whatever the turn) gives inf."""
    if np.all(corr > 1.0 - 1e-9):
        return float("inf")
    return float(max(np.trapezoid(corr, psi), psi[1] - psi[0]))


def photocentre_statistics(shape: TargetShape, spinning: bool = True, seed: int = 0,
                           n_axes: int = BIAS_SPIN_AXES, n_phases: int = BIAS_SPIN_PHASES,
                           offset=None) -> PhotocentreStatistics:
    """The bias and white parts of the photocentre's residual (module docstring) at each phase angle of
    :data:`BIAS_PHASE_GRID_DEG`, for a target spinning (``spinning``) or held (its attitude fixed over the
    approach: the whole residual is the bias).  ``offset(R_body, sun, obs) -> (B, 3)``: the photocentre model
    (default: the Lambertian facets' ``photocentre_offset(shape, ...)``; e.g. :func:`shaded_photocentre_offset`).

    Geometry per phase angle alpha: Sun along +z, observer at angle alpha from it, turned about z by each angle
    of :data:`BIAS_TURN_DEG`; offsets projected on the plane of the sky, along the Sun's projection and across.
    Where nothing lit faces the camera (possible beyond 90 deg of phase) the offsets are zero
    (``photocentre_offset``) and count, where ``photocentre_table`` keeps the lit attitudes only."""
    if offset is None:
        def offset(R_body, sun, obs):
            return photocentre_offset(shape, R_body, sun, obs)
    rng = np.random.default_rng([seed, 23, 6])
    axes = rng.normal(size=(n_axes, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    u = rng.random((3, n_axes))
    R0 = quat_to_dcm(quaternions_from_uniforms(u[0], u[1], u[2]))
    K = n_phases if spinning else 1
    phi = np.arange(K) * (2.0 * np.pi / K)
    R = frame_rotation((axes[:, None, :] * phi[None, :, None]).reshape(-1, 3)) @ np.repeat(R0, K, 0)   # (M K, 3, 3)
    sun = np.array([0.0, 0.0, 1.0])
    turns = np.radians(BIAS_TURN_DEG)
    alpha = np.radians(BIAS_PHASE_GRID_DEG)
    out = np.zeros((8, alpha.size))
    half = turns.size // 2 + 1
    for i, a in enumerate(alpha):
        obs = np.stack([np.sin(a) * np.cos(turns), np.sin(a) * np.sin(turns), np.full_like(turns, np.cos(a))], -1)
        e_sun = sun - np.cos(a) * obs                                   # the Sun's projection across obs
        n = np.linalg.norm(e_sun, axis=-1, keepdims=True)
        e_sun = np.where(n > 1e-12, e_sun / np.where(n > 1e-12, n, 1.0), np.array([1.0, 0.0, 0.0]))
        e_cross = np.cross(obs, e_sun)
        off = offset(np.tile(R, (turns.size, 1, 1)), np.tile(sun, (turns.size * len(R), 1)),
                     np.repeat(obs, len(R), 0)).reshape(turns.size, n_axes, K, 3)
        comp = np.stack([np.einsum("tmkj,tj->tmk", off, e_sun), np.einsum("tmkj,tj->tmk", off, e_cross)], -1)
        spin_mean = comp.mean(2)                                        # (turns, M, 2)
        out[5, i] = comp[..., 0].mean()
        bias = spin_mean - spin_mean.mean(1, keepdims=True)
        out[0, i], out[1, i] = np.sqrt(np.mean(bias ** 2, (0, 1)))
        out[2, i] = np.sqrt(np.mean(comp.var(2)))                       # mean of the two within-spin variances
        out[6, i], out[7, i] = np.sqrt(np.mean(comp.var(2), (0, 1)))
        for c in (0, 1):
            b = bias[..., c]                                            # (turns, M)
            var0 = np.sum(b * b)
            corr = np.array([np.sum(b * np.roll(b, -lag, 0)) / var0 if var0 > 0 else 1.0 for lag in range(half)])
            out[3 + c, i] = correlation_angle(turns[:half], corr)
    return PhotocentreStatistics(alpha, out[5], out[0], out[1], out[2], out[3:5].T.copy(), out[6], out[7])
