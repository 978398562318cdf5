"""Scores of the hardware-in-the-loop runs against independently known truth.

Star tracker (one real frame), all angles between unit vectors (``scene.units.angle_between``):

    boresight error   angle between the solved camera +z axis (third row of A_est) and the truth's
                      (third row of the truth matrix); ``boresight_error_radec`` uses the truth file's
                      ``ra_deg``/``dec_deg`` instead (they differ from R's third row by up to 63 arcsec
                      on the poorly solved ESA frame).
    attitude error    rotation angle of A_true A_est^T; ``err_x/y/z`` the reference's Eqs. 4-7 about the
                      camera axes (x, y across the boresight, z = roll), as the SIL job's "camera" frame.
    status            with truth: success (every axis error <= the limit), confident_wrong (failed,
                      T > 0), no_solution (T <= 0 or no attitude), as :func:`dualsight.nav.errors.classify`;
                      without truth: identified / no_solution.
    truth stars       a truth file's matched star is "the same detection" as ours when the centroids are
                      within :data:`TRUTH_MATCH_PX`, and "the same star" when its catalog position is within
                      :data:`TRUTH_ID_ARCSEC` of ours.

Proximity (one image at one threshold): ``range_error_m`` = estimate - truth, ``abs_error_m``,
``rel_error`` = abs / truth (a fraction), ``within_min_max`` = truth in [range_min, range_max] (False when
no blob was found; None without truth).

Plain dicts of floats/ints/bools in SI units (radians, metres): the job turns them into lake rows.
"""

from __future__ import annotations

import math

import numpy as np

from dualsight.nav.errors import STATUS_NAMES, axis_errors, classify, total_error_angle
from dualsight.scene.attitude import radec_to_unit, unit_to_radec
from dualsight.scene.pointing import roll_deg
from dualsight.scene.units import ARCSEC, angle_between

__all__ = ["TRUTH_MATCH_PX", "TRUTH_ID_ARCSEC", "FILE_LIMIT_ARCSEC", "ALTAZ_LIMIT_ARCSEC", "status_limit_arcsec",
           "truth_star_checks", "truth_star_counts", "score_star_frame", "residual_stats", "score_range"]

TRUTH_MATCH_PX = 2.0
"""A truth-file matched star is "the same detection" as ours when the centroids are within 2 px."""
TRUTH_ID_ARCSEC = 60.0
"""...and "the same star" when its catalog position is within 60 arcsec of ours (catalog and epoch
differences are a few arcsec; the nearest other V <= 7.5 star is usually tens of arcmin away)."""
FILE_LIMIT_ARCSEC = 100.0
"""Status limit per axis against a plate-solved truth file: the reference's 100 arcsec."""
ALTAZ_LIMIT_ARCSEC = 7200.0
"""Default status limit against an alt/az (tripod) truth: a nominal mount pointing is good to ~1 deg."""


def status_limit_arcsec(truth_source: str, limit_arcsec: float | None) -> float:
    """The per-axis status limit: ``limit_arcsec`` if given, else by the truth's source."""
    if limit_arcsec is not None:
        return float(limit_arcsec)
    return FILE_LIMIT_ARCSEC if truth_source == "file" else ALTAZ_LIMIT_ARCSEC


def truth_star_checks(x, y, u, matched: dict | None):
    """Per identified star (centroids ``x``, ``y`` px; catalog unit vectors ``u`` (K, 3)): is there a truth
    star at the same centroid (:data:`TRUTH_MATCH_PX`), and is it the same sky position
    (:data:`TRUTH_ID_ARCSEC`)?  ``matched`` holds arrays ``row``, ``col``, ``ra_deg``, ``dec_deg``.
    (None, None) without a truth file."""
    if matched is None:
        return None, None
    x, y = np.asarray(x, float), np.asarray(y, float)
    mcol, mrow = np.asarray(matched["col"], float), np.asarray(matched["row"], float)
    if mrow.size == 0:
        return np.zeros(len(x), bool), np.zeros(len(x), bool)
    d = np.hypot(x[:, None] - mcol[None], y[:, None] - mrow[None])
    k = d.argmin(axis=1)
    hit = d[np.arange(len(x)), k] <= TRUTH_MATCH_PX
    tv = radec_to_unit(np.radians(np.asarray(matched["ra_deg"], float)[k]),
                       np.radians(np.asarray(matched["dec_deg"], float)[k]))
    agree = angle_between(u, tv) <= TRUTH_ID_ARCSEC * ARCSEC
    return hit, agree


def truth_star_counts(matched: dict, ours_xy: np.ndarray | None, agrees) -> dict:
    """``truth_stars`` (truth file's matched stars), ``truth_stars_found`` (of them, one of ours within
    :data:`TRUTH_MATCH_PX`), ``truth_ids_agree`` / ``truth_ids_disagree`` (our identified stars whose truth
    match is / is not the same sky position; ``agrees`` None where there is no truth match)."""
    mrow, mcol = np.asarray(matched["row"], float), np.asarray(matched["col"], float)
    out = {"truth_stars": int(mrow.size), "truth_stars_found": 0, "truth_ids_agree": 0, "truth_ids_disagree": 0}
    if ours_xy is not None and len(ours_xy) and mrow.size:
        d = np.hypot(mcol[:, None] - ours_xy[None, :, 0], mrow[:, None] - ours_xy[None, :, 1])
        out["truth_stars_found"] = int((d.min(axis=1) <= TRUTH_MATCH_PX).sum())
    if agrees is not None:
        out["truth_ids_agree"] = sum(1 for a in agrees if a is True)
        out["truth_ids_disagree"] = sum(1 for a in agrees if a is False)
    return out


def score_star_frame(A_est: np.ndarray | None, T: int, A_true: np.ndarray | None, *, truth_source: str,
                     limit_arcsec: float | None = None, radec_true_deg: tuple[float, float] | None = None,
                     altaz_A: np.ndarray | None = None) -> dict:
    """Errors of one solved frame against its truth and its status (module docstring).

    A_est : (3, 3) solved attitude, or None when the frame was not identified.
    T : the voting's match threshold.
    A_true : (3, 3) truth attitude or None; ``truth_source`` "file", "altaz" or "none".
    radec_true_deg : the truth file's own boresight (``boresight_error_radec``), if any.
    altaz_A : the tripod (alt/az) attitude, reported beside the truth (``altaz_*``), if any.
    """
    row: dict = {}
    if A_true is not None:
        At = np.asarray(A_true, np.float64)
        ra_t, dec_t = unit_to_radec(At[2])
        lim = status_limit_arcsec(truth_source, limit_arcsec)
        row.update(ra_true_rad=float(ra_t), dec_true_rad=float(dec_t), roll_true_deg=float(roll_deg(At)),
                   A_true=At.ravel().tolist(), limit_arcsec=lim)
        if A_est is not None:
            A = np.asarray(A_est, np.float64)
            row["boresight_error_rad"] = float(angle_between(A[2], At[2]))
            if radec_true_deg is not None:
                b = radec_to_unit(math.radians(radec_true_deg[0]), math.radians(radec_true_deg[1]))
                row["boresight_error_radec_rad"] = float(angle_between(A[2], b))
            e = axis_errors(A[None], At[None], frame="camera")[0]
            tot = float(total_error_angle(A[None], At[None])[0])
            row.update(err_x_rad=float(e[0]), err_y_rad=float(e[1]), err_z_rad=float(e[2]), attitude_error_rad=tot)
            row["status"] = STATUS_NAMES[int(classify(e[None], np.array([tot]), np.array([T]), lim)[0])]
        else:
            row["status"] = "no_solution"
    else:
        row["status"] = "identified" if A_est is not None else "no_solution"
    if altaz_A is not None:
        Aa = np.asarray(altaz_A, np.float64)
        ra_a, dec_a = unit_to_radec(Aa[2])
        row.update(altaz_ra_rad=float(ra_a), altaz_dec_rad=float(dec_a))
        if A_est is not None:
            row["altaz_error_rad"] = float(angle_between(np.asarray(A_est)[2], Aa[2]))
    return row


def residual_stats(resid: np.ndarray) -> dict:
    """``residual_median_rad``, ``residual_max_rad``, ``residual_rms_rad`` of per-star residuals (rad)."""
    r = np.asarray(resid, np.float64)
    return {"residual_median_rad": float(np.median(r)), "residual_max_rad": float(np.max(r)),
            "residual_rms_rad": float(np.sqrt(np.mean(r ** 2)))}


def score_range(found: bool, range_m: float | None, range_min_m: float | None, range_max_m: float | None,
                truth_m: float | None) -> dict:
    """Range errors of one blob against a true range (module docstring); all None without truth.

    ``within_min_max`` (truth inside the orientation interval [min, max]) is None, undefined, when the
    interval is a point: a target whose projected area does not depend on its orientation (a sphere) has
    min = max, and "the truth lies in a point" would always be false; no blob counts as outside."""
    row = {"range_error_m": None, "abs_error_m": None, "rel_error": None, "within_min_max": None}
    if truth_m is None:
        return row
    row["within_min_max"] = False
    if found and range_m is not None:
        e = range_m - truth_m
        degenerate = range_min_m is None or range_max_m is None or range_max_m - range_min_m <= 1e-9 * abs(range_m)
        row.update(range_error_m=e, abs_error_m=abs(e), rel_error=abs(e) / truth_m,
                   within_min_max=None if degenerate else bool(range_min_m <= truth_m <= range_max_m))
    return row
