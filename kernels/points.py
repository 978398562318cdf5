"""Proximity-operations renderers (Taichi CPU), batched over B frames: ``paper`` and ``accurate``.

Both shade by the reference's Eqs. 2-3 (Phong-style, Sec. 2.2.4):

    R.V = 2 (N.V)(N.L) - (V.L)                                       (Eq. 2)
    I   = I_a k_a + I_l (k_l max(N.L, 0) + k_s max(R.V, 0)^n)        (Eq. 3, clamped)

with N the unit surface normal, L the unit vector towards the (distant) light, V the unit vector
from the surface point to the camera.  Clamping choices (the paper's Eq. 3 has none):

* diffuse ``max(N.L, 0)``: a surface facing away from the light gets ambient light only;
* the specular term is added only when ``N.L > 0`` (no highlight on a self-shadowed surface) and
  uses ``max(R.V, 0)^n``;
* a zero normal (cuboid edge points) gets ambient light only, ``I = I_a k_a`` -- Eq. 2 with N = 0
  would otherwise give R.V = -(V.L), a spurious specular term.

``paper`` -- the reference's point-cloud splatter.  Every point is moved into the camera frame,
back-facing points (N.V < 0, non-zero N) are dropped (exact self-occlusion for the convex
primitives), the rest are projected (pinhole + the camera's distortion) and the *nearest* point per
pixel wins: pass 1 keeps, per pixel, the minimum of a 64-bit key (depth bits << 32 | point index)
in a z-buffer (one frame per task, so no atomics), pass 2 shades the winner of every pixel of the
frame's bounding box and resets the z-buffer.  A point lights the whole pixel it falls in, so the
image keeps the reference's artifacts: holes when the point spacing projects to more than a pixel
(up close) and whole-pixel blobs far away.  Zero-normal edge points are never culled.

``accurate`` -- rasterises the surfaces instead: every component is a closed convex triangle mesh
(scene/primitives.py), back faces are culled in 3-D, and each front triangle's exact coverage of
every pixel it touches is computed analytically (fully inside / outside by the edge functions at
the pixel centre +- half the pixel's extent along the edge normal; otherwise the pixel square is
clipped by the triangle's three half-planes, Sutherland & Hodgman 1974, and the clipped polygon's
area and centroid taken by the shoelace formula), in float64.  The fragment is shaded at the
clipped polygon's centroid with perspective-correct interpolation of position and normal.  For one
component the coverage image sums to the exact projected area in pixels (the front faces of a
convex body tile its silhouette without overlap): no holes up close, exact partial pixels far away.

Several components (occlusion, ``depth_test``): the triangles of a frame are ordered component by
component, front to back (each component by its nearest front triangle).  Pass 1 records per pixel
the nearest depth of any triangle covering the *whole* pixel; fragments behind it are dropped (a
true per-pixel z-buffer for fully covered pixels, whatever the order).  Pass 2 gathers, per pixel,
one component's fragments (summed coverage and coverage x intensity, and the union of their 8 x 8
sub-pixel sample masks) and composites them when the next component reaches the pixel or the row
ends: the component keeps the share of its samples not already taken by the components composited
before it, ``vis = min(coverage x free/own samples, 1 - coverage so far)``.  So partly covered
pixels where components overlap are resolved to 1/64 of a pixel; a component whose fragments in a
pixel hit no sample (slivers) is given the average free share.

The rendering work is limited to each frame's bounding box; scratch buffers cover the batch's
largest bounding box only.  Triangles with a vertex within 0.1 mm of the camera plane are dropped
(no near-plane clipping; the camera is never inside the target at resolvable ranges).

Inputs are plain arrays (kernels are leaves): geometry in component-local frames plus per-frame
component -> camera transforms ``x_cam = R[b, c] @ x + t[b, c]``.  ``camera`` is any object with
``width, height, fx, fy, cx, cy, distortion`` (scene.camera.Camera fits).  Pixel coordinates
follow DESIGN.md: (col, row) from the top-left corner, pixel (i, j) spans [i, i+1) x [j, j+1).

Outputs are float32 ``image`` (B, H, W) -- sum of coverage x Eq. 3 intensity -- and ``coverage``
(B, H, W) in [0, 1] (``paper``: 1 where a point landed).
"""

import math

import numpy as np

from dualsight.kernels._runtime import ensure_init

MODES = ("paper", "accurate")
_MAXU64 = 0xFFFFFFFFFFFFFFFF
_ZNEAR = 1e-4  # m; geometry closer to the camera plane is dropped

_K: dict = {}
_ZBUF: dict = {}


def _cam_vec(camera) -> np.ndarray:
    d = tuple(getattr(camera, "distortion", (0.0,) * 5)) + (0.0,) * 5
    return np.array([camera.fx, camera.fy, camera.cx, camera.cy, *d[:5]], dtype=np.float64)


def _kernels() -> dict:
    """Build (once) the Taichi functions and kernels; initialises Taichi lazily."""
    if _K:
        return _K
    ti = ensure_init()
    f32 = ti.f32
    nd = ti.types.ndarray

    @ti.func
    def shade(p, n, L, ka, kl, ks, ne, Ia, Il):
        """Eq. 3 at camera-frame point p with (not necessarily unit) normal n; L unit, towards the light."""
        V = -p / p.norm()
        I = Ia * ka
        nn = n.norm_sqr()
        if nn > 0:
            N = n / ti.sqrt(nn)
            NL = N.dot(L)
            if NL > 0:
                RV = 2.0 * N.dot(V) * NL - V.dot(L)          # Eq. 2
                spec = 0.0
                if RV > 0:
                    spec = ks * ti.pow(RV, ne)
                I += Il * (kl * NL + spec)
        return I

    @ti.func
    def project(p, cam):
        """Pinhole + OpenCV radial-tangential distortion; returns (u, v) pixel coords from the corner."""
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
        return ti.Vector([R[b, c, 0, 0] * q[0] + R[b, c, 0, 1] * q[1] + R[b, c, 0, 2] * q[2] + t[b, c, 0],
                          R[b, c, 1, 0] * q[0] + R[b, c, 1, 1] * q[1] + R[b, c, 1, 2] * q[2] + t[b, c, 1],
                          R[b, c, 2, 0] * q[0] + R[b, c, 2, 1] * q[1] + R[b, c, 2, 2] * q[2] + t[b, c, 2]])

    @ti.func
    def rotate(R: ti.template(), b, c, q):
        return ti.Vector([R[b, c, 0, 0] * q[0] + R[b, c, 0, 1] * q[1] + R[b, c, 0, 2] * q[2],
                          R[b, c, 1, 0] * q[0] + R[b, c, 1, 1] * q[1] + R[b, c, 1, 2] * q[2],
                          R[b, c, 2, 0] * q[0] + R[b, c, 2, 1] * q[1] + R[b, c, 2, 2] * q[2]])

    # ------------------------------------------------------------------ paper: points
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
                        if p[2] > _ZNEAR:
                            u, v = 0.0, 0.0
                            if distorted:
                                uv = project(p, camv)
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
                    if key != ti.u64(_MAXU64):
                        i = ti.cast(key & ti.u64(0xFFFFFFFF), ti.i32)
                        c = comp[i]
                        p = xform(R, t, b, c, ti.Vector([pts[i, 0], pts[i, 1], pts[i, 2]]))
                        n = rotate(R, b, c, ti.Vector([nrm[i, 0], nrm[i, 1], nrm[i, 2]]))
                        img[b, y, x] = shade(p, n, L, mat[c, 0], mat[c, 1], mat[c, 2], mat[c, 3], Ia[b], Il[b])
                        cov[b, y, x] = 1.0
                        zbuf[b, y, x] = ti.u64(_MAXU64)

    # ------------------------------------------------------------------ accurate: triangles
    G = ti.f64  # geometry precision: edge functions and clipping in double, so that the coverages of
    #             two triangles sharing an edge add up to 1 to ~1e-12 (storage stays float32)

    @ti.func
    def band_span(xs, ys, y0, y1):
        """x-extent of the triangle (xs, ys) inside the horizontal band y0 <= y <= y1."""
        lo, hi = G(1e30), G(-1e30)
        for k in ti.static(range(3)):
            if ys[k] >= y0 and ys[k] <= y1:
                lo = ti.min(lo, xs[k])
                hi = ti.max(hi, xs[k])
        for k in ti.static(range(3)):
            k1 = (k + 1) % 3
            for yl in ti.static([0, 1]):
                yy = y0 if yl == 0 else y1
                if (ys[k] - yy) * (ys[k1] - yy) < 0:
                    xi = xs[k] + (yy - ys[k]) * (xs[k1] - xs[k]) / (ys[k1] - ys[k])
                    lo = ti.min(lo, xi)
                    hi = ti.max(hi, xi)
        return lo, hi

    @ti.func
    def clip_pixel(ea, eb, ec):
        """Area and centroid (pixel-local coords) of the unit square clipped by a.x + b.y + c >= 0 (x3)."""
        px = ti.Vector([0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], dt=G)
        py = ti.Vector([0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], dt=G)
        qx = ti.Vector.zero(G, 10)
        qy = ti.Vector.zero(G, 10)
        n = 4
        for k in ti.static(range(3)):
            m = 0
            for j in range(n):
                j1 = (j + 1) % n
                dj = ea[k] * px[j] + eb[k] * py[j] + ec[k]
                dn = ea[k] * px[j1] + eb[k] * py[j1] + ec[k]
                if dj >= 0:
                    qx[m] = px[j]
                    qy[m] = py[j]
                    m += 1
                if (dj >= 0 and dn < 0) or (dj < 0 and dn >= 0):
                    s = dj / (dj - dn)
                    qx[m] = px[j] + s * (px[j1] - px[j])
                    qy[m] = py[j] + s * (py[j1] - py[j])
                    m += 1
            n = m
            for j in range(n):
                px[j] = qx[j]
                py[j] = qy[j]
        a2 = G(0.0)
        gx = G(0.0)
        gy = G(0.0)
        for j in range(n):
            j1 = (j + 1) % n
            cr = px[j] * py[j1] - px[j1] * py[j]
            a2 += cr
            gx += (px[j] + px[j1]) * cr
            gy += (py[j] + py[j1]) * cr
        cx, cy = G(0.5), G(0.5)
        if a2 > 1e-12:
            cx = gx / (3.0 * a2)
            cy = gy / (3.0 * a2)
        return ti.max(0.5 * a2, G(0.0)), cx, cy

    @ti.func
    def tri_setup(px: ti.template(), k):
        """Edge functions e_i(x, y) = a_i x + b_i y + c_i (unit normals, >= 0 inside), edge lengths, |2 area|."""
        xs = ti.Vector([px[k, 0], px[k, 2], px[k, 4]], dt=G)
        ys = ti.Vector([px[k, 1], px[k, 3], px[k, 5]], dt=G)
        area2 = (xs[1] - xs[0]) * (ys[2] - ys[0]) - (xs[2] - xs[0]) * (ys[1] - ys[0])
        s = G(1.0) if area2 > 0 else G(-1.0)
        ea = ti.Vector.zero(G, 3)
        eb = ti.Vector.zero(G, 3)
        ec = ti.Vector.zero(G, 3)
        ln = ti.Vector.zero(G, 3)
        for e in ti.static(range(3)):
            e1 = (e + 1) % 3
            dx = xs[e1] - xs[e]
            dy = ys[e1] - ys[e]
            l = ti.sqrt(dx * dx + dy * dy) + 1e-300
            ea[e] = -s * dy / l
            eb[e] = s * dx / l
            ec[e] = -(ea[e] * xs[e] + eb[e] * ys[e])
            ln[e] = l
        return xs, ys, ti.abs(area2), ea, eb, ec, ln

    @ti.func
    def fragment(ea, eb, ec, x, y):
        """Coverage of pixel (x, y) by the triangle and the point (absolute coords) to shade at."""
        fx = ti.cast(x, G)
        fy = ti.cast(y, G)
        e = ea * (fx + 0.5) + eb * (fy + 0.5) + ec
        r = 0.5 * (ti.abs(ea) + ti.abs(eb))
        cov, gx, gy = G(0.0), fx + 0.5, fy + 0.5
        if e[0] >= r[0] and e[1] >= r[1] and e[2] >= r[2]:
            cov = G(1.0)
        elif e[0] > -r[0] and e[1] > -r[1] and e[2] > -r[2]:
            a, lx, ly = clip_pixel(ea, eb, ea * fx + eb * fy + ec)     # pixel-local coordinates
            cov = a
            gx = fx + lx
            gy = fy + ly
        return cov, gx, gy

    @ti.func
    def interp(pc: ti.template(), k, ea, eb, ec, ln, area2, gx, gy):
        """Perspective-correct depth (m) and vertex weights at pixel point (gx, gy)."""
        # screen-space barycentric of vertex v is the edge function of the opposite edge (v+1 -> v+2)
        lam = ti.Vector([(ea[1] * gx + eb[1] * gy + ec[1]) * ln[1],
                         (ea[2] * gx + eb[2] * gy + ec[2]) * ln[2],
                         (ea[0] * gx + eb[0] * gy + ec[0]) * ln[0]]) / area2
        w = ti.Vector([lam[0] / pc[k, 2], lam[1] / pc[k, 5], lam[2] / pc[k, 8]])
        zi = 1.0 / (w[0] + w[1] + w[2])
        return ti.cast(zi, f32), ti.cast(w * zi, f32)

    @ti.func
    def sample_mask(ea, eb, ec, x, y):
        """64-bit mask of the 8 x 8 sub-pixel samples of pixel (x, y) inside the triangle."""
        el = ea * ti.cast(x, G) + eb * ti.cast(y, G) + ec
        m = ti.u64(0)
        for j in range(8):
            sy = (ti.cast(j, G) + 0.5) * 0.125
            for i in range(8):
                sx = (ti.cast(i, G) + 0.5) * 0.125
                e = ea * sx + eb * sy + el
                if e[0] >= 0 and e[1] >= 0 and e[2] >= 0:
                    m |= ti.u64(1) << ti.cast(j * 8 + i, ti.u64)
        return m

    @ti.func
    def resolve(b, ys0, xl, y, x, smask: ti.template(), sid: ti.template(), pend: ti.template(),
                img: ti.template(), cov: ti.template()):
        """Composite the pending fragments of one component into pixel (x, y): the share of its sample
        mask not taken by the components composited before it (front to back) scales its coverage."""
        cc = pend[b, ys0, xl, 0]
        if cc > 0:
            cm = smask[b, ys0, xl, 1]
            pm = smask[b, ys0, xl, 0]
            nm = ti.math.popcnt(cm)
            frac = ti.cast(1.0, f32)
            if nm > 0:
                frac = ti.cast(ti.math.popcnt(cm & ~pm), f32) / ti.cast(nm, f32)
            else:                      # slivers between the samples: assume the average free share
                frac = 1.0 - ti.cast(ti.math.popcnt(pm), f32) / 64.0
            vis = ti.min(cc * frac, 1.0 - cov[b, y, x])
            if vis > 0:
                img[b, y, x] += pend[b, ys0, xl, 1] / cc * vis
                cov[b, y, x] += vis
            smask[b, ys0, xl, 0] = pm | cm
        smask[b, ys0, xl, 1] = ti.u64(0)
        pend[b, ys0, xl, 0] = 0.0
        pend[b, ys0, xl, 1] = 0.0
        sid[b, ys0, xl] = 0

    @ti.kernel
    def tri_raster(px: nd(dtype=ti.f64, ndim=2), pc: nd(dtype=f32, ndim=2), pn: nd(dtype=f32, ndim=2),
                   tcomp: nd(dtype=ti.i32, ndim=1), mat: nd(dtype=f32, ndim=2), off: nd(dtype=ti.i32, ndim=1),
                   box: nd(dtype=ti.i32, ndim=2), light: nd(dtype=f32, ndim=2), Ia: nd(dtype=f32, ndim=1),
                   Il: nd(dtype=f32, ndim=1), depth_test: ti.i32, zfull: nd(dtype=f32, ndim=3),
                   smask: nd(dtype=ti.u64, ndim=4), sid: nd(dtype=ti.i32, ndim=3), pend: nd(dtype=f32, ndim=4),
                   img: nd(dtype=f32, ndim=3), cov: nd(dtype=f32, ndim=3)):
        B, H, W = img.shape[0], img.shape[1], img.shape[2]
        ti.loop_config(block_dim=2)
        for b, y in ti.ndrange(B, H):
            if y >= box[b, 1] and y <= box[b, 3]:
                fy0 = ti.cast(y, G)
                fy1 = fy0 + 1.0
                L = ti.Vector([light[b, 0], light[b, 1], light[b, 2]])
                ys0 = y - box[b, 1]          # scratch arrays cover the frame's bounding box only
                xs0 = box[b, 0]
                if depth_test != 0:
                    for x in range(box[b, 0], box[b, 2] + 1):
                        zfull[b, ys0, x - xs0] = 3.0e38
                        smask[b, ys0, x - xs0, 0] = ti.u64(0)
                        smask[b, ys0, x - xs0, 1] = ti.u64(0)
                        sid[b, ys0, x - xs0] = 0
                        pend[b, ys0, x - xs0, 0] = 0.0
                        pend[b, ys0, x - xs0, 1] = 0.0
                    # pass 1: nearest depth of any triangle covering the whole pixel
                    for k in range(off[b], off[b + 1]):
                        if ti.max(px[k, 1], px[k, 3], px[k, 5]) <= fy0 or ti.min(px[k, 1], px[k, 3], px[k, 5]) >= fy1:
                            continue
                        xs, ys, area2, ea, eb, ec, ln = tri_setup(px, k)
                        if area2 > 1e-9:
                            lo, hi = band_span(xs, ys, fy0, fy1)
                            x0 = ti.max(ti.cast(ti.floor(lo), ti.i32), 0)
                            x1 = ti.min(ti.cast(ti.ceil(hi), ti.i32), W)
                            for x in range(x0, x1):
                                cxp = ti.cast(x, G) + 0.5
                                e = ea * cxp + eb * (fy0 + 0.5) + ec
                                r = 0.5 * (ti.abs(ea) + ti.abs(eb))
                                if e[0] >= r[0] and e[1] >= r[1] and e[2] >= r[2]:
                                    zi, mu = interp(pc, k, ea, eb, ec, ln, area2, cxp, fy0 + 0.5)
                                    zfull[b, ys0, x - xs0] = ti.min(zfull[b, ys0, x - xs0], zi)
                for k in range(off[b], off[b + 1]):
                    if ti.max(px[k, 1], px[k, 3], px[k, 5]) <= fy0 or ti.min(px[k, 1], px[k, 3], px[k, 5]) >= fy1:
                        continue
                    xs, ys, area2, ea, eb, ec, ln = tri_setup(px, k)
                    if area2 > 1e-9:
                        lo, hi = band_span(xs, ys, fy0, fy1)
                        x0 = ti.max(ti.cast(ti.floor(lo), ti.i32), 0)
                        x1 = ti.min(ti.cast(ti.ceil(hi), ti.i32), W)
                        c = tcomp[k]
                        for x in range(x0, x1):
                            cv, gx, gy = fragment(ea, eb, ec, x, y)
                            if cv > 0:
                                zi, mu = interp(pc, k, ea, eb, ec, ln, area2, gx, gy)
                                xl = x - xs0
                                if depth_test == 0 or zi <= zfull[b, ys0, xl] * (1.0 + 1e-5):
                                    p = ti.Vector([mu[0] * pc[k, 0] + mu[1] * pc[k, 3] + mu[2] * pc[k, 6],
                                                   mu[0] * pc[k, 1] + mu[1] * pc[k, 4] + mu[2] * pc[k, 7],
                                                   zi])
                                    n = ti.Vector([mu[0] * pn[k, 0] + mu[1] * pn[k, 3] + mu[2] * pn[k, 6],
                                                   mu[0] * pn[k, 1] + mu[1] * pn[k, 4] + mu[2] * pn[k, 7],
                                                   mu[0] * pn[k, 2] + mu[1] * pn[k, 5] + mu[2] * pn[k, 8]])
                                    I = shade(p, n, L, mat[c, 0], mat[c, 1], mat[c, 2], mat[c, 3], Ia[b], Il[b])
                                    cvf = ti.cast(cv, f32)
                                    if depth_test == 0:
                                        # one convex component: its front triangles tile the silhouette
                                        vis = ti.min(cvf, 1.0 - cov[b, y, x])
                                        img[b, y, x] += vis * I
                                        cov[b, y, x] += vis
                                    else:
                                        # several components: a component's fragments in this pixel are
                                        # gathered (coverage, intensity, 8x8 sample mask) and composited
                                        # when the next component arrives or the row ends
                                        if sid[b, ys0, xl] != c + 1:
                                            resolve(b, ys0, xl, y, x, smask, sid, pend, img, cov)
                                            sid[b, ys0, xl] = c + 1
                                        fm = ti.u64(_MAXU64)
                                        if cv < 1.0:
                                            fm = sample_mask(ea, eb, ec, x, y)
                                        smask[b, ys0, xl, 1] |= fm
                                        pend[b, ys0, xl, 0] += cvf
                                        pend[b, ys0, xl, 1] += cvf * I
                if depth_test != 0:
                    for x in range(box[b, 0], box[b, 2] + 1):
                        resolve(b, ys0, x - xs0, y, x, smask, sid, pend, img, cov)

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
            if gg.dot(cen) < 0 and zmin > _ZNEAR:
                for v in ti.static(range(3)):
                    uv = project(ti.Vector([P[v, 0], P[v, 1], P[v, 2]]), camv)
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

    # ------------------------------------------------------------------ sensor effects
    @ti.func
    def mix64(z):
        z = (z ^ (z >> ti.u64(30))) * ti.u64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> ti.u64(27))) * ti.u64(0x94D049BB133111EB)
        return z ^ (z >> ti.u64(31))

    @ti.kernel
    def blur_rows(src: nd(dtype=f32, ndim=3), dst: nd(dtype=f32, ndim=3), w: nd(dtype=f32, ndim=1),
                  axis: ti.i32):
        B, H, W = src.shape[0], src.shape[1], src.shape[2]
        r = (w.shape[0] - 1) // 2
        for b, y in ti.ndrange(B, H):
            for x in range(W):
                s = 0.0
                for k in range(-r, r + 1):
                    if axis == 1:
                        xx = ti.min(ti.max(x + k, 0), W - 1)
                        s += w[k + r] * src[b, y, xx]
                    else:
                        yy = ti.min(ti.max(y + k, 0), H - 1)
                        s += w[k + r] * src[b, yy, x]
                dst[b, y, x] = s

    @ti.kernel
    def noise_quant(img: nd(dtype=f32, ndim=3), seeds: nd(dtype=ti.u64, ndim=1), read_noise: f32,
                    gain: f32, maxdn: f32):
        B, H, W = img.shape[0], img.shape[1], img.shape[2]
        for b, y in ti.ndrange(B, H):
            key0 = mix64(seeds[b] ^ ti.u64(0x2545F4914F6CDD1D))
            key1 = mix64(key0 ^ ti.u64(0x9E3779B97F4A7C15))
            for x in range(W):
                v = img[b, y, x] * gain
                if read_noise > 0:
                    idx = ti.cast(y * W + x, ti.u64) + ti.u64(1)
                    h0 = mix64(key0 + idx * ti.u64(0x9E3779B97F4A7C15))
                    h1 = mix64(key1 + idx * ti.u64(0x9E3779B97F4A7C15))
                    u1 = (ti.cast(h0 >> ti.u64(11), ti.f64) + 0.5) * (1.0 / 9007199254740992.0)
                    u2 = (ti.cast(h1 >> ti.u64(11), ti.f64) + 0.5) * (1.0 / 9007199254740992.0)
                    g = ti.sqrt(-2.0 * ti.log(u1)) * ti.cos(2.0 * math.pi * u2)
                    v += read_noise * ti.cast(g, f32)
                if maxdn > 0:
                    v = ti.min(ti.max(ti.round(v), 0.0), maxdn)
                img[b, y, x] = v

    _K.update(pts_zpass=pts_zpass, pts_shade=pts_shade, tri_raster=tri_raster, tri_transform=tri_transform,
              blur_rows=blur_rows, noise_quant=noise_quant)
    return _K


# ----------------------------------------------------------------------------- helpers
def _f32(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)


def _per_frame(v, B: int) -> np.ndarray:
    return _f32(np.broadcast_to(np.asarray(v, dtype=np.float32), (B,)))


def _poses(R, t, light):
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if R.ndim == 3:                      # (B, 3, 3) single component
        R, t = R[:, None], t[:, None]
    B = R.shape[0]
    L = np.broadcast_to(np.asarray(light, dtype=np.float64), (B, 3))
    L = L / np.linalg.norm(L, axis=-1, keepdims=True)
    return R, t, L, B


def _zbuf(nb: int, H: int, W: int) -> np.ndarray:
    """A persistent (nb, H, W) u64 z-buffer, all MAX; kernels reset what they touch."""
    key = (H, W)
    z = _ZBUF.get(key)
    if z is None or z.shape[0] < nb:
        z = np.full((nb, H, W), _MAXU64, dtype=np.uint64)
        _ZBUF[key] = z
    return z[:nb]


_GROUPED: dict = {}


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
    out = (_f32(np.asarray(cloud.points)[order]), _f32(np.asarray(cloud.normals)[order]),
           np.ascontiguousarray(comp[order], dtype=np.int32), cstart)
    if len(_GROUPED) > 8:
        _GROUPED.clear()
    _GROUPED[key] = (cloud.points, out)
    return out


# ----------------------------------------------------------------------------- public API
def render_points(cloud, materials, R, t, light, camera, I_a=0.3, I_l=1.0, *, chunk_frames: int = 8):
    """``paper`` mode: splat a point cloud with a z-buffer and shade by Eq. 3.

    Parameters
    ----------
    cloud : object with ``points`` (P, 3), ``normals`` (P, 3) and ``component`` (P,) in component-local
        frames (scene.primitives.PointCloud); float32 arrays avoid a copy.
    materials : (C, 4) [k_a, k_l, k_s, n] per component.
    R, t : (B, C, 3, 3) and (B, C, 3) component -> camera transforms (m), or (B, 3, 3), (B, 3) for C = 1.
    light : (B, 3) or (3,) direction towards the light, camera frame.
    camera : width, height, fx, fy, cx, cy, distortion.
    I_a, I_l : scalars or (B,) ambient and light intensities.

    Returns
    -------
    image, coverage : (B, H, W) float32.
    """
    K = _kernels()
    R, t, L, B = _poses(R, t, light)
    W, H = int(camera.width), int(camera.height)
    pts, nrm, comp, cstart = _grouped_cloud(cloud)
    mat = _f32(materials).reshape(-1, 4)
    if R.shape[1] < cstart.size - 1:
        raise ValueError(f"the cloud has {cstart.size - 1} components but R has {R.shape[1]}")
    cam = _cam_vec(camera)
    Ia, Il = _per_frame(I_a, B), _per_frame(I_l, B)
    img = np.zeros((B, H, W), np.float32)
    cov = np.zeros((B, H, W), np.float32)
    for s in range(0, B, chunk_frames):  # loop over chunks of frames (bounds the z-buffer's memory)
        e = min(s + chunk_frames, B)
        zb = _zbuf(e - s, H, W)
        bbox = np.tile(np.array([W, H, -1, -1], np.int32), (e - s, 1))
        Rc, tc = _f32(R[s:e]), _f32(t[s:e])
        K["pts_zpass"](pts, nrm, cstart, Rc, tc, cam, zb, bbox)
        K["pts_shade"](pts, nrm, comp, Rc, tc, mat, _f32(L[s:e]), Ia[s:e], Il[s:e], zb, bbox, img[s:e], cov[s:e])
    return img, cov


def prepare_triangles(mesh, R, t, camera):
    """Move a mesh into the camera frame per frame, cull back faces, project, sort front to back.

    Returns a dict of flat arrays (front triangles of all frames, frame-major) for :func:`render_mesh`:
    ``px`` (N, 6) float64 pixel coords of the 3 vertices, ``pc`` (N, 9) float32 camera-frame vertices,
    ``pn`` (N, 9) float32 camera-frame vertex normals, ``comp`` (N,) int32, ``off`` (B+1,) int32 and
    ``box`` (B, 4) int32 pixel bounding box [x0, y0, x1, y1] (inclusive; empty = x1 < x0).
    Within a frame the components come front to back (by their nearest front triangle) and each
    component's triangles front to back (by centroid depth).  Triangles with a vertex closer than
    0.1 mm to the camera plane are dropped (no near-plane clipping).
    """
    K = _kernels()
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
    K["tri_transform"](V, Nv, comp, np.ascontiguousarray(R), np.ascontiguousarray(t), _cam_vec(camera), W, H,
                       pc, pn, px, flag, ext)
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
    return dict(px=np.ascontiguousarray(px[bi, ti_]), pc=_f32(pc[bi, ti_]), pn=np.ascontiguousarray(pn[bi, ti_]),
                comp=np.ascontiguousarray(comp[ti_]), off=off, box=box)


def render_mesh(mesh, materials, R, t, light, camera, I_a=0.3, I_l=1.0, *, depth_test: bool | None = None):
    """``accurate`` mode: analytic-coverage rasterisation of triangle meshes, shaded by Eq. 3.

    Parameters
    ----------
    mesh : object with ``vertices`` (T, 3, 3), ``normals`` (T, 3, 3), ``component`` (T,) in component-
        local frames (scene.primitives.Mesh): closed convex components, outward winding.
    materials, R, t, light, camera, I_a, I_l : as :func:`render_points`.
    depth_test : per-pixel full-coverage depth pass; default on when there is more than one component
        (a single convex component needs none: back-face culling is exact).

    Returns
    -------
    image, coverage : (B, H, W) float32; ``coverage.sum((1, 2))`` is the projected area in pixels.
    """
    K = _kernels()
    R, t, L, B = _poses(R, t, light)
    W, H = int(camera.width), int(camera.height)
    mat = _f32(materials).reshape(-1, 4)
    if depth_test is None:
        depth_test = mat.shape[0] > 1 and np.unique(np.asarray(mesh.component)).size > 1
    tri = prepare_triangles(mesh, R, t, camera)
    Ia, Il = _per_frame(I_a, B), _per_frame(I_l, B)
    img = np.zeros((B, H, W), np.float32)
    cov = np.zeros((B, H, W), np.float32)
    # per-pixel scratch for the depth test, over the largest bounding box of the batch
    bw = max(int((tri["box"][:, 2] - tri["box"][:, 0]).max()) + 1, 1) if depth_test else 1
    bh = max(int((tri["box"][:, 3] - tri["box"][:, 1]).max()) + 1, 1) if depth_test else 1
    nb = B if depth_test else 1
    zfull = np.empty((nb, bh, bw), np.float32)
    smask = np.empty((nb, bh, bw, 2), np.uint64)
    sid = np.empty((nb, bh, bw), np.int32)
    pend = np.empty((nb, bh, bw, 2), np.float32)
    K["tri_raster"](tri["px"], tri["pc"], tri["pn"], tri["comp"], mat, tri["off"], tri["box"], _f32(L), Ia, Il,
                    int(bool(depth_test)), zfull, smask, sid, pend, img, cov)
    return img, cov


def render(mode: str, geometry, materials, R, t, light, camera, I_a=0.3, I_l=1.0, **kw):
    """Dispatch: ``paper`` -> :func:`render_points` (geometry = point cloud), ``accurate`` ->
    :func:`render_mesh` (geometry = mesh)."""
    if mode == "paper":
        return render_points(geometry, materials, R, t, light, camera, I_a, I_l, **kw)
    if mode == "accurate":
        return render_mesh(geometry, materials, R, t, light, camera, I_a, I_l, **kw)
    raise ValueError(f"unknown render mode {mode!r}; allowed: {', '.join(MODES)}")


def gaussian_weights(sigma_px: float) -> np.ndarray:
    """Normalised 1-D Gaussian taps, radius ceil(3 sigma)."""
    r = max(int(math.ceil(3.0 * sigma_px)), 1)
    k = np.arange(-r, r + 1, dtype=np.float64)
    w = np.exp(-0.5 * (k / sigma_px) ** 2)
    return (w / w.sum()).astype(np.float32)


def apply_sensor(images, *, psf_sigma_px: float = 0.0, read_noise: float = 0.0, gain: float = 1.0,
                 bits: int | None = None, seeds=None) -> np.ndarray:
    """Optional sensor effects on rendered images (B, H, W), returning a new float32 array.

    Order: Gaussian PSF blur (separable, sigma in pixels, edges clamped) -> scale by ``gain``
    (image units to DN) -> additive Gaussian read noise (DN, one counter-based SplitMix64 hash per
    (seed, pixel), so a frame is the same whatever batch it is in) -> quantisation to integers in
    [0, 2^bits - 1] when ``bits`` is given.
    """
    K = _kernels()
    out = _f32(np.array(images, dtype=np.float32, copy=True))
    if out.ndim == 2:
        out = out[None]
    B = out.shape[0]
    if psf_sigma_px > 0:
        w = gaussian_weights(psf_sigma_px)
        tmp = np.empty_like(out)
        K["blur_rows"](out, tmp, w, 1)
        K["blur_rows"](tmp, out, w, 0)
    if read_noise > 0 or bits or gain != 1.0:
        sd = np.zeros(B, np.uint64) if seeds is None else np.ascontiguousarray(
            np.broadcast_to(np.asarray(seeds, dtype=np.uint64), (B,)))
        maxdn = float(2 ** int(bits) - 1) if bits else 0.0
        K["noise_quant"](out, sd, float(read_noise), float(gain), maxdn)
    return out
