"""Where a camera points, in the words of an observer: boresight RA/Dec and roll (position angle).

Roll convention (the HIL star report's): the position angle of the image's "up" direction (camera -y,
decreasing row) at the boresight, measured from celestial north through east, in [0, 360) deg.  A sky
image is not mirrored, so with roll 0 north is up and east is to the left.

numpy only.
"""

from __future__ import annotations

import numpy as np

__all__ = ["roll_deg"]


def roll_deg(A: np.ndarray) -> np.ndarray:
    """Roll (deg, [0, 360)) of (..., 3, 3) ICRS -> camera matrices: position angle of the image's "up"
    (camera -y) at the boresight, from celestial north through east (module docstring)."""
    A = np.asarray(A, dtype=np.float64)
    z = A[..., 2, :]
    up = -A[..., 1, :]
    east = np.cross(np.array([0.0, 0.0, 1.0]), z)
    east /= np.linalg.norm(east, axis=-1, keepdims=True)
    north = np.cross(z, east)
    return np.mod(np.degrees(np.arctan2(np.sum(up * east, -1), np.sum(up * north, -1))), 360.0)
