"""Camera-frame geometry shared by the proximity renderers: poses, transforms, projection.

Inputs are plain arrays (kernels are leaves): geometry in component-local frames plus per-frame
component -> camera transforms ``x_cam = R[b, c] @ x + t[b, c]`` (m).  ``camera`` is any object with
``width, height, fx, fy, cx, cy, distortion`` (scene.camera.Camera fits).  Pixel coordinates follow
docs/architecture.md: (col, row) from the top-left corner, pixel (i, j) spans [i, i+1) x [j, j+1).
"""

import numpy as np
import taichi as ti

MAXU64 = 0xFFFFFFFFFFFFFFFF   # an empty z-buffer entry
ZNEAR = 1e-4                  # m; geometry closer to the camera plane is dropped


def cam_vec(camera) -> np.ndarray:
    """(9,) float64 [fx, fy, cx, cy, k1, k2, p1, p2, k3] of ``camera`` (px; OpenCV distortion order)."""
    d = tuple(getattr(camera, "distortion", (0.0,) * 5)) + (0.0,) * 5
    return np.array([camera.fx, camera.fy, camera.cx, camera.cy, *d[:5]], dtype=np.float64)


def as_f32(a) -> np.ndarray:
    """``a`` as a C-contiguous float32 array (no copy when it already is one)."""
    return np.ascontiguousarray(a, dtype=np.float32)


def per_frame(v, B: int) -> np.ndarray:
    """A scalar or (B,) value as a (B,) float32 array."""
    return as_f32(np.broadcast_to(np.asarray(v, dtype=np.float32), (B,)))


def poses(R, t, light):
    """Validate per-frame poses and light.

    R, t : (B, C, 3, 3) and (B, C, 3) component -> camera transforms (m), or (B, 3, 3), (B, 3) for C = 1.
    light : (B, 3) or (3,) direction towards the light, camera frame (any length).
    Returns R (B, C, 3, 3) float64, t (B, C, 3) float64, unit light (B, 3) float64 and B.
    """
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if R.ndim == 3:                      # (B, 3, 3) single component
        R, t = R[:, None], t[:, None]
    B = R.shape[0]
    L = np.broadcast_to(np.asarray(light, dtype=np.float64), (B, 3))
    L = L / np.linalg.norm(L, axis=-1, keepdims=True)
    return R, t, L, B


@ti.func
def project(p, cam):
    """Pinhole + OpenCV radial-tangential distortion of camera-frame point p (m): (u, v) pixel coords from
    the image corner.  cam: the 9-vector of :func:`cam_vec`."""
    x = p[0] / p[2]
    y = p[1] / p[2]
    k1, k2, p1, p2, k3 = cam[4], cam[5], cam[6], cam[7], cam[8]
    if k1 != 0 or k2 != 0 or p1 != 0 or p2 != 0 or k3 != 0:
        r2 = x * x + y * y
        rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x, y = xd, yd
    return ti.Vector([cam[0] * x + cam[2], cam[1] * y + cam[3]])


@ti.func
def xform(R: ti.template(), t: ti.template(), b, c, q):
    """R[b, c] @ q + t[b, c]: a component-local point into the camera frame of frame b."""
    return ti.Vector([R[b, c, 0, 0] * q[0] + R[b, c, 0, 1] * q[1] + R[b, c, 0, 2] * q[2] + t[b, c, 0],
                      R[b, c, 1, 0] * q[0] + R[b, c, 1, 1] * q[1] + R[b, c, 1, 2] * q[2] + t[b, c, 1],
                      R[b, c, 2, 0] * q[0] + R[b, c, 2, 1] * q[1] + R[b, c, 2, 2] * q[2] + t[b, c, 2]])


@ti.func
def rotate(R: ti.template(), b, c, q):
    """R[b, c] @ q: a component-local direction into the camera frame of frame b."""
    return ti.Vector([R[b, c, 0, 0] * q[0] + R[b, c, 0, 1] * q[1] + R[b, c, 0, 2] * q[2],
                      R[b, c, 1, 0] * q[0] + R[b, c, 1, 1] * q[1] + R[b, c, 1, 2] * q[2],
                      R[b, c, 2, 0] * q[0] + R[b, c, 2, 1] * q[1] + R[b, c, 2, 2] * q[2]])
