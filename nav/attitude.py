"""Attitude from matched vector pairs by the SVD method (Markley 1988), batched over cases.

Wahba's problem: find the rotation ``A`` minimising ``sum_k w_k |b_k - A r_k|^2`` with ``b_k`` the
observed (camera-frame) unit vectors and ``r_k`` the reference (ICRS) unit vectors.  Markley,
"Attitude determination using vector observations and the singular value decomposition",
J. Astronaut. Sci. 36(3), 245-258 (1988):

    B = sum_k w_k b_k r_k^T,   B = U S V^T,   A = U diag(1, 1, det(U) det(V)) V^T.

``A`` maps reference vectors into the observed frame (``b = A r``), the project's attitude convention
(inertial -> camera, docs/architecture.md).  Everything is vectorised over a leading case axis; padded entries
carry weight 0.
"""

from __future__ import annotations

import numpy as np

__all__ = ["svd_attitude", "solve_identified"]


def _lapack_gufuncs():
    """numpy's own LAPACK gufuncs behind ``np.linalg.svd`` (full matrices) and ``np.linalg.det``, called
    directly: the same LAPACK calls, bit for bit, without the wrappers' per-call checks and error-state
    set-up, which cost more than the 3 x 3 factorisation itself on one frame (~40 of ~50 us per attitude;
    5 attitudes per frame).  Falls back to the wrappers when this numpy names them otherwise."""
    try:
        from numpy.linalg import _umath_linalg as ul
    except ImportError:                                  # pragma: no cover (numpy 1.26 and 2.x have it)
        ul = None
    svd = getattr(ul, "svd_f", None) or getattr(ul, "svd_n_f", None)      # numpy 2.x / 1.26 (m >= n)
    det = getattr(ul, "det", None)
    if svd is None or det is None:                       # pragma: no cover
        return np.linalg.svd, np.linalg.det
    return (lambda a: svd(a, signature="d->ddd")), (lambda a: det(a, signature="d->d"))


_SVD, _DET = _lapack_gufuncs()


def svd_attitude(obs: np.ndarray, ref: np.ndarray, weights: np.ndarray, *,
                 return_cov: bool = False, rank_tol: float = 1e-10):
    """Batched SVD solution of Wahba's problem (Markley 1988).

    Parameters
    ----------
    obs : (B, S, 3) observed unit vectors b_k (camera frame).  Entries with weight 0 are ignored
        (they may hold NaN).
    ref : (B, S, 3) reference unit vectors r_k (ICRS), matched row by row to ``obs``.
    weights : (B, S) non-negative weights w_k (0 = padding).  For :math:`w_k = 1/\\sigma_k^2`
        (rad^-2) the returned covariance is in rad^2; for unit weights multiply it by sigma^2.
    return_cov : also return the attitude-error covariance.
    rank_tol : the solution is ``ok`` only if the second singular value of B exceeds
        ``rank_tol`` times the first.  For two unit-weight vectors separated by theta the ratio is
        (1 - cos theta) / (1 + cos theta) ~ theta^2 / 4, so 1e-10 rejects pairs closer than ~4 arcsec
        (parallel observations, attitude undetermined about their common direction).

    Returns
    -------
    A : (B, 3, 3) float64 rotation matrices with ``b ~ A r`` (NaN where not ok).
    ok : (B,) bool, at least two non-parallel observations with positive weight (False, A NaN, for a case
        whose profile matrix is not finite, e.g. an infinite weight; the other cases are unaffected).
    cov : (B, 3, 3) float64, only if ``return_cov``: covariance (rad^2) of the small error rotation
        vector ``dtheta`` in the camera frame, ``A_true ~ (I + [dtheta x]) A`` to first order, from
        Markley 1988 (covariance of the SVD estimate; also Markley & Crassidis 2014, Sec. 5.5):
        ``P = U diag(1/(s2+s3), 1/(s3+s1), 1/(s1+s2)) U^T`` with ``s3 = det(U) det(V) S33``.
        Valid for the QUEST measurement model (noise perpendicular to b_k, variance sigma_k^2 per
        axis) with ``w_k = 1/sigma_k^2``; checked by Monte Carlo in tests/test_nav_star.py.
        ``sqrt(P[2, 2])`` is the roll (about the boresight) uncertainty, the weak axis of a narrow
        field.  NaN where not ok.
    """
    obs = np.asarray(obs, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    if obs.ndim != 3 or obs.shape[-1] != 3 or ref.shape != obs.shape or w.shape != obs.shape[:2]:
        raise ValueError(f"expected obs/ref (B,S,3) and weights (B,S), got {obs.shape}, {ref.shape}, {w.shape}")
    use = w > 0
    w = np.where(use, w, 0.0)
    b = np.where(use[..., None], obs, 0.0)
    r = np.where(use[..., None], ref, 0.0)
    Bm = np.einsum("bs,bsi,bsj->bij", w, b, r)                       # attitude profile matrix
    with np.errstate(invalid="ignore"):       # a factorisation that fails (non-finite B) gives NaN: not ok
        U, s, Vt = _SVD(Bm)
        d = _DET(U) * _DET(Vt)                                        # +-1
    U_d = U.copy() if return_cov else U                                 # (U itself is needed for cov only)
    U_d[:, :, 2] *= d[:, None]                                        # U diag(1, 1, d)
    A = U_d @ Vt
    ok = (np.count_nonzero(use, axis=1) >= 2) & (s[:, 0] > 0) & (s[:, 1] > rank_tol * s[:, 0])
    if not ok.all():
        A[~ok] = np.nan
    if not return_cov:
        return A, ok
    s1, s2, s3 = s[:, 0], s[:, 1], d * s[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        diag = np.stack([1.0 / (s2 + s3), 1.0 / (s3 + s1), 1.0 / (s1 + s2)], axis=-1)
    cov = np.einsum("bik,bk,bjk->bij", U, diag, U)
    cov[~ok] = np.nan
    return A, ok, cov


def solve_identified(obs: np.ndarray, ids: np.ndarray, accepted: np.ndarray, cat_unit: np.ndarray,
                     weights: np.ndarray | None = None, **kwargs):
    """Attitude from identified stars: :func:`svd_attitude` on the accepted (observed, catalog) pairs.

    Parameters
    ----------
    obs : (B, S, 3) camera-frame unit vectors of the observed stars.
    ids : (B, S) int catalog rows (-1 = unidentified).
    accepted : (B, S) bool, which identifications to use.
    cat_unit : (N, 3) ICRS unit vectors of the catalog.
    weights : optional (B, S) weights (default 1 for every accepted star).
    **kwargs : passed to :func:`svd_attitude` (``return_cov``, ``rank_tol``).

    Returns
    -------
    As :func:`svd_attitude`.
    """
    ids = np.asarray(ids)
    use = np.asarray(accepted, dtype=bool) & (ids >= 0)
    ref = np.asarray(cat_unit, dtype=np.float64)[np.where(use, ids, 0)]
    w = use.astype(np.float64) if weights is None else np.where(use, np.asarray(weights, dtype=np.float64), 0.0)
    return svd_attitude(obs, ref, w, **kwargs)
