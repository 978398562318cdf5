"""Issue 25 point 4: the pair catalog's cost estimated before a build, a refusal beyond the bound, a progress bar on
long builds, and the cache folder's size limit with ``dualsight cache list`` / ``clear``.

Truths: brute-force pair counts (every pair's angle), the real builds' lengths, a uniform sky's statistics, and the
files on disk (their names, sizes and times, set here)."""

from __future__ import annotations

import fcntl
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from dualsight.catalogs import cache_budget, pair_estimate
from dualsight.catalogs.build_progress import NullBar, build_bar
from dualsight.catalogs.cache_budget import enforce_limit, list_entries, mark_in_use
from dualsight.catalogs.pair_cache import check_new_pair_catalog, load_pair_catalog
from dualsight.catalogs.pair_estimate import PairCatalogTooLarge, PairLimits, estimate_pairs
from dualsight.catalogs.pairs import build_pair_catalog
from dualsight.catalogs.stars import StarCatalogConfig, load_star_catalog
from dualsight.jobs.cli.main import main
from dualsight.nav.pair_index import VotingIndex
from dualsight.scene.units import angle_between

REPO = Path(__file__).resolve().parents[1]
ESA = Path("/work/shared/data/real/esa_tetra3")
TIFF = ESA / "2019-07-29T204726_Alt40_Azi45_Try1.tiff"
HOSTILE = {"camera": {"name": "hostile", "width": 1024, "height": 768, "pixel_pitch_um": 6.9, "fx": 213.0,
                      "fy": 22.0, "cx": 512.0, "cy": 7495.0, "distortion": [-0.45, 0.2, 0.01, -0.01, -0.05],
                      "bit_depth": 12}}


@pytest.fixture(autouse=True)
def cache(tmp_path, monkeypatch):
    """Every test on its own cache folder and the default bounds."""
    d = tmp_path / "cache"
    monkeypatch.setenv("DUALSIGHT_CACHE", str(d))
    for var in ("DUALSIGHT_CACHE_GB", "DUALSIGHT_MAX_PAIR_GB", "DUALSIGHT_MAX_PAIR_SECONDS"):
        monkeypatch.delenv(var, raising=False)
    cache_budget._IN_USE.clear()                         # marks of earlier tests are about other folders
    return d


def sphere(n: int, seed: int) -> np.ndarray:
    v = np.random.default_rng([25, 4, seed]).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def brute_pairs(u: np.ndarray, theta: float) -> int:
    """Every pair's angle (atan2 form), counted below ``theta``."""
    a = angle_between(u[:, None, :], u[None, :, :])
    iu = np.triu_indices(len(u), 1)
    return int(np.count_nonzero(a[iu] < theta))


# ============================================================================================ 1. the estimate
@pytest.mark.parametrize("theta_deg", [3.0, 20.0, 90.0, 179.0, 180.0])
def test_estimate_equals_brute_force_on_a_small_catalog(theta_deg):
    u = sphere(1500, 1)
    u = np.concatenate([u, u[:3]])                       # identical stars: angle 0, a pair at any theta
    est = estimate_pairs(u, math.radians(theta_deg))
    assert est.exact and est.n_stars == 1503
    assert est.pairs == brute_pairs(u, math.radians(theta_deg))


def test_estimate_of_a_count_matches_a_uniform_sky():
    """The count-only estimate is the mean over uniform skies: brute force on 4 random skies of 1,200 stars."""
    theta = math.radians(25.0)
    counts = [brute_pairs(sphere(1200, s), theta) for s in range(10, 14)]
    est = estimate_pairs(1200, theta)
    assert not est.exact
    # Poisson-like spread of a pair count (~ sqrt of the count, x2 for the shared stars): 5 sigma of the mean
    assert abs(np.mean(counts) - est.pairs) < 5 * 2 * math.sqrt(est.pairs) / 2


@pytest.mark.parametrize("mag, theta_deg, tol", [(5.5, 30.0, 0.0), (6.5, 14.25, 0.03), (6.5, 40.0, 0.03)])
def test_estimate_against_the_real_builds(mag, theta_deg, tol, tmp_path):
    cat = load_star_catalog(StarCatalogConfig(mag_limit=mag))
    theta = math.radians(theta_deg)
    est = estimate_pairs(cat.unit, theta, mag)
    built = build_pair_catalog(cat.unit, theta, work_dir=tmp_path)
    assert est.exact == (tol == 0.0)
    assert abs(est.pairs - len(built)) <= tol * len(built), (est.pairs, len(built))
    assert est.disk_bytes == pytest.approx(32 * len(built), rel=max(tol, 1e-9))
    assert est.seconds > 0 and est.memory_bytes > 16 * est.pairs
    assert est.mag_limit == mag and est.field_deg == pytest.approx(theta_deg)


def test_estimate_of_the_hostile_field():
    """Its time is benchmarks/bench_pair_estimate.py's (0.2-0.3 s at V 8), not a test's."""
    cat = load_star_catalog(StarCatalogConfig(mag_limit=8.0))
    est = estimate_pairs(cat.unit, math.radians(173.5), 8.0)
    # nearly every pair of the sky: N (N - 1) / 2 x (1 - cos 173.5) / 2 for a uniform sky, within 1 %
    n = len(cat)
    assert est.pairs == pytest.approx(n * (n - 1) / 2 * (1 - math.cos(math.radians(173.5))) / 2, rel=0.01)
    assert est.disk_bytes > 20e9 and est.seconds > 300


# ============================================================================================ 2. the refusal
def test_load_refuses_over_the_bound_and_writes_nothing(cache):
    cat = load_star_catalog(StarCatalogConfig(mag_limit=5.0), write=False)
    assert not cache.exists()                            # a check writes nothing, not even the folder
    with pytest.raises(PairCatalogTooLarge) as e:
        load_pair_catalog(cat, math.radians(20), limits=PairLimits(max_bytes=1e3, max_seconds=None), source="cam.toml")
    msg = str(e.value)
    assert msg.startswith("cam.toml: the pair catalog of a 20.0 deg field") and "V 5" in msg
    assert "\n" not in msg and "DUALSIGHT_MAX_PAIR_GB=" in msg and "--mag-limit" in msg
    assert not cache.exists()
    p = load_pair_catalog(cat, math.radians(20), limits=PairLimits(None, None))    # no bound: built
    assert len(p) > 0 and check_new_pair_catalog(cat, math.radians(20), limits=PairLimits(1e3, 1e-3)) is None


def test_env_bounds_and_their_errors(monkeypatch, cache):
    cat = load_star_catalog(StarCatalogConfig(mag_limit=5.0), write=False)
    monkeypatch.setenv("DUALSIGHT_MAX_PAIR_SECONDS", "1e-6")
    with pytest.raises(PairCatalogTooLarge, match=r"over the bound \(2 GB, 1e-06 s\)"):
        check_new_pair_catalog(cat, math.radians(10))
    monkeypatch.setenv("DUALSIGHT_MAX_PAIR_SECONDS", "0")                      # 0 lifts it
    assert check_new_pair_catalog(cat, math.radians(10)).pairs > 0
    monkeypatch.setenv("DUALSIGHT_MAX_PAIR_GB", "lots")
    with pytest.raises(pair_estimate.InputError, match=r"\$DUALSIGHT_MAX_PAIR_GB: must be a number"):
        check_new_pair_catalog(cat, math.radians(10))


CHILD = """
import sys, time
t0 = time.perf_counter()
from dualsight.jobs.cli.main import main
from dualsight.nav.pair_index import VotingIndex
rc = main(sys.argv[2:])
# VmHWM: this program's own peak (ru_maxrss would carry the forking test process's size across exec)
hwm = next(int(x.split()[1]) for x in open("/proc/self/status") if x.startswith("VmHWM:"))
open(sys.argv[1], "w").write(f"{rc} {hwm} {time.perf_counter() - t0}")
"""


@pytest.mark.skipif(not TIFF.is_file(), reason="ESA tetra3 frames not present")
def test_hostile_camera_is_refused_in_one_line_fast(tmp_path, cache):
    cam = tmp_path / "hostile.toml"
    cam.write_text(tomli_w.dumps(HOSTILE))
    lake, out = tmp_path / "lake", tmp_path / "child.txt"
    r = subprocess.run([sys.executable, "-c", CHILD, str(out), "hil", "star", str(TIFF), "--camera", str(cam),
                        "--lake", str(lake)], capture_output=True, text=True, timeout=60,
                       env={**os.environ, "DUALSIGHT_CACHE": str(cache)})
    rc, rss_kb, secs = out.read_text().split()
    lines = r.stderr.strip().splitlines()
    assert int(rc) == 2 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    line = lines[0]
    assert line.startswith(f"dualsight: error: {cam}: the pair catalog of a 173.5 deg field"), line
    for part in ("to V 8 (41,4", "pairs", "GB on disk", "to build", "--mag-limit", "DUALSIGHT_MAX_PAIR_GB="):
        assert part in line, (part, line)
    assert float(secs) < 15 and int(rss_kb) < 1 << 20    # the bound: seconds (a hang guard), < 1 GiB RSS
    assert not lake.exists()
    left = sorted(p.name for p in cache.iterdir()) if cache.exists() else []
    assert not [n for n in left if "pairs" in n], left           # no pair catalog, no build folder, no lock


def test_star_run_of_a_wide_camera_is_refused_before_the_lake(tmp_path, capsys):
    cfg = tmp_path / "wide.toml"
    cfg.write_text(tomli_w.dumps({"camera": {"focal_length_mm": 2.0}, "catalog": {"mag_limit": 7.0}}))
    lake = tmp_path / "lake"
    rc = main(["star", "run", "--config", str(cfg), "--cases", "4", "--lake", str(lake), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "the pair catalog of a" in err, err
    assert "Traceback" not in err and not lake.exists()


# ============================================================================================ 3. progress
class CountingBar:
    def __init__(self):
        self.n, self.total = 0, 0

    def update(self, n=1):
        self.n += n


def test_build_progress_counts_every_pair_twice(tmp_path):
    u = sphere(3000, 2)
    bar = CountingBar()
    cat = build_pair_catalog(u, math.radians(15), work_dir=tmp_path, progress=bar, max_bytes=1 << 20)
    assert bar.n == 2 * len(cat) == bar.total and len(cat) > 0


def test_progress_bar_only_on_long_builds(capsys):
    cat = load_star_catalog(StarCatalogConfig(mag_limit=5.0))
    load_pair_catalog(cat, math.radians(12))                          # ~0.1 s: no bar
    assert capsys.readouterr().err == ""
    load_pair_catalog(cat, math.radians(13), progress=True)
    err = capsys.readouterr().err
    assert "pair catalog (13.0 deg, " in err and "100%" in err


# ============================================================================================ 4. cache limit
def fake_cache(root: Path) -> dict[str, list[Path]]:
    """Entries of known sizes and last uses (days ago): pairs A (5 d), stars (4 d), hip2 (3 d), pairs B (2 d),
    areas (1 d); plus Taichi's folder and a file that is not dualsight's (10 d)."""
    root.mkdir(parents=True, exist_ok=True)
    now = time.time()
    spec = {"pairsA": (5, [f"pairs-v3-{'a' * 16}.{x}" for x in ("i.npy", "j.npy", "angle.npy", "json", "vstars.npy")]),
            "stars": (4, ["stars-v1-V7-1487490f83d5b8a9.parquet"]),
            "hip": (3, ["hip2-vmag-40f7a78ee11afae3.npy"]),
            "pairsB": (2, [f"pairs-v3-{'b' * 16}.{x}" for x in ("i.npy", "j.npy", "angle.npy", "json")]),
            "areas": (1, ["areas/121a0e59f206a86b.parquet", "areas/121a0e59f206a86b.samples.parquet"]),
            "taichi": (10, ["taichi/T00.tic"]), "unknown": (10, ["notes.txt"])}
    files = {}
    for k, (days, names) in spec.items():
        files[k] = []
        for i, n in enumerate(names):
            p = root / n
            p.parent.mkdir(exist_ok=True)
            p.write_bytes(b"x" * (1000 + 100 * i))
            t = now - days * 86400
            os.utime(p, (t, t))
            files[k].append(p)
    (root / f"pairs-v3-{'a' * 16}.lock").touch()
    return files


def sizes(paths) -> int:
    return sum(p.stat().st_size for p in paths)


def test_entries_group_the_files_on_disk(cache):
    files = fake_cache(cache)
    entries = list_entries(cache)
    assert [e.kind for e in entries] == ["unknown", "pairs", "stars", "hip2-vmag", "pairs", "areas"]
    for e in entries:
        key = {"notes.txt": "unknown", "stars-v1-V7-1487490f83d5b8a9": "stars", "hip2-vmag-40f7a78ee11afae3": "hip",
               f"pairs-v3-{'a' * 16}": "pairsA", f"pairs-v3-{'b' * 16}": "pairsB",
               "areas/121a0e59f206a86b": "areas"}[e.name]
        assert sorted(e.files) == sorted(files[key]) and e.size == sizes(files[key])
        assert e.last_used == pytest.approx(max(p.stat().st_mtime for p in files[key]))


def test_eviction_oldest_first_down_to_the_limit(cache, monkeypatch):
    files = fake_cache(cache)
    known = ("pairsA", "stars", "hip", "pairsB", "areas")
    total = sum(sizes(files[k]) for k in known) + sizes(files["unknown"])
    # room for all but the two oldest entries (pairs A, stars): they go, in that order
    limit = total - sizes(files["pairsA"]) - sizes(files["stars"])
    monkeypatch.setenv("DUALSIGHT_CACHE_GB", repr(limit / 2**30))
    removed = enforce_limit(cache)
    assert [e.name for e in removed] == [f"pairs-v3-{'a' * 16}", "stars-v1-V7-1487490f83d5b8a9"]
    for k in known:
        assert all(p.exists() == (k not in ("pairsA", "stars")) for p in files[k]), k
    assert all(p.exists() for p in files["taichi"] + files["unknown"])
    assert (cache / f"pairs-v3-{'a' * 16}.lock").exists()                       # the build lock stays
    assert sum(e.size for e in list_entries(cache)) <= limit


def test_eviction_spares_entries_in_use_here_or_locked_elsewhere(cache, monkeypatch):
    files = fake_cache(cache)
    mark_in_use(cache, files["pairsA"][0])                  # used by this process: now the most recent too
    assert files["pairsA"][0].stat().st_atime > time.time() - 60
    os.utime(files["pairsA"][0], (time.time() - 9 * 86400,) * 2)   # even when its times say "oldest"
    lock = open(cache / f"pairs-v3-{'b' * 16}.lock", "a+b")  # pairs B being built by "another process"
    fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
    try:
        monkeypatch.setenv("DUALSIGHT_CACHE_GB", repr(1 / 2**30))       # 1 byte: remove all that may go
        removed = {e.name for e in enforce_limit(cache)}
    finally:
        lock.close()
    assert removed == {"stars-v1-V7-1487490f83d5b8a9", "hip2-vmag-40f7a78ee11afae3", "areas/121a0e59f206a86b"}
    assert all(p.exists() for k in ("pairsA", "pairsB", "taichi", "unknown") for p in files[k])


def test_a_fresh_build_folder_is_kept_a_stale_one_removed(cache, monkeypatch):
    build = cache / f".pairs-v3-{'c' * 16}.build-xyz"
    build.mkdir(parents=True)
    (build / "b00000001.rec").write_bytes(b"r" * 5000)
    monkeypatch.setenv("DUALSIGHT_CACHE_GB", repr(1 / 2**30))
    assert enforce_limit(cache) == [] and build.exists()                   # modified just now: a build running
    old = time.time() - 3600
    os.utime(build / "b00000001.rec", (old, old))
    os.utime(build, (old, old))
    assert [e.name for e in enforce_limit(cache)] == [f"pairs-v3-{'c' * 16}"] and not build.exists()


@pytest.mark.parametrize("step", ["pairs", "voting"])
def test_a_build_holds_the_cache_under_its_limit(cache, monkeypatch, step):
    cat = load_star_catalog(StarCatalogConfig(mag_limit=5.0))
    p = load_pair_catalog(cat, math.radians(8)) if step == "voting" else None
    files = fake_cache(cache)
    monkeypatch.setenv("DUALSIGHT_CACHE_GB", repr(1 / 2**30))
    if step == "pairs":
        p = load_pair_catalog(cat, math.radians(8))                    # a new pair catalog written
    else:
        VotingIndex.load_or_build(p)                                   # its voting arrays written
    left = {e.name for e in list_entries(cache)}
    stem = Path(p.i.filename).name[:-len(".i.npy")]
    assert left == {"notes.txt", stem, "stars-v1-V5-" + cat.config.key()}   # the entries in use stay
    assert all(p.exists() for p in files["taichi"])


def test_the_bar_shows_only_for_long_builds():
    assert isinstance(build_bar("x", 10, 1.9), NullBar) and isinstance(build_bar("x", 10, 60.0, False), NullBar)
    bar = build_bar("x", 10, 2.1)
    assert not isinstance(bar, NullBar) and bar.total == 10
    bar.close()


# ============================================================================================ 5. the command
def test_cache_list_matches_the_files(cache, capsys):
    files = fake_cache(cache)
    assert main(["cache", "list", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["folder"] == str(cache) and doc["limit_bytes"] == 2 * 2**30
    assert doc["taichi_bytes"] == sizes(files["taichi"])
    by_name = {e["name"]: e for e in doc["entries"]}
    assert by_name[f"pairs-v3-{'a' * 16}"]["bytes"] == sizes(files["pairsA"])
    assert sorted(by_name["areas/121a0e59f206a86b"]["files"]) == sorted(map(str, files["areas"]))
    assert doc["total_bytes"] == sum(sizes(v) for k, v in files.items() if k != "taichi")
    assert main(["cache", "list"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].split() == ["kind", "entry", "holds", "size", "last", "used"]
    row = next(r for r in out if "stars-v1-V7" in r)
    assert "star catalog to V 7" in row and "1000 B" in row and "(4.0 d ago)" in row
    assert out[-1].startswith(f"6 entries, {sum(sizes(v) for k, v in files.items() if k != 'taichi') / 1024:.1f} KiB"
                              f" in {cache}; limit 2.00 GiB")


def test_cache_clear(cache, capsys):
    files = fake_cache(cache)
    old = sizes(files["pairsA"] + files["stars"] + files["hip"])
    assert main(["cache", "clear"]) == 2
    assert "give --all, --older-than DAYS or --taichi" in capsys.readouterr().err
    assert main(["cache", "clear", "--older-than", "2.5"]) == 0               # pairs A, stars, hip: 5, 4, 3 days
    assert capsys.readouterr().out.startswith(f"removed 3 entries ({old / 1024:.1f} KiB)")
    for k in files:
        assert all(p.exists() == (k not in ("pairsA", "stars", "hip")) for p in files[k]), k
    assert main(["cache", "clear", "--all"]) == 0
    assert sorted(p.relative_to(cache).as_posix() for p in cache.rglob("*") if p.is_file()) == \
        ["notes.txt", f"pairs-v3-{'a' * 16}.lock", "taichi/T00.tic"]
    assert "notes.txt (not dualsight's)" in capsys.readouterr().err
    assert main(["cache", "clear", "--taichi"]) == 0 and not (cache / "taichi").exists()
    assert main(["cache", "clear", "--older-than", "-1"]) == 2


def test_cache_command_parses_without_numpy():
    code = ("import sys; from dualsight.jobs.cli.main import build_parser; "
            "build_parser().parse_args(['cache', 'clear', '--all']); print('numpy' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert r.stdout.strip() == "False", r.stderr
