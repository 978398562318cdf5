"""Finding the target in a sequence of star-camera frames without the truth (issue 23, point 3).

AVANTI (DLR, 2016) recognised its target as the point that moves against the stars over a sequence.  Here:

1. **Unmatched detections** (:func:`unmatched`): after the frame's attitude solve, every detection's line of sight
   is turned into ICRS (``u_icrs = A^T v_cam``, A the ICRS -> camera attitude) and compared with the catalog stars
   near the boresight; a detection within ``match_tol_rad`` of a catalog star is that star.
2. **Fixed objects** (:func:`repeats`): among the unmatched ones, a detection whose ICRS direction recurs within
   ``icrs_tol_rad`` in at least ``min_frames - 1`` other frames is fixed on the sky (an uncatalogued star, a
   planet over a short sequence); one whose pixel position recurs within ``pixel_tol_px`` in as many other frames
   is fixed on the detector (a hot pixel, a ghost).  Neither is the target, which moves against the stars (the
   chaser's line of sight to it turns with the orbit) and, pointed at with an error drawn per frame, does not sit
   on one pixel either.  A single repeat can be chance; ``min_frames`` = 3 asks for two.
3. **The filter's gate** (:func:`predicted_bearing`, :func:`innovation_d2`, :func:`pick`): of the remaining
   candidates of a frame, the one nearest the filter's predicted line of sight in the metric of the innovation
   covariance ``S = E (J P J^T + C) E^T`` (2 x 2 in the tangent plane of the prediction; J the Jacobian of the
   line of sight, C the candidate's own covariance) is the target, if its squared Mahalanobis distance is inside
   the chi-square(2) gate (``gate_d2``; Bar-Shalom, Li & Kirubarajan 2001, Sec. 5.4.2 / 8.2.2 "validation
   gate").  Outside the gate the frame has no bearing: a wrong identification or attitude (a heavy-tailed error
   that the stated covariance does not describe) never enters the filter.

Units: radians, pixels; unit vectors ICRS.  Pure numpy: the loop in :func:`unmatched` is over frames (a few
dozen), the catalog test over each frame's detections and the stars in its cone at once.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["chi2_gate_2dof", "unmatched", "repeats", "predicted_bearing", "innovation_d2", "pick",
           "FOUND_BY"]

FOUND_BY = ("none", "gate", "gated_out", "resolved_blob")
"""How a frame's target was found: no candidate at all; the moving unmatched detection nearest the prediction
inside the gate; candidates but none inside the gate (no bearing used); the proximity camera's resolved blob (a
target no star could make: the blobber's blob) inside the gate."""


def chi2_gate_2dof(prob: float) -> float:
    """The ``prob`` quantile of chi-square with 2 degrees of freedom: ``-2 ln(1 - prob)`` (exact: its CDF is
    ``1 - exp(-x / 2)``)."""
    if not 0.0 < prob < 1.0:
        raise ValueError(f"gate probability must lie in (0, 1), got {prob!r}")
    return -2.0 * math.log1p(-prob)


def unmatched(frame, u_icrs, boresight, cat_unit, match_tol_rad: float, cone_rad: float) -> np.ndarray:
    """(K,) bool: detections with no catalog star within ``match_tol_rad``.

    frame : (K,) int frame index of each detection; u_icrs : (K, 3) their ICRS unit lines of sight (through each
    frame's estimated attitude); boresight : (T, 3) ICRS unit boresight per frame; cat_unit : (N, 3) catalog unit
    vectors; cone_rad : half-angle of the cone about the boresight that holds every detection (the field's
    half-diagonal; the stars tested are those within ``cone_rad + match_tol_rad`` of it)."""
    frame = np.asarray(frame, np.int64)
    u = np.asarray(u_icrs, np.float64)
    cat = np.asarray(cat_unit, np.float64)
    out = np.ones(len(frame), bool)
    cos_tol = math.cos(match_tol_rad)
    cos_cone = math.cos(min(cone_rad + match_tol_rad, math.pi))
    for f in np.unique(frame):
        k = np.flatnonzero(frame == f)
        near = cat[cat @ np.asarray(boresight[f], np.float64) >= cos_cone]
        if len(near):
            out[k] = np.max(u[k] @ near.T, axis=1) < cos_tol
    return out


def repeats(frame, points, tol: float, min_frames: int = 3) -> np.ndarray:
    """(K,) bool: points (K, d) (ICRS unit vectors with ``tol`` in radians as the chord, or pixel positions with
    ``tol`` in pixels) that have a point within ``tol`` in at least ``min_frames - 1`` other frames (``frame`` (K,)
    their frame indices): an object fixed in that frame of reference."""
    frame = np.asarray(frame, np.int64)
    p = np.asarray(points, np.float64)
    if len(frame) == 0:
        return np.zeros(0, bool)
    d2 = np.sum((p[:, None, :] - p[None, :, :]) ** 2, axis=-1)
    close = (d2 <= tol ** 2) & (frame[:, None] != frame[None, :])
    # count distinct other frames: one hit per (detection, frame)
    T = int(frame.max()) + 1
    hit = np.zeros((len(frame), T), bool)
    i, j = np.nonzero(close)
    hit[i, frame[j]] = True
    return hit.sum(1) >= min_frames - 1


def predicted_bearing(x, P, R_hill) -> tuple[np.ndarray, np.ndarray]:
    """The filter's predicted ICRS line of sight from chaser to target ``u = -R rho / |rho|`` (B, 3) and its
    covariance ``J P_pos J^T`` (B, 3, 3), ``J = -R (I - rho^ rho^T) / |rho|`` (the bearing update's Jacobian,
    ``nav/relative_filter.py``); x (B, 6) Hill states, P (B, 6, 6), R_hill (3, 3) Hill -> ICRS."""
    x = np.asarray(x, np.float64)
    rho = x[:, :3]
    r = np.linalg.norm(rho, axis=1)
    rh = rho / r[:, None]
    R = np.asarray(R_hill, np.float64)
    u = -rh @ R.T
    J = -R @ ((np.eye(3) - rh[:, :, None] * rh[:, None, :]) / r[:, None, None])
    return u, J @ np.asarray(P, np.float64)[:, :3, :3] @ np.swapaxes(J, -1, -2)


def innovation_d2(u_cand, C_cand, u_pred, C_pred) -> np.ndarray:
    """(K,) squared Mahalanobis distances of candidate lines of sight u_cand (K, 3) (covariances C_cand (K, 3, 3))
    from one prediction u_pred (3,) with covariance C_pred (3, 3): in the tangent plane of u_pred (basis E (2, 3)),
    ``e = E u_cand``, ``S = E (C_pred + C_cand) E^T``, ``d2 = e^T S^-1 e`` (a candidate behind the prediction, u . u_pred
    <= 0, gets inf)."""
    u = np.asarray(u_cand, np.float64)
    up = np.asarray(u_pred, np.float64)
    ref = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, ref)
    e1 /= np.linalg.norm(e1)
    E = np.stack([e1, np.cross(up, e1)])
    e = u @ E.T
    S = E @ (np.asarray(C_pred, np.float64)[None] + np.asarray(C_cand, np.float64)) @ E.T
    d2 = np.einsum("ki,ki->k", e, np.linalg.solve(S, e[..., None])[..., 0])
    return np.where(u @ up > 0, d2, np.inf)


def pick(d2, gate_d2: float) -> tuple[int, int]:
    """(index of the candidate with the smallest d2 or -1, ``FOUND_BY`` code: 1 inside the gate, 2 none inside it,
    0 no candidate)."""
    d2 = np.asarray(d2, np.float64)
    if d2.size == 0:
        return -1, 0
    k = int(np.argmin(d2))
    return (k, 1) if d2[k] <= gate_d2 else (-1, 2)
