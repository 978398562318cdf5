"""dualsight.allocator: frame-sized temporaries reuse the process's pages instead of faulting in new ones.

Counted, not timed: the minor page faults (``getrusage``) of a loop that makes and drops three 1024 x 768
float32 temporaries per iteration, in a fresh process.  Untuned glibc maps each one anew (3 x 768 pages
of first touches per iteration, measured 2272); after ``import dualsight`` none fault.
"""

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


def test_tune_is_idempotent_and_reports():
    from dualsight import allocator

    first = allocator.tune()
    assert allocator.tune() is first
    assert isinstance(first, bool)
