"""Lens distortion from the sky: ``dualsight hil star IMAGES --camera F --fit-distortion -o CAMERA.toml``.

Independent truth: frames rendered by dualsight's own star renderer (kernels/starfield.py, through
scene/camera.py's Brown-Conrady projection) with KNOWN coefficients and attitudes, written as 12-bit-in-16-bit
TIFFs with a truth file; the solver gets a camera file with no distortion and a focal length 1 % short.
The fitted coefficients are compared with the known ones, and the frames are solved with the fitted camera,
the true camera and the uncorrected one by the unchanged ``hil star`` command (its attitude error against
the truth file is computed by nav/hil_score.py, not by the fit).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from dualsight.nav import distortion_fit as dfit
from dualsight.scene.attitude import quat_to_dcm, random_quaternions, unit_to_radec
from dualsight.scene.camera import Camera
from helpers import run_cli

W, H = 1024, 768
HFOV_DEG = 30.0                                  # horizontal field; diagonal 37.0 deg
FX = (W / 2) / math.tan(math.radians(HFOV_DEG / 2))   # 1910.8 px
K1, K2 = -0.22, 0.05                             # barrel: the corners move 15.4 px towards the centre
N_FRAMES = 12
FX_GIVEN = round(0.99 * FX, 1)                   # the camera file's focal length: 1 % short
SOLVE = ["--mag-limit", "6.0", "--epoch", "2000", "--no-compare"]


def write_camera(path: Path, fx: float, distortion=None) -> Path:
    lines = ["[camera]", f"width = {W}", f"height = {H}", "pixel_pitch_um = 4.65", f"fx = {fx!r}"]
    if distortion is not None:
        lines.append(f"distortion = {list(distortion)!r}")
    path.write_text("\n".join(lines) + "\n")
    return path


def corner_shift_px(cam: Camera) -> float:
    """How far the distortion moves the image corner's star (px), from the camera model."""
    v = np.array([[(0 - cam.cx) / cam.fx, (0 - cam.cy) / cam.fy, 1.0]])
    ideal = np.array([cam.cx + cam.fx * v[0, 0], cam.cy + cam.fy * v[0, 1]])
    return float(np.linalg.norm(cam.project(v)[0][0] - ideal))


@pytest.fixture(scope="module")
def sky(tmp_path_factory):
    """12 noisy frames at random attitudes through the distorted lens (stars to V 7; the solver's catalog
    goes to V 6), their truth file, and camera files: true; without coefficients and fx 1 % short (what the
    fit starts from); without coefficients and the true fx."""
    from dualsight.catalogs.stars import StarCatalogConfig, load_star_catalog
    from dualsight.jobs.kinds.star import psf_margin_px
    from dualsight.kernels.sensor_config import SensorConfig, flux_from_magnitude
    from dualsight.kernels.starfield import render_star_fields
    from dualsight.scene.starfield_geometry import stars_in_field

    tmp = tmp_path_factory.mktemp("distortion")
    cam = Camera(W, H, 4.65e-6, FX, FX, W / 2, H / 2, (K1, K2, 0.0, 0.0, 0.0))
    A = quat_to_dcm(random_quaternions(np.random.default_rng(3), N_FRAMES))
    cat = load_star_catalog(StarCatalogConfig(mag_limit=7.0, epoch_jyear=2000.0))
    sensor = SensorConfig(exposure_s=0.3, shot_noise=True, read_noise_e=15.0, sky_background_e=300.0,
                          bias_adu=20.0)
    f = stars_in_field(A, cat.unit, flux_from_magnitude(cat.vmag, sensor), cam, psf_margin_px(sensor))
    imgs = render_star_fields(f.x, f.y, f.flux_e, f.valid, W, H, sensor, np.arange(N_FRAMES, dtype=np.uint64) + 100)
    frames = tmp / "frames"
    frames.mkdir()
    truth = {}
    for i in range(N_FRAMES):
        name = f"frame{i:02d}.tiff"
        cv2.imwrite(str(frames / name), np.clip(imgs[i], 0, 4095).astype(np.uint16) << 4)
        ra, dec = (math.degrees(x) for x in unit_to_radec(A[i, 2]))
        truth[name] = {"ra_deg": ra, "dec_deg": dec, "R_icrs_to_cam": A[i].tolist(), "matched": []}
    (tmp / "truth.json").write_text(json.dumps(truth))
    return {"tmp": tmp, "frames": frames, "truth": tmp / "truth.json", "camera": cam,
            "true_toml": write_camera(tmp / "true.toml", FX, cam.distortion),
            "plain_toml": write_camera(tmp / "plain.toml", FX_GIVEN),
            "fx_only_toml": write_camera(tmp / "fx_only.toml", FX),
            "n_generated": f.n_generated}


@pytest.fixture(scope="module")
def fitted(sky):
    out = sky["tmp"] / "fitted.toml"
    rc, stdout, err = run_cli(["hil", "star", sky["frames"], "--camera", sky["plain_toml"], "--truth", sky["truth"],
                               *SOLVE, "--fit-distortion", "-o", out, "--json"])
    assert rc == 0, err
    return {"path": out, "json": json.loads(stdout), "camera": Camera.from_toml(out)}


def solve_with(sky, camera_toml: Path, lake: Path) -> dict:
    """``hil star`` (the engine, unchanged) on the frames with a camera file: solve count and attitude errors
    against the truth file (arcsec)."""
    rc, out, err = run_cli(["hil", "star", sky["frames"], "--camera", camera_toml, "--truth", sky["truth"], *SOLVE,
                            "--json", "--lake", lake, "--workers", "1", "--no-progress"])
    assert rc == 0, err
    rows = json.loads(out)
    ok = [r for r in rows if r["identified"]]
    errs = np.array([r["attitude_error_arcsec"] for r in ok])
    return {"solved": len(ok), "success": sum(r["status"] == "success" for r in rows), "err": errs,
            "stars": sum(r["stars_identified"] for r in ok)}


# ============================================================================================ the model
def test_model_is_the_camera_projection_and_its_jacobians_are_derivatives():
    """The fit's own model equations agree with scene/camera.py's projection (the renderer's), and its
    analytic derivatives with central differences."""
    rng = np.random.default_rng(0)
    intr = dfit.Intrinsics(1900.0, 1910.0, 500.0, 390.0, (-0.2, 0.05, 1e-3, -2e-3, 0.01))
    cam = Camera(W, H, 4.65e-6, intr.fx, intr.fy, intr.cx, intr.cy, intr.distortion)
    v = np.column_stack([rng.normal(0, 0.2, (50, 2)), np.ones(50)])
    px, d_v, d_k, _ = dfit.project_with_jacobians(v, intr)
    assert np.allclose(px, cam.project(v)[0], rtol=0, atol=1e-9)
    h = 1e-6
    num = np.stack([(dfit.project(v + h * e, intr) - dfit.project(v - h * e, intr)) / (2 * h) for e in np.eye(3)], -1)
    assert np.allclose(num, d_v, rtol=1e-6, atol=1e-6)
    for j in range(2):
        up, dn = np.array(intr.distortion), np.array(intr.distortion)
        up[j] += h
        dn[j] -= h
        num = (dfit.project(v, dfit.Intrinsics(intr.fx, intr.fy, intr.cx, intr.cy, tuple(up)))
               - dfit.project(v, dfit.Intrinsics(intr.fx, intr.fy, intr.cx, intr.cy, tuple(dn)))) / (2 * h)
        assert np.allclose(num, d_k[:, :, j], rtol=1e-6, atol=1e-6)


def test_fit_recovers_known_coefficients_and_rejects_misidentified_stars():
    """Arrays only (no images): 20 frames x 40 stars projected by a known camera, 0.1 px noise, attitudes
    off by ~1 arcmin, 6 stars given a wrong identity (moved 30-60 px): the fitted k1, k2, fx are within 3
    sigma of the truth and exactly the 6 wrong stars are rejected."""
    rng = np.random.default_rng(1)
    true = Camera(W, H, 4.65e-6, FX, FX, W / 2, H / 2, (K1, K2, 0.0, 0.0, 0.0))
    F, n = 20, 40
    A = quat_to_dcm(random_quaternions(rng, F))
    pts = np.column_stack([rng.uniform(0, W, F * n), rng.uniform(0, H, F * n)])
    frame = np.repeat(np.arange(F), n)
    u = np.einsum("nji,nj->ni", A[frame], true.backproject(pts))          # A^T v: ICRS directions
    px = pts + rng.normal(0, 0.1, pts.shape)
    bad = rng.choice(F * n, 6, replace=False)
    px[bad] += rng.uniform(30, 60, (6, 1)) * np.array([[0.6, -0.8]])
    A0 = dfit.rotation_exp(rng.normal(0, 3e-4, (F, 3))) @ A
    r = dfit.fit_camera(u, frame, px, A0, dfit.Intrinsics(FX_GIVEN, FX_GIVEN, W / 2, H / 2))
    k1, k2 = r.intrinsics.distortion[:2]
    assert abs(k1 - K1) < 3 * r.std["k1"] and abs(k2 - K2) < 3 * r.std["k2"], (k1, k2, r.std)
    assert abs(r.intrinsics.fx - FX) < 3 * r.std["fx"] and r.intrinsics.fx == r.intrinsics.fy
    assert set(np.flatnonzero(~r.inlier)) == set(bad)
    assert 0.09 < r.sigma_px < 0.11 and r.n_frames == F


# ============================================================================================ from the sky
def test_the_rendered_lens_is_strongly_distorted(sky):
    assert 14.0 < corner_shift_px(sky["camera"]) < 17.0
    assert sky["n_generated"].min() > 100                  # stars to V 7 on every frame


def test_fitted_k1_within_10_percent_of_the_truth(sky, fitted):
    cam = fitted["camera"]
    k1, k2 = cam.distortion[:2]
    print(f"\nk1 true {K1} fitted {k1:.5f} ({(k1 - K1) / abs(K1):+.2%}); k2 true {K2} fitted {k2:.5f}; fx true "
          f"{FX:.2f} given {FX_GIVEN} fitted {cam.fx:.2f}; {fitted['json']['stars_used']} stars in "
          f"{fitted['json']['frames_used']} frames; rms {fitted['json']['rms_before_px']:.3f} -> "
          f"{fitted['json']['rms_after_px']:.3f} px")
    assert abs(k1 - K1) < 0.10 * abs(K1)
    assert abs(cam.fx - FX) < 0.001 * FX and cam.fy == cam.fx
    assert (cam.cx, cam.cy) == (W / 2, H / 2) and cam.distortion[2:] == (0.0, 0.0, 0.0)
    # the fitted model puts every pixel of the image where the true lens does, to a fraction of a pixel
    g = np.stack(np.meshgrid(np.linspace(0, W, 17), np.linspace(0, H, 13)), -1).reshape(-1, 2)
    dirs = sky["camera"].backproject(g)
    assert np.abs(cam.project(dirs)[0] - g).max() < 0.3


def test_fitted_camera_file_says_what_was_fitted(fitted):
    text = fitted["path"].read_text()
    j = fitted["json"]
    head = [line for line in text.splitlines() if line.startswith("#")]
    assert any(f"{j['stars_used']} identified stars in {j['frames_used']} solved frames" in line for line in head)
    assert any("rms residual" in line and "before" in line and "after" in line for line in head)
    assert j["rms_after_px"] < 0.2 < 1.0 < j["rms_before_px"]
    import tomllib
    d = tomllib.loads(text)
    assert d["distortion_fit"]["stars_used"] == j["stars_used"] >= 500
    assert set(d["camera"]) >= {"width", "height", "pixel_pitch_um", "fx", "fy", "cx", "cy", "distortion"}


def test_fit_solves_as_well_as_the_true_coefficients_and_better_than_none(sky, fitted):
    lake = sky["tmp"] / "lake"
    with_true = solve_with(sky, sky["true_toml"], lake)
    with_fit = solve_with(sky, fitted["path"], lake)
    without = solve_with(sky, sky["plain_toml"], lake)
    fx_only = solve_with(sky, sky["fx_only_toml"], lake)          # the true focal length, still no distortion
    for name, s in (("true", with_true), ("fitted", with_fit), ("none", without), ("fx only", fx_only)):
        e = s["err"]
        print(f"{name:>6}: {s['solved']}/{N_FRAMES} solved, {s['success']} success, {s['stars']} stars, attitude "
              f"error median {np.median(e) if e.size else float('nan'):.2f} max "
              f"{e.max() if e.size else float('nan'):.2f} arcsec")
    assert with_true["solved"] == with_true["success"] == N_FRAMES
    # (b) fitted camera: every frame, errors comparable with the true lens's
    assert with_fit["solved"] == with_fit["success"] == N_FRAMES
    assert np.median(with_fit["err"]) < 1.5 * np.median(with_true["err"]) + 1.0
    assert with_fit["err"].max() < 1.5 * with_true["err"].max() + 1.0
    assert with_fit["stars"] >= 0.95 * with_true["stars"]
    # (c) without the fit, even with the true focal length: fewer frames solve, and those that do are worse
    for s in (without, fx_only):
        assert s["solved"] <= N_FRAMES // 2 and s["stars"] < 0.2 * with_true["stars"]
        if s["err"].size:
            assert np.median(s["err"]) > 3 * np.median(with_fit["err"])


# ============================================================================================ the command line
def test_refusals_are_one_line(sky, tmp_path):
    base = ["hil", "star", sky["frames"], "--camera", sky["plain_toml"], *SOLVE, "--fit-distortion"]
    rc, out, err = run_cli(base)
    assert rc == 2 and err.count("\n") == 1 and "-o/--output" in err, err
    existing = tmp_path / "exists.toml"
    existing.write_text("# mine\n")
    rc, out, err = run_cli([*base, "-o", existing])
    assert rc == 2 and err.count("\n") == 1 and "exists" in err and "--force" in err, err
    assert existing.read_text() == "# mine\n"
    rc, out, err = run_cli(["hil", "star", sky["frames"], "--camera", sky["plain_toml"], "-o", tmp_path / "x.toml"])
    assert rc == 2 and err.count("\n") == 1 and "--fit-distortion" in err, err
    # too few stars: two frames, each keeping only its 10 brightest detections (max_obs), so <= 20 identified
    cfg = tmp_path / "few.toml"
    cfg.write_text("max_obs = 10\n")
    two = sorted(sky["frames"].glob("*.tiff"))[:2]
    rc, out, err = run_cli(["hil", "star", *two, "--camera", sky["true_toml"], *SOLVE, "--config", cfg,
                            "--fit-distortion", "-o", tmp_path / "few_out.toml"])
    last = err.splitlines()[-1]                  # after the progress lines of the passes, one line
    assert rc == 2 and last.startswith("dualsight: error: --fit-distortion: only "), err
    assert "stars identified" in last and "at least 30" in last, err
    assert not (tmp_path / "few_out.toml").exists()


def test_the_fitted_camera_keeps_everything_but_the_intrinsics():
    """A fit replaces fx, fy, cx, cy and the distortion; the size, pixel pitch, bit depth and the stated PSF width of
    the input camera file stay (a fitted camera file that dropped ``psf_sigma_px`` would slow every later run)."""
    from dualsight.nav.distortion_procedure import camera_with
    from dualsight.scene.segment import undistort_image

    cam = Camera(640, 480, 4.65e-6, 800.0, 800.0, 320.0, 240.0, (0.01, 0.0, 0.0, 0.0, 0.0), 10, 0.8)
    out = camera_with(cam, dfit.Intrinsics(810.0, 812.0, 321.0, 239.0, (0.1, 0.01, 0.0, 0.0, 0.0)))
    assert (out.fx, out.fy, out.cx, out.cy, out.distortion) == (810.0, 812.0, 321.0, 239.0, (0.1, 0.01, 0.0, 0.0, 0.0))
    assert (out.width, out.height, out.pixel_pitch_m, out.bit_depth, out.psf_sigma_px) == (640, 480, 4.65e-6, 10, 0.8)
    _, flat = undistort_image(np.zeros((480, 640), np.uint16), cam)
    assert flat.distortion == (0.0,) * 5 and flat.psf_sigma_px == 0.8 and flat.fx == 800.0


def test_the_fitted_camera_file_states_the_frames_psf_width(sky, fitted):
    """The input camera file states no PSF width; the frames, rendered with a 0.8 px Gaussian, measure one: the
    fitted camera file states it (within 3 %) and says where it came from."""
    assert "psf_sigma_px" not in sky["plain_toml"].read_text()
    assert fitted["camera"].psf_sigma_px == pytest.approx(0.8, rel=0.03)
    assert any("psf_sigma_px" in line for line in fitted["path"].read_text().splitlines() if line.startswith("#"))
