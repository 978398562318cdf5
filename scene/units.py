"""Angle units and the angle between directions: the one place the project defines them.

docs/architecture.md: SI units inside (radians), arcseconds and degrees only at the edges (reports, CLI, config
files, truth files).  Convert at the edge by multiplying with a constant (``20 * ARCSEC`` rad) or
dividing by it (``err_rad / ARCSEC`` arcsec); degrees also with ``np.radians`` / ``np.degrees``,
which use the same factor as :data:`DEG`.  Pure numpy, no project import.
"""

from __future__ import annotations

import numpy as np

__all__ = ["DEG", "ARCSEC", "MAS", "angle_between"]

DEG = np.pi / 180.0
"""One degree in radians."""
ARCSEC = np.pi / (180.0 * 3600.0)
"""One arcsecond in radians (4.848e-6)."""
MAS = np.pi / (180.0 * 3600.0 * 1000.0)
"""One milliarcsecond in radians (Hipparcos proper motions are in mas/yr)."""


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (rad, in [0, pi]) between directions: ``atan2(|a x b|, a . b)``.

    Parameters
    ----------
    a, b : (..., 3) vectors (any length, not necessarily unit; broadcast against each other).

    Returns
    -------
    (...,) float64 angles in radians.

    Accurate to rounding at every angle, unlike ``acos(a . b)`` (which loses ~1e-8 rad near 0 and
    pi, where its argument is flat) or the chord ``2 asin(|a - b| / 2)`` (which needs unit vectors
    and loses precision near pi).  The components are written out (no ``np.cross`` /
    ``np.linalg.norm`` call overhead); the result is bit for bit ``np.arctan2(np.linalg.norm(
    np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))``.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    cx = a1 * b2 - a2 * b1
    cy = a2 * b0 - a0 * b2
    cz = a0 * b1 - a1 * b0
    return np.arctan2(np.sqrt(cx * cx + cy * cy + cz * cz), a0 * b0 + a1 * b1 + a2 * b2)
