"""Camera files: the TOML file a camera is read from by the simulator and the HIL jobs.

:func:`write_camera_toml` writes the ``[camera]`` table the simulator reads (:meth:`Camera.from_toml`) and, for
a calibration (:class:`dualsight.scene.calibration.CalibrationResult`), a ``[calibration]`` table with the fit
quality and the per-image board poses (``[[calibration.views]]``: :func:`calibration_table`), serialised by
tomli-w (:func:`toml_dumps`), into an existing folder (none is created).  :func:`read_camera_toml` reads both.
Pixel coordinates are dualsight's, from the image's top-left corner (``cx = cx_opencv + 0.5``).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import tomli_w

from dualsight.errors import ConfigError, InputError
from dualsight.scene.camera import CAMERA_FILE_TABLES, Camera, read_toml

__all__ = ["write_camera_toml", "calibration_table", "read_camera_toml", "toml_dumps"]

_FLAG_NAMES = {  # cv2.CALIB_* bits, for the camera file
    1: "CALIB_USE_INTRINSIC_GUESS", 2: "CALIB_FIX_ASPECT_RATIO", 4: "CALIB_FIX_PRINCIPAL_POINT",
    8: "CALIB_ZERO_TANGENT_DIST", 16: "CALIB_FIX_FOCAL_LENGTH", 32: "CALIB_FIX_K1", 64: "CALIB_FIX_K2",
    128: "CALIB_FIX_K3", 2048: "CALIB_FIX_K4", 4096: "CALIB_FIX_K5", 8192: "CALIB_FIX_K6",
    16384: "CALIB_RATIONAL_MODEL",
}


def write_camera_toml(result_or_camera, path: str | Path, extra: dict | None = None,
                      *, name: str | None = None, notes: str | None = None, comment: str | None = None) -> Path:
    """Write a camera file: ``[camera]`` (what :meth:`Camera.from_toml` reads) and, for a
    calibration, ``[calibration]`` with ``[[calibration.views]]``.

    Parameters
    ----------
    result_or_camera : a :class:`Camera`, or a calibration result
        (:class:`~dualsight.scene.calibration.CalibrationResult`: its ``camera``, and the fit for the
        ``[calibration]`` table).
    path : output file, in an existing folder (none is created: InputError otherwise); written to a
        temporary name and renamed, so it is never half-written.
    extra : further top-level tables (e.g. ``{"source": {"images": "..."}}``), of
        :data:`~dualsight.scene.camera.CAMERA_FILE_TABLES` only (what the readers accept); may not redefine
        ``camera`` or ``calibration``.
    name, notes : optional ``camera.name`` / ``camera.notes`` strings.
    comment : text for the header comment (one or more lines).
    """
    path = Path(path)
    result = None if isinstance(result_or_camera, Camera) else result_or_camera
    camera = result_or_camera if result is None else getattr(result, "camera", None)
    if not isinstance(camera, Camera):
        raise TypeError(f"expected a CalibrationResult or Camera, got {type(result_or_camera).__name__}")
    cam = {}
    if name is not None:
        cam["name"] = str(name)
    if result is not None and not result.pixel_pitch_known:
        auto = ("pixel pitch unknown at calibration: pixel_pitch_um is a placeholder; "
                "fx, fy (px) are the measured quantities")
        notes = f"{notes}; {auto}" if notes else auto
    if notes is not None:
        cam["notes"] = str(notes)
    cam.update(camera.to_dict())
    doc = {"camera": cam}
    if result is not None:
        doc["calibration"] = calibration_table(result)
    for k, v in (extra or {}).items():
        if k in doc:
            raise ConfigError(f"extra may not redefine [{k}]", source=str(path), field=k)
        if k not in CAMERA_FILE_TABLES or not isinstance(v, dict):
            raise ConfigError(f"extra [{k}] is not a table a camera file may hold ({', '.join(CAMERA_FILE_TABLES)})",
                              source=str(path), field=k)
        doc[k] = v

    fh, fv, fd = (math.degrees(a) for a in camera.fov_rad)
    head = []
    if comment:
        head += [f"# {line}".rstrip() for line in str(comment).splitlines()]
    head += ["# dualsight camera file. Pixel coordinates from the image's top-left corner "
             "(cx = cx_opencv + 0.5).",
             f"# focal length {camera.focal_length_m * 1e3:.4f} mm"
             + ("" if result is None or result.pixel_pitch_known else " (placeholder pitch: not meaningful)")
             + f"; field of view {fh:.3f} x {fv:.3f} deg, diagonal {fd:.3f} deg"]
    text = "\n".join(head) + "\n\n" + toml_dumps(doc)
    if not path.parent.is_dir():
        raise InputError(f"folder {path.parent} does not exist (camera files are written only into existing "
                         "folders)", source=str(path))
    tmp = path.with_name(path.name + f".tmp{os.getpid()}")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
    return path

def calibration_table(result) -> dict:
    """The ``[calibration]`` table of a camera file (plain TOML types) for a
    :class:`~dualsight.scene.calibration.CalibrationResult`."""
    import cv2

    flags = [n for bit, n in _FLAG_NAMES.items() if result.flags & bit]
    return {
        "method": "chessboard (Zhang/Bouguet) via OpenCV findChessboardCorners + cornerSubPix + calibrateCamera",
        "opencv_version": cv2.__version__,
        "board_inner_corners": list(result.board),
        "square_m": result.square_m,
        "flags": result.flags,
        "flag_names": flags,
        "pixel_pitch_known": result.pixel_pitch_known,
        "rms_px": result.rms_px,
        "n_views": len(result.views),
        "std": dict(result.std),
        "not_found": [str(p.name) for p in result.not_found],
        "unreadable": [f"{p.name}: {why}" for p, why in result.unreadable],
        "views": [{"image": v.path.name, "rms_px": v.rms_px, "distance_m": v.distance_m,
                   "rvec": [float(x) for x in v.rvec], "tvec_m": [float(x) for x in v.tvec]}
                  for v in result.views],
    }

def read_camera_toml(path: str | Path) -> tuple[Camera, dict]:
    """(Camera, the ``[calibration]`` table or {}) of a camera file."""
    path = Path(path)
    cam = Camera.from_toml(path)
    cal = read_toml(path).get("calibration", {})
    if not isinstance(cal, dict):
        raise ConfigError("must be a table", source=str(path), field="calibration")
    return cam, cal


# ---------------------------------------------------------------------------------------------- TOML writer
def toml_dumps(doc: dict) -> str:
    """TOML text of nested dicts/lists of str, int, float, bool (tomli-w; numpy scalars and arrays, tuples and
    paths converted to plain values first).  Dicts become tables, lists of dicts arrays of tables; floats
    round-trip exactly, NaN/inf as ``nan``/``inf``."""
    return tomli_w.dumps(_plain(doc))

def _plain(v):
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_plain(x) for x in v]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v)
    if isinstance(v, Path):
        return str(v)
    if isinstance(v, str):
        return v
    raise TypeError(f"cannot write {type(v).__name__} to TOML")
