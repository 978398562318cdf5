"""Star tracking over an image sequence: predict, match in windows, solve, verify (issue 22, point 2).

A star tracker in tracking mode knows its last attitude and its rate, so it needs no pattern identification:

1. :func:`propagate` / :func:`predict`: the previous attitude ``A_prev`` (inertial -> camera, docs/architecture.md)
   turned by the rate over ``dt`` with the exact exponential map, ``A = exp(-[omega dt x]) A_prev``
   (``scene/rotation_vector.py``); its error covariance carried along, ``P = Phi P_prev Phi^T + dt^2 Q_omega``
   (first order; ``Phi`` the same rotation).  The brightest catalog stars that the predicted attitude puts in the
   image are projected with the camera model (``scene/camera.py``, distortion included); each predicted position
   has a 2 x 2 covariance ``G P G^T + sigma_c^2 I`` with ``G`` (P, 2, 3) the pixel derivatives with respect to a
   small attitude error (:func:`pixel_jacobian`: closed form for the pinhole, central differences through the camera
   model with distortion) and ``sigma_c`` the centroid noise.  The
   match window of a star is ``k`` times the largest principal sigma, clipped to [min, max] px.
2. :func:`match`: each predicted star takes the detection inside its window; a window holding two or more
   detections is ambiguous and dropped, and so is every star of a detection claimed by two windows (one
   detection per star, one star per detection).  A (P, D) distance table, no loop over stars.
3. :func:`track`: the attitude of the matched pairs by weighted least squares on their reprojection error,
   Gauss-Newton from the prediction (:func:`solve_reprojection`; the prediction's pixel Jacobians serve the first
   step, and within a window's pixels one step from the prediction usually meets the tolerance), each pair weighted
   by its 2 x 2 centroid covariance (:func:`centroid_whitening`: the detector's sigma, and a streak's variance along
   and across it when the caller knows the rate), with the attitude covariance scaled by the fit's a posteriori
   variance factor ``max(1, rms^2)``; the residual test (a star whose deleted residual, the residual a fit
   without it sees, :func:`deleted_residuals`, is beyond ``residual_k_sigma`` is dropped and the attitude solved
   again once; then the RMS per degree of freedom must stay
   below ``max_rms_sigma``) and the chance-match test (:func:`tracking_chance` over ``nav/chance.py``'s binomial
   tail).  Lock is lost by rule, one code of :data:`LOCK_REASONS`: too few matches (``min_stars``, or
   ``min_stars_tight`` when every window is tight), a degenerate geometry, the residual test, the chance-match
   probability.  The caller then falls back to lost-in-space (``nav/star_solution.py`` identify + solve).  A lock
   whose stated covariance has a principal 1-sigma above ``max_sigma_rad`` is flagged *degraded* (a two-star or
   short-baseline roll, smeared centroids): the caller withholds it (issue 22, point 6: no false lock).

This follows what tetra3rs 0.5.1 (MIT) describes for its tracking mode (previous attitude as a hint with an
uncertainty cone, nearest detections, SVD solve, the same false-match test, 3 stars instead of 4) with the cone
replaced by per-star windows from the propagated covariance and the SVD by a fit in pixels from the prediction; the
code is dualsight's own.  Angles in radians, pixels in the (col, row) convention of docs/architecture.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dualsight.nav.tracking_config import TrackingConfig
from dualsight.nav.chance import binomial_tail
from dualsight.scene.rotation_vector import frame_rotation
from dualsight.scene.starfield_geometry import field_half_angle

__all__ = ["LOCK_REASONS", "LOCKED", "NO_PRIOR", "TOO_FEW_MATCHES", "DEGENERATE", "RESIDUAL", "P_CHANCE", "DEGRADED",
           "Prediction", "TrackResult", "propagate", "pixel_jacobian", "predict", "match", "tracking_chance",
           "solve_pairs", "inverse_sym3", "centroid_whitening", "solve_reprojection", "deleted_residuals",
           "deleted_residual_bound", "max_sigma", "track"]

LOCK_REASONS = ("locked", "no_prior", "too_few_matches", "degenerate", "residual", "p_chance", "degraded")
"""Names of :attr:`TrackResult.reason` (index = code): lock held, or why it was lost; ``degraded`` is set by the
caller (``nav/sequence.py``) for a lock whose stated covariance is too wide to output (:attr:`TrackResult.degraded`)."""
LOCKED, NO_PRIOR, TOO_FEW_MATCHES, DEGENERATE, RESIDUAL, P_CHANCE, DEGRADED = range(len(LOCK_REASONS))

_EPS_ROT = 1e-6
"""Rotation step (rad) of the central differences of the pixel positions (truncation ~1e-12 px at 1e7 px focal
lengths' curvature, rounding ~1e-16 * 1e4 px / 1e-6 = 1e-6 px relative: far below any centroid error)."""


@dataclass(frozen=True)
class Prediction:
    """Where the catalog stars of a predicted attitude fall, and how sure that is.

    A : (3, 3) predicted attitude (inertial -> camera).  cov : (3, 3) rad^2 its error covariance (camera frame,
    the convention of ``nav.attitude.svd_attitude``).  rows : (P,) int64 catalog rows, brightest first.
    xy : (P, 2) float64 predicted pixel positions (col, row).  sigma_px : (P,) largest principal 1-sigma of each
    position (px), centroid noise included.  radius_px : (P,) match window radius (px).  G : (P, 2, 3) px/rad the
    pixel Jacobians at the predicted positions (:func:`pixel_jacobian`; what a caller needs for each star's image
    motion, ``G omega``, and for a least-squares step from ``A``), or None.
    """

    A: np.ndarray
    cov: np.ndarray
    rows: np.ndarray
    xy: np.ndarray
    sigma_px: np.ndarray
    radius_px: np.ndarray
    G: np.ndarray | None = None

    def take(self, keep: np.ndarray) -> "Prediction":
        """The prediction of the stars ``keep`` ((P,) bool or int index) only; A and cov unchanged."""
        return Prediction(self.A, self.cov, self.rows[keep], self.xy[keep], self.sigma_px[keep],
                          self.radius_px[keep], None if self.G is None else self.G[keep])


@dataclass(frozen=True)
class TrackResult:
    """One frame's tracking answer.

    A : (3, 3) attitude (NaN when not locked).  cov : (3, 3) rad^2 its error covariance (NaN when not locked).
    locked : bool.  reason : int code of :data:`LOCK_REASONS`.
    det_row : (D,) int64 catalog row of each detection used in the solution (-1 = unmatched, ambiguous or
        rejected).  residual_sigma : (D,) post-fit residual of each used detection in its centroid sigmas (the
        norm of its whitened 2-vector, :func:`solve_reprojection`; NaN otherwise).
    n_predicted, n_matched (unique pairs before the residual test), n_used (in the final solution),
    n_ambiguous (windows with two or more detections) : int.  two_star : the lock rests on two stars (allowed
    only under a tight prediction).  rms_sigma : post-fit RMS per degree of freedom in centroid sigmas.
    p_chance : chance-match probability (:func:`tracking_chance`).  degraded : locked, but the stated covariance
    (variance factor applied) has a principal 1-sigma above ``cfg.max_sigma_rad``: too weak to output.
    star, det : (n_used,) int64 the pairs of the final solution: index into the :class:`Prediction` and into the
    detections (empty when not locked).
    """

    A: np.ndarray
    cov: np.ndarray
    locked: bool
    reason: int
    det_row: np.ndarray
    residual_sigma: np.ndarray
    n_predicted: int
    n_matched: int
    n_used: int
    n_ambiguous: int
    two_star: bool
    rms_sigma: float
    p_chance: float
    degraded: bool = False
    star: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    det: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


def propagate(A_prev: np.ndarray, cov_prev: np.ndarray, omega: np.ndarray, cov_omega: np.ndarray,
              dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Attitude and covariance after ``dt`` s at the constant body rate ``omega``.

    A_prev : (3, 3) inertial -> camera.  cov_prev : (3, 3) rad^2 attitude error covariance (camera frame).
    omega : (3,) rad/s body rate in the camera frame (a solution's or a gyro's).  cov_omega : (3, 3) (rad/s)^2.
    Returns ``(exp(-[omega dt x]) A_prev, Phi cov_prev Phi^T + dt^2 cov_omega)`` (Markley & Crassidis 2014,
    Eq. 3.21 kinematics; the error of the rate enters as ``dt * delta_omega``).
    """
    dt = float(dt)
    Phi = frame_rotation(np.asarray(omega, np.float64) * dt)
    P = Phi @ cov_prev @ Phi.T + (dt * dt) * np.asarray(cov_omega, np.float64)
    return Phi @ A_prev, 0.5 * (P + P.T)


def pixel_jacobian(v: np.ndarray, camera) -> np.ndarray:
    """(P, 2, 3) d(pixel) / d(theta) of camera-frame vectors ``v`` (P, 3) under a small frame rotation theta
    (``v -> v - theta x v``).

    Without distortion, the pinhole's image Jacobian of a rotation in closed form (x = v_x / v_z, y = v_y / v_z):
    ``du/dtheta = fx (x y, -(1 + x^2), y)``, ``dv/dtheta = fy (1 + y^2, -x y, -x)`` (the rotational part of the
    interaction matrix, Chaumette & Hutchinson, "Visual servo control I", IEEE RAM 2006, Eq. 11, in this frame
    convention).  With distortion, central differences through ``camera.project``: the six perturbed copies of
    every star in one projection call.
    """
    if not camera.has_distortion:
        return _pinhole_jacobian(v[:, 0] / v[:, 2], v[:, 1] / v[:, 2], camera)
    x, y, z = v[:, 0] * _EPS_ROT, v[:, 1] * _EPS_ROT, v[:, 2] * _EPS_ROT
    d = np.zeros((3,) + v.shape)                     # d[i] = v x (eps e_i)
    d[0, :, 1], d[0, :, 2] = z, -y
    d[1, :, 0], d[1, :, 2] = -z, x
    d[2, :, 0], d[2, :, 1] = y, -x
    px = camera.project(np.concatenate([v[None] + d, v[None] - d]))[0]                       # (6, P, 2)
    return np.moveaxis((px[:3] - px[3:]) / (2 * _EPS_ROT), 0, -1)


def _pinhole_jacobian(x: np.ndarray, y: np.ndarray, camera) -> np.ndarray:
    """(P, 2, 3) :func:`pixel_jacobian` of the pinhole at normalised coordinates x, y (P,)."""
    G = np.empty((len(x), 2, 3))
    xy = x * y
    fx, fy = camera.fx, camera.fy
    G[:, 0, 0], G[:, 0, 1], G[:, 0, 2] = fx * xy, -fx * (1.0 + x * x), fx * y
    G[:, 1, 0], G[:, 1, 1], G[:, 1, 2] = fy * (1.0 + y * y), -fy * xy, -fy * x
    return G


def predict(A: np.ndarray, cov: np.ndarray, cat_unit: np.ndarray, camera, cfg: TrackingConfig,
            rows: np.ndarray | None = None, near: bool = False) -> Prediction:
    """The catalog stars that attitude ``A`` (already propagated, :func:`propagate`) puts in the image, their
    predicted pixels, uncertainties and match windows.

    A : (3, 3) inertial -> camera.  cov : (3, 3) rad^2 its error covariance.  cat_unit : (N, 3) ICRS unit
    vectors, brightest first (the stars a detector can see: the catalog's magnitude limit).  camera :
    ``scene.camera.Camera``.  rows : optional (N,) int64 the row of each ``cat_unit`` entry in a larger catalog (a
    subset near the boresight, ``nav/sequence.py``): the prediction's ``rows`` are then that catalog's.  near: the
    caller vouches that every row of ``cat_unit`` lies in front of the camera (less than 90 deg from the boresight,
    as a subset within the field's half-angle + a few degrees is), so the cone test is left out and the camera
    model alone decides what is in the image.  Keeps the ``cfg.max_predicted`` brightest stars inside the image.
    """
    A = np.asarray(A, np.float64)
    cos_half, lo, hi, f2, c2 = _camera_constants(camera)
    if near:                                  # every row in front of the camera (the caller's subset)
        cand, v = None, cat_unit @ A.T
    else:                                     # cone test, then the camera model
        cand = (cat_unit @ A[2] > cos_half).nonzero()[0]
        v = cat_unit[cand] @ A.T
    if camera.has_distortion:
        px, _ = camera.project(v)             # inside the cone (< 90 deg): z > 0, px finite
        keep = camera.in_image(px).nonzero()[0][: cfg.max_predicted]
        sel, v, px = (keep if cand is None else cand[keep]), v[keep], px[keep]
        G = pixel_jacobian(v, camera).reshape(-1, 3)                  # rows u0, v0, u1, v1, ...
    else:                                     # the pinhole (camera.project's formula) and its Jacobian in one pass
        xn = v[:, :2] / v[:, 2:]              # inside the image: lo <= xn < hi (px = f xn + c in [0, size))
        keep = ((xn >= lo) & (xn < hi)).all(axis=1).nonzero()[0][: cfg.max_predicted]
        sel, xn = (keep if cand is None else cand[keep]), xn[keep]
        px = xn * f2 + c2
        G = _pinhole_jacobian(xn[:, 0], xn[:, 1], camera).reshape(-1, 3)
    cov = np.asarray(cov, np.float64)
    GP = G @ cov
    ac = (GP * G).sum(axis=1)                                          # S = G P G^T: its diagonal (a, c) ...
    a, c = ac[0::2], ac[1::2]
    b = (GP[0::2] * G[1::2]).sum(axis=1)                               # ... and off-diagonal entry
    lam = 0.5 * (a + c) + np.hypot(0.5 * (a - c), b)                   # largest eigenvalue of the 2 x 2
    sigma = np.sqrt(lam + cfg.centroid_sigma_px ** 2)
    radius = np.minimum(np.maximum(cfg.window_k_sigma * sigma, cfg.window_min_px), cfg.window_max_px)
    return Prediction(A, cov, sel if rows is None else rows[sel], px, sigma, radius, G.reshape(-1, 2, 3))


_CAMERA: list = [None, None]
"""The last camera of :func:`_camera_constants` and its constants (a tracker keeps one camera; hashing the camera
for ``field_half_angle``'s memo costs more than the cone test)."""


def _camera_constants(camera) -> tuple:
    """(cosine of the image's cone half-angle, lo (2,), hi (2,) the image's normalised pinhole coordinates
    ``[-c / f, (size - c) / f)``, f (2,) = (fx, fy), c (2,) = (cx, cy)) of the last camera asked for."""
    if _CAMERA[0] is not camera:
        f2, c2 = np.array([camera.fx, camera.fy]), np.array([camera.cx, camera.cy])
        _CAMERA[0], _CAMERA[1] = camera, (math.cos(field_half_angle(camera)), -c2 / f2,
                                          (np.array([camera.width, camera.height]) - c2) / f2, f2, c2)
    return _CAMERA[1]


def match(pred_xy: np.ndarray, radius_px: np.ndarray, det_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Unique pairs (predicted star, detection) inside the windows.

    pred_xy : (P, 2) px.  radius_px : (P,) window radii (px).  det_xy : (D, 2) px (NaN rows never match).
    Returns (star (M,) int64 index into the predictions, det (M,) int64 index into the detections, the number of
    ambiguous windows).  A star pairs with the one detection inside its window (distance <= radius); a window
    with two or more detections is dropped (ambiguous: a double, a false star or a window too wide), and so are
    all the stars whose windows hold the same single detection.  Pairs in prediction order.
    """
    P, D = len(pred_xy), len(det_xy)
    if P == 0 or D == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), 0
    zp = np.ascontiguousarray(pred_xy, np.float64).view(np.complex128)     # (P, 1): x + i y, no copy
    zd = np.ascontiguousarray(det_xy, np.float64).view(np.complex128)      # (D, 1)
    inside = np.abs(zp - zd.T) <= np.asarray(radius_px, np.float64)[:, None]   # (P, D); NaN compares False
    n_in = inside.sum(axis=1)
    one = n_in == 1
    det = inside.argmax(axis=1)
    claims = np.bincount(det[one], minlength=D)
    star = (one & (claims[det] == 1)).nonzero()[0]
    return star, det[star], int((n_in >= 2).sum())


def tracking_chance(n_used: int, n_predicted: int, n_detections: int, radius_px: float, area_px: float) -> float:
    """Chance-match probability of a tracked answer: ``P[Binomial(P, q) >= n]`` with ``q = 1 - exp(-lambda pi r^2)``.

    Null hypothesis: the detections are unrelated to the predicted stars (a wrong prediction, a sky that
    moved away), spread uniformly over the image at ``lambda = D / area`` detections per px^2 (Poisson), so each of
    the ``P`` windows catches one with probability ``q``; ``r`` is the largest window (an upper bound).  One
    hypothesis is tested (the prediction), so no look-elsewhere factor, unlike lost-in-space's pair hypotheses
    (``nav/chance.py``).  The tail is summed term by term (ratio recurrence) for P <= 60, else by
    ``nav.chance.binomial_tail`` in log space.  Returns 1 when n <= 0, 0 when n > P.
    """
    if n_used <= 0:
        return 1.0
    if n_used > n_predicted:
        return 0.0
    lam = float(n_detections) / float(area_px)
    q = float(-np.expm1(-lam * np.pi * float(radius_px) ** 2))
    if q >= 1.0:
        return 1.0
    if q <= 0.0:
        return 0.0
    if n_predicted > 60:                        # long tails: nav/chance.py's log-space sum
        return float(binomial_tail(np.array([n_predicted]), np.array([n_used]), np.array([q]))[0])
    # short tails (the usual case, P <= max_predicted): the terms by their ratio, summed until they vanish
    m, k = int(n_predicted), int(n_used)
    term = math.comb(m, k) * q ** k * (1.0 - q) ** (m - k)
    total, r = term, q / (1.0 - q)
    for j in range(k, m):                       # at most P - n terms, each a few flops
        term *= (m - j) / (j + 1) * r
        total += term
        if term < 1e-17 * total:
            break
    return min(1.0, total)


def solve_pairs(b: np.ndarray, r: np.ndarray, w: np.ndarray):
    """Weighted SVD attitude of one frame's pairs (Markley 1988; the math of ``nav.attitude.svd_attitude`` for
    one case, without the batch's padding and checks, which cost more than the 3 x 3 factorisation on a tracked
    frame).  b, r : (M, 3) observed / catalog unit vectors; w : (M,) rad^-2.  Returns (A (3, 3), ok, cov (3, 3)
    rad^2): ``A = U diag(1, 1, d) V^T``, ``cov = U diag(1/(s2+s3), 1/(s3+s1), 1/(s1+s2)) U^T``, ``s3 = d S33``,
    ``d = det U det V``; ok when the second singular value exceeds 1e-10 times the first (two non-parallel
    stars)."""
    U, s, Vt = np.linalg.svd((b * w[:, None]).T @ r)
    (a0, a1, a2), (b0, b1, b2), (c0, c1, c2) = U.tolist()
    (e0, e1, e2), (f0, f1, f2), (g0, g1, g2) = Vt.tolist()
    d = ((a0 * (b1 * c2 - b2 * c1) - a1 * (b0 * c2 - b2 * c0) + a2 * (b0 * c1 - b1 * c0))
         * (e0 * (f1 * g2 - f2 * g1) - e1 * (f0 * g2 - f2 * g0) + e2 * (f0 * g1 - f1 * g0)))
    s1, s2, s3 = float(s[0]), float(s[1]), float(s[2]) * (1.0 if d > 0 else -1.0)
    if not (s1 > 0.0 and s2 > 1e-10 * s1):
        return None, False, None
    Ud = U.copy()
    if d < 0:
        Ud[:, 2] = -Ud[:, 2]
    return Ud @ Vt, True, (U * np.array([1.0 / (s2 + s3), 1.0 / (s3 + s1), 1.0 / (s1 + s2)])) @ U.T


def max_sigma(cov: np.ndarray) -> float:
    """Largest principal 1-sigma (rad) of a (3, 3) attitude error covariance (rad^2): the frame-free measure of
    :attr:`TrackingConfig.max_sigma_rad`'s rule (NaN -> NaN)."""
    (a, b, c), (_, d, e), (_, _, f) = np.asarray(cov, np.float64).tolist()
    if not all(map(math.isfinite, (a, b, c, d, e, f))):
        return float("nan")
    # the largest eigenvalue of a symmetric 3 x 3 in closed form (Smith, "Eigenvalues of a symmetric 3 x 3
    # matrix", Comm. ACM 4(4), 1961): m = tr / 3, B = (C - m I) / p, lambda = m + 2 p cos(acos(det B / 2) / 3)
    m = (a + d + f) / 3.0
    q = b * b + c * c + e * e
    p2 = ((a - m) ** 2 + (d - m) ** 2 + (f - m) ** 2 + 2.0 * q) / 6.0
    if p2 <= 0.0:
        return math.sqrt(max(0.0, m))
    p = math.sqrt(p2)
    a1, d1, f1 = (a - m) / p, (d - m) / p, (f - m) / p
    b1, c1, e1 = b / p, c / p, e / p
    h = 0.5 * (a1 * (d1 * f1 - e1 * e1) - b1 * (b1 * f1 - e1 * c1) + c1 * (b1 * e1 - d1 * c1))
    lam = m + 2.0 * p * math.cos(math.acos(min(1.0, max(-1.0, h))) / 3.0)
    return math.sqrt(max(0.0, lam))


def centroid_whitening(sigma_px: np.ndarray, u: np.ndarray | None = None, var_along: np.ndarray | None = None,
                       var_cross: np.ndarray | None = None, gain_along: np.ndarray | None = None) -> np.ndarray:
    """(M, 2, 2) ``L^T`` per centroid with ``L L^T = C^-1``, the inverse of its 2 x 2 covariance
    ``C = (sigma^2 (1 + gain_along) + var_along) u u^T + (sigma^2 + var_cross) n n^T`` (``n = (-u_y, u_x)``, across
    ``u``): rows ``u / sqrt(sigma^2 (1 + gain_along) + var_along)`` and ``n / sqrt(sigma^2 + var_cross)``.
    sigma_px : (M,) the detector's isotropic 1-sigma (px).  u : (M, 2) unit directions (a streak's); var_along,
    var_cross : (M,) px^2 added along and across it (var_cross None: nothing across); gain_along : optional (M,)
    the detector's variance's relative growth along it (a streak's profile is wider along it: ``nav/smear_weights.py``).  Without ``u``: ``I / sigma``
    (isotropic)."""
    M = len(sigma_px)
    L = np.zeros((M, 2, 2))
    if u is None:
        w = 1.0 / sigma_px
        L[:, 0, 0] = w
        L[:, 1, 1] = w
        return L
    s2 = sigma_px * sigma_px
    wa = (s2 + var_along if gain_along is None else s2 * (1.0 + gain_along) + var_along) ** -0.5
    wc = s2 ** -0.5 if var_cross is None else (s2 + var_cross) ** -0.5
    L[:, 0] = u * wa[:, None]
    L[:, 1, 0] = -u[:, 1] * wc
    L[:, 1, 1] = u[:, 0] * wc
    return L


def inverse_sym3(H: np.ndarray) -> np.ndarray | None:
    """Inverse of a symmetric positive (semi-)definite 3 x 3 by its cofactors (faster than ``np.linalg.inv`` on one
    3 x 3), or None when it is singular to 1e-14 of its diagonal's scale (the geometry of one star, or none)."""
    (a, b, c), (_, d, e), (_, _, f) = H.tolist()
    A_, B_, C_ = d * f - e * e, c * e - b * f, b * e - c * d
    det = a * A_ + b * B_ + c * C_
    scale = max(a, d, f)
    if not det > 1e-14 * scale * scale * scale:          # also NaN
        return None
    D_, E_, F_ = a * f - c * c, b * c - a * e, a * d - b * b
    return np.array([[A_, B_, C_], [B_, D_, E_], [C_, E_, F_]]) / det


def solve_reprojection(A: np.ndarray, r: np.ndarray, det_xy: np.ndarray, L: np.ndarray, camera,
                       G: np.ndarray | None = None, px: np.ndarray | None = None, max_iter: int = 5):
    """Weighted least-squares attitude on the reprojection error: Gauss-Newton from ``A`` (Hartley & Zisserman,
    "Multiple View Geometry", 2nd ed., Sec. A6.1), ``delta = (J^T J)^-1 J^T z`` with the whitened Jacobian
    ``J_i = L_i^T G_i`` and residuals ``z_i = L_i^T (x_det,i - x_pred,i)`` (``L_i L_i^T = C_i^-1``, the centroid's
    2 x 2 covariance: :func:`centroid_whitening`), ``A <- exp(-[delta x]) A``, until the step's second-order term
    ``f |delta|^2 / 2`` is below 1e-3 px; the normal matrix, the residuals and the covariance ``(J^T J)^-1``
    (rad^2) are those of the last linearisation, the residuals after its step ``z - J delta``.

    A : (3, 3) starting attitude (inertial -> camera), e.g. the prediction (within a match window's 50 px the first
    step leaves ~0.3 px; tracking's arcseconds, 1e-6 px).  r : (M, 3) catalog unit vectors.  det_xy : (M, 2) px.
    L : (M, 2, 2).  G : (M, 2, 3) px/rad and px : (M, 2) the pixel Jacobians and positions at ``r @ A.T`` when the
    caller has them (a :class:`Prediction`'s), else computed.  Returns (A, cov, e (M, 2) whitened residuals, ok);
    ok is False when ``J^T J`` is singular or the steps do not converge in ``max_iter``.
    """
    tol = math.sqrt(2e-3 / (0.5 * (camera.fx + camera.fy)))
    for _ in range(max_iter):
        if G is None or px is None:
            v = r @ A.T
            G = pixel_jacobian(v, camera)
            if camera.has_distortion:
                px, _ = camera.project(v)
            else:                                 # the pinhole (camera.project's formula)
                px = v[:, :2] / v[:, 2:] * (camera.fx, camera.fy) + (camera.cx, camera.cy)
        J = (L @ G).reshape(-1, 3)
        z = (L @ (det_xy - px)[:, :, None]).reshape(-1)
        cov = inverse_sym3(J.T @ J)
        if cov is None:
            return A, None, None, False
        delta = cov @ (z @ J)
        A = frame_rotation(delta) @ A
        step2 = float(delta @ delta)
        if step2 < tol * tol:
            return A, cov, (z - J @ delta).reshape(-1, 2), True
        if not math.isfinite(step2):
            return A, None, None, False
        G = None
    return A, None, None, False


def deleted_residuals(e: np.ndarray, J: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Each observation's residual as the fit *without* it would see it, in its own sigmas: (M,) ``sqrt(e_i^T (I -
    H_ii)^-1 e_i)``, ``H_ii = J_i cov J_i^T`` the 2 x 2 diagonal block of the hat matrix (the observation's
    leverage).

    e : (M, 2) whitened post-fit residuals, J : (M, 2, 3) whitened Jacobians (``L_i^T G_i``, rad -> sigmas), cov :
    (3, 3) ``(J^T J)^-1`` (:func:`solve_reprojection`).  The deleted residual ``d_i = z_i - J_i x_(i)`` of a fit
    without observation i is ``(I - H_ii)^-1 e_i`` with covariance ``(I - H_ii)^-1``, so the statistic is
    chi-square with 2 degrees of freedom for a correct observation (Belsley, Kuh & Welsch, "Regression
    Diagnostics", 1980, Sec. 2.1; Cook & Weisberg, "Residuals and Influence in Regression", 1982, Sec. 2.2).  A
    star with a small stated sigma pulls the fit towards itself and leaves a small post-fit residual however wrong
    it is; its deleted residual shows the error.  Where ``I - H_ii`` is singular to 1e-9 (a star the fit cannot do
    without: two stars) the post-fit norm ``|e_i|`` is returned.
    """
    Jf = J.reshape(-1, 3)
    JC = Jf @ cov                                                    # rows J_i0 cov, J_i1 cov, ...
    hd = (JC * Jf).sum(axis=1)                                       # H_ii's diagonal (h00, h11, h00, ...) ...
    a, d = 1.0 - hd[0::2], 1.0 - hd[1::2]                            # I - H_ii = [[a, b], [b, d]]
    b = -(JC[0::2] * Jf[1::2]).sum(axis=1)                           # ... and off-diagonal
    det = a * d - b * b
    e0, e1 = e[:, 0], e[:, 1]
    q = d * e0 * e0 - 2.0 * b * e0 * e1 + a * e1 * e1
    if det.min() > 1e-9:
        return np.sqrt(np.maximum(q / det, 0.0))
    ok = det > 1e-9
    q = np.where(ok, q / np.where(ok, det, 1.0), e0 * e0 + e1 * e1)
    return np.sqrt(np.maximum(q, 0.0))


def deleted_residual_bound(res_norm: np.ndarray, J: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """An upper bound (M,) of :func:`deleted_residuals` that costs a third of it: ``|e_i| / sqrt(1 - tr(H_ii))``
    (``|e_i| * 1e150`` where ``tr(H_ii) >= 1``, where the bound does not hold: above any threshold).

    res_norm : (M,) ``|e_i|``, the norms of the whitened post-fit residuals.  J : (M, 2, 3) whitened Jacobians.
    cov : (3, 3) ``(J^T J)^-1``.  ``e_i^T (I - H_ii)^-1 e_i <= |e_i|^2 / (1 - lambda_max(H_ii))`` and
    ``lambda_max(H_ii) <= tr(H_ii)`` (``H_ii = J_i cov J_i^T`` is positive semi-definite).  On a tracked frame the
    leverages are ~3 / M and the residuals ~1 sigma, so the bound clears the outlier threshold on almost every
    frame and :func:`track` computes the exact statistic only when it does not: the same decisions.
    """
    Jf = J.reshape(-1, 3)
    tr = ((Jf @ cov) * Jf).sum(axis=1).reshape(-1, 2).sum(axis=1)
    return res_norm / np.sqrt(np.maximum(1.0 - tr, 1e-300))       # tr >= 1: |e_i| * 1e150, beyond any threshold


def _outlier_statistic(e: np.ndarray, res_norm: np.ndarray, J: np.ndarray, cov: np.ndarray,
                       k_sigma: float) -> tuple[np.ndarray, bool]:
    """(M,) the statistic :func:`track`'s outlier test compares with ``k_sigma``, and whether every pair is within it:
    :func:`deleted_residual_bound` when its largest value is within ``k_sigma`` (then so is every deleted
    residual), else :func:`deleted_residuals`.  Three pairs or more; e, J, cov as there."""
    bound = deleted_residual_bound(res_norm, J, cov)
    if bound.max() <= k_sigma:
        return bound, True
    exact = deleted_residuals(e, J, cov)
    return exact, bool(exact.max() <= k_sigma)


def track(pred: Prediction, det_xy: np.ndarray, det_sigma_px: np.ndarray | None, cat_unit: np.ndarray, camera,
          cfg: TrackingConfig, streak: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> TrackResult:
    """Match one frame's detections to a :class:`Prediction`, solve and verify (module docstring, steps 2-3).

    det_xy : (D, 2) centroids (px).  det_sigma_px : optional (D,) 1-sigma centroid error per axis (px), e.g. the
    local detector's Cramér-Rao bound; None (or non-finite entries) = ``cfg.centroid_sigma_px``.  streak :
    optional ``(u (P, 2), var_along (P,), var_cross (P,)[, gain_along (P,)])`` per predicted star: what the
    detector's sigma leaves out and the prediction knows, the variance (px^2) added along the star's image motion
    ``u`` and across it, and the relative growth of the detector's variance along it (a streak's:
    ``nav/sequence.py``, ``nav/smear_weights.py``; :func:`centroid_whitening`).  The attitude is the weighted least-squares fit of
    the reprojection error from the prediction (:func:`solve_reprojection`, each pair weighted by the inverse of
    its 2 x 2 centroid covariance, :func:`centroid_whitening`), so its covariance is in rad^2; it is then
    multiplied by the a posteriori variance factor ``max(1, rms^2)`` (``rms``: the post-fit residuals' RMS per
    degree of freedom in their sigmas; a centroid error larger than stated widens the stated covariance instead of
    leaving it optimistic; Bevington & Robinson, "Data Reduction and Error Analysis", 3rd ed., Sec. 7.2).  A pair
    whose deleted residual (:func:`deleted_residuals`: its whitened residual against the fit without it; a bright
    star's post-fit residual hides its error) exceeds ``cfg.residual_k_sigma`` is dropped and the attitude solved
    again once; with fewer than 3 pairs the post-fit residual is tested.
    A verified answer whose largest principal 1-sigma exceeds ``cfg.max_sigma_rad`` is *degraded*
    (``TrackResult.degraded``; e.g. a two-star or short-baseline solution's roll): the caller does not output it.
    cat_unit : (N, 3) the catalog ``pred.rows`` index.  camera : ``scene.camera.Camera``.
    """
    det_xy = np.asarray(det_xy, np.float64).reshape(-1, 2)
    D = det_xy.shape[0]
    det_row = np.full(D, -1, np.int64)
    res_sigma = np.full(D, np.nan)
    P = len(pred.rows)
    star, det, n_amb = match(pred.xy, pred.radius_px, det_xy)
    n_matched = len(star)
    r_max = float(pred.radius_px.max()) if P else 0.0
    tight = P > 0 and r_max <= cfg.tight_window_px
    need = cfg.min_stars_tight if tight else cfg.min_stars

    def lost(reason, n_used=0, rms=np.nan, p=np.nan):
        nan3 = np.full((3, 3), np.nan)
        return TrackResult(nan3, nan3.copy(), False, reason, det_row, res_sigma, P, n_matched, n_used, n_amb,
                           n_used == 2, float(rms), float(p), False)

    if n_matched < need:
        return lost(TOO_FEW_MATCHES, n_matched)
    if det_sigma_px is None:
        sig = np.full(n_matched, cfg.centroid_sigma_px)
    else:
        sig = np.asarray(det_sigma_px, np.float64)[det]
        if not (sig.min() > 0 and sig.max() < math.inf):        # NaN fails both
            sig = np.where(np.isfinite(sig) & (sig > 0), sig, cfg.centroid_sigma_px)
    L = (centroid_whitening(sig) if streak is None
         else centroid_whitening(sig, streak[0][star], streak[1][star],
                                 None if streak[2] is None else streak[2][star],
                                 streak[3][star] if len(streak) > 3 else None))
    r = cat_unit[pred.rows[star]]
    xy = det_xy[det]
    G = None if pred.G is None else pred.G[star]
    if G is None:
        G = pixel_jacobian(r @ pred.A.T, camera)
    A, cov, e, ok = solve_reprojection(pred.A, r, xy, L, camera, G, pred.xy[star])
    if not ok:
        return lost(DEGENERATE, n_matched)
    nres = np.sqrt((e * e).sum(axis=1))
    k = cfg.residual_k_sigma
    if n_matched >= 3:                                  # the outlier test: deleted residuals, their bound first
        stat, within = _outlier_statistic(e, nres, L @ G, cov, k)
    else:
        stat, within = nres, bool(nres.max() <= k)
    use = None if within else stat <= k                 # None: every pair within residual_k_sigma
    n_used = n_matched if use is None else int(use.sum())
    if n_used < n_matched:                              # drop the outliers, solve once more
        if n_used < need:
            return lost(RESIDUAL, n_used)
        det, star, r, xy, L, G = det[use], star[use], r[use], xy[use], L[use], G[use]
        A, cov, e, ok = solve_reprojection(A, r, xy, L, camera)
        if not ok:
            return lost(DEGENERATE, n_used)
        nres = np.sqrt((e * e).sum(axis=1))
        worst = float((_outlier_statistic(e, nres, L @ G, cov, k)[0] if n_used >= 3 else nres).max())
    else:                                               # every residual already within residual_k_sigma
        worst = 0.0
    dof = max(1, 2 * n_used - 3)
    rms = math.sqrt(float(nres @ nres) / dof)
    p = tracking_chance(n_used, P, D, r_max, camera.width * camera.height)
    if rms > cfg.max_rms_sigma or worst > cfg.residual_k_sigma:
        return lost(RESIDUAL, n_used, rms, p)
    if p > cfg.max_p_chance:
        return lost(P_CHANCE, n_used, rms, p)
    if rms > 1.0:
        cov = cov * (rms * rms)
    det_row[det] = pred.rows[star]
    res_sigma[det] = nres
    # degraded: the largest principal sigma beyond max_sigma_rad; the trace bounds the largest eigenvalue, so the
    # exact one is needed only when the trace exceeds the limit (a tracked frame's is far below it)
    lim2 = cfg.max_sigma_rad * cfg.max_sigma_rad
    degraded = not cov[0, 0] + cov[1, 1] + cov[2, 2] <= lim2 and max_sigma(cov) > cfg.max_sigma_rad
    return TrackResult(A, cov, True, LOCKED, det_row, res_sigma, P, n_matched, n_used, n_amb, n_used == 2, rms, p,
                       degraded, star, det)
