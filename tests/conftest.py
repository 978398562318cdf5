"""Fixtures shared by the test modules (plain helpers: ``helpers.py``)."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def make_lake(tmp_path_factory):
    """``make_lake(name, *jobs)``: a new lake folder (``tmp_path_factory.mktemp(name)``) holding the runs of
    ``jobs``, each the argv of one ``dualsight`` job command without its lake and worker options: every job runs
    in this process with ``--lake <folder> --workers 1 --no-progress`` appended and must exit 0 (``{lake}`` in
    an argument stands for the folder).  Returns the folder.  For module-scoped lake fixtures; each call makes its
    own lake (nothing is shared between callers)."""
    from dualsight.jobs.cli.main import main

    def make(name: str, *jobs):
        root = tmp_path_factory.mktemp(name)
        for argv in jobs:
            argv = [str(a).replace("{lake}", str(root)) for a in argv]
            assert main([*argv, "--lake", str(root), "--workers", "1", "--no-progress"]) == 0, argv
        return root

    return make


@pytest.fixture
def no_rebuild(monkeypatch):
    """``no_rebuild(module, name)``: replace the builder ``module.name`` for this test by one that fails the test
    ("rebuilt although cached"): what is loaded next must come from the cache."""
    def forbid(module, name: str) -> None:
        def no_build(*a, **k):
            raise AssertionError("rebuilt although cached")
        monkeypatch.setattr(module, name, no_build)

    return forbid
