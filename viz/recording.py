"""rerun recordings (.rrd) of single cases: the image, detections, identities, predictions, numbers.

Draws arrays and query results only; never calls back into ``jobs``.  Imports rerun (the replay commands
import this module when they record).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rerun as rr


def open_recording(path: Path | str, app_id: str = "dualsight"):
    """A rerun recording stream that saves to ``path``."""
    rec = rr.RecordingStream(app_id)
    rec.save(str(path))
    return rec


def _display(image: np.ndarray) -> np.ndarray:
    """Stretch a raw frame to 8 bits for viewing (sqrt stretch of the 99.9th percentile)."""
    img = np.asarray(image, dtype=np.float32)
    hi = float(np.percentile(img, 99.9)) or float(img.max()) or 1.0
    return (np.sqrt(np.clip(img / hi, 0, 1)) * 255).astype(np.uint8)


def log_attitudes(rec, attitudes: dict[str, np.ndarray | None]):
    """Log attitudes as the camera's three axes in the inertial frame (Arrows3D, unit length).

    attitudes : {name: (3, 3) DCM A (inertial -> camera; its rows are the camera axes in the inertial
    frame) or None}; entity ``attitude/<name>``, arrows x red, y green, z (boresight) blue.
    """
    for name, A in attitudes.items():
        if A is not None and np.all(np.isfinite(A)):
            rec.log(f"attitude/{name}", rr.Arrows3D(vectors=np.asarray(A, dtype=np.float64).reshape(3, 3),
                                                    colors=[[240, 60, 60], [40, 220, 40], [80, 140, 255]],
                                                    labels=[f"{name} x", f"{name} y", f"{name} z"]))


def log_scalars(rec, scalars: dict[str, float | None]):
    """Log finite numbers as time series ``metrics/<name>`` (plotted along the recording's time lines)."""
    for k, v in scalars.items():
        if v is not None and np.isfinite(v):
            rec.log(f"metrics/{k}", rr.Scalars(float(v)))


def log_star_case(rec, *, image: np.ndarray, det_xy: np.ndarray, det_labels: list[str], det_ok: np.ndarray,
                  pred_xy: np.ndarray, pred_labels: list[str], truth_xy: np.ndarray, info_md: str,
                  frame: int = 0, attitudes: dict | None = None, scalars: dict | None = None):
    """Log one star-tracker case.

    image : (H, W) raw frame.  det_xy : (K, 2) centroids (col, row; top-left corner convention).
    det_labels : (K,) "HIP <id> V<mag>" of identified detections.
    det_ok : (K,) bool, identity accepted and right (green) / otherwise (red).
    pred_xy : (M, 2) catalog stars projected with the *estimated* attitude (predicted positions).
    truth_xy : (G, 2) catalog stars projected with the true attitude (generated stars).
    attitudes : {"true": A, "estimated": A} (:func:`log_attitudes`).  scalars : numbers (:func:`log_scalars`).
    """
    rec.set_time("frame", sequence=frame)
    log_attitudes(rec, attitudes or {})
    log_scalars(rec, scalars or {})
    rec.log("camera/image", rr.Image(_display(image)))
    green, red, blue, yellow = [40, 220, 40], [240, 60, 60], [80, 140, 255], [250, 210, 40]
    if len(truth_xy):
        rec.log("camera/image/truth", rr.Points2D(truth_xy, radii=6.0, colors=[blue]))
    if len(det_xy):
        colors = np.where(np.asarray(det_ok)[:, None], green, red).astype(np.uint8)
        rec.log("camera/image/detections", rr.Points2D(det_xy, radii=3.0, colors=colors, labels=det_labels))
    if len(pred_xy):
        rec.log("camera/image/predicted", rr.Points2D(pred_xy, radii=9.0, colors=[yellow], labels=pred_labels))
    rec.log("case", rr.TextDocument(info_md, media_type=rr.MediaType.MARKDOWN))


def log_prox_frame(rec, *, image: np.ndarray, cob_xy, axes: np.ndarray | None, blob_mask: np.ndarray | None,
                   true_xy, info_md: str, scalars: dict[str, float], frame: int = 0,
                   positions: dict[str, np.ndarray] | None = None):
    """Log one proximity frame: image, blob, centre of brightness, principal axes, numbers.

    axes : (2, 2, 2) line segments (major, minor) through the COB, in pixels, or None.
    positions : {name: (3,) target position in the camera frame (m)}, logged as ``scene/<name>``
        points (true and each estimator's), so a trajectory's frames trace both paths on the time line.
    """
    rec.set_time("frame", sequence=frame)
    colors = {"true": [80, 140, 255], "paper": [250, 210, 40], "subpixel": [40, 220, 40]}
    for name, p in (positions or {}).items():
        if p is not None and np.all(np.isfinite(p)):
            rec.log(f"scene/{name}", rr.Points3D([np.asarray(p, dtype=np.float64)], radii=0.02,
                                                 colors=[colors.get(name, [200, 200, 200])], labels=[name]))
    rec.log("camera/image", rr.Image(_display(image)))
    if blob_mask is not None:
        rec.log("camera/image/blob", rr.SegmentationImage(blob_mask.astype(np.uint8)))
    if cob_xy is not None and np.all(np.isfinite(cob_xy)):
        rec.log("camera/image/cob", rr.Points2D([cob_xy], radii=4.0, colors=[[250, 210, 40]], labels=["COB"]))
    if true_xy is not None and np.all(np.isfinite(true_xy)):
        rec.log("camera/image/true_centre", rr.Points2D([true_xy], radii=4.0, colors=[[80, 140, 255]],
                                                        labels=["truth"]))
    if axes is not None and np.all(np.isfinite(axes)):
        rec.log("camera/image/axes", rr.LineStrips2D(axes, colors=[[240, 60, 60], [40, 220, 40]]))
    log_scalars(rec, scalars)
    rec.log("case", rr.TextDocument(info_md, media_type=rr.MediaType.MARKDOWN))


def log_image_case(rec, *, image: np.ndarray | None, points: np.ndarray, labels: list[str], info_md: str,
                   frame: int = 0):
    """Log a real-image case: the frame (when readable), its detections (K, 2) px with labels, the row as text."""
    rec.set_time("frame", sequence=frame)
    if image is not None:
        rec.log("camera/image", rr.Image(_display(image)))
    if len(points):
        rec.log("camera/image/detections", rr.Points2D(points, radii=4.0, colors=[[40, 220, 40]],
                                                       labels=labels or None))
    rec.log("case", rr.TextDocument(info_md, media_type=rr.MediaType.MARKDOWN))


def circles(centres: np.ndarray, radii: np.ndarray, n: int = 32) -> np.ndarray:
    """(P, n + 1, 2) closed polygons of ``n`` sides around ``centres`` (P, 2) px with ``radii`` (P,) px."""
    a = np.linspace(0.0, 2.0 * np.pi, n + 1)
    ring = np.stack([np.cos(a), np.sin(a)], axis=-1)                                  # (n + 1, 2)
    return np.asarray(centres, np.float64)[:, None, :] + np.asarray(radii, np.float64)[:, None, None] * ring


def log_track_frame(rec, *, frame: int, image: np.ndarray | None, det_xy: np.ndarray, det_labels: list[str],
                    det_used: np.ndarray, windows_xy: np.ndarray | None, windows_r: np.ndarray | None,
                    truth_xy: np.ndarray, mode_text: str, info_md: str, attitudes: dict | None = None,
                    scalars: dict | None = None):
    """Log one frame of a star-tracking sequence at ``frame`` on the ``frame`` time line.

    image : (H, W) raw frame or None (a dropped frame).  det_xy : (K, 2) centroids (col, row; top-left corner
    convention); det_labels : (K,) "HIP <id>" of the detections in the answer, "" otherwise; det_used : (K,) bool
    (green / grey).  windows_xy, windows_r : (P, 2) predicted positions and (P,) match-window radii (px) of tracking
    (``nav.tracking.Prediction``), drawn as yellow circles, or None where tracking did not run.  truth_xy : (G, 2)
    catalog stars at the true attitude (blue).  mode_text : the mode as a line of ``mode`` (TextLog).
    attitudes : {"true": A, "estimated": A or None} (:func:`log_attitudes`).  scalars : numbers (:func:`log_scalars`).
    Entities of an earlier frame that this frame lacks are cleared, so that the time line never shows a stale one.
    """
    rec.set_time("frame", sequence=frame)
    log_attitudes(rec, attitudes or {})
    for name, A in (attitudes or {}).items():
        if A is None or not np.all(np.isfinite(A)):
            rec.log(f"attitude/{name}", rr.Clear(recursive=False))
    log_scalars(rec, scalars or {})
    if image is not None:
        rec.log("camera/image", rr.Image(_display(image)))
    else:
        rec.log("camera/image", rr.Clear(recursive=True))
    green, grey, blue, yellow = [40, 220, 40], [150, 150, 150], [80, 140, 255], [250, 210, 40]
    if len(truth_xy):
        rec.log("camera/image/truth", rr.Points2D(truth_xy, radii=6.0, colors=[blue]))
    else:
        rec.log("camera/image/truth", rr.Clear(recursive=False))
    if len(det_xy):
        colors = np.where(np.asarray(det_used, bool)[:, None], green, grey).astype(np.uint8)
        rec.log("camera/image/detections", rr.Points2D(det_xy, radii=3.0, colors=colors, labels=det_labels))
    else:
        rec.log("camera/image/detections", rr.Clear(recursive=False))
    if windows_xy is not None and len(windows_xy):
        rec.log("camera/image/windows", rr.LineStrips2D(circles(windows_xy, windows_r), colors=[yellow]))
    else:
        rec.log("camera/image/windows", rr.Clear(recursive=False))
    rec.log("mode", rr.TextLog(mode_text))
    rec.log("case", rr.TextDocument(info_md, media_type=rr.MediaType.MARKDOWN))
