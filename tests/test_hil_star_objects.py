"""``hil star``'s unknown objects and ``--target`` (issue 23, point 3): detections that no catalog star explains,
their ICRS positions and magnitudes, and the target spacecraft's bearing and range.

Independent truths: the photometric zero point against fluxes made from a known one; the catalog match against a
brute-force loop; on the ESA tetra3 frames the counts of unknown objects (checked by eye: a red Hipparcos star is
explained, a warm pixel on the frame's edge and faint stars Hipparcos lacks are what remains); a Gaussian spot of
known flux planted into an ESA frame against astropy (its pixel through the plate solution's attitude) and an
aperture-photometry zero point of the plate solution's matched stars written out here; rendered frames with a 3U
CubeSat (scene/target_in_field.py) against the direction and range they were rendered with.
"""

from __future__ import annotations

import json
import math
import shutil

import cv2
import numpy as np
import pytest

from dualsight.nav.field_target import brightest_star_npix, pick_point_target
from dualsight.nav.photometric_zero_point import zero_point
from dualsight.nav.unknown_objects import UnknownConfig, explained_by_catalog
from helpers import ROOT, orion_field, run_cli, shared_real

CAMERA = ROOT / "examples" / "cameras" / "esa_tetra3.toml"
ESA = shared_real() / "esa_tetra3"
TRUTH = ESA / "truth.json"
ARCSEC = math.pi / (180 * 3600)


# ============================================================================================ pure stages
def test_zero_point_is_the_median_offset_and_its_robust_scatter():
    rng = np.random.default_rng([23, 3])
    V = rng.uniform(1.0, 7.0, 41)
    noise = rng.normal(0.0, 0.1, 41)
    flux = 10 ** (-0.4 * (V - 13.7 - noise))
    flux[0] *= 10.0                               # a blend: 2.5 mag off, must not move the median
    zp = zero_point(flux, V, use=np.r_[True, np.ones(40, bool)])
    offs = V + 2.5 * np.log10(flux)
    assert zp.n == 41 and zp.zp_mag == pytest.approx(np.median(offs), abs=1e-12)
    assert abs(zp.zp_mag - 13.7) < 0.05 and 0.06 < zp.scatter_mag < 0.15   # 1.4826 MAD of N(0, 0.1)
    sat = np.zeros(41, bool)
    sat[1:5] = True                               # saturated stars are left out of the fit
    assert zero_point(flux, V, use=~sat).n == 37
    assert zero_point([], []).n == 0 and math.isnan(zero_point([], []).zp_mag)


def test_catalog_explanation_against_a_brute_force_loop():
    rng = np.random.default_rng([23, 4])
    xy = rng.uniform(0, 100, (60, 2))
    mag = rng.uniform(3, 9, 60)
    rad = rng.uniform(0.5, 3.0, 60)
    cxy = rng.uniform(0, 100, (300, 2))
    cv = rng.uniform(2, 12, 300)
    ex, near, dist = explained_by_catalog(xy, mag, rad, cxy, cv, 3.0)
    for k in range(60):
        d = [math.hypot(*(xy[k] - c)) for c in cxy]
        assert ex[k] == any(d[j] <= rad[k] and cv[j] <= mag[k] + 3.0 for j in range(300))
        if ex[k]:
            assert near[k] == -1 and dist[k] == math.inf
        else:                                     # the unexplained ones: their nearest star, at any distance
            assert near[k] == int(np.argmin(d)) and dist[k] == pytest.approx(min(d))
    # a star exactly at the radius explains (<=), one a hair beyond does not; stars sharing a column are all seen
    one = explained_by_catalog(np.array([[10.0, 10.0]]), np.array([5.0]), np.array([2.0]),
                               np.array([[12.0, 10.0], [10.0, 30.0], [10.0, 12.0 + 1e-9]]), np.array([5.0, 5.0, 5.0]),
                               3.0)
    assert one[0][0]
    col = explained_by_catalog(np.array([[10.0, 10.0]]), np.array([5.0]), np.array([2.0]),
                               np.array([[10.0, 30.0], [10.0, 20.0], [10.0, 11.0]]), np.array([5.0, 5.0, 5.0]), 3.0)
    assert col[0][0]
    # planted bug seen failing: dropping the magnitude window (any faint star explains a bright light)
    assert not ex.all() and (~ex).sum() < 60


def test_brightest_star_blob_is_the_gaussian_contour():
    # F = 10^(0.4 (zp - V)); pixels above t: pi r^2 with F/(2 pi s^2) exp(-r^2 / 2 s^2) = t
    F = 10 ** (0.4 * (13.7 + 1.46))
    s, t = 0.7, 40.0
    r2 = -2 * s * s * math.log(t * 2 * math.pi * s * s / F)
    assert brightest_star_npix(13.7, s, t) == pytest.approx(math.pi * r2, rel=1e-12)
    # brute force: count the pixel centres of a fine grid above t (well sampled: the same area)
    g = np.arange(-20, 20, 0.05) + 0.025
    X, Y = np.meshgrid(g, g)
    n = np.count_nonzero(F / (2 * math.pi * s * s) * np.exp(-(X ** 2 + Y ** 2) / (2 * s * s)) > t) * 0.05 ** 2
    assert brightest_star_npix(13.7, s, t) == pytest.approx(n, rel=0.01)


def test_point_target_is_the_brightest_or_the_nearest_to_a_direction():
    u = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    assert pick_point_target(u, np.array([5.0, 9.0, 1.0])) == (1, None)
    near = np.array([0.0, 0.01, 1.0]) / math.hypot(0.01, 1.0)
    assert pick_point_target(u, np.array([5.0, 9.0, 1.0]), near, math.radians(1.0)) == (2, None)
    j, why = pick_point_target(u, np.array([5.0, 9.0, 1.0]), near, math.radians(0.1))
    assert j == -1 and "--target-near" in why
    j, why = pick_point_target(np.zeros((0, 3)), np.zeros(0))
    assert j == -1 and "no unknown object" in why


def test_the_cone_keeps_every_catalog_star_in_the_image():
    """The deep catalog's stars in the image through the boresight cone = those of projecting every star (random
    attitudes, the ESA camera and a 90 x 70 deg one with distortion)."""
    from dualsight.catalogs.stars import StarCatalogConfig, load_star_catalog
    from dualsight.jobs.kinds.hil_star_objects import stars_in_image
    from dualsight.scene.attitude import quat_to_dcm, random_quaternions
    from dualsight.scene.camera import Camera
    from dualsight.scene.starfield_geometry import catalog_in_image

    cat = load_star_catalog(StarCatalogConfig(mag_limit=12.0, epoch_jyear=2019.6))
    wide = Camera(width=640, height=480, pixel_pitch_m=5e-6, fx=320.0, fy=320.0, cx=320.0, cy=240.0,
                  distortion=(-0.1, 0.01, 0.0, 0.0, 0.0))
    for cam in (Camera.from_toml(CAMERA), wide):
        for A in quat_to_dcm(random_quaternions(np.random.default_rng([23, 5]), 6)):
            xy0, rows0 = catalog_in_image(A, cat.unit, cam)
            xy, rows = stars_in_image(A, cat.unit, cam)
            assert np.array_equal(rows, rows0) and np.array_equal(xy, xy0) and len(rows) > 0


def test_unknown_config_errors_name_the_field():
    with pytest.raises(ValueError, match="mag_window"):
        UnknownConfig(mag_window=-1.0)


# ============================================================================================ ESA frames
needs_esa = pytest.mark.skipif(not TRUTH.exists(), reason=f"ESA tetra3 frames not found at {ESA}")


@pytest.fixture(scope="module")
def esa_objects(tmp_path_factory):
    if not TRUTH.exists():
        pytest.skip(f"ESA tetra3 frames not found at {ESA}")
    lake = tmp_path_factory.mktemp("objects") / "lake"
    rc, out, err = run_cli(["hil", "star", ESA, "--camera", CAMERA, "--truth", TRUTH, "--json", "--lake", lake,
                            "--run", "esa"])
    assert rc == 0, err
    return {"json": {r["image"]: r for r in json.loads(out)}, "lake": lake}


# per frame: listed unknown objects (at least V 7.0 bright on the frame's zero point), looked at one by one:
#   Alt40_Azi135: two stars that Hipparcos lacks at V ~6.6-7.0 (their nearest catalog stars 8.7 and 27.8 px off)
#   Alt60_Azi45: two more (8.5 and 24.6 px from the nearest catalog star; one on the last row)
#   Alt60_Azi135: a warm pixel pair on column 0 (fitted off the frame at x = -1.03 px, sigma 3.1 px: 124 arcsec),
#                 and two stars Hipparcos lacks at 6.6-6.8
# A red catalog star (HIP 96580, V 9.0 seen at 6.7, 0.09 px from its place) is explained (mag_window 3).
ESA_UNKNOWN = {"Alt40_Azi-135": 0, "Alt40_Azi-45": 0, "Alt40_Azi135": 2, "Alt40_Azi45": 0,
               "Alt60_Azi-135": 0, "Alt60_Azi-45": 0, "Alt60_Azi135": 3, "Alt60_Azi45": 2}


@needs_esa
def test_esa_frames_have_few_unknown_objects(esa_objects):
    got = {k.split("_", 1)[1].rsplit("_", 1)[0]: r for k, r in esa_objects["json"].items()}
    assert {k: len(r["unknown_objects"]) for k, r in got.items()} == ESA_UNKNOWN
    for k, r in got.items():
        assert r["identified"] and 13.5 < r["zp_mag"] < 14.0 and r["zp_scatter_mag"] < 0.35 and r["zp_stars"] >= 18
        for o in r["unknown_objects"]:
            assert 6.0 < o["mag"] <= 7.0 and o["nearest_sep_px"] > 5.0, (k, o)
        assert r["unknown_faint"] >= 0
    # the dataset holds the same objects; dualsight sql lists them
    rc, out, err = run_cli(["sql", "SELECT count(*) AS n FROM hil_star_objects WHERE run = 'esa'", "--lake",
                            esa_objects["lake"], "--json"])
    assert rc == 0, err
    assert json.loads(out)[0]["n"] == sum(ESA_UNKNOWN.values())


def _aperture_zero_point(img: np.ndarray, matched: list[dict]) -> float:
    """Zero point (V = zp - 2.5 log10 F) of the plate solution's matched stars by plain aperture photometry: the sum
    over a 9 x 9 box minus the median of the 21 x 21 box's border, unsaturated stars away from the edges."""
    offs = []
    for star in matched:
        i, j, m = int(star["row"]), int(star["col"]), star["mag"]
        if not (10 <= i < img.shape[0] - 10 and 10 <= j < img.shape[1] - 10):
            continue
        big = img[i - 10:i + 11, j - 10:j + 11].astype(np.float64)
        if big.max() >= 4095:
            continue
        border = np.concatenate([big[0], big[-1], big[1:-1, 0], big[1:-1, -1]])
        f = (big[6:15, 6:15] - np.median(border)).sum()
        if f > 0:
            offs.append(m + 2.5 * math.log10(f))
    return float(np.median(offs))


@needs_esa
def test_a_planted_point_source_is_an_unknown_object_at_its_place_and_magnitude(tmp_path):
    from astropy.coordinates import CartesianRepresentation, SkyCoord

    def ndtr(z):                                         # standard normal CDF
        return 0.5 * (1.0 + np.vectorize(math.erf)(np.asarray(z) / math.sqrt(2.0)))

    name = "2019-07-29T204726_Alt40_Azi-45_Try1.tiff"
    truth = json.loads(TRUTH.read_text())[name]
    img = cv2.imread(str(ESA / name), cv2.IMREAD_UNCHANGED).astype(np.int64) >> 4     # 12-bit ADC counts
    zp_truth = _aperture_zero_point(img, truth["matched"])
    noise = 1.4826 * np.median(np.abs(img - np.median(img)))
    # an empty place: nothing above 5 sigma within 12 px
    for x0, y0 in [(300.3, 500.7), (700.6, 200.2), (150.8, 600.4), (850.1, 650.9)]:
        win = img[int(y0) - 12:int(y0) + 13, int(x0) - 12:int(x0) + 13]
        if win.max() < np.median(img) + 5 * noise:
            break
    else:
        pytest.fail("no empty place to plant the source")
    mag, s = 5.5, 0.67                                  # the frames' PSF width (psf_sigma_px 0.64-0.70)
    F = 10 ** (0.4 * (zp_truth - mag))
    cols, rows = np.arange(img.shape[1]), np.arange(img.shape[0])
    fx = ndtr((cols + 1 - x0) / s) - ndtr((cols - x0) / s)        # pixel-integrated Gaussian (pixel i: [i, i+1))
    fy = ndtr((rows + 1 - y0) / s) - ndtr((rows - y0) / s)
    planted = np.clip(np.round(img + F * np.outer(fy, fx)), 0, 4095).astype(np.uint16)
    tif = tmp_path / name
    cv2.imwrite(str(tif), planted << 4)
    tfile = tmp_path / "truth.json"
    tfile.write_text(json.dumps({name: truth}))
    rc, out, err = run_cli(["hil", "star", tif, "--camera", CAMERA, "--truth", tfile, "--json", "--no-lake"])
    assert rc == 0, err
    r = json.loads(out)[0]
    assert r["identified"] and r["status"] == "success"
    near = [o for o in r["unknown_objects"] if math.hypot(o["x_px"] - x0, o["y_px"] - y0) < 1.0]
    assert len(near) == 1, r["unknown_objects"]
    o = near[0]
    # astropy: the planted pixel through the plate solution's attitude (pinhole, no distortion, centre (512, 384))
    R = np.asarray(truth["R_icrs_to_cam"])
    v = np.array([(x0 - 512.0) / 5119.0, (y0 - 384.0) / 5119.0, 1.0])
    u = R.T @ (v / np.linalg.norm(v))
    sc = SkyCoord(CartesianRepresentation(*u), frame="icrs")
    sep = sc.separation(SkyCoord(o["ra_deg"], o["dec_deg"], unit="deg", frame="icrs")).arcsec
    # stated error: 3 x the object's sigma with the truth attitude's own fit residual beside it
    tol = 3 * math.hypot(o["sigma_arcsec"], truth["fit_residual_arcsec_median"])
    assert sep < tol, (sep, tol, o)
    assert abs(o["mag"] - mag) < 0.2, (o["mag"], mag, zp_truth, r["zp_mag"])
    assert not o["is_target"] and o["nearest_sep_px"] > 1.0


# ============================================================================================ --target, rendered
SAT = ROOT / "examples" / "satellites" / "cubesat_3u.toml"


def _render_with_target(tmp_path, name: str, range_m: float, pix: tuple[float, float], phase_deg: float = 30.0,
                        rot: tuple[float, float, float] = (0.4, 1.1, 0.3)):
    """A noisy ESA-camera star field (the synthetic round trip's sensor) with a 3U CubeSat at ``range_m`` in the
    direction of pixel ``pix``, lit at ``phase_deg``, written as a 12-bit-in-16-bit TIFF; returns (path, truth):
    the centre of brightness's ICRS direction, the range, the target's V and whether it was rasterised.  ``rot``: the
    target's attitude, 1-2-3 angles (rad)."""
    from dualsight.scene.target_config import TargetConfig
    from dualsight.kernels.starfield import render_star_fields
    from dualsight.scene.attitude import rot_axis
    from dualsight.scene.camera import Camera
    from dualsight.scene.satellite import load_satellite
    from dualsight.scene.target_in_field import TargetCases, target_frames, with_target
    from dualsight.scene.target_photometry import target_shape

    cam = Camera.from_toml(CAMERA)
    A, cat, sensor, field_ = orion_field(cam)
    u = cam.backproject(np.array([pix], np.float64))                       # (1, 3) camera frame
    o = -u[0]
    e1 = np.cross(o, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    a = math.radians(phase_deg)
    sun_cam = (math.cos(a) * o + math.sin(a) * e1)[None]
    R_body = rot_axis(1, rot[0])[0] @ rot_axis(2, rot[1])[0] @ rot_axis(3, rot[2])[0]
    cases = TargetCases(np.array([True]), np.array([range_m]), u * range_m, R_body[None], sun_cam,
                        sun_cam @ A, np.array([a]))
    sat = load_satellite(SAT)
    cfg = TargetConfig(satellite=str(SAT), range_m=(range_m, range_m))
    tf = target_frames(cfg, sat, target_shape(sat.components), cases, field_, cam, sensor)
    render, _ = with_target(field_, tf)
    img = render_star_fields(render.x, render.y, render.flux_e, render.valid, cam.width, cam.height, sensor,
                             np.array([4242], np.uint64))[0].astype(np.float64)
    tif = tmp_path / name
    cv2.imwrite(str(tif), (np.clip(np.round(img), 0, 4095).astype(np.uint16) << 4))
    cob = cam.backproject(np.array([[tf.cob_x_px[0], tf.cob_y_px[0]]]))[0]
    return tif, {"u": A.T @ cob, "range_m": range_m, "vmag": float(tf.vmag[0]), "resolved": bool(tf.resolved[0]),
                 "cob_px": (float(tf.cob_x_px[0]), float(tf.cob_y_px[0]))}


def _sep_arcsec(u, ra_deg, dec_deg):
    v = np.array([math.cos(math.radians(dec_deg)) * math.cos(math.radians(ra_deg)),
                  math.cos(math.radians(dec_deg)) * math.sin(math.radians(ra_deg)), math.sin(math.radians(dec_deg))])
    return math.degrees(math.atan2(np.linalg.norm(np.cross(u, v)), float(np.dot(u, v)))) * 3600


def test_target_resolved_and_point_on_rendered_frames(tmp_path):
    """A resolved 3U CubeSat (40 m: ~38 x 13 px, saturated) and a point-like one (60 km, V ~ 2.7) in rendered star fields: RA/Dec within
    3 stated sigma of the centre of brightness they were rendered with, the range within the blobber's min/max,
    the point's magnitude on the stars' zero point.

    One scene, not a coverage proof: over 8 random attitudes, ranges (25-80 m) and phase angles (0-80 deg) of the
    same target the range fell inside [min, max] in 5 (outside: 78.4 m seen as at most 76.3, 36.2 as at most 35.5,
    53.3 as at least 60.2 -- part of the silhouette unlit at 60-80 deg phase, which Eq. 1 cannot know) and the
    bearing within 3 sigma in 8."""
    near_tif, near = _render_with_target(tmp_path, "near.tiff", 40.0, (600.0, 300.0))
    far_tif, far = _render_with_target(tmp_path, "far.tiff", 60000.0, (400.0, 500.0))     # V ~ +2.7
    assert near["resolved"] and not far["resolved"]
    rc, out, err = run_cli(["hil", "star", near_tif, far_tif, "--camera", CAMERA, "--target", SAT, "--json",
                            "--no-lake", "--epoch", "2019.6"])
    assert rc == 0, err
    res = {r["image"]: r for r in json.loads(out)}
    for name, truth, kind in (("near.tiff", near, "resolved"), ("far.tiff", far, "point")):
        r = res[name]
        assert r["identified"], r
        assert r["target"] and r["target_kind"] == kind and r["target_reason"] is None, r
        sep = _sep_arcsec(truth["u"], r["target_ra_deg"], r["target_dec_deg"])
        assert sep < 3 * r["target_sigma_arcsec"], (name, sep, r["target_sigma_arcsec"])
        assert r["target_pixels"] > 0
    r = res["near.tiff"]
    assert r["target_range_min_m"] <= near["range_m"] <= r["target_range_max_m"], r
    assert r["target_range_min_m"] < r["target_range_m"] < r["target_range_max_m"]
    r = res["far.tiff"]
    assert r["target_range_m"] is None and abs(r["target_mag"] - far["vmag"]) < 0.3, (r["target_mag"], far["vmag"])


# ============================================================================================ hostile input
@pytest.mark.parametrize("flags, needle", [
    (["--target", str(CAMERA)], "[body]"),                                     # a camera file, not a satellite file
    (["--target", "/nonexistent/sat.toml"], "file not found"),
    (["--target", str(ROOT / "README.md")], "not valid TOML"),
    (["--target", str(ROOT / "examples")], "folder"),
    (["--target-near", "10,20"], "goes with --target"),
    (["--target", str(SAT), "--target-near", "10,95"], "DEC in [-90, 90]"),
    (["--target", str(SAT), "--target-near", "ten,20"], "RA,DEC"),
    (["--target", str(SAT), "--target-near", "10,20,0"], "RADIUS in (0, 180]"),
])
def test_bad_target_options_exit_2_with_one_line(tmp_path, flags, needle):
    img = tmp_path / "x.tiff"
    cv2.imwrite(str(img), np.zeros((768, 1024), np.uint16))
    lake = tmp_path / "lake"
    rc, out, err = run_cli(["hil", "star", img, "--camera", CAMERA, "--lake", lake, *flags])
    assert rc == 2, (rc, err)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in err, err
    assert not lake.exists()


@needs_esa
def test_a_target_not_in_the_image_is_null_with_its_reason(tmp_path):
    names = ["2019-07-29T204726_Alt40_Azi-45_Try1.tiff", "2019-07-29T204726_Alt60_Azi135_Try1.tiff"]
    for n in names:
        shutil.copy(ESA / n, tmp_path / n)
    rc, out, err = run_cli(["hil", "star", *[tmp_path / n for n in names], "--camera", CAMERA, "--target", SAT,
                            "--json", "--no-lake"])
    assert rc == 0, err
    r0, r1 = json.loads(out)
    # no listed unknown object, no resolved blob: null with the reason
    assert r0["identified"] and r0["target_kind"] is None and r0["target_ra_deg"] is None
    assert "no unknown object" in r0["target_reason"] and r0["target_range_m"] is None
    # listed unknown objects: the brightest is the point target (here the warm pixel pair on column 0)
    assert r1["target_kind"] == "point" and r1["target_reason"] is None
    assert sum(o["is_target"] for o in r1["unknown_objects"]) == 1
    # --target-near a direction without any unknown object: null, the reason names the option
    rc, out, err = run_cli(["hil", "star", tmp_path / names[1], "--camera", CAMERA, "--target", SAT,
                            "--target-near", "10,-40,0.5", "--json", "--no-lake"])
    assert rc == 0, err
    r = json.loads(out)[0]
    assert r["target_kind"] is None and "--target-near" in r["target_reason"], r["target_reason"]
    # and near the second-brightest listed object: that one is the target
    o = sorted(r["unknown_objects"], key=lambda o: -o["flux_adu"])[1]
    rc, out, err = run_cli(["hil", "star", tmp_path / names[1], "--camera", CAMERA, "--target", SAT,
                            "--target-near", f"{o['ra_deg']},{o['dec_deg']},0.05", "--json", "--no-lake"])
    r = json.loads(out)[0]
    assert r["target_kind"] == "point" and abs(r["target_ra_deg"] - o["ra_deg"]) < 1e-6
