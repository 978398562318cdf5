"""Every range of the stage configs is declared once, in the field types (pydantic ``Field`` / ``Literal``),
and enforced on both paths: a TOML table through ``dualsight.config`` (one ConfigError naming the
file, the dotted key and the value) and a dataclass built directly in Python (a ValueError naming the
field, the value and the allowed range)."""

from __future__ import annotations

import copy
import dataclasses
import time

import pytest

from dualsight.catalogs.stars import StarCatalogConfig
from dualsight.errors import ConfigError
from dualsight.jobs.kinds import prox
from dualsight.config import dataclass_from_table
from dualsight.config import allowed_range
from dualsight.kernels.detect import DetectConfig
from dualsight.kernels.sensor_config import SensorConfig
from dualsight.nav.blobber import BlobberConfig
from dualsight.nav.voting_config import MAX_TOLERANCE_RAD, VotingConfig
from dualsight.scene.camera import Camera
from dualsight.scene.satellite import MAX_SURFACE_POINTS, satellite_from_dict
from dualsight.scene.units import ARCSEC

CONFIGS = {"voting": VotingConfig, "sensor": SensorConfig, "detect": DetectConfig, "blobber": BlobberConfig,
           "catalog": StarCatalogConfig}

# (section, field, bad value): each value breaks exactly one declared bound
BAD_FIELDS = [
    ("voting", "tolerance_rad", 1e9 * ARCSEC),        # the example: 1e9 arcsec was accepted
    ("voting", "tolerance_rad", 2 * MAX_TOLERANCE_RAD),
    ("voting", "tolerance_rad", 0.0),
    ("voting", "verify_tolerance_rad", 0.1),
    ("voting", "attitude_tolerance_rad", 1.0),
    ("voting", "max_stars", 10**6),
    ("voting", "max_stars", 1),
    ("voting", "candidates_per_star", 6),
    ("voting", "min_accepted", 1001),
    ("voting", "min_verified", 10**9),
    ("voting", "max_vote_cells", 2**40),
    ("voting", "accept_fraction", 1.5),
    ("voting", "accept_rule", "most"),
    ("sensor", "psf_sigma_px", 1e3),                  # a huge PSF hung the renderer
    ("sensor", "psf_sigma_px", 0.0),
    ("sensor", "psf_window_sigma", 100.0),
    ("sensor", "psf_window_sigma", 0.5),
    ("sensor", "exposure_s", 1e6),
    ("sensor", "exposure_s", 0.0),
    ("sensor", "gain_e_per_adu", 0.0),
    ("sensor", "gain_e_per_adu", 1e9),
    ("sensor", "full_well_e", 1e13),
    ("sensor", "bit_depth", 25),
    ("sensor", "bias_adu", 1e9),
    ("sensor", "zero_mag_rate_e_per_s", 1e15),
    ("sensor", "read_noise_e", 1e13),
    ("sensor", "dark_current_e_per_s", -1.0),
    ("sensor", "sky_background_e", 1e13),
    ("sensor", "hot_pixel_fraction", 1.5),
    ("sensor", "hot_pixel_e", 1e13),
    ("sensor", "hot_pixel_seed", 2**64),
    ("sensor", "false_stars_per_frame", 10**6),
    ("sensor", "false_star_flux_min_e", 0.0),
    ("sensor", "false_star_flux_max_e", 1e13),
    ("detect", "threshold_adu", 1e9),
    ("detect", "k_sigma", 1e4),
    ("detect", "background_adu", -1e9),
    ("detect", "noise_sigma_adu", -1.0),
    ("detect", "min_pixels", 0),
    ("detect", "min_pixels", 2**33),
    ("detect", "max_blobs_per_frame", 10**7),
    ("detect", "background_step", 10**6),
    ("detect", "connectivity", 6),
    ("blobber", "estimator", "magic"),
    ("blobber", "threshold", -1.0),
    ("blobber", "threshold", 1e13),
    ("blobber", "connectivity", 6),
    ("blobber", "target", "smallest"),
    ("blobber", "area_curve", "median-ish"),
    ("blobber", "min_pixels", 2**33),
    ("catalog", "mag_limit", 13.0),
    ("catalog", "epoch_jyear", 3000.0),
]


@pytest.mark.parametrize("section, name, bad", BAD_FIELDS)
def test_table_value_out_of_range_names_file_key_and_value(section, name, bad):
    with pytest.raises(ConfigError) as e:
        dataclass_from_table(CONFIGS[section], {name: bad}, source="spec.toml", section=section)
    assert e.value.source == "spec.toml" and e.value.field == f"{section}.{name}", str(e.value)
    msg = str(e.value)
    assert f"got {bad!r}" in msg and "\n" not in msg, msg


@pytest.mark.parametrize("section, name, bad", BAD_FIELDS)
def test_direct_construction_out_of_range_names_field_value_and_range(section, name, bad):
    with pytest.raises(ValueError) as e:
        CONFIGS[section](**{name: bad})
    msg = str(e.value)
    assert name in msg and f"got {bad!r}" in msg and "\n" not in msg, msg


def test_tolerance_given_in_arcsec_is_bounded_too():
    """The issue's case: ``tolerance_arcsec = 1e9`` in a star spec is refused (1 deg at most)."""
    with pytest.raises(ConfigError) as e:
        dataclass_from_table(VotingConfig, {"tolerance_arcsec": 1e9}, source="spec.toml", section="voting")
    # named as written, in the units written: 1 deg = 3600 arcsec
    assert e.value.field == "voting.tolerance_arcsec" and "(allowed (0, 3600] arcsec)" in str(e.value) and "1000000000" in str(e.value)
    ok = dataclass_from_table(VotingConfig, {"tolerance_arcsec": 3600.0}, source="spec.toml", section="voting")
    assert ok.tolerance_rad == pytest.approx(MAX_TOLERANCE_RAD)


def _numeric_fields(cls):
    import typing
    hints = typing.get_type_hints(cls, include_extras=True)
    for f in dataclasses.fields(cls):
        base = hints[f.name]
        args = [a for a in typing.get_args(base) if a is not type(None)] if typing.get_origin(base) is not \
            typing.Annotated else [base]
        inner = typing.get_args(args[0])[0] if args and typing.get_origin(args[0]) is typing.Annotated else (
            args[0] if args else base)
        if inner in (int, float):
            yield f.name, base


@pytest.mark.parametrize("cls", [*CONFIGS.values(), Camera], ids=lambda c: c.__name__)
def test_every_number_field_has_both_bounds(cls):
    """Memory and time stay bounded: every int/float field of a stage config declares a lower and an
    upper bound in its type (a count or size without an upper bound fails here)."""
    fields = list(_numeric_fields(cls))
    assert fields
    for name, annotation in fields:
        rng = allowed_range(annotation)
        assert rng.removeprefix("None or ")[:1] in "[(" and "," in rng, f"{cls.__name__}.{name}: {rng!r}"


def test_cross_field_rule_kept():
    with pytest.raises(ValueError, match="false_star_flux_max_e must be >= false_star_flux_min_e"):
        SensorConfig(false_star_flux_min_e=1e4, false_star_flux_max_e=1e3)
    with pytest.raises(ConfigError) as e:
        dataclass_from_table(SensorConfig, {"false_star_flux_min_e": 1e4, "false_star_flux_max_e": 1e3},
                             source="spec.toml", section="sensor")
    assert "false_star_flux_max_e" in str(e.value) and e.value.field == "sensor"


def test_direct_construction_unchanged_for_good_values():
    import numpy as np
    assert VotingConfig() == VotingConfig.paper() and SensorConfig().psf_sigma_px == 0.8
    assert DetectConfig(max_blobs_per_frame=np.int64(3)).max_blobs_per_frame == 3   # numpy scalars as numbers
    assert type(DetectConfig(max_blobs_per_frame=np.int64(3)).max_blobs_per_frame) is int
    six = StarCatalogConfig(mag_limit=6)                    # an int limit is kept as the float 6.0: the same
    assert type(six.mag_limit) is float and six.mag_limit == 6.0    # config, hence the same catalog cache file
    assert six.key() == StarCatalogConfig(mag_limit=6.0).key() != StarCatalogConfig(mag_limit=6.1).key()
    with pytest.raises(dataclasses.FrozenInstanceError):
        SensorConfig().psf_sigma_px = 2.0


# ------------------------------------------------------------------------------------------ camera file
CAM = {"width": 1024, "height": 768, "pixel_pitch_um": 4.65, "focal_length_mm": 17.0}
BAD_CAMERA = [
    ("width", 0), ("width", 70_000), ("height", 2**40), ("pixel_pitch_um", 0.001), ("pixel_pitch_um", 2000.0),
    ("focal_length_mm", 0.0), ("focal_length_mm", 1e5), ("fx", 0.5), ("fx", 1e8), ("fy", -3.0), ("cx", 2e6),
    ("cy", -2e6), ("bit_depth", 0), ("bit_depth", 33), ("width", 1024.5), ("name", 3),
]


@pytest.mark.parametrize("key, bad", BAD_CAMERA)
def test_camera_file_key_out_of_range(key, bad):
    with pytest.raises(ConfigError) as e:
        Camera.from_dict({**CAM, key: bad}, source="cam.toml")
    assert e.value.source == "cam.toml" and e.value.field == f"camera.{key}", str(e.value)
    assert f"got {bad!r}" in str(e.value)


def test_camera_file_rules_between_keys():
    with pytest.raises(ConfigError) as e:
        Camera.from_dict({k: v for k, v in CAM.items() if k != "focal_length_mm"}, source="cam.toml")
    assert e.value.field == "camera.focal_length_mm" and "missing" in str(e.value)
    with pytest.raises(ConfigError) as e:     # a focal length that is fine in mm but absurd in pixels
        Camera.from_dict({**CAM, "pixel_pitch_um": 0.01, "focal_length_mm": 10_000.0}, source="cam.toml")
    assert e.value.field == "camera.focal_length_mm" and "px" in str(e.value)
    with pytest.raises(ConfigError) as e:
        Camera.from_dict({**CAM, "distortion": [0.0] * 6}, source="cam.toml")
    assert e.value.field == "camera.distortion"
    with pytest.raises(ConfigError) as e:
        Camera(10, 10, 1e-6, 100.0, 100.0, 5.0, 5.0, (0.0, float("nan"), 0.0, 0.0, 0.0))
    assert e.value.field == "camera.distortion[1]"


# ------------------------------------------------------------------------------------------ satellite file
SAT = prox.resolve_spec("paper", None)["satellite"]


def _sat(path: str, value):
    d = copy.deepcopy(SAT)
    node = d
    keys = path.split(".")
    for k in keys[:-1]:
        node = node[int(k)] if isinstance(node, list) else node[k]
    node[keys[-1]] = value
    return d


BAD_SATELLITE = [
    ("frames", 0, "frames"), ("frames", 10**8, "frames"),
    ("camera.I_a", -1.0, "camera.I_a"), ("camera.I_l", 1e4, "camera.I_l"),
    ("camera.position", [1e6, 0.0, 0.0], "camera.position.0"),
    ("camera.rotation_deg", [0.0, 400.0, 0.0], "camera.rotation_deg.1"),
    ("body.position", [0.0, 0.0, 2e5], "body.position.2"),
    ("body.velocity", [0.0, -1e6, 0.0], "body.velocity.1"),
    ("body.surface_resolution", 1e13, "body.surface_resolution"),
    ("body.components", 5000, "body.components"),
    ("component.0.size", [0.1, 0.1, 2000.0], "component[0].size.2"),
    ("component.0.k_s", 11.0, "component[0].k_s"),
    ("component.0.n", 0.0, "component[0].n"),
    ("component.0.surface_resolution", 0.0, "component[0].surface_resolution"),
]


@pytest.mark.parametrize("path, bad, field", BAD_SATELLITE)
def test_satellite_key_out_of_range(path, bad, field):
    with pytest.raises(ConfigError) as e:
        satellite_from_dict(_sat(path, bad), source="sat.toml")
    assert e.value.source == "sat.toml" and e.value.field == field, str(e.value)
    if not isinstance(bad, list):
        assert f"got {bad!r}" in str(e.value)


def test_satellite_point_budget_refused_before_anything_is_built():
    """1e11 points/m^2 on the 3U CubeSat would be ~1.4e10 points (hundreds of GB): refused at once."""
    t0 = time.perf_counter()
    with pytest.raises(ConfigError) as e:
        satellite_from_dict(_sat("body.surface_resolution", 1e11), source="sat.toml")
    assert time.perf_counter() - t0 < 2.0
    assert e.value.field == "body.surface_resolution" and f"{MAX_SURFACE_POINTS:.0e}" in str(e.value)
    many = _sat("component", [dict(SAT["component"][0])] * 1001)
    with pytest.raises(ConfigError) as e:
        satellite_from_dict(many, source="sat.toml")
    assert e.value.field == "component"


def test_satellite_thin_cylinder_does_not_allocate_while_searching_a_resolution():
    """A 1 um thin, 1 km long cylinder has no points at 1e6/m^2; finding the resolution that would give it
    some must stop at the point budget instead of building 1e8-element grids."""
    d = _sat("component", [{"shape": "cylinder", "size": [1e-6, 1000.0]}])
    t0 = time.perf_counter()
    with pytest.raises(ConfigError) as e:
        satellite_from_dict(d, source="sat.toml")
    assert time.perf_counter() - t0 < 5.0
    assert e.value.field in ("component[0].size", "body.surface_resolution"), str(e.value)


@pytest.mark.parametrize("where", ["top", "camera", "body", "component"])
def test_unknown_key_with_a_newline_is_one_line(where):
    """Found by tests/test_fuzz_inputs.py: a key holding a newline is named escaped, on one line."""
    d = copy.deepcopy(SAT)
    {"top": d, "camera": d["camera"], "body": d["body"], "component": d["component"][0]}[where]["a\nb"] = 1
    with pytest.raises(ConfigError) as e:
        satellite_from_dict(d, source="sat.toml")
    assert "\n" not in str(e.value) and "a\\nb" in str(e.value) and "unknown key" in str(e.value)
    with pytest.raises(ConfigError) as e:
        Camera.from_dict({**CAM, "a\nb": 1}, source="cam.toml")
    assert "\n" not in str(e.value) and e.value.field == "camera.a\\nb"


@pytest.mark.parametrize("cls, section, name, bad, stated", [
    ("tracking", "tracking", "window_k_sigma", 50.0, "(0, 20]"),          # TrackingConfig's docstring ranges
    ("tracking", "tracking", "streak_psf_sigma_px", -1.0, "[0, 20]"),
    ("tracking", "tracking", "edge_margin_px", 2000.0, "[0, 1000]"),
    ("tracking", "tracking", "model_switch_prob", 0.7, "(0, 0.666667)"),
    ("catalog", "catalog", "mag_limit", 13.0, "[-2, 12]"),
])
def test_a_toml_value_out_of_range_states_the_whole_range(cls, section, name, bad, stated):
    """Not only the bound it broke ("less than or equal to 20") but the field's whole range, as its docstring
    states it."""
    from dualsight.nav.tracking_config import TrackingConfig

    tp = TrackingConfig if cls == "tracking" else CONFIGS[cls]
    with pytest.raises(ConfigError) as e:
        dataclass_from_table(tp, {name: bad}, source="spec.toml", section=section)
    assert f"(allowed {stated})" in str(e.value), str(e.value)
