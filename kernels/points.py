"""Proximity-operations renderers (Taichi CPU), batched over B frames: ``paper`` and ``accurate``.

One module per stage; this one only dispatches (:func:`render`):

=====================  ==========================================================================
stage                  module
=====================  ==========================================================================
shading (Eqs. 2-3)     :mod:`dualsight.kernels.prox_shading` -- ``shade``, used by both renderers
camera geometry        :mod:`dualsight.kernels.prox_geometry` -- poses, transforms, projection
``paper``              :mod:`dualsight.kernels.prox_splat` -- :func:`render_points`: the reference's
                       point-cloud splatter with a z-buffer (holes up close, whole-pixel blobs far away)
``accurate``, 1        :mod:`dualsight.kernels.prox_triangles` -- :func:`prepare_triangles`: mesh into
                       the camera frame, back faces culled, projected, sorted front to back
``accurate``, 2        :mod:`dualsight.kernels.prox_raster` -- :func:`render_mesh`: exact pixel coverage
                       of every front triangle, occlusion between components to 1/64 px
sensor effects         :mod:`dualsight.kernels.prox_sensor` -- :func:`apply_sensor`: PSF blur, gain,
                       counter-based read noise, quantisation
=====================  ==========================================================================

Inputs are plain arrays (kernels are leaves): geometry in component-local frames plus per-frame
component -> camera transforms ``x_cam = R[b, c] @ x + t[b, c]``.  ``camera`` is any object with
``width, height, fx, fy, cx, cy, distortion`` (scene.camera.Camera fits).  Pixel coordinates
follow docs/architecture.md: (col, row) from the top-left corner, pixel (i, j) spans [i, i+1) x [j, j+1).

Outputs are float32 ``image`` (B, H, W) -- sum of coverage x Eq. 3 intensity -- and ``coverage``
(B, H, W) in [0, 1] (``paper``: 1 where a point landed).
"""

from dualsight.kernels.prox_raster import render_mesh
from dualsight.kernels.prox_splat import render_points

__all__ = ["MODES", "render"]

MODES = ("paper", "accurate")


def render(mode: str, geometry, materials, R, t, light, camera, I_a=0.3, I_l=1.0, **kw):
    """Render B frames of a target: ``paper`` -> :func:`render_points` (geometry = point cloud),
    ``accurate`` -> :func:`render_mesh` (geometry = triangle mesh); both shade by Eqs. 2-3.

    Arguments as those functions': materials (C, 4) [k_a, k_l, k_s, n]; R, t (B, C, 3, 3), (B, C, 3)
    component -> camera (m); light (B, 3) or (3,) towards the light, camera frame; I_a, I_l scalars or (B,).
    Returns image, coverage: (B, H, W) float32 each.
    """
    if mode == "paper":
        return render_points(geometry, materials, R, t, light, camera, I_a, I_l, **kw)
    if mode == "accurate":
        return render_mesh(geometry, materials, R, t, light, camera, I_a, I_l, **kw)
    raise ValueError(f"unknown render mode {mode!r}; allowed: {', '.join(MODES)}")
