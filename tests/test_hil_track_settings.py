"""``dualsight hil star IMAGES --track --tracking FILE.toml`` (issue 22, point 4): the tracker's settings from a file,
so that a camera known to turn slowly tracks from the second frame (without them the second frame's prior has no
rate and windows too wide to pass the chance-match test: tracking from the third).

Independent truth: the rendered ground camera of tests/test_hil_track.py (a fixed camera on the rotating Earth, its
attitude written out there), the sidereal rate (IERS), the attitude's declination from the rendered matrix."""

from __future__ import annotations

import numpy as np

from test_hil_track import OMEGA_EARTH, _render_ground_sequence, _track


def test_a_ground_camera_tracks_from_the_second_frame_with_its_settings(tmp_path):
    """Four frames 30 s apart: with ``rate_sigma_arcsec_s = 6`` (the sidereal 15 arcsec/s is 2.5 sigma of it) the second frame's
    windows are tight enough: lost in space on the first frame, tracking from the second; every later attitude's
    declination within 10 arcsec of the rendered one, each rate 15.04 arcsec/s within 3 stated sigmas."""
    cam, paths, times, A = _render_ground_sequence(tmp_path, 4, 30.0)
    settings = tmp_path / "tracking.toml"
    settings.write_text("max_coast_frames = 3\n[tracking]\nrate_sigma_arcsec_s = 6\n")
    rc, docs, err = _track(cam, paths, times, tmp_path / "lake", "--tracking", settings)
    assert rc == 0, err
    modes = [(d["mode"], d["mode_reason"]) for d in docs]
    assert modes == [("lost_in_space", "no_prior")] + [("tracking", "locked")] * 3, modes
    for k in range(1, 4):
        d = docs[k]
        assert abs(d["track_dec_deg"] - np.degrees(np.arcsin(A[k][2, 2]))) < 10 / 3600
        w, sig = np.radians(d["rate_deg_s"]), np.radians(d["rate_sigma_deg_s"])
        u = w / np.linalg.norm(w)
        assert abs(np.linalg.norm(w) - OMEGA_EARTH) <= 3 * float(np.sqrt(np.sum((u * sig) ** 2))), k
    # without the file the second frame cannot track yet (the reason this option exists)
    rc, docs, err = _track(cam, paths, times, tmp_path / "lake2")
    assert rc == 0 and docs[1]["mode"] == "lost_in_space", [(d["mode"], d["mode_reason"]) for d in docs]


def test_tracking_file_refusals_are_one_line(tmp_path, capsys):
    from dualsight.jobs.cli.main import main
    from helpers import ROOT

    import cv2

    cam = ROOT / "examples" / "cameras" / "esa_tetra3.toml"
    img = tmp_path / "2020-01-01T000000_a.tiff"
    cv2.imwrite(str(img), np.zeros((768, 1024), np.uint16))
    f = tmp_path / "t.toml"
    for text, argv, needle in (
            ("[tracking]\nrate_sigma_arcsec_s = 30\n", [], "--tracking: goes with --track"),
            ("[tracking]\nrate_sigma_deg_s = -1\n", ["--track"],
             f"{f} [tracking.rate_sigma_deg_s]: must be in (0, 30 deg/s], got -1"),
            ("[tracking]\nwindow_k = 3\n", ["--track"], f"{f} [tracking.window_k]: unknown key"),
            ("max_coast = 3\n", ["--track"], f"{f} [max_coast]: unknown key"),
            ("lis_min_stars = 2\n", ["--track"], f"{f} [lis_min_stars]: Input should be greater than or equal to 3")):
        f.write_text(text)
        assert main(["hil", "star", str(img), "--camera", str(cam), "--no-lake", "--tracking", str(f), *argv]) == 2
        e = capsys.readouterr().err
        assert e.count("\n") == 1 and needle in e, (text, e)
