"""A bright object crossing the field of a tracking sequence (issue 22, point 1): ``[sequence] bright_crossings``.

Independent truths: the crossing's straight path (equal steps covering the image diagonal, written out here), the
object's pixel position from its stored RA/Dec through a pinhole and the true attitude written out here, the
error limit from the stored true and estimated attitudes (``eq4_errors`` of tests/test_star_track_job.py), and the
report's crossing-frame counts recounted with numpy from the ``star_frames`` rows.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from dualsight.scene.attitude_trajectory import CROSSING, EVENT_NAMES, NORMAL, crossing_paths
from dualsight.warehouse.query import run_sql
from helpers import run_cli

ARCSEC = math.pi / 180 / 3600


def test_crossing_paths_cover_the_diagonal_in_equal_steps():
    W, H, L = 1024, 768, 6
    fr, xy, idx = crossing_paths(40, 3, L, W, H, np.random.default_rng(2))
    assert fr.shape == (3 * L,) and set(idx.tolist()) == {0, 1, 2}
    diag = math.hypot(W, H)
    for c in range(3):
        f, p = fr[idx == c], xy[idx == c]
        assert f[0] >= 1 and np.all(np.diff(f) == 1)                   # consecutive, never the first frame
        steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
        np.testing.assert_allclose(steps, diag / L, rtol=1e-12)
        d = np.diff(p, axis=0)                                           # one straight line
        assert np.abs(d[:, 0] * d[0, 1] - d[:, 1] * d[0, 0]).max() < 1e-6 * (diag / L) ** 2
        mid = 0.5 * (p[0] + p[-1])
        assert W / 4 <= mid[0] <= 3 * W / 4 and H / 4 <= mid[1] <= 3 * H / 4


def _pinhole(cam, A, radec_deg):
    """Pixel (col, row) of an ICRS direction through an undistorted pinhole: x = fx X / Z + cx."""
    ra, dec = np.radians(radec_deg[0]), np.radians(radec_deg[1])
    v = A @ np.array([math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec)])
    return np.array([cam.fx * v[0] / v[2] + cam.cx, cam.fy * v[1] / v[2] + cam.cy])


def _eq4(A_true, A_est):
    """Per-axis errors (rad) by the reference's Eq. 4: A_true A_est^T ~ I + [phi x]."""
    D = A_true @ A_est.T
    return np.array([D[1, 2] - D[2, 1], D[2, 0] - D[0, 2], D[0, 1] - D[1, 0]]) / 2


@pytest.fixture(scope="module")
def track():
    from dualsight.jobs.kinds import star_track as st

    def run(radius_px, vmag, cases=(0, 1, 2)):
        sp = st.spec_from_dict({**st.PRESETS["paper"], "sequence": {
            "frames": 14, "bright_crossings": 1, "crossing_frames": 6, "crossing_radius_px": radius_px,
            "crossing_vmag": vmag, "rate_max_deg_s": 0.5, "blinded": 0, "dropped": 0,
            "shadow_lost_in_space": True}}, source="test")
        ctx = st.make_context(sp)
        return sp, [st.compute_sequence(sp, ctx, i) for i in cases]
    return run


@pytest.mark.parametrize("radius_px, vmag", [(0.0, -4.0), (12.0, -8.0)])
def test_crossing_frames_keep_a_valid_attitude_and_no_identity_on_the_object(track, radius_px, vmag):
    """Paper preset, 3 sequences of 14 frames at up to 0.5 deg/s, one crossing of 6 frames each, a Venus-like point
    (V -4) or a Moon-like disk (radius 12 px, V -8): every crossing frame has a valid attitude within the 100 arcsec
    limit; the object is where its RA/Dec projects; a point object is detected there but neither tracking nor
    lost-in-space (run on the same frames) gives it an identity; a disk's blob is dropped as no star's."""
    sp, outs = track(radius_px, vmag)
    cam = sp.star.camera
    n_in = 0
    for o in outs:
        d, r, res = o["draw"], o["rendered"], o["result"]
        cross = np.flatnonzero(d["events"] == CROSSING)
        assert cross.size == 6 and EVENT_NAMES[CROSSING] == "crossing"
        assert np.all(res.mode[cross] != 0), res.mode[cross]
        for k in cross:
            e = _eq4(d["A_true"][k], res.A[k])
            assert np.all(np.abs(e) <= 100 * ARCSEC), (k, e / ARCSEC)
            j = np.flatnonzero(d["crossing_frame"] == k)[0]
            p = _pinhole(cam, d["A_true"][k], d["crossing_radec_deg"][j])
            np.testing.assert_allclose(p, d["crossing_xy"][j], atol=1e-6)
            if not (5 <= p[0] <= cam.width - 5 and 5 <= p[1] <= cam.height - 5):
                continue
            n_in += 1
            a, b = int(r["offsets"][k]), int(r["offsets"][k + 1])
            dist = np.linalg.norm(r["xy"][a:b] - p, axis=1)
            if radius_px == 0:
                i = int(np.argmin(dist))
                assert dist[i] < 1.0, dist[i]                          # the object is detected ...
                assert res.det_row[a + i] == -1                        # ... and tracking took it for no star
                assert res.shadow_rows[a + i] == -1                    # nor did lost-in-space
            else:
                assert r["n_excluded"][k] >= 1 and not np.any(dist < radius_px), dist.min()
    assert n_in >= 6, n_in                                               # the check saw the object


def test_frame_rows_and_report_count_crossing_frames(tmp_path):
    """``dualsight star track`` with one crossing per sequence: the frame rows say ``crossing``; the report's
    crossing frames, their availability and false locks equal numpy's count over the rows."""
    cfg = tmp_path / "t.toml"
    cfg.write_text("[sequence]\nframes = 12\nbright_crossings = 1\ncrossing_frames = 5\nrate_max_deg_s = 0.5\n"
                   "blinded = 1\ndropped = 0\n")
    lake = tmp_path / "lake"
    rc, out, err = run_cli(["star", "track", "--config", cfg, "--lake", lake, "--run", "c", "--preset", "paper",
                            "--cases", "3", "--seed", "4", "--workers", "1", "--no-progress"])
    assert rc == 0, err
    cols, rows = run_sql(lake, "SELECT event, within_limit, false_lock FROM star_frames WHERE run = 'c'")
    ev = np.array([r[0] for r in rows])
    within = np.array([bool(r[1]) for r in rows])
    false = np.array([bool(r[2]) for r in rows])
    cross = ev == "crossing"
    assert 3 * 4 <= cross.sum() <= 3 * 5                                # a blinded frame may take one
    rc, out, err = run_cli(["star", "track", "--report", "--json", "--lake", lake, "--run", "c"])
    assert rc == 0, err
    j = json.loads(out)
    assert j["frames_crossing"] == int(cross.sum())
    assert j["availability_crossing_frames"] == pytest.approx(within[cross].mean())
    assert j["false_locks_crossing_frames"] == int(false[cross].sum())
    assert j["frames_normal"] == int(np.sum(ev == EVENT_NAMES[NORMAL]))
    rc, out, err = run_cli(["star", "track", "--report", "--lake", lake, "--run", "c"])
    assert rc == 0 and "frames with a bright object crossing" in out, out
