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
(``dualsight/api.py``, ``warehouse/lake.py``, ``dualsight/version.py``).  They are resolved on first use
by the module ``__getattr__`` below (PEP 562), never at import: every
``import dualsight.kernels.x`` runs this file first, and the kernels must not
pull in the engine, the lake or the catalogs.
"""

import importlib
import os as _os

from dualsight import allocator as _allocator

# Process settings, before any module imports taichi: no banner on stdout (it would corrupt --json output),
# no version check over the network.  Taichi itself starts lazily at the first kernel call.
_os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")
_os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "False")
# BLAS/OpenMP pools: one thread unless the user says otherwise (set before numpy loads its BLAS; a script that
# imported numpy first keeps numpy's pool).  dualsight's BLAS calls are 3x3 SVDs and small products, where a pool
# gains nothing and its threads compete for cores that Taichi's threads and the engine's workers already use
# (benchmarks/bench_thread_pools.py); one thread also keeps BLAS sums in one order, run after run.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")
_allocator.tune()

_FACADE = {
    "__version__": "dualsight.version",
    "solve": "dualsight.api",
    "Solution": "dualsight.api",
    "Star": "dualsight.api",
    "Timings": "dualsight.api",
    "Lake": "dualsight.api",
    "run": "dualsight.api",
    "RunRecord": "dualsight.warehouse.lake",
}
"""Facade name -> the module that defines it."""

__all__ = list(_FACADE)


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
