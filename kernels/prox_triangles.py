"""``accurate`` proximity renderer, stage 1: triangles into the camera frame, back faces culled, projected, sorted.

Per (frame, triangle), in parallel (``tri_transform``, float64): the component's vertices and vertex normals
are moved into the camera frame (``x_cam = R[b, c] @ x + t[b, c]``), back faces (whose normal points away
from the camera) and triangles with a vertex within 0.1 mm of the camera plane are dropped (no near-plane
clipping: the camera is never inside the target at resolvable ranges), the rest projected (pinhole + the
camera's distortion).  numpy then keeps the front triangles that reach the image and orders them for the
rasteriser (:mod:`dualsight.kernels.prox_raster`): frame by frame, component by component front to back (by
each component's nearest front triangle), and inside a component front to back (by centroid depth).
"""

import numpy as np
import taichi as ti

from dualsight.kernels import prox_geometry as geo
from dualsight.kernels.taichi_runtime import KernelCache

__all__ = ["prepare_triangles"]

f32 = ti.f32
nd = ti.types.ndarray
_KERNELS = KernelCache()      # builders registered below


def _build_tri_transform(_dtype=None):
    @ti.kernel
    def tri_transform(V: nd(dtype=ti.f64, ndim=2), Nv: nd(dtype=ti.f64, ndim=2), comp: nd(dtype=ti.i32, ndim=1),
                      R: nd(dtype=ti.f64, ndim=4), t: nd(dtype=ti.f64, ndim=3), cam: nd(dtype=ti.f64, ndim=1),
                      W: ti.i32, H: ti.i32, pc: nd(dtype=ti.f64, ndim=3), pn: nd(dtype=f32, ndim=3),
                      px: nd(dtype=ti.f64, ndim=3), flag: nd(dtype=ti.i32, ndim=2), ext: nd(dtype=ti.f64, ndim=3)):
        """Per (frame, triangle): camera-frame vertices and normals, pixel coords, front/in-image flag,
        [umin, umax, vmin, vmax, centroid depth]."""
        B, T = flag.shape[0], flag.shape[1]
        for b, k in ti.ndrange(B, T):
            c = comp[k]
            M = ti.Matrix([[R[b, c, i, j] for j in ti.static(range(3))] for i in ti.static(range(3))], dt=ti.f64)
            tv = ti.Vector([t[b, c, 0], t[b, c, 1], t[b, c, 2]], dt=ti.f64)
            camv = ti.Vector([cam[i] for i in ti.static(range(9))], dt=ti.f64)
            P = ti.Matrix.zero(ti.f64, 3, 3)
            zmin = ti.f64(1e300)
            for v in ti.static(range(3)):
                q = M @ ti.Vector([V[k, 3 * v], V[k, 3 * v + 1], V[k, 3 * v + 2]], dt=ti.f64) + tv
                nn = M @ ti.Vector([Nv[k, 3 * v], Nv[k, 3 * v + 1], Nv[k, 3 * v + 2]], dt=ti.f64)
                for i in ti.static(range(3)):
                    P[v, i] = q[i]
                    pc[b, k, 3 * v + i] = q[i]
                    pn[b, k, 3 * v + i] = ti.cast(nn[i], f32)
                zmin = ti.min(zmin, q[2])
            gg = (ti.Vector([P[1, 0] - P[0, 0], P[1, 1] - P[0, 1], P[1, 2] - P[0, 2]])).cross(
                ti.Vector([P[2, 0] - P[0, 0], P[2, 1] - P[0, 1], P[2, 2] - P[0, 2]]))
            cen = ti.Vector([P[0, 0] + P[1, 0] + P[2, 0], P[0, 1] + P[1, 1] + P[2, 1],
                             P[0, 2] + P[1, 2] + P[2, 2]]) / 3.0
            f = 0
            umin, umax, vmin, vmax = ti.f64(1e300), ti.f64(-1e300), ti.f64(1e300), ti.f64(-1e300)
            if gg.dot(cen) < 0 and zmin > geo.ZNEAR:
                for v in ti.static(range(3)):
                    uv = geo.project(ti.Vector([P[v, 0], P[v, 1], P[v, 2]]), camv)
                    px[b, k, 2 * v] = uv[0]
                    px[b, k, 2 * v + 1] = uv[1]
                    umin = ti.min(umin, uv[0])
                    umax = ti.max(umax, uv[0])
                    vmin = ti.min(vmin, uv[1])
                    vmax = ti.max(vmax, uv[1])
                if umax > 0 and umin < W and vmax > 0 and vmin < H:
                    f = 1
            flag[b, k] = f
            ext[b, k, 0] = umin
            ext[b, k, 1] = umax
            ext[b, k, 2] = vmin
            ext[b, k, 3] = vmax
            ext[b, k, 4] = cen[2]
    return tri_transform


_KERNELS.builders.update({"tri_transform": _build_tri_transform})


def prepare_triangles(mesh, R, t, camera):
    """Move a mesh into the camera frame per frame, cull back faces, project, sort front to back.

    Parameters
    ----------
    mesh : object with ``vertices`` (T, 3, 3) (m), ``normals`` (T, 3, 3) and ``component`` (T,) int in
        component-local frames (scene.primitives.Mesh).
    R, t : (B, C, 3, 3) and (B, C, 3) component -> camera transforms (m), or (B, 3, 3), (B, 3) for C = 1.
    camera : width, height (px), fx, fy, cx, cy (px), distortion (OpenCV k1, k2, p1, p2, k3).

    Returns
    -------
    dict of flat arrays (front triangles of all frames, frame-major) for
    :func:`dualsight.kernels.prox_raster.render_mesh`: ``px`` (N, 6) float64 pixel coords (u, v) of the 3
    vertices, ``pc`` (N, 9) float32 camera-frame vertices (m), ``pn`` (N, 9) float32 camera-frame vertex
    normals, ``comp`` (N,) int32, ``off`` (B+1,) int32 (frame b's triangles are [off[b], off[b+1])) and
    ``box`` (B, 4) int32 pixel bounding box [x0, y0, x1, y1] (inclusive; empty = x1 < x0).  Within a frame
    the components come front to back (by their nearest front triangle) and each component's triangles
    front to back (by centroid depth).
    """
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if R.ndim == 3:
        R, t = R[:, None], t[:, None]
    B = R.shape[0]
    W, H = int(camera.width), int(camera.height)
    V = np.ascontiguousarray(np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 9))
    Nv = np.ascontiguousarray(np.asarray(mesh.normals, dtype=np.float64).reshape(-1, 9))
    comp = np.ascontiguousarray(mesh.component, dtype=np.int32)
    T = V.shape[0]
    pc = np.empty((B, T, 9))
    pn = np.empty((B, T, 9), np.float32)
    px = np.empty((B, T, 6))
    flag = np.empty((B, T), np.int32)
    ext = np.empty((B, T, 5))
    _KERNELS.get("tri_transform")(V, Nv, comp, np.ascontiguousarray(R), np.ascontiguousarray(t),
                                  geo.cam_vec(camera), W, H, pc, pn, px, flag, ext)
    bi, ti_ = np.nonzero(flag)
    zc = ext[bi, ti_, 4]
    cc = comp[ti_].astype(np.int64)
    C = int(comp.max()) + 1 if comp.size else 1
    near = np.full((B, C), np.inf)
    np.minimum.at(near, (bi, cc), zc)
    rank = np.argsort(np.argsort(near, axis=1, kind="stable"), axis=1)
    order = np.lexsort((zc, rank[bi, cc], bi))           # frame, component rank, depth
    bi, ti_ = bi[order], ti_[order]
    off = np.zeros(B + 1, np.int32)
    np.cumsum(np.bincount(bi, minlength=B), out=off[1:])
    box = np.tile(np.array([0, 0, -1, -1], np.int32), (B, 1))
    if bi.size:
        e = ext[bi, ti_]
        lo_u = np.full(B, np.inf); hi_u = np.full(B, -np.inf)
        lo_v = np.full(B, np.inf); hi_v = np.full(B, -np.inf)
        np.minimum.at(lo_u, bi, e[:, 0]); np.maximum.at(hi_u, bi, e[:, 1])
        np.minimum.at(lo_v, bi, e[:, 2]); np.maximum.at(hi_v, bi, e[:, 3])
        has = np.isfinite(lo_u)
        box[has, 0] = np.clip(np.floor(lo_u[has]), 0, W - 1)
        box[has, 1] = np.clip(np.floor(lo_v[has]), 0, H - 1)
        box[has, 2] = np.clip(np.ceil(hi_u[has]) - 1, 0, W - 1)
        box[has, 3] = np.clip(np.ceil(hi_v[has]) - 1, 0, H - 1)
    return dict(px=np.ascontiguousarray(px[bi, ti_]), pc=geo.as_f32(pc[bi, ti_]),
                pn=np.ascontiguousarray(pn[bi, ti_]), comp=np.ascontiguousarray(comp[ti_]), off=off, box=box)
