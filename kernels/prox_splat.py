"""``paper`` proximity renderer: the reference's point-cloud splatter with a z-buffer (Taichi CPU), batched
over B frames.

Every point is moved into the camera frame, back-facing points (N.V < 0, non-zero N) are dropped (exact
self-occlusion for the convex primitives), the rest are projected (pinhole + the camera's distortion) and
the *nearest* point per pixel wins: pass 1 (``pts_zpass``) keeps, per pixel, the minimum of a 64-bit key
(depth bits << 32 | point index) in a z-buffer (one frame per task, so no atomics), pass 2 (``pts_shade``)
shades the winner of every pixel of the frame's bounding box by Eqs. 2-3
(:func:`dualsight.kernels.prox_shading.shade`) and resets the z-buffer.  A point lights the whole pixel it
falls in, so the image keeps the reference's artifacts: holes when the point spacing projects to more than
a pixel (up close) and whole-pixel blobs far away.  Zero-normal edge points are never culled.
"""

import numpy as np
import taichi as ti

from dualsight.kernels import prox_geometry as geo
from dualsight.kernels.taichi_runtime import KernelCache
from dualsight.kernels.prox_shading import shade

__all__ = ["render_points"]

f32 = ti.f32
nd = ti.types.ndarray
_KERNELS = KernelCache()      # builders registered below
_ZBUF: dict = {}
_GROUPED: dict = {}


def _build_pts_zpass(_dtype=None):
    @ti.kernel
    def pts_zpass(pts: nd(dtype=f32, ndim=2), nrm: nd(dtype=f32, ndim=2), cstart: nd(dtype=ti.i32, ndim=1),
                  R: nd(dtype=f32, ndim=4), t: nd(dtype=f32, ndim=3), cam: nd(dtype=ti.f64, ndim=1),
                  zbuf: nd(dtype=ti.u64, ndim=3), bbox: nd(dtype=ti.i32, ndim=2)):
        # One frame per task: the frame's z-buffer is owned by one thread, so no atomics are needed.
        # Points are grouped by component (cstart: (C+1,) offsets) so each transform is loaded once.
        B, H, W = zbuf.shape[0], zbuf.shape[1], zbuf.shape[2]
        C = cstart.shape[0] - 1
        fx, fy, cx, cy = ti.cast(cam[0], f32), ti.cast(cam[1], f32), ti.cast(cam[2], f32), ti.cast(cam[3], f32)
        distorted = cam[4] != 0 or cam[5] != 0 or cam[6] != 0 or cam[7] != 0 or cam[8] != 0
        ti.loop_config(block_dim=1)
        for b in range(B):
            camv = ti.Vector([ti.cast(cam[k], f32) for k in ti.static(range(9))])
            xmin, ymin, xmax, ymax = W, H, -1, -1
            fW = ti.cast(W, f32)
            fH = ti.cast(H, f32)
            for c in range(C):
                M = ti.Matrix([[R[b, c, i, j] for j in ti.static(range(3))] for i in ti.static(range(3))])
                tv = ti.Vector([t[b, c, 0], t[b, c, 1], t[b, c, 2]])
                e = M.transpose() @ tv            # camera origin is at -e in the local frame
                for i in range(cstart[c], cstart[c + 1]):
                    x = ti.Vector([pts[i, 0], pts[i, 1], pts[i, 2]])
                    n = ti.Vector([nrm[i, 0], nrm[i, 1], nrm[i, 2]])
                    # N.V > 0  <=>  (R n).(R x + t) = n.(x + e) < 0; zero normals (edges) give 0: kept
                    if n.dot(x + e) <= 0:
                        p = M @ x + tv
                        if p[2] > geo.ZNEAR:
                            u, v = 0.0, 0.0
                            if distorted:
                                uv = geo.project(p, camv)
                                u, v = uv[0], uv[1]
                            else:
                                iz = 1.0 / p[2]
                                u = fx * p[0] * iz + cx
                                v = fy * p[1] * iz + cy
                            if u >= 0 and u < fW and v >= 0 and v < fH:
                                ix = ti.min(ti.cast(u, ti.i32), W - 1)
                                iy = ti.min(ti.cast(v, ti.i32), H - 1)
                                key = (ti.cast(ti.bit_cast(p[2], ti.u32), ti.u64) << ti.u64(32)) | ti.cast(i, ti.u64)
                                if key < zbuf[b, iy, ix]:
                                    zbuf[b, iy, ix] = key
                                xmin = ti.min(xmin, ix)
                                xmax = ti.max(xmax, ix)
                                ymin = ti.min(ymin, iy)
                                ymax = ti.max(ymax, iy)
            bbox[b, 0] = xmin
            bbox[b, 1] = ymin
            bbox[b, 2] = xmax
            bbox[b, 3] = ymax
    return pts_zpass


def _build_pts_shade(_dtype=None):
    @ti.kernel
    def pts_shade(pts: nd(dtype=f32, ndim=2), nrm: nd(dtype=f32, ndim=2), comp: nd(dtype=ti.i32, ndim=1),
                  R: nd(dtype=f32, ndim=4), t: nd(dtype=f32, ndim=3), mat: nd(dtype=f32, ndim=2),
                  light: nd(dtype=f32, ndim=2), Ia: nd(dtype=f32, ndim=1), Il: nd(dtype=f32, ndim=1),
                  zbuf: nd(dtype=ti.u64, ndim=3), bbox: nd(dtype=ti.i32, ndim=2),
                  img: nd(dtype=f32, ndim=3), cov: nd(dtype=f32, ndim=3)):
        B, H = img.shape[0], img.shape[1]
        ti.loop_config(block_dim=2)
        for b, y in ti.ndrange(B, H):
            if y >= bbox[b, 1] and y <= bbox[b, 3]:
                L = ti.Vector([light[b, 0], light[b, 1], light[b, 2]])
                for x in range(bbox[b, 0], bbox[b, 2] + 1):
                    key = zbuf[b, y, x]
                    if key != ti.u64(geo.MAXU64):
                        i = ti.cast(key & ti.u64(0xFFFFFFFF), ti.i32)
                        c = comp[i]
                        p = geo.xform(R, t, b, c, ti.Vector([pts[i, 0], pts[i, 1], pts[i, 2]]))
                        n = geo.rotate(R, b, c, ti.Vector([nrm[i, 0], nrm[i, 1], nrm[i, 2]]))
                        img[b, y, x] = shade(p, n, L, mat[c, 0], mat[c, 1], mat[c, 2], mat[c, 3], Ia[b], Il[b])
                        cov[b, y, x] = 1.0
                        zbuf[b, y, x] = ti.u64(geo.MAXU64)
    return pts_shade


_KERNELS.builders.update({"pts_zpass": _build_pts_zpass, "pts_shade": _build_pts_shade})


def _zbuf(nb: int, H: int, W: int) -> np.ndarray:
    """A persistent (nb, H, W) u64 z-buffer, all MAX; kernels reset what they touch."""
    key = (H, W)
    z = _ZBUF.get(key)
    if z is None or z.shape[0] < nb:
        z = np.full((nb, H, W), geo.MAXU64, dtype=np.uint64)
        _ZBUF[key] = z
    return z[:nb]


def _grouped_cloud(cloud):
    """float32 points/normals sorted (stably) by component, their component ids and (C+1,) offsets.

    Cached for the last few clouds (keyed by the identity of the arrays, which are kept alive)."""
    key = (id(cloud.points), id(cloud.normals), id(cloud.component))
    hit = _GROUPED.get(key)
    if hit is not None and hit[0] is cloud.points:
        return hit[1]
    comp = np.asarray(cloud.component, dtype=np.int64)
    order = np.argsort(comp, kind="stable")
    C = int(comp.max()) + 1 if comp.size else 0
    cstart = np.zeros(C + 1, np.int32)
    np.cumsum(np.bincount(comp, minlength=C), out=cstart[1:])
    out = (geo.as_f32(np.asarray(cloud.points)[order]), geo.as_f32(np.asarray(cloud.normals)[order]),
           np.ascontiguousarray(comp[order], dtype=np.int32), cstart)
    if len(_GROUPED) > 8:
        _GROUPED.clear()
    _GROUPED[key] = (cloud.points, out)
    return out


def render_points(cloud, materials, R, t, light, camera, I_a=0.3, I_l=1.0, *, chunk_frames: int = 8):
    """``paper`` mode: splat a point cloud with a z-buffer; each pixel shows its nearest point, shaded by
    Eqs. 2-3 (:func:`dualsight.kernels.prox_shading.shade`).

    Parameters
    ----------
    cloud : object with ``points`` (P, 3) (m), ``normals`` (P, 3) (unit, or 0 for edge points) and
        ``component`` (P,) int, in component-local frames (scene.primitives.PointCloud); float32 arrays
        avoid a copy.
    materials : (C, 4) float [k_a, k_l, k_s, n] per component (Eq. 3 coefficients, specular exponent).
    R, t : (B, C, 3, 3) and (B, C, 3) component -> camera transforms (m), or (B, 3, 3), (B, 3) for C = 1.
    light : (B, 3) or (3,) direction towards the light, camera frame (any length).
    camera : width, height (px), fx, fy, cx, cy (px), distortion (OpenCV k1, k2, p1, p2, k3).
    I_a, I_l : scalars or (B,) ambient and light intensities of Eq. 3 (image units).
    chunk_frames : frames per kernel call (bounds the chunk_frames x H x W uint64 z-buffer).

    Returns
    -------
    image : (B, H, W) float32 Eq. 3 intensity of each pixel's nearest point (0 where no point landed).
    coverage : (B, H, W) float32, 1 where a point landed, else 0.
    """
    R, t, L, B = geo.poses(R, t, light)
    W, H = int(camera.width), int(camera.height)
    pts, nrm, comp, cstart = _grouped_cloud(cloud)
    mat = geo.as_f32(materials).reshape(-1, 4)
    if R.shape[1] < cstart.size - 1:
        raise ValueError(f"the cloud has {cstart.size - 1} components but R has {R.shape[1]}")
    cam = geo.cam_vec(camera)
    Ia, Il = geo.per_frame(I_a, B), geo.per_frame(I_l, B)
    img = np.zeros((B, H, W), np.float32)
    cov = np.zeros((B, H, W), np.float32)
    for s in range(0, B, chunk_frames):  # loop over chunks of frames (bounds the z-buffer's memory)
        e = min(s + chunk_frames, B)
        zb = _zbuf(e - s, H, W)
        bbox = np.tile(np.array([W, H, -1, -1], np.int32), (e - s, 1))
        Rc, tc = geo.as_f32(R[s:e]), geo.as_f32(t[s:e])
        _KERNELS.get("pts_zpass")(pts, nrm, cstart, Rc, tc, cam, zb, bbox)
        _KERNELS.get("pts_shade")(pts, nrm, comp, Rc, tc, mat, geo.as_f32(L[s:e]), Ia[s:e], Il[s:e], zb, bbox,
                                  img[s:e], cov[s:e])
    return img, cov
