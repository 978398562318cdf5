"""One rendezvous approach's draw and truth (:mod:`dualsight.jobs.kinds.rendezvous`): its inputs from
``default_rng([seed, case_id])``, the Clohessy-Wiltshire trajectory with the executed manoeuvres, and per frame the
camera's attitude, the target's geometry in the camera frame and the Sun, Earth and Moon along the boresight."""

from __future__ import annotations

import math

import numpy as np

from dualsight.scene.attitude import quat_to_dcm, quaternions_from_uniforms
from dualsight.scene.ephemeris import jd_tt_from_unix, moon_position, sun_position
from dualsight.scene.keepout import KeepOut, keep_out
from dualsight.scene.relative_orbit import hill_to_icrs, propagate
from dualsight.scene.rotation_vector import frame_rotation
from dualsight.scene.target_in_field import TargetCases
from dualsight.scene.units import ARCSEC, DEG
from dualsight.jobs.kinds.rendezvous_spec import RendezvousSpec


def draw_case(spec: RendezvousSpec, case_id: int) -> dict:
    """Inputs of approach ``case_id`` from ``default_rng([seed, case_id])`` alone, always in this order whatever
    the options: initial-state dispersion (6 normals), manoeuvre execution errors (M x 3 normals), the target's spin
    axis (3 normals) and initial attitude (3 uniforms), pointing errors (T x 3 normals), attitude-knowledge errors
    (T x 3 normals), per-frame sensor noise seeds (T).

    Returns dict: x0 (6,) true initial Hill state; x0_nominal (6,); dv_nominal, dv_exec (M, 3) m/s; spin_axis (3,);
    q0 (4,); pointing_err, attitude_err (T, 3) rad; noise_seeds (T,) uint64."""
    c = spec.cfg
    T, M = c.frames, len(c.manoeuvre_times_s)
    rng = np.random.default_rng([spec.seed, int(case_id)])
    nominal = np.array(list(c.position_m) + list(c.velocity_m_s), np.float64)
    disp = np.array(list(c.dispersion_position_m) + list(c.dispersion_velocity_m_s))
    x0 = nominal + rng.normal(size=6) * disp
    dv_nom = np.asarray(c.manoeuvre_dv_m_s, np.float64).reshape(M, 3)
    dv_sig = np.sqrt((c.dv_error_frac * np.linalg.norm(dv_nom, axis=1)) ** 2 + c.dv_error_m_s ** 2)
    dv_exec = dv_nom + rng.normal(size=(M, 3)) * dv_sig[:, None]
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    u = rng.random(3)
    q0 = quaternions_from_uniforms(u[0:1], u[1:2], u[2:3])[0]
    pe = rng.normal(size=(T, 3)) * c.pointing_error_deg * DEG
    ae = rng.normal(size=(T, 3)) * c.attitude_sigma_arcsec * ARCSEC
    noise = rng.integers(0, 2**63 - 1, size=T, dtype=np.int64).astype(np.uint64)
    return {"x0": x0, "x0_nominal": nominal, "dv_nominal": dv_nom, "dv_exec": dv_exec, "spin_axis": axis, "q0": q0,
            "pointing_err": pe, "attitude_err": ae, "noise_seeds": noise}


def truth_trajectory(spec: RendezvousSpec, draw: dict) -> np.ndarray:
    """(T, 6) true Hill states at the frame times: CW from the drawn initial state with the executed manoeuvres."""
    c = spec.cfg
    return propagate(draw["x0"][None], spec.times, spec.orbit.mean_motion, dv_times=np.asarray(c.manoeuvre_times_s),
                     dv=draw["dv_exec"][None] if len(c.manoeuvre_times_s) else None)[0]


def sun_icrs(spec: RendezvousSpec) -> np.ndarray:
    """(3,) unit vector towards the Sun: the spec's, else the first frame's epoch's (``[rendezvous.environment]``,
    ``scene/ephemeris.py``, from the Earth's centre: 10 arcsec from the chaser's), else the reference orbit's
    normal."""
    if spec.cfg.sun_icrs is not None:
        s = np.asarray(spec.cfg.sun_icrs, np.float64)
        return s / np.linalg.norm(s)
    if spec.cfg.environment is not None:
        s = sun_position(jd_tt_from_unix(spec.cfg.environment.epoch_unix_s))
        return s / np.linalg.norm(s)
    return hill_to_icrs(spec.orbit, [0.0])[0][:, 2]


def look_at(los: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(T, 3, 3) attitudes (ICRS -> camera) with the boresight +z along ``los`` (T, 3) (unit) and +x along
    ``up x los`` (``up`` (T, 3); where it is within 1e-6 of the boresight, ICRS x or y instead)."""
    z = np.asarray(los, np.float64)
    up = np.asarray(up, np.float64)
    x = np.cross(up, z)
    bad = np.linalg.norm(x, axis=-1) < 1e-6
    if bad.any():
        alt = np.where(np.abs(z[bad, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
        x[bad] = np.cross(alt, z[bad])
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    return np.stack([x, np.cross(z, x), z], -2)


def geometry(spec: RendezvousSpec, draw: dict, truth: np.ndarray) -> dict:
    """Per frame: true camera attitude A_true (T, 3, 3) (ICRS -> camera), the Hill rotation R (T, 3, 3), the true
    line of sight u_true (T, 3) chaser -> target (ICRS), and the target's geometry in the camera frame as
    ``scene/target_in_field.TargetCases`` (present = in front of the camera and inside the image)."""
    c = spec.cfg
    t = spec.times
    R = hill_to_icrs(spec.orbit, t)
    rho_i = np.einsum("tij,tj->ti", R, truth[:, :3])
    rng_m = np.linalg.norm(rho_i, axis=1)
    u_true = -rho_i / rng_m[:, None]
    up = R[:, :, 2]                                              # the orbit normal: camera +x along-track-ish
    if c.pointing == "target":
        A_nom = look_at(u_true, up)
    else:
        x0n = draw["x0_nominal"][:3]
        u0 = -(R[0] @ x0n) / np.linalg.norm(x0n)
        A_nom = np.broadcast_to(look_at(u0[None], up[:1])[0], (len(t), 3, 3))
    A = frame_rotation(draw["pointing_err"]) @ A_nom
    pos_cam = np.einsum("tij,tj->ti", A, u_true * rng_m[:, None])
    R_icrs = frame_rotation(draw["spin_axis"][None] * (c.target_rate_deg_s * DEG * t)[:, None]) @ \
        quat_to_dcm(draw["q0"][None])[0]                      # body -> ICRS (passive rotation of the body's axes)
    R_body = A @ R_icrs
    s = sun_icrs(spec)
    sun_cam = np.einsum("tij,j->ti", A, s)
    o = -pos_cam / rng_m[:, None]                                # target -> camera
    phase = np.arccos(np.clip(np.einsum("tk,tk->t", sun_cam, o), -1.0, 1.0))
    xy, _ = spec.camera.project(pos_cam)
    inside = (pos_cam[:, 2] > 0) & np.all(np.isfinite(xy), axis=1) & (xy[:, 0] >= 0) & \
        (xy[:, 0] < spec.camera.width) & (xy[:, 1] >= 0) & (xy[:, 1] < spec.camera.height)
    tc = TargetCases(inside, rng_m, pos_cam, R_body, sun_cam, np.broadcast_to(s, (len(t), 3)).copy(), phase)
    return {"A_true": A, "R": R, "u_true": u_true, "targets": tc}


def frame_view(spec: RendezvousSpec, geo: dict, truth: np.ndarray) -> KeepOut | None:
    """Each frame's Sun, Earth and Moon along the true boresight (``geo["A_true"]`` row 2) with
    ``[rendezvous.environment]`` (``scene/keepout.py``), else None.  Frame k at the epoch + t_k; the chaser at the
    reference orbit's position plus its Hill offset ``truth[:, :3]`` (km, GCRS); the Sun and Moon of
    ``scene/ephemeris.py`` at each frame's time."""
    env = spec.cfg.environment
    if env is None:
        return None
    jd = jd_tt_from_unix(env.epoch_unix_s + spec.times)
    R = geo["R"]
    r_km = (spec.orbit.radius_m * R[:, :, 0] + np.einsum("tij,tj->ti", R, truth[:, :3])) / 1e3
    return keep_out(r_km, geo["A_true"][:, 2, :], sun_position(jd), moon_position(jd),
                    sun_half_rad=math.radians(env.sun_keepout_deg), earth_half_rad=math.radians(env.earth_keepout_deg),
                    moon_half_rad=math.radians(env.moon_keepout_deg))
