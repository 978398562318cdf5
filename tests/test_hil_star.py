"""Star hardware-in-the-loop (``dualsight hil star``): the SIL star chain on real night-sky frames.

Independent truths: the ESA tetra3 frames' plate solutions (``truth.json``, from another lost-in-space
solver: boresight, attitude matrix, matched stars with their own centroids and catalog positions), the
tripod's time/site/alt-az through astropy (README: site near 52.08 N 4.37 E, mount good to ~1 deg), and a
synthetic frame rendered at a known attitude (runs without the real data).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from dualsight.errors import ConfigError
from dualsight.jobs.kinds import hil_star as hs
from dualsight.jobs.kinds.hil_common import n_cases
from dualsight.jobs.kinds.hil_star_spec import settings_from_table
from dualsight.jobs.engine.runner import run_job
from dualsight.scene.attitude import radec_to_unit, rot_axis, unit_to_radec
from dualsight.kernels.background import bin_size, subtract_background
from dualsight.scene.camera import Camera
from dualsight.scene.pointing import roll_deg
from dualsight.scene.timescale import julian_year, observation_epoch
from dualsight.scene.units import angle_between
from dualsight.warehouse.lake import Lake
from dualsight.warehouse.query import connect, run_report, run_sql
from helpers import ROOT, esa_spec, hil_star_rows, orion_field, run_cli, shared_real

CAMERA = ROOT / "examples" / "cameras" / "esa_tetra3.toml"
ARCSEC = math.pi / (180 * 3600)
ESA = shared_real() / "esa_tetra3"
TRUTH = ESA / "truth.json"
SITE = ["--lat", "52.08", "--lon", "4.37"]          # esa_tetra3/README.md: fitted, unpublished site
needs_esa = pytest.mark.skipif(not TRUTH.exists(), reason=f"ESA tetra3 frames not found at {ESA}")


# ============================================================================================ ESA frames
@pytest.fixture(scope="module")
def esa(tmp_path_factory):
    """One run over the 8 frames: truth file + tripod truth, JSON, lake and overlays."""
    if not TRUTH.exists():
        pytest.skip(f"ESA tetra3 frames not found at {ESA}")
    tmp = tmp_path_factory.mktemp("hil")
    lake, ov = tmp / "lake", tmp / "overlays"
    rc, out, err = run_cli(["hil", "star", ESA, "--camera", CAMERA, "--truth", TRUTH, *SITE, "--json", "--lake", lake,
                            "--run", "esa", "--overlay-dir", ov])
    assert rc == 0, err
    return {"json": json.loads(out), "stderr": err, "lake": lake, "overlays": ov,
            "truth": json.loads(TRUTH.read_text())}


@needs_esa
def test_all_eight_frames_identified_lost_in_space(esa):
    res = esa["json"]
    assert len(res) == 8 and {r["image"] for r in res} == set(esa["truth"])
    for r in res:
        assert r["error"] is None and r["identified"], r["image"]
        assert r["status"] == "success" and r["truth_source"] == "file", r["image"]
        assert r["method"] == "robust" and r["T"] >= 10 and r["stars_identified"] >= 15, r
        for key in ("image", "identified", "stars_detected", "stars_identified", "ra_deg", "dec_deg",
                    "boresight_error_arcsec", "residual_median_arcsec"):
            assert key in r
    # the reference's method ran beside it on the same detections, and also solves every frame
    assert all(r["alt"]["method"] == "paper" and r["alt"]["identified"] for r in res)
    # every frame answered in the cheaper first round: its 12 brightest detections voted
    assert [r["stars_used"] for r in res] == [12] * 8


def test_stars_used_counts_the_answering_rounds_voters():
    sched = ((0, 12), (0, 25), (25, 50))                 # first_stars 12, max_stars 25, widening to 50
    assert [hs.voters_in_round(30, r, sched) for r in range(3)] == [12, 25, 5]
    assert [hs.voters_in_round(8, r, sched) for r in range(3)] == [8, 8, 0]


@needs_esa
def test_boresight_within_30_arcsec_of_the_plate_solutions(esa):
    """Boresight error = angle between the solved +z axis and truth.json's R third row, recomputed here
    from the printed RA/Dec (rounded to 1e-6 deg = 0.004 arcsec)."""
    errs = []
    for r in esa["json"]:
        R = np.asarray(esa["truth"][r["image"]]["R_icrs_to_cam"])
        b = radec_to_unit(math.radians(r["ra_deg"]), math.radians(r["dec_deg"]))
        e = float(angle_between(b, R[2])) / ARCSEC
        assert e == pytest.approx(r["boresight_error_arcsec"], abs=0.05)
        errs.append(e)
    assert np.median(errs) < 30.0, errs
    assert max(errs) < 30.0, errs            # measured 0.6-6.1 arcsec (6.1: Alt40_Azi45, the hard frame)


@needs_esa
def test_per_star_residuals_under_15_arcsec(esa):
    """Table 6: every identified star's observed-versus-predicted error; median < 15 arcsec overall and
    per frame, and the error against the truth attitude is as small (the attitude is not overfitted)."""
    all_err = [s["error_arcsec"] for r in esa["json"] for s in r["stars"]]
    assert len(all_err) == sum(r["stars_identified"] for r in esa["json"])
    assert np.median(all_err) < 15.0
    for r in esa["json"]:
        assert r["residual_median_arcsec"] < 15.0, r["image"]
        assert r["truth_residual_median_arcsec"] < 15.0, r["image"]
        assert all(s["hip"] > 0 and s["vmag"] <= 7.0 for s in r["stars"])
        # the printed predicted pixel differs from the observed one by the printed error (1 px ~ 40.3 arcsec)
        for s in r["stars"][:5]:
            d_px = math.hypot(s["x_px"] - s["pred_x_px"], s["y_px"] - s["pred_y_px"])
            assert d_px * 40.3 == pytest.approx(s["error_arcsec"], rel=0.05, abs=0.3)


@needs_esa
def test_identities_agree_with_the_independent_solution(esa):
    """truth.json's matched stars (their own centroids and catalog RA/Dec): every one brighter than V 6.5
    is among ours at the same centroid (2 px) with the same sky position (60 arcsec), and no identity of
    ours contradicts one of theirs."""
    for r in esa["json"]:
        m = esa["truth"][r["image"]]["matched"]
        ours = np.array([[s["x_px"], s["y_px"]] for s in r["stars"]])
        for t in m:
            if t["mag"] > 6.5:
                continue
            d = np.hypot(ours[:, 0] - t["col"], ours[:, 1] - t["row"])
            k = int(d.argmin())
            assert d[k] <= 2.0, (r["image"], t)
        assert r["truth_ids_disagree"] == 0, r["image"]
        assert r["truth_ids_agree"] >= 0.6 * r["truth_stars"], r["image"]


@needs_esa
def test_roll_is_the_position_angle_of_image_up(esa):
    """Roll = position angle (north through east) of the image's up direction at the boresight, checked
    by projecting points 0.001 deg north and east of the boresight through truth.json's R and a pinhole."""
    cam = Camera.from_toml(CAMERA)
    for r in esa["json"]:
        R = np.asarray(esa["truth"][r["image"]]["R_icrs_to_cam"])
        ra0, dec0 = (math.degrees(a) for a in unit_to_radec(R[2]))
        c = cam.project(R @ radec_to_unit(math.radians(ra0), math.radians(dec0)))[0]
        n = cam.project(R @ radec_to_unit(math.radians(ra0), math.radians(dec0 + 1e-3)))[0] - c
        e = cam.project(R @ radec_to_unit(math.radians(ra0 + 1e-3 / math.cos(math.radians(dec0))),
                                          math.radians(dec0)))[0] - c
        up = np.array([0.0, -1.0])
        coef = np.linalg.solve(np.stack([n, e], axis=1), up)      # up = a north + b east (in pixels)
        pa = math.degrees(math.atan2(coef[1] * np.linalg.norm(e), coef[0] * np.linalg.norm(n))) % 360
        assert abs((r["roll_true_deg"] - pa + 180) % 360 - 180) < 0.005, r["image"]
        assert abs((r["roll_deg"] - r["roll_true_deg"] + 180) % 360 - 180) < 0.05, r["image"]


@needs_esa
def test_tripod_truth_reported_beside_the_file_truth(esa):
    """Time from the file names, site from the README, nominal alt/az: within 2 deg of the solved boresight."""
    for r in esa["json"]:
        assert r["altaz_error_deg"] is not None and r["altaz_error_deg"] < 2.0, r["image"]


@needs_esa
def test_table6_and_figure11_per_image(esa):
    pngs = sorted(esa["overlays"].glob("*.png"))
    assert len(pngs) == 8
    for r in esa["json"]:
        assert Path(r["overlay"]).exists()
        img = cv2.imread(r["overlay"])
        assert img is not None and img.shape[0] > 500 and img.shape[1] > 1000
    # text mode: the summary line and Table 6 for one frame (no lake)
    one = ESA / "2019-07-29T204726_Alt60_Azi-45_Try1.tiff"
    rc, out, err = run_cli(["hil", "star", str(one), "--camera", str(CAMERA), "--truth", str(TRUTH), "--no-lake",
                            "--no-compare"])
    assert rc == 0, err
    assert "HIP" in out and "error (arcsec)" in out and "boresight error" in out
    assert "68756" in out   # HIP 68756 (V 3.65), the frame's brightest star in truth.json


@needs_esa
def test_lake_rows_are_queryable_with_sql(esa):
    lake = esa["lake"]
    m = Lake(lake).read_manifest("esa")
    assert m["kind"] == "hil_star" and m["status"] == "complete" and m["n_cases"] == 8
    assert m["spec"]["settings"]["method"] == "robust"
    cols, rows = run_sql(lake, "SELECT count(*), count(*) FILTER (WHERE identified), sum(stars_identified) "
                               "FROM hil_star WHERE run = 'esa'")
    n, n_id, n_stars = rows[0]
    assert (n, n_id) == (8, 8)
    _, rows = run_sql(lake, "SELECT count(*), median(residual_rad) * 206264.8 FROM hil_star_stars WHERE run = 'esa'")
    assert rows[0][0] == n_stars and rows[0][1] < 15.0
    con = connect(lake)
    cols, rows = run_report(con, "hil_star_summary", run="esa")
    s = dict(zip(cols, rows[0]))
    assert s["images"] == 8 and s["identified"] == 8 and s["errors"] == 0
    assert s["median_boresight_error_arcsec"] < 30.0 and s["all_stars_median_residual_arcsec"] < 15.0
    assert s["truth_ids_disagree"] == 0
    cols, rows = run_report(con, "hil_star_table6", run="esa")
    assert len(rows) == n_stars and {"hip", "vmag", "error_arcsec"} <= set(cols)
    cols, rows = run_report(con, "hil_star_images", run="esa")
    assert [r[cols.index("image")] for r in rows] == [r["image"] for r in esa["json"]]


@needs_esa
def test_real_and_simulated_runs_of_the_same_camera_side_by_side(esa, tmp_path):
    """warehouse/sql/hil_star_vs_sim.sql over the HIL run and a small SIL run of the ESA camera."""
    spec = tmp_path / "esa_sim.toml"
    spec.write_text("[camera]\nwidth = 1024\nheight = 768\npixel_pitch_um = 6.9\nfx = 5119.0\nfy = 5119.0\n"
                    "[catalog]\nmag_limit = 7.0\nepoch_jyear = 2019.6\n"
                    "[voting]\ntolerance_arcsec = 20.0\nmax_stars = 25\n")
    rc, _, err = run_cli(["star", "run", "--config", str(spec), "--cases", "12", "--lake", str(esa["lake"]), "--run",
                          "sim-esa", "--workers", "1", "--no-progress"])
    assert rc == 0, err
    cols, rows = run_report(connect(esa["lake"]), "hil_star_vs_sim", run="esa", sim_run="sim-esa")
    t = {(r[0], r[1]): dict(zip(cols, r)) for r in rows}
    assert set(t) == {("real", "robust"), ("sim", "paper"), ("sim", "robust")}
    assert t[("real", "robust")]["cases"] == 8 and t[("sim", "paper")]["cases"] == 12
    assert t[("real", "robust")]["identified_rate"] == 1.0
    # real centroids are ~10x worse than the ideal simulated ones: the residuals show it
    assert t[("real", "robust")]["median_residual_arcsec"] > t[("sim", "paper")]["median_residual_arcsec"]


def _astropy_boresight(time_utc: str, lat: float, lon: float, alt: float, az: float) -> np.ndarray:
    """ICRS unit vector of a horizontal (alt, az) direction, straight from astropy (not through the code under
    test): geometric, no refraction, site at height 0."""
    from astropy.utils import iers

    iers.conf.auto_download = False
    import astropy.units as u
    from astropy.coordinates import ICRS, AltAz, EarthLocation, SkyCoord
    from astropy.time import Time

    frame = AltAz(obstime=Time(time_utc, scale="utc"), location=EarthLocation.from_geodetic(lon * u.deg, lat * u.deg,
                                                                                           0 * u.m))
    c = SkyCoord(alt=alt * u.deg, az=az * u.deg, frame=frame).transform_to(ICRS())
    return radec_to_unit(c.ra.rad, c.dec.rad)


@needs_esa
def test_tripod_truth_alone(tmp_path):
    """Alt/az truth only (time and nominal alt/az from the file names, site from the README), checked
    against two truths the code under test does not compute:

    * astropy's own AltAz -> ICRS of the file name's (alt, az) at 2019-07-29T20:47:26 UTC: the reported
      truth boresight within 0.05 arcsec (the JSON rounds RA/Dec to 1e-6 deg = 0.004 arcsec);
    * the independent plate solution (truth.json's R_icrs_to_cam): the tripod boresight within 2 deg of
      R's third row (the README: a nominal mount pointing is good to about 1 deg; measured 1.25 and 1.35 deg)
      and the level-mount roll within 5 deg of R's roll (measured 1.4 and 1.9 deg); our solution's error
      against the alt/az truth equals the angle between the two truths within 30 arcsec (our solution is
      within 7 arcsec of R on these frames).
    Explicit --time/--alt/--az give the same truth as the file names."""
    names = ["2019-07-29T204726_Alt40_Azi-135_Try1.tiff", "2019-07-29T204726_Alt60_Azi45_Try1.tiff"]
    nominal = {names[0]: (40.0, -135.0), names[1]: (60.0, 45.0)}
    file_truth = json.loads(TRUTH.read_text())
    rc, out, err = run_cli(["hil", "star", *[str(ESA / n) for n in names], "--camera", str(CAMERA), *SITE, "--json",
                            "--no-lake", "--no-compare"])
    assert rc == 0, err
    res = json.loads(out)
    assert [r["image"] for r in res] == names
    for r in res:
        assert r["truth_source"] == "altaz" and r["identified"] and r["status"] == "success"
        z_tripod = radec_to_unit(math.radians(r["ra_true_deg"]), math.radians(r["dec_true_deg"]))
        z_astropy = _astropy_boresight("2019-07-29T20:47:26", 52.08, 4.37, *nominal[r["image"]])
        assert float(angle_between(z_tripod, z_astropy)) / ARCSEC < 0.05, r["image"]
        R = np.asarray(file_truth[r["image"]]["R_icrs_to_cam"])
        gap_deg = math.degrees(float(angle_between(z_tripod, R[2])))
        assert 0.1 < gap_deg < 2.0, (r["image"], gap_deg)
        assert abs((r["roll_true_deg"] - float(roll_deg(R)) + 180) % 360 - 180) < 5.0, r["image"]
        assert r["boresight_error_arcsec"] == pytest.approx(gap_deg * 3600, abs=30.0), r["image"]
        assert r["altaz_error_deg"] == pytest.approx(r["boresight_error_arcsec"] / 3600, abs=1e-3)
    rc, out2, err = run_cli(["hil", "star", str(ESA / names[0]), "--camera", str(CAMERA), *SITE, "--time",
                             "2019-07-29T20:47:26", "--alt", "40", "--az", "-135", "--json", "--no-lake",
                             "--no-compare"])
    assert rc == 0, err
    assert json.loads(out2)[0]["altaz_error_deg"] == pytest.approx(res[0]["altaz_error_deg"], abs=1e-6)


@needs_esa
def test_bad_images_are_reported_and_the_others_run(tmp_path):
    good = ESA / "2019-07-29T204726_Alt60_Azi135_Try1.tiff"
    trunc = tmp_path / "truncated.tiff"
    trunc.write_bytes(good.read_bytes()[:400_000])
    missing = tmp_path / "missing.tiff"
    lake = tmp_path / "lake"
    rc, out, err = run_cli(["hil", "star", str(trunc), str(missing), str(good), "--camera", str(CAMERA), "--truth",
                            str(TRUTH), "--json", "--lake", str(lake), "--run", "bad", "--no-compare"])
    assert rc == 1
    assert "truncated.tiff" in err and "missing.tiff" in err and "not found" in err
    res = json.loads(out)
    assert [r["image"] for r in res] == ["truncated.tiff", "missing.tiff", good.name]
    assert res[0]["error"] and "TIFF" in res[0]["error"] and not res[0]["identified"]
    assert res[1]["error"] and "not found" in res[1]["error"]
    assert res[2]["error"] is None and res[2]["identified"] and res[2]["boresight_error_arcsec"] < 30
    _, rows = run_sql(lake, "SELECT image, status, error IS NOT NULL FROM hil_star ORDER BY case_id")
    assert rows == [("truncated.tiff", "error", True), ("missing.tiff", "error", True), (good.name, "success", False)]


@needs_esa
def test_detector_flag_selects_the_global_path_and_contradictions_are_refused(tmp_path):
    """``--detector global``: smooth background + one threshold (21-111 detections per ESA frame, against
    2.5-4x as many for the matched filter's), still identified within 30 arcsec of the plate solution; a ``--config``
    that says otherwise is refused in one line naming the flag, before the lake is touched."""
    names = [str(ESA / "2019-07-29T204726_Alt60_Azi45_Try1.tiff"), str(ESA / "2019-07-29T204726_Alt40_Azi-135_Try1.tiff")]
    got = {}
    for det in ("global", "local"):
        rc, out, err = run_cli(["hil", "star", *names, "--camera", str(CAMERA), "--truth", str(TRUTH), "--json",
                                "--no-lake", "--no-compare", "--detector", det])
        assert rc == 0, err
        got[det] = json.loads(out)
    for r in got["global"]:
        assert r["identified"] and r["boresight_error_arcsec"] < 30, r
    for g, loc in zip(got["global"], got["local"]):
        assert loc["stars_detected"] > 2 * g["stars_detected"], (g["image"], g["stars_detected"], loc["stars_detected"])
    cfg, lake = tmp_path / "c.toml", tmp_path / "lake"
    cfg.write_text('detector = "local"\n')
    rc, out, err = run_cli(["hil", "star", names[0], "--camera", str(CAMERA), "--detector", "global", "--config",
                            str(cfg), "--lake", str(lake)])
    assert rc == 2 and "--detector" in err and len(err.strip().splitlines()) == 1, err
    assert not lake.exists()


# ============================================================================================ no real data needed
WIDE = "width = 1024\nheight = 768\npixel_pitch_um = 5.0\nfx = 56.0\nfy = 56.0"          # 170 deg diagonal
HUGE = "width = 65536\nheight = 65536\npixel_pitch_um = 5.0\nfocal_length_mm = 5000.0"   # the largest frame


@pytest.mark.parametrize("kind, camera, flags, needle", [
    ("star", "nope.toml", [], "nope.toml"),
    ("star", CAMERA, ["--lat", "52"], "--lon"),
    ("star", CAMERA, ["--mag-limit", "30"], "mag_limit"),
    # the HIL kinds' memory_estimate, checked by the engine before anything is allocated:
    ("star", WIDE, ["--mag-limit", "12"], "GiB per worker"),    # catalog to V 12 over 170 deg: ~1e12 pairs
    ("star", HUGE, [], "GiB per worker"),                        # 16 frames of 65536^2 px in a batch: ~1.6 TB
    ("prox", HUGE, ["--target", ROOT / "examples" / "targets" / "cubesat_3u_analog.toml"], "GiB per worker"),
], ids=["no-camera-file", "lat-without-lon", "mag-limit-30", "star-V12-170deg", "star-huge-frames", "prox-huge-frame"])
def test_bad_options_exit_2_with_one_line_and_leave_the_lake_untouched(tmp_path, kind, camera, flags, needle):
    img, lake, cam = tmp_path / "x.png", tmp_path / "lake", camera
    cv2.imwrite(str(img), np.zeros((8, 8), np.uint8))
    if camera in (WIDE, HUGE):
        cam = tmp_path / "cam.toml"
        cam.write_text(f"[camera]\n{camera}\n")
    elif not isinstance(camera, Path):
        cam = tmp_path / camera                                  # does not exist
    rc, out, err = run_cli(["hil", kind, img, "--camera", cam, *flags, "--lake", lake])
    assert rc == 2 and needle in err and len(err.strip().splitlines()) == 1, err
    assert not lake.exists() and out == ""


def test_subtract_background_removes_a_gradient_and_keeps_stars():
    rng = np.random.default_rng(1)
    H, W = 100, 130                                     # not multiples of the block
    yy, xx = np.mgrid[0:H, 0:W]
    sky = 100.0 + 0.5 * xx + 0.3 * yy
    star = 500.0 * np.exp(-((xx + 0.5 - 60.3) ** 2 + (yy + 0.5 - 40.7) ** 2) / (2 * 0.8 ** 2))
    f = (sky + star + rng.normal(0, 3, (H, W)))[None].astype(np.float32)
    f_before = f.copy()
    r, level = subtract_background(f, 16)
    assert np.array_equal(f, f_before)                  # the caller's float32 frames are not written over
    assert r.shape == f.shape and r.dtype == np.float32
    far = np.hypot(xx - 60, yy - 40) > 6
    assert abs(float(np.median(r[0][far]))) < 0.5 and float(np.std(r[0][far])) < 3.5
    assert float(r[0][~far].sum()) == pytest.approx(star.sum(), rel=0.05)
    assert 120 < level[0] < 160
    r0, _ = subtract_background(f, 0)
    assert np.array_equal(r0, f)
    # integer frames are partitioned in their own type: the same medians (exact) and residuals as float32
    for blk in (16, 15):                                  # even and odd block areas
        fu = np.round(f).astype(np.uint16)
        fu_before = fu.copy()
        ru, lu = subtract_background(fu, blk)
        assert np.array_equal(fu, fu_before)
        rf, lf = subtract_background(fu.astype(np.float32), blk)
        assert ru.dtype == np.float32 and np.array_equal(ru, rf) and np.array_equal(lu, lf)


@pytest.mark.parametrize("block", [32, 30, 15])           # bins of 4, 2 and 1 px
def test_subtract_background_is_exact_on_a_ramp_and_as_quiet_as_a_full_median(block):
    """A noise-free linear sky: every bin mean is the ramp at the bin's centre, their median the ramp at
    the block's centre, and bilinear interpolation between centres is exact for a linear function, so the
    residual between the outer block centres is 0.  On white noise sigma the block levels scatter by
    ~sqrt(pi/2) sigma / block (the median of all block^2 pixels' figure; module docstring)."""
    H, W = 6 * block, 8 * block
    yy, xx = np.mgrid[0:H, 0:W]
    sky = (200.0 + 0.37 * xx - 0.21 * yy)[None].astype(np.float32)
    r, level = subtract_background(sky, block)
    c0, c1 = block // 2, block // 2 + 1                  # inside the outer centres (+- half a block)
    inner = r[0, c0 + 1:H - c1, c0 + 1:W - c1]
    assert float(np.abs(inner).max()) < 2e-3
    cy, cx = np.mgrid[0:6, 0:8] * block + 0.5 * block - 0.5           # block centres, pixel indices
    assert level[0] == pytest.approx(float(np.median(200.0 + 0.37 * cx - 0.21 * cy)), abs=1e-3)
    assert bin_size(block) == {32: 4, 30: 2, 15: 1}[block]
    rng = np.random.default_rng(7)
    sigma = 10.0
    noise = rng.normal(1000.0, sigma, (4, 20 * block, 20 * block)).astype(np.float32)
    rn, _ = subtract_background(noise, block)
    bg = noise - rn                                       # the background map; its block-centre values
    cen = bg[:, block // 2::block, block // 2::block]
    expect = math.sqrt(math.pi / 2) * sigma / block
    assert float(np.std(cen)) == pytest.approx(expect, rel=0.2)


def test_roll_convention():
    """Boresight on the equator at RA 0 with image-up = celestial north: roll 0; turning the camera
    frame by R_3(a) about the boresight gives roll -a."""
    z = np.array([1.0, 0.0, 0.0])
    north = np.array([0.0, 0.0, 1.0])
    y = -north
    x = np.cross(y, z)
    A0 = np.stack([x, y, z])
    assert roll_deg(A0) == pytest.approx(0.0, abs=1e-9)
    for a in (10.0, 90.0, 200.0):
        assert roll_deg(rot_axis(3, math.radians(a))[0] @ A0) == pytest.approx((-a) % 360, abs=1e-9)
    # with north up, east is to the image's left (a sky image, not a mirror image): x = -east
    assert np.allclose(x, [0.0, -1.0, 0.0])


def test_observation_epoch():
    names = ["2019-07-29T204726_Alt40_Azi-135_Try1.tiff", "2019-07-29T204726_Alt60_Azi45_Try1.tiff"]
    assert observation_epoch(names) == 2019.6
    assert observation_epoch(["left01.jpg"]) is None
    assert observation_epoch(["left01.jpg"], "2000-01-01T12:00:00") == 2000.0
    assert julian_year("2000-01-01T12:00:00") == pytest.approx(2000.0, abs=1e-9)


def test_synthetic_frame_round_trip(tmp_path):
    """A noisy frame rendered at a known attitude (sky gradient, shot/read noise, hot pixels), written as
    a 12-bit-in-16-bit TIFF like the ESA frames, with a truth file of the same format: identified, and the
    boresight within a few arcsec of the attitude it was rendered with."""
    from dualsight.kernels.starfield import render_star_fields

    cam = Camera.from_toml(CAMERA)
    A, cat, sensor, f = orion_field(cam)                 # Orion, 30 deg roll, V 7 catalog, noisy sensor
    img = render_star_fields(f.x, f.y, f.flux_e, f.valid, cam.width, cam.height, sensor,
                             np.array([12345], np.uint64))[0].astype(np.float64)
    img += 40.0 * np.linspace(0, 1, cam.width)[None, :]                     # vignetting-like gradient
    tif = tmp_path / "synthetic.tiff"
    cv2.imwrite(str(tif), (np.clip(np.round(img), 0, 4095).astype(np.uint16) << 4))
    ra, dec = (math.degrees(v) for v in unit_to_radec(A[2]))
    truth = tmp_path / "truth.json"
    truth.write_text(json.dumps({"synthetic.tiff": {"ra_deg": ra, "dec_deg": dec, "R_icrs_to_cam": A.tolist(),
                                                    "matched": []}}))
    rc, out, err = run_cli(["hil", "star", str(tif), "--camera", str(CAMERA), "--truth", str(truth), "--json",
                            "--lake", str(tmp_path / "lake"), "--epoch", "2019.6"])
    assert rc == 0, err
    r = json.loads(out)[0]
    assert r["identified"] and r["status"] == "success", r
    assert r["boresight_error_arcsec"] < 5.0 and r["residual_median_arcsec"] < 5.0
    assert abs((r["roll_deg"] - r["roll_true_deg"] + 180) % 360 - 180) < 0.01
    assert r["alt"]["identified"]
    m = Lake(tmp_path / "lake").list_manifests()
    assert len(m) == 1 and m[0]["kind"] == "hil_star" and m[0]["run_id"].startswith("hil-star-")


# ============================================================================================ the engine's job kind
def test_spec_round_trip_and_errors_name_the_field(tmp_path):
    img = tmp_path / "frame.png"
    cv2.imwrite(str(img), np.zeros((768, 1024), np.uint8))
    d = hs.build_spec([img, tmp_path / "missing.png"], Camera.from_toml(CAMERA),
                      settings_from_table({"voting": {"tolerance_arcsec": 15.0}}))
    spec = hs.spec_from_dict(d)
    assert hs.spec_from_dict(spec.to_dict()) == spec and hs.spec_from_dict(json.loads(json.dumps(spec.to_dict()))) == spec
    assert n_cases(spec) == 2 and spec.images[1].bytes is None and spec.images[0].bytes == img.stat().st_size
    assert spec.settings.voting["tolerance_rad"] == pytest.approx(15 * ARCSEC) and spec.settings.alt_voting
    # the robust method's cheaper first round is in the HIL spec; the paper method (alt) has none, and its
    # table does not even hold the key (a newer option at its default leaves older tables unchanged)
    from dualsight.jobs.kinds.hil_star_spec import HIL_FIRST_STARS
    assert spec.settings.voting["first_stars"] == HIL_FIRST_STARS == 12
    assert "first_stars" not in spec.settings.alt_voting
    from dualsight.jobs.kinds import star
    d_star, _ = star.resolve_spec("paper", None)
    assert "first_stars" not in d_star["robust"] and "first_stars" not in d_star["voting"]
    for change, field, words in (({"settings": {"max_obs": 1}}, "settings.max_obs", "greater than or equal to 2"),
                                 ({"settings": {"batch_size": "3"}}, "settings.batch_size", "valid integer"),
                                 ({"settings": {"background_block_px": 2}}, "settings.background_block_px", "[4, 4096]"),
                                 ({"settings": {"catalog": {"mag_limit": 30.0}}}, "settings.catalog", "mag_limit"),
                                 ({"images": [{"path": "rel.png"}]}, "images.0.path", "absolute"),
                                 ({"truths": [{"source": "none"}]}, "truths", "one entry per image"),
                                 ({"truths": [{"source": "file"}] * 2}, "truths.0", "truth attitude"),
                                 ({"colour": 1}, "colour", "unknown key")):
        bad = {**spec.to_dict(), **change}
        with pytest.raises(ConfigError) as e:
            hs.spec_from_dict(bad, source="test.toml")
        assert e.value.source == "test.toml" and field in (e.value.field or ""), (change, e.value)
        assert words in str(e.value), (change, str(e.value))


@needs_esa
def test_local_workers_and_shards_give_the_in_process_rows(tmp_path):
    """The 8 frames with 2 spawned local workers and 3 images per shard (3 shards) against one in-process shard:
    every column of every image and star row equal, timing columns excepted."""
    spec = esa_spec()
    lake = Lake(tmp_path / "lake")
    m1 = run_job("hil_star", spec, n_cases=8, lake=lake, run_id="inproc", workers=1, progress=False)
    m2 = run_job("hil_star", spec, n_cases=8, lake=lake, run_id="pool", workers=2, shard_size=3, progress=False)
    assert m1["status"] == m2["status"] == "complete"
    assert (m1["n_shards"], m2["n_shards"]) == (1, 3) and m2["stats"]["identified"] == 8
    a, b = hil_star_rows(lake.root, "inproc"), hil_star_rows(lake.root, "pool")
    assert len(a["hil_star"]) == 8 and len(a["hil_star_stars"]) > 100
    assert a == b


@needs_esa
def test_resume_recomputes_a_deleted_shard_with_the_same_rows(tmp_path):
    spec = esa_spec()
    lake = Lake(tmp_path / "lake")
    m = run_job("hil_star", spec, n_cases=8, lake=lake, run_id="r", workers=1, shard_size=3, progress=False)
    assert m["status"] == "complete" and m["n_shards"] == 3
    before = hil_star_rows(lake.root, "r")
    for ds in hs.SCHEMAS:
        lake.shard_path(ds, "r", 1).unlink()
    assert len(hil_star_rows(lake.root, "r")["hil_star"]) == 5           # images 3-5 are gone
    m = run_job("hil_star", spec, n_cases=8, lake=lake, run_id="r", workers=1, progress=False)
    assert m["status"] == "complete" and m["executions"][-1]["resumed_shards"] == 2
    assert hil_star_rows(lake.root, "r") == before


@needs_esa
def test_an_image_changed_after_planning_gives_an_error_row(tmp_path):
    frame = tmp_path / "frame.tiff"
    frame.write_bytes((ESA / "2019-07-29T204726_Alt60_Azi135_Try1.tiff").read_bytes())
    d = esa_spec()
    d = hs.build_spec([frame], d["camera"], d["settings"])
    spec = hs.spec_from_dict(d)
    ctx = hs.make_context(spec)
    ok = hs.compute_shard(spec, np.arange(1), ctx)["hil_star"].to_pylist()[0]
    assert ok["error"] is None and ok["identified"]
    os.utime(frame, ns=(frame.stat().st_atime_ns, frame.stat().st_mtime_ns + 10**9))
    row = hs.compute_shard(spec, np.arange(1), ctx)["hil_star"].to_pylist()[0]
    assert row["status"] == "error" and "changed since the run was planned" in row["error"] and not row["identified"]


@needs_esa
def test_an_answer_from_two_identified_stars_is_not_identified(monkeypatch):
    """Issue 11.8: the paper method reported "identified" from 2 stars with a 285,338 arcsec error and its JSON had
    no status.  Two stars fit any catalog pair at their separation, so an answer needs a third star that checks it
    (``MIN_IDENTIFIED_STARS``).  Here the identification of a real ESA frame (which solves with ~20 stars) is cut
    to its first two accepted stars, as a 2-star answer from the voting would be: the attitude solver still gets
    an attitude from them, but the row and the JSON say not identified, with a status, for both methods."""
    one = ESA / "2019-07-29T204726_Alt60_Azi-45_Try1.tiff"
    real_identify = hs.identify

    def two_only(*a, **k):
        ident = real_identify(*a, **k)
        acc = ident.accepted.copy()
        keep = np.cumsum(acc, axis=1) <= 2
        return dataclasses.replace(ident, accepted=acc & keep)

    rc, out, err = run_cli(["hil", "star", str(one), "--camera", str(CAMERA), "--truth", str(TRUTH), "--no-lake",
                            "--json"])
    assert rc == 0, err
    full = json.loads(out)[0]
    assert full["identified"] and full["stars_identified"] >= 10 and full["status"] == "success"
    monkeypatch.setattr(hs, "identify", two_only)
    rc, out, err = run_cli(["hil", "star", str(one), "--camera", str(CAMERA), "--truth", str(TRUTH), "--no-lake",
                            "--json"])
    assert rc == 0, err
    r = json.loads(out)[0]
    assert r["stars_identified"] == 2 and r["T"] > 0            # the voting's answer, cut to two stars
    assert r["identified"] is False and r["status"] not in (None, "success")
    assert r["ra_deg"] is None and r["boresight_error_arcsec"] is None
    assert r["alt"]["identified"] is False and r["alt"]["stars_identified"] == 2
    assert r["alt"]["status"] not in (None, "success") and full["alt"]["status"] == "success"


def test_a_camera_file_without_the_psf_width_gets_the_measured_one_suggested(tmp_path):
    """Frames rendered with a known Gaussian PSF, solved with a camera file that does not state its width: the run
    ends with one stderr line suggesting ``psf_sigma_px`` = the frames' measured median, within 3 % of the width they
    were rendered with; with that line in the camera file nothing is suggested and the frames are solved alike (the
    same boresight to 1 arcsec, the identified stars within 2)."""
    from dualsight.kernels.starfield import render_star_fields

    cam = Camera.from_toml(CAMERA)
    A, cat, sensor, f = orion_field(cam)
    for i in range(3):
        img = render_star_fields(f.x, f.y, f.flux_e, f.valid, cam.width, cam.height, sensor,
                                 np.array([100 + i], np.uint64))[0]
        cv2.imwrite(str(tmp_path / f"f{i}.tiff"), np.clip(np.round(img), 0, 4095).astype(np.uint16) << 4)
    plain = tmp_path / "plain.toml"
    plain.write_text("".join(l for l in CAMERA.read_text().splitlines(True) if not l.startswith("psf_sigma_px")))
    rc, out, err = run_cli(["hil", "star", str(tmp_path), "--camera", str(plain), "--json", "--no-lake",
                            "--epoch", "2019.6"])
    assert rc == 0, err
    hint = [l for l in err.splitlines() if "psf_sigma_px = " in l]
    assert len(hint) == 1 and str(plain) in hint[0], err
    width = float(hint[0].split("psf_sigma_px = ")[1].split()[0])
    assert width == pytest.approx(sensor.psf_sigma_px, rel=0.03)
    stated = tmp_path / "stated.toml"
    stated.write_text(plain.read_text() + f"psf_sigma_px = {width}\n")
    rc2, out2, err2 = run_cli(["hil", "star", str(tmp_path), "--camera", str(stated), "--json", "--no-lake",
                               "--epoch", "2019.6"])
    assert rc2 == 0 and "psf_sigma_px = " not in err2, err2
    a, b = json.loads(out), json.loads(out2)
    assert all(x["identified"] and y["identified"] for x, y in zip(a, b))
    for x, y in zip(a, b):                        # each frame's own width, or the stated median: nearly one answer
        assert abs(x["stars_identified"] - y["stars_identified"]) <= 2
        assert abs(x["ra_deg"] - y["ra_deg"]) * math.cos(math.radians(x["dec_deg"])) * 3600 < 1.0
        assert abs(x["dec_deg"] - y["dec_deg"]) * 3600 < 1.0
