"""What every figure of dualsight shares: matplotlib without a display (:func:`pyplot`: the Agg backend, set when
this module is imported), writing a figure to a file (:func:`save_figure`) or to PNG bytes (:func:`png_bytes`), and
a small PNG thumbnail of a frame (:func:`thumbnail_png`, OpenCV imported when it is called).  The figure modules
of viz import this one, so importing any of them imports matplotlib: the command line imports them when it draws.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")            # files only, never a window; before pyplot is imported
import matplotlib.pyplot as plt  # noqa: E402

from dualsight.errors import output_path  # noqa: E402

__all__ = ["pyplot", "save_figure", "png_bytes", "thumbnail_png"]


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend (files only, never a window)."""
    return plt


def save_figure(fig, path: Path, dpi: int = 110) -> Path:
    """Write ``fig`` as ``path`` (its folder must exist) and close it; returns the path."""
    try:
        path = output_path(path)
    except Exception:
        plt.close(fig)
        raise
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def png_bytes(draw) -> bytes:
    """Bytes of the PNG that ``draw(path)`` writes (to a temporary file)."""
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "f.png"
        draw(p)
        return p.read_bytes()


def thumbnail_png(image: np.ndarray, width: int = 280, centre=None, half: float | None = None) -> bytes:
    """A small 8-bit PNG of a frame ``image`` (H, W): max-pooled (so one-pixel stars stay visible), or with
    ``centre`` (x, y px) and ``half`` a crop of +-half px around it, enlarged; square-root stretch of the 99.9th
    percentile; ``width`` px wide."""
    import cv2

    img = np.asarray(image, dtype=np.float32)
    if centre is not None and half and np.all(np.isfinite(centre)):
        h = int(max(16, min(half, max(img.shape))))
        x0, y0 = int(centre[0]) - h, int(centre[1]) - h
        img = np.pad(img, h)[y0 + h: y0 + 3 * h, x0 + h: x0 + 3 * h]
        interp = cv2.INTER_NEAREST
    else:
        f = max(1, int(np.ceil(img.shape[1] / width)))
        H_, W_ = -(-img.shape[0] // f) * f, -(-img.shape[1] // f) * f
        img = np.pad(img, ((0, H_ - img.shape[0]), (0, W_ - img.shape[1]))).reshape(H_ // f, f, W_ // f, f).max((1, 3))
        interp = cv2.INTER_AREA
    hi = float(np.percentile(img, 99.9)) or float(img.max()) or 1.0
    u8 = (np.sqrt(np.clip(img / hi, 0, 1)) * 255).astype(np.uint8)
    height = max(1, round(u8.shape[0] * width / u8.shape[1]))
    ok, buf = cv2.imencode(".png", cv2.resize(u8, (width, height), interpolation=interp))
    return buf.tobytes()
