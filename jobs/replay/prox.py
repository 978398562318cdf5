"""Replay a proximity case bit-identically (rerun recording) and write trajectory videos."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from dualsight.errors import InputError, output_path
from dualsight.jobs.replay.cases import recompute_case
from dualsight.viz.recording import log_prox_frame, open_recording
from dualsight.warehouse.lake import Lake


def replay_prox_case(lake: Lake, run_id: str, case_id: int, output: Path | None = None, rec=None) -> Path:
    """Re-render a proximity case, verify it against its row (image digest and every metric), and log it
    into ``rec`` (an open recording) or a new recording at ``output``."""
    from dualsight.jobs.kinds import prox                     # Taichi

    _, spec, ctx, out, fresh = recompute_case(lake, run_id, case_id, prox, "prox_cases",
                                              ("prox_sweep", "prox_trajectory"))
    res = out["results"]["paper"]
    img = out["images"][0]
    cam = spec.satellite.camera.camera
    true_px, _ = cam.project(out["draw"]["poses"].t_body)
    axes = None
    if res.found[0]:
        c = res.cob_px[0]
        a = res.angle_rad[0]
        u = np.array([math.cos(a), math.sin(a)])
        v = np.array([-u[1], u[0]])
        axes = np.array([[c - u * res.major_px[0] / 2, c + u * res.major_px[0] / 2],
                         [c - v * res.minor_px[0] / 2, c + v * res.minor_px[0] / 2]])
    info = "\n".join([
        f"# proximity case {case_id} of run `{run_id}` ({spec.job}, renderer {spec.mode})", "",
        f"- true range: {fresh['true_range_m']:.4f} m", f"- blob pixels: {fresh['n_pixels']}, "
        f"axis ratio {fresh['axis_ratio']:.3f}",
        f"- paper (Eq. 1): {fresh['paper_range_min_m']:.3f} / **{fresh['paper_range_est_m']:.3f}** / "
        f"{fresh['paper_range_max_m']:.3f} m (min / est / max)",
        f"- subpixel: {fresh['subpixel_range_min_m']:.3f} / **{fresh['subpixel_range_est_m']:.3f}** / "
        f"{fresh['subpixel_range_max_m']:.3f} m",
        f"- image digest: {fresh['image_digest']} (re-rendered frame = stored)", "",
        "Yellow: centre of brightness; blue: true body origin; red/green: major/minor axes.", "",
        "Replay reproduced the lake's row bit for bit."])
    output = Path(output or f"{run_id}-case{case_id}.rrd")
    own = rec is None
    rec = open_recording(output) if own else rec
    t_true = out["draw"]["poses"].t_body[0]
    positions = {"true": t_true} | {est: np.array([fresh[f"{est}_x_m"], fresh[f"{est}_y_m"], fresh[f"{est}_z_m"]],
                                                 dtype=float) for est in ("paper", "subpixel")}
    log_prox_frame(rec, image=img, cob_xy=res.cob_px[0], axes=axes, blob_mask=(img > 0), true_xy=true_px[0],
                   positions=positions,
                   info_md=info, scalars={"true_range_m": fresh["true_range_m"],
                                          "paper_range_m": fresh["paper_range_est_m"],
                                          "subpixel_range_m": fresh["subpixel_range_est_m"]}, frame=case_id)
    if own:
        rec.flush()
    return output


def write_trajectory_video(spec, path: Path, fps: float = 10.0, batch: int = 16) -> Path:
    """Render the trajectory's frames (same renderer, same poses as the run) into a video file."""
    import cv2

    from dualsight.jobs.kinds import prox

    ctx = prox.make_context(spec)
    cam = spec.satellite.camera.camera
    path = output_path(path)
    fourcc = cv2.VideoWriter_fourcc(*("mp4v" if path.suffix.lower() == ".mp4" else "MJPG"))
    writer = cv2.VideoWriter(str(path), fourcc, float(fps), (cam.width, cam.height), isColor=False)
    if not writer.isOpened():
        raise InputError("cannot write a video here (supported: .mp4, .avi)", source=str(path))
    try:
        for s in range(0, spec.frames, batch):
            ids = np.arange(s, min(s + batch, spec.frames), dtype=np.int64)
            imgs = prox.compute_batch(spec, ctx, ids, keep_images=True)["images"]
            hi = max(float(imgs.max()), 1e-9)
            for im in imgs:  # one write call per frame: the encoder takes frames one at a time
                writer.write(np.clip(im / hi * 255.0, 0, 255).astype(np.uint8))
    finally:
        writer.release()
    return path
