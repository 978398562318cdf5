"""The rendezvous job's spec (:mod:`dualsight.jobs.kinds.rendezvous`): the presets ``far`` and ``close``, the
TOML layout (``seed``, ``cases``, ``[rendezvous]``: ``dualsight/config.py`` ``RendezvousConfig``) and its validation
into a :class:`RendezvousSpec`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from dualsight.config import RendezvousConfig, dataclass_from_table, dataclass_to_table, validate
from dualsight.errors import ConfigError
from dualsight.jobs.engine.specs import preset_and_config, seed_and_case_count
from dualsight.jobs.kinds import star
from dualsight.scene.camera import Camera
from dualsight.scene.relative_orbit import CircularOrbit
from dualsight.scene.example_files import shipped_path
from dualsight.scene.satellite import load_satellite
from dualsight.scene.units import DEG


DEFAULT_CASES = 100

def _hop_preset(altitude_km: float, start_m: float, end_m: float, frames_before: int, frames_orbit: int,
                **extra) -> dict:
    """A V-bar hop from ``start_m`` to ``end_m`` behind the target (y < 0) with one along-track burn
    ``dv_y = (start - end) n / (6 pi)`` (CW: one orbit later the chaser is at ``end_m``, Curtis Sec. 7.5), fired
    at frame ``frames_before``; frames every period / ``frames_orbit`` until one orbit after the burn."""
    orbit = CircularOrbit(altitude_km * 1e3)
    dt = orbit.period_s / frames_orbit
    t_burn = frames_before * dt
    dv = -(abs(start_m) - abs(end_m)) * orbit.mean_motion / (6.0 * math.pi)
    return {"altitude_km": altitude_km, "position_m": [0.0, -abs(start_m), 0.0], "velocity_m_s": [0.0, 0.0, 0.0],
            "frame_interval_s": dt, "duration_s": t_burn + orbit.period_s + 1e-6 * dt,
            "manoeuvre_times_s": [t_burn], "manoeuvre_dv_m_s": [[0.0, dv, 0.0]], **extra}


PRESETS = {
    # issue 23.6 (e): 2 km -> 200 m on V-bar, one known burn (executed to 0.3 % per axis: the benchmark
    # benchmarks/bench_relative_nav.py shows a 1 % burn error leaves ~1.8 % of range), star camera and the paper
    # sensor, bearings only; 64 frames (~99.6 s apart), the burn at frame 6.  The truth moves by CW exactly, its
    # burn error is the filter's dv_error_frac, so the filter has no process noise (accel_psd 0; the earlier 1e-14
    # stood in for the photocentre's bias, now states of the filter: target_selector); the photocentre's spread is
    # the target's own (scene/photocentre_bias.py), so no further cob_sigma_frac.
    "far": {"seed": 1, "cases": DEFAULT_CASES, "rendezvous": _hop_preset(
        500.0, 2000.0, 200.0, 6, 57, camera="star", sensor="paper", range_source="none", dv_error_frac=0.003,
        dispersion_position_m=[2.0, 50.0, 2.0], dispersion_velocity_m_s=[1e-4] * 3,
        prior_position_m=[2.0, 50.0, 2.0], prior_velocity_m_s=[1e-4] * 3, pointing_error_deg=0.5,
        cob_sigma_frac=0.0, accel_psd=0.0)},
    # issue 23.6 (d): the paper's proximity camera and 3U CubeSat, 50 m -> 2 m on V-bar in one orbit, bearings and
    # the blobber's range every frame the target is resolved; 61 frames (~96 s apart), the burn at frame 1.  No
    # process noise (as far); the centre of brightness corrected by the renderer's own shading's mean photocentre
    # (prox_photocentre: ambient + diffuse + specular, ~1.4 cm towards the Sun at 90 deg phase, which the bearings
    # carried uncorrected before) with its bias states; the blobber's range with its known bias removed
    # (range_model).
    "close": {"seed": 1, "cases": DEFAULT_CASES, "rendezvous": _hop_preset(
        500.0, 50.0, 2.0, 1, 59, camera="examples/cameras/paper_prox.toml", range_source="blobber",
        dv_error_frac=0.01, dispersion_position_m=[0.1, 2.5, 0.1], dispersion_velocity_m_s=[1e-4] * 3,
        prior_position_m=[0.1, 2.5, 0.1], prior_velocity_m_s=[1e-4] * 3, pointing_error_deg=0.5,
        phase_correction=True, cob_sigma_frac=0.0, accel_psd=0.0)},
}


class RendezvousTable(BaseModel):
    """The top level of a rendezvous spec's TOML layout (pydantic); ``[rendezvous]`` becomes a RendezvousConfig."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    seed: int = Field(1, ge=0, le=2**63 - 1)
    cases: int | None = Field(None, ge=1, le=10**9)
    preset: str | None = None
    rendezvous: dict = {}
    camera_table: dict | None = None


@dataclass(frozen=True)
class RendezvousSpec:
    """A validated rendezvous campaign: the approach (``RendezvousConfig``), the camera (the star preset's or the
    camera file's, stored inline so a run replays without the file) and, with the star camera, the star job's spec
    of the sensor preset with the target."""

    seed: int
    cfg: RendezvousConfig
    camera: Camera
    star: object = None                   # star.StarSpec (camera = "star") or None
    source: str = field(default="spec", compare=False)

    @property
    def is_star(self) -> bool:
        return self.cfg.camera == "star"

    @property
    def orbit(self) -> CircularOrbit:
        c = self.cfg
        return CircularOrbit(c.altitude_km * 1e3, c.inclination_deg * DEG, c.raan_deg * DEG, c.arg_lat_deg * DEG)

    @property
    def times(self) -> np.ndarray:
        return np.arange(self.cfg.frames) * self.cfg.frame_interval_s

    def to_dict(self) -> dict:
        d = {"seed": self.seed, "rendezvous": dataclass_to_table(self.cfg)}
        if not self.is_star:
            d["camera_table"] = self.camera.to_dict()
        return d


def spec_from_dict(d: dict, source: str = "spec") -> RendezvousSpec:
    """Validate a spec dict (TOML layout); every error names ``source`` and the key."""
    top = validate(RendezvousTable, d, source=source)
    cfg = dataclass_from_table(RendezvousConfig, d.get("rendezvous"), source=source, section="rendezvous")
    last = (cfg.frames - 1) * cfg.frame_interval_s
    for i, t in enumerate(cfg.manoeuvre_times_s):
        if t > last + 1e-9:
            raise ConfigError(f"must lie in (0, {last:g}] s (the last frame's time), got {t!r}", source=source,
                              field=f"rendezvous.manoeuvre_times_s[{i}]")
    load_satellite(cfg.satellite)                 # errors name that file and its key
    if cfg.camera == "star":
        if cfg.range_source != "none":
            raise ConfigError("the star camera gives bearings only: must be 'none' with camera = 'star' (a range "
                              "needs a proximity camera file)", source=source, field="rendezvous.range_source")
        sd = {k: v for k, v in star.PRESETS[cfg.sensor].items() if k != "cases"}
        sd = {**sd, "seed": int(top.seed), "target": {"satellite": cfg.satellite}}
        sp = star.spec_from_dict(sd, source=source)
        return RendezvousSpec(int(top.seed), cfg, sp.camera, sp, source)
    if top.camera_table is not None:
        camera = Camera.from_dict(top.camera_table, source=source)
    else:
        cam_path = shipped_path(cfg.camera)
        if not cam_path.is_file():
            raise ConfigError(f"no such camera file: {cfg.camera} ('star' or a camera file)", source=source,
                              field="rendezvous.camera")
        camera = Camera.from_toml(cam_path)
    return RendezvousSpec(int(top.seed), cfg, camera, None, source)


def resolve_spec(preset: str | None, config, *, seed: int | None = None, cases: int | None = None) -> tuple[dict, int]:
    """The preset (default far), the ``--config`` TOML over it and the flags, validated: (canonical spec dict,
    number of cases)."""
    d, source = preset_and_config(PRESETS, preset, config, default="far")
    n = seed_and_case_count(d, seed, cases, DEFAULT_CASES, source)
    return spec_from_dict(d, source=source).to_dict(), int(n)
