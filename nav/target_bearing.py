"""The target's inertial line of sight from the star camera's own frame (issue 23, point 3).

    centre of brightness (px) -> camera-frame line of sight (camera model, distortion removed)
        -> ICRS through the star attitude:  u_I = A^T u_c

with its covariance from the centroid and the attitude.  With the attitude convention of ``nav/attitude.py``
(``A_true ~ (I + [dtheta x]) A``, dtheta the small error rotation in the camera frame with covariance P) and a
centroid error dp (px) with covariance sigma_px^2 I, the bearing error is, to first order,

    du_I = A^T (J dp - [u_c x] dtheta),     cov = A^T (sigma_px^2 J J^T + [u_c x] P [u_c x]^T) A

with J = d u_c / d(x, y) the (3, 2) derivative of the back-projection (central differences through the camera
model).  The attitude's P is the SVD solution's (Markley 1988, ``nav/attitude.svd_attitude``) for unit weights,
scaled by the a-posteriori variance of the star residuals (:func:`attitude_covariance`).

Phase angle: a lit body's centre of brightness is not its centre.  For a Lambertian sphere of radius R at range d
the offset is ``delta(alpha)`` of ``scene/target_photometry.sphere_photocentre_offset`` towards the Sun in the plane
of the sky (Basilisk corrects its heading the same way); :func:`sphere_phase_correction` moves the line of sight
back by delta / d away from the Sun.

Centroid sigma of the target's blob (:func:`blob_centroid_sigma`): the point-source centroid sigma (the detector's
Cramer-Rao bound, or the stars' a-posteriori scatter) describes a faint, unsaturated star.  The target is neither: a
point-like target at 1-10 km is brighter than any star and saturates, so its profile is flattened and its
intensity-weighted centroid or PSF fit moves with the plateau's pixel sampling; a resolved one is partly lit and
saturated, so its blob's centroid is pulled from the photometric centre of brightness towards the centroid of its
lit silhouette (for a lit sphere at 90 deg phase the two are (3 pi/16) R = 0.589 R and 4 R / (3 pi) = 0.424 R from
its centre: 0.165 R apart, 0.33 of the lit half-disc's RMS radius R / 2).  Both errors scale with the blob's size, so the blob adds ``k r_rms`` per axis, r_rms =
sqrt(npix / (2 pi)) the RMS radius of a uniform disc of the blob's npix pixels, with k :data:`BLOB_SIGMA_FRAC_POINT`
for a blob a star could make and :data:`BLOB_SIGMA_FRAC_RESOLVED` for one larger than any star
(``nav/resolved_blobs.star_blob_limit``), those of the local detector (PSF fit); the global detector's
intensity-weighted centroid follows a flattened blob better and takes smaller ones
(:data:`BLOB_SIGMA_FRAC_BY_DETECTOR`).  The fractions are empirical: chosen on the star job's seed-1 runs of the
paper preset (global detector, no noise) and the realistic one (local detector, noise) with a 3U CubeSat at
100 m - 10 km and phase 0-90 deg, as about the smallest that put >= 99.73 % of the 2-dof NEES under 11.83, and
checked on seed 2 (``benchmarks/bench_target_bearing_cov.py``).  The errors they cover are systematic for a given
geometry (heavy-tailed), so the mean NEES stays well under 2 where the 99.73 % point is met.

Units: radians, pixels; vectors (..., 3).  Pure numpy (flight algorithm: no storage, no drawing).
"""

from __future__ import annotations

import numpy as np

__all__ = ["line_of_sight", "los_jacobian", "attitude_covariance", "inertial_bearing", "sphere_phase_correction",
           "bearing_error", "bearing_nees", "skew", "BLOB_SIGMA_FRAC_POINT", "BLOB_SIGMA_FRAC_RESOLVED",
           "BLOB_SIGMA_FRAC_BY_DETECTOR", "blob_centroid_sigma", "offset_correction"]

BLOB_SIGMA_FRAC_POINT = 0.02
"""1-sigma centroid error per axis of a target blob a star could make, in units of its RMS radius (module doc)."""
BLOB_SIGMA_FRAC_RESOLVED = 0.25
"""1-sigma centroid error per axis of a target blob larger than any star, in units of its RMS radius (module doc)."""
BLOB_SIGMA_FRAC_BY_DETECTOR = {"global": (0.012, 0.12), "local": (BLOB_SIGMA_FRAC_POINT, BLOB_SIGMA_FRAC_RESOLVED)}
"""(point, resolved) fractions per star detector: the global threshold's intensity-weighted centroid follows a
flattened blob more closely than the local detector's PSF fit, which assumes a star's profile (module doc)."""


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3, 3) cross-product matrices [v x] of (..., 3) vectors."""
    v = np.asarray(v, np.float64)
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1), np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def line_of_sight(xy: np.ndarray, camera) -> np.ndarray:
    """(..., 3) camera-frame unit vectors of (..., 2) pixel positions (col, row) (``camera.backproject``)."""
    return camera.backproject(np.asarray(xy, np.float64))


def los_jacobian(xy: np.ndarray, camera, h_px: float = 0.25) -> np.ndarray:
    """(..., 3, 2) derivative of the line of sight with respect to (x, y) in rad per px (central differences of
    ``camera.backproject`` over +-``h_px``: exact for the pinhole to O(h^2), distortion included)."""
    xy = np.asarray(xy, np.float64)
    dx, dy = np.array([h_px, 0.0]), np.array([0.0, h_px])
    jx = (camera.backproject(xy + dx) - camera.backproject(xy - dx)) / (2 * h_px)
    jy = (camera.backproject(xy + dy) - camera.backproject(xy - dy)) / (2 * h_px)
    return np.stack([jx, jy], -1)


def attitude_covariance(cov_unit: np.ndarray, residual_rad: np.ndarray, n_used: np.ndarray,
                        floor_rad: float = 0.0) -> np.ndarray:
    """(B, 3, 3) attitude error covariance (rad^2, camera frame): the unit-weight SVD covariance ``cov_unit``
    (``svd_attitude(..., weights=1, return_cov=True)``) times the a-posteriori variance per axis of the star
    residuals, ``sigma^2 = max(sum r^2 / max(2 n - 3, 1), floor_rad^2)`` (n stars, 2 n measurements, 3 unknowns;
    ``residual_rad`` (B, S) angles, NaN where unused)."""
    r2 = np.nansum(np.asarray(residual_rad, np.float64) ** 2, axis=1)
    dof = np.maximum(2 * np.asarray(n_used) - 3, 1)
    s2 = np.maximum(r2 / dof, floor_rad ** 2)
    return np.asarray(cov_unit, np.float64) * s2[:, None, None]


def inertial_bearing(A: np.ndarray, att_cov: np.ndarray, xy: np.ndarray, sigma_px, camera):
    """The target's ICRS line of sight and its covariance.

    A : (B, 3, 3) attitude (inertial -> camera); att_cov : (B, 3, 3) rad^2 its error covariance (camera frame,
    ``A_true ~ (I + [dtheta x]) A``); xy : (B, 2) centre of brightness (px); sigma_px : scalar or (B,) centroid
    1-sigma per axis (px).  Returns u (B, 3) ICRS unit vectors and cov (B, 3, 3) rad^2 (rank 2: across u)."""
    u_c = line_of_sight(xy, camera)
    J = los_jacobian(xy, camera)
    s2 = np.broadcast_to(np.asarray(sigma_px, np.float64) ** 2, u_c.shape[:-1])
    K = skew(u_c)
    c_cam = s2[:, None, None] * (J @ np.swapaxes(J, -1, -2)) + K @ att_cov @ np.swapaxes(K, -1, -2)
    At = np.swapaxes(A, -1, -2)
    return np.einsum("bij,bj->bi", At, u_c), At @ c_cam @ A


def sphere_phase_correction(u: np.ndarray, sun: np.ndarray, offset_m, range_m) -> np.ndarray:
    """The line of sight to a sphere's centre from the one to its centre of brightness: ``u`` (B, 3) moved by
    ``offset_m / range_m`` rad away from the Sun's direction ``sun`` (B, 3) projected across ``u``
    (``offset_m``: ``scene/target_photometry.sphere_photocentre_offset(R, alpha)``).  Unit vectors out."""
    u = np.asarray(u, np.float64)
    s = np.asarray(sun, np.float64)
    s_perp = s - np.einsum("bk,bk->b", s, u)[:, None] * u
    n = np.linalg.norm(s_perp, axis=-1, keepdims=True)
    s_perp = np.divide(s_perp, n, out=np.zeros_like(s_perp), where=n > 0)
    ang = np.asarray(offset_m, np.float64) / np.asarray(range_m, np.float64)
    v = np.cos(ang)[..., None] * u - np.sin(ang)[..., None] * s_perp
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def blob_centroid_sigma(npix, sigma_px, resolved, frac_point: float = BLOB_SIGMA_FRAC_POINT,
                        frac_resolved: float = BLOB_SIGMA_FRAC_RESOLVED) -> np.ndarray:
    """(B,) 1-sigma centroid error per axis (px) of the target's blob: ``sqrt(sigma_px^2 + (k r_rms)^2)``.

    npix : (B,) pixels of the blob; sigma_px : scalar or (B,) the point-source centroid sigma (detector's bound or
    the stars' scatter, px); resolved : (B,) bool, the blob is larger than any star could make (then k is
    ``frac_resolved``, else ``frac_point``); r_rms = sqrt(npix / (2 pi)) px (module doc)."""
    r_rms = np.sqrt(np.asarray(npix, np.float64) / (2.0 * np.pi))
    k = np.where(np.asarray(resolved, bool), frac_resolved, frac_point)
    return np.hypot(np.asarray(sigma_px, np.float64), k * r_rms)


def offset_correction(u: np.ndarray, offset: np.ndarray, range_m) -> np.ndarray:
    """The line of sight to a target's body origin from the one to its centre of brightness: (B, 3) unit vectors
    ``u - offset_perp / range_m`` normalised, with ``offset`` (B, 3) m the centre of brightness minus the body
    origin (same frame as ``u``; e.g. ``scene/target_photometry.photocentre_offset`` for a known attitude) and
    ``offset_perp`` its part across ``u`` (the part along u does not move the image).  Small-angle exact to
    O((|offset| / range)^2)."""
    u = np.asarray(u, np.float64)
    o = np.asarray(offset, np.float64)
    o_perp = o - np.einsum("bk,bk->b", o, u)[:, None] * u
    v = u - o_perp / np.asarray(range_m, np.float64).reshape(-1, 1)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def bearing_error(u_est: np.ndarray, u_true: np.ndarray) -> np.ndarray:
    """(B,) angle (rad) between estimated and true lines of sight (atan2 of the cross and dot products)."""
    a, b = np.asarray(u_est, np.float64), np.asarray(u_true, np.float64)
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.einsum("bk,bk->b", a, b))


def bearing_nees(u_est: np.ndarray, u_true: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(B,) normalised squared error e^T C^-1 e in the plane across ``u_est`` (2 degrees of freedom: chi-square
    with 2 dof, 99.73 % below 11.83 when the covariance holds); e = u_true - u_est projected on that plane."""
    u = np.asarray(u_est, np.float64)
    ref = np.where(np.abs(u[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = np.cross(u, ref)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = np.cross(u, e1)
    E = np.stack([e1, e2], -2)                                   # (B, 2, 3)
    e = np.einsum("bij,bj->bi", E, np.asarray(u_true, np.float64) - u)
    C = E @ cov @ np.swapaxes(E, -1, -2)
    with np.errstate(invalid="ignore"):
        return np.einsum("bi,bi->b", e, np.linalg.solve(C, e[..., None])[..., 0])
