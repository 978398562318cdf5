"""Proximity renderers (kernels/points.py) against independent truth.

Truth used here, none of it computed by the code under test:
- the exact perspective image of a cuboid: a planar face projects to the quadrilateral of its projected
  corners (pinhole), so the silhouette area is the sum over front faces of the shoelace areas (clipped
  to the frame with a Sutherland-Hodgman clipper written here);
- the orthographic projected area of a convex body A = 1/2 sum_i |n_i . v| A_i, times f^2 / z^2 far away;
- Eq. 2-3 evaluated by hand with numpy for a single point, and along the ray through a pixel centre
  for a flat face;
- occlusion geometry with faces parallel to the image plane (projected rectangles).
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from dualsight.kernels import points as KP
from dualsight.kernels.prox_raster import render_mesh
from dualsight.kernels.prox_sensor import apply_sensor
from dualsight.kernels.prox_splat import render_points
from dualsight.scene import primitives as prim
from dualsight.scene.attitude import quat_to_dcm, random_quaternions
from dualsight.scene.camera import Camera

CAM = Camera.pinhole(1024, 768, 4.65e-6, 6e-3)          # reference Table 1
F = CAM.fx
SIZE = np.array([0.1, 0.1, 0.3])                          # 3U CubeSat
AMBIENT = np.array([[1.0, 0.0, 0.0, 1.0]])                # k_a only
SHINY = np.array([[0.5, 0.8, 0.4, 12.0]])


def _shoelace(poly):
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _clip(poly, W, H):
    """Sutherland-Hodgman clip of a convex polygon to [0, W] x [0, H]."""
    for axis, bound, keep_less in ((0, 0, False), (0, W, True), (1, 0, False), (1, H, True)):
        out = []
        n = len(poly)
        for i in range(n):
            a, b = poly[i], poly[(i + 1) % n]
            ina = a[axis] <= bound if keep_less else a[axis] >= bound
            inb = b[axis] <= bound if keep_less else b[axis] >= bound
            if ina:
                out.append(a)
            if ina != inb:
                s = (bound - a[axis]) / (b[axis] - a[axis])
                out.append(a + s * (b - a))
        poly = np.array(out) if out else np.zeros((0, 2))
        if len(poly) == 0:
            break
    return poly


def cuboid_perspective_area(size, R, t, cam=CAM, clip=True):
    """Exact pixel area of a cuboid (rotation R, centre t, camera frame) by projecting its front faces."""
    h = np.asarray(size) / 2
    total = 0.0
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        for s in (-1.0, 1.0):
            q = np.zeros((4, 3))
            q[:, a] = s * h[a]
            q[:, b] = np.array([-1, 1, 1, -1]) * h[b]
            q[:, c] = np.array([-1, -1, 1, 1]) * h[c]
            n = np.zeros(3)
            n[a] = s
            qc = q @ R.T + t
            if np.dot(R @ n, qc.mean(axis=0)) >= 0:       # back face
                continue
            px, _ = cam.project(qc)
            total += _shoelace(_clip(px, cam.width, cam.height) if clip else px)
    return total


def _random_R(n, seed):
    return quat_to_dcm(random_quaternions(np.random.default_rng(seed), n))


def _render(mode, geom, mat, R, t, light=(0.3, -0.4, -1.0), **kw):
    return KP.render(mode, geom, mat, R[:, None], t[:, None], light, CAM, **kw)


# ----------------------------------------------------------------------------- accurate: exact areas
@pytest.mark.parametrize("rng_m", [0.5, 1.0, 3.0, 10.0, 100.0])
def test_accurate_area_equals_exact_perspective(rng_m):
    B = 6
    R = _random_R(B, int(rng_m * 10))
    off = np.random.default_rng(1).uniform(-0.15, 0.15, (B, 2)) * rng_m    # off-axis, up to ~8.5 deg
    t = np.column_stack([off, np.full(B, rng_m)])
    img, cov = _render("accurate", prim.cuboid_mesh(SIZE), SHINY, R, t)
    got = cov.sum(axis=(1, 2))
    exact = np.array([cuboid_perspective_area(SIZE, R[b], t[b]) for b in range(B)])
    assert np.all(cov <= 1.0 + 1e-5) and np.all(cov >= 0)
    assert np.allclose(got, exact, rtol=2e-4 if rng_m < 50 else 2e-3), (got, exact)
    if rng_m <= 1.0:
        assert np.all(exact > 1e4)                    # the brief's "blobs over 10^4 pixels" within 1 %


def test_accurate_area_far_matches_orthographic_formula():
    B = 8
    for rng_m in (40.0, 100.0):
        R = _random_R(B, 5)
        t = np.tile([0.0, 0.0, rng_m], (B, 1))
        _, cov = _render("accurate", prim.cuboid_mesh(SIZE), SHINY, R, t)
        v = R[:, 2, :]                                 # viewing direction (camera +z) in the body frame
        A = (np.abs(v[:, 0]) * SIZE[1] * SIZE[2] + np.abs(v[:, 1]) * SIZE[0] * SIZE[2]
             + np.abs(v[:, 2]) * SIZE[0] * SIZE[1])   # 1/2 sum |n.v| A_i
        expect = A * CAM.fx * CAM.fy / rng_m ** 2
        assert np.allclose(cov.sum(axis=(1, 2)), expect, rtol=0.01)
        # partly covered pixels: most blob pixels are fractional, yet the sum is exact
        assert np.mean((cov > 0) & (cov < 0.999)) > 0


def test_accurate_near_no_holes_and_frame_clipping():
    # a cube face-on at 0.2 m: its 0.1 m face spans 645 px, every pixel inside it fully covered
    R = np.eye(3)[None]
    t = np.array([[0.0, 0.0, 0.25]])                  # face at z = 0.2
    _, cov = _render("accurate", prim.cuboid_mesh((0.1, 0.1, 0.1)), AMBIENT, R, t)
    side = F * 0.1 / 0.2
    assert cov.sum() == pytest.approx(side * side, rel=1e-5)
    lo, hi = int(math.ceil(512 - side / 2)), int(math.floor(512 + side / 2))
    rlo, rhi = int(math.ceil(384 - side / 2)), int(math.floor(384 + side / 2))
    assert cov[0, rlo:rhi, lo:hi].min() == pytest.approx(1.0, abs=1e-6)       # no holes
    # a tilted 3U CubeSat at 0.3 m sticking out of the frame: exact clipped area
    R = _random_R(4, 11)
    t = np.tile([0.05, -0.02, 0.3], (4, 1))
    _, cov = _render("accurate", prim.cuboid_mesh(SIZE), SHINY, R, t)
    exact = np.array([cuboid_perspective_area(SIZE, R[b], t[b]) for b in range(4)])
    unclipped = np.array([cuboid_perspective_area(SIZE, R[b], t[b], clip=False) for b in range(4)])
    assert np.any(unclipped > exact * 1.01)           # some of it is cut by the frame
    assert np.allclose(cov.sum(axis=(1, 2)), exact, rtol=2e-4)


# ----------------------------------------------------------------------------- Eq. 2-3
def eq3(p, N, L, ka, kl, ks, n, Ia, Il):
    V = -p / np.linalg.norm(p)
    NL, NV, VL = N @ L, N @ V, V @ L
    RV = 2 * NV * NL - VL
    I = Ia * ka
    if NL > 0:
        I += Il * (kl * NL + ks * max(RV, 0.0) ** n)
    return I


def test_eq3_single_point_by_hand():
    p = np.array([0.012, -0.02, 2.0])
    N = np.array([0.2, -0.3, -1.0]); N /= np.linalg.norm(N)
    L = np.array([0.35, 0.1, -1.0]); L /= np.linalg.norm(L)
    mat = np.array([[0.3, 0.7, 0.5, 7.0]])
    Ia, Il = 0.4, 1.2
    V = -p / np.linalg.norm(p)
    NL, NV, VL = N @ L, N @ V, V @ L
    RV = 2 * NV * NL - VL                              # Eq. 2
    assert NL > 0 and RV > 0
    I_hand = Ia * 0.3 + Il * (0.7 * NL + 0.5 * RV ** 7)   # Eq. 3
    cloud = SimpleNamespace(points=p[None], normals=N[None], component=np.zeros(1, np.int32))
    img, cov = render_points(cloud, mat, np.eye(3)[None, None], np.zeros((1, 1, 3)), L, CAM, Ia, Il)
    u, v = F * p[0] / p[2] + 512, F * p[1] / p[2] + 384
    assert cov.sum() == 1 and cov[0, int(v), int(u)] == 1        # lands in pixel (floor u, floor v)
    assert img[0, int(v), int(u)] == pytest.approx(I_hand, rel=1e-5)
    # zero normal (cuboid edge point): ambient only; light behind the surface: ambient only
    for nrm, L2 in ((np.zeros(3), L), (N, -L)):
        cloud = SimpleNamespace(points=p[None], normals=nrm[None], component=np.zeros(1, np.int32))
        img, _ = render_points(cloud, mat, np.eye(3)[None, None], np.zeros((1, 1, 3)), L2, CAM, Ia, Il)
        assert img[0, int(v), int(u)] == pytest.approx(Ia * 0.3, rel=1e-6)
    # a back-facing point (N.V < 0) is not drawn
    cloud = SimpleNamespace(points=p[None], normals=-N[None], component=np.zeros(1, np.int32))
    img, cov = render_points(cloud, mat, np.eye(3)[None, None], np.zeros((1, 1, 3)), L, CAM, Ia, Il)
    assert cov.sum() == 0


def test_eq3_flat_face_accurate_per_pixel():
    # one face of a big thin plate, tilted, seen from 1.5 m: every fully covered pixel is Eq. 3 at
    # the point where the ray through the pixel centre meets the face
    ang = math.radians(25)
    R = np.array([[math.cos(ang), 0, math.sin(ang)], [0, 1, 0], [-math.sin(ang), 0, math.cos(ang)]])
    t = np.array([0.05, 0.03, 1.5])
    mesh = prim.cuboid_mesh((0.4, 0.3, 0.01))
    L = np.array([0.2, -0.5, -1.0]); L /= np.linalg.norm(L)
    mat = np.array([[0.2, 0.9, 0.6, 15.0]])
    img, cov = render_mesh(mesh, mat, R[None], t[None], L, CAM, 0.5, 1.3)
    N = R @ np.array([0, 0, -1.0])                     # the face towards the camera
    d0 = N @ (t + R @ np.array([0, 0, -0.005]))        # plane N.x = d0
    rng = np.random.default_rng(0)
    rows, cols = np.nonzero(cov[0] > 0.999999)
    pick = rng.choice(rows.size, 40, replace=False)
    for r, c in zip(rows[pick], cols[pick]):
        ray = np.array([(c + 0.5 - CAM.cx) / CAM.fx, (r + 0.5 - CAM.cy) / CAM.fy, 1.0])
        p = ray * d0 / (N @ ray)
        assert img[0, r, c] == pytest.approx(eq3(p, N, L, *mat[0], 0.5, 1.3), rel=2e-4)


# ----------------------------------------------------------------------------- occlusion
def _two_body_scene(front_x):
    """Plate (0.2 x 0.2 x 0.01, k_a 1) at z = 2 centred at x = front_x; cube (0.2, k_a 3) at z = 3."""
    R = np.tile(np.eye(3), (1, 2, 1, 1))
    t = np.array([[[front_x, 0.0, 2.0], [0.0, 0.0, 3.0]]])
    mat = np.array([[1.0, 0, 0, 1], [3.0, 0, 0, 1]])
    sizes = [(0.2, 0.2, 0.01), (0.2, 0.2, 0.2)]
    mesh = prim.concat_meshes([prim.cuboid_mesh(s, component_id=i) for i, s in enumerate(sizes)])
    cloud = prim.concat_clouds([prim.cuboid_points(s, 4e6, component_id=i) for i, s in enumerate(sizes)])
    return R, t, mat, mesh, cloud


@pytest.mark.parametrize("mode", ["paper", "accurate"])
def test_occlusion_hidden_component_not_seen(mode):
    R, t, mat, mesh, cloud = _two_body_scene(0.0)      # the cube is entirely behind the plate
    geom = mesh if mode == "accurate" else cloud
    img, cov = KP.render(mode, geom, mat, R, t, (0, 0, -1.0), CAM, 1.0, 1.0)
    assert img.max() == pytest.approx(1.0)             # only the plate's k_a I_a ever shows
    assert np.all((img == 0) | np.isclose(img, 1.0 * cov, atol=1e-5))
    if mode == "accurate":
        side = F * 0.2 / 1.995
        assert cov.sum() == pytest.approx(side * side, rel=1e-4)    # the plate's front face only
    # identical to the plate rendered alone
    if mode == "accurate":
        plate = prim.Mesh(mesh.vertices[mesh.component == 0], mesh.normals[mesh.component == 0],
                          mesh.component[mesh.component == 0])
    else:
        keep = cloud.component == 0
        plate = prim.PointCloud(cloud.points[keep], cloud.normals[keep], cloud.component[keep])
    alone, cov_alone = KP.render(mode, plate, mat[:1], R[:, :1], t[:, :1], (0, 0, -1.0), CAM, 1.0, 1.0)
    assert np.allclose(img, alone, atol=1e-6) and np.allclose(cov, cov_alone, atol=1e-6)


def test_occlusion_partial_accurate():
    # plate covering x in [-0.2, 0] at z = 1.995; cube front face x, y in [-0.1, 0.1] at z = 2.9
    R, t, mat, mesh, cloud = _two_body_scene(-0.1)
    img, cov = KP.render("accurate", mesh, mat, R, t, (0, 0, -1.0), CAM, 1.0, 1.0)
    plate = (F * 0.2 / 1.995) ** 2
    cube_visible = (F * 0.1 / 2.9) * (F * 0.2 / 2.9)   # the right half of its front face
    assert cov.sum() == pytest.approx(plate + cube_visible, rel=2e-4)
    assert (img.sum() - 1.0 * plate) / 3.0 == pytest.approx(cube_visible, rel=2e-3)
    # left of the image centre only the plate is seen, right of it only the cube (inside its rows)
    left = img[0, 300:460, 400:505]
    right = img[0, 345:420, 516:552]
    assert np.allclose(left[cov[0, 300:460, 400:505] > 0.999], 1.0)
    assert np.allclose(right, 3.0)


def test_occlusion_partial_paper():
    R, t, mat, mesh, cloud = _two_body_scene(-0.1)
    img, cov = KP.render("paper", cloud, mat, R, t, (0, 0, -1.0), CAM, 1.0, 1.0)
    # plate pixels (left half) never show the cube's k_a = 3
    assert np.all(img[0, :, :500][cov[0, :, :500] > 0] <= 1.0 + 1e-6)
    assert np.allclose(img[0, 345:420, 516:552], 3.0)


# ----------------------------------------------------------------------------- paper mode artifacts
def test_paper_mode_holes_near_and_whole_pixels_far():
    cloud = prim.cuboid_points(SIZE, 1e6)             # 1 mm spacing; a pixel is 0.78 mm at 1 m
    mesh = prim.cuboid_mesh(SIZE)
    R = _random_R(4, 2)
    near = np.tile([0.0, 0.0, 1.0], (4, 1))
    _, cov_p = _render("paper", cloud, SHINY, R, near)
    _, cov_a = _render("accurate", mesh, SHINY, R, near)
    frac = cov_p.sum(axis=(1, 2)) / cov_a.sum(axis=(1, 2))
    assert np.all(frac < 0.95) and frac.mean() < 0.9                               # holes
    far = np.tile([0.0, 0.0, 100.0], (4, 1))
    _, cov_p = _render("paper", cloud, SHINY, R, far)
    _, cov_a = _render("accurate", mesh, SHINY, R, far)
    assert np.all(cov_p.sum(axis=(1, 2)) > 1.3 * cov_a.sum(axis=(1, 2)))        # whole-pixel blobs
    assert np.array_equal(cov_p > 0, (cov_a > 0) & (cov_p > 0))                  # lit only where covered


# ----------------------------------------------------------------------------- batching, sensor
@pytest.mark.parametrize("mode", ["paper", "accurate"])
def test_frame_independent_of_batch(mode):
    geom = prim.cuboid_points(SIZE, 2.5e5) if mode == "paper" else prim.cuboid_mesh(SIZE)
    R = _random_R(5, 9)
    t = np.column_stack([np.zeros(5), np.zeros(5), np.geomspace(1, 50, 5)])
    img, cov = _render(mode, geom, SHINY, R, t)
    one, cov1 = _render(mode, geom, SHINY, R[3:4], t[3:4])
    assert np.array_equal(img[3], one[0]) and np.array_equal(cov[3], cov1[0])


def test_sensor_effects():
    img = np.zeros((3, 64, 80), np.float32)
    img[:, 30:34, 40:44] = 100.0
    blurred = apply_sensor(img, psf_sigma_px=1.5)
    assert blurred.sum() == pytest.approx(img.sum(), rel=1e-5)                 # flux kept
    assert blurred.max() < 100.0
    q = apply_sensor(img, gain=3.0, bits=8)
    assert q.max() == 255.0 and np.array_equal(q, np.round(q))
    noisy = apply_sensor(np.zeros((2, 256, 256), np.float32), read_noise=2.0, seeds=[7, 8])
    assert noisy[0].std() == pytest.approx(2.0, rel=0.03) and abs(noisy[0].mean()) < 0.05
    again = apply_sensor(np.zeros((1, 256, 256), np.float32), read_noise=2.0, seeds=[8])
    assert np.array_equal(again[0], noisy[1])                                   # same seed, same noise
    assert not np.array_equal(noisy[0], noisy[1])


def test_read_noise_is_the_counter_based_rng_stream():
    # pixel (r, c) of a frame with seed s: Box-Muller of the uniforms (numpy twins of kernels/rng.py) at counter
    # r * W + c under key0 = stream_key(s, STREAM_PROX_READ, 0) and key1 = derived_key(key0); 2 pi in float32
    from dualsight.kernels import rng
    seeds = np.array([7, 2**64 - 5, 123456789], np.uint64)
    H, W = 40, 56
    got = apply_sensor(np.zeros((3, H, W), np.float32), read_noise=2.5, seeds=seeds)
    idx = np.arange(H * W, dtype=np.uint64)[None]
    key0 = rng.stream_key_np(seeds[:, None], rng.STREAM_PROX_READ, 0)
    u1, u2 = rng.u01_key_np(key0, idx), rng.u01_key_np(rng.derived_key_np(key0), idx)
    g = np.sqrt(-2.0 * np.log(u1)) * np.cos(float(np.float32(2 * np.pi)) * u2)
    expect = (np.float32(2.5) * g.astype(np.float32)).reshape(3, H, W)
    np.testing.assert_allclose(got, expect, rtol=1e-6, atol=1e-6)   # libm cos/log may differ in the last bit
    assert np.mean(got == expect) > 0.99


def test_occlusion_partial_pixels_far_composite():
    # far away, components overlap inside partly covered pixels: the coverage must be the union of
    # the components' silhouettes.  Truth: each component rendered alone on a 32x finer camera,
    # the silhouettes OR-ed and averaged back to the coarse pixels.
    cam = Camera.pinhole(64, 48, 4.65e-6, 6e-3)
    S = 32
    fine = Camera(64 * S, 48 * S, 4.65e-6 / S, cam.fx * S, cam.fy * S, cam.cx * S, cam.cy * S)
    parts = [prim.cuboid_mesh((0.5, 0.5, 0.7)), prim.cylinder_mesh(0.2, 0.3, 64, position=(0, 0, 0.5)),
             prim.sphere_mesh(0.3, 32, position=(0, 0, -0.5)),
             prim.cuboid_mesh((1.0, 0.5, 0.02), position=(0.76, 0, 0))]
    mesh = prim.concat_meshes([prim.Mesh(m.vertices, m.normals, np.full(len(m), i, np.int32))
                               for i, m in enumerate(parts)])
    mat = np.array([[1.0, 0.5, 0.2, 5.0]] * 4)
    Rb = _random_R(6, 21)
    for b in range(6):
        R = np.repeat(Rb[b][None, None], 4, axis=1)
        t = np.repeat(np.array([[[0.1, -0.05, 400.0]]]), 4, axis=1)
        _, cov = KP.render("accurate", mesh, mat, R, t, (0.3, -0.2, -1.0), cam)
        union = np.zeros((48 * S, 64 * S), bool)
        for i, m in enumerate(parts):
            _, c = KP.render("accurate", m, mat[:1], R[:, :1], t[:, :1], (0.3, -0.2, -1.0), fine)
            union |= c[0] > 0.5
        truth = union.reshape(48, S, 64, S).mean(axis=(1, 3))
        assert cov.sum() == pytest.approx(truth.sum(), rel=0.02)
        assert np.abs(cov[0] - truth).max() < 0.1
