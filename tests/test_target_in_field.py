"""A spacecraft in the star field (issue 23, points 1-2): the target's draws, its rendering into the star frame
(light on the stars' zero point, stars hidden behind it, saturation up close), the resolved-blob exclusion, and a
campaign with and without the target through the star job's compute_shard."""

import math

import numpy as np
import pytest

from dualsight.scene.target_config import TargetConfig
from dualsight.errors import ConfigError
from dualsight.jobs.engine.specs import preset_and_config
from dualsight.jobs.kinds import star
from dualsight.kernels.sensor_config import SensorConfig, flux_from_magnitude
from dualsight.nav.observations import observations
from dualsight.nav.resolved_blobs import excluded_blobs, without_excluded
from dualsight.scene.camera import Camera
from dualsight.scene.satellite import load_satellite
from dualsight.scene.starfield_geometry import FieldStars
from dualsight.scene.target_in_field import draw_targets, target_frames, with_target
from dualsight.scene.target_photometry import target_shape

SAT = "examples/satellites/cubesat_3u.toml"
CAM = Camera.pinhole(1024, 768, 4.65e-6, 17e-3)


def test_draws_follow_the_case_generator_after_the_star_draws():
    """The target's nine draws are default_rng([seed, i])'s 5th..13th (after 3 attitude angles and the noise seed),
    so the stars' draws are those of the run without a target."""
    cfg = TargetConfig(satellite=SAT, range_m=(100.0, 1e4), phase_deg=(20.0, 80.0))
    ids = np.array([0, 5, 77])
    A = np.tile(np.eye(3), (3, 1, 1))
    tc = draw_targets(cfg, 9, ids, A, CAM)
    for k, i in enumerate(ids):
        g = np.random.default_rng([9, int(i)])
        g.uniform(-np.pi, np.pi, size=3)
        g.integers(0, 2 ** 63, dtype=np.uint64)
        u = g.random(9)
        assert tc.range_m[k] == pytest.approx(100.0 * 100.0 ** u[1], rel=1e-12)
        px = CAM.project(tc.pos_cam[k])[0]
        assert px == pytest.approx([1024 * (0.05 + 0.9 * u[2]), 768 * (0.05 + 0.9 * u[3])], abs=1e-6)
        # phase angle: between the Sun and the target -> camera direction, uniform in [20, 80] deg
        o = -tc.pos_cam[k] / np.linalg.norm(tc.pos_cam[k])
        assert math.degrees(math.acos(np.dot(tc.sun_cam[k], o))) == pytest.approx(20 + 60 * u[7], abs=1e-9)
    assert np.allclose(np.linalg.norm(tc.sun_cam, axis=1), 1.0)
    assert np.allclose(tc.R_body @ np.swapaxes(tc.R_body, 1, 2), np.eye(3), atol=1e-12)


def _one_case(range_m, offset=(0.0, 0.0), sun=(0.0, 0.0, -1.0), stars_xy=((512.0, 384.0), (100.5, 100.5)),
              R_body=np.eye(3)):
    """A target at ``offset`` and ``range_m``, the Sun behind the camera (phase 0), face-on, and stars."""
    cfg = TargetConfig(satellite=SAT, range_m=(range_m, range_m), offset_deg=offset, sun_icrs=sun)
    tc = draw_targets(cfg, 1, np.array([0]), np.eye(3)[None], CAM)
    tc = type(tc)(tc.present, tc.range_m, tc.pos_cam, R_body[None], tc.sun_cam, tc.sun_icrs, tc.phase_rad)
    xy = np.array(stars_xy)
    n = len(xy)
    fs = FieldStars(xy[None, :, 0], xy[None, :, 1], np.full((1, n), 1e4, np.float32), np.ones((1, n), bool),
                    np.arange(n)[None], np.ones((1, n), bool), np.array([n]))
    sat = load_satellite(SAT)
    return cfg, tc, fs, target_frames(cfg, sat, target_shape(sat.components), tc, fs, CAM, SensorConfig())


def test_resolved_target_light_hides_stars_and_saturates():
    """At 100 m, face-on (0.1 x 0.1 m end towards the camera: 1 cm^2 ... the -z face, lx * ly) with the Sun behind
    the camera: the window's sources sum to the photometric electrons (rho a / (pi d^2) on the zero point), the
    projected area is lx ly / d^2 in pixels, the star behind it is hidden, the other untouched, every lit pixel is
    far above the full well, and the light's centroid is the body's centre."""
    cfg, tc, fs, tf = _one_case(100.0)
    sensor = SensorConfig()
    f = CAM.fx
    ratio = 0.8 * 0.01 / (math.pi * 100.0 ** 2)
    expect_e = sensor.zero_mag_rate_e_per_s * 10 ** (-0.4 * (-26.74 - 2.5 * math.log10(ratio))) * sensor.exposure_s
    assert tf.resolved[0]
    assert tf.electrons[0] == pytest.approx(expect_e, rel=1e-9)
    flux = tf.src_flux[0][tf.src_valid[0]].astype(float)
    assert flux.sum() == pytest.approx(expect_e, rel=1e-5)
    assert tf.area_px[0] == pytest.approx(0.01 / 100.0 ** 2 * f * f, rel=1e-9)
    side = 0.1 / 100.0 * f                                          # 3.66 px square
    assert tf.pixels[0] == (math.ceil(512 + side / 2) - math.floor(512 - side / 2)) ** 2
    assert flux.min() > sensor.full_well_e
    sx, sy = tf.src_x[0][tf.src_valid[0]], tf.src_y[0][tf.src_valid[0]]
    assert np.sum(sx * flux) / flux.sum() == pytest.approx(512.0, abs=0.05)
    assert np.sum(sy * flux) / flux.sum() == pytest.approx(384.0, abs=0.05)
    assert tf.star_keep[0, 0] == 0.0 and tf.star_keep[0, 1] == 1.0
    render, truth = with_target(fs, tf)
    assert truth.valid[0].tolist() == [False, True] and truth.n_generated[0] == 1
    assert render.valid[0].sum() == 2 + len(flux) and render.flux_e[0, 0] == 0.0


def test_long_side_hides_the_stars_along_it():
    """The 0.3 m axis along the columns (body z -> camera x) at 100 m: an 11 x 3.7 px rectangle; a star 4 px
    along the columns is hidden, one 4 px along the rows is not."""
    R = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    cfg, tc, fs, tf = _one_case(100.0, stars_xy=((516.5, 384.5), (512.5, 388.5)), R_body=R)
    assert tf.star_keep[0].tolist() == [0.0, 1.0]
    assert tf.area_px[0] == pytest.approx(0.03 / 100.0 ** 2 * CAM.fx ** 2, rel=1e-9)


def test_point_target_is_one_source_at_its_centre_of_brightness():
    cfg, tc, fs, tf = _one_case(10000.0, offset=(1.0, -0.5))
    assert not tf.resolved[0] and tf.src_valid[0].sum() == 1
    # the Sun behind the camera lights only the -z face (0.15 m nearer than the body origin): its centre is the
    # centre of brightness
    x, y = CAM.project(tc.pos_cam[0] - [0.0, 0.0, 0.15])[0]
    assert tf.src_x[0, 0] == pytest.approx(x, abs=1e-9) and tf.src_y[0, 0] == pytest.approx(y, abs=1e-9)
    assert tf.x_px[0] == pytest.approx(512 + CAM.fx * math.tan(math.radians(1.0)), abs=1e-9)
    assert tf.src_flux[0, 0] == pytest.approx(tf.electrons[0], rel=1e-6)
    assert np.all(tf.star_keep == 1.0)
    # the Sun along -z lights the -z face fully (cos i = 1); the camera sees it at the offset angle (cos e = u_z)
    u = np.array([math.tan(math.radians(1.0)), math.tan(math.radians(-0.5)), 1.0])
    cos_e = 1.0 / np.linalg.norm(u)
    assert tf.vmag[0] == pytest.approx(-26.74 - 2.5 * math.log10(0.8 * 0.01 * cos_e / (math.pi * 1e8)), abs=1e-9)


def test_saturated_pixels_in_the_rendered_frame_at_100m():
    """Through the star job's renderer (dense path, kept images): the target at 100 m saturates the ADC."""
    d, _ = preset_and_config(star.PRESETS, "paper", None)
    d["target"] = {"satellite": SAT, "range_m": [100.0, 100.0], "offset_deg": [0.0, 0.0]}
    spec = star.spec_from_dict(d, source="test")
    ctx = star.make_context(spec)
    out = star.compute_batch(spec, ctx, np.arange(2, dtype=np.int64), keep_images=True)
    img = out["rendered"].images
    full = min(math.floor(spec.sensor.full_well_e / spec.sensor.gain_e_per_adu), spec.sensor.max_adu)
    assert img[:, 380:389, 507:518].max(axis=(1, 2)).tolist() == [full] * 2
    t = out["tables"]["star_cases"]
    assert t.column("target_excluded").to_pylist() == [True, True]
    assert t.column("target_voted").to_pylist() == [False, False]


def test_target_in_front_of_a_star_hides_it_in_the_job():
    """Case 0's brightest star in the image, with the target at 60 m pointed at it: the star is neither generated
    nor the truth of any detection, and the other stars are those of the run without the target."""
    d, _ = preset_and_config(star.PRESETS, "paper", None)
    base = star.spec_from_dict(d, source="test")
    ctx = star.make_context(base)
    out0 = star.compute_batch(base, ctx, np.arange(1, dtype=np.int64))
    f = out0["field"]
    k = int(np.flatnonzero(f.inside[0])[0])
    hip = int(ctx.catalog.hip[f.cat_row[0, k]])
    c = base.camera
    off = [math.degrees(math.atan((f.x[0, k] - c.cx) / c.fx)), math.degrees(math.atan((f.y[0, k] - c.cy) / c.fy))]
    d["target"] = {"satellite": SAT, "range_m": [60.0, 60.0], "offset_deg": off}
    spec = star.spec_from_dict(d, source="test")
    out = star.compute_batch(spec, star.make_context(spec), np.arange(1, dtype=np.int64))
    t0, t = out0["tables"], out["tables"]
    assert t["star_cases"].column("n_generated")[0].as_py() == t0["star_cases"].column("n_generated")[0].as_py() - 1
    assert hip in t0["star_detections"].column("hip_true").to_pylist()
    assert hip not in t["star_detections"].column("hip_true").to_pylist()


def test_excluded_blobs_leave_the_observations():
    class Det:
        case = np.array([0, 0, 0, 1])
        offsets = np.array([0, 3, 4])
        x = np.array([10.0, 20.0, 30.0, 40.0])
        y = np.array([5.0, 6.0, 7.0, 8.0])
        npix = np.array([200, 9, 12, 80])
    ex = excluded_blobs(Det.npix, 75)
    assert ex.tolist() == [True, False, False, True]
    obs = without_excluded(observations(Det, 2, CAM), Det.case, Det.offsets, ex)
    assert obs.valid.tolist() == [[False, True, True], [False, False, False]]
    assert np.isnan(obs.vec[0, 0]).all() and obs.x[0, 1] == 20.0


def test_bad_target_table_is_one_line():
    d, _ = preset_and_config(star.PRESETS, "paper", None)
    d["target"] = {"satellite": SAT, "range_m": [1.0, 10.0]}
    with pytest.raises(ConfigError, match=r"target\.range_m.*px across at 1 m"):
        star.spec_from_dict(d, source="cfg.toml")
    d["target"] = {"satellite": SAT, "phase_deg": [100.0, 10.0]}
    with pytest.raises(ConfigError, match=r"target\.phase_deg"):
        star.spec_from_dict(d, source="cfg.toml")
    d["target"] = {"satellite": "no/such/file.toml"}
    with pytest.raises(Exception, match="no/such/file.toml"):
        star.spec_from_dict(d, source="cfg.toml")


@pytest.fixture(scope="module")
def campaign():
    """400 cases of the paper preset, with and without the example's target (100 m - 10 km, random Sun)."""
    d, _ = preset_and_config(star.PRESETS, "paper", "examples/star/target_in_field.toml")
    with_t = star.spec_from_dict(d, source="example")
    without = star.spec_from_dict({k: v for k, v in d.items() if k != "target"}, source="paper")
    ids = np.arange(400, dtype=np.int64)
    return (star.compute_shard(without, ids, star.make_context(without))["star_cases"],
            star.compute_shard(with_t, ids, star.make_context(with_t))["star_cases"])


def test_campaign_target_does_not_fool_identification(campaign):
    """Same cases: the robust method's success rate with the target within 0.5 points of without, beyond the
    binomial noise of the discordant pairs (3 sigma), and no confident-wrong answer that the target caused; no
    identity is accepted for a resolved target's blob; the target columns are null without a target."""
    base, tgt = campaign
    n = base.num_rows
    for c in ("theta1_rad", "theta2_rad", "theta3_rad"):      # the stars' draws (the attitudes) are the same
        assert base.column(c).to_pylist() == tgt.column(c).to_pylist()
    sb = np.array(base.column("status_robust").to_pylist())
    st = np.array(tgt.column("status_robust").to_pylist())
    lost = int(((sb == "success") & (st != "success")).sum())
    gained = int(((sb != "success") & (st == "success")).sum())
    assert lost - gained <= 0.005 * n + 3 * math.sqrt(lost + gained + 1)
    assert int(((st == "confident_wrong") & (sb != "confident_wrong")).sum()) == 0
    res = np.array(tgt.column("target_resolved").to_pylist())
    assert res.sum() > 50 and (~res).sum() > 50
    acc = np.array(tgt.column("target_id_accepted_robust").to_pylist())
    assert not acc[res].any()
    assert tgt.column("target_present").to_pylist() == [True] * n
    vm = np.array(tgt.column("target_vmag").to_pylist())
    rng = np.array(tgt.column("target_range_m").to_pylist())
    assert np.all((vm > -13) & (vm < 2)) and np.all((rng >= 100) & (rng <= 1e4))
    assert base.column("target_present").null_count == n and base.column("sun_keepout").null_count == n


def test_campaign_resolved_targets_are_excluded(campaign):
    """Every detected resolved target larger than 10 px across is kept out of the vote (its blob exceeds any
    star's); no point-like target under V -2 (fainter than Sirius can look) is excluded."""
    _, tgt = campaign
    diam = np.array(tgt.column("target_diameter_px").to_pylist())
    exc = np.array([v is True for v in tgt.column("target_excluded").to_pylist()])
    det = np.array([v is not None for v in tgt.column("target_det_npix").to_pylist()])
    vm = np.array(tgt.column("target_vmag").to_pylist())
    big = det & (diam > 10)
    assert big.sum() > 10 and exc[big].all()
    assert not exc[det & (vm > -2)].any()


def test_electrons_are_the_stars_conversion(campaign):
    _, tgt = campaign
    vm = np.array(tgt.column("target_vmag").to_pylist())
    e = np.array(tgt.column("target_electrons").to_pylist())
    np.testing.assert_allclose(e, flux_from_magnitude(vm, SensorConfig()), rtol=1e-12)


def test_campaign_bearing_rows(campaign):
    """The target's inertial bearing in the rows: present wherever the robust method solved and the target was
    detected; for point-like targets the median error against the true centre of brightness is a few arcsec
    (noise-free frames: centroid and attitude errors ~0.1 px = 5.6 arcsec) and its error against the body origin
    is never more than the target's angular radius plus 30 arcsec (it is at most the centre of brightness's offset)."""
    base, tgt = campaign
    g = lambda t, c: np.array([np.nan if v is None else v for v in t.column(c).to_pylist()], float)  # noqa: E731
    st = np.array(tgt.column("status_robust").to_pylist())
    det = np.array([v is not None for v in tgt.column("target_det_npix").to_pylist()])
    cob = g(tgt, "target_bearing_cob_err_rad")
    assert np.isfinite(cob[(st == "success") & det]).all()
    res = np.array(tgt.column("target_resolved").to_pylist())
    pt = (st == "success") & det & ~res
    assert np.median(cob[pt]) < 5e-5
    body = g(tgt, "target_bearing_err_rad")
    radius = 0.5 * g(tgt, "target_diameter_px") / (17e-3 / 4.65e-6)        # rad: the paper camera's focal length
    assert np.all(body[pt] < radius[pt] + 30 / 206265)
    assert base.column("target_bearing_nees").null_count == base.num_rows
