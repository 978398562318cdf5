"""The engine's own errors, importable without the engine (the command line's SIGTERM handler raises
:class:`Interrupted`; the Dask executor raises :class:`EngineError`)."""

from __future__ import annotations

from dualsight.errors import InputError

__all__ = ["EngineError", "Interrupted"]


class EngineError(InputError):
    """A run could not go on (a worker died repeatedly, the scheduler went away, a shard failed)."""


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM reached the coordinating process."""
