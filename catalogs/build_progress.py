"""A progress bar on stderr for a long catalog build: the engine's bar (jobs/engine/runner.py: tqdm on stderr,
the same smoothing and refresh interval), shown only when the build is expected to take longer than
:data:`PROGRESS_AFTER_S`.

``enabled=None`` (the default of the builders) shows it when expected to last longer than that and stderr is a
terminal (tqdm's ``disable=None``), so logs and captured output stay one line per message; True forces it, False
hides it.  The builders advance it by whole chunks (pairs routed, sorted or derived), never per star.
"""

from __future__ import annotations

import sys

from tqdm import tqdm

__all__ = ["PROGRESS_AFTER_S", "NullBar", "build_bar"]

PROGRESS_AFTER_S = 2.0
"""A build expected to take longer than this (s) shows a progress bar."""


class NullBar:
    """The bar of a short build: every call does nothing."""

    total = 0

    def update(self, n: int = 1) -> None:
        """Nothing."""

    def close(self) -> None:
        """Nothing."""


def build_bar(desc: str, total: int, expected_s: float, enabled: bool | None = None, unit: str = "pair"):
    """A tqdm bar (``desc``, ``total`` units of ``unit``) on stderr, or a :class:`NullBar` when ``enabled`` is
    False, or None and ``expected_s`` <= :data:`PROGRESS_AFTER_S`.  Close it when done."""
    if enabled is False or (enabled is None and expected_s <= PROGRESS_AFTER_S):
        return NullBar()
    return tqdm(total=max(int(total), 1), desc=desc, unit=unit, unit_scale=True, dynamic_ncols=True,
                file=sys.stderr, smoothing=0.1, mininterval=0.5, disable=None if enabled is None else False)
