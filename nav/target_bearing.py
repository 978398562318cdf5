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

from typing import NamedTuple

import numpy as np

__all__ = ["line_of_sight", "los_jacobian", "attitude_covariance", "inertial_bearing", "centroid_cov_icrs",
           "sphere_phase_correction",
           "bearing_error", "bearing_nees", "skew", "BLOB_SIGMA_FRAC_POINT", "BLOB_SIGMA_FRAC_RESOLVED",
           "BLOB_SIGMA_FRAC_BY_DETECTOR", "blob_centroid_sigma", "offset_correction", "PointCentroidTable",
           "point_centroid_table", "point_centroid_sigma"]

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


def centroid_cov_icrs(A: np.ndarray, xy: np.ndarray, cov_px: np.ndarray, camera) -> np.ndarray:
    """(B, 3, 3) rad^2 ICRS covariance of the line of sight (rank 2, across it) from a centroid covariance ``cov_px``
    (B, 2, 2) px^2 in (col, row) at pixels ``xy`` (B, 2), attitude A (B, 3, 3) inertial -> camera: A^T J C J^T A
    with J = :func:`los_jacobian` (the centroid term of :func:`inertial_bearing`, for a covariance that is not the
    same on both axes)."""
    J = los_jacobian(xy, camera)
    At = np.swapaxes(A, -1, -2)
    return At @ (J @ np.asarray(cov_px, np.float64) @ np.swapaxes(J, -1, -2)) @ A


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


class PointCentroidTable(NamedTuple):
    """The detector's centroid error of a point source against its measured flux (:func:`point_centroid_table`):
    ``log_flux`` (L,) increasing natural log of the median measured flux per level (the detector's units, ADU),
    ``sigma_px`` (L,) the RMS error per axis (px) at that level, ``n`` (L,) samples (2 axes x renders)."""

    log_flux: np.ndarray
    sigma_px: np.ndarray
    n: np.ndarray


def point_centroid_table(level: np.ndarray, flux: np.ndarray, err_xy: np.ndarray) -> PointCentroidTable:
    """The RMS centroid error per axis of a point source per brightness level, from a Monte Carlo of the camera's
    own render and detector (the caller renders one point source per frame at a uniform random sub-pixel
    position, with the sensor's noise if it has any).

    level : (K,) int the brightness level of each render (its electrons); flux : (K,) measured flux (ADU: the
    detector's ``flux``, what the flight software has for the target); err_xy : (K, 2) detected minus true
    position (px), NaN where nothing was detected (left out).  Levels are ordered by their median measured flux;
    the RMS pools both axes (the pixel grid's error is the same along x and y), so each level's sigma has a
    relative 1-sigma scatter of about 1 / sqrt(2 n) from the draw.

    Why a table and not a formula: a noise-free star-camera frame has no Cramer-Rao scatter; a point source's
    intensity-weighted centroid errs by the pixel-phase bias of its sampled profile (the "S-curve", Rufino &
    Accardo, Acta Astronautica 53, 2003), and once the peak saturates the flat plateau's edges cross pixel
    boundaries at flux-dependent places, so the error's RMS over phases oscillates with the flux (0.002 px
    unsaturated, 0.02-0.05 px saturated for the paper sensor).  The phase is unknown but uniform, the flux is
    measured: the RMS at the measured flux is the error's standard deviation given what is known."""
    level = np.asarray(level, np.int64)
    flux = np.asarray(flux, np.float64)
    e = np.asarray(err_xy, np.float64)
    ok = np.isfinite(flux) & (flux > 0) & np.all(np.isfinite(e), axis=1)
    lv, inv = np.unique(level[ok], return_inverse=True)
    L = len(lv)
    cnt = np.bincount(inv, minlength=L)
    ss = np.bincount(inv, weights=np.sum(e[ok] ** 2, axis=1), minlength=L)
    order = np.lexsort((np.log(flux[ok]), inv))
    lf = np.log(flux[ok])[order]
    starts = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    med = lf[starts + (cnt - 1) // 2]                        # lower median of each level's log flux
    o = np.argsort(med, kind="stable")
    return PointCentroidTable(med[o], np.sqrt(ss / (2 * cnt))[o], 2 * cnt[o])


def point_centroid_sigma(flux, table: PointCentroidTable) -> np.ndarray:
    """(B,) 1-sigma centroid error per axis (px) of point sources of measured ``flux`` (B,) (ADU), linearly
    interpolated in log flux in :func:`point_centroid_table`'s table (its end values beyond its range; NaN for
    a non-positive flux)."""
    f = np.asarray(flux, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        lf = np.where(f > 0, np.log(np.where(f > 0, f, 1.0)), np.nan)
    return np.where(np.isfinite(lf), np.interp(lf, table.log_flux, table.sigma_px), np.nan)


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
