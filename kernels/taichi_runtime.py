"""Lazy, once-per-process Taichi initialisation on the CPU backend.

Taichi is never initialised at import time.  The first kernel call in a
process calls :func:`ensure_init`, which sets ``TI_SKIP_VERSION_CHECK`` and an
explicit offline-cache folder and then calls ``ti.init(arch=ti.cpu)`` once.
Worker processes must be *spawned* (a fork of an initialised runtime hangs).

Environment:
    DUALSIGHT_TI_CACHE    offline kernel cache folder (default ~/.cache/dualsight/taichi)
    DUALSIGHT_TI_THREADS  CPU threads Taichi may use in this process (default: all cores)
    DUALSIGHT_TI_LAUNCHER ``fast`` (default): kernels are called through :class:`FastKernel`; ``taichi``:
                          always through Taichi's own launcher (for comparison, or should a Taichi release
                          change the internals FastKernel uses)
"""

from __future__ import annotations

import contextlib
import io
import os
import threading
from ctypes import addressof as _addressof, c_char as _c_char
from pathlib import Path

import numpy as np

#: Taichi 1.7's CPU backend hands a range-for to its thread pool in tasks of at least 512 consecutive
#: iterations (its adaptive block size, min(1024, max(512, n / (32 threads))); ``loop_config(block_dim=)``
#: does not lower it), so a loop of fewer than 1024 iterations runs on ONE thread.  A loop that must
#: spread a few long work items (e.g. one per thread) over the cores runs ``range(items * TASK_ITEMS)``
#: and works only where ``t % TASK_ITEMS == 0``: one item per task.  Measured in
#: ``benchmarks/bench_taichi_threads.py``.
TASK_ITEMS = 512


def task_stride(n: int) -> int:
    """Stride that spreads a kernel loop of ``n`` long work items over the thread pool: TASK_ITEMS when
    n < 2 TASK_ITEMS (else one task would hold them all), 1 otherwise (the loop is split already).  The
    kernel runs ``for t in range(n * stride)`` and works where ``t % stride == 0`` on item ``t // stride``."""
    return TASK_ITEMS if 1 < n < 2 * TASK_ITEMS else 1

_lock = threading.Lock()
_initialised = False


def cache_dir() -> Path:
    """Folder of Taichi's offline kernel cache."""
    env = os.environ.get("DUALSIGHT_TI_CACHE")
    if env:
        return Path(env)
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "dualsight" / "taichi"


def ensure_init(threads: int | None = None):
    """Initialise Taichi (CPU) once in this process and return the module.

    Parameters
    ----------
    threads : optional cap on Taichi's CPU threads; only honoured by the first
        call in a process (``DUALSIGHT_TI_THREADS`` overrides it).
    """
    global _initialised
    os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")
    import taichi as ti

    if _initialised:
        return ti
    with _lock:
        if _initialised:
            return ti
        cdir = cache_dir()
        cdir.mkdir(parents=True, exist_ok=True)
        kwargs = dict(arch=ti.cpu, offline_cache=True, offline_cache_file_path=str(cdir),
                      log_level=ti.WARN, default_fp=ti.f32, random_seed=0)
        env_threads = os.environ.get("DUALSIGHT_TI_THREADS")
        if env_threads:
            threads = int(env_threads)
        if threads:
            kwargs["cpu_max_num_threads"] = int(threads)
        with contextlib.redirect_stdout(io.StringIO()):   # ti.init prints "[Taichi] Starting on arch=..."
            ti.init(**kwargs)
        _initialised = True
    return ti


def is_initialised() -> bool:
    return _initialised


class KernelCache:
    """Kernels built lazily, once per (name, dtype, variant) per process, from a table of builder functions.

    ``builders`` maps a name to ``builder(dtype) -> kernel``; it may be filled after the cache is made
    (builders are usually defined below it in their module).  :meth:`get` starts Taichi on first use.
    A builder that also takes ``serial=True`` has a serial variant (its loops under
    ``ti.loop_config(serialize=True)``), for calls too small to pay for the parallel launch: every launch
    of a parallel loop is a round trip through Taichi's thread pool, ~0.1 ms on a 2-core VM whatever the
    thread count (a 2-argument kernel: 30-40 us with a serial loop, 110-150 us with a parallel one;
    ``benchmarks/bench_taichi_threads.py``), more than the work of the small kernels on one frame.
    """

    def __init__(self, builders: dict | None = None):
        self.builders = builders if builders is not None else {}
        self._built: dict = {}
        self._lock = threading.Lock()

    def get(self, name: str, dtype=None, serial: bool = False):
        key = (name, None if dtype is None else np.dtype(dtype).str, bool(serial))
        k = self._built.get(key)
        if k is None:
            with self._lock:
                k = self._built.get(key)
                if k is None:
                    ensure_init()
                    k = self.builders[name](dtype, serial=True) if serial else self.builders[name](dtype)
                    if os.environ.get("DUALSIGHT_TI_LAUNCHER", "fast") != "taichi":
                        k = FastKernel(k)
                    self._built[key] = k
        return k


class FastKernel:
    """A Taichi kernel called through a shorter launcher (what :meth:`KernelCache.get` returns).

    Taichi 1.7's Python launcher (``Kernel.__call__``) spends ~10 us per numpy-array argument (template
    lookup, a type dispatch per argument, ``ndarray.ctypes``) before the launch itself: ~130 us for a kernel
    of 10 arrays on this VM, more than the kernel's own work on one frame.  The first call with an argument
    *signature* (each array's dtype and ndim, each scalar's Python type) goes through Taichi's launcher,
    which compiles, type-checks and raises Taichi's own errors; the compiled kernel and one setter per
    argument are then kept, and later calls with that signature set the arguments on a launch context and
    launch it directly (~30 us for 10 arrays; ``benchmarks/bench_taichi_threads.py``).  The kernel sees the
    very same arguments either way.  Calls the plan does not cover (keyword arguments, an array that is
    not C-contiguous, a Taichi ndarray or field, a kernel with a return value, autodiff) use Taichi's launcher.
    """

    __slots__ = ("kernel", "_plans")

    def __init__(self, kernel):
        self.kernel = kernel
        self._plans: dict = {}

    def __call__(self, *args):
        sig = _signature(args)
        plan = self._plans.get(sig) if sig is not None else False
        if plan is None:                                 # first call with this signature: Taichi's launcher
            out = self.kernel(*args)
            self._plans[sig] = _plan(self.kernel, args)
            return out
        if plan is False:
            return self.kernel(*args)
        t_kernel, setters, prog = plan
        ctx = t_kernel.make_launch_context()
        for i, a in enumerate(args):
            setters[i](ctx, (i,), a)
        prog.launch_kernel(prog.compile_kernel(prog.config(), prog.get_device_caps(), t_kernel), ctx)
        return None


_SCALARS = (int, float, bool)


def _signature(args) -> tuple | None:
    """The plan key of a call: (dtype number, ndim) per C-contiguous numpy array, the type of each Python or
    numpy scalar; None when an argument is anything else."""
    sig = []
    for a in args:
        t = type(a)
        if t is np.ndarray:
            if not a.flags.c_contiguous:
                return None
            sig.append((a.dtype.num, a.ndim))
        elif t in _SCALARS or isinstance(a, (np.integer, np.floating)):
            sig.append(t)
        else:
            return None
    return tuple(sig)


def _set_array(ctx, idx, a):
    try:         # the data address through the buffer protocol: ~0.3 us against ~1 us for ``a.ctypes.data``
        ptr = _addressof(_c_char.from_buffer(a))       # (~85 arrays per frame)
    except (TypeError, ValueError):                    # read-only or empty arrays
        ptr = a.ctypes.data
    ctx.set_arg_external_array_with_shape(idx, ptr, a.nbytes, a.shape, 0)


def _set_float(ctx, idx, v):
    ctx.set_arg_float(idx, float(v))


def _set_int(ctx, idx, v):
    ctx.set_arg_int(idx, int(v))


def _set_uint(ctx, idx, v):
    ctx.set_arg_uint(idx, int(v))


def _plan(kernel, args):
    """(compiled Taichi kernel, setter per argument, program) for calls like ``args`` (just launched by
    Taichi), or False when the short launcher does not cover the kernel or its arguments (see
    :class:`FastKernel`).  Uses Taichi 1.7's launcher internals, each checked (anything unexpected: False)."""
    try:
        from taichi.lang import impl
        from taichi.lang.enums import AutodiffMode
        from taichi.lang.util import cook_dtype
        from taichi.types import ndarray_type, primitive_types
        from taichi.types.utils import is_signed

        primal = kernel._primal
        if (primal.autodiff_mode != AutodiffMode.NONE or primal.return_type is not None or primal.has_print
                or len(primal.arguments) != len(args)):
            return False
        setters = []
        for a, arg in zip(args, primal.arguments):
            anno = arg.annotation
            if isinstance(anno, ndarray_type.NdarrayType):
                if not (anno.dtype is None or id(anno.dtype) in primitive_types.type_ids):   # (a: a numpy array)
                    return False
                setters.append(_set_array)
            elif id(anno) in primitive_types.real_type_ids:
                setters.append(_set_float)
            elif id(anno) in primitive_types.integer_type_ids:
                setters.append(_set_int if is_signed(cook_dtype(anno)) else _set_uint)
            else:
                return False
        key = primal.ensure_compiled(*args)
        return primal.compiled_kernels[key], tuple(setters), impl.get_runtime().prog
    except Exception:                                   # another Taichi version's internals: its own launcher
        return False
