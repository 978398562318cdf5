"""Unknown objects of a solved star frame: detections that no catalog star explains (issue 23, point 3).

After the attitude solve, a detection is a star when it was identified (it voted and was accepted) or when a
catalog star, down to a deeper magnitude than the vote used (``deep_mag_limit``), projects through the solved
attitude within ``match_k_sigma`` standard deviations of it and is not much fainter than it looks
(``V_cat <= m + mag_window``: a V 11 star does not explain a V 5 light beside it).  The standard deviation of a
detection's position is ``hypot(sigma_px, sigma_sys_px)``: its centroid's own (the detector's Cramér-Rao bound)
and the solved frame's systematic residual (the identified stars' RMS residual, in px: lens distortion the camera
model does not hold, the attitude's error), with a floor radius ``match_floor_px``.

What is left is unknown: satellites, planets, asteroids, hot pixels the detector kept, stars the catalog lacks.
Each gets its ICRS direction through the solved attitude (``nav/target_bearing.inertial_bearing``: u_I = A^T u_c,
with the covariance of the centroid and the attitude) and a magnitude on the catalog's scale from the frame's
zero point (``nav/photometric_zero_point.py``).  A catalog complete only to some depth (Hipparcos: V ~ 7.3-9)
cannot explain the fainter stars it lacks, so objects fainter than ``mag_limit`` are counted, not listed.

Units: px, rad, mag.  Pure numpy (flight algorithm).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np
from pydantic import Field

from dualsight.config import check_fields
from dualsight.nav.photometric_zero_point import magnitude
from dualsight.nav.target_bearing import inertial_bearing
from dualsight.scene.attitude import unit_to_radec

__all__ = ["UnknownConfig", "UnknownObjects", "explained_by_catalog", "unknown_objects", "match_radius_px"]


@dataclass(frozen=True)
class UnknownConfig:
    """Settings of :func:`unknown_objects` (``[unknown]`` of ``hil star``'s settings).

    enabled : list the unknown objects (default True).
    mag_limit : list only objects at least this bright (catalog V scale), in [-30, 30]; None = every one.  Default
        7.0: Hipparcos is complete to V ~ 7.3, and a red star looks brighter than its V to an unfiltered silicon
        sensor, so fainter unmatched detections are mostly stars the catalog lacks (counted, not listed).
    deep_mag_limit : depth (V) of the catalog that explains detections, in [-2, 12] (12: all of Hipparcos).
    match_k_sigma : a catalog star explains a detection within this many position sigmas, in [0, 100].
    match_floor_px : and always within this radius (px), in [0, 1000].
    mag_window : a catalog star explains a detection only when V_cat <= m + mag_window (mag), in [0, 30].  Default
        3.0: HIP 96580 (V 9.0, a red star) looks like V 6.7 to the ESA frames' unfiltered sensor, 0.09 px from its
        catalog place.
    """

    enabled: bool = True
    mag_limit: Annotated[float, Field(ge=-30.0, le=30.0)] | None = 7.0
    deep_mag_limit: Annotated[float, Field(ge=-2.0, le=12.0)] = 12.0
    match_k_sigma: Annotated[float, Field(ge=0.0, le=100.0)] = 5.0
    match_floor_px: Annotated[float, Field(ge=0.0, le=1000.0)] = 1.0
    mag_window: Annotated[float, Field(ge=0.0, le=30.0)] = 3.0

    def __post_init__(self):
        check_fields(self, units={"mag_limit": "mag", "deep_mag_limit": "mag", "match_floor_px": "px",
                                  "mag_window": "mag"})


@dataclass(frozen=True)
class UnknownObjects:
    """The unknown objects of one frame, brightest first (U of them).

    index (U,) detection index in the frame; listed (U,) bool at least ``mag_limit`` bright; mag (U,) catalog-V
    scale (NaN without a zero point); ra_rad, dec_rad (U,) ICRS; sigma_rad (U,) 1-sigma per axis of the direction
    (sqrt(trace(cov) / 2)); nearest_row (U,) deep-catalog row of the nearest catalog star in the image (-1: none),
    nearest_sep_px (U,) its distance (px)."""

    index: np.ndarray
    listed: np.ndarray
    mag: np.ndarray
    ra_rad: np.ndarray
    dec_rad: np.ndarray
    sigma_rad: np.ndarray
    nearest_row: np.ndarray
    nearest_sep_px: np.ndarray


def match_radius_px(sigma_px, sigma_sys_px: float, cfg: UnknownConfig) -> np.ndarray:
    """(K,) radius (px) within which a catalog star explains each detection:
    ``max(match_k_sigma * hypot(sigma_px, sigma_sys_px), match_floor_px)`` (``sigma_px`` NaN counts as 0)."""
    s = np.nan_to_num(np.asarray(sigma_px, np.float64), nan=0.0)
    return np.maximum(cfg.match_k_sigma * np.hypot(s, sigma_sys_px), cfg.match_floor_px)


def explained_by_catalog(xy: np.ndarray, mag: np.ndarray, radius_px: np.ndarray, cat_xy: np.ndarray,
                         cat_vmag: np.ndarray, mag_window: float):
    """Which detections a catalog star explains, and the nearest catalog star of the others.

    xy (K, 2) px; mag (K,) (NaN: any catalog star within the radius explains it); radius_px (K,); cat_xy (M, 2)
    projected catalog stars; cat_vmag (M,).  Returns (explained (K,) bool, nearest (K,) int64 row of ``cat_xy`` for
    the detections no star explains (-1 for the explained ones, and when M = 0), its distance (K,) px (inf where
    nearest is -1)).

    A star explains a detection when it lies within the detection's radius and is not ``mag_window`` fainter.  Only
    the stars whose column lies within the radius are compared (the catalog sorted by column once, each detection's
    range by a binary search: ~K M (2 r / W) pairs instead of K M); the nearest star of each unexplained detection
    (a few per frame) by a full comparison."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    K, M = len(xy), len(cat_xy)
    explained = np.zeros(K, bool)
    nearest = np.full(K, -1, np.int64)
    dist = np.full(K, np.inf)
    if M == 0:
        return explained, nearest, dist
    cxy = np.asarray(cat_xy, np.float64).reshape(-1, 2)
    cv = np.asarray(cat_vmag, np.float64)
    m = np.asarray(mag, np.float64)
    r = np.broadcast_to(np.asarray(radius_px, np.float64), (K,))
    order = np.argsort(cxy[:, 0], kind="stable")
    cx_sorted = cxy[order, 0]
    lo = np.searchsorted(cx_sorted, xy[:, 0] - r, side="left")
    hi = np.searchsorted(cx_sorted, xy[:, 0] + r, side="right")
    n = hi - lo
    det = np.repeat(np.arange(K), n)                                   # candidate pairs (detection, star)
    star = order[np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n) + np.repeat(lo, n)]
    d = np.hypot(xy[det, 0] - cxy[star, 0], xy[det, 1] - cxy[star, 1])
    bright_enough = ~(cv[star] > (m[det] + mag_window))                 # NaN magnitude: any star
    explained[det[(d <= r[det]) & bright_enough]] = True
    u = np.flatnonzero(~explained)
    if u.size:
        du = np.hypot(xy[u, None, 0] - cxy[None, :, 0], xy[u, None, 1] - cxy[None, :, 1])
        j = np.argmin(du, axis=1)
        nearest[u], dist[u] = j, du[np.arange(u.size), j]
    return explained, nearest, dist


def unknown_objects(xy: np.ndarray, flux: np.ndarray, sigma_px: np.ndarray, identified: np.ndarray, A: np.ndarray,
                    att_cov: np.ndarray, camera, cat_xy: np.ndarray, cat_vmag: np.ndarray, zp_mag: float,
                    sigma_sys_px: float, cfg: UnknownConfig, centroid_floor_px: float = 0.0) -> UnknownObjects:
    """The unknown objects of one solved frame (module docstring).

    xy (K, 2) detections (col, row) px, brightest first; flux (K,) ADU; sigma_px (K,) centroid 1-sigma per axis
    (px; NaN: unknown, ``sigma_sys_px`` alone); identified (K,) bool; A (3, 3) solved attitude (ICRS -> camera);
    att_cov (3, 3) its error covariance (rad^2, camera frame; ``nav/target_bearing.attitude_covariance``); camera:
    ``scene.camera.Camera``; cat_xy (M, 2), cat_vmag (M,) the deep catalog's stars projected into the image by A
    (``scene.starfield_geometry.catalog_in_image``); zp_mag: the frame's zero point; sigma_sys_px: the frame's
    systematic position error (px); centroid_floor_px: added in quadrature to each centroid's sigma in the
    direction's covariance."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    sig = np.asarray(sigma_px, np.float64)
    mag = magnitude(flux, zp_mag)
    cand = np.flatnonzero(~np.asarray(identified, bool))
    expl, near, dist = explained_by_catalog(xy[cand], mag[cand], match_radius_px(sig[cand], sigma_sys_px, cfg),
                                            cat_xy, cat_vmag, cfg.mag_window)
    k = cand[~expl]
    near, dist = near[~expl], dist[~expl]
    listed = np.ones(len(k), bool) if cfg.mag_limit is None else ~(mag[k] > cfg.mag_limit)
    U = len(k)
    if U:
        s_c = np.hypot(np.nan_to_num(sig[k], nan=0.0), centroid_floor_px)
        u, C = inertial_bearing(np.broadcast_to(A, (U, 3, 3)), np.broadcast_to(att_cov, (U, 3, 3)), xy[k], s_c,
                                camera)
        ra, dec = unit_to_radec(u)
        sigma = np.sqrt(np.maximum(np.trace(C, axis1=1, axis2=2), 0.0) / 2)
    else:
        ra = dec = sigma = np.zeros(0)
    return UnknownObjects(k.astype(np.int64), listed, mag[k], np.asarray(ra, np.float64), np.asarray(dec, np.float64),
                          sigma, near, np.where(np.isfinite(dist), dist, np.nan))
