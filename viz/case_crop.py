"""A case's frame as a picture worth forwarding: a stretched crop with what the pipeline saw marked on it.

:func:`stretch` maps a frame to 8 bits so that the sky is dark grey (not black), faint stars and PSF wings show
and bright stars do not saturate: an asinh stretch from the sky level (median) to the 99.95th percentile, with
a softening scale of 5 noise sigma (1.4826 x MAD; a noise-free frame: 0.2 % of the range), Lupton et al. (2004,
PASP 116, 133) in one channel.  :func:`case_crop_png` crops the frame to the box around the marks (padded,
at least :data:`MIN_BOX` px), scales it to ``width`` px (block maximum when shrinking, so one-pixel stars stay,
nearest neighbour when enlarging) and draws, with OpenCV:

* detections: circles (green: identified right, orange: identified wrong, red: not identified);
* identified stars: their HIP number beside the circle;
* catalog positions predicted by the solved attitude: magenta crosses (x);
* catalog stars at the true attitude (simulations) or of an independent solution (real frames): cyan plus signs;
* a legend strip under the picture.

Pixel coordinates are continuous (col, row) from the image's top-left corner (docs/architecture.md): pixel (i, j)
spans [i, i+1), so a position x maps to the picture's ``(x - x0) * scale`` column.  Returns the PNG bytes and the
mapping with every drawn mark in picture pixels, so a test (or a reader) can check the marks against the lake.
Draws arrays only; never calls back into ``jobs``.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["MIN_BOX", "stretch", "crop_box", "case_crop_png"]

MIN_BOX = 96
"""Smallest side (px of the frame) of a crop: a lone star is shown with its surroundings."""

SKY_GREY = 0.16
"""Grey level of the sky (the frame's median) in the stretched picture: dark, not black."""

_GREEN, _ORANGE, _RED = (60, 220, 60), (0, 165, 255), (60, 60, 255)          # BGR
_MAGENTA, _CYAN, _WHITE = (240, 60, 240), (255, 220, 60), (235, 235, 235)


def stretch(image: np.ndarray) -> np.ndarray:
    """(H, W) frame -> (H, W) uint8: asinh stretch, sky (median) at :data:`SKY_GREY`, 99.95th percentile at white."""
    img = np.asarray(image, dtype=np.float32)
    sample = img[::2, ::2] if img.size > 4096 else img
    sky = float(np.median(sample))
    sig = 1.4826 * float(np.median(np.abs(sample - sky)))
    hi = float(np.percentile(img, 99.95))
    if hi <= sky:
        hi = float(img.max())
    span = max(hi - sky, 1e-6)
    soft = max(5.0 * sig, 2e-3 * span)
    v = np.arcsinh((img - sky) / soft) / math.asinh(span / soft)
    out = np.clip(SKY_GREY + (1.0 - SKY_GREY) * v, 0.0, 1.0)
    return (out * 255.0 + 0.5).astype(np.uint8)


def crop_box(shape: tuple[int, int], points: np.ndarray, pad: float = 24.0) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) integer pixel box of the frame holding every point ``points`` (N, 2) (col, row) with
    ``pad`` px around it, at least :data:`MIN_BOX` px a side (or the frame), inside the frame; the whole frame
    when there is no finite point."""
    H, W = shape
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    p = p[np.isfinite(p).all(1)]
    if not len(p):
        return 0, 0, W, H
    lo = np.floor(p.min(0) - pad)
    hi = np.ceil(p.max(0) + pad)
    for k, n in ((0, W), (1, H)):
        side = hi[k] - lo[k]
        want = min(n, max(side, MIN_BOX))
        c = 0.5 * (lo[k] + hi[k])
        lo[k], hi[k] = c - want / 2, c + want / 2
        shift = max(0.0, -lo[k]) - max(0.0, hi[k] - n)
        lo[k], hi[k] = max(0.0, lo[k] + shift), min(float(n), hi[k] + shift)
    return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])


def _scaled(u8: np.ndarray, width: int):
    """The crop ``u8`` (h, w) at ``width`` px wide; returns (picture, scale: picture px per frame px along x, y).

    Shrinking by f = ceil(w / width): each f x f block shows its mean, or its maximum where that maximum stands
    clearly above the block means around it (a star: one-pixel stars stay visible; the sky's noise is averaged,
    not brightened by taking the largest of f^2 noise values); then a nearest-neighbour resize to ``width``."""
    import cv2

    h, w = u8.shape
    f = max(1, int(math.ceil(w / width)))
    if f > 1:
        H_, W_ = -(-h // f) * f, -(-w // f) * f
        pad = np.full((H_, W_), np.median(u8), np.float32)
        pad[:h, :w] = u8
        blocks = pad.reshape(H_ // f, f, W_ // f, f)
        mean, peak = blocks.mean((1, 3)), blocks.max((1, 3))
        sky = float(np.median(mean))
        noise = max(1.4826 * float(np.median(np.abs(mean - sky))), 1.0)
        star = peak > sky + max(40.0, 10.0 * noise)
        u8 = np.where(star, peak, mean).astype(np.uint8)
    ph, pw = u8.shape
    out_w = width
    out_h = max(1, int(round(ph * out_w / pw)))
    pic = cv2.resize(u8, (out_w, out_h), interpolation=cv2.INTER_NEAREST)
    return pic, (out_w / pw) / f, (out_h / ph) / f


def case_crop_png(image: np.ndarray, *, detections: np.ndarray, det_state: np.ndarray | None = None,
                  det_labels: list[str] | None = None, predicted: np.ndarray | None = None,
                  reference: np.ndarray | None = None, reference_label: str = "catalog stars, true attitude",
                  width: int = 440, title: str = "") -> tuple[bytes, dict]:
    """Stretched crop of ``image`` (H, W) with the case's marks; returns (PNG bytes, marks).

    detections : (K, 2) centroids (col, row); det_state : (K,) int 0 not identified, 1 identified right,
        2 identified wrong (default all 0); det_labels : (K,) text beside each detection ("" for none);
    predicted : (P, 2) catalog positions by the solved attitude (crosses), or None;
    reference : (R, 2) catalog positions at the true attitude / an independent solution (plus signs), or None.
    marks : {"box": (x0, y0, x1, y1) frame px, "scale": (sx, sy) picture px per frame px, "size": (w, h) of the
    picture without the legend, "detections" / "predicted" / "reference": lists of [u, v] picture px, i.e.
    ``u = (x - x0) * sx``}.
    """
    import cv2

    det = np.asarray(detections, dtype=float).reshape(-1, 2)
    pred = np.asarray(predicted if predicted is not None else np.zeros((0, 2)), dtype=float).reshape(-1, 2)
    ref = np.asarray(reference if reference is not None else np.zeros((0, 2)), dtype=float).reshape(-1, 2)
    state = np.zeros(len(det), int) if det_state is None else np.asarray(det_state, int)
    labels = det_labels or [""] * len(det)
    H, W = np.asarray(image).shape[:2]
    inside = lambda p: p[np.isfinite(p).all(1) & (p[:, 0] >= 0) & (p[:, 0] < W) & (p[:, 1] >= 0) & (p[:, 1] < H)]  # noqa: E731
    pred, ref = inside(pred), inside(ref)
    x0, y0, x1, y1 = crop_box((H, W), np.concatenate([det, pred, ref]))
    pic, sx, sy = _scaled(stretch(np.asarray(image)[y0:y1, x0:x1]), width)
    ph, pw = pic.shape
    rgb = cv2.cvtColor(pic, cv2.COLOR_GRAY2BGR)
    to_px = lambda p: np.stack([(p[:, 0] - x0) * sx, (p[:, 1] - y0) * sy], 1) if len(p) else np.zeros((0, 2))  # noqa: E731
    d_px, p_px, r_px = to_px(det), to_px(pred), to_px(ref)
    r = 5
    for u, v in r_px:
        cv2.drawMarker(rgb, (int(round(u)), int(round(v))), _CYAN, cv2.MARKER_CROSS, 11, 1, cv2.LINE_AA)
    for u, v in p_px:
        cv2.drawMarker(rgb, (int(round(u)), int(round(v))), _MAGENTA, cv2.MARKER_TILTED_CROSS, 13, 2, cv2.LINE_AA)
    for (u, v), s, lab in zip(d_px, state, labels):
        c = {1: _GREEN, 2: _ORANGE}.get(int(s), _RED)
        cv2.circle(rgb, (int(round(u)), int(round(v))), r + 4, c, 2, cv2.LINE_AA)
        if lab:
            cv2.putText(rgb, lab, (int(round(u)) + r + 5, int(round(v)) - r - 2), cv2.FONT_HERSHEY_SIMPLEX, 0.36,
                        _WHITE, 1, cv2.LINE_AA)
    legend = [(_GREEN, "o", "detection, identified right"), (_ORANGE, "o", "identified wrong"),
              (_RED, "o", "detection, not identified"), (_MAGENTA, "x", "catalog, solved attitude"),
              (_CYAN, "+", reference_label)]
    shown = [(state == 1).any() or not len(det), (state == 2).any(), (state == 0).any(), len(p_px) > 0,
             len(r_px) > 0]
    legend = [e for e, on in zip(legend, shown) if on] or legend[:1]
    lh = 16
    strip = np.full((lh * ((len(legend) + 1) // 2) + 10 + (lh if title else 0), pw, 3), 250, np.uint8)
    yb = 4
    if title:
        cv2.putText(strip, title[:80], (6, yb + 11), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (30, 30, 30), 1, cv2.LINE_AA)
        yb += lh
    for k, (c, sym, text) in enumerate(legend):
        x, y = 8 + (k % 2) * (pw // 2), yb + (k // 2) * lh + 8
        if sym == "o":
            cv2.circle(strip, (x, y), 5, c, 2, cv2.LINE_AA)
        else:
            cv2.drawMarker(strip, (x, y), c, cv2.MARKER_TILTED_CROSS if sym == "x" else cv2.MARKER_CROSS, 10, 2)
        cv2.putText(strip, text, (x + 10, y + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.36, (30, 30, 30), 1, cv2.LINE_AA)
    ok, buf = cv2.imencode(".png", np.concatenate([rgb, strip], 0))
    marks = {"box": [x0, y0, x1, y1], "scale": [sx, sy], "size": [pw, ph],
             "detections": d_px.round(2).tolist(), "predicted": p_px.round(2).tolist(),
             "reference": r_px.round(2).tolist()}
    return buf.tobytes(), marks
