"""``dualsight hil star IMAGES --track`` (issue 22, point 4): the images' times (scene/frame_times.py) against
hand-written truth and files written by independent writers (Pillow's EXIF, astropy's FITS), and the frames solved
as one ordered sequence (nav/sequence.py) against the sidereal rate of a fixed ground camera."""

from __future__ import annotations

from datetime import datetime, timezone

import numpy as np
import pytest

from dualsight.errors import InputError
from dualsight.scene import frame_times as ft


def _utc(*a):
    return datetime(*a, tzinfo=timezone.utc)


# ============================================================================================ times
def test_file_name_times():
    assert ft.filename_time("2019-07-29T204726_Alt40_Azi-135_Try1.tiff") == _utc(2019, 7, 29, 20, 47, 26)
    assert ft.filename_time("/x/night_2021-01-02T03:04:05.25.png") == _utc(2021, 1, 2, 3, 4, 5, 250000)
    assert ft.filename_time("20210102T030405.fits") == _utc(2021, 1, 2, 3, 4, 5)
    assert ft.filename_time("2021-01-02_030405.jpg") == _utc(2021, 1, 2, 3, 4, 5)
    for bad in ("frame_0001.tiff", "2021-13-02T030405.png", "12021-01-02T030405.png"):
        assert ft.filename_time(bad) is None, bad


def test_times_csv_and_its_errors(tmp_path):
    f = tmp_path / "t.csv"
    f.write_text("image,utc\n# comment\n\na.png,2020-01-01T00:00:10.5Z\n/some/dir/b.png, 2020-01-01T01:00:00+01:00\n")
    assert ft.read_times_csv(f) == {"a.png": _utc(2020, 1, 1, 0, 0, 10, 500000), "b.png": _utc(2020, 1, 1)}
    for text, needle in (("name,time\na.png,2020-01-01T00:00:00\n", "line 1: the header must be image,utc"),
                         ("image,utc\na.png\n", "line 2: needs two fields"),
                         ("image,utc\n,2020-01-01T00:00:00\n", "line 2: field image is empty"),
                         ("image,utc\na.png,2020-01-01T00:00:00\n\na.png,2020-01-01T00:00:01\n",
                          "line 4: field image 'a.png' is listed twice"),
                         ("image,utc\na.png,yesterday\n", "line 2: field utc is not an ISO 8601 time"),
                         ("", "is empty")):
        f.write_text(text)
        with pytest.raises(InputError) as e:
            ft.read_times_csv(f)
        assert str(e.value).startswith(str(f)) and needle in str(e.value), (text, str(e.value))
    with pytest.raises(InputError, match="is not a file"):
        ft.read_times_csv(tmp_path / "missing.csv")


def test_exif_times_written_by_pillow(tmp_path):
    Image = pytest.importorskip("PIL.Image")
    img = Image.new("L", (16, 8), 7)
    cases = [("a.jpg", {0x9003: "2022:03:04 05:06:07"}, _utc(2022, 3, 4, 5, 6, 7)),
             ("b.jpg", {0x9003: "2022:03:04 05:06:07", 0x9291: "25", 0x9011: "+02:00"},
              _utc(2022, 3, 4, 3, 6, 7, 250000)),
             ("c.tiff", {0x9003: "2022:03:04 05:06:07", 0x9291: "5", 0x9011: "-01:30"},
              _utc(2022, 3, 4, 6, 36, 7, 500000)),
             ("d.jpg", {}, None)]
    for name, tags, truth in cases:
        exif = Image.Exif()
        exif[0x0110] = "test camera"
        if tags:
            exif.get_ifd(0x8769).update(tags)
        if name.endswith(".tiff"):          # Pillow's TIFF writer drops the Exif IFD: its EXIF block is a TIFF
            (tmp_path / name).write_bytes(exif.tobytes()[6:])
        else:
            img.save(tmp_path / name, exif=exif)
        assert ft.exif_datetime(tmp_path / name) == truth, name
    assert ft.exif_datetime(tmp_path / "missing.jpg") is None


def test_fits_date_obs_and_the_order_of_sources(tmp_path):
    fits = pytest.importorskip("astropy.io.fits")
    hdu = fits.PrimaryHDU(np.zeros((4, 4), np.uint16))
    hdu.header["DATE-OBS"] = "2023-05-06T07:08:09.125"
    hdu.writeto(tmp_path / "2000-01-01T000000_x.fits")
    p_fits = tmp_path / "2000-01-01T000000_x.fits"
    p_name = tmp_path / "2001-02-03T040506_y.png"
    p_none = tmp_path / "z.png"
    for p in (p_name, p_none):
        p.write_bytes(b"")
    got = ft.frame_times([p_fits, p_name])
    assert [(t.utc, t.source) for t in got] == [(_utc(2023, 5, 6, 7, 8, 9, 125000), "fits"),
                                                (_utc(2001, 2, 3, 4, 5, 6), "file_name")]
    assert got[0].iso == "2023-05-06T07:08:09.125000Z"
    csv = tmp_path / "t.csv"
    csv.write_text("image,utc\nz.png,2024-01-01T00:00:00Z\n2000-01-01T000000_x.fits,2024-01-01T00:00:01Z\n")
    got = ft.frame_times([p_fits, p_none, p_name], csv)
    assert [t.source for t in got] == ["times_file", "times_file", "file_name"]
    assert ft.time_order(got) == [2, 1, 0]
    assert ft.seconds_since([got[i] for i in (1, 0)]) == [0.0, 1.0]
    with pytest.raises(InputError) as e:
        ft.frame_times([p_name, p_none])
    assert str(e.value).startswith("--track: z.png: no time") and "--times FILE" in str(e.value)
    with pytest.raises(InputError, match=r"^--times: z.png: no time \(not listed in"):
        ft.frame_times([p_none], tmp_path / "empty.csv") if (tmp_path / "empty.csv").write_text(
            "image,utc\n") else None


def test_time_order_is_stable_for_equal_times():
    t = [ft.FrameTime(_utc(2020, 1, 1, 0, 0, s), "file_name") for s in (5, 1, 5, 0)]
    assert ft.time_order(t) == [3, 1, 0, 2]


# ============================================================================================ a fixed ground camera
OMEGA_EARTH = 7.2921150e-5
"""Earth's rotation rate relative to the stars (rad/s; IERS), 15.041 arcsec/s."""


def _render_ground_sequence(tmp_path, n: int, dt: float, dec_deg: float = 5.0):
    """``n`` noisy 12-bit-in-16-bit TIFFs of a camera fixed on the rotating Earth, ``dt`` s apart, and a CSV of
    their times (written in reverse order, to be sorted).  A(t) = A0 R_3(omega t) (passive R_3, the
    reference's convention): the camera's axes turn by +omega t about the ICRS z axis, eastward with the Earth.
    Returns (camera file, image paths in time order, times CSV, A(t) (n, 3, 3))."""
    import cv2

    from dualsight.catalogs.stars import StarCatalogConfig, load_star_catalog
    from dualsight.jobs.kinds.star import psf_margin_px
    from dualsight.kernels.sensor_config import SensorConfig, flux_from_magnitude
    from dualsight.kernels.starfield import render_star_fields
    from dualsight.scene.attitude import radec_to_unit, rot_axis
    from dualsight.scene.camera import Camera
    from dualsight.scene.starfield_geometry import stars_in_field
    from helpers import ROOT

    camera_file = ROOT / "examples" / "cameras" / "esa_tetra3.toml"
    cam = Camera.from_toml(camera_file)
    z = radec_to_unit(np.radians(84.0), np.radians(dec_deg))
    east = np.cross([0.0, 0.0, 1.0], z)
    east /= np.linalg.norm(east)
    north = np.cross(z, east)
    A0 = rot_axis(3, np.radians(30.0))[0] @ np.stack([np.cross(-north, z), -north, z])
    t = dt * np.arange(n)
    A = A0[None] @ rot_axis(3, OMEGA_EARTH * t)
    cat = load_star_catalog(StarCatalogConfig(mag_limit=7.0, epoch_jyear=2019.6))
    sensor = SensorConfig(exposure_s=0.3, shot_noise=True, read_noise_e=15.0, sky_background_e=300.0, bias_adu=20.0)
    f = stars_in_field(A, cat.unit, flux_from_magnitude(cat.vmag, sensor), cam, psf_margin_px(sensor))
    imgs = render_star_fields(f.x, f.y, f.flux_e, f.valid, cam.width, cam.height, sensor,
                              np.arange(100, 100 + n, dtype=np.uint64))
    paths = []
    for k in range(n):
        p = tmp_path / f"frame_{k:02d}.tiff"
        cv2.imwrite(str(p), np.clip(np.round(imgs[k]), 0, 4095).astype(np.uint16) << 4)
        paths.append(p)
    times = tmp_path / "times.csv"
    t0 = datetime(2024, 3, 1, 22, 0, 0, tzinfo=timezone.utc).timestamp()
    times.write_text("image,utc\n" + "".join(
        f"{paths[k].name},{datetime.fromtimestamp(t0 + t[k], timezone.utc).isoformat()}\n" for k in reversed(range(n))))
    return camera_file, paths, times, A


def _track(camera_file, images, times, lake, *extra):
    import json

    from helpers import run_cli

    argv = ["hil", "star", *images, "--camera", camera_file, "--track", "--json", "--no-compare", "--epoch",
            "2019.6", "--lake", lake, "--no-progress", *extra]
    if times is not None:
        argv += ["--times", times]
    rc, out, err = run_cli(argv)
    return rc, (json.loads(out) if out.strip() else None), err


def test_a_fixed_ground_camera_sees_the_sidereal_rate_about_the_pole(tmp_path):
    """Five frames 30 s apart of a camera fixed on the ground, given in shuffled order with a --times CSV: sorted by
    time, lost in space on the first, tracking from the third on (module: the second has no rate yet), and each rate 15.04 arcsec/s within its stated
    3 sigma and, rotated to ICRS by the rendered attitude, along +z (the Earth's axis: the camera turns
    eastward) within 2 deg."""
    n, dt = 5, 30.0
    cam, paths, times, A = _render_ground_sequence(tmp_path, n, dt)
    shuffled = [paths[i] for i in (3, 0, 4, 2, 1)]
    rc, docs, err = _track(cam, shuffled, times, tmp_path / "lake")
    assert rc == 0, err
    assert [d["image"] for d in docs] == [p.name for p in paths]
    assert [d["time_source"] for d in docs] == ["times_file"] * n
    t = [datetime.fromisoformat(d["time_utc"].replace("Z", "+00:00")).timestamp() for d in docs]
    assert np.allclose(np.diff(t), dt, atol=1e-6)
    modes = [(d["mode"], d["mode_reason"]) for d in docs]
    # the second frame has no rate yet: a zero-rate prior of TrackingConfig.rate_sigma_rad_s (0.5 deg/s x 30 s)
    # caps its windows at 50 px, where the chance-match test refuses the lock and lost-in-space answers; from the
    # third frame on the rate of the first two fixes makes the windows tight
    assert modes[0] == ("lost_in_space", "no_prior") and modes[1] in (("tracking", "locked"),
                                                                      ("lost_in_space", "p_chance")), modes
    assert modes[2:] == [("tracking", "locked")] * (n - 2), modes
    assert docs[0]["rate_deg_s"] is None
    for k in range(1, n):
        d = docs[k]
        w = np.radians(d["rate_deg_s"])                  # rad/s, camera frame
        sig = np.radians(d["rate_sigma_deg_s"])
        mag = np.linalg.norm(w)
        u = w / mag
        sig_mag = float(np.sqrt(np.sum((u * sig) ** 2)))       # per-axis sigmas along the rate's direction
        assert abs(mag - OMEGA_EARTH) <= 3 * sig_mag, (k, mag / OMEGA_EARTH, sig_mag / OMEGA_EARTH)
        assert sig_mag < 0.02 * OMEGA_EARTH, (k, sig_mag / OMEGA_EARTH)        # the check means something
        icrs = A[k].T @ u
        off_axis = np.degrees(np.arccos(np.clip(icrs[2], -1, 1)))
        bound = np.degrees(3 * np.linalg.norm(sig) / mag)       # 3 sigma of the rate across its direction
        assert off_axis < min(bound, 5.0), (k, off_axis, bound)
        # the sequence's attitude is the rendered one (boresight within 10 arcsec)
        assert abs(d["track_dec_deg"] - np.degrees(np.arcsin(A[k][2, 2]))) < 10 / 3600


# ============================================================================================ the ESA frames
def _esa():
    from helpers import ROOT, shared_real

    esa = shared_real() / "esa_tetra3"
    if not (esa / "truth.json").exists():
        pytest.skip(f"ESA tetra3 frames not found at {esa}")
    return ROOT / "examples" / "cameras" / "esa_tetra3.toml", sorted(esa.glob("*.tiff"))


def test_esa_frames_at_one_instant_are_solved_lost_in_space_each(tmp_path):
    """The eight ESA frames share one time (their file names) and eight pointings: no sequence (dt = 0), each
    frame lost in space alone, no rate; the lost-in-space keys are those of a run without --track."""
    cam, frames = _esa()
    rc, docs, err = _track(cam, frames, None, tmp_path / "lake")
    assert rc == 0, err
    assert len(docs) == 8 and {d["time_utc"] for d in docs} == {"2019-07-29T20:47:26.000000Z"}
    assert {d["time_source"] for d in docs} == {"file_name"}
    assert [(d["mode"], d["mode_reason"], d["rate_deg_s"]) for d in docs] == [("lost_in_space", "no_prior", None)] * 8
    for d in docs:         # the sequence's attitude is the frame's own lost-in-space answer
        assert d["identified"] and abs(d["track_dec_deg"] - d["dec_deg"]) < 1 / 3600, d["image"]


def test_esa_frames_given_as_a_sequence_fall_back_to_lost_in_space(tmp_path):
    """The same frames 7 s apart by a --times CSV: the prediction from the previous pointing (>= 20 deg away)
    matches nothing, so every frame falls back to lost in space and is solved; the rate is the (large) one
    between two successive fixes."""
    cam, frames = _esa()
    times = tmp_path / "t.csv"
    times.write_text("image,utc\n" + "".join(f"{p.name},2019-07-29T20:47:{7 * k:02d}Z\n" for k, p in enumerate(frames)))
    rc, docs, err = _track(cam, frames, times, tmp_path / "lake")
    assert rc == 0, err
    assert [d["image"] for d in docs] == [p.name for p in frames]
    assert [d["mode"] for d in docs] == ["lost_in_space"] * 8
    assert docs[0]["mode_reason"] == "no_prior"
    assert all(d["mode_reason"] in ("too_few_matches", "p_chance", "residual", "degenerate") for d in docs[1:])
    assert all(d["rate_deg_s"] is not None and np.linalg.norm(d["rate_deg_s"]) > 1.0 for d in docs[1:])


def test_track_refusals_are_one_line(tmp_path, capsys):
    from dualsight.jobs.cli.main import main
    from helpers import ROOT

    import cv2

    cam = ROOT / "examples" / "cameras" / "esa_tetra3.toml"
    img = tmp_path / "no_time.tiff"
    cv2.imwrite(str(img), np.zeros((768, 1024), np.uint16))
    bad = tmp_path / "t.csv"
    bad.write_text("image,utc\nno_time.tiff,soon\n")
    for argv, needle in ((["--track"], "--track: no_time.tiff: no time"),
                         (["--times", str(bad)], "--times: goes with --track"),
                         (["--track", "--times", str(bad)], f"{bad}: line 2: field utc is not an ISO 8601 time"),
                         (["--track", "--sweep", "k-sigma=4,5"], "--track: solves one sequence")):
        assert main(["hil", "star", str(img), "--camera", str(cam), "--no-lake", *argv]) == 2, argv
        e = capsys.readouterr().err
        assert e.count("\n") == 1 and needle in e, (argv, e)
