"""``hil star --track``: a ``hil_star`` run's images as one ordered sequence through the tracker's state machine
(``nav/sequence.py``: lost-in-space until a verified fix, then tracking, fallback, re-acquisition; issue 22,
point 4).

The spec's ``track`` table (:class:`TrackSpec`) holds every image's UTC time and its source
(``scene/frame_times.py``; the command sorts the images by time before the spec is made, so case i is the i-th
frame in time), the tracker's settings (``TrackingConfig``'s table, ``max_coast_frames``, ``lis_min_stars``: from
``--tracking FILE.toml``, :func:`tracking_settings`; the defaults without it).  After the shard's
frames are detected (``jobs/kinds/hil_star.py``: the same detections as the lost-in-space rows), the frames run
through :func:`dualsight.nav.sequence.run_sequence` in case order; the command makes the whole run one shard, so
the sequence is every image.  Frames whose time is not after the previous frame's (a set taken at one instant)
start a new sequence: a rate needs ``dt > 0``.  An image that could not be read is a dropped frame.

Columns added to the ``hil_star`` rows (null in runs without ``--track``): ``time_utc``, ``time_source``,
``track_mode`` (``nav.sequence.MODE_NAMES``: ``none``, ``lost_in_space``, ``tracking``), ``track_reason``
(``REASON_NAMES``), ``track_stars`` (stars in the sequence's answer), ``track_A`` (its attitude, inertial ->
camera, row-major), ``rate_rad_s`` (3,) and ``rate_cov`` (9,) (rad/s, (rad/s)^2, camera frame of the frame) and
``rate_source``: the rate from the displacements of the stars identified in this frame and the previous fix
(``stars``, Crassidis 2002) when at least two are common, else from the two attitudes (``attitudes``), else null.
"""

from __future__ import annotations

import math
from datetime import datetime, timedelta

import numpy as np
from pydantic import Field

from dualsight.config import dataclass_from_table, dataclass_to_table, validate
from dualsight.nav.tracking_config import TrackingConfig
from dualsight.errors import ConfigError
from dualsight.jobs.kinds.hil_common import Frozen
from dualsight.nav.sequence import MODE_NAMES, REASON_NAMES, run_sequence
from dualsight.scene.camera import read_toml

__all__ = ["TrackSpec", "track_columns", "segments", "tracking_settings"]


class TrackSpec(Frozen):
    """The ``track`` table of a ``hil_star`` spec (module docstring): one time per image, in the spec's order."""

    times_utc: tuple[str, ...] = Field(min_length=1)
    time_sources: tuple[str, ...] = ()
    tracking: dict = Field(default_factory=dict)
    max_coast_frames: int = Field(default=10, ge=0, le=10_000)
    lis_min_stars: int = Field(default=3, ge=3, le=100)


_RATE_SUFFIXES = {"_deg_s": "_rad_s", "_arcsec_s": "_rad_s"}
"""Rate keys of a ``--tracking`` file: ``<name>_deg_s`` / ``<name>_arcsec_s`` fill the field ``<name>_rad_s``."""


def tracking_settings(path) -> dict:
    """The tracker's settings of ``hil star --track --tracking FILE.toml``: a ``[tracking]`` table
    (``nav/tracking_config.TrackingConfig``'s keys, ``<name>_deg`` / ``<name>_arcsec`` for a ``<name>_rad`` field and
    ``<name>_deg_s`` / ``<name>_arcsec_s`` for a ``<name>_rad_s`` one) and the top-level keys ``max_coast_frames``
    (integer in [0, 10000]) and ``lis_min_stars`` (integer in [3, 100]).  Validated now; an error names the file
    and the key (ConfigError).  Returns the spec's ``track`` keys: tracking (the canonical table, every field),
    max_coast_frames, lis_min_stars (those given).

    The default prior of a frame after a first fix has no rate, so its windows are sized by ``rate_sigma_rad_s``
    (0.5 deg/s: 15 deg over 30 s, capped at ``window_max_px``) and the chance-match test refuses them: tracking
    starts at the third frame.  A camera known to turn slowly says so and tracks from the second frame: e.g. a
    ground camera (the sidereal rate, 15 arcsec/s) of 40 arcsec pixels with frames 30 s apart tracks from the second
    frame with ``rate_sigma_arcsec_s = 6`` (windows ~22 px, the true rate at 2.5 sigma), not with 30 (windows at
    the 50 px cap; tests/test_hil_track_settings.py)."""
    src = str(path)
    d = read_toml(path)
    top = {k: v for k, v in d.items() if k != "tracking"}
    bad = sorted(set(top) - {"max_coast_frames", "lis_min_stars"})
    if bad:
        raise ConfigError("unknown key; allowed: [tracking], max_coast_frames, lis_min_stars", source=src,
                          field=bad[0])
    table = d.get("tracking", {})
    if not isinstance(table, dict):
        raise ConfigError("must be a table", source=src, field="tracking")
    conv, written = {}, {}
    for key, value in table.items():
        for suffix, to in _RATE_SUFFIXES.items():
            name = key[: -len(suffix)] + to
            if key.endswith(suffix) and name in TrackingConfig.__dataclass_fields__:
                if isinstance(value, bool) or not isinstance(value, (int, float)):
                    raise ConfigError(f"must be a number, got {value!r}", source=src, field=f"tracking.{key}")
                written[name] = (key, value)
                key, value = name, value * (math.pi / 180.0 if suffix == "_deg_s" else math.pi / 648000.0)
                break
        conv[key] = value
    try:
        cfg = dataclass_from_table(TrackingConfig, conv, source=src, section="tracking")
    except ConfigError as e:                 # name a rate key and its value as written
        name = (e.field or "").removeprefix("tracking.")
        if name not in written:
            raise
        key, value = written[name]
        raise ConfigError(f"must be in (0, 30 deg/s], got {value!r}", source=src, field=f"tracking.{key}") from None
    validate(TrackSpec, {"times_utc": ["-"], **top}, source=src)
    return {"tracking": dataclass_to_table(cfg), **top}


def _seconds(times_utc) -> np.ndarray:
    t = [datetime.fromisoformat(s.replace("Z", "+00:00")) for s in times_utc]
    return np.array([(x - t[0]) / timedelta(microseconds=1) * 1e-6 for x in t], np.float64)


def segments(t: np.ndarray) -> list[slice]:
    """Runs of strictly increasing times: the sequences of frames ``t`` (s) (a frame not after its predecessor
    starts a new one)."""
    cut = np.flatnonzero(np.diff(t) <= 0) + 1
    edges = np.concatenate([[0], cut, [len(t)]])
    return [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def track_columns(case_ids: list[int], dets: list, track: TrackSpec, ctx, engine: str = "numpy") -> list[dict]:
    """The tracking columns (module docstring) of the frames ``case_ids`` (ascending, consecutive in time).

    dets : per frame ``(xy (D, 2) px brightest first, sigma_px (D,) or None)``, or None for an image that could
    not be read.  ctx : the ``hil_star`` kind's context (camera, star catalog, voting index, voting settings).
    Returns one dict of columns per frame.
    """
    rt = ctx.rt
    cfg = validate(TrackingConfig, track.tracking, source="spec", section="track.tracking")
    t_all = _seconds(track.times_utc)
    t = t_all[np.asarray(case_ids, np.int64)]
    out = [{"time_utc": track.times_utc[k],
            "time_source": track.time_sources[k] if track.time_sources else None} for k in case_ids]
    for seg in segments(t):
        idx = range(seg.start, seg.stop)
        avail = np.array([dets[i] is not None for i in idx], bool)
        xy = [dets[i][0] if dets[i] is not None else np.zeros((0, 2)) for i in idx]
        sg = [(dets[i][1] if dets[i][1] is not None else np.full(len(dets[i][0]), np.nan))
              if dets[i] is not None else np.zeros(0) for i in idx]
        offsets = np.concatenate([[0], np.cumsum([len(a) for a in xy])]).astype(np.int64)
        res = run_sequence(t[seg], np.concatenate(xy).reshape(-1, 2), np.concatenate(sg), offsets, rt.camera,
                           ctx.catalog.unit, ctx.index, rt.voting, cfg, available=avail,
                           cat_vmag=ctx.catalog.vmag, max_coast_frames=track.max_coast_frames,
                           lis_min_stars=track.lis_min_stars, engine=engine)
        for j, i in enumerate(idx):
            mode = int(res.mode[j])
            row = out[i]
            row.update(track_mode=MODE_NAMES[mode], track_reason=REASON_NAMES[int(res.reason[j])],
                       track_stars=int(res.n_used[j]))
            if mode:
                row["track_A"] = res.A[j].ravel().tolist()
            for source, w, C in (("stars", res.rate_star[j], res.rate_star_cov[j]),
                                 ("attitudes", res.rate_att[j], res.rate_att_cov[j])):
                if np.all(np.isfinite(w)):
                    row.update(rate_rad_s=w.tolist(), rate_cov=C.ravel().tolist(), rate_source=source)
                    break
    return out
