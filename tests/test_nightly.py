"""The nightly (`dualsight nightly`): verdicts that go red on planted regressions and stay green on noise.

Every night below runs in-process (``workers=1``) so that pytest's monkeypatch reaches the stage functions the
jobs call.  Numbers are checked against independent truth: rates and means recomputed with numpy from the
raw Parquet files (pyarrow, not the nightly's SQL), Fisher p-values recomputed with exact integer arithmetic.

Power of the planted-regression tests (the two samples are independent, the fixed-seed comparison is in fact
paired, so these are lower bounds): identification failing for 3 % of 2,000 cases moves the rate from ~0.99 to
~0.96, z = 0.03 / sqrt(0.99 * 0.01 / 2000 + 0.96 * 0.04 / 2000) = 6.1 against the critical z of 3.7 at the
per-test alpha of ~2.6e-4 (family-wise 0.01 over ~38 tests): power 99.3 % (Phi(2.4)); measured p ~1e-8 to 1e-14.
A 0.3 px centroid bias moves the mean centroid error from ~0.02 px to ~0.30 px (standard error ~0.001 px); a 5 %
range scale moves the mean range bias by 0.05 with a standard error of ~0.004 over 220 cases.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import types
import zlib

import numpy as np
import pyarrow.parquet as pq
import pytest

from dualsight.errors import InputError
from dualsight.jobs.nightly import run as nightly, stats as st
from dualsight.jobs.nightly import store
from dualsight.jobs.nightly import suite as ns
from dualsight.jobs.kinds import prox, star
from dualsight.jobs.engine.lakecheck import check_run
from dualsight.warehouse.lake import Lake
from dualsight.warehouse.query import run_sql
from helpers import run_cli

STAR_JOB = {"name": "star", "kind": "star", "spec": "paper", "cases": 2000, "seed": 1}
SWEEP_JOB = {"name": "sweep", "kind": "prox_sweep", "spec": "accurate", "cases": 220, "seed": 1}


def suite(*jobs, alpha=0.01):
    return ns.build_suite({"name": "test", "alpha": alpha, "job": list(jobs)}, source="test suite", base=ns.REPO)


def night(lake: Lake, s, **kw) -> dict:
    return nightly.run_nightly(s, lake, workers=1, log=lambda m: None, **kw)


def by(rows, job, comparison, metric) -> dict:
    hit = [r for r in rows if (r["job"], r["comparison"], r["metric"]) == (job, comparison, metric)]
    assert len(hit) == 1, (job, comparison, metric)
    return hit[0]


def table(lake: Lake, dataset: str, run_id: str):
    return pq.read_table(lake.root / dataset / f"run={run_id}")


def fisher_exact_int(k1, n1, k2, n2) -> float:
    """Two-sided Fisher exact p with Python's exact integers (independent of the numpy implementation)."""
    K, N = k1 + k2, n1 + n2
    num = {x: math.comb(K, x) * math.comb(N - K, n1 - x) for x in range(max(0, K - n2), min(K, n1) + 1)}
    obs = num[k1]
    return sum(v for v in num.values() if v <= obs) / math.comb(N, n1)


def patch_stage(monkeypatch, job_module, name, wrap):
    """Patch ``name`` where ``job_module`` looks it up at call time: its own global, or the attribute of the
    project module it calls through (e.g. star.py's ``pipe.identify``)."""
    g = vars(job_module)
    if callable(g.get(name)) and not isinstance(g[name], types.ModuleType):
        monkeypatch.setattr(job_module, name, wrap(g[name]))
        return
    for v in g.values():
        if isinstance(v, types.ModuleType) and v.__name__.startswith("dualsight.") and callable(getattr(v, name, None)):
            monkeypatch.setattr(v, name, wrap(getattr(v, name)))
            return
    raise AssertionError(f"{job_module.__name__} calls no {name}")


@pytest.fixture(scope="module")
def base_lake(tmp_path_factory):
    """One accepted night of star (2,000 cases) and an accurate sweep (220 cases), fixed and fresh seeds."""
    lake = Lake(tmp_path_factory.mktemp("nightly") / "lake")
    s = night(lake, suite(STAR_JOB, SWEEP_JOB), accept=True, fresh_seed=11)
    assert s["exit"] == 0 and s["accepted"] and not s["failed"], s["message"]
    return lake


@pytest.fixture
def lake(base_lake, tmp_path):
    shutil.copytree(base_lake.root, tmp_path / "lake")
    return Lake(tmp_path / "lake")


# ============================================================================================ statistics
def test_fisher_exact_matches_exact_integer_arithmetic():
    assert st.fisher_exact(3, 4, 1, 4) == pytest.approx(0.4857142857, rel=1e-9)      # Fisher's tea tasting
    rng = np.random.default_rng(3)
    for _ in range(40):
        n1, n2 = rng.integers(1, 300, 2)
        k1, k2 = rng.integers(0, n1 + 1), rng.integers(0, n2 + 1)
        assert st.fisher_exact(k1, n1, k2, n2) == pytest.approx(fisher_exact_int(k1, n1, k2, n2), rel=1e-6, abs=1e-300)


def test_permutation_test_is_exact_on_a_small_sample():
    a, b = np.array([1.0, 2.0, 3.0]), np.array([4.0, 5.0, 6.0, 7.0])
    pooled, obs = np.r_[a, b], abs(a.mean() - b.mean())
    import itertools

    d = [abs(pooled[list(c)].mean() - np.delete(pooled, list(c)).mean()) for c in itertools.combinations(range(7), 3)]
    assert st.permutation_pvalue(a, b, "t") == pytest.approx(np.mean(np.array(d) >= obs - 1e-12))


def test_p_values_are_calibrated_under_the_null():
    """Same distribution on both sides: the share of p < 0.05 is about 5 % (Fisher: at most, it is conservative)."""
    rng = np.random.default_rng(7)
    p_rate = [st.rate_test(*(int(rng.binomial(500, 0.9)), 500), *(int(rng.binomial(500, 0.9)), 500))[2]
              for _ in range(400)]
    assert np.mean(np.array(p_rate) < 0.05) <= 0.07
    p_mean, p_q = [], []
    for i in range(150):
        res = st.distribution_tests(rng.lognormal(0, 0.5, 300), rng.lognormal(0, 0.5, 300), f"null{i}")
        p_mean.append(res["mean"][2])
        p_q.append(res["p95"][2])
    assert 0.01 <= np.mean(np.array(p_mean) < 0.05) <= 0.11
    assert 0.01 <= np.mean(np.array(p_q) < 0.05) <= 0.12


def test_throughput_tolerance_from_the_accepted_spread():
    tol, how = st.throughput_tolerance([100.0, 110.0, 90.0])
    assert tol == pytest.approx(4 * np.std([100, 110, 90], ddof=1) / 100) and "3 accepted" in how
    assert st.throughput_tolerance([100.0])[0] == st.DEFAULT_THROUGHPUT_TOL
    assert st.throughput_verdict(100.0, 60.0, 0.3) == "REGRESSION" and st.throughput_verdict(100.0, 80.0, 0.3) == "ok"


# ============================================================================================ green nights
@pytest.mark.slow
def test_unchanged_build_stays_green_for_five_nights_with_fresh_seeds(lake):
    """False alarms: the same code, five new nights with fresh seeds.  Fixed seeds give identical rows; the
    fresh samples and the seeds check are tested (52 tests a night at alpha 0.01 / 52 each)."""
    s = suite(STAR_JOB, SWEEP_JOB)
    ps = []
    for k in range(5):
        res = night(lake, s, fresh_seed=100 + k)
        assert res["exit"] == 0, res["message"]
        rows = res["verdicts"]
        assert by(rows, "star", "fixed", "rows")["verdict"] == "identical"
        assert all(r["verdict"] == "identical" for r in rows if r["comparison"] == "fixed")
        ps += [r["p"] for r in rows if r.get("p") is not None]
    assert len(ps) == 5 * 52
    assert np.mean(np.array(ps) < 0.05) < 0.15          # per-test rate at 0.05 (tests are correlated)
    # identical by an independent comparison of the Parquet files (timing columns dropped)
    runs = sorted(m["run_id"] for m in lake.list_manifests() if m["run_id"].endswith("-star"))
    a, b = (table(lake, "star_cases", r).sort_by("case_id") for r in runs[:2])
    keep = [c for c in a.column_names if not (c.startswith("t_") and c.endswith("_ns")) and c != "run"]
    for c in keep:                      # NaN-aware (json writes NaN as NaN): every value equal
        assert json.dumps(a.column(c).to_pylist()) == json.dumps(b.column(c).to_pylist()), c


def test_verdicts_are_a_verified_dataset_and_the_baseline_names_runs(lake):
    res = night(lake, suite(STAR_JOB), fresh_seed=5)
    rid = store.run_id(res["night"], "verdicts")
    assert lake.scan(rid).problems == [] and check_run(lake, rid)["verdict"] == "ok"
    cols, rows = run_sql(lake, f"SELECT count(*), min(case_id), max(case_id), count(DISTINCT night) FROM "
                               f"nightly_verdicts WHERE run = '{rid}'")
    assert rows[0] == (len(res["verdicts"]), 0, len(res["verdicts"]) - 1, 1)
    doc = json.loads(store.baseline_path(lake).read_text())
    assert set(doc["jobs"]) == {"star", "sweep"}
    assert all(lake.read_manifest(j["fixed"])["status"] == "complete" for j in doc["jobs"].values())
    assert not list(store.baseline_path(lake).parent.glob(".*tmp*"))
    m = lake.read_manifest(store.run_id(res["night"], "star", fresh=True))
    assert m["spec"]["seed"] == 5 and res["runs"]["star"]["fresh_seed"] == 5       # the fresh seed is recorded


def test_a_changed_spec_is_not_comparable(lake):
    changed = dict(STAR_JOB, spec={"preset": "paper", "voting": {"tolerance_arcsec": 12.0}})
    res = night(lake, suite(changed), fresh_seed=6)
    assert res["exit"] == 1
    for comp in ("fixed", "fresh"):
        r = by(res["verdicts"], "star", comp, "success_rate")
        assert r["verdict"] == "not comparable" and "voting" in r["test"]


def test_another_suite_than_the_baseline_is_refused_before_running(lake):
    # the README's old nightly block accepted the quick suite, then ran the standard one: 90 "not comparable"
    other = ns.build_suite({"name": "other", "job": [STAR_JOB]}, source="test suite", base=ns.REPO)
    before = sorted(p.name for p in (lake.root / "_manifests").iterdir())
    with pytest.raises(InputError, match="accepted from suite 'test', tonight's suite is 'other'.*--accept"):
        night(lake, other, fresh_seed=6)
    assert sorted(p.name for p in (lake.root / "_manifests").iterdir()) == before     # nothing ran
    res = night(lake, other, accept=True, fresh_seed=6)                                # accepting it is allowed
    assert res["exit"] == 0 and res["accepted"]


# ============================================================================================ planted regressions
def test_identification_failing_for_3_percent_of_cases_turns_red(lake, monkeypatch):
    def wrap(orig):
        def identify(obs, *a, **k):
            ident = orig(obs, *a, **k)
            fail = np.array([zlib.crc32(np.nan_to_num(v).tobytes()) % 100 < 3 for v in obs.vec])
            return dataclasses.replace(ident, accepted=ident.accepted & ~fail[:, None],
                                       T=np.where(fail, 0, ident.T).astype(ident.T.dtype),
                                       ids=np.where(fail[:, None], -1, ident.ids).astype(ident.ids.dtype))
        return identify

    patch_stage(monkeypatch, star, "identify", wrap)
    res = night(lake, suite(STAR_JOB), fresh_seed=12)
    assert res["exit"] == 1
    base = json.loads(store.baseline_path(lake).read_text())["jobs"]["star"]
    for comp, base_run, now_run in (("fixed", base["fixed"], res["runs"]["star"]["fixed"]),
                                    ("fresh", base["fresh"], res["runs"]["star"]["fresh"])):
        r = by(res["verdicts"], "star", comp, "identification_rate")
        assert r["verdict"] == "REGRESSION", r
        ok_b = table(lake, "star_cases", base_run).column("id_correct").to_numpy(zero_copy_only=False)
        ok_n = table(lake, "star_cases", now_run).column("id_correct").to_numpy(zero_copy_only=False)
        assert (r["baseline"], r["now"]) == (pytest.approx(ok_b.mean()), pytest.approx(ok_n.mean()))
        assert 0.015 < ok_b.mean() - ok_n.mean() < 0.05
        assert r["p"] == pytest.approx(fisher_exact_int(int(ok_b.sum()), len(ok_b), int(ok_n.sum()), len(ok_n)),
                                       rel=1e-6)
        assert r["p"] < r["alpha"] == pytest.approx(0.01 / res["tests"])
    assert by(res["verdicts"], "star", "fixed", "confident_wrong_rate")["verdict"] in ("ok", "improved")


def test_a_0_3_px_centroid_bias_turns_red(lake, monkeypatch):
    def wrap(orig):
        def render_and_detect(*a, **k):
            r = orig(*a, **k)
            return dataclasses.replace(r, detections=dataclasses.replace(r.detections, x=r.detections.x + 0.3))
        return render_and_detect

    patch_stage(monkeypatch, star, "render_and_detect", wrap)
    res = night(lake, suite(STAR_JOB), fresh_seed=13)
    assert res["exit"] == 1

    def centroid(run_id):
        t = table(lake, "star_detections", run_id)
        case, d, hip = (t.column(c).to_numpy() for c in ("case_id", "true_dist_px", "hip_true"))
        ok = (hip >= 0) & np.isfinite(d)
        sums = np.bincount(case[ok], weights=d[ok])
        cnt = np.bincount(case[ok])
        return (sums[cnt > 0] / cnt[cnt > 0]).mean()

    base = json.loads(store.baseline_path(lake).read_text())["jobs"]["star"]
    for comp, key in (("fixed", "fixed"), ("fresh", "fresh")):
        r = by(res["verdicts"], "star", comp, "centroid_err_px.mean")
        assert r["verdict"] == "REGRESSION", r
        assert r["baseline"] == pytest.approx(centroid(base[key]), rel=1e-9)
        assert r["now"] == pytest.approx(centroid(res["runs"]["star"][key]), rel=1e-9)
        assert 0.2 < r["now"] - r["baseline"] < 0.35


def test_a_5_percent_range_scale_in_the_blobber_turns_red(lake, monkeypatch):
    def wrap(orig):
        def run_blobber(*a, **k):
            res = orig(*a, **k)
            return dataclasses.replace(res, range_est=res.range_est * 1.05, position=res.position * 1.05)
        return run_blobber

    patch_stage(monkeypatch, prox, "run_blobber", wrap)
    res = night(lake, suite(SWEEP_JOB), fresh_seed=14)
    assert res["exit"] == 1

    def bias(run_id):
        t = table(lake, "prox_cases", run_id)
        found = t.column("found").to_numpy(zero_copy_only=False)
        est, true = t.column("subpixel_range_est_m").to_numpy(), t.column("true_range_m").to_numpy()
        ok = found & np.isfinite(est)
        return ((est[ok] - true[ok]) / true[ok]).mean()

    base = json.loads(store.baseline_path(lake).read_text())["jobs"]["sweep"]
    for comp in ("fixed", "fresh"):
        r = by(res["verdicts"], "sweep", comp, "range_bias_subpixel.mean")
        assert r["verdict"] == "REGRESSION", r
        assert r["baseline"] == pytest.approx(bias(base[comp]), rel=1e-9)
        assert r["now"] == pytest.approx(bias(res["runs"]["sweep"][comp]), rel=1e-9)
        if comp == "fixed":             # the same cases: bias_now = 1.05 (1 + bias) - 1 exactly
            assert r["now"] - r["baseline"] == pytest.approx(0.05 * (1 + r["baseline"]), abs=1e-9)
        else:                           # other orientations: the 5 % plus sampling noise (se ~0.008)
            assert 0.02 < r["now"] - r["baseline"] < 0.08
    assert by(res["verdicts"], "sweep", "fixed", "found_rate")["verdict"] == "identical" or \
        by(res["verdicts"], "sweep", "fixed", "found_rate")["verdict"] == "ok"


# ============================================================================================ command line
TINY = """
name = "tiny"
[[job]]
name = "star"
kind = "star"
spec = "paper"
cases = 300
seed = 3
[[job]]
name = "hil_star"
kind = "hil_star"
images = "{shared}/data/real/esa_tetra3/*.tiff"
camera = "examples/cameras/esa_tetra3.toml"
truth = "{shared}/data/real/esa_tetra3/truth.json"
[[job]]
name = "hil_prox"
kind = "hil_prox"
images = "{shared}/data/real/opencv_chessboard"
target = "examples/targets/opencv_chessboard.toml"
calibrate = { board = [9, 6], square_m = 0.025 }
spec = { thresholds = [210.0], invert = true, border_px = 6, open_px = 9, close_px = 61 }
"""


def test_cli_nights_history_and_page(tmp_path):
    f = tmp_path / "tiny.toml"
    f.write_text(TINY)
    lake = tmp_path / "lake"
    args = ["nightly", "--suite", f, "--lake", lake, "--workers", "1", "--no-progress"]
    rc, out, err = run_cli(args)
    assert rc == 2 and "--accept" in out                       # no baseline yet: could not compare
    rc, out, err = run_cli(args + ["--accept"])
    assert rc == 0 and "accepted night" in out, err
    rc, out, err = run_cli(args + ["--json", "--html", tmp_path / "page.html"])
    assert rc == 0, out[-2000:]
    doc = json.loads(out)
    assert doc["exit"] == 0 and doc["message"].startswith("GREEN")
    hil = [r for r in doc["verdicts"] if r["job"].startswith("hil")]
    real = ns.shared_root() / "data" / "real"
    for job, folder in (("hil_star", "esa_tetra3"), ("hil_prox", "opencv_chessboard")):
        vs = {r["verdict"] for r in hil if r["job"] == job}
        assert vs <= ({"identical", "info"} if (real / folder).is_dir() else {"skipped"}), (job, vs)
    # the star rows: success rate of tonight's fixed run recomputed from the Parquet rows
    r = by(doc["verdicts"], "star", "fixed", "success_rate")
    st_ = table(Lake(lake), "star_cases", r["now_run"]).column("status").to_pylist()
    assert r["now"] == pytest.approx(np.mean([s == "success" for s in st_]))
    # history over the three nights (SQL over nightly_verdicts)
    rc, out, err = run_cli(["nightly", "history", "--lake", lake, "--json"])
    assert rc == 0, err
    h = json.loads(out)
    assert len(h["nights"]) == 3
    t = next(t for t in h["trends"] if (t["job"], t["comparison"], t["metric"]) == ("star", "fixed", "success_rate"))
    assert [p["now"] for p in t["points"]][-1] == pytest.approx(r["now"])
    rc, out, err = run_cli(["nightly", "history", "--lake", lake])
    assert rc == 0 and "success_rate" in out
    page = (tmp_path / "page.html").read_text()
    png = (tmp_path / "page.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and "data:image/png;base64," in page
    assert "http://" not in page and "https://" not in page and "<script" not in page


@pytest.mark.parametrize("doc, words", [
    ('[[job]]\nname = "a"\nkind = "stars"', ["job.0.kind", "'star'"]),
    ('[[job]]\nname = "a"\nkind = "star"\ncases = 0', ["job.0.cases", "greater than or equal to 1"]),
    ('[[job]]\nname = "a"\nkind = "prox_sweep"\nspec = "accurate"\ncases = 100', ["job.0.cases", "multiple", "11"]),
    ('[[job]]\nname = "a"\nkind = "hil_star"\nimages = "x"\nseed = 1', ["job.0.seed", "not allowed"]),
    ('[[job]]\nname = "a"\nkind = "star"\nspec = "fancy"', ["job.0.spec", "unknown preset", "paper"]),
    ('[[job]]\nname = "A b"\nkind = "star"', ["job.0.name", "pattern"]),
    ('alpha = 0.5\n[[job]]\nname = "a"\nkind = "star"', ["alpha", "less than or equal to 0.2"]),
    ('[[job]]\nname = "a"\nkind = "star"\n[job.spec]\nvoting = {tolerance_arcsec = -1.0}', ["voting", "tolerance"]),
])
def test_bad_suites_fail_with_one_line_naming_the_field(tmp_path, doc, words):
    f = tmp_path / "bad.toml"
    f.write_text(doc)
    rc, out, err = run_cli(["nightly", "--suite", f, "--lake", tmp_path / "lake"])
    assert rc == 2 and out == "" and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert str(f) in err or "job.0" in err, err
    for w in words:
        assert w in err, (w, err)
    assert not (tmp_path / "lake").exists()


def test_other_errors_are_one_line(tmp_path):
    lake = tmp_path / "lake"
    (lake / "_nightly").mkdir(parents=True)
    (lake / "_nightly" / "baseline.json").write_text("{not json")
    f = tmp_path / "s.toml"
    f.write_text('[[job]]\nname = "a"\nkind = "star"\ncases = 10\n')
    for argv, words in ((["nightly", "--suite", tmp_path / "missing.toml"], ["missing.toml", "not found"]),
                        (["nightly", "--suite", f, "--lake", lake], ["baseline.json", "damaged"]),
                        (["nightly", "--suite", f, "--html", tmp_path / "no" / "p.html"], ["--html", "does not exist"]),
                        (["nightly", "history", "--lake", tmp_path / "empty"], ["no nightly verdicts"])):
        rc, out, err = run_cli(argv)
        assert rc == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, (argv, err)
        assert all(w in err for w in words), (argv, err)


def test_the_shipped_suites_load():
    quick = ns.load_suite("quick")
    standard = ns.load_suite("standard")
    assert [j.kind for j in quick.jobs] == [j.kind for j in standard.jobs] == \
        ["star", "star", "star_track", "prox_sweep", "prox_trajectory", "hil_star", "hil_prox"]
    assert [j.n_cases for j in standard.jobs[:4]] == [20000, 2000, 200, 3300]
    assert standard.jobs[1].spec["sensor"]["shot_noise"]
    assert standard.jobs[2].spec["sequence"]["blinded"] == 1 and quick.jobs[2].n_cases == 24
    assert all(j.fresh_cases == j.n_cases for j in standard.jobs[:5])
    assert standard.jobs[0].make(99, 10)[0]["seed"] == 99
