"""The focal length refined while tracking (issue 22, point 3: "the field of view (focal length) refined while
tracking when the camera file allows it"; tetra3rs #27 reports that its tracking never re-estimates it).

One frame (:func:`focal_from_fix`): the matched (detection, catalog star) pairs of a fix and its attitude ``A``.
The pixel of catalog star ``c`` is ``p(phi, kappa) = project_{(1 + kappa) f}(exp(-[phi x]) A c)``: the camera's
pinhole + distortion model with both focal lengths scaled by ``1 + kappa`` (the principal point, the aspect ratio
and the distortion kept), and a small attitude correction ``phi`` (rad), because the fix's attitude was solved with
the old focal length.  Weighted Gauss-Newton on the four parameters ``(phi, kappa)`` over the pixel residuals
(weights ``1 / sigma_px^2`` per axis; Jacobian by central differences, vectorised over stars), three iterations from
zero; the covariance ``(J^T W J)^-1`` times the a posteriori variance factor ``max(1, chi^2 / (2 n - 4))``
(Bjorck 1996, Sec. 1.1.5, weighted least squares).  A scale error moves every star radially about the principal
point and a rotation moves them all alike, so the two separate when the stars spread over the field; the
marginal variance of ``kappa`` says how well.

Over frames (:class:`FocalFuser`): the recursive weighted mean of the per-frame estimates
``f_fused = sum(f_k / var_k) / sum(1 / var_k)``, ``var_fused = 1 / sum(1 / var_k)`` (frames' centroid noise is
independent), and the camera with the fused focal lengths for the next frame's prediction and lost-in-space.
A frame's estimate is skipped when it rests on fewer than ``min_stars`` stars, its 1-sigma exceeds ``max_sigma``
(relative) or it moves the focal length by more than ``max_step`` (relative; a wrong match, not a lens).

Units: pixels, radians; the focal lengths in px (``Camera.fx``, ``Camera.fy``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from dualsight.scene.rotation_vector import frame_rotation

__all__ = ["FocalFix", "focal_from_fix", "scaled_camera", "FocalFuser"]

_STEP_PHI = 1e-6
"""Central-difference step of the attitude correction (rad)."""
_STEP_KAPPA = 1e-6
"""Central-difference step of the relative focal change."""


@dataclasses.dataclass(frozen=True)
class FocalFix:
    """One frame's estimate: kappa (relative change of both focal lengths against the camera passed in), its
    variance, the attitude correction phi (3,) rad, stars used, chi^2 / dof of the fit."""

    kappa: float
    var: float
    phi: np.ndarray
    n: int
    chi2_dof: float


def scaled_camera(camera, scale: float):
    """``camera`` with both focal lengths times ``scale`` (principal point, aspect ratio, distortion kept)."""
    return dataclasses.replace(camera, fx=camera.fx * float(scale), fy=camera.fy * float(scale))


def _predict(camera, A: np.ndarray, c: np.ndarray, params: np.ndarray) -> np.ndarray:
    """(P, n, 2) pixels of catalog vectors c (n, 3) for parameter rows (P, 4) = (phi (3), kappa)."""
    out = np.empty((len(params), len(c), 2))
    for i, p in enumerate(params):          # a handful of parameter sets (1 + 2 x 4), each vectorised over stars
        v = c @ (frame_rotation(p[:3]) @ A).T
        out[i] = scaled_camera(camera, 1.0 + p[3]).project(v)[0]
    return out


def focal_from_fix(xy: np.ndarray, sigma_px: np.ndarray, cat_vec: np.ndarray, A: np.ndarray, camera,
                   iterations: int = 3) -> FocalFix | None:
    """Least-squares focal length of one fix (module docstring).

    xy : (n, 2) matched detections (px).  sigma_px : (n,) 1-sigma centroid error per axis (px).  cat_vec : (n, 3)
    their catalog unit vectors (ICRS).  A : (3, 3) the fix's attitude (inertial -> camera).  camera : the
    ``scene.camera.Camera`` the fix was solved with.  Returns None with fewer than 3 stars (4 unknowns)."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    n = len(xy)
    if n < 3:
        return None
    w = 1.0 / np.asarray(sigma_px, np.float64) ** 2                         # (n,) per axis
    W = np.repeat(w, 2)
    h = np.array([_STEP_PHI] * 3 + [_STEP_KAPPA])
    x = np.zeros(4)
    for _ in range(int(iterations)):
        P = np.vstack([x, x + np.diag(h), x - np.diag(h)])                 # (9, 4)
        pred = _predict(camera, A, cat_vec, P)
        if not np.all(np.isfinite(pred)):
            return None
        r = (xy - pred[0]).reshape(-1)                                      # (2n,)
        J = ((pred[1:5] - pred[5:9]) / (2 * h)[:, None, None]).reshape(4, -1).T       # (2n, 4)
        N = J.T @ (J * W[:, None])
        dx = np.linalg.solve(N, J.T @ (W * r))
        x = x + dx
    pred = _predict(camera, A, cat_vec, x[None])[0]
    r = (xy - pred).reshape(-1)
    chi2 = float(np.sum(W * r * r))
    dof = max(1, 2 * n - 4)
    C = np.linalg.inv(N) * max(1.0, chi2 / dof)
    return FocalFix(float(x[3]), float(C[3, 3]), x[:3].copy(), n, chi2 / dof)


class FocalFuser:
    """The focal length over a sequence (module docstring): ``update`` after each fix returns the camera for the
    next frame.  Per frame (T,) arrays, NaN where none: ``f_frame`` / ``sigma_frame`` (px, that frame's estimate of
    fx) and ``f_fused`` / ``sigma_fused`` (px, the fused fx after that frame).  Construct one per sequence."""

    def __init__(self, camera, n_frames: int, *, min_stars: int = 4, max_sigma: float = 0.05,
                 max_step: float = 0.2):
        self.camera0 = camera
        self.min_stars, self.max_sigma, self.max_step = int(min_stars), float(max_sigma), float(max_step)
        self.f_frame, self.sigma_frame, self.f_fused, self.sigma_fused = (np.full(int(n_frames), np.nan)
                                                                          for _ in range(4))
        self._info = 0.0            # sum of 1 / var (px^-2)
        self._sum = 0.0             # sum of f / var

    def update(self, k: int, xy: np.ndarray, sigma_px: np.ndarray, rows: np.ndarray, A: np.ndarray,
               cat_unit: np.ndarray, camera):
        """Fold frame ``k``'s fix in.  xy (D, 2) px and sigma_px (D,) of the frame's detections; rows (D,) their
        catalog rows (-1: not in the answer); A the fix's attitude; camera the one it was solved with.  Returns
        the camera for the next frame (``camera0`` with the fused focal lengths; ``camera`` while none)."""
        rows = np.asarray(rows, np.int64)
        m = rows >= 0
        if m.sum() >= self.min_stars:
            est = focal_from_fix(np.asarray(xy)[m], np.asarray(sigma_px)[m], cat_unit[rows[m]], A, camera)
            if est is not None and np.isfinite(est.var) and est.var > 0:
                f = camera.fx * (1.0 + est.kappa)
                s = camera.fx * np.sqrt(est.var)
                if s <= self.max_sigma * f and abs(f / self.camera0.fx - 1.0) <= self.max_step:
                    self.f_frame[k], self.sigma_frame[k] = f, s
                    self._info += 1.0 / s ** 2
                    self._sum += f / s ** 2
        if self._info <= 0:
            return camera
        self.f_fused[k] = self._sum / self._info
        self.sigma_fused[k] = 1.0 / np.sqrt(self._info)
        return scaled_camera(self.camera0, self.f_fused[k] / self.camera0.fx)
