"""The proximity camera's bearing through the target's silhouette centre (issue 23, points 4 and 6 c;
``nav/blob_centre_error.py``, ``rendezvous.bearing_point``): the calibration's kernel estimate against a known
spread, the spec's rules, and the close preset's bearings against the true line of sight of rendered approaches
(the truth's body origin: a silhouette centre within ~1 mm where the centre of brightness leans ~14 mm towards
the Sun, and a stated covariance that holds)."""

import math

import numpy as np
import pytest

from dualsight.errors import ConfigError
from dualsight.jobs.kinds import rendezvous as rz, rendezvous_measure, rendezvous_spec, rendezvous_truth
from dualsight.jobs.kinds.rendezvous_filter import silhouette_cov
from dualsight.nav.blob_centre_error import CENTRE_SIGMA_FLOOR_PX, CentreErrorCalibration
from dualsight.scene.satellite import load_satellite


def test_calibration_recovers_a_known_spread_against_coverage():
    """err ~ N(mu, s(n)) per axis with s(n) = 0.5 (n / 100)^-1/2 px and a bias mu = (0.1, -0.05) px, blobs of random
    axis ratio and angle: the root mean square along either axis is sqrt(s^2 + |mu|^2 / 2); the kernel over 0.1
    decade of n blurs s^2 = 0.25 (100 / n) by exp((0.1 ln 10)^2 / 2) = 1.027 (a log-normal's mean), so within 4 %
    (its ~1,000 effective samples: ~2 % on a sigma)."""
    rng = np.random.default_rng([23, 61])
    M = 300000
    n = 10 ** rng.uniform(0.5, 4.5, M)
    ratio = rng.uniform(1.0, 3.4, M)
    ang = rng.uniform(-math.pi / 2, math.pi / 2, M)
    s = 0.5 * (n / 100) ** -0.5
    err = rng.normal(size=(M, 2)) * s[:, None] + np.array([0.1, -0.05])
    err[7] = np.nan                                   # ignored
    cal = CentreErrorCalibration(n, err, ratio, ang)
    q = np.array([10.0, 100.0, 1000.0, 10000.0])
    want = np.sqrt(0.25 * 100 / q * math.exp(0.5 * (0.1 * math.log(10)) ** 2) + (0.1 ** 2 + 0.05 ** 2) / 2)
    got = cal.axes_px(q, np.full(4, 2.0))
    np.testing.assert_allclose(got, np.stack([want, want], -1), rtol=0.04)
    out = cal.axes_px(np.array([np.nan, 0.0, -3.0, 100.0]), np.array([2.0, 2.0, 2.0, np.nan]))
    assert np.isnan(out).all()
    one = np.ones(2)
    tiny = CentreErrorCalibration(np.array([10.0, 20.0]), np.zeros((2, 2)), 2 * one, 0 * one)
    assert np.all(tiny.axes_px(np.array([15.0]), np.array([2.0])) == CENTRE_SIGMA_FLOOR_PX)
    with pytest.raises(ValueError, match="no finite sample"):
        CentreErrorCalibration(np.array([np.nan]), np.zeros((1, 2)), one[:1], one[:1])


@pytest.mark.parametrize("table,field", [
    ({"bearing_point": "silhouette", "phase_correction": False}, "rendezvous.bearing_point"),     # star camera
    ({"camera": "examples/cameras/paper_prox.toml", "bearing_point": "silhouette"}, "rendezvous.phase_correction"),
    ({"camera": "examples/cameras/paper_prox.toml", "bearing_point": "middle"}, "rendezvous.bearing_point"),
])
def test_spec_rules_name_the_field(table, field):
    with pytest.raises(ConfigError) as e:
        d, _ = rendezvous_spec.resolve_spec(None, {"rendezvous": table})
        rz.spec_from_dict(d)
    assert f"[{field}]" in str(e.value), str(e.value)


def test_default_spec_stores_no_bearing_point():
    """The field is left out of a stored spec at its default, so older runs keep their ids."""
    assert "bearing_point" not in rz.plan_run("far", None, cases=1).spec["rendezvous"]
    assert rz.plan_run("close", None, cases=1).spec["rendezvous"]["bearing_point"] == "silhouette"


@pytest.fixture(scope="module")
def close_bearings():
    """6 approaches of the close preset (50 m -> 2 m, 61 frames), rendered and measured as ``rendezvous run`` does:
    each bearing's error across the true line of sight in metres at the true range and its squared error over the
    stated covariance, once through the silhouette centre (the preset) and once through the centre of
    brightness."""
    out = {}
    for point in ("silhouette", "brightness"):
        cfg = {"preset": "close", "rendezvous": {"bearing_point": point, "phase_correction": False}}
        if point == "brightness":                          # no range: no calibration renders to wait for
            cfg["rendezvous"]["range_source"] = "none"
        d, _ = rendezvous_spec.resolve_spec(None, cfg, cases=6)
        spec = rz.spec_from_dict(d)
        ctx = rz.make_context(spec)
        err, d2 = [], []
        for i in range(6):
            draw = rendezvous_truth.draw_case(spec, i)
            truth = rendezvous_truth.truth_trajectory(spec, draw)
            geo = rendezvous_truth.geometry(spec, draw, truth)
            m, _ = rendezvous_measure.measure_prox(spec, ctx, draw, geo, False)
            c = m["cand"]
            r = np.linalg.norm(truth[c["frame"], :3], axis=1)
            ut = geo["u_true"][c["frame"]]
            e = c["u"] - ut
            err.append(np.linalg.norm(e, axis=1) * r)
            for j, k in enumerate(c["frame"]):           # the stated covariance (rank 2, across the line of sight)
                C = c["C"][j]
                if point == "silhouette":                 # what the filter adds (rendezvous_filter.target_selector)
                    C = C + silhouette_cov(ctx, m["centre_cov"][k], c["u"][j:j + 1], geo["R"][k][:, 2])[0]
                d2.append(float(e[j] @ np.linalg.pinv(C, rcond=1e-12, hermitian=True) @ e[j]))
        out[point] = (np.concatenate(err), np.array(d2))
    return out


def test_silhouette_bearing_is_within_a_millimetre_where_the_brightness_leans_to_the_sun(close_bearings):
    e_sil, _ = close_bearings["silhouette"]
    e_cob, _ = close_bearings["brightness"]
    rms_sil, rms_cob = np.sqrt(np.mean(e_sil ** 2)), np.sqrt(np.mean(e_cob ** 2))
    print(f"bearing error RMS, silhouette {1e3 * rms_sil:.2f} mm, centre of brightness {1e3 * rms_cob:.2f} mm")
    assert rms_sil < 4e-3            # attitude (10 arcsec: 2.4 mm at 50 m) + the centre (perspective: ~4 mm at 3 m)
    assert rms_cob > 10e-3           # the centre of brightness's ~14 mm lean towards the Sun
    assert rms_sil < 0.3 * rms_cob


def test_silhouette_bearing_covariance_holds(close_bearings):
    """The 2-dof squared error over the stated covariance (attitude + the calibrated centre, its variance times
    the sequence gain along the orbit normal and across, ``rendezvous_filter.silhouette_cov``): >= 99 % inside the
    99.73 % point (11.83; issue 23 point 6 b's test on the bearings) and a mean between 2 / 2.5 (the gains widen
    it; 1.1-2.5, ``rendezvous_context.silhouette_sequence_gain``) and 2."""
    _, d2 = close_bearings["silhouette"]
    assert d2.size > 300
    print(f"bearings' 2-dof NEES: mean {np.mean(d2):.2f}, {100 * np.mean(d2 <= 11.83):.1f} % within 11.83")
    assert np.mean(d2 <= 11.83) >= 0.99
    assert 0.8 < np.mean(d2) < 2.1, np.mean(d2)


def test_sequence_gain_against_closed_forms():
    """White: 1; held constant: N; first-order Gauss-Markov with correlation a per frame: the maximum over N of
    1 + 2 sum_{l<N} (1 - l/N) a^l (Bendat & Piersol Sec. 8.2.1), by hand; a sampling error ~sqrt(2 / S)."""
    from dualsight.nav.blob_centre_error import sequence_gain

    rng = np.random.default_rng([23, 62])
    S, L = 20000, 30
    white = rng.normal(size=(S, L, 1))
    held = np.repeat(rng.normal(size=(S, 1, 1)), L, axis=1)
    a = 0.8
    ar = np.empty((S, L, 1))
    ar[:, 0] = rng.normal(size=(S, 1))
    for k in range(1, L):
        ar[:, k] = a * ar[:, k - 1] + math.sqrt(1 - a * a) * rng.normal(size=(S, 1))
    g = sequence_gain(np.concatenate([white, held, ar], axis=2))
    want_ar = max(1 + 2 * sum((1 - lag / n) * a ** lag for lag in range(1, n)) for n in range(1, L + 1))
    assert g[0] == pytest.approx(1.0, abs=0.06)              # max over 30 windows of ~1 +- 1 %: a little above 1
    assert g[1] == pytest.approx(L, rel=0.03)
    assert g[2] == pytest.approx(want_ar, rel=0.03)
    assert sequence_gain(held, max_frames=5)[0] == pytest.approx(5, rel=0.03)
    nan = white.copy()
    nan[:, ::2] = np.nan                                      # a lost frame counts as 0: max at N = 2, 1/2
    assert sequence_gain(nan)[0] == pytest.approx(0.5, abs=0.05)


def test_silhouette_cov_by_hand():
    """Line of sight +x, orbit normal in the x-z plane (across the line of sight: +z), gains (2.5, 1.2) along z and
    y: a centre covariance [[a, c], [c, b]] on (y, z) becomes [[1.2 a, sqrt(3) c], [sqrt(3) c, 2.5 b]] (each axis
    times its gain, the cross term times the square root of their product), nothing along the line of sight."""
    from types import SimpleNamespace

    ctx = SimpleNamespace(silhouette_gain=np.array([2.5, 1.2]))
    a, b, c = 4e-10, 1e-10, -1.5e-10
    C_in = np.array([[0.0, 0.0, 0.0], [0.0, a, c], [0.0, c, b]])
    C = silhouette_cov(ctx, C_in, np.array([[1.0, 0.0, 0.0]]), np.array([0.4, 0.0, 1.0]) / math.hypot(0.4, 1.0))[0]
    x = math.sqrt(2.5 * 1.2) * c
    np.testing.assert_allclose(C, [[0.0, 0.0, 0.0], [0.0, 1.2 * a, x], [0.0, x, 2.5 * b]], atol=1e-22)


def test_calibration_gives_the_error_along_the_blobs_own_axes():
    """Errors along each sample's major axis (a random angle) with sd 0.5 (3.5 - ratio) px and along its minor axis
    with sd 0.1 px, for axis ratios uniform in [1, 3.4]: axes_px recovers both at ratios 1.5 and 2.5 (the kernel's
    0.05 of ratio blurs a^2 by ~0.25 x 0.05^2; its ~3,000 effective samples know a sigma to ~1.3 %: within 6 %),
    the same at any coverage; cov_px turns them to a new blob's angle: its eigenvectors lie along and across that
    angle."""
    rng = np.random.default_rng([23, 63])
    M = 200000
    n = 10 ** rng.uniform(1.0, 4.0, M)
    ratio = rng.uniform(1.0, 3.4, M)
    ang = rng.uniform(-math.pi / 2, math.pi / 2, M)
    a, b = 0.5 * (3.5 - ratio), np.full(M, 0.1)
    e_maj, e_min = rng.normal(size=M) * a, rng.normal(size=M) * b
    err = np.stack([e_maj * np.cos(ang) - e_min * np.sin(ang), e_maj * np.sin(ang) + e_min * np.cos(ang)], -1)
    cal = CentreErrorCalibration(n, err, ratio, ang)
    got = cal.axes_px(np.array([100.0, 1000.0, 100.0]), np.array([1.5, 1.5, 2.5]))
    np.testing.assert_allclose(got[:, 0], [1.0, 1.0, 0.5], rtol=0.06)
    np.testing.assert_allclose(got[:, 1], 0.1, rtol=0.06)
    C = cal.cov_px(np.array([300.0]), np.array([2.0]), np.array([0.6]))[0]
    w, V = np.linalg.eigh(C)
    assert w[1] == pytest.approx(0.75 ** 2, rel=0.12) and w[0] == pytest.approx(0.01, rel=0.12)
    assert abs(abs(V[:, 1] @ [math.cos(0.6), math.sin(0.6)]) - 1.0) < 1e-6
    assert np.isnan(cal.cov_px(np.array([np.nan]), np.array([2.0]), np.array([0.1]))).all()


def test_calibrations_are_cached_by_content_and_rebuilt_when_stale(tmp_path, monkeypatch):
    """The second call reads what the first wrote (no render: the computing functions would raise), the same arrays,
    and announces nothing (the first announced each calibration with its render count); another camera is another
    key (computed again); a corrupt file is rebuilt, not trusted."""
    from dataclasses import replace

    from dualsight.jobs.kinds import rendezvous_context as rc

    monkeypatch.setattr(rc, "RANGE_CALIB_SPANS", ((10.0, 20.0, 24),))
    monkeypatch.setattr(rc, "SEQUENCE_GAIN_SEQUENCES", 4)
    monkeypatch.setattr(rc, "SEQUENCE_GAIN_FRAMES", 6)
    d, _ = rendezvous_spec.resolve_spec("close", None, cases=1)
    spec = rz.spec_from_dict(d)
    sat = load_satellite(spec.cfg.satellite)
    mesh, materials = sat.mesh(), sat.materials()
    from dualsight.catalogs.areas import area_table

    table = area_table(sat, n=2000, bin_width=0.05, cache_dir=tmp_path)
    said = []
    cal, cen = rc.cached_blobber_calibration(sat, mesh, materials, table, spec.camera, cache_dir=tmp_path,
                                             announce=said.append)
    g = rc.cached_sequence_gain(sat, mesh, materials, table, spec.camera, cen, 1.7, 0.1, 6, cache_dir=tmp_path,
                                announce=said.append)
    assert len(said) == 2 and "24 renders" in said[0] and "24 renders" in said[1], said    # 24 and 4 x 6
    computed = {"blobber_calibration": rc.blobber_calibration, "silhouette_sequence_gain": rc.silhouette_sequence_gain}

    def refuse(*a, **k):
        raise AssertionError("computed again")
    monkeypatch.setattr(rc, "blobber_calibration", refuse)
    monkeypatch.setattr(rc, "silhouette_sequence_gain", refuse)
    cal2, cen2 = rc.cached_blobber_calibration(sat, mesh, materials, table, spec.camera, cache_dir=tmp_path,
                                               announce=said.append)
    g2 = rc.cached_sequence_gain(sat, mesh, materials, table, spec.camera, cen2, 1.7, 0.1, 6, cache_dir=tmp_path,
                                 announce=said.append)
    assert len(said) == 2                                 # read from the cache: nothing announced
    np.testing.assert_array_equal(cal2.q, cal.q)
    np.testing.assert_array_equal(cen2.err_px, cen.err_px)
    np.testing.assert_array_equal(cen2.angle_rad, cen.angle_rad)
    np.testing.assert_array_equal(cen2.axis_ratio, cen.axis_ratio)
    np.testing.assert_array_equal(g2, g)
    other = replace(spec.camera, fx=spec.camera.fx * 1.01)
    with pytest.raises(AssertionError, match="computed again"):
        rc.cached_blobber_calibration(sat, mesh, materials, table, other, cache_dir=tmp_path)
    with pytest.raises(AssertionError, match="computed again"):                  # another spin step
        rc.cached_sequence_gain(sat, mesh, materials, table, spec.camera, cen, 1.8, 0.1, 6, cache_dir=tmp_path)
    for f in (tmp_path / "rendezvous").glob("*.parquet"):
        f.write_bytes(b"not parquet")
    monkeypatch.setattr(rc, "blobber_calibration", computed["blobber_calibration"])
    cal3, _ = rc.cached_blobber_calibration(sat, mesh, materials, table, spec.camera, cache_dir=tmp_path)
    np.testing.assert_array_equal(cal3.q, cal.q)


def test_centroid_covariance_in_icrs_at_the_principal_point():
    """At the principal point of a pinhole camera a pixel is 1 / fx rad along camera x and 1 / fy along y: a centroid
    covariance [[4, 1], [1, 9]] px^2 is [[4 / fx^2, 1 / (fx fy)], [1 / (fx fy), 9 / fy^2]] rad^2 on (x, y) and 0
    along the boresight, turned to ICRS by the attitude's transpose (A: ICRS -> camera)."""
    from dualsight.nav.target_bearing import centroid_cov_icrs
    from dualsight.scene.camera import Camera
    from dualsight.scene.rotation_vector import frame_rotation

    cam = Camera.from_toml("examples/cameras/paper_prox.toml")
    fx, fy = cam.fx, cam.fy
    want_cam = np.array([[4 / fx ** 2, 1 / (fx * fy), 0.0], [1 / (fx * fy), 9 / fy ** 2, 0.0], [0.0, 0.0, 0.0]])
    A = frame_rotation(np.array([[0.3, -0.2, 1.1]]))
    got = centroid_cov_icrs(A, np.array([[cam.cx, cam.cy]]), np.array([[[4.0, 1.0], [1.0, 9.0]]]), cam)[0]
    np.testing.assert_allclose(got, A[0].T @ want_cam @ A[0], rtol=1e-5, atol=1e-16)


def test_the_central_window_changes_the_pixels_rendered_not_the_blobs():
    """The sequence-gain calibration renders a window around the principal point (rendezvous_context.central_window):
    the 3U CubeSat at 2-50 m on the boresight gives, in the window, the same silhouette centre relative to the
    projection of its origin, the same coverage and the same axis ratio and angle as in the whole 1024 x 768 frame."""
    from dualsight.jobs.kinds import rendezvous_context as rc
    from dualsight.scene.attitude import quat_to_dcm, quaternions_from_uniforms

    d, _ = rendezvous_spec.resolve_spec("close", None, cases=1)
    spec = rz.spec_from_dict(d)
    sat = load_satellite(spec.cfg.satellite)
    mesh, materials, table = sat.mesh(), sat.materials(), rc.prox_area_table(sat)
    cam = spec.camera
    win = rc.central_window(cam, 123)
    assert (win.width, win.height) == (246, 246) and (win.cx, win.cy) == (cam.cx - 389, cam.cy - 261)
    rng = np.random.default_rng([23, 64])
    M = 16
    u = rng.random((M, 3))
    R = quat_to_dcm(quaternions_from_uniforms(u[:, 0], u[:, 1], u[:, 2]))
    pos = np.stack([np.zeros(M), np.zeros(M), np.geomspace(2.0, 50.0, M)], -1)
    sun = np.tile([0.0, 1.0, 0.0], (M, 1))
    got = {}
    for c in (cam, win):
        rows = []
        for i, b in rc.rendered_blobs(sat, mesh, materials, table, c, R, pos, sun):
            assert b.found.all() and not rc.touches_edge(b.box, c).any()
            rows.append(np.column_stack([b.centre_px - c.project(pos[i])[0], b.n_coverage, b.axis_ratio,
                                         b.angle_rad]))
        got[c.width] = np.concatenate(rows)
    np.testing.assert_allclose(got[246], got[cam.width], rtol=1e-9, atol=1e-9)
