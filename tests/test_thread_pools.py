"""Thread pools sized to the cores a process may use (issue 24 point 2): BLAS/OpenMP pools default to one thread
in every dualsight process (set before numpy loads its BLAS) unless the user set them; spawned workers get their
share of the cores (cores // workers) for Taichi and OpenCV, and never more BLAS threads than the parent asked for."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from dualsight.jobs.engine.runner import worker_threads

SHOW = ("import dualsight, os, numpy, cv2\n"
        "print(os.environ['OPENBLAS_NUM_THREADS'], os.environ['OMP_NUM_THREADS'], cv2.getNumThreads())")


def _run(extra: dict) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                                                              "MKL_NUM_THREADS", "OPENCV_FOR_THREADS_NUM")}
    env.update(extra)
    return subprocess.run([sys.executable, "-c", SHOW], env=env, capture_output=True, text=True,
                          check=True).stdout.split()


def test_blas_pools_default_to_one_thread_and_respect_the_user():
    blas, omp, cv = _run({})
    assert (blas, omp) == ("1", "1")
    assert int(cv) == os.cpu_count()                 # in-process work may use every core
    assert _run({"OPENBLAS_NUM_THREADS": "3", "OMP_NUM_THREADS": "2"})[:2] == ["3", "2"]


@pytest.mark.parametrize("current, share, want", [(None, 2, 2), ("1", 2, 1), ("8", 2, 2), ("x", 3, 3), ("0", 2, 2),
                                                  (None, 1, 1), ("4", 4, 4)])
def test_worker_share_of_the_cores(current, share, want):
    assert worker_threads(current, share) == want
