"""Truth inputs of the hardware-in-the-loop runs, resolved once when a run is planned and embedded in its
spec (so the workers need neither the truth files nor astropy, and a changed truth makes another run).

Star tracker, per image (:func:`resolve_star_truths`):
  * a truth file in the format of ``shared/data/real/esa_tetra3/truth.json``
    (:func:`dualsight.scene.skytruth.load_truth_json`), keyed by image file name: the truth attitude is
    its ``R_icrs_to_cam``; its ``matched`` stars are compared with ours;
  * or the reference's tripod test: UTC time, site latitude/longitude/height and the mount's altitude,
    azimuth (and roll) through astropy (:func:`dualsight.scene.skytruth.attitude_from_altaz`); time,
    altitude and azimuth default to the ones in the file name (``2019-07-29T204726_Alt40_Azi-135``).
    A nominal mount pointing is good to about a degree only, so the status limit defaults to 2 deg
    for this source (100 arcsec, the reference's, for a truth file).
  With both, the truth file is the truth and the alt/az pointing is reported beside it (``altaz_*``).

Proximity, per image (:func:`load_range_truth`): a number (metres, every image), a JSON file
``{"<image file name>": metres, ...}`` (or ``{"name": {"range_m": metres}}``), or a camera file written
by ``dualsight calibrate`` whose ``[[calibration.views]]`` give each board's ``distance_m`` keyed by image
name.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dualsight.errors import ConfigError, InputError
from dualsight.scene.camera_file import read_camera_toml
from dualsight.scene.skytruth import altaz_from_filename, attitude_from_altaz

__all__ = ["Site", "resolve_star_truths", "load_range_truth"]


@dataclass(frozen=True)
class Site:
    """The tripod test's inputs: site, and optionally one time / mount pointing for every image
    (None = take it from each file name, ``scene.skytruth.altaz_from_filename``)."""

    lat_deg: float
    lon_deg: float
    height_m: float = 0.0
    time_utc: str | None = None
    alt_deg: float | None = None
    az_deg: float | None = None
    roll_deg: float = 0.0
    pressure_hpa: float = 0.0

    def __post_init__(self):
        for name, lo, hi in (("lat_deg", -90.0, 90.0), ("lon_deg", -360.0, 360.0), ("height_m", -500.0, 1e5),
                             ("alt_deg", -89.99, 90.0), ("az_deg", -360.0, 720.0), ("roll_deg", -360.0, 360.0),
                             ("pressure_hpa", 0.0, 1100.0)):
            v = getattr(self, name)
            if v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo <= v <= hi:
                flag = "--" + name.rsplit("_", 1)[0].replace("_", "-")
                raise InputError(f"must be a number in [{lo:g}, {hi:g}], got {v!r}", source=flag)


def _matrix(a) -> list[float]:
    return [float(x) for x in np.asarray(a, np.float64).ravel()]


def resolve_star_truths(paths, truth_file: dict | None, site: Site | None) -> list[dict]:
    """Truth of every image as spec entries (``jobs.kinds.hil_star_spec.StarTruth``): ``source`` ("file", "altaz",
    "none"), ``A`` (9 floats, row-major ICRS -> camera), the truth file's ``ra_deg``/``dec_deg`` and
    ``matched`` stars, the tripod attitude ``altaz_A``, and a ``note`` when an image has no truth.
    The alt/az attitudes come from one astropy call."""
    out = [{"source": "none"} for _ in paths]
    if truth_file is not None:
        for t, p in zip(out, paths):
            e = truth_file.get(Path(p).name)
            if e is None:
                t["note"] = "not in the truth file"
                continue
            m = e["matched"]
            t.update(source="file", A=_matrix(e["R_icrs_to_cam"]), ra_deg=float(e["ra_deg"]),
                     dec_deg=float(e["dec_deg"]),
                     matched={k: [float(x) for x in m[k]] for k in ("row", "col", "ra_deg", "dec_deg", "mag")})
    if site is None:
        return out
    want, times, alts, azs = [], [], [], []
    for k, p in enumerate(paths):
        t_, a_, z_ = site.time_utc, site.alt_deg, site.az_deg
        if t_ is None or a_ is None or z_ is None:
            try:
                ft, fa, fz = altaz_from_filename(p)
            except ConfigError:
                out[k]["note"] = ("no --time/--alt/--az given and the file name carries no "
                                  "'YYYY-MM-DDTHHMMSS..._Alt<deg>_Azi<deg>'")
                continue
            t_ = ft if t_ is None else t_
            a_ = fa if a_ is None else a_
            z_ = fz if z_ is None else z_
        want.append(k)
        times.append(t_)
        alts.append(a_)
        azs.append(z_)
    if want:
        try:
            A = attitude_from_altaz(times, site.lat_deg, site.lon_deg, site.height_m, np.asarray(alts),
                                    np.asarray(azs), site.roll_deg, pressure_hpa=site.pressure_hpa)
        except (ValueError, TypeError) as e:   # astropy rejects a malformed time string
            raise InputError(f"cannot compute the alt/az truth: {e}", source="--time") from None
        for k, a in zip(want, np.asarray(A).reshape(-1, 3, 3)):
            out[k]["altaz_A"] = _matrix(a)
            if out[k]["source"] == "none":
                out[k].update(source="altaz", A=_matrix(a))
                out[k].pop("note", None)
    return out


def load_range_truth(spec, paths) -> tuple[list[float | None], str]:
    """Per-image true ranges from ``--range-truth`` (module docstring) and the source name ("value",
    "json" or "calibration"; "none" without); images without an entry get None."""
    paths = [Path(p) for p in paths]
    if spec is None:
        return [None] * len(paths), "none"
    if isinstance(spec, (int, float)) and not isinstance(spec, bool):
        v = float(spec)
        _check_range(v, "--range-truth")
        return [v] * len(paths), "value"
    text = str(spec)
    try:
        v = float(text)
    except ValueError:
        v = None
    if v is not None:
        _check_range(v, "--range-truth")
        return [v] * len(paths), "value"
    p = Path(text)
    if not p.is_file():
        raise InputError("is neither a number (metres) nor a truth file (JSON or camera TOML)", source=text)
    table: dict[str, float] = {}
    if p.suffix.lower() == ".json":
        try:
            data = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise InputError(f"cannot be read as JSON ({e})", source=text) from None
        if not isinstance(data, dict):
            raise InputError("must be a JSON object {\"image name\": range_m, ...}", source=text)
        for k, val in data.items():
            if isinstance(val, dict):
                val = val.get("range_m", val.get("distance_m"))
            if isinstance(val, bool) or not isinstance(val, (int, float)):
                raise InputError(f"entry {k!r} must be a number (metres) or {{\"range_m\": number}}", source=text)
            _check_range(float(val), text, k)
            table[Path(k).name] = float(val)
        kind = "json"
    else:
        _, cal = read_camera_toml(p)
        views = cal.get("views") or []
        for i, vw in enumerate(views):
            if not isinstance(vw, dict) or "image" not in vw or "distance_m" not in vw:
                raise InputError("needs image and distance_m", source=text, field=f"calibration.views[{i}]")
            _check_range(float(vw["distance_m"]), text, f"calibration.views[{i}].distance_m")
            table[Path(str(vw["image"])).name] = float(vw["distance_m"])
        if not table:
            raise InputError("has no [[calibration.views]] with distance_m (write it with dualsight calibrate)",
                             source=text)
        kind = "calibration"
    return [table.get(q.name) for q in paths], kind


def _check_range(v: float, source: str, key: str | None = None):
    if not (math.isfinite(v) and v > 0):
        raise InputError(f"a true range must be a number > 0 m, got {v!r}", source=source, field=key)
