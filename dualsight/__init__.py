"""dualsight: end-to-end test bench for a dual-use small-satellite camera.

The import package's sub-packages live in the repository's top-level folders
(``scene/``, ``nav/``, ``kernels/``, ``catalogs/``, ``jobs/``, ``warehouse/``,
``viz/``), mapped by ``package-dir`` in ``pyproject.toml``.  This folder holds
the root package: errors, configuration, code version, allocator setting and
the Python API (``api.py``, docs/api.md).

The API's names are reachable from the root: ``dualsight.solve``,
``dualsight.Lake``, ``dualsight.run`` and the types they return
(``Solution``, ``Star``, ``Timings``, ``RunRecord``).  This facade is the one
deliberate place where the root package names things defined elsewhere
(``dualsight/api.py``, ``warehouse/lake.py``).  They are resolved on first use
by the module ``__getattr__`` below (PEP 562), never at import: every
``import dualsight.kernels.x`` runs this file first, and the kernels must not
pull in the engine, the lake or the catalogs.
"""

import importlib

__version__ = "0.1.0"

from dualsight import allocator as _allocator

_allocator.tune()

_FACADE = {
    "solve": "dualsight.api",
    "Solution": "dualsight.api",
    "Star": "dualsight.api",
    "Timings": "dualsight.api",
    "Lake": "dualsight.api",
    "run": "dualsight.api",
    "RunRecord": "dualsight.warehouse.lake",
}
"""Facade name -> the module that defines it."""

__all__ = ["__version__", *_FACADE]


def __getattr__(name: str):
    """A facade name, imported from its module on first use (then kept in this module's namespace)."""
    module = _FACADE.get(name)
    if module is None:
        raise AttributeError(f"module 'dualsight' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
