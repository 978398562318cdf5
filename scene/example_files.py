"""Relative file names in specs and presets that name the repository's own files (``examples/...``).

A preset says ``examples/satellites/cubesat_3u.toml`` or ``examples/cameras/paper_prox.toml``; read from the
working folder alone, such a name works only from the checkout's top folder.  :func:`shipped_path` keeps the
user's file first (an absolute path, or one that exists from the working folder) and otherwise looks the name up
under the repository's top folder, so a preset runs from any folder.  The spec keeps the name as written.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["REPOSITORY", "shipped_path"]

REPOSITORY = Path(__file__).resolve().parents[1]
"""The folder that holds ``examples/`` beside the package's folders (a source checkout)."""


def shipped_path(path: str | Path) -> Path:
    """``path`` as given when it is absolute or exists from the working folder; else the repository's file of that
    relative name when there is one; else ``path`` as given (reading it then names it as not found)."""
    p = Path(path)
    if p.is_absolute() or p.exists():
        return p
    q = REPOSITORY / p
    return q if q.is_file() else p
