"""dualsight.allocator: frame-sized temporaries reuse the process's pages instead of faulting in new ones.

Counted, not timed: the minor page faults (``getrusage``) of a loop that makes and drops three 1024 x 768
float32 temporaries per iteration, in a fresh process.  Untuned glibc maps each one anew (3 x 768 pages
of first touches per iteration, measured 2272); after ``import dualsight`` none fault.
"""

import json
import subprocess
import sys
import textwrap

import pytest

LOOP = textwrap.dedent("""
    import resource, sys
    import numpy as np
    if sys.argv[1] == "1":
        import dualsight  # noqa: F401  (tunes the allocator)
    a = np.ones((768, 1024), np.uint16)
    def step():
        f = a.astype(np.float32); g = f + 1.0; h = np.empty_like(f); np.subtract(g, f, out=h)
        return float(h[0, 0])
    for _ in range(3):
        step()
    r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(20):
        step()
    print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0) / 20)
""")

PAGES = 768 * 1024 * 4 // 4096        # one float32 frame


def faults(import_dualsight: bool, env_tune: str | None = None) -> float:
    import os
    env = dict(os.environ)
    env.pop("DUALSIGHT_MALLOC_TUNE", None)
    if env_tune is not None:
        env["DUALSIGHT_MALLOC_TUNE"] = env_tune
    r = subprocess.run([sys.executable, "-c", LOOP, "1" if import_dualsight else "0"], capture_output=True,
                       text=True, env=env, check=True)
    return float(r.stdout.strip())


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt: Linux only")
def test_frame_temporaries_do_not_fault_after_import():
    untuned = faults(False)
    if untuned < PAGES:
        pytest.skip(f"this libc already reuses the pages ({untuned:.0f} faults per step)")
    assert untuned >= 2 * PAGES                        # fresh pages for (at least) two of the three temporaries
    assert faults(True) < 0.05 * PAGES                 # reused: no first touches
    assert faults(True, env_tune="0") >= 2 * PAGES     # the opt-out leaves glibc as it is


THRESHOLDS = textwrap.dedent("""
    import ctypes, json, os
    os.environ["DUALSIGHT_MALLOC_TUNE"] = "0"
    from dualsight import allocator            # the package's import calls tune(): a no-op under the opt-out

    class MallInfo2(ctypes.Structure):
        _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                   "fsmblks", "uordblks", "fordblks", "keepcost")]

    libc = ctypes.CDLL(None)
    libc.mallinfo2.restype = MallInfo2
    libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
    libc.free.argtypes = [ctypes.c_void_p]
    N = 24 << 20                    # below the tuned mmap threshold (32 MiB), far above glibc's default (128 KiB)

    def malloc_counting_maps(n):
        before = libc.mallinfo2().hblks
        p = libc.malloc(n)
        return p, libc.mallinfo2().hblks - before

    out = {"opt_out": allocator.tune()}
    held, out["maps_untuned"] = malloc_counting_maps(N)   # kept: freeing it would raise glibc's own threshold
    allocator._done = None                               # the same process, now without the opt-out
    os.environ["DUALSIGHT_MALLOC_TUNE"] = "1"
    out["tuned"] = allocator.tune()
    out["again"] = allocator.tune()
    p, out["maps_tuned"] = malloc_counting_maps(N)
    libc.free(p)
    out["top_kept"] = libc.mallinfo2().keepcost          # the freed block at the heap's top: returned or kept
    libc.free(held)
    print(json.dumps(out))
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt: Linux only")
def test_tune_reports_and_changes_glibcs_thresholds():
    """tune() reports True once glibc took both thresholds, and they act (mallinfo2, in a fresh process): a 24 MiB
    block, mmapped before tune(), comes from the heap after it (mmap threshold 32 MiB), and freeing it at the
    heap's top keeps the memory in the process (trim threshold 512 MiB) instead of returning it to the kernel."""
    import ctypes

    if not hasattr(ctypes.CDLL(None), "mallinfo2"):
        pytest.skip("no mallinfo2 (glibc < 2.33)")
    r = subprocess.run([sys.executable, "-c", THRESHOLDS], capture_output=True, text=True, check=True)
    out = json.loads(r.stdout)
    assert out["opt_out"] is False
    if out["maps_untuned"] != 1:
        pytest.skip(f"this libc does not mmap a 24 MiB block by default ({out})")
    assert out["tuned"] is True and out["again"] is True, out      # reported, and once per process
    assert out["maps_tuned"] == 0, out                              # the mmap threshold moved above 24 MiB
    assert out["top_kept"] >= 24 << 20, out                         # the trim threshold moved above 24 MiB
