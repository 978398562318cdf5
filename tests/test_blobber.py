"""Blob labelling/moments (kernels/blobs.py) and the blobber (nav/blobber.py) against independent truth.

Truth used here, none of it computed by the code under test:
- synthetic images of rectangles and rotated rectangles whose pixel counts, centroids and second
  moments are known in closed form (pixel-centre variance of n consecutive pixels: (n^2 - 1) / 12;
  a filled a x b rectangle: a^2 / 12, b^2 / 12);
- OpenCV's ``connectedComponentsWithStats`` (an independent labeller) on random images;
- Eq. 1 evaluated by hand, rho = f sqrt(A / (N p^2));
- the true pose of rendered targets (range, direction), and a sphere's circular silhouette.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from dualsight.catalogs.areas import area_table
from dualsight.kernels import points as KP
from dualsight.kernels.blobs import label_blobs
from dualsight.nav.blobber import BlobberConfig, moments_to_axes, run_blobber
from dualsight.nav.range import range_eq1, range_oblique
from dualsight.scene import primitives as prim
from dualsight.scene.attitude import quat_to_dcm, random_quaternions
from dualsight.scene.camera import Camera

CAM = Camera.pinhole(1024, 768, 4.65e-6, 6e-3)


@pytest.fixture(scope="module")
def table_3u(tmp_path_factory):
    return area_table(("cuboid", (0.1, 0.1, 0.3)), n=20000, cache_dir=tmp_path_factory.mktemp("cache"))


def _scene():
    img = np.zeros((120, 160), np.float32)
    img[20:40, 30:60] = 2.0                  # 30 x 20 rectangle, 600 px
    img[80:90, 100:110] = 5.0                # 10 x 10 square
    img[100, 10] = img[101, 11] = 1.0        # two diagonal neighbours
    return img


# ----------------------------------------------------------------------------- labelling
def test_labels_counts_moments_and_connectivity():
    img = _scene()
    o8 = label_blobs(img, 0.0, connectivity=8)
    o4 = label_blobs(img, 0.0, connectivity=4)
    assert o8["n_blobs"][0] == 3 and o4["n_blobs"][0] == 4
    s = o8["best"][0]
    assert s[0] == 600
    xs, ys = np.arange(30, 60) + 0.5, np.arange(20, 40) + 0.5
    assert s[1] / s[0] == pytest.approx(xs.mean()) and s[2] / s[0] == pytest.approx(ys.mean())
    cxx = s[3] / s[0] - (s[1] / s[0]) ** 2
    cyy = s[5] / s[0] - (s[2] / s[0]) ** 2
    cxy = s[4] / s[0] - s[1] * s[2] / s[0] ** 2
    assert cxx == pytest.approx((30 ** 2 - 1) / 12) and cyy == pytest.approx((20 ** 2 - 1) / 12)
    assert cxy == pytest.approx(0.0, abs=1e-9)
    assert s[6] == pytest.approx(1200.0)                       # sum of intensities
    assert list(o8["box"][0]) == [30, 20, 59, 39]
    assert o8["all"][0, 0] == 600 + 100 + 2


def test_labels_agree_with_opencv_on_random_images():
    rng = np.random.default_rng(5)
    imgs = (rng.random((6, 97, 131)) > 0.55).astype(np.float32) * rng.random((6, 97, 131)).astype(np.float32)
    for conn in (4, 8):
        out = label_blobs(imgs, 0.0, connectivity=conn, return_mask=True)
        for b in range(imgs.shape[0]):
            n, lab, stats, _ = cv2.connectedComponentsWithStats((imgs[b] > 0).astype(np.uint8), connectivity=conn)
            areas = stats[1:, cv2.CC_STAT_AREA]
            assert out["n_blobs"][b] == n - 1
            assert out["best"][b, 0] == areas.max()
            k = 1 + int(np.argmax(areas))                     # OpenCV numbers blobs in raster order too
            assert np.array_equal(out["mask"][b], lab == k)


def test_threshold_and_coverage_sums():
    img = _scene()
    cov = np.where(img > 0, 0.25, 0.0).astype(np.float32)
    out = label_blobs(img[None], 1.5, coverage=cov[None])
    assert out["n_blobs"][0] == 2                              # the 1.0 pixels are below threshold
    assert out["best"][0, 9] == pytest.approx(600 * 0.25)      # summed coverage
    empty = label_blobs(np.zeros((2, 10, 10), np.float32), 0.0)
    assert np.all(empty["n_blobs"] == 0) and np.all(empty["best"] == 0)


# ----------------------------------------------------------------------------- blobber pieces
def test_centre_of_brightness_and_axes(table_3u):
    img = np.zeros((1, 120, 160), np.float32)
    x = np.arange(30, 60)
    img[0, 20:40, 30:60] = x[None, :].astype(np.float32)       # brightness grows with the column
    res = run_blobber(img, CAM, table_3u)
    xc = x + 0.5
    assert res.cob_px[0, 0] == pytest.approx((x * xc).sum() / x.sum())
    assert res.cob_px[0, 1] == pytest.approx(30.0)
    # paper: binary moments of pixel centres; subpixel (coverage 1): + 1/12 -> exactly 30/20
    assert res.axis_ratio[0] == pytest.approx(math.sqrt((30 ** 2 - 1) / (20 ** 2 - 1)))
    sp = run_blobber(img, CAM, table_3u, BlobberConfig(estimator="subpixel"))
    assert sp.axis_ratio[0] == pytest.approx(1.5)
    assert sp.major_px[0] == pytest.approx(4 * 30 / math.sqrt(12))
    assert res.unit[0] == pytest.approx(CAM.backproject(res.cob_px[0]))


def test_silhouette_centre_ignores_the_brightness_and_weighs_the_coverage(table_3u):
    """The rectangle's centre (45, 30) whatever its brightness gradient (the centre of brightness leans to the
    bright side, above); ``subpixel`` weighs each pixel by its coverage: a half-covered last column moves the
    centre to the coverage's centroid, computed here by hand."""
    img = np.zeros((1, 120, 160), np.float32)
    x = np.arange(30, 60)
    img[0, 20:40, 30:60] = x[None, :].astype(np.float32) ** 2
    res = run_blobber(img, CAM, table_3u)
    assert res.centre_px[0] == pytest.approx([45.0, 30.0], abs=1e-12)
    assert res.cob_px[0, 0] > 46.0
    cov = np.where(img > 0, 1.0, 0.0).astype(np.float32)
    cov[0, 20:40, 59] = 0.5
    sp = run_blobber(img, CAM, table_3u, BlobberConfig(estimator="subpixel"), coverage=cov)
    xc = np.arange(30, 60) + 0.5
    w = np.where(np.arange(30, 60) == 59, 0.5, 1.0)
    assert sp.centre_px[0] == pytest.approx([(w * xc).sum() / w.sum(), 30.0], abs=1e-9)
    assert not np.isfinite(run_blobber(np.zeros((1, 20, 20), np.float32), CAM, table_3u).centre_px).any()


def test_rotated_rectangle_axes():
    a, b, th = 60.0, 20.0, math.radians(30)
    yy, xx = np.mgrid[0:200, 0:200] + 0.5
    u = (xx - 100) * math.cos(th) + (yy - 100) * math.sin(th)
    v = -(xx - 100) * math.sin(th) + (yy - 100) * math.cos(th)
    img = ((np.abs(u) <= a / 2) & (np.abs(v) <= b / 2)).astype(np.float32)
    s = label_blobs(img, 0.0)["best"][0]
    m = s[1] / s[0], s[2] / s[0]
    l1, l2, ratio, ang = moments_to_axes(s[3] / s[0] - m[0] ** 2 + 1 / 12, s[4] / s[0] - m[0] * m[1],
                                         s[5] / s[0] - m[1] ** 2 + 1 / 12)
    assert ratio == pytest.approx(3.0, rel=0.01)
    assert math.degrees(ang) == pytest.approx(30.0, abs=0.3)
    assert l1 == pytest.approx(a * a / 12, rel=0.02)


def test_eq1_by_hand():
    # 1000 pixels of 4.65 um behind 6 mm, area 0.03 m^2
    rho = 6e-3 * math.sqrt(0.03 / (1000 * 4.65e-6 ** 2))
    assert range_eq1(1000, 0.03, 6e-3, 4.65e-6) == pytest.approx(rho)
    assert rho == pytest.approx(1290.3226 * math.sqrt(3e-5), rel=1e-7)       # 7.0674 m
    f_px = 6e-3 / 4.65e-6
    assert range_oblique(1000, 0.03, f_px, f_px, 1.0) == pytest.approx(rho)
    assert range_oblique(1000, 0.03, f_px, f_px, math.cos(0.3)) == pytest.approx(rho / math.cos(0.3) ** 1.5)
    assert np.isnan(range_eq1(0, 0.03, 6e-3, 4.65e-6))


def test_not_found_and_targets(table_3u):
    img = np.zeros((2, 120, 160), np.float32)
    img[1] = _scene()
    res = run_blobber(img, CAM, table_3u)
    assert not res.found[0] and np.isnan(res.range_est[0]) and np.isnan(res.unit[0]).all()
    assert res.found[1] and res.n_pixels[1] == 600 and res.n_blobs[1] == 3
    allp = run_blobber(img, CAM, table_3u, BlobberConfig(target="all"))
    assert allp.n_pixels[1] == 702
    with pytest.raises(ValueError, match="estimator"):
        BlobberConfig(estimator="magic")
    with pytest.raises(ValueError, match="connectivity"):
        BlobberConfig(connectivity=6)
    cols = res.as_columns("prox_")
    assert "prox_range_est" in cols and "prox_unit_z" in cols and "prox_cov_xy" in cols


# ----------------------------------------------------------------------------- end to end
def _render(mode, geom, R, t, mat=np.array([[1.0, 0.0, 0.0, 1.0]]), light=(0, 0, -1.0)):
    return KP.render(mode, geom, mat, R[:, None], t[:, None], light, CAM, 0.5, 1.0)


@pytest.mark.parametrize("mode,estimator,tol", [("accurate", "subpixel", 0.01), ("accurate", "paper", 0.02),
                                                ("paper", "paper", 0.03)])
def test_sphere_axis_ratio_near_one_from_any_view(table_3u, mode, estimator, tol):
    B = 6
    R = quat_to_dcm(random_quaternions(np.random.default_rng(2), B))
    t = np.tile([0.0, 0.0, 2.0], (B, 1))
    geom = prim.sphere_mesh(0.3, 48) if mode == "accurate" else prim.sphere_points(0.3, 4e6)
    img, cov = _render(mode, geom, R, t, mat=np.array([[0.3, 0.8, 0.4, 10.0]]), light=(0.3, -0.2, -1.0))
    res = run_blobber(img, CAM, table_3u, BlobberConfig(estimator=estimator), coverage=cov)
    assert np.all(res.axis_ratio < 1 + tol), res.axis_ratio
    assert np.all(res.n_pixels > 7000)


def test_direction_to_off_axis_sphere():
    # ambient light only: the centre of brightness is the silhouette's centroid
    dirs = np.array([[0.1, -0.05, 1.0], [-0.2, 0.15, 1.0], [0.0, 0.0, 1.0]])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t = dirs * 6.0
    R = np.tile(np.eye(3), (3, 1, 1))
    img, cov = _render("accurate", prim.sphere_mesh(0.2, 64), R, t)
    res = run_blobber(img, CAM, area_table(("sphere", (0.2,)), cache=False))
    ang = np.arccos(np.clip(np.sum(res.unit * dirs, axis=1), -1, 1))
    assert np.all(ang < 2e-4), ang


def test_face_on_and_broadside_ranges(table_3u):
    # face-on (ratio 1, A/A0 = 1) and broadside (ratio 3, A/A0 = 3) 3U CubeSat at 10 m
    R = np.array([np.eye(3), [[0, 0, 1.0], [0, 1.0, 0], [-1.0, 0, 0]]])      # second: long axis along x
    t = np.tile([0.0, 0.0, 10.0], (2, 1))
    img, cov = _render("accurate", prim.cuboid_mesh((0.1, 0.1, 0.3)), R, t)
    res = run_blobber(img, CAM, table_3u, BlobberConfig(estimator="subpixel"), coverage=cov)
    assert res.axis_ratio == pytest.approx([1.0, 3.0], rel=0.01)
    assert np.all(res.range_min <= 10.0 * 1.005) and np.all(res.range_max >= 10.0 * 0.995)
    # face-on: the smallest area of the table is the true one -> range_min is the true range
    assert res.range_min[0] == pytest.approx(10.0, rel=0.02)
    # the paper estimator applies Eq. 1 as printed with the whole-pixel count
    pap = run_blobber(img, CAM, table_3u, BlobberConfig(estimator="paper"), coverage=cov)
    A = pap.area_rel_est * table_3u.A0_m2
    assert pap.range_est == pytest.approx(6e-3 * np.sqrt(A / (pap.n_pixels * 4.65e-6 ** 2)))
    assert np.all(pap.n_pixels >= res.n_blob)                # whole pixels >= covered area


def test_range_sweep_subpixel_beats_paper_far(table_3u):
    # Table 3 style: 3U CubeSat, random orientations; far away the paper estimator underestimates
    # (whole-pixel counts grow the blob) while the subpixel one stays unbiased
    B = 9
    R = quat_to_dcm(random_quaternions(np.random.default_rng(4), B))
    mesh = prim.cuboid_mesh((0.1, 0.1, 0.3))
    out = {}
    for r in (2.512, 63.1):
        t = np.tile([0.0, 0.0, r], (B, 1))
        img, cov = _render("accurate", mesh, R, t, mat=np.array([[0.5, 0.8, 0.3, 10.0]]), light=(0.3, -0.4, -1))
        for est in ("paper", "subpixel"):
            res = run_blobber(img, CAM, table_3u, BlobberConfig(estimator=est), coverage=cov)
            out[r, est] = np.mean(res.range_est / r - 1)
    assert abs(out[2.512, "subpixel"]) < 0.1
    assert out[63.1, "paper"] < -0.15                        # paper: large underestimate (Table 3: -33 %)
    assert abs(out[63.1, "subpixel"]) < abs(out[63.1, "paper"])
