"""The automatic catalog magnitude limit (catalogs/auto_limit.py) and ``mag_limit = "auto"`` in ``hil star``.

Independent truths: the solid angle of a centred pinhole rectangle, Omega = 4 arcsin(sin a sin b) with a, b
the half-angles of its sides; a Monte Carlo count of random sky directions that the camera's forward model
(``Camera.project`` with its distortion) puts inside the image; star counts made here by counting the
catalog's magnitudes directly on the 0.1 mag grid; the sensor formula written out by hand.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from dualsight.catalogs import auto_limit as al
from dualsight.catalogs.stars import MIN_STARS, StarCatalogConfig, johnson_v, load_star_catalog, read_hip2
from dualsight.scene.camera import Camera
from helpers import ROOT, phi, run_cli, shared_real

ESA = Camera.from_toml(ROOT / "examples" / "cameras" / "esa_tetra3.toml")


def _pinhole_omega(cam: Camera) -> float:
    a = math.atan(cam.width / 2 / cam.fx)
    b = math.atan(cam.height / 2 / cam.fy)
    return 4 * math.asin(math.sin(a) * math.sin(b))


def _hand_limit(vmag, omega, target):
    """The smallest V on the 0.1 grid whose count N(V <= limit) * omega / 4 pi reaches the target,
    counted directly."""
    v = np.asarray(vmag, np.float64)
    for k in range(-20, 121):
        lim = round(k * 0.1, 6)
        if np.count_nonzero(v <= lim) * omega / (4 * math.pi) >= target:
            return lim
    return math.inf


@pytest.fixture(scope="module")
def all_v():
    v, _ = johnson_v(read_hip2())
    return v


# ------------------------------------------------------------------------------------ the field
@pytest.mark.parametrize("w,h,f", [(1024, 768, 5119.0), (1024, 768, 1000.0), (640, 480, 300.0), (2000, 10, 900.0),
                                   (4096, 4096, 2048.0)])
def test_solid_angle_of_a_pinhole_rectangle(w, h, f):
    cam = Camera(w, h, 5e-6, f, f * 1.1, w / 2, h / 2)
    assert al.field_solid_angle(cam) == pytest.approx(_pinhole_omega(cam), rel=1e-10)


@pytest.mark.parametrize("dist", [(-0.3, 0.05, 0.0, 0.0, 0.0), (0.2, 0.0, 0.001, -0.002, 0.0), (0.0,) * 5])
def test_solid_angle_with_distortion_by_monte_carlo(dist):
    """Random directions in a cap that holds the field, kept when ``project`` lands them in the image:
    Omega = cap * fraction (2e6 samples: ~0.2 % standard error)."""
    cam = Camera(800, 600, 5e-6, 700.0, 700.0, 410.0, 290.0, dist)
    rng = np.random.default_rng(0)
    cos_cap = math.cos(math.radians(60))
    n = 2_000_000
    z = rng.uniform(cos_cap, 1.0, n)                      # uniform on the cap: z uniform (Archimedes)
    phi = rng.uniform(0, 2 * math.pi, n)
    s = np.sqrt(1 - z * z)
    v = np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)
    px, front = cam.project(v)
    inside = front & (px[:, 0] >= 0) & (px[:, 0] <= cam.width) & (px[:, 1] >= 0) & (px[:, 1] <= cam.height)
    corners = cam.backproject(np.array([[0, 0], [800, 0], [0, 600], [800, 600]], float))
    assert corners[:, 2].min() > cos_cap + 0.05            # the cap holds the whole field
    mc = 2 * math.pi * (1 - cos_cap) * inside.mean()
    got = al.field_solid_angle(cam)
    assert got == pytest.approx(mc, rel=0.01)
    if any(dist):
        assert abs(got - _pinhole_omega(Camera(800, 600, 5e-6, 700.0, 700.0, 400.0, 300.0))) > 0.02 * got


def test_field_size():
    w, h = al.field_size_deg(ESA)
    assert w == pytest.approx(math.degrees(ESA.fov_rad[0]), abs=1e-9)
    assert h == pytest.approx(math.degrees(ESA.fov_rad[1]), abs=1e-9)


# ------------------------------------------------------------------------------------ the limit
def test_hipparcos_counts_are_the_catalogs(all_v):
    v = al.hipparcos_vmag()
    assert v.size == all_v.size == 117955 and np.array_equal(v, np.sort(all_v)) and not v.flags.writeable
    cat = load_star_catalog(StarCatalogConfig(mag_limit=6.0))
    assert np.count_nonzero(all_v <= 6.0) == len(cat)        # the catalog keeps V <= limit, as counted


@pytest.mark.parametrize("target", [5, 15, 30, 60])
@pytest.mark.parametrize("fx", [5119.0, 3000.0, 1600.0])
def test_auto_limit_by_hand(all_v, target, fx):
    cam = Camera(1024, 768, 6.9e-6, fx, fx, 512.0, 384.0)
    omega = _pinhole_omega(cam)
    want = _hand_limit(all_v, omega, target)
    a = al.auto_limit(cam, target_per_field=target, complete_v=99.0)
    assert a.wanted == want and a.mag_limit == min(want, 12.0)
    assert a.mag_limit == al.auto_mag_limit(cam, all_v, target, complete_v=99.0)
    n = np.count_nonzero(all_v <= a.mag_limit)
    assert a.stars_per_field == pytest.approx(n * omega / (4 * math.pi), rel=1e-12) and a.stars_per_field >= target
    below = np.count_nonzero(all_v <= a.mag_limit - 0.1)
    assert below * omega / (4 * math.pi) < target           # and 0.1 mag brighter does not reach it


def test_synthetic_counts():
    """Magnitudes 0.01, 0.02, ..., 10.00 (1000 stars) and a field of 1/100 of the sky: 15 stars per field
    need 1500 stars: more than exist, so the range cap; 5 per field need 500 stars: V 5.00."""
    v = np.arange(1, 1001) * 0.01
    cam = Camera(1024, 768, 6.9e-6, 1000.0, 1000.0, 512.0, 384.0)
    omega = 4 * math.pi / 100
    assert al.auto_mag_limit(cam, v, 5, field_sr=omega, complete_v=99.0) == 5.0
    assert al.auto_mag_limit(cam, v, 5.01, field_sr=omega, complete_v=99.0) == 5.1
    a = al.auto_limit(cam, v, 15, field_sr=omega, complete_v=99.0)
    assert a.capped_by == "range" and a.mag_limit == 12.0


def test_caps_and_floor(all_v):
    narrow = Camera(1024, 768, 6.9e-6, 20000.0, 20000.0, 512.0, 384.0)            # 2.9 x 2.2 deg
    a = al.auto_limit(narrow)
    assert a.wanted > 8.5 and a.mag_limit == al.HIPPARCOS_COMPLETE_V == 8.0 and a.capped_by == "completeness"
    assert a.stars_per_field < 15 and "completeness" in a.describe()
    b = al.auto_limit(ESA, target_per_field=30, sensor_v=6.46)
    assert b.mag_limit == 6.4 and b.capped_by == "sensor" and "sensor" in b.describe()
    cat7 = load_star_catalog(StarCatalogConfig(mag_limit=7.0))
    c = al.auto_limit(narrow, cat7)                                                   # counts of a cut catalog
    assert c.mag_limit == 7.0 and c.capped_by == "catalog"
    wide = Camera(1024, 768, 6.9e-6, 50.0, 50.0, 512.0, 384.0)                         # 169 x 165 deg
    d = al.auto_limit(wide)
    floor = _hand_limit(all_v, 4 * math.pi, MIN_STARS)                                # MIN_STARS over the sky
    assert d.wanted < floor and d.mag_limit == floor and d.capped_by == "min_stars"
    assert np.count_nonzero(all_v <= d.mag_limit) >= MIN_STARS


def test_example_cameras(all_v):
    """The limits the example cameras get (the report's table), each checked by hand."""
    got = {}
    for f in sorted((ROOT / "examples" / "cameras").glob("*.toml")):
        cam = Camera.from_toml(f)
        for target in (al.DEFAULT_TARGET, al.HIL_TARGET_PER_FIELD):
            a = al.auto_limit(cam, target_per_field=target)
            assert a.mag_limit == min(_hand_limit(all_v, _pinhole_omega(cam), target), 8.0), (f.name, target)
            got[f.stem, target] = a.mag_limit
    assert got["esa_tetra3", 15.0] == 6.3 and got["esa_tetra3", 35.0] == 7.0      # 7.0: the measured default
    assert got["paper_star", 15.0] == 5.7 and got["paper_star", 35.0] == 6.4


def test_describe():
    a = al.auto_limit(ESA, target_per_field=30)
    assert a.describe() == f"catalog to V 6.9 (auto: {a.stars_per_field:.1f} stars per 11.4 x 8.6 deg field)"
    assert al.describe_mag_limit(ESA, 6.9, 30) == a.describe()
    n7 = np.count_nonzero(al.hipparcos_vmag() <= 7.0) * _pinhole_omega(ESA) / (4 * math.pi)
    assert al.describe_mag_limit(ESA, 7.0, 30) == f"catalog to V 7.0 ({n7:.1f} stars per 11.4 x 8.6 deg field)"
    assert al.describe_mag_limit(ESA, 7.0) == f"catalog to V 7.0 (auto: {n7:.1f} stars per 11.4 x 8.6 deg field)"


@pytest.mark.parametrize("bad", [0, -1, float("nan"), float("inf")])
def test_bad_target(bad):
    with pytest.raises(ValueError):
        al.auto_mag_limit(ESA, target_per_field=bad)


# ------------------------------------------------------------------------------------ the sensor
def test_sensor_limit_by_hand():
    from dualsight.kernels.sensor_config import SensorConfig

    s = SensorConfig(psf_sigma_px=0.05, read_noise_e=10.0, quantize=False, exposure_s=0.1,
                     zero_mag_rate_e_per_s=1.5e6)
    # sigma 0.05 px: one pixel holds erf(10/sqrt 2)^2 ~ 1 of the light; T = 5 x 10 e-
    assert al.sensor_limit_v(s, 5.0, 1) == pytest.approx(-2.5 * math.log10(50.0 / 1.5e5), abs=1e-9)
    s2 = SensorConfig(psf_sigma_px=0.8, read_noise_e=5.0, shot_noise=True, sky_background_e=100.0,
                      dark_current_e_per_s=0.0, gain_e_per_adu=2.0, quantize=True)
    q0 = 2 * phi(0.5 / 0.8) - 1
    q1 = phi(1.5 / 0.8) - phi(0.5 / 0.8)
    p3 = q0 * q1                                           # 3rd brightest pixel of a centred star: a side one
    sigma = math.sqrt(25.0 + 100.0 + 4.0 / 12)
    want = -2.5 * math.log10(5 * sigma / (1.5e6 * 0.1 * p3))
    assert al.sensor_limit_v(s2, 5.0, 3) == pytest.approx(want, abs=1e-9)
    assert al.sensor_limit_v(s2, 5.0, 1) > al.sensor_limit_v(s2, 5.0, 3) > al.sensor_limit_v(s2, 8.0, 3)
    assert al.sensor_limit_v(SensorConfig(quantize=False)) is None                    # no noise: sees all
    ideal = SensorConfig()                                  # quantised: one ADU step (5 e-) on the 1st-3rd pixel
    assert al.sensor_limit_v(ideal, 5.0, 1) == pytest.approx(
        -2.5 * math.log10(5.0 / (1.5e5 * (2 * phi(0.5 / 0.8) - 1) ** 2)), abs=1e-9)


# ------------------------------------------------------------------------------------ hil star settings
def test_hil_settings_resolve_auto_from_the_camera(tmp_path):
    from dualsight.jobs.kinds import hil_star as hs
    from dualsight.jobs.kinds.hil_star_spec import settings_from_table

    deferred = settings_from_table(None, mag_limit=None, epoch_jyear=2019.6)
    assert deferred.catalog == {"mag_limit": "auto", "epoch_jyear": 2019.6}
    img = tmp_path / "frame.png"
    img.write_bytes(b"x")
    spec = hs.spec_from_dict(hs.build_spec([img], ESA, deferred))
    want = al.auto_mag_limit(ESA, target_per_field=al.HIL_TARGET_PER_FIELD)
    assert spec.settings.catalog["mag_limit"] == want == 7.0                         # the stored spec: a number
    assert hs.spec_from_dict(spec.to_dict()) == spec
    assert hs.memory_estimate(spec) > 0
    paper = Camera.from_toml(ROOT / "examples" / "cameras" / "paper_star.toml")
    s = settings_from_table({"catalog": {"mag_limit": "auto"}}, mag_limit=7.5, camera=paper)
    assert s.catalog["mag_limit"] == al.auto_mag_limit(paper, target_per_field=al.HIL_TARGET_PER_FIELD) == 6.4
    assert settings_from_table({"catalog": {"mag_limit": 6.0}}, mag_limit=None, camera=paper).catalog[
        "mag_limit"] == 6.0                                                            # a number in the table wins
    assert settings_from_table(None, mag_limit=7.5, camera=paper).catalog["mag_limit"] == 7.5
    assert settings_from_table(None, camera=paper).catalog["mag_limit"] == 7.0     # the Python API's default


def test_cli_default_is_auto():
    import argparse

    from dualsight.jobs.cli import hil_star as cli_hil

    p = argparse.ArgumentParser()
    cli_hil.add_star_parser(p.add_subparsers())
    args = p.parse_args(["star", "x.tiff", "--camera", "c.toml"])
    assert args.mag_limit is None
    assert p.parse_args(["star", "x.tiff", "--camera", "c.toml", "--mag-limit", "6.5"]).mag_limit == 6.5


def test_hil_star_header_states_the_automatic_depth(tmp_path):
    """`hil star` without --mag-limit uses the camera's automatic limit and says so in its header."""
    frames = shared_real() / "esa_tetra3"
    if not frames.is_dir():
        pytest.skip(f"real ESA frames not found in {frames}")
    frame = sorted(frames.glob("*.tiff"))[0]
    rc, out, _ = run_cli(["hil", "star", frame, "--camera", ROOT / "examples" / "cameras" / "esa_tetra3.toml",
                          "--no-lake", "--no-compare"])
    head = out.splitlines()[0]
    want = al.auto_mag_limit(ESA, target_per_field=al.HIL_TARGET_PER_FIELD)
    assert rc == 0 and head.startswith(f"catalog to V {want:.1f} (auto: "), head


def test_whole_sky_magnitudes_are_cached_and_a_damaged_cache_is_rebuilt(tmp_path, monkeypatch):
    monkeypatch.setenv("DUALSIGHT_CACHE", str(tmp_path))
    want = np.sort(johnson_v(read_hip2())[0])
    al.hipparcos_vmag.cache_clear()
    try:
        got = al.hipparcos_vmag()
        files = list(tmp_path.glob("hip2-vmag-*.npy"))
        assert np.array_equal(got, want) and len(files) == 1
        files[0].write_bytes(b"not an array")
        al.hipparcos_vmag.cache_clear()
        assert np.array_equal(al.hipparcos_vmag(), want)
        assert np.array_equal(np.load(files[0]), want)               # rewritten
    finally:
        al.hipparcos_vmag.cache_clear()
