"""Poses of the camera, the body and its components at frame k, vectorised over frames.

Reference Sec. 2.2.3-2.2.4 and Table 2: every moving thing has an initial position and orientation and
a constant motion per frame -- a velocity (m/frame) and a rotation (deg/frame).

Conventions
-----------
* World frame: inertial.  Orientation is three 1-2-3 Euler angles (deg) ``o``; at frame k the angles
  are ``o + k w`` with ``w`` the rotation (deg/frame) -- the angles grow linearly, as a per-frame
  "rotation (5, 5, 5) deg/frame" reads.  Positions are ``p + k v``.
* ``euler123_to_dcm`` (scene/attitude.py) gives the passive matrix A mapping parent-frame vectors into
  the child frame.  The camera's A maps world vectors into the camera frame (docs/architecture.md: attitude
  matrices map inertial vectors into the camera frame); for the body and the components the
  local-to-parent (active) matrix is A^T.
* Components are placed relative to the body (position, orientation and motion in the body frame).
* The outputs are camera-frame transforms: a component-local point x maps to ``R @ x + t`` in the
  camera frame (+x along columns, +y along rows, +z along the boresight).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dualsight.scene.attitude import euler123_to_dcm


def euler_deg_to_local_to_parent(angles_deg) -> np.ndarray:
    """(..., 3) 1-2-3 Euler angles (deg) -> (..., 3, 3) local-to-parent rotations A^T."""
    a = np.asarray(angles_deg, dtype=np.float64)
    A = euler123_to_dcm(np.deg2rad(a.reshape(-1, 3)))
    return np.swapaxes(A, -1, -2).reshape(a.shape[:-1] + (3, 3))


def linear_motion(position, orientation_deg, velocity, rotation_deg, frames):
    """Position and orientation angles at the given frames.

    Parameters
    ----------
    position, orientation_deg, velocity, rotation_deg : (3,) initial position (m), initial 1-2-3 angles
        (deg), velocity (m/frame), rotation (deg/frame).
    frames : (K,) frame numbers (int or float).

    Returns
    -------
    pos : (K, 3) m;  angles_deg : (K, 3) deg.
    """
    k = np.asarray(frames, dtype=np.float64).reshape(-1, 1)
    pos = np.asarray(position, float) + k * np.asarray(velocity, float)
    ang = np.asarray(orientation_deg, float) + k * np.asarray(rotation_deg, float)
    return pos, ang


@dataclass(frozen=True)
class FramePoses:
    """Camera-frame poses of a satellite over K frames (everything a renderer needs but the geometry).

    Attributes
    ----------
    frames : (K,) frame numbers.
    R : (K, C, 3, 3) component-local -> camera rotation.
    t : (K, C, 3) component origin in the camera frame (m).
    R_body : (K, 3, 3) body -> camera rotation.
    t_body : (K, 3) body origin in the camera frame (m); the truth for range (``|t_body|``) and
        direction (``t_body / |t_body|``).
    light : (K, 3) unit vector towards the light source, camera frame.
    """

    frames: np.ndarray
    R: np.ndarray
    t: np.ndarray
    R_body: np.ndarray
    t_body: np.ndarray
    light: np.ndarray

    @property
    def true_range(self) -> np.ndarray:
        """(K,) distance camera -> body origin (m)."""
        return np.linalg.norm(self.t_body, axis=-1)

    @property
    def true_direction(self) -> np.ndarray:
        """(K, 3) unit vector camera -> body origin, camera frame."""
        return self.t_body / np.linalg.norm(self.t_body, axis=-1, keepdims=True)


def component_poses_in_body(cfg, frames) -> tuple[np.ndarray, np.ndarray]:
    """(K, C, 3, 3) component -> body rotations and (K, C, 3) component origins in the body frame."""
    frames = np.atleast_1d(np.asarray(frames, dtype=np.float64))
    Rs, ts = [], []
    for comp in cfg.components:  # a handful of components, each vectorised over frames
        pos, ang = linear_motion(comp.position, comp.orientation_deg, comp.velocity, comp.rotation_deg, frames)
        Rs.append(euler_deg_to_local_to_parent(ang))
        ts.append(pos)
    return np.stack(Rs, axis=1), np.stack(ts, axis=1)


def frame_poses(cfg, frames) -> FramePoses:
    """Poses of ``cfg`` (a :class:`~dualsight.scene.satellite.SatelliteConfig`) at ``frames``.

    Camera at frame k: position c_k, attitude A_k (world -> camera).  Body: position p_k, rotation
    B_k (body -> world).  Component i: position q_ik and rotation Q_ik in the body frame.  Then
    ``R = A_k B_k Q_ik``, ``t = A_k (p_k + B_k q_ik - c_k)``, light ``A_k L / |L|``.
    """
    frames = np.atleast_1d(np.asarray(frames, dtype=np.float64))
    cam, body = cfg.camera, cfg.body
    c, ca = linear_motion(cam.position, cam.orientation_deg, cam.velocity, cam.rotation_deg, frames)
    A = euler123_to_dcm(np.deg2rad(ca))                                    # (K,3,3) world -> camera
    p, ba = linear_motion(body.position, body.orientation_deg, body.velocity, body.rotation_deg, frames)
    B = euler_deg_to_local_to_parent(ba)                                    # (K,3,3) body -> world
    R_body = A @ B
    t_body = np.einsum("kij,kj->ki", A, p - c)
    L = np.asarray(cam.light_direction, dtype=np.float64)
    light = np.einsum("kij,j->ki", A, L / np.linalg.norm(L))
    return place_body(cfg, R_body, t_body, light, frames=frames)


def place_body(cfg, R_body, t_body, light, frames=0) -> FramePoses:
    """Poses for a body placed directly in the camera frame (Monte-Carlo sweeps).

    Parameters
    ----------
    cfg : SatelliteConfig (only its components' relative poses/motion are used).
    R_body : (K, 3, 3) body -> camera rotations.
    t_body : (K, 3) body origin in the camera frame (m).
    light : (K, 3) or (3,) direction towards the light, camera frame (normalised here).
    frames : scalar or (K,) frame numbers for the components' own motion relative to the body.
    """
    R_body = np.asarray(R_body, dtype=np.float64).reshape(-1, 3, 3)
    K = R_body.shape[0]
    t_body = np.broadcast_to(np.asarray(t_body, dtype=np.float64), (K, 3)).copy()
    fr = np.broadcast_to(np.asarray(frames, dtype=np.float64), (K,)).copy()
    Q, q = component_poses_in_body(cfg, fr)
    R = R_body[:, None] @ Q
    t = np.einsum("kij,kcj->kci", R_body, q) + t_body[:, None, :]
    L = np.broadcast_to(np.asarray(light, dtype=np.float64), (K, 3))
    L = L / np.linalg.norm(L, axis=-1, keepdims=True)
    return FramePoses(fr, R, t, R_body, t_body, L.copy())
