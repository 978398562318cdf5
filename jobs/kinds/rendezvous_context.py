"""Per-process state of the rendezvous job (:mod:`dualsight.jobs.kinds.rendezvous`): the target's satellite
file and photometric shape, the star job's context or the proximity renderer's mesh, and the two ground
calibrations through the camera's own renderer and detector: the point target's centroid error against its flux
(star camera) and the blobber's range and silhouette centre against the truth (proximity camera; cached on disk by
content, :func:`cached_blobber_calibration`)."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace

import numpy as np

from dualsight.catalogs.cache import resolve_cache_dir, short_hash
from dualsight.jobs.kinds import star
from dualsight.nav.blob_centre_error import CentreErrorCalibration, sequence_gain
from dualsight.nav.blobber import BlobberConfig, run_blobber
from dualsight.nav.blobber_range_error import RangeRatioCalibration, range_ratio_statistics
from dualsight.nav.target_bearing import PointCentroidTable, point_centroid_table
from dualsight.scene.attitude import quat_to_dcm, quaternions_from_uniforms
from dualsight.scene.camera import Camera
from dualsight.scene.motion import place_body
from dualsight.scene.rotation_vector import frame_rotation
from dualsight.scene.photocentre_bias import (PhotocentreStatistics, facet_materials, photocentre_statistics,
                                              shaded_photocentre_offset)
from dualsight.scene.satellite import load_satellite
from dualsight.scene.starfield_geometry import FieldStars
from dualsight.scene.target_photometry import photocentre_table, target_shape
from dualsight.scene.units import DEG
from dualsight.jobs.kinds.rendezvous_spec import RendezvousSpec


STAR_CHUNK = 16
"""Star-camera frames rendered per call (full frames: 16 x 1024 x 768)."""

PROX_CHUNK = 8
"""Proximity frames rendered per call (8 x 1024 x 768 float32 image + coverage: ~50 MB)."""

BLOBBER = BlobberConfig(estimator="subpixel", threshold=0.0, target="all", connectivity=8)
"""The proximity frames' blobber (``nav/blobber.py``)."""


@dataclass(frozen=True)
class RendezvousContext:
    """Per-process state: the target's satellite file and photometric shape, and either the star job's context
    (catalogs, voting index, star blob limit) or the proximity renderer's mesh, materials and area table."""

    sat: object
    shape: object
    photocentre: tuple = ()                # photocentre_table(shape)
    photocentre_bias: PhotocentreStatistics | None = None   # photocentre_statistics(shape, spinning)
    star: object = None
    mesh: object = None
    materials: np.ndarray | None = None
    table: object = None
    range_ratio: tuple = ()                # (bin centres, m_q, s_q): nav/blobber_range_error on ``table``
    centroid: PointCentroidTable | None = None   # star camera: point_centroid_calibration(spec)
    range_calibration: RangeRatioCalibration | None = None   # proximity: blobber_calibration(...)[0]
    centre_calibration: CentreErrorCalibration | None = None  # proximity: blobber_calibration(...)[1]
    silhouette_gain: np.ndarray | None = None     # proximity, bearing_point "silhouette": silhouette_sequence_gain


def make_context(spec: RendezvousSpec) -> RendezvousContext:
    sat = load_satellite(spec.cfg.satellite)
    shape = target_shape(sat.components)
    spinning = spec.cfg.target_rate_deg_s > 0
    if spec.is_star:
        pc = photocentre_table(shape)
        pb = photocentre_statistics(shape, spinning=spinning)
        sctx = star.make_context(spec.star)
        return RendezvousContext(sat, shape, pc, pb, star=sctx, centroid=point_centroid_calibration(spec, sctx.psf))
    pc, pb = prox_photocentre(sat, shape, spinning)
    table = prox_area_table(sat)
    mq, sq = range_ratio_statistics(table.samples_ratio, table.samples_area, table.ratio_lo, table.ratio_hi,
                                    table.curve(BLOBBER.curve))
    mesh, materials = sat.mesh(), sat.materials()
    cal, cen, gain = prox_calibrations(spec, sat, mesh, materials, table)
    return RendezvousContext(sat, shape, pc, pb, mesh=mesh, materials=materials, table=table,
                             range_ratio=(table.ratio, mq, sq), range_calibration=cal,
                             centre_calibration=cen, silhouette_gain=gain)


RANGE_CALIB_SPANS = ((10.0, 80.0, 12000), (0.4, 10.0, 6000))
"""Ranges (m) of :func:`blobber_calibration`'s renders: (low, high, count) log-uniform; more where the blob
is small (its observed axis ratio is poor and q's mean moves with it) than where the table alone is right."""
RANGE_CALIB_POINTING_DEG = 0.5
"""1-sigma per axis of the calibration target's offset from the boresight (the presets' pointing error)."""


def rendered_blobs(sat, mesh, materials, table, camera: Camera, R_body, pos, sun):
    """Yield (indices, ``nav/blobber.BlobResult``) over chunks of :data:`PROX_CHUNK` renders of the target by the
    camera's own renderer ("accurate", the satellite file's light) and blobber (:data:`BLOBBER`, the area table
    ``table``): attitudes R_body (M, 3, 3) body -> camera, positions pos (M, 3) m and Sun directions sun (M, 3) in
    the camera frame."""
    from dualsight.kernels.points import render              # Taichi

    light = sat.camera
    M = len(R_body)
    for s in range(0, M, PROX_CHUNK):
        i = np.arange(s, min(M, s + PROX_CHUNK))
        poses = place_body(sat, R_body[i], pos[i], sun[i])
        img, cov = render("accurate", mesh, materials, poses.R, poses.t, poses.light, camera, light.I_a, light.I_l)
        yield i, run_blobber(img, camera, table, BLOBBER, coverage=cov)


def prox_area_table(sat):
    """The target's projected-area table as the proximity camera's blobber reads it (``catalogs/areas``, cached)."""
    from dualsight.catalogs.areas import area_table        # pyarrow

    return area_table(sat, n=20000, bin_width=0.05)


def blobber_calibration(sat, mesh, materials, table,
                        camera: Camera) -> tuple[RangeRatioCalibration, CentreErrorCalibration]:
    """The proximity camera's blobber range and silhouette centre against the truth, by Monte Carlo of the camera's
    own renderer (``kernels/points.render``, "accurate", the satellite file's light) and blobber (:data:`BLOBBER`,
    the area table ``table``): the target at ranges log-uniform in each of :data:`RANGE_CALIB_SPANS`, off the
    boresight by :data:`RANGE_CALIB_POINTING_DEG`, orientations uniform on SO(3), the Sun from a uniform direction;
    a blob that touches the image's edge is not a range (:func:`touches_edge`) and is left out.  Returns the
    samples as ``nav/blobber_range_error.RangeRatioCalibration`` (q = range_est / range against n_blob and the
    observed axis ratio) and ``nav/blob_centre_error.CentreErrorCalibration`` (the blob's ``centre_px`` minus the
    projection of the body's origin, px, against n_blob).  Deterministic (its own generator, not the run's seed): a
    ground calibration of the blobber on the target's model, as :func:`point_centroid_calibration` is of the star
    camera.  ~10 s for the 3U CubeSat and the paper's proximity camera (one process, 2 shared cores)."""
    rng = np.random.default_rng([23, 6, 4])
    r = np.concatenate([np.exp(rng.uniform(math.log(lo), math.log(hi), n)) for lo, hi, n in RANGE_CALIB_SPANS])
    M = r.size
    u = rng.random((M, 3))
    R_body = quat_to_dcm(quaternions_from_uniforms(u[:, 0], u[:, 1], u[:, 2]))
    off = rng.normal(size=(M, 2)) * RANGE_CALIB_POINTING_DEG * DEG
    los = np.stack([np.tan(off[:, 0]), np.tan(off[:, 1]), np.ones(M)], -1)
    pos = los / np.linalg.norm(los, axis=1, keepdims=True) * r[:, None]
    sun = rng.normal(size=(M, 3))
    sun /= np.linalg.norm(sun, axis=1, keepdims=True)
    q, n_blob, ratio, angle = (np.full(M, np.nan) for _ in range(4))
    err = np.full((M, 2), np.nan)
    for i, b in rendered_blobs(sat, mesh, materials, table, camera, R_body, pos, sun):
        ok = b.found & ~touches_edge(b.box, camera) & np.isfinite(b.range_est)
        q[i] = np.where(ok, b.range_est / r[i], np.nan)
        n_blob[i] = np.where(ok, b.n_blob, np.nan)
        ratio[i] = np.where(ok, b.axis_ratio, np.nan)
        angle[i] = np.where(ok, b.angle_rad, np.nan)
        err[i] = np.where(ok[:, None], b.centre_px - camera.project(pos[i])[0], np.nan)
    return RangeRatioCalibration(n_blob, ratio, q), CentreErrorCalibration(n_blob, err, ratio, angle)


SEQUENCE_GAIN_SEQUENCES, SEQUENCE_GAIN_FRAMES = 1200, 48
"""Rendered sequences x frames (at most; the approach's frames if fewer) of :func:`silhouette_sequence_gain`: 57,600
renders, ~33 s in one process (a window around the body: :func:`central_window`), once per target, camera, spin and
frame rate (cached).  The error's size varies with the spin axis (a heavy tail), so few sequences give an unstable
gain, and the maximum over window lengths is biased upwards by the sampling noise: across the turn axis 1.83 from
400 sequences, 1.33 from 1,200 (along it 2.05 and 2.07; the close preset, errors over the calibrated sigma along the
blob's own axes, 2026-11-28)."""
SEQUENCE_GAIN_RANGES_M = (2.0, 50.0)
"""Ranges (m) of the sequences, log-uniform (one per sequence, the close preset's span)."""


def central_window(camera: Camera, half_px: int) -> Camera:
    """The camera cut to a window of at most 2 ``half_px`` x 2 ``half_px`` pixels around its principal point: the same
    focal lengths and distortion (in normalised coordinates), the principal point moved by the cut, so a body near
    the boresight projects to the same pixels relative to it.  A calibration of a target on the boresight renders and
    blobs that window only (the 3U CubeSat at 2 m and more in the paper's proximity camera: 246 x 246 pixels instead
    of 1024 x 768, ~2x faster per render, the same blobs)."""
    x0 = max(0, min(int(math.floor(camera.cx)) - half_px, camera.width - 2 * half_px))
    y0 = max(0, min(int(math.floor(camera.cy)) - half_px, camera.height - 2 * half_px))
    return replace(camera, width=min(camera.width, 2 * half_px), height=min(camera.height, 2 * half_px),
                   cx=camera.cx - x0, cy=camera.cy - y0)


def silhouette_sequence_gain(sat, mesh, materials, table, camera: Camera, centre: CentreErrorCalibration,
                             spin_step_rad: float, turn_step_rad: float, frames: int) -> np.ndarray:
    """(2,) ``nav/blob_centre_error.sequence_gain`` of the silhouette centre's error along the observer's turn
    axis and across it, by the camera's own renderer and blobber (the area table ``table``): sequences of the
    target spinning about an axis uniform on the sphere (its initial attitude uniform on SO(3)) by
    ``spin_step_rad`` a frame while the observer turns about the camera's y axis (the Sun along it) by
    ``turn_step_rad`` a frame, at a range log-uniform in :data:`SEQUENCE_GAIN_RANGES_M`, each frame's error over
    the calibration's sigma on that axis at the blob's coverage, axis ratio and angle (``centre.cov_px``).
    Deterministic (its own generator): a ground calibration, as :func:`blobber_calibration`."""
    rng = np.random.default_rng([23, 6, 5])
    S, L = SEQUENCE_GAIN_SEQUENCES, max(1, min(int(frames), SEQUENCE_GAIN_FRAMES))
    axes = rng.normal(size=(S, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    u = rng.random((S, 3))
    R0 = quat_to_dcm(quaternions_from_uniforms(u[:, 0], u[:, 1], u[:, 2]))
    lo, hi = SEQUENCE_GAIN_RANGES_M
    r = np.exp(rng.uniform(math.log(lo), math.log(hi), S))
    k = np.arange(L)
    spin = frame_rotation((axes[:, None, :] * (k * spin_step_rad)[None, :, None]).reshape(-1, 3)).reshape(S, L, 3, 3)
    obs = frame_rotation(np.outer(k * turn_step_rad, [0.0, 1.0, 0.0]))[None]
    R_body = (obs @ spin @ R0[:, None]).reshape(-1, 3, 3)
    pos = np.repeat(np.stack([np.zeros(S), np.zeros(S), r], -1), L, 0)
    sun = np.tile([0.0, 1.0, 0.0], (S * L, 1))
    z = np.full((S * L, 2), np.nan)
    rb = sat.bounding_radius                # the window that holds the body at the nearest range, perspective included
    win = camera if lo <= rb else central_window(camera, int(math.ceil(rb * max(camera.fx, camera.fy) / (lo - rb))) + 6)
    for i, b in rendered_blobs(sat, mesh, materials, table, win, R_body, pos, sun):
        ok = b.found & ~touches_edge(b.box, win)
        e = (b.centre_px - win.project(pos[i])[0])[:, ::-1]             # (row: along the turn axis, column)
        C = centre.cov_px(np.where(ok, b.n_coverage, np.nan), b.axis_ratio, b.angle_rad)   # (col, row) px^2
        sd = np.sqrt(np.stack([C[:, 1, 1], C[:, 0, 0]], -1))              # the stated sigma on each of those axes
        z[i] = np.where(ok[:, None], e / sd, np.nan)
    return sequence_gain(z.reshape(S, L, 2))


def prox_calibrations(spec: RendezvousSpec, sat, mesh, materials, table, announce=None):
    """(range calibration, centre calibration, sequence gain) a proximity spec needs (None each where it does not:
    the range with ``range_source`` "blobber", the centre with it or with ``bearing_point`` "silhouette", the gain
    with the latter), from the cache or computed (:func:`cached_blobber_calibration`); ``announce(message)`` is
    called before a calibration is computed."""
    c = spec.cfg
    cal = cen = gain = None
    if c.range_source == "blobber" or c.bearing_point == "silhouette":
        cal, cen = cached_blobber_calibration(sat, mesh, materials, table, spec.camera, announce=announce)
    if c.bearing_point == "silhouette":      # an approach in the orbit plane: its line of sight turns with the Hill
        gain = cached_sequence_gain(sat, mesh, materials, table, spec.camera, cen,         # frame, n dt a frame
                                    c.target_rate_deg_s * DEG * c.frame_interval_s,
                                    spec.orbit.mean_motion * c.frame_interval_s, c.frames, announce=announce)
    return cal, cen, gain


def warm_calibrations(spec: RendezvousSpec, announce=None) -> None:
    """Compute and cache the calibrations a proximity spec's workers will read (:func:`prox_calibrations`), once in
    this process instead of in every worker at once; nothing for the star camera."""
    if spec.is_star:
        return
    sat = load_satellite(spec.cfg.satellite)
    prox_calibrations(spec, sat, sat.mesh(), sat.materials(), prox_area_table(sat), announce)


CALIBRATION_VERSION = 2
"""Part of the cache key of :func:`cached_blobber_calibration` and :func:`cached_sequence_gain`: raise it when the
renderer, the blobber or the calibrations' sampling change what they compute (as ``catalogs/areas.TABLE_VERSION``)."""
_CAL_META = b"dualsight.rendezvous_calibration"


def _calibration_key(sat, mesh, materials, table, camera: Camera, **extra) -> str:
    """A content key of a calibration's inputs: the target's mesh, materials, light and components, its area
    table's key, the camera, :data:`CALIBRATION_VERSION`, the sampling constants and ``extra``."""
    light = sat.camera
    body = short_hash(b"".join(np.ascontiguousarray(a).tobytes() for a in (mesh.vertices, mesh.normals,
                                                                            mesh.component, materials)))
    payload = {"version": CALIBRATION_VERSION, "body": body, "components": repr(sat.components),
               "light": [float(light.I_a), float(light.I_l)], "table": table.key, "camera": camera.to_dict(),
               "spans": RANGE_CALIB_SPANS, "pointing": RANGE_CALIB_POINTING_DEG,
               "sequences": [SEQUENCE_GAIN_SEQUENCES, SEQUENCE_GAIN_FRAMES, list(SEQUENCE_GAIN_RANGES_M)], **extra}
    return short_hash(json.dumps(payload, sort_keys=True, default=str))


def cached_blobber_calibration(sat, mesh, materials, table, camera: Camera, cache_dir=None,
                               announce=None) -> tuple[RangeRatioCalibration, CentreErrorCalibration]:
    """:func:`blobber_calibration`, read from ``<cache>/rendezvous/<key>.parquet`` (``catalogs/cache``:
    DUALSIGHT_CACHE or ~/.cache/dualsight) when a run on the same target and camera made it, else computed and
    written there (atomically); a missing, unreadable or foreign file is rebuilt (``announce(message)`` first)."""
    import pyarrow as pa

    from dualsight.catalogs.parquet_cache import read_parquet_or_none, write_parquet_atomic

    key = _calibration_key(sat, mesh, materials, table, camera, kind="blobber")
    path = resolve_cache_dir(cache_dir) / "rendezvous" / f"{key}.parquet"
    t = read_parquet_or_none(path, _CAL_META, key.encode())
    if t is not None:
        c = {name: t.column(name).to_numpy() for name in t.column_names}
        return (RangeRatioCalibration(c["n_blob"], c["ratio"], c["q"]),
                CentreErrorCalibration(c["n_blob"], np.stack([c["err_x"], c["err_y"]], -1), c["ratio"], c["angle"]))
    if announce is not None:
        n = sum(k for _, _, k in RANGE_CALIB_SPANS)
        announce(f"calibrating the blobber's range and silhouette centre on {n:,} renders of the target (once per "
                 f"target and camera, cached in {path.parent})")
    cal, cen = blobber_calibration(sat, mesh, materials, table, camera)
    err = np.asarray(cen.err_px, np.float64)
    t = pa.table({"n_blob": np.asarray(cal.n_blob, np.float64), "ratio": np.asarray(cal.ratio, np.float64),
                  "q": np.asarray(cal.q, np.float64), "err_x": err[:, 0], "err_y": err[:, 1],
                  "angle": np.asarray(cen.angle_rad, np.float64)})
    write_parquet_atomic(t.replace_schema_metadata({_CAL_META: key.encode()}), path)
    return cal, cen


def cached_sequence_gain(sat, mesh, materials, table, camera: Camera, centre: CentreErrorCalibration,
                         spin_step_rad: float, turn_step_rad: float, frames: int, cache_dir=None,
                         announce=None) -> np.ndarray:
    """:func:`silhouette_sequence_gain`, cached as :func:`cached_blobber_calibration` (its key adds the spin and
    turn steps and the frames; the centre calibration it normalises by is the cached one of the same target and
    camera)."""
    import pyarrow as pa

    from dualsight.catalogs.parquet_cache import read_parquet_or_none, write_parquet_atomic

    key = _calibration_key(sat, mesh, materials, table, camera, kind="sequence_gain",
                           steps=[float(spin_step_rad), float(turn_step_rad)], frames=int(frames))
    path = resolve_cache_dir(cache_dir) / "rendezvous" / f"{key}.parquet"
    t = read_parquet_or_none(path, _CAL_META, key.encode())
    if t is not None:
        return t.column("gain").to_numpy().astype(np.float64)
    if announce is not None:
        n = SEQUENCE_GAIN_SEQUENCES * max(1, min(int(frames), SEQUENCE_GAIN_FRAMES))
        announce(f"calibrating the silhouette centre's frame-to-frame correlation on {n:,} renders of the spinning "
                 f"target (once per target, camera, spin and frame rate, cached in {path.parent})")
    gain = silhouette_sequence_gain(sat, mesh, materials, table, camera, centre, spin_step_rad, turn_step_rad, frames)
    write_parquet_atomic(pa.table({"gain": np.asarray(gain, np.float64)}).replace_schema_metadata(
        {_CAL_META: key.encode()}), path)
    return gain


def touches_edge(box: np.ndarray, camera: Camera) -> np.ndarray:
    """(B,) whether a blob's inclusive bounding box (B, 4) [x0, y0, x1, y1] reaches the image's first or last row
    or column: the target is cut by the frame, its pixel count and centre of brightness are the visible part's."""
    box = np.asarray(box)
    return (box[:, 0] <= 0) | (box[:, 1] <= 0) | (box[:, 2] >= camera.width - 1) | (box[:, 3] >= camera.height - 1)


def prox_photocentre(sat, shape, spinning: bool) -> tuple[tuple, PhotocentreStatistics | None]:
    """The proximity camera's photocentre correction and statistics: under the renderer's own shading (the
    satellite file's ``I_a``, ``I_l`` and each component's ``k_a``, ``k_l``, ``k_s``, ``n``:
    ``scene/photocentre_bias.shaded_photocentre_offset``; its ambient light pulls the photocentre towards the
    silhouette's centre, to about a third of the Lambertian table's offset for the 3U CubeSat at 90 deg phase),
    as (alpha, mean offset towards the Sun, total spread) in ``photocentre_table``'s layout and the statistics;
    a target with spheres keeps the Lambertian table and no statistics (not modelled)."""
    try:
        mats = facet_materials(sat.components)
    except ValueError:
        return photocentre_table(shape), None
    light = sat.camera

    def offset(R_body, sun, obs):
        return shaded_photocentre_offset(shape, mats, light.I_a, light.I_l, R_body, sun, obs)

    pb = photocentre_statistics(shape, spinning=spinning, offset=offset)
    spread = np.sqrt(pb.spread_white ** 2 + 0.5 * (pb.sigma_sun ** 2 + pb.sigma_cross ** 2))
    return (pb.alpha, pb.mean_sun, spread), pb


CALIB_LEVELS = np.logspace(3.0, 11.0, 321)
"""Electrons per exposure of the point sources of :func:`point_centroid_calibration` (40 levels per decade: the
saturated centroid's error oscillates with the flux, a period of about a quarter decade for the paper sensor)."""
CALIB_PHASES = 64
"""Renders per level of :func:`point_centroid_calibration` (uniform sub-pixel positions; each level's sigma is
then known to about 1 / sqrt(2 x 64) = 9 %, and the many levels a campaign's targets span average that out)."""
CALIB_WINDOW_PX = 64
"""Side of the window the calibration renders in (the point source near its centre; the sensor, PSF, detector and
distortion of the star camera)."""


def point_centroid_calibration(spec: RendezvousSpec, psf=None) -> PointCentroidTable:
    """The star camera's centroid error for a point source against its measured flux, by Monte Carlo of the
    camera's own render and detector (``jobs/kinds/star.render_and_detect``: the spec's sensor, with its noise if
    any, its detector and PSF) on :data:`CALIB_WINDOW_PX`-pixel windows, one source per window at a uniform
    sub-pixel position, :data:`CALIB_PHASES` renders at each of :data:`CALIB_LEVELS`; the table of
    ``nav/target_bearing.point_centroid_table``.  Deterministic (its own generator, not the run's seed): a ground
    calibration of the camera, as a flight star tracker's centroid error model is.  ~0.5 s noise-free (sparse
    path), longer with noise (full windows)."""
    sp = spec.star
    w = CALIB_WINDOW_PX
    c0 = 0.5 * w
    cam = replace(sp.camera, width=w, height=w, cx=c0, cy=c0)
    L, K = len(CALIB_LEVELS), CALIB_PHASES
    rng = np.random.default_rng([23, 6, 3])
    x = c0 + rng.random(L * K)
    y = c0 + rng.random(L * K)
    e = np.repeat(CALIB_LEVELS, K).astype(np.float32)
    level = np.repeat(np.arange(L), K)
    seeds = rng.integers(0, 2**63 - 1, size=L * K, dtype=np.int64).astype(np.uint64)
    flux = np.full(L * K, np.nan)
    err = np.full((L * K, 2), np.nan)
    chunk = 4096 if (sp.sensor.is_ideal and sp.detector == "global") else 512
    for s in range(0, L * K, chunk):
        i = np.arange(s, min(L * K, s + chunk))
        n = len(i)
        fs = FieldStars(x[i, None], y[i, None], e[i, None], np.ones((n, 1), bool), np.zeros((n, 1), np.int64),
                        np.ones((n, 1), bool), np.ones(n, np.int64))
        det = star.render_and_detect(fs, seeds[i], cam, sp.sensor, sp.detect, keep_images=False,
                                     attitude=np.broadcast_to(np.eye(3), (n, 3, 3)), detector=sp.detector,
                                     psf=psf).detections
        case = np.asarray(det.case, np.int64)
        d2 = (det.x - x[i][case]) ** 2 + (det.y - y[i][case]) ** 2
        o = np.lexsort((d2, case))                            # each window's detection nearest the source
        first = o[np.unique(case[o], return_index=True)[1]]
        near = first[d2[first] < 9.0]
        b = i[case[near]]
        flux[b] = det.flux[near]
        err[b] = np.stack([det.x[near] - x[b], det.y[near] - y[b]], -1)
    return point_centroid_table(level, flux, err)
