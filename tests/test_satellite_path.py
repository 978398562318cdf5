"""A preset's relative satellite or camera file (``examples/satellites/cubesat_3u.toml``) is found from any working folder
(scene/example_files.shipped_path), a file of the working folder wins, and a missing one is named as given."""

from __future__ import annotations

import pytest

from dualsight.errors import ConfigError, InputError
from dualsight.scene.satellite import load_satellite

REL = "examples/satellites/cubesat_3u.toml"


def test_a_preset_satellite_is_found_from_another_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    sat = load_satellite(REL)
    assert sat.bounding_radius == pytest.approx(0.5 * (0.1 ** 2 + 0.1 ** 2 + 0.3 ** 2) ** 0.5, rel=1e-6)


def test_the_working_folder_wins_and_a_missing_file_is_named_as_given(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "examples" / "satellites").mkdir(parents=True)
    (tmp_path / REL).write_text("this is = not [ toml\n")
    with pytest.raises((ConfigError, InputError)) as e:
        load_satellite(REL)                       # the local (broken) file, not the repository's
    assert REL in str(e.value)
    with pytest.raises((ConfigError, InputError)) as e:
        load_satellite("examples/satellites/none.toml")
    assert "examples/satellites/none.toml" in str(e.value)


def test_the_close_preset_runs_from_another_folder(tmp_path, monkeypatch):
    """Its camera file ``examples/cameras/paper_prox.toml`` is a relative name too."""
    from dualsight.jobs.kinds import rendezvous, rendezvous_spec
    monkeypatch.chdir(tmp_path)
    spec_dict, n = rendezvous_spec.resolve_spec("close", None, cases=1)
    spec = rendezvous.spec_from_dict(spec_dict)
    assert (spec.camera.width, spec.camera.height) == (1024, 768)           # the paper's Table 1 camera (6 mm)
