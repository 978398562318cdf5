"""``accurate`` proximity renderer, stage 2: exact-coverage triangle rasterisation, shaded by Eqs. 2-3.

Rasterises the surfaces instead of splatting points: every component is a closed convex triangle mesh
(scene/primitives.py) whose front triangles come from :mod:`dualsight.kernels.prox_triangles`.  Each front
triangle's exact coverage of every pixel it touches is computed analytically (fully inside / outside by the
edge functions at the pixel centre +- half the pixel's extent along the edge normal; otherwise the pixel
square is clipped by the triangle's three half-planes, Sutherland & Hodgman 1974, and the clipped polygon's
area and centroid taken by the shoelace formula), in float64.  The fragment is shaded at the clipped
polygon's centroid with perspective-correct interpolation of position and normal
(:func:`dualsight.kernels.prox_shading.shade`, Eqs. 2-3).  For one component the coverage image sums to the
exact projected area in pixels (the front faces of a convex body tile its silhouette without overlap): no
holes up close, exact partial pixels far away.

Several components (occlusion, ``depth_test``): the triangles of a frame come component by component, front
to back.  Pass 1 records per pixel the nearest depth of any triangle covering the *whole* pixel; fragments
behind it are dropped (a true per-pixel z-buffer for fully covered pixels, whatever the order).  Pass 2
gathers, per pixel, one component's fragments (summed coverage and coverage x intensity, and the union of
their 8 x 8 sub-pixel sample masks) and composites them when the next component reaches the pixel or the row
ends: the component keeps the share of its samples not already taken by the components composited before
it, ``vis = min(coverage x free/own samples, 1 - coverage so far)``.  So partly covered pixels where
components overlap are resolved to 1/64 of a pixel; a component whose fragments in a pixel hit no sample
(slivers) is given the average free share.

The rendering work is limited to each frame's bounding box; scratch buffers cover the batch's largest
bounding box only.  One (frame, row) per task: no atomics.
"""

import numpy as np
import taichi as ti

from dualsight.kernels import prox_geometry as geo
from dualsight.kernels.taichi_runtime import KernelCache
from dualsight.kernels.prox_shading import shade
from dualsight.kernels.prox_triangles import prepare_triangles

__all__ = ["render_mesh"]

f32 = ti.f32
nd = ti.types.ndarray
G = ti.f64  # geometry precision: edge functions and clipping in double, so that the coverages of
#             two triangles sharing an edge add up to 1 to ~1e-12 (storage stays float32)
_KERNELS = KernelCache()      # builders registered below


@ti.func
def _band_span(xs, ys, y0, y1):
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
def _clip_pixel(ea, eb, ec):
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
def _tri_setup(px: ti.template(), k):
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
def _row_setup(px: ti.template(), k, fy0, fy1, W):
    """Triangle k's edge functions and the pixel columns [x0, x1) it may touch in the row band fy0 <= y <= fy1
    (x1 = x0 = 0 when it misses the band or is degenerate): area2, ea, eb, ec, ln, x0, x1."""
    area2 = G(0.0)
    ea = ti.Vector.zero(G, 3)
    eb = ti.Vector.zero(G, 3)
    ec = ti.Vector.zero(G, 3)
    ln = ti.Vector.zero(G, 3)
    x0, x1 = 0, 0
    if ti.max(px[k, 1], px[k, 3], px[k, 5]) > fy0 and ti.min(px[k, 1], px[k, 3], px[k, 5]) < fy1:
        xs, ys, a2, a, bb, c, l = _tri_setup(px, k)
        if a2 > 1e-9:
            area2, ea, eb, ec, ln = a2, a, bb, c, l
            lo, hi = _band_span(xs, ys, fy0, fy1)
            x0 = ti.max(ti.cast(ti.floor(lo), ti.i32), 0)
            x1 = ti.min(ti.cast(ti.ceil(hi), ti.i32), W)
    return area2, ea, eb, ec, ln, x0, x1


@ti.func
def _fragment(ea, eb, ec, x, y):
    """Coverage of pixel (x, y) by the triangle and the point (absolute coords) to shade at."""
    fx = ti.cast(x, G)
    fy = ti.cast(y, G)
    e = ea * (fx + 0.5) + eb * (fy + 0.5) + ec
    r = 0.5 * (ti.abs(ea) + ti.abs(eb))
    cov, gx, gy = G(0.0), fx + 0.5, fy + 0.5
    if e[0] >= r[0] and e[1] >= r[1] and e[2] >= r[2]:
        cov = G(1.0)
    elif e[0] > -r[0] and e[1] > -r[1] and e[2] > -r[2]:
        a, lx, ly = _clip_pixel(ea, eb, ea * fx + eb * fy + ec)     # pixel-local coordinates
        cov = a
        gx = fx + lx
        gy = fy + ly
    return cov, gx, gy


@ti.func
def _interp(pc: ti.template(), k, ea, eb, ec, ln, area2, gx, gy):
    """Perspective-correct depth (m) and vertex weights at pixel point (gx, gy)."""
    # screen-space barycentric of vertex v is the edge function of the opposite edge (v+1 -> v+2)
    lam = ti.Vector([(ea[1] * gx + eb[1] * gy + ec[1]) * ln[1],
                     (ea[2] * gx + eb[2] * gy + ec[2]) * ln[2],
                     (ea[0] * gx + eb[0] * gy + ec[0]) * ln[0]]) / area2
    w = ti.Vector([lam[0] / pc[k, 2], lam[1] / pc[k, 5], lam[2] / pc[k, 8]])
    zi = 1.0 / (w[0] + w[1] + w[2])
    return ti.cast(zi, f32), ti.cast(w * zi, f32)


@ti.func
def _sample_mask(ea, eb, ec, x, y):
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
def _resolve(b, ys0, xl, y, x, smask: ti.template(), sid: ti.template(), pend: ti.template(),
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


def _build_tri_raster(_dtype=None):
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
                        area2, ea, eb, ec, ln, x0, x1 = _row_setup(px, k, fy0, fy1, W)
                        for x in range(x0, x1):
                            cxp = ti.cast(x, G) + 0.5
                            e = ea * cxp + eb * (fy0 + 0.5) + ec
                            r = 0.5 * (ti.abs(ea) + ti.abs(eb))
                            if e[0] >= r[0] and e[1] >= r[1] and e[2] >= r[2]:
                                zi, mu = _interp(pc, k, ea, eb, ec, ln, area2, cxp, fy0 + 0.5)
                                zfull[b, ys0, x - xs0] = ti.min(zfull[b, ys0, x - xs0], zi)
                for k in range(off[b], off[b + 1]):
                    area2, ea, eb, ec, ln, x0, x1 = _row_setup(px, k, fy0, fy1, W)
                    c = tcomp[k]
                    for x in range(x0, x1):
                        cv, gx, gy = _fragment(ea, eb, ec, x, y)
                        if cv > 0:
                            zi, mu = _interp(pc, k, ea, eb, ec, ln, area2, gx, gy)
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
                                        _resolve(b, ys0, xl, y, x, smask, sid, pend, img, cov)
                                        sid[b, ys0, xl] = c + 1
                                    fm = ti.u64(geo.MAXU64)
                                    if cv < 1.0:
                                        fm = _sample_mask(ea, eb, ec, x, y)
                                    smask[b, ys0, xl, 1] |= fm
                                    pend[b, ys0, xl, 0] += cvf
                                    pend[b, ys0, xl, 1] += cvf * I
                if depth_test != 0:
                    for x in range(box[b, 0], box[b, 2] + 1):
                        _resolve(b, ys0, x - xs0, y, x, smask, sid, pend, img, cov)
    return tri_raster


_KERNELS.builders.update({"tri_raster": _build_tri_raster})


def render_mesh(mesh, materials, R, t, light, camera, I_a=0.3, I_l=1.0, *, depth_test: bool | None = None):
    """``accurate`` mode: exact-coverage rasterisation of triangle meshes, shaded by Eqs. 2-3
    (:func:`dualsight.kernels.prox_shading.shade`).

    Parameters
    ----------
    mesh : object with ``vertices`` (T, 3, 3) (m), ``normals`` (T, 3, 3) (unit vertex normals) and
        ``component`` (T,) int, in component-local frames (scene.primitives.Mesh): closed convex
        components, outward winding.
    materials : (C, 4) float [k_a, k_l, k_s, n] per component (Eq. 3 coefficients, specular exponent).
    R, t : (B, C, 3, 3) and (B, C, 3) component -> camera transforms (m), or (B, 3, 3), (B, 3) for C = 1.
    light : (B, 3) or (3,) direction towards the light, camera frame (any length).
    camera : width, height (px), fx, fy, cx, cy (px), distortion (OpenCV k1, k2, p1, p2, k3).
    I_a, I_l : scalars or (B,) ambient and light intensities of Eq. 3 (image units).
    depth_test : per-pixel full-coverage depth pass; default on when there is more than one component
        (a single convex component needs none: back-face culling is exact).

    Returns
    -------
    image : (B, H, W) float32, per pixel the sum of coverage x Eq. 3 intensity of the visible surfaces.
    coverage : (B, H, W) float32 in [0, 1]; ``coverage.sum((1, 2))`` is the projected area in pixels.
    """
    R, t, L, B = geo.poses(R, t, light)
    W, H = int(camera.width), int(camera.height)
    mat = geo.as_f32(materials).reshape(-1, 4)
    if depth_test is None:
        depth_test = mat.shape[0] > 1 and np.unique(np.asarray(mesh.component)).size > 1
    tri = prepare_triangles(mesh, R, t, camera)
    Ia, Il = geo.per_frame(I_a, B), geo.per_frame(I_l, B)
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
    _KERNELS.get("tri_raster")(tri["px"], tri["pc"], tri["pn"], tri["comp"], mat, tri["off"], tri["box"],
                               geo.as_f32(L), Ia, Il, int(bool(depth_test)), zfull, smask, sid, pend, img, cov)
    return img, cov
