"""Keep freed frame-sized buffers in the process instead of returning them to the kernel.

glibc's ``malloc`` serves every request above its mmap threshold (128 KiB at start, rising adaptively only
after such a block is freed) with a fresh ``mmap``, and ``free`` unmaps it: the next array of that size
starts again on untouched pages, and on this project's VMs each first touch of a 4 KiB page costs ~1.5 us
of kernel time.  A 1024 x 768 float32 frame is 768 pages: ~1.2 ms of page faults every time a
temporary of that size is made, more than the arithmetic on it (measured in ``kernels/background.py``'s
chain: 6 ms per frame with fresh pages, 0.8 ms with reused ones).

:func:`tune` raises the mmap threshold to glibc's maximum (32 MiB on 64-bit: blocks below it come from
the heap and are reused after ``free``) and the trim threshold to 512 MiB (the heap's top is returned to
the kernel only when that much is free).  Resident memory then stays at the process's peak rather than
falling back after each temporary; the peak itself does not change.  Called once per process by the
package's import (workers are spawned and import it too); a no-op where ``mallopt`` is not glibc's
(macOS, musl) or when ``DUALSIGHT_MALLOC_TUNE=0``.
"""

from __future__ import annotations

import ctypes
import os

__all__ = ["tune", "MMAP_THRESHOLD", "TRIM_THRESHOLD"]

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3                   # glibc <malloc.h>
MMAP_THRESHOLD = 32 * 1024 * 1024                             # glibc's DEFAULT_MMAP_THRESHOLD_MAX (64-bit)
TRIM_THRESHOLD = 512 * 1024 * 1024

_done: bool | None = None


def tune() -> bool:
    """Set the thresholds once per process; True when glibc accepted both (False: unchanged)."""
    global _done
    if _done is not None:
        return _done
    _done = False
    if os.environ.get("DUALSIGHT_MALLOC_TUNE", "1") == "0":
        return False
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):          # no C library by that name (Windows), no mallopt
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    _done = bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
    return _done
