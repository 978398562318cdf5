"""Focal length and radial lens distortion from identified stars (``dualsight hil star --fit-distortion``).

The sky is the calibration target: once frames are identified and solved, every identified star has a
catalog direction ``u`` (ICRS unit vector) and a measured centroid; a camera model that is wrong in its
focal length or distortion leaves residuals that grow with the distance from the principal point, the
same way in every frame.  This module fits the camera's intrinsics jointly with a small rotation
correction per frame by nonlinear least squares (Levenberg-Marquardt over a Schur complement: numpy only,
no Python loop over stars), robust to a few misidentified stars.

Model (OpenCV's radial-tangential model on normalised coordinates, as ``scene/camera.py``; dualsight's
pixel convention: pixel (r, c) has its centre at (c + 0.5, r + 0.5))::

    v_i    = exp([w_f]x) A_f u_i                  camera-frame direction of star i seen in frame f
    x      = v_x / v_z,   y = v_y / v_z,   r^2 = x^2 + y^2
    radial = 1 + k1 r^2 + k2 r^4 + k3 r^6
    x_d    = x radial + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d    = y radial + p1 (r^2 + 2 y^2) + 2 p2 x y
    col    = fx x_d + cx,   row = fy y_d + cy       (px)

    e_i    = (col_i, row_i) - measured centroid_i   (px)
    minimise  sum_i  rho(|e_i|)   over  theta = (s [or sx, sy], k1, k2 [, cx, cy])  and  w_f (3 per frame)

with ``fx = fx0 s``, ``fy = fy0 s`` (one focal scale, ``focal = "common"``) or separate scales
(``"separate"``); ``A_f`` the attitude of frame f (inertial -> camera) as solved, ``w_f`` (rad) the rotation
correcting it (``A_f <- exp([w_f]x) A_f`` after every step); p1, p2, k3 and, unless
``fit_principal_point``, cx, cy are held at their input values.  A principal-point shift is nearly a
rotation of the frame (only the distortion and the perspective tell them apart), so it is fixed by default.

Solver: Levenberg-Marquardt with Marquardt's damping (lambda times the diagonal of the normal matrix), the
per-frame 3 x 3 blocks eliminated by the Schur complement, so a step costs O(N) for N stars plus a P x P solve
(P <= 6 camera parameters).  One-sigma uncertainties of the camera parameters come from the inverse of the
undamped Schur complement times the weighted residual variance.

Robustness (iteratively reweighted rounds): the first round is plain least squares (rho = e^2 / 2) over every
star, so the distortion that the fit is there to find is not mistaken for outliers; the next rounds use
Huber's loss on |e| (weight 1 up to c = ``huber_k`` sigma, c / |e| beyond) until the weights settle (so one
frame's wrong stars no longer drag its rotation), then every star with ``|e| > max(reject_sigma * sigma,
reject_floor_px)`` (default 5 sigma, 0.5 px) is rejected as misidentified, repeating until the set of stars
kept stops changing (at most ``max_rounds`` rounds).  ``sigma`` is the robust per-axis
residual scale ``median(|e|) / 1.1774`` (the median of a 2-D Gaussian residual's length is
sqrt(2 ln 2) sigma).  A frame keeps its stars only while it has at least ``min_stars_per_frame`` of them
(three stars fix its rotation).

Units: pixels for centroids, residuals, fx, fy, cx, cy; radians for rotations; k1, k2, p1, p2, k3 and the
focal scales are dimensionless.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from dualsight.config import check_fields
from dualsight.errors import ConfigError

__all__ = ["Intrinsics", "FitConfig", "FitResult", "project", "project_with_jacobians", "rotation_exp",
           "fit_camera", "robust_sigma", "RAYLEIGH_MEDIAN"]

RAYLEIGH_MEDIAN = math.sqrt(2 * math.log(2))
"""Median of the length of a 2-D residual with independent N(0, sigma^2) axes, in units of sigma (1.1774)."""


@dataclass(frozen=True)
class Intrinsics:
    """Camera intrinsics of the model (module docstring): fx, fy, cx, cy in px (dualsight convention:
    from the image's top-left corner); distortion (k1, k2, p1, p2, k3), OpenCV's coefficients."""

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @classmethod
    def of(cls, camera) -> "Intrinsics":
        """The intrinsics of a ``scene.camera.Camera``."""
        return cls(float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy),
                   tuple(float(x) for x in camera.distortion))


@dataclass(frozen=True)
class FitConfig:
    """What :func:`fit_camera` fits, and how robustly.

    focal : "common" (one scale s: fx = fx0 s, fy = fy0 s), "separate" (fx and fy), or "fixed".
    fit_k1, fit_k2 : fit the radial coefficients k1 and k2 (else held at their input values).
    fit_principal_point : fit cx, cy (default False: held; see the module docstring).
    huber_k : Huber threshold of the robust rounds, in robust sigmas (per axis), in [0.5, 100].
    reject_sigma : a star whose residual length exceeds ``reject_sigma`` robust sigmas (and
        ``reject_floor_px``) is rejected as misidentified, in [2, 1000]; at 5 a correctly identified star
        of Gaussian centroid noise is rejected with probability exp(-12.5) = 4e-6.
    reject_floor_px : never reject a residual shorter than this (px), in [0, 1e4]: keeps the rejection
        from biting into the noise when sigma is tiny (noise-free frames).
    min_stars_per_frame : a frame contributes only with at least this many kept stars, an integer in [3, 1000].
    max_rounds : robust rounds (reweighting and rejection) after the least-squares round, in [0, 100].
    max_iterations : Levenberg-Marquardt iterations per round, in [1, 10000].
    tol : a round ends when an accepted step lowers the cost by less than ``tol`` (relative), in (0, 0.1].
    """

    focal: Literal["common", "separate", "fixed"] = "common"
    fit_k1: bool = True
    fit_k2: bool = True
    fit_principal_point: bool = False
    huber_k: Annotated[float, Field(ge=0.5, le=100.0)] = 2.0
    reject_sigma: Annotated[float, Field(ge=2.0, le=1000.0)] = 5.0
    reject_floor_px: Annotated[float, Field(ge=0.0, le=1e4)] = 0.5
    min_stars_per_frame: Annotated[int, Field(ge=3, le=1000)] = 3
    max_rounds: Annotated[int, Field(ge=0, le=100)] = 20
    max_iterations: Annotated[int, Field(ge=1, le=10_000)] = 100
    tol: Annotated[float, Field(gt=0.0, le=0.1)] = 1e-10

    def __post_init__(self):
        check_fields(self, lambda name, msg: ConfigError(msg, field=f"distortion_fit.{name}"),
                     {"reject_floor_px": "px", "huber_k": "sigma", "reject_sigma": "sigma",
                      "min_stars_per_frame": "stars"})

    @property
    def names(self) -> tuple[str, ...]:
        """Names of the fitted global parameters, in the order of the parameter vector."""
        n = {"common": ("s",), "separate": ("sx", "sy"), "fixed": ()}[self.focal]
        n += ("k1",) if self.fit_k1 else ()
        n += ("k2",) if self.fit_k2 else ()
        return n + (("cx", "cy") if self.fit_principal_point else ())


@dataclass(frozen=True)
class FitResult:
    """Output of :func:`fit_camera` (N stars, F frames).

    intrinsics : the fitted :class:`Intrinsics`.
    A : (F, 3, 3) attitudes (inertial -> camera) after the fit (the input's where a frame had too few stars).
    residual_px : (N, 2) float64 model minus measurement (px) of every star at the solution.
    inlier : (N,) bool, the star was kept (not rejected, in a frame with enough kept stars).
    frame_used : (F,) bool, the frame had at least ``min_stars_per_frame`` kept stars.
    rms_px : rms of the residual length over the kept stars (px) = sqrt(mean |e|^2).
    sigma_px : robust per-axis residual scale of the kept stars (px), median(|e|) / 1.1774.
    std : {name: one-sigma uncertainty} of fx, fy, k1, k2, cx, cy as fitted (from the weighted normal
        matrix, scaled by the residual variance; fx/fy in px).
    rounds, iterations : robust rounds run and Levenberg-Marquardt iterations in all.
    """

    intrinsics: Intrinsics
    A: np.ndarray
    residual_px: np.ndarray
    inlier: np.ndarray
    frame_used: np.ndarray
    rms_px: float
    sigma_px: float
    std: dict = field(default_factory=dict)
    rounds: int = 0
    iterations: int = 0

    @property
    def n_stars(self) -> int:
        return int(self.inlier.sum())

    @property
    def n_frames(self) -> int:
        return int(self.frame_used.sum())


# ============================================================================================ the model
def rotation_exp(w: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors (rad) -> (..., 3, 3) rotation matrices exp([w]x) (Rodrigues)."""
    w = np.asarray(w, np.float64)
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = _skew(w)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th ** 2 / 6, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th ** 2 / 24, (1 - np.cos(ths)) / ths ** 2)
    return np.eye(3) + a * K + b * (K @ K)


def _skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices [v]x (so [v]x a = v x a)."""
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1),
                     np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def project(v_cam: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """(N, 3) camera-frame vectors (z > 0) -> (N, 2) pixel coordinates (col, row), px: the model's equations."""
    return project_with_jacobians(v_cam, intr)[0]


def project_with_jacobians(v_cam: np.ndarray, intr: Intrinsics):
    """The model and its derivatives at (N, 3) camera-frame vectors ``v``.

    Returns
    -------
    px : (N, 2) pixel coordinates (col, row), px.
    d_v : (N, 2, 3) d(col, row) / dv (px per unit of v).
    d_k : (N, 2, 2) d(col, row) / d(k1, k2) = (fx x r^2, fx x r^4; fy y r^2, fy y r^4) (px).
    d_xy : (N, 2) (x_d, y_d): d col / d fx and d row / d fy.
    """
    v = np.asarray(v_cam, np.float64)
    k1, k2, p1, p2, k3 = intr.distortion
    z = v[:, 2]
    x, y = v[:, 0] / z, v[:, 1] / z
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = k1 + r2 * (2 * k2 + 3 * k3 * r2)                # d radial / d r^2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    px = np.stack([intr.fx * xd + intr.cx, intr.fy * yd + intr.cy], -1)
    # d(x_d, y_d) / d(x, y)
    jd = np.empty((len(v), 2, 2))
    jd[:, 0, 0] = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x
    jd[:, 0, 1] = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
    jd[:, 1, 0] = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
    jd[:, 1, 1] = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x
    # d(x, y) / dv
    jp = np.zeros((len(v), 2, 3))
    jp[:, 0, 0] = 1 / z
    jp[:, 0, 2] = -x / z
    jp[:, 1, 1] = 1 / z
    jp[:, 1, 2] = -y / z
    f = np.array([intr.fx, intr.fy])
    d_v = f[None, :, None] * np.einsum("nij,njk->nik", jd, jp)
    d_k = np.stack([np.stack([intr.fx * x * r2, intr.fx * x * r2 * r2], -1),
                    np.stack([intr.fy * y * r2, intr.fy * y * r2 * r2], -1)], 1)
    return px, d_v, d_k, np.stack([xd, yd], -1)


def robust_sigma(e: np.ndarray) -> float:
    """Robust per-axis scale (px) of (N, 2) residuals: median(|e|) / 1.1774 (:data:`RAYLEIGH_MEDIAN`)."""
    n = np.linalg.norm(np.asarray(e, np.float64).reshape(-1, 2), axis=-1)
    return float(np.median(n) / RAYLEIGH_MEDIAN) if n.size else float("nan")


# ============================================================================================ the fit
def _intrinsics(theta: np.ndarray, names, base: Intrinsics) -> Intrinsics:
    p = dict(zip(names, theta))
    sx = p.get("s", p.get("sx", 1.0))
    sy = p.get("s", p.get("sy", 1.0))
    k1, k2, p1, p2, k3 = base.distortion
    return Intrinsics(float(base.fx * sx), float(base.fy * sy), float(p.get("cx", base.cx)),
                      float(p.get("cy", base.cy)), (float(p.get("k1", k1)), float(p.get("k2", k2)), p1, p2, k3))


def _theta0(names, base: Intrinsics) -> np.ndarray:
    start = {"s": 1.0, "sx": 1.0, "sy": 1.0, "k1": base.distortion[0], "k2": base.distortion[1],
             "cx": base.cx, "cy": base.cy}
    return np.array([start[n] for n in names], np.float64)


def _evaluate(u, frame, px, R, theta, names, base):
    """Residuals (N, 2) and Jacobians: d e / d theta (N, 2, P) and d e / d w_f (N, 2, 3)."""
    intr = _intrinsics(theta, names, base)
    v = np.einsum("nij,nj->ni", R[frame], u)
    model, d_v, d_k, xyd = project_with_jacobians(v, intr)
    e = model - px
    jw = -np.einsum("nij,njk->nik", d_v, _skew(v))                # dv / dw = -[v]x
    cols = []
    for n in names:                                              # loop over <= 6 parameters, not stars
        if n == "s":
            cols.append(np.stack([base.fx * xyd[:, 0], base.fy * xyd[:, 1]], -1))
        elif n == "sx":
            cols.append(np.stack([base.fx * xyd[:, 0], np.zeros(len(u))], -1))
        elif n == "sy":
            cols.append(np.stack([np.zeros(len(u)), base.fy * xyd[:, 1]], -1))
        elif n == "k1":
            cols.append(d_k[:, :, 0])
        elif n == "k2":
            cols.append(d_k[:, :, 1])
        elif n == "cx":
            cols.append(np.tile([1.0, 0.0], (len(u), 1)))
        elif n == "cy":
            cols.append(np.tile([0.0, 1.0], (len(u), 1)))
    jg = np.stack(cols, -1) if cols else np.zeros((len(u), 2, 0))
    return e, jg, jw


def _normal(e, jg, jw, wt, frame, F):
    """Blocks of the weighted normal equations: U (P, P), V (F, 3, 3), W (F, 3, P), bg (P,), bw (F, 3)."""
    def by_frame(a):
        out = np.zeros((F,) + a.shape[1:])
        np.add.at(out, frame, a)
        return out

    w = wt[:, None, None]
    U = np.einsum("nkp,nkq->pq", w * jg, jg)
    V = by_frame(np.einsum("nki,nkj->nij", w * jw, jw))
    W = by_frame(np.einsum("nki,nkp->nip", w * jw, jg))
    bg = np.einsum("nkp,nk->p", w * jg, e)
    bw = by_frame(np.einsum("nki,nk->ni", w * jw, e))
    return U, V, W, bg, bw


def _solve_step(U, V, W, bg, bw, lam):
    """Damped Gauss-Newton step by the Schur complement: (dtheta (P,), dw (F, 3)).

    [U + lam D_U, W^T; W, V + lam D_V] [dtheta; dw] = -[bg; bw], D = diagonal of the undamped blocks.
    """
    P = U.shape[0]
    Vd = V + lam * np.einsum("fii->fi", V)[..., None] * np.eye(3) + 1e-18 * np.eye(3)
    Vinv = np.linalg.inv(Vd)
    if P:
        Ud = U + lam * np.diag(np.diag(U))
        VW = Vinv @ W                                                 # (F, 3, P)
        S = Ud - np.einsum("fip,fiq->pq", W, VW)
        rhs = -bg + np.einsum("fip,fi->p", VW, bw)
        dtheta = np.linalg.solve(S, rhs)
        dw = -np.einsum("fij,fj->fi", Vinv, bw + W @ dtheta)
    else:
        dtheta = np.zeros(0)
        dw = -np.einsum("fij,fj->fi", Vinv, bw)
    return dtheta, dw


def _lm(u, frame, px, wt, R, theta, names, base, cfg: FitConfig):
    """Levenberg-Marquardt over (theta, w_f) with fixed weights ``wt`` (N,); returns (R, theta, iterations)."""
    F = R.shape[0]
    e, jg, jw = _evaluate(u, frame, px, R, theta, names, base)
    cost = float(np.sum(wt * np.sum(e * e, -1)))
    lam, it = 1e-3, 0
    for it in range(1, cfg.max_iterations + 1):
        U, V, W, bg, bw = _normal(e, jg, jw, wt, frame, F)
        improved = False
        while lam < 1e12:
            dtheta, dw = _solve_step(U, V, W, bg, bw, lam)
            R_t = rotation_exp(dw) @ R
            th_t = theta + dtheta
            e_t, jg_t, jw_t = _evaluate(u, frame, px, R_t, th_t, names, base)
            cost_t = float(np.sum(wt * np.sum(e_t * e_t, -1)))
            if np.isfinite(cost_t) and cost_t <= cost:
                improved = True
                break
            lam *= 10
        if not improved:
            break
        gain = (cost - cost_t) / max(cost, 1e-300)
        R, theta, e, jg, jw, cost = R_t, th_t, e_t, jg_t, jw_t, cost_t
        lam = max(lam / 10, 1e-12)
        if gain < cfg.tol:
            break
    return R, theta, it


def _frames_with(inlier, frame, F, k):
    """(F,) bool: frames with at least k of the stars marked in ``inlier``."""
    return np.bincount(frame[inlier], minlength=F) >= k


def fit_camera(u: np.ndarray, frame: np.ndarray, px: np.ndarray, A: np.ndarray, intr: Intrinsics,
               cfg: FitConfig = FitConfig()) -> FitResult:
    """Fit the camera (``cfg.names``) and each frame's rotation to identified stars (module docstring).

    Parameters
    ----------
    u : (N, 3) ICRS unit vectors of the identified catalog stars.
    frame : (N,) int, the frame (row of ``A``) each star was seen in.
    px : (N, 2) measured centroids (col, row), px.
    A : (F, 3, 3) attitudes (inertial -> camera) of the frames as solved, the starting point.
    intr : the starting :class:`Intrinsics` (what is not fitted is held at these values).
    cfg : :class:`FitConfig`.

    Returns
    -------
    :class:`FitResult`.  Raises ValueError for inconsistent shapes or a star behind the camera.
    """
    u = np.asarray(u, np.float64)
    frame = np.asarray(frame, np.int64)
    px = np.asarray(px, np.float64)
    A = np.asarray(A, np.float64)
    N, F = len(u), len(A)
    if u.shape != (N, 3) or px.shape != (N, 2) or frame.shape != (N,) or A.shape != (F, 3, 3):
        raise ValueError(f"expected u (N,3), frame (N,), px (N,2), A (F,3,3); got {u.shape}, {frame.shape}, "
                         f"{px.shape}, {A.shape}")
    if N and (frame.min() < 0 or frame.max() >= F):
        raise ValueError("frame indices must lie in [0, F)")
    names = cfg.names
    theta = _theta0(names, intr)
    R = A.copy()
    inlier = np.isfinite(px).all(-1) & np.isfinite(u).all(-1)
    used = _frames_with(inlier, frame, F, cfg.min_stars_per_frame)
    inlier &= used[frame]
    wt = np.ones(N)
    iters = rounds = 0
    rejecting = False
    for rounds in range(cfg.max_rounds + 1):
        keep = np.flatnonzero(inlier)
        if keep.size == 0:
            break
        # compact the frames with stars (frames without any are not parameters of this round)
        fr_ids, fr_local = np.unique(frame[keep], return_inverse=True)
        R_sub, theta, it = _lm(u[keep], fr_local, px[keep], wt[keep], R[fr_ids], theta, names, intr, cfg)
        R[fr_ids] = R_sub
        iters += it
        if rounds == cfg.max_rounds:
            break
        e = _evaluate(u, frame, px, R, theta, names, intr)[0]
        norm = np.linalg.norm(e, axis=-1)
        sig = robust_sigma(e[inlier])
        c = cfg.huber_k * sig
        new_wt = np.where(norm <= c, 1.0, c / np.maximum(norm, 1e-300))
        new = inlier
        if rejecting:
            new = inlier & (norm <= max(cfg.reject_sigma * sig, cfg.reject_floor_px))
            new &= _frames_with(new, frame, F, cfg.min_stars_per_frame)[frame]
        settled = rounds > 0 and np.array_equal(new, inlier) and np.allclose(new_wt[new], wt[new], rtol=1e-2, atol=0)
        inlier, wt = new, new_wt
        if settled:
            if rejecting:
                break
            rejecting = True        # the Huber weights have settled: from now on reject the outliers too
    fitted = _intrinsics(theta, names, intr)
    e = _evaluate(u, frame, px, R, theta, names, intr)[0] if N else np.zeros((0, 2))
    used = _frames_with(inlier, frame, F, cfg.min_stars_per_frame)
    rms = float(np.sqrt(np.mean(np.sum(e[inlier] ** 2, -1)))) if inlier.any() else float("nan")
    std = _std(u, frame, px, R, theta, names, intr, wt, inlier, F) if inlier.any() else {}
    return FitResult(fitted, R, e, inlier, used, rms, robust_sigma(e[inlier]), std, rounds, iters)


def _std(u, frame, px, R, theta, names, base, wt, inlier, F) -> dict:
    """One-sigma uncertainties of the fitted global parameters (fx, fy in px), from the inverse of the
    undamped Schur complement times the weighted residual variance."""
    if not names:
        return {}
    keep = np.flatnonzero(inlier)
    fr_ids, fr_local = np.unique(frame[keep], return_inverse=True)
    e, jg, jw = _evaluate(u[keep], fr_local, px[keep], R[fr_ids], theta, names, base)
    U, V, W, _, _ = _normal(e, jg, jw, wt[keep], fr_local, len(fr_ids))
    S = U - np.einsum("fip,fiq->pq", W, np.linalg.inv(V + 1e-18 * np.eye(3)) @ W)
    dof = max(2 * keep.size - len(names) - 3 * len(fr_ids), 1)
    s2 = float(np.sum(wt[keep] * np.sum(e * e, -1))) / dof
    try:
        sd = np.sqrt(np.clip(np.diag(np.linalg.inv(S)) * s2, 0, None))
    except np.linalg.LinAlgError:
        sd = np.full(len(names), np.nan)
    out = {}
    for n, s in zip(names, sd):
        if n == "s":
            out["fx"], out["fy"] = base.fx * s, base.fy * s
        elif n in ("sx", "sy"):
            out["f" + n[1]] = (base.fx if n == "sx" else base.fy) * s
        else:
            out[n] = float(s)
    return {k: float(v) for k, v in out.items()}
