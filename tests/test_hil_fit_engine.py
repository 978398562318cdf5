"""The local detector's "auto" engine in ``hil star`` (jobs/kinds/hil_star_spec.resolve_fit_engine): a short run
solves with the numpy passes and starts no Taichi (a one-image solve in a fraction of a second), a long run with
the compiled passes, and the choice is stored in the run's spec so that replay and resume run the same engine."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from dualsight.jobs.kinds.hil_star_spec import (COMPILED_DETECT_MIN_IMAGES, resolve_fit_engine, settings_from_table,
                                                spec_from_dict)
from dualsight.kernels.detect_local import LocalDetectConfig
from dualsight.scene.camera_file import read_camera_toml

ESA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "esa_tetra3"
CAMERA = Path(__file__).resolve().parents[1] / "examples" / "cameras" / "esa_tetra3.toml"


def _engine(table, n):
    return resolve_fit_engine(settings_from_table(table), n).detect_local["fit_engine"]


def test_auto_resolves_by_the_run_size_and_a_chosen_engine_stays():
    assert LocalDetectConfig().fit_engine == "auto" and LocalDetectConfig().engine == "taichi"
    assert _engine(None, 1) == "numpy"
    assert _engine(None, COMPILED_DETECT_MIN_IMAGES - 1) == "numpy"
    assert _engine(None, COMPILED_DETECT_MIN_IMAGES) == "taichi"
    assert _engine({"detect_local": {"fit_engine": "taichi"}}, 1) == "taichi"
    assert _engine({"detect_local": {"fit_engine": "numpy"}}, 10 ** 6) == "numpy"


def test_the_spec_stores_the_resolved_engine():
    cam = read_camera_toml(CAMERA)[0].to_dict()
    for n, want in ((3, "numpy"), (COMPILED_DETECT_MIN_IMAGES, "taichi")):
        d = {"images": [{"path": f"/nonexistent/f{i}.tif"} for i in range(n)],
             "camera": cam, "settings": settings_from_table(None).model_dump()}
        spec = spec_from_dict(d)
        assert spec.settings.detect_local["fit_engine"] == want


@pytest.mark.skipif(not ESA.is_dir(), reason="../shared/data/real/esa_tetra3 is absent")
def test_one_image_solve_starts_no_taichi():
    frame = sorted(ESA.glob("*.tif*"))[0]
    code = ("import dualsight\n"
            "from dualsight.kernels.taichi_runtime import is_initialised\n"
            f"s = dualsight.solve({str(frame)!r}, {str(CAMERA)!r})\n"
            "print(s.status, is_initialised())\n")
    env = dict(os.environ, TI_SKIP_VERSION_CHECK="ON")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    status, started = out.stdout.split()[-2:]
    assert status == "success" and started == "False", out.stdout
