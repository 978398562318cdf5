"""``hil star``'s unknown objects and target (issue 23, point 3): what a solved frame holds besides its catalog stars.

Per solved image (after jobs/kinds/hil_star.py's identification and attitude):

* photometric zero point from the identified, unsaturated stars (``nav/photometric_zero_point.py``);
* unknown objects: detections that no catalog star explains to V 12 (``nav/unknown_objects.py``), with ICRS
  RA/Dec through the solved attitude (covariance from the centroid and the attitude,
  ``nav/target_bearing.inertial_bearing``), pixel position, pixels and magnitude; those at least
  ``unknown.mag_limit`` bright are listed (lake dataset ``hil_star_objects``), the fainter ones counted;
* with ``--target SAT.toml``, the target (``nav/field_target.py``'s rule: the resolved blob, else the brightest
  unknown object, or the one nearest ``--target-near``): RA/Dec, pixels, 1-sigma, and for a resolved blob the
  range by Eq. 1 with the satellite's projected-area table (min / estimate / max).

Columns added to the ``hil_star`` row: ``zp_mag``, ``zp_scatter_mag``, ``zp_stars``, ``unknown_objects`` (listed),
``unknown_faint`` (unknown but fainter than the limit), ``target_*`` (``--target`` only; ``target_reason`` says why
a target is null).  Angles in radians, ranges in metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from dualsight.catalogs.stars import StarCatalogConfig, load_star_catalog
from dualsight.config import validate
from dualsight.nav.attitude import solve_identified
from dualsight.nav.blobber import BlobberConfig, run_blobber
from dualsight.nav.field_target import (FieldTarget, brightest_star_npix, pick_point_target, silhouette_axis_ratio,
                                        silhouette_pixels)
from dualsight.nav.range import range_eq1
from dualsight.nav.photometric_zero_point import MAD_TO_SIGMA, zero_point
from dualsight.nav.resolved_blobs import star_blob_limit
from dualsight.nav.target_bearing import attitude_covariance, inertial_bearing
from dualsight.nav.unknown_objects import UnknownConfig, unknown_objects
from dualsight.scene.attitude import radec_to_unit, unit_to_radec
from dualsight.scene.starfield_geometry import catalog_in_image

__all__ = ["OBJECT_COLUMNS", "OBJECTS_SCHEMA", "ObjectContext", "object_context", "frame_objects",
           "unknown_config", "stars_in_image"]

OBJECT_COLUMNS = [
    ("zp_mag", pa.float64()), ("zp_scatter_mag", pa.float64()), ("zp_stars", pa.int32()),
    ("unknown_objects", pa.int32()), ("unknown_faint", pa.int32()), ("unknown_mag_limit", pa.float64()),
    ("target", pa.string()), ("target_kind", pa.string()), ("target_reason", pa.string()),
    ("target_x_px", pa.float64()), ("target_y_px", pa.float64()),
    ("target_ra_rad", pa.float64()), ("target_dec_rad", pa.float64()), ("target_sigma_rad", pa.float64()),
    ("target_pixels", pa.int32()), ("target_mag", pa.float64()),
    ("target_range_m", pa.float64()), ("target_range_min_m", pa.float64()), ("target_range_max_m", pa.float64()),
]
"""Columns of the ``hil_star`` row (null where not applicable)."""

OBJECTS_SCHEMA = pa.schema([
    ("case_id", pa.int64()), ("image", pa.string()), ("method", pa.string()), ("det_index", pa.int32()),
    ("x_px", pa.float64()), ("y_px", pa.float64()), ("flux", pa.float64()), ("npix", pa.int32()),
    ("sigma_px", pa.float64()), ("saturated", pa.bool_()), ("mag", pa.float64()),
    ("ra_rad", pa.float64()), ("dec_rad", pa.float64()), ("sigma_rad", pa.float64()),
    ("nearest_hip", pa.int32()), ("nearest_vmag", pa.float64()), ("nearest_sep_px", pa.float64()),
    ("is_target", pa.bool_()),
])
"""``hil_star_objects``: one row per listed unknown object (and the target, listed or not)."""


@dataclass
class ObjectContext:
    """Per-process state: the unknown objects' settings, the deep catalog that explains detections, and the
    target (``jobs/kinds/hil_prox.Target``: name and projected-area table; None without ``--target``) with its
    optional ``near`` (ICRS unit vector, radius rad)."""

    cfg: UnknownConfig
    deep: object
    target: object = None
    near: tuple | None = None


def unknown_config(settings) -> UnknownConfig:
    """The ``unknown`` table of the ``hil_star`` settings as :class:`~dualsight.nav.unknown_objects.UnknownConfig`."""
    return validate(UnknownConfig, settings.unknown, source="spec", section="settings.unknown")


def object_context(settings, target=None, near=None) -> ObjectContext:
    """The context of :func:`frame_objects` for run settings (their ``unknown`` table and catalog epoch), the
    target (``hil_prox.Target`` or None) and ``near`` = (ra_deg, dec_deg, radius_deg) or None."""
    cfg = unknown_config(settings)
    deep = None
    if cfg.enabled or target is not None:
        deep = load_star_catalog(StarCatalogConfig(mag_limit=cfg.deep_mag_limit,
                                                   epoch_jyear=float(settings.catalog["epoch_jyear"])))
    nr = None
    if near is not None:
        nr = (radec_to_unit(math.radians(near[0]), math.radians(near[1])), math.radians(near[2]))
    return ObjectContext(cfg, deep, target, nr)


def stars_in_image(A: np.ndarray, cat_unit: np.ndarray, camera) -> tuple[np.ndarray, np.ndarray]:
    """``scene.starfield_geometry.catalog_in_image`` (xy (M, 2) px, catalog rows (M,)) of the stars in a cone around
    the boresight A[2] (the image's half-diagonal + 0.01 rad) only: projecting all 117k Hipparcos stars costs ~70 ms
    a frame, the cone's dot products ~1 ms."""
    corners = camera.backproject(np.array([[0.0, 0.0], [camera.width, 0.0], [0.0, camera.height],
                                           [camera.width, camera.height]], np.float64))
    cos_cone = math.cos(min(math.pi, float(np.arccos(np.clip(corners[:, 2], -1, 1)).max()) + 0.01))
    cone = np.flatnonzero(cat_unit @ np.asarray(A, np.float64)[2] >= cos_cone)
    xy, rows = catalog_in_image(A, cat_unit[cone], camera)
    return xy, cone[rows]


def _null_target(reason: str, name: str | None) -> dict:
    return {"target": name, "target_kind": None, "target_reason": reason}


def frame_objects(res, b: int, det, obs, ident, sol, cat_unit: np.ndarray, camera, settings, octx: ObjectContext,
                  residual: np.ndarray | None = None, frame: np.ndarray | None = None) -> list[dict]:
    """Fill ``res.row`` (an ``ImageResult`` of jobs/kinds/hil_star.py whose stars are filled) with the zero point,
    unknown-object and target columns of frame ``b`` of the batch; return its ``hil_star_objects`` rows.

    det, obs, ident, sol : the batch's detections, observations, identification and solution; cat_unit : (N, 3)
    the vote catalog's unit vectors (their ids); residual : (H, W) background-subtracted frame and frame : (H, W)
    the frame as read (ADU; its saturated pixels), both needed for a resolved target."""
    r = res.row
    cfg = octx.cfg
    name = octx.target.name if octx.target is not None else None
    r["unknown_mag_limit"] = cfg.mag_limit
    if not r.get("identified"):
        if octx.target is not None:
            r.update(_null_target("the frame has no attitude (not identified)", name))
        return []
    s0, s1 = int(det.offsets[b]), int(det.offsets[b + 1])
    K = s1 - s0
    xy = np.stack([det.x[s0:s1], det.y[s0:s1]], 1)
    flux = np.asarray(det.flux[s0:s1], np.float64)
    sig = (np.asarray(det.sigma_px[s0:s1], np.float64) if det.sigma_px is not None else np.full(K, np.nan))
    sat = np.asarray(det.saturated[s0:s1], bool) if det.saturated is not None else np.zeros(K, bool)
    identified = np.zeros(K, bool)
    identified[[s.det_index for s in res.stars if s.det_index < K]] = True
    zp = zero_point([s.flux for s in res.stars], [s.vmag for s in res.stars],
                    [not s.saturated for s in res.stars])
    r.update(zp_mag=zp.zp_mag if zp.n else None, zp_scatter_mag=zp.scatter_mag if zp.n >= 2 else None,
             zp_stars=zp.n)
    A = np.asarray(sol.A_est[b], np.float64)
    acc = ident.accepted[b] & (ident.ids[b] >= 0) & obs.valid[b]
    f = max(camera.fx, camera.fy)
    floor = settings.centroid_floor_px or 0.0
    _, ok, cov_unit = solve_identified(obs.vec[b:b + 1], ident.ids[b:b + 1], acc[None], cat_unit, return_cov=True)
    resid = np.where(acc, sol.residual[b], np.nan)[None]
    P = attitude_covariance(cov_unit, resid, acc.sum()[None], floor_rad=floor / f)[0] if ok[0] else np.zeros((3, 3))
    sigma_sys = float(r.get("residual_rms_rad") or 0.0) * f
    cat_xy, rows = stars_in_image(A, octx.deep.unit, camera)
    unk = unknown_objects(xy, flux, sig, identified, A, P, camera, cat_xy, octx.deep.vmag[rows],
                          zp.zp_mag if zp.n else float("nan"), sigma_sys, cfg, centroid_floor_px=floor)
    listed = unk.listed if cfg.enabled else np.zeros(len(unk.index), bool)
    r.update(unknown_objects=int(listed.sum()) if cfg.enabled else None,
             unknown_faint=int((~unk.listed).sum()) if cfg.enabled else None)
    t_row = -1
    if octx.target is not None:
        tgt = _choose_target(unk, flux, xy, sig, sat, np.asarray(det.npix[s0:s1]), camera, r, zp, residual, frame,
                             settings, octx)
        t_row = tgt.index
        r.update(_target_columns(tgt, A, P, camera, floor, name, unk, det.npix[s0:s1]))
    out = []
    for j in np.flatnonzero(listed | (np.arange(len(unk.index)) == t_row)):
        k = int(unk.index[j])
        nr = int(unk.nearest_row[j])
        out.append({"case_id": r["case_id"], "image": r["image"], "method": r["method"], "det_index": k,
                    "x_px": float(xy[k, 0]), "y_px": float(xy[k, 1]), "flux": float(flux[k]),
                    "npix": int(det.npix[s0 + k]), "sigma_px": None if not np.isfinite(sig[k]) else float(sig[k]),
                    "saturated": bool(sat[k]), "mag": None if not np.isfinite(unk.mag[j]) else float(unk.mag[j]),
                    "ra_rad": float(unk.ra_rad[j]), "dec_rad": float(unk.dec_rad[j]),
                    "sigma_rad": float(unk.sigma_rad[j]),
                    "nearest_hip": int(octx.deep.hip[rows[nr]]) if nr >= 0 else None,
                    "nearest_vmag": float(octx.deep.vmag[rows[nr]]) if nr >= 0 else None,
                    "nearest_sep_px": float(unk.nearest_sep_px[j]) if nr >= 0 else None,
                    "is_target": bool(j == t_row)})
    return out


CENTROID_SIZE_FRACTION = 0.25
"""1-sigma per axis of a resolved blob's centroid against the target's centre of brightness, as a fraction of the
blob's RMS radius: a saturated blob shows its silhouette, not its shading (a Lambertian sphere's photocentre is up
to 0.42 R off its centre at 90 deg phase, scene/target_photometry.py)."""


REACH_UNCERTAINTY_PX = 0.5
"""Uncertainty (px) of the blur's reach d(t) of a resolved blob (nav/field_target.py): its two contours are each
whole pixels, so the rim's width between them is known to about half a pixel; the range's min and max cover it."""
PLATEAU_MIN_PX = 4
"""Fewest pixels at a blob's highest raw value that make it a saturated plateau."""


def _choose_target(unk, flux, xy, sig, sat, npix, camera, row, zp, residual, frame, settings, octx: ObjectContext
                   ) -> FieldTarget:
    """The frame's target by ``nav/field_target.py``'s rule: a resolved blob, else a point-like unknown object."""
    if residual is not None and zp.n:
        from dualsight.kernels.blobs import label_blobs          # Taichi-free numpy labeller of the blobber

        noise = float(MAD_TO_SIGMA * np.median(np.abs(residual - np.median(residual))))
        k = float(settings.detect_local.get("k_sigma", 5.0) if settings.detector == "local"
                  else settings.detect.get("k_sigma", 5.0))
        t = max(k * noise, 1e-9)
        psf = row.get("psf_sigma_px") or float(settings.detect_local.get("psf_sigma_init_px", 1.0))
        limit = star_blob_limit([brightest_star_npix(zp.zp_mag, psf, t)])
        res32 = np.asarray(residual, np.float32)[None]
        blob = run_blobber(res32, camera, octx.target.table, BlobberConfig(threshold=t))
        n = int(blob.n_pixels[0])
        if bool(blob.found[0]) and n > limit:
            mask = label_blobs(res32, t, return_mask=True)["mask"][0]
            edges = (np.count_nonzero(mask[:, 1:] != mask[:, :-1]) + np.count_nonzero(mask[1:] != mask[:-1])
                     + np.count_nonzero(mask[:, [0, -1]]) + np.count_nonzero(mask[[0, -1]]))
            perim = edges * math.pi / 4                      # a digital outline's edges: 4/pi x its length
            # saturated plateau: pixels within k_sigma noise of the blob's highest raw value, when at least
            # PLATEAU_MIN_PX (a sensor clips at its full well or its ADC's top code, with read noise after the well)
            top = float(frame[mask].max()) if frame is not None else float("inf")
            n_sat = int(np.count_nonzero(frame[mask] >= top - k * noise)) if frame is not None else 0
            n_sat = n_sat if n_sat >= PLATEAU_MIN_PX else 0
            level = float(np.median((top - (frame - residual))[mask])) if n_sat else float("nan")
            peak = float(np.percentile(residual[mask], 95))
            s_edge = math.hypot(psf, math.sqrt(1 / 12))          # the PSF integrated over a pixel
            _, d, _ = silhouette_pixels(n, perim, n_sat, t, level, s_edge, None if n_sat else peak)
            l1, l2 = np.linalg.eigvalsh(blob.cov_px[0])[::-1]
            tab = octx.target.table
            f, p = camera.focal_length_m, camera.pixel_pitch_m
            # the estimate at d; min and max over the area table's band and over d +- REACH_UNCERTAINTY_PX
            est, lo, hi = [], [], []
            for dd in (d, d - REACH_UNCERTAINTY_PX, d + REACH_UNCERTAINTY_PX):
                npx = np.array([max(1.0, n - perim * dd + math.pi * dd * dd)])
                ratio = np.array([silhouette_axis_ratio(float(l1), float(l2), dd)])
                if dd == d:
                    est.append(float(range_eq1(npx, tab.lookup(ratio, "mean") * tab.A0_m2, f, p)[0]))
                lo.append(float(range_eq1(npx, tab.lookup(ratio, "min") * tab.A0_m2, f, p)[0]))
                hi.append(float(range_eq1(npx, tab.lookup(ratio, "max") * tab.A0_m2, f, p)[0]))
            rng = [min(lo), est[0], max(hi)]
            s_px = CENTROID_SIZE_FRACTION * math.sqrt(max(float(l1 + l2) / 2, 0.0))
            return FieldTarget("resolved", xy=(float(blob.cob_px[0, 0]), float(blob.cob_px[0, 1])), pixels=n,
                               sigma_px=s_px, range_m=rng[1], range_min_m=rng[0], range_max_m=rng[2])
    cand = np.flatnonzero(unk.listed)                # a point target is a listed unknown object
    dec, ra = unk.dec_rad[cand], unk.ra_rad[cand]
    u = np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], -1)
    near_u, rad = octx.near if octx.near is not None else (None, None)
    j, reason = pick_point_target(u, flux[unk.index[cand]], near_u, rad)
    if j < 0:
        if octx.cfg.mag_limit is not None and reason is not None:
            reason += f" at least V {octx.cfg.mag_limit:g} bright (settings unknown.mag_limit)"
        return FieldTarget(None, reason=reason)
    j = int(cand[j])
    k = int(unk.index[j])
    s_px = float(sig[k])
    if sat is not None and sat[k]:          # a saturated point: fitted on its rim, its sigma understated
        s_px = math.hypot(s_px, CENTROID_SIZE_FRACTION * 0.5 * math.sqrt(npix[k] / math.pi))
    return FieldTarget("point", xy=(float(xy[k, 0]), float(xy[k, 1])), pixels=None, sigma_px=s_px, index=j)


def _target_columns(tgt: FieldTarget, A, P, camera, floor: float, name, unk, det_npix) -> dict:
    """The ``target_*`` columns of a chosen target (its bearing through ``inertial_bearing``)."""
    if tgt.kind is None:
        return _null_target(tgt.reason, name)
    s = math.hypot(tgt.sigma_px if tgt.sigma_px is not None and math.isfinite(tgt.sigma_px) else 0.0, floor)
    u, C = inertial_bearing(A[None], P[None], np.array([tgt.xy]), s, camera)
    ra, dec = unit_to_radec(u[0])
    out = {"target": name, "target_kind": tgt.kind, "target_reason": None, "target_x_px": tgt.xy[0],
           "target_y_px": tgt.xy[1], "target_ra_rad": float(ra), "target_dec_rad": float(dec),
           "target_sigma_rad": float(math.sqrt(max(np.trace(C[0]) / 2, 0.0)))}
    if tgt.kind == "point":
        k = int(unk.index[tgt.index])
        m = unk.mag[tgt.index]
        out.update(target_pixels=int(det_npix[k]), target_mag=float(m) if np.isfinite(m) else None)
    else:
        out.update(target_pixels=tgt.pixels, target_range_m=_fin(tgt.range_m), target_range_min_m=_fin(tgt.range_min_m),
                   target_range_max_m=_fin(tgt.range_max_m))
    return out


def _fin(v):
    return float(v) if v is not None and math.isfinite(v) else None
