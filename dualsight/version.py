"""The code version that is part of every run's identity.

``code_version()`` is ``<package version>+<12 hex digits>``: the digits are a SHA-256 over the source
files (``*.py`` and ``*.sql``) of every ``dualsight`` sub-package, in sorted order.  Two processes give the
same value exactly when they run the same code, so a run started with one build is never resumed, or
completed on a cluster worker, by another.  Computed once per process (~10 ms).
"""

from __future__ import annotations

import functools
import hashlib
from importlib import import_module
from pathlib import Path

__version__ = "0.1.0"
"""The package version (as in pyproject.toml); ``dualsight.__version__`` names this."""

SUBPACKAGES = ("dualsight", "dualsight.scene", "dualsight.nav", "dualsight.kernels", "dualsight.catalogs",
               "dualsight.jobs", "dualsight.warehouse", "dualsight.viz")


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """``"0.1.0+1a2b3c4d5e6f"``: package version plus a hash of the package's source files."""
    h = hashlib.sha256()
    for name in SUBPACKAGES:
        folder = Path(import_module(name).__file__).parent
        for p in sorted(folder.rglob("*")):
            if p.suffix in (".py", ".sql") and "__pycache__" not in p.parts:
                h.update(f"{name}/{p.relative_to(folder).as_posix()}\0".encode())
                h.update(p.read_bytes())
                h.update(b"\0")
    return f"{__version__}+{h.hexdigest()[:12]}"
