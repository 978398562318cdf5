"""Attitude error metrics of the reference (Eqs. 4-7) and the star-case status, batched over cases.

Reference, Sec. 3.3, Eqs. 4-7::

    Theta = R_calc^-1 R_actual = [[ ~1, -phi_z,  phi_y],
                                  [ phi_z,  ~1, -phi_x],
                                  [-phi_y, phi_x,   ~1]]
    eps_i = 90 deg - acos(phi_i),   i = x, y, z

and a case fails when any |eps_i| exceeds 100 arcsec.  Here ``R`` is the project's attitude matrix
``A`` (inertial -> camera, docs/architecture.md), so ``Theta = A_est^T A_true`` and ``A_true = A_est Theta``.

Sign: ``Theta ~ I + [phi x]`` is the *active* rotation by the small vector ``phi`` (right-hand rule);
``eps_i = asin(phi_i)`` (identical to ``90 deg - acos(phi_i)``) is positive when Theta rotates
positively about axis i.  For example ``A_est = A_true @ R_1(+a)`` (the passive ``rot_axis(1, a)`` of
``dualsight.scene.attitude``), i.e. ``Theta`` the active rotation by +a about x, gives ``eps_x = +a``.

Frame: with ``Theta = A_est^T A_true`` the rotation acts on inertial coordinates, so the three axes
are the ICRS axes (``frame="inertial"``, the literal Eq. 4 in this project's convention).
``frame="camera"`` evaluates the same equations on ``Theta_c = A_true A_est^T = A_est Theta A_est^T``,
the same rotation with its axis expressed in the camera frame (x, y across the boresight,
z = roll about the boresight).  The reference does not state its frame convention; its Table 5 has
the largest error on x, which is what camera-frame errors give when the camera's boresight is x.

Caveat: Eq. 4 keeps only the antisymmetric first-order terms, so a large error can look small;
a 180-degree rotation about any axis has ``phi = 0`` on all three axes.  :func:`classify` therefore
also checks the total rotation angle of Theta (:func:`total_error_angle`).
"""

from __future__ import annotations

import numpy as np

from dualsight.scene.units import ARCSEC

__all__ = ["error_matrix", "axis_errors", "total_error_angle", "classify",
           "SUCCESS", "NO_SOLUTION", "CONFIDENT_WRONG", "STATUS_NAMES"]

SUCCESS, NO_SOLUTION, CONFIDENT_WRONG = 0, 1, 2
STATUS_NAMES = ("success", "no_solution", "confident_wrong")
"""Names of the status codes returned by :func:`classify` (index = code)."""


def error_matrix(A_est: np.ndarray, A_true: np.ndarray, frame: str = "inertial") -> np.ndarray:
    """Error rotation Theta (reference Eq. 4).

    Parameters
    ----------
    A_est, A_true : (B, 3, 3) inertial -> camera attitude matrices (estimated, true).
    frame : "inertial" -> ``A_est^T A_true`` (literal Eq. 4, axes = ICRS axes);
        "camera" -> ``A_true A_est^T`` (same rotation, axes = camera axes).

    Returns
    -------
    (B, 3, 3) Theta.
    """
    Ae = np.asarray(A_est, dtype=np.float64)
    At = np.asarray(A_true, dtype=np.float64)
    if frame == "inertial":
        return np.swapaxes(Ae, -1, -2) @ At
    if frame == "camera":
        return At @ np.swapaxes(Ae, -1, -2)
    raise ValueError(f"frame must be 'inertial' or 'camera', got {frame!r}")


def axis_errors(A_est: np.ndarray, A_true: np.ndarray, frame: str = "inertial") -> np.ndarray:
    """Signed per-axis errors eps_x, eps_y, eps_z (reference Eqs. 4-7).

    ``phi_x = Theta[2, 1]``, ``phi_y = Theta[0, 2]``, ``phi_z = Theta[1, 0]`` and
    ``eps_i = 90 deg - acos(phi_i) = asin(phi_i)`` (see the module docstring for sign and frame).

    Parameters
    ----------
    A_est, A_true : (B, 3, 3) inertial -> camera attitude matrices; NaN estimates give NaN errors.
    frame : "inertial" (default, literal Eq. 4) or "camera".

    Returns
    -------
    (B, 3) float64 signed errors in radians (multiply by 1/ARCSEC for arcseconds).
    """
    T = error_matrix(A_est, A_true, frame)
    phi = np.stack([T[..., 2, 1], T[..., 0, 2], T[..., 1, 0]], axis=-1)
    return np.arcsin(np.clip(phi, -1.0, 1.0))


def total_error_angle(A_est: np.ndarray, A_true: np.ndarray) -> np.ndarray:
    """Rotation angle of Theta (the same in either frame), in [0, pi] radians, shape (B,).

    ``angle = atan2(|vee(Theta - Theta^T)| / 2, (trace(Theta) - 1) / 2)`` (Euler's rotation theorem;
    the atan2 form stays accurate for small angles where acos of the trace loses precision).
    """
    T = error_matrix(A_est, A_true, "inertial")
    v = np.stack([T[..., 2, 1] - T[..., 1, 2], T[..., 0, 2] - T[..., 2, 0], T[..., 1, 0] - T[..., 0, 1]], axis=-1)
    return np.arctan2(0.5 * np.linalg.norm(v, axis=-1), 0.5 * (np.trace(T, axis1=-2, axis2=-1) - 1.0))


def classify(axis_err: np.ndarray, total_angle: np.ndarray, T: np.ndarray,
             limit_arcsec: float = 100.0) -> np.ndarray:
    """Status of each star case: success, no solution, or confident but wrong (reference Sec. 3.3).

    A case succeeds when every ``|eps_i| <= limit`` **and** the total error angle is consistent with
    that, ``total_angle <= sqrt(3) * limit`` (all three small-angle errors at the limit; this catches
    the large rotations, e.g. 180 degrees, for which Eq. 4 gives phi ~ 0).  NaN errors (no attitude)
    fail.  A failed case is "no_solution" when the match threshold ``T <= 0`` and "confident_wrong"
    when ``T > 0``.  As in the reference, success does not itself require ``T > 0``.

    Parameters
    ----------
    axis_err : (B, 3) signed per-axis errors (rad), from :func:`axis_errors`.
    total_angle : (B,) total error angle (rad), from :func:`total_error_angle`.
    T : (B,) match threshold (verification votes) of each case.
    limit_arcsec : per-axis limit in arcseconds (reference: 100).

    Returns
    -------
    (B,) int8 codes: SUCCESS = 0, NO_SOLUTION = 1, CONFIDENT_WRONG = 2 (names in ``STATUS_NAMES``).
    """
    e = np.asarray(axis_err, dtype=np.float64)
    ang = np.asarray(total_angle, dtype=np.float64)
    lim = float(limit_arcsec) * ARCSEC
    with np.errstate(invalid="ignore"):
        ok = np.all(np.abs(e) <= lim, axis=-1) & (ang <= np.sqrt(3.0) * lim)   # NaN compares False
    conf = np.asarray(T) > 0
    return np.where(ok, SUCCESS, np.where(conf, CONFIDENT_WRONG, NO_SOLUTION)).astype(np.int8)
