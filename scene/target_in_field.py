"""A spacecraft in the star camera's field (issue 23, point 1): each case's target geometry, its photometry on the
stars' zero point, and its light as extra point sources of the star renderer, with the stars behind it hidden.

Stage between ``scene/starfield_geometry.stars_in_field`` and the render kernels of the star job.  Per case
(``[target]`` of the spec, ``scene/target_config.TargetConfig``):

* draws (from the case's own generator ``default_rng([seed, i])``, after the star job's four draws, so the
  attitude and the noise seed of every case are those of the same run without a target): presence, range
  (log-uniform in ``range_m``), direction (``offset_deg`` or uniform over the inner 90 % of the image), the
  target's attitude (uniform on SO(3)), the Sun (``sun_icrs`` through the case's attitude, or at a phase angle
  uniform in ``phase_deg`` with a uniform azimuth about the line of sight);
* photometry: ``scene/target_photometry.apparent_brightness`` (magnitude, centre of brightness), electrons per
  exposure by the star renderer's own ``flux_from_magnitude``;
* rendering: a *point-like* target (the bounding sphere < :data:`RESOLVED_PX` across) is one point source at its
  centre of brightness; a *resolved* one is rasterised by ``kernels/prox_raster.render_mesh`` (exact pixel
  coverage, Lambertian shading ``k_l max(N.L, 0)``, no ambient light, no specular term) in a window around it,
  scaled so that its pixels sum to the photometric electrons, and each lit pixel becomes a point source at its
  centre (the star renderer then applies the PSF, the sensor and saturation to it as to the stars).  A star
  whose centre falls on a pixel the target covers keeps ``1 - coverage`` of its flux (hidden behind it).

Pixel coordinates: (col, row) from the top-left corner (docs/architecture.md).  Units: m, rad.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from dualsight.scene.target_config import TargetConfig
from dualsight.kernels.sensor_config import SensorConfig, flux_from_magnitude
from dualsight.scene.attitude import quat_to_dcm, quaternions_from_uniforms
from dualsight.scene.case_rng import streams as case_streams
from dualsight.scene.motion import place_body
from dualsight.scene.starfield_geometry import FieldStars
from dualsight.scene.target_photometry import TargetShape, apparent_brightness

__all__ = ["STAR_JOB_DRAWS", "RESOLVED_PX", "MAX_WINDOW_PX", "MESH_SEGMENTS", "TargetCases", "draw_targets",
           "TargetFrame", "target_frames", "with_target", "diameter_px"]

STAR_JOB_DRAWS = 4
"""Raw 64-bit draws each case of the star job takes before the target's (three attitude draws, one noise seed:
``jobs/kinds/star.draw_cases``)."""
RESOLVED_PX = 3.0
"""A target whose bounding sphere spans at least this many pixels is rasterised; smaller ones are a point."""
MAX_WINDOW_PX = 512
"""Largest side (px) of a resolved target's window: the spec's nearest range must keep the target inside it."""
MESH_SEGMENTS = 32
"""Segments of the meshes of curved components (spheres, cylinders) when rasterised."""


@dataclass(frozen=True)
class TargetCases:
    """Each case's target geometry (camera frame unless said).

    present (B,) bool; range_m (B,) m; pos_cam (B, 3) body origin (m); R_body (B, 3, 3) body -> camera;
    sun_cam (B, 3), sun_icrs (B, 3) unit vectors towards the Sun; phase_rad (B,) Sun-target-camera angle.
    """

    present: np.ndarray
    range_m: np.ndarray
    pos_cam: np.ndarray
    R_body: np.ndarray
    sun_cam: np.ndarray
    sun_icrs: np.ndarray
    phase_rad: np.ndarray


def draw_targets(cfg: TargetConfig, seed: int, case_ids: np.ndarray, A_true: np.ndarray, camera,
                 sun_icrs: np.ndarray | None = None) -> TargetCases:
    """The target of each case from ``default_rng([seed, case_id])`` (its draws after :data:`STAR_JOB_DRAWS`).

    A_true : (B, 3, 3) inertial -> camera attitudes of the cases; camera : ``scene.camera.Camera``; sun_icrs :
    (B, 3) unit vectors towards each case's Sun (ICRS; ``scene/case_environment.py``), before ``cfg.sun_icrs``.
    Every case takes the same nine draws whatever the options, in this order: presence, range, x, y, three for
    the target's attitude, phase, azimuth."""
    rng = case_streams(seed, np.asarray(case_ids, np.int64))
    for _ in range(STAR_JOB_DRAWS):
        rng.next_uint64()
    u_present, u_range, u_x, u_y = rng.random(), rng.random(), rng.random(), rng.random()
    q = quaternions_from_uniforms(rng.random(), rng.random(), rng.random())
    u_phase, u_az = rng.random(), rng.random()
    B = len(case_ids)
    lo, hi = cfg.range_m
    rng_m = lo * (hi / lo) ** u_range
    if cfg.offset_deg is not None:
        v = np.array([math.tan(math.radians(cfg.offset_deg[0])), math.tan(math.radians(cfg.offset_deg[1])), 1.0])
        u = np.tile(v / np.linalg.norm(v), (B, 1))
    else:
        px = np.stack([camera.width * (0.05 + 0.9 * u_x), camera.height * (0.05 + 0.9 * u_y)], -1)
        u = camera.backproject(px)
    A_true = np.asarray(A_true, np.float64)
    o = -u                                                   # target -> camera
    if sun_icrs is not None:                                # each case's own Sun (its epoch)
        s_case = np.asarray(sun_icrs, np.float64)
        s_cam = np.einsum("bij,bj->bi", A_true, s_case / np.linalg.norm(s_case, axis=-1, keepdims=True))
    elif cfg.sun_icrs is not None:
        s_icrs = np.asarray(cfg.sun_icrs, np.float64)
        s_cam = np.einsum("bij,j->bi", A_true, s_icrs / np.linalg.norm(s_icrs))
    else:
        lo_a, hi_a = np.radians(cfg.phase_deg[0]), np.radians(cfg.phase_deg[1])
        alpha = lo_a + (hi_a - lo_a) * u_phase
        psi = 2 * np.pi * u_az
        ref = np.where(np.abs(o[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
        e1 = np.cross(o, ref)
        e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
        e2 = np.cross(o, e1)
        s_cam = (np.cos(alpha)[:, None] * o + np.sin(alpha)[:, None]
                 * (np.cos(psi)[:, None] * e1 + np.sin(psi)[:, None] * e2))
    s_icrs_case = np.einsum("bji,bj->bi", A_true, s_cam)
    phase = np.arccos(np.clip(np.einsum("bk,bk->b", s_cam, o), -1.0, 1.0))
    return TargetCases(u_present < cfg.probability, rng_m, u * rng_m[:, None], quat_to_dcm(q), s_cam, s_icrs_case,
                       phase)


def diameter_px(bounding_radius_m: float, range_m, camera) -> np.ndarray:
    """Apparent diameter (px) of a sphere of ``bounding_radius_m`` at ``range_m`` (small angle, larger focal length)."""
    return 2.0 * bounding_radius_m / np.asarray(range_m, np.float64) * max(camera.fx, camera.fy)


@dataclass(frozen=True)
class TargetFrame:
    """The target's part of each frame.

    present (B,) bool; vmag (B,) apparent V magnitude (NaN without target); electrons (B,) per exposure;
    x_px, y_px (B,) projection of the body origin; cob_x_px, cob_y_px (B,) projection of the photometric centre
    of brightness (:mod:`dualsight.scene.target_photometry`); resolved (B,) bool; diameter_px (B,) of the
    bounding sphere; area_px (B,) projected area (px^2); pixels (B,) int64 pixels it covers (resolved; -1 for a
    point); sources x, y, flux_e, valid (B, T) its point sources; star_keep (B, S) fraction of each field star's
    flux left visible; sun_angle_rad (B,) Sun from the boresight; sun_keepout (B,) bool inside the keep-out cone.
    """

    present: np.ndarray
    vmag: np.ndarray
    electrons: np.ndarray
    x_px: np.ndarray
    y_px: np.ndarray
    cob_x_px: np.ndarray
    cob_y_px: np.ndarray
    resolved: np.ndarray
    diameter_px: np.ndarray
    area_px: np.ndarray
    pixels: np.ndarray
    src_x: np.ndarray
    src_y: np.ndarray
    src_flux: np.ndarray
    src_valid: np.ndarray
    star_keep: np.ndarray
    sun_angle_rad: np.ndarray
    sun_keepout: np.ndarray


def _window_camera(camera, x0: int, y0: int, w: int, h: int):
    """The camera cropped to the window [x0, x0 + w) x [y0, y0 + h) (principal point shifted; same distortion)."""
    return dataclasses.replace(camera, width=int(w), height=int(h), cx=camera.cx - x0, cy=camera.cy - y0)


def target_frames(cfg: TargetConfig, sat, shape: TargetShape, cases: TargetCases, field_: FieldStars, camera,
                  sensor: SensorConfig) -> TargetFrame:
    """Photometry and rendering of each case's target over the batch (see the module doc).

    sat : the ``SatelliteConfig`` of ``cfg.satellite``; shape : ``target_shape(sat.components)``;
    field_ : the case's stars (for the occlusion); camera, sensor : the star job's."""
    B = len(cases.range_m)
    br = apparent_brightness(shape, cases.R_body, cases.pos_cam, cases.sun_cam, sensor.zero_mag_rate_e_per_s)
    present = cases.present & np.isfinite(br.vmag)
    e = np.where(present, flux_from_magnitude(np.where(np.isfinite(br.vmag), br.vmag, 99.0), sensor), 0.0)
    xy, _ = camera.project(cases.pos_cam)
    cob, _ = camera.project(br.cob_cam)
    diam = diameter_px(shape.bounding_radius, cases.range_m, camera)
    f = max(camera.fx, camera.fy)
    area_px = br.area_m2 / cases.range_m ** 2 * f * f
    resolved = present & (diam >= RESOLVED_PX)
    keep = np.ones(field_.x.shape, np.float64)
    pixels = np.full(B, -1, np.int64)
    per_case = [(np.array([cob[b, 0]]), np.array([cob[b, 1]]), np.array([e[b]])) if present[b] and not resolved[b]
                else (np.zeros(0), np.zeros(0), np.zeros(0)) for b in range(B)]
    if resolved.any():
        mesh = sat.mesh(MESH_SEGMENTS)
        mat = np.array([[0.0, c.k_l, 0.0, 1.0] for c in sat.components])
        from dualsight.kernels.prox_raster import render_mesh    # Taichi: only when a target is resolved

        for b in np.flatnonzero(resolved):    # one window per resolved case (its own principal point)
            half = int(math.ceil(0.5 * diam[b])) + 2
            cx, cy = int(math.floor(xy[b, 0])), int(math.floor(xy[b, 1]))
            x0, y0 = cx - half, cy - half
            wcam = _window_camera(camera, x0, y0, 2 * half + 1, 2 * half + 1)
            poses = place_body(sat, cases.R_body[b:b + 1], cases.pos_cam[b:b + 1], cases.sun_cam[b:b + 1])
            img, cov = render_mesh(mesh, mat, poses.R[:, :], poses.t, poses.light, wcam, I_a=0.0, I_l=1.0)
            img, cov = img[0].astype(np.float64), cov[0].astype(np.float64)
            pixels[b] = int(np.count_nonzero(cov > 0))
            lit = img > 0
            r, c = np.nonzero(lit)
            per_case[b] = (x0 + c + 0.5, y0 + r + 0.5, e[b] * img[lit] / img[lit].sum()) if lit.any() else \
                per_case[b]
            # stars whose centre lies on a covered pixel of the window
            sx = np.floor(field_.x[b]).astype(np.int64) - x0
            sy = np.floor(field_.y[b]).astype(np.int64) - y0
            on = field_.valid[b] & (sx >= 0) & (sx < cov.shape[1]) & (sy >= 0) & (sy < cov.shape[0])
            keep[b, on] = 1.0 - cov[sy[on], sx[on]]
    T = max(1, max(len(p[0]) for p in per_case))
    src = np.zeros((3, B, T))
    valid = np.zeros((B, T), bool)
    for b, (x, y, fl) in enumerate(per_case):     # a loop over cases, each filled whole
        n = len(x)
        src[0, b, :n], src[1, b, :n], src[2, b, :n], valid[b, :n] = x, y, fl, True
    sun_angle = np.arccos(np.clip(cases.sun_cam[:, 2], -1.0, 1.0))
    return TargetFrame(present, np.where(present, br.vmag, np.nan), e, xy[:, 0], xy[:, 1], cob[:, 0], cob[:, 1],
                       resolved, diam, area_px, pixels, src[0], src[1], src[2].astype(np.float32), valid, keep,
                       sun_angle, sun_angle < math.radians(cfg.sun_keepout_deg))


def with_target(field_: FieldStars, tf: TargetFrame) -> tuple[FieldStars, FieldStars]:
    """(what to render, the stars' truth): the field's stars dimmed by the target's cover with the target's
    sources appended (catalog row -1, not counted as generated), and the stars alone with those more than half
    hidden marked invalid (they cannot be detected: no detection is their truth)."""
    flux = (field_.flux_e * tf.star_keep).astype(np.float32)
    B, T = tf.src_valid.shape
    render = FieldStars(np.concatenate([field_.x, tf.src_x], 1), np.concatenate([field_.y, tf.src_y], 1),
                        np.concatenate([flux, tf.src_flux], 1), np.concatenate([field_.valid, tf.src_valid], 1),
                        np.concatenate([field_.cat_row, np.full((B, T), -1, np.int64)], 1),
                        np.concatenate([field_.inside, np.zeros((B, T), bool)], 1), field_.n_generated)
    hidden = tf.star_keep < 0.5
    truth = dataclasses.replace(field_, valid=field_.valid & ~hidden, inside=field_.inside & ~hidden,
                                n_generated=(field_.inside & ~hidden).sum(1))
    return render, truth
