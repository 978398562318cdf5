"""What the camera measures over one rendezvous approach (:mod:`dualsight.jobs.kinds.rendezvous`): star camera
(stars and target in one frame, identification, attitude, the target's candidates and inertial bearings) or
proximity camera (the blobber's centre of brightness and range), and the range model the filter takes."""

from __future__ import annotations

import time

import numpy as np

from dualsight.scene.target_config import TargetConfig
from dualsight.jobs.kinds import star, star_target
from dualsight.kernels.digest import frame_digest, to_int64
from dualsight.kernels.sensor_config import flux_from_magnitude
from dualsight.nav.attitude import solve_identified
from dualsight.nav.blob_centre_error import CENTRE_SIGMA_FLOOR_PX
from dualsight.nav.blobber import run_blobber
from dualsight.nav.blobber_range_error import range_ratio_at
from dualsight.nav.observations import observations
from dualsight.nav.resolved_blobs import excluded_blobs, without_excluded
from dualsight.nav.star_solution import centroid_weights, identify, solve
from dualsight.nav.target_finding import repeats, unmatched
from dualsight.nav.target_bearing import (BLOB_SIGMA_FRAC_BY_DETECTOR, attitude_covariance, bearing_error,
                                          blob_centroid_sigma, centroid_cov_icrs, inertial_bearing,
                                          point_centroid_sigma)
from dualsight.scene.motion import place_body
from dualsight.scene.rotation_vector import frame_rotation
from dualsight.scene.starfield_geometry import stars_in_field
from dualsight.scene.target_in_field import diameter_px, target_frames, with_target
from dualsight.scene.units import ARCSEC
from dualsight.jobs.kinds.rendezvous_spec import RendezvousSpec
from dualsight.jobs.kinds.rendezvous_context import BLOBBER, PROX_CHUNK, STAR_CHUNK, RendezvousContext, touches_edge


MATCH_TOL_PX = 2.0
"""A detection within this many pixels' angle of a catalog star (through the frame's attitude) is that star."""

FIXED_SKY_TOL_PX = 2.0
"""An unmatched detection recurring within this many pixels' angle in ICRS in another frame is fixed on the sky."""

FIXED_PIXEL_TOL_PX = 1.5
"""An unmatched detection recurring within this many pixels in two other frames is fixed on the detector."""

RANGE_FLOOR_FRAC = 0.005
"""Smallest 1-sigma of a blobber range given to the filter, as a fraction of the range (a [min, max] of zero width
would be an exact range)."""


def _empty_meas(T: int) -> dict:
    nan = np.full(T, np.nan)
    return {"attitude": np.zeros(T, np.int8), "n_stars": np.zeros(T, np.int64), "in_field": np.zeros(T, bool),
            "detected": np.zeros(T, bool), "resolved": np.zeros(T, bool), "pixels": np.full(T, -1, np.int64),
            "vmag": nan.copy(), "phase": nan.copy(), "u": np.full((T, 3), np.nan), "C": np.zeros((T, 3, 3)),
            "bearing_used": np.zeros(T, bool), "bearing_err": nan.copy(), "bearing_sigma": nan.copy(),
            "range": nan.copy(), "range_min": nan.copy(), "range_max": nan.copy(), "range_used": np.zeros(T, bool),
            "range_sigma": nan.copy(), "digest": np.zeros(T, np.int64), "t_render_ns": np.zeros(T, np.int64),
            "u_used": np.full((T, 3), np.nan), "C_used": np.zeros((T, 3, 3)), "bearing_raw_err": nan.copy(),
            "target_xy": np.full((T, 2), np.nan), "found_by": np.zeros(T, np.int8), "found_true": np.zeros(T, bool),
            "axis_ratio": nan.copy(), "range_filter": nan.copy(), "cand": None, "n_blob": nan.copy(), "range_sigma_frac": nan.copy(),
            "cut": np.zeros(T, bool), "centre_cov": np.zeros((T, 3, 3))}


def _candidates(frame, u, C, xy, true) -> dict:
    """The target candidates of a sequence: frame (K,), ICRS lines of sight u (K, 3) and covariances C (K, 3, 3),
    pixel positions xy (K, 2), and whether each is the true target's detection (``true`` (K,), for scoring only)."""
    return {"frame": np.asarray(frame, np.int64), "u": np.asarray(u, np.float64).reshape(-1, 3),
            "C": np.asarray(C, np.float64).reshape(-1, 3, 3), "xy": np.asarray(xy, np.float64).reshape(-1, 2),
            "true": np.asarray(true, bool)}


def measure_star(spec: RendezvousSpec, ctx: RendezvousContext, draw: dict, geo: dict, keep_images: bool = False):
    """Star camera: stars and target in one frame, detection, identification, attitude, the target's bearing.
    Returns (measurements dict, images (T, H, W) or None)."""
    sp, sc = spec.star, ctx.star
    cat = sc.catalog
    tc = geo["targets"]
    T = len(tc.range_m)
    m = _empty_meas(T)
    m["phase"] = tc.phase_rad
    m["in_field"] = tc.present.copy()
    flux = flux_from_magnitude(cat.vmag.astype(np.float64), sp.sensor)
    A_true = geo["A_true"]
    field_ = stars_in_field(A_true, cat.unit, flux, sp.camera, star.psf_margin_px(sp.sensor, sp.camera, sc.psf))
    tcfg = TargetConfig(satellite=spec.cfg.satellite)
    tf = target_frames(tcfg, ctx.sat, ctx.shape, tc, field_, sp.camera, sp.sensor)
    render_field, _ = with_target(field_, tf)
    m["resolved"], m["pixels"], m["vmag"] = tf.resolved.copy(), tf.pixels.copy(), tf.vmag.copy()
    voting = sp.robust if sp.robust is not None else sp.voting
    f = max(sp.camera.fx, sp.camera.fy)
    images = [] if keep_images else None
    parts = []
    A_all = np.tile(np.eye(3), (T, 1, 1))
    bs = min(sp.batch_size, STAR_CHUNK)
    for s in range(0, T, bs):
        fr = np.arange(s, min(T, s + bs))
        sub = _take_field(render_field, fr)
        # full frames always (keep_images=True): the sparse path renders windows sized for stars, which would cut
        # the wings of a target brighter than any star (and the replay re-renders whole frames)
        r = star.render_and_detect(sub, draw["noise_seeds"][fr], sp.camera, sp.sensor, sp.detect,
                                   keep_images=True, attitude=A_true[fr], detector=sp.detector, psf=sc.psf)
        if keep_images:
            images.append(r.images)
        m["t_render_ns"][fr] = (r.t_render_ns + (r.t_detect_ns or 0)) // len(fr)
        m["digest"][fr] = to_int64(r.digest)
        det = r.detections
        obs = observations(det, len(fr), sp.camera)
        obs = without_excluded(obs, det.case, det.offsets, excluded_blobs(det.npix, sc.star_blob_limit))
        ident = identify(obs, cat.unit, sc.index, voting, cat_vmag=cat.vmag)
        sol = solve(obs, ident, cat.unit, A_true[fr], sp.error_frame, weights=centroid_weights(det, obs, 0.02))
        used = ident.accepted & (ident.ids >= 0) & obs.valid
        n_used = used.sum(1)
        _, ok, cov_unit = solve_identified(obs.vec, ident.ids, used, cat.unit, return_cov=True)
        att_ok = ok & sol.ok
        s2 = attitude_covariance(np.ones((len(fr), 1, 1)), sol.residual, n_used,
                                 floor_rad=float(np.min(ctx.centroid.sigma_px)) / f)[:, 0, 0]
        P_att = np.where(att_ok[:, None, None], cov_unit, 0.0) * s2[:, None, None]
        # every detection of a frame with an attitude is a candidate until the catalog and its motion say
        # otherwise (nav/target_finding.py); the truth only scores the pick afterwards (target_detection)
        kt = star_target.target_detection(det, _take_tf(tf, fr))
        case = np.asarray(det.case, np.int64)
        kk = np.flatnonzero(att_ok[case])
        cl = case[kk]
        npix = np.asarray(det.npix)[kk]
        resolved = npix > sc.star_blob_limit
        # a blob a star could make: the camera's own centroid error at its measured flux (pixel phase, saturation,
        # noise: point_centroid_calibration); a larger one: the star's scatter plus the partly lit, saturated
        # body's share of its size (nav/target_bearing.blob_centroid_sigma, the spec's detector's fraction)
        sig_pt = point_centroid_sigma(np.asarray(det.flux)[kk], ctx.centroid)
        sig_res = blob_centroid_sigma(npix, np.sqrt(s2)[cl] * f, True,
                                      frac_resolved=BLOB_SIGMA_FRAC_BY_DETECTOR[sp.detector][1])
        sig_px = np.where(resolved, sig_res, sig_pt)
        xy = np.stack([det.x[kk], det.y[kk]], -1)
        u, C = inertial_bearing(sol.A_est[cl], P_att[cl], xy, sig_px, sp.camera)
        parts.append((fr[cl], u, C, xy, kk == kt[cl]))
        A_all[fr[att_ok]] = sol.A_est[att_ok]
        m["attitude"][fr] = np.where(att_ok, 1, 0)
        m["n_stars"][fr] = np.where(att_ok, n_used, 0)
        m["detected"][fr] = kt >= 0
    cand = _candidates(*(np.concatenate([p[i] for p in parts]) for i in range(5)))
    pix = 1.0 / f
    keep = unmatched(cand["frame"], cand["u"], A_all[:, 2, :], cat.unit, MATCH_TOL_PX * pix,
                     0.5 * sp.camera.fov_rad[2])
    keep &= ~repeats(cand["frame"], cand["u"], FIXED_SKY_TOL_PX * pix, min_frames=2)
    keep &= ~repeats(cand["frame"], cand["xy"], FIXED_PIXEL_TOL_PX, min_frames=3)
    m["cand"] = {k: v[keep] for k, v in cand.items()}
    return m, (np.concatenate(images) if keep_images else None)


def _take_field(f, idx):
    return type(f)(*(getattr(f, k)[idx] for k in f.__dataclass_fields__))


def _take_tf(tf, idx):
    return type(tf)(*(getattr(tf, k)[idx] for k in tf.__dataclass_fields__))


def bearing_scores(m: dict, geo: dict) -> None:
    """Fill the errors against the true direction to the body origin of the measured (``bearing_raw_err``) and the
    used bearing (after the filter's adjustment), and the used one's stated 1-sigma per axis, where a bearing was
    used."""
    ok = m["bearing_used"]
    if ok.any():
        m["bearing_raw_err"][ok] = bearing_error(m["u"][ok], geo["u_true"][ok])
        m["bearing_err"][ok] = bearing_error(m["u_used"][ok], geo["u_true"][ok])
        m["bearing_sigma"][ok] = np.sqrt(np.trace(m["C_used"][ok], axis1=1, axis2=2) / 2)


def measure_prox(spec: RendezvousSpec, ctx: RendezvousContext, draw: dict, geo: dict, keep_images: bool = False):
    """Proximity camera: the target rendered alone (exact coverage), the blobber's centre of brightness (or, with
    ``bearing_point`` "silhouette", its silhouette centre and that centre's calibrated spread,
    ``nav/blob_centre_error.py``) and range, the bearing through the chaser's star-tracker attitude (truth +
    ``attitude_err``).  Returns (measurements,
    images (T, H, W) or None)."""
    from dualsight.kernels.points import render              # Taichi

    c = spec.cfg
    cam = spec.camera
    tc = geo["targets"]
    T = len(tc.range_m)
    m = _empty_meas(T)
    m["phase"], m["in_field"] = tc.phase_rad, tc.present.copy()
    m["attitude"][:] = 2
    light = ctx.sat.camera
    bcfg = BLOBBER
    A_true = geo["A_true"]
    A_est = frame_rotation(draw["attitude_err"]) @ A_true
    sa = c.attitude_sigma_arcsec * ARCSEC
    diam = diameter_px(ctx.shape.bounding_radius, tc.range_m, cam)
    m["resolved"] = tc.present & (diam >= 3.0)
    images = [] if keep_images else None
    for s in range(0, T, PROX_CHUNK):
        fr = np.arange(s, min(T, s + PROX_CHUNK))
        t0 = time.perf_counter_ns()
        poses = place_body(ctx.sat, tc.R_body[fr], tc.pos_cam[fr], tc.sun_cam[fr])
        img, cov = render("accurate", ctx.mesh, ctx.materials, poses.R, poses.t, poses.light, cam, light.I_a,
                          light.I_l)
        img = np.where(tc.present[fr, None, None], img, np.float32(0.0))
        cov = np.where(tc.present[fr, None, None], cov, np.float32(0.0))
        m["t_render_ns"][fr] = (time.perf_counter_ns() - t0) // len(fr)
        m["digest"][fr] = to_int64(frame_digest(img))
        if keep_images:
            images.append(img)
        b = run_blobber(img, cam, ctx.table, bcfg, coverage=cov)
        found = b.found & tc.present[fr]
        m["detected"][fr] = found
        m["pixels"][fr] = np.where(found, np.nan_to_num(b.n_pixels), -1).astype(np.int64)
        point = b.centre_px if c.bearing_point == "silhouette" else b.cob_px
        xy = np.where(found[:, None], point, 0.5 * np.array([cam.width, cam.height]))
        m["target_xy"][fr] = np.where(found[:, None], xy, np.nan)
        sig_px = np.full(len(fr), star_target.CENTROID_FLOOR_PX)
        if c.bearing_point == "silhouette":      # the silhouette centre's spread at the blob's coverage and shape
            sig_px[:] = CENTRE_SIGMA_FLOOR_PX    # (the filter adds it with its gains: rendezvous_filter.silhouette_cov)
            cpx = ctx.centre_calibration.cov_px(np.where(found, b.n_coverage, np.nan), b.axis_ratio,
                                                 b.angle_rad)                             # along the blob's axes
            ok_c = found & np.isfinite(cpx).all((1, 2))
            m["centre_cov"][fr] = np.where(ok_c[:, None, None], centroid_cov_icrs(
                A_est[fr], xy, np.where(ok_c[:, None, None], cpx, 0.0), cam), 0.0)
        u, C = inertial_bearing(A_est[fr], np.broadcast_to(sa ** 2 * np.eye(3), (len(fr), 3, 3)), xy, sig_px, cam)
        m["u"][fr] = np.where(found[:, None], u, np.nan)        # the candidates (the one blob), picked by the gate
        m["C"][fr] = np.where(found[:, None, None], C, 0.0)
        rok = found & m["resolved"][fr] & np.isfinite(b.range_est) & (b.range_est > 0)
        m["range"][fr] = np.where(rok, b.range_est, np.nan)
        m["range_min"][fr] = np.where(rok, b.range_min, np.nan)
        m["range_max"][fr] = np.where(rok, b.range_max, np.nan)
        m["axis_ratio"][fr] = np.where(rok, b.axis_ratio, np.nan)
        m["n_blob"][fr] = np.where(rok, b.n_blob, np.nan)
        m["cut"][fr] = found & touches_edge(b.box, cam)
    # a blob the frame's edge cuts gives neither a bearing (its centre of brightness is the visible part's) nor a
    # range (its pixels are): the target is too close or off the boresight
    # (rendezvous_context.touches_edge)
    m["range"][m["cut"]] = np.nan
    k = np.flatnonzero(m["detected"] & ~m["cut"])
    m["cand"] = _candidates(k, m["u"][k], m["C"][k], m["target_xy"][k], np.ones(len(k), bool))
    m["u"][:], m["C"][:] = np.nan, 0.0
    rok = np.isfinite(m["range"]) & (c.range_source == "blobber")
    m["range_used"] = rok
    range_model(ctx, m)
    return m, (np.concatenate(images) if keep_images else None)


def range_model(ctx: RendezvousContext, m: dict) -> None:
    """The filter's blobber range (``m["range_filter"]``) and its 1-sigma (``m["range_sigma"]``) where
    ``m["range_used"]``: the blobber's known bias removed and its spread as the sigma, ``range / m_q`` and
    ``range s_q / m_q^2`` (``nav/blobber_range_error.py``), at least :data:`RANGE_FLOOR_FRAC` of the range; the
    filter takes the sigma as the fraction ``m["range_sigma_frac"]`` = s_q / m_q of its predicted range
    (``relative_filter.run``'s ``range_sig_frac``: a sigma scaled by the measured range biases the estimate short).  m_q and
    s_q are the calibration's (``ctx.range_calibration``: q's mean and spread over renders at the blob's summed
    coverage ``m["n_blob"]`` and observed axis ratio,
    :func:`~dualsight.jobs.kinds.rendezvous_context.blobber_calibration`), else the area table's
    at the observed axis ratio (``ctx.range_ratio``: exact silhouettes, no pixel sampling)."""
    rok = m["range_used"]
    if ctx.range_calibration is not None:
        mq, sq, _ = ctx.range_calibration.at(m["n_blob"], m["axis_ratio"])
    else:
        mq, sq = range_ratio_at(m["axis_ratio"], *ctx.range_ratio)
    m["range_filter"] = np.where(rok, m["range"] / mq, np.nan)
    m["range_sigma_frac"] = np.where(rok, np.maximum(sq / mq, RANGE_FLOOR_FRAC), np.nan)
    m["range_sigma"] = m["range_sigma_frac"] * m["range_filter"]
