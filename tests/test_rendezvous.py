"""The rendezvous job kind (issue 23, point 5): truth against the closed-form Clohessy-Wiltshire solution, rows that
reproduce from the seed, the report's numbers against numpy over the rows, one-line refusals of bad specs."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from dualsight.nav.relative_filter import FilterConfig
from dualsight.jobs.kinds import (rendezvous as rz, rendezvous_context, rendezvous_filter, rendezvous_measure,
                                  rendezvous_spec, rendezvous_truth, star)
from dualsight.scene.target_photometry import photocentre_table
from dualsight.jobs.reports import rendezvous as report
from dualsight.nav.nees_band import inside_probability, simultaneous_mean_bounds
from dualsight.nav import relative_filter as rf
from dualsight.scene.relative_orbit import CircularOrbit, hill_to_icrs
from dualsight.warehouse.lake import Lake

FAR_SMALL = {"rendezvous": {"duration_s": 6600.0, "frame_interval_s": 600.0, "manoeuvre_times_s": [600.0]}}
"""The far preset over 12 frames 600 s apart, the burn at frame 1: the frame one orbit later (t = 6277 s) is 10."""
CLOSE_SMALL = {"preset": "close", "rendezvous": {"duration_s": 690.0, "frame_interval_s": 30.0,
                                                 "manoeuvre_times_s": [30.0]}}
"""The close preset over 24 frames 30 s apart (frames >= 20 exist: point 6 d's window)."""


def _spec(config):
    d, _ = rendezvous_spec.resolve_spec(None, config)
    return rz.spec_from_dict(d)


def _cw_closed_form(n, t, x0):
    """Curtis Eqs. 7.53 written out (s = sin nt, c = cos nt): the state at t from x0 with no manoeuvre."""
    x, y, z, vx, vy, vz = x0
    s, c = math.sin(n * t), math.cos(n * t)
    return np.array([
        (4 - 3 * c) * x + s / n * vx + 2 * (1 - c) / n * vy,
        6 * (s - n * t) * x + y - 2 * (1 - c) / n * vx + (4 * s - 3 * n * t) / n * vy,
        c * z + s / n * vz,
        3 * n * s * x + c * vx + 2 * s * vy,
        -6 * n * (1 - c) * x - 2 * s * vx + (4 * c - 3) * vy,
        -n * s * z + c * vz])


def test_truth_is_the_closed_form_cw_solution_with_the_executed_burn():
    spec = _spec(None)                                       # far preset: 64 frames, one burn at frame 6
    draw = rendezvous_truth.draw_case(spec, 3)
    truth = rendezvous_truth.truth_trajectory(spec, draw)
    n = CircularOrbit(500e3).mean_motion
    tb = spec.cfg.manoeuvre_times_s[0]
    x_b = _cw_closed_form(n, tb, draw["x0"])
    x_b[3:] += draw["dv_exec"][0]
    for k, t in enumerate(spec.times):
        want = _cw_closed_form(n, t, draw["x0"]) if t < tb else _cw_closed_form(n, t - tb, x_b)
        np.testing.assert_allclose(truth[k], want, rtol=1e-9, atol=1e-9)
    # the executed burn differs from the nominal by its drawn error (0.3 % of |dv| per axis)
    assert 0 < np.linalg.norm(draw["dv_exec"] - draw["dv_nominal"]) < 0.05 * np.linalg.norm(draw["dv_nominal"])


def test_the_presets_v_bar_hop_ends_at_its_range_one_orbit_later():
    for preset, start, end in (("far", 2000.0, 200.0), ("close", 50.0, 2.0)):
        spec = _spec({"preset": preset})
        c = spec.cfg
        n = spec.orbit.mean_motion
        x = np.array(list(c.position_m) + list(c.velocity_m_s))
        assert x[1] == -start
        tb = c.manoeuvre_times_s[0]
        x = _cw_closed_form(n, tb, x)
        x[3:] += np.asarray(c.manoeuvre_dv_m_s[0])
        x = _cw_closed_form(n, 2 * math.pi / n, x)
        np.testing.assert_allclose(x[:3], [0.0, -end, 0.0], atol=1e-6)
        _, k = rendezvous_filter.burn_frames(spec)
        assert abs(spec.times[k] - tb - 2 * math.pi / n) <= 0.5 * c.frame_interval_s


def test_look_at_puts_the_boresight_on_the_line_of_sight():
    rng = np.random.default_rng(5)
    los = rng.normal(size=(20, 3))
    los /= np.linalg.norm(los, axis=1, keepdims=True)
    up = rng.normal(size=(20, 3))
    up[0] = los[0]                                            # degenerate: the fallback axis
    A = rendezvous_truth.look_at(los, up)
    np.testing.assert_allclose(A @ np.swapaxes(A, 1, 2), np.broadcast_to(np.eye(3), A.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(A), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("tij,tj->ti", A, los), np.tile([0.0, 0.0, 1.0], (20, 1)), atol=1e-12)


def test_filter_adjust_hook_sees_the_predicted_state():
    orbit = CircularOrbit(500e3)
    n = orbit.mean_motion
    times = np.array([0.0, 50.0, 100.0])
    x0 = np.array([[0.0, -500.0, 0.0, 0.0, 0.0, 0.0]])
    P0 = np.diag([10.0, 10.0, 10.0, 0.01, 0.01, 0.01])[None] ** 2
    u = -np.einsum("tij,j->ti", hill_to_icrs(orbit, times), x0[0, :3] / 500.0)[None]
    C = rf.isotropic_bearing_cov(u[0], 1e-5)[None]
    seen = []
    cfg = FilterConfig()
    xs, Ps = rf.run(x0, P0, times, orbit, cfg, bearings=u, bearing_cov=C,
                    adjust=lambda k, x, P, b, c: (seen.append((k, x.copy())), (b, c))[1])
    xs0, _ = rf.run(x0, P0, times, orbit, cfg, bearings=u, bearing_cov=C)
    np.testing.assert_array_equal(xs, xs0)                    # an identity hook changes nothing
    xp, _ = rf.predict(xs[:, 0], Ps[:, 0], 50.0, n, cfg)
    assert [k for k, _ in seen] == [0, 1, 2]
    np.testing.assert_allclose(seen[1][1], xp)                # frame 1's hook got frame 0's estimate predicted


@pytest.fixture(scope="module")
def small_runs(tmp_path_factory):
    lake = Lake(tmp_path_factory.mktemp("rdv") / "lake")
    runs = {}
    for name, cfg, n in (("far", FAR_SMALL, 4), ("close", CLOSE_SMALL, 3)):
        plan = rz.plan_run(None, cfg, cases=n, run_id=f"rdv-{name}")
        rz.start_run(plan, lake, workers=1, progress=False)
        runs[name] = plan
    return lake, runs


def _rows(lake, run, dataset):
    t = pq.read_table(lake.root / dataset / f"run={run}")
    return {k: np.array([np.nan if v is None else v for v in t.column(k).to_pylist()])
            if t.schema.field(k).type.num_fields == 0 and str(t.schema.field(k).type) != "string"
            else t.column(k).to_pylist() for k in t.column_names}


def test_a_case_reproduces_its_rows_from_its_seed(small_runs):
    lake, runs = small_runs
    plan = runs["far"]
    spec = rz.spec_from_dict(plan.spec)
    ctx = rz.make_context(spec)
    stored = pq.read_table(lake.root / "rendezvous_frames" / f"run={plan.run_id}")
    drop = ["t_render_ns", "t_nav_ns"]
    for case in (0, 2):
        got = rz.compute_case(spec, ctx, case)["frames"].drop(drop)
        want = stored.filter(np.asarray(stored.column("case_id").to_pylist()) == case).sort_by("frame")
        want = want.select(got.column_names)
        assert got.equals(want.cast(got.schema)), f"case {case} differs from its stored rows"


def test_report_numbers_equal_numpy_over_the_rows(small_runs):
    lake, runs = small_runs
    for name in ("far", "close"):
        run = runs[name].run_id
        f = _rows(lake, run, "rendezvous_frames")
        rep = report.build(lake, run)
        j = rep["json"]
        assert j["bearing_point"] == ("silhouette" if name == "close" else "brightness")   # the presets' specs
        assert ("through the target's silhouette centre" in report.text(rep)) == (name == "close")
        used = f["bearing_used"].astype(bool)
        assert j["approaches"] == len(set(f["case_id"]))
        assert j["availability"] == pytest.approx(used.mean())
        be = f["bearing_err_arcsec"][used]
        assert j["bearing_err_rms_arcsec"] == pytest.approx(np.sqrt(np.mean(be ** 2)))
        frames = f["frame"].astype(int)
        for r in j["per_frame"]:
            sel = frames == r["frame"]
            assert r["mean_nees"] == pytest.approx(f["nees"][sel].mean())
            assert r["pos_err_rms_m"] == pytest.approx(np.sqrt(np.mean(f["pos_err_m"][sel] ** 2)))
            for ax, key in zip("xyz", ("z2_radial", "z2_along", "z2_cross")):   # Hill x radial, y along, z cross
                z = (f[f"est_{ax}"][sel] - f[f"true_{ax}"][sel]) / f[f"sigma_{ax}"][sel]
                assert r[key] == pytest.approx(np.mean(z ** 2)), (r["frame"], key)
        lo, hi = rf.chi2_mean_bounds(6, j["approaches"])
        conv = rz.spec_from_dict(runs[name].spec).cfg.converged_after_frames
        inside = [lo <= f["nees"][frames == k].mean() <= hi for k in range(conv, frames.max() + 1)]
        assert j["nees_frames_inside"] == sum(inside) and j["nees_frames_checked"] == len(inside)
        assert j["nees_first_frames_inside"] == sum(inside)       # fewer than 100 approaches: the same ones
        # the simultaneous band: each approach's NEES after convergence, its lag-1 correlation by np.corrcoef
        ks = range(conv, frames.max() + 1)
        N = np.array([[f["nees"][(frames == k) & (f["case_id"] == c)][0] for k in ks] for c in sorted(set(f["case_id"]))])
        lag1 = np.mean([np.corrcoef(N[:, i], N[:, i + 1])[0, 1] for i in range(N.shape[1] - 1)])
        assert j["nees_band_lag1"] == pytest.approx(lag1)
        blo, bhi, _ = simultaneous_mean_bounds(6, j["approaches"], len(inside), lag1)
        assert j["nees_band_95"] == pytest.approx([blo, bhi])
        assert j["nees_band_frames_inside"] == sum(blo <= f["nees"][frames == k].mean() <= bhi for k in ks)
        assert j["nees_bounds_inside_probability"] == pytest.approx(inside_probability(len(inside), lag1))
        assert "simultaneous 95 % band" in report.text(rep)
        if name == "far":
            o = f["orbit_after_burn"].astype(bool)
            assert o.sum() == j["approaches"] and set(frames[o]) == {10}
            pct = f["pos_err_m"][o] / f["range_m"][o]
            assert j["orbit_pos_err_rms_pct"] == pytest.approx(100 * np.sqrt(np.mean(pct ** 2)))
        else:
            late = frames >= report.AFTER_FRAMES
            lr = late & f["range_used"].astype(bool)
            assert lr.sum() > 0
            assert j["late_vel_err_rms_m_s"] == pytest.approx(np.sqrt(np.mean(f["vel_err_m_s"][late] ** 2)))
            assert j["filtered_range_err_rms_m"] == pytest.approx(np.sqrt(np.mean(f["range_err_m"][lr] ** 2)))
            e = f["range_meas_m"][lr] - f["range_m"][lr]
            assert j["blobber_range_err_rms_m"] == pytest.approx(np.sqrt(np.mean(e ** 2)))
            # the filter's range error is the estimate's, not the measurement's
            est = np.sqrt(f["est_x"] ** 2 + f["est_y"] ** 2 + f["est_z"] ** 2)
            np.testing.assert_allclose(f["range_err_m"], est - f["range_m"], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("body,field,allowed", [
    ("[rendezvous]\naltitude_km = 10.0\n", "rendezvous.altitude_km", "150"),
    ("[rendezvous]\nmanoeuvre_times_s = [99999.0]\nmanoeuvre_dv_m_s = [[0.0, 0.1, 0.0]]\n",
     "rendezvous.manoeuvre_times_s[0]", "(0, "),
    ("[rendezvous]\ndispersion_position_m = [1.0, -5.0, 1.0]\n", "rendezvous.dispersion_position_m.1",
     "greater than or equal to 0"),
    ('[rendezvous]\nbearing_point = "silhouette"\nphase_correction = false\n', "rendezvous.bearing_point",
     '"brightness" with camera = "star"'),
])
def test_a_hostile_spec_value_is_one_line_naming_file_field_and_range(tmp_path, body, field, allowed):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(body)
    p = subprocess.run([sys.executable, "-m", "dualsight.jobs.cli.main", "rendezvous", "run", "--config", str(cfg),
                        "--cases", "1", "--lake", str(tmp_path / "lake")], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in p.stderr
    assert str(cfg) in lines[0] and field in lines[0] and allowed in lines[0], lines[0]
    assert not (tmp_path / "lake" / "rendezvous_cases").exists()


def test_replay_records_the_verified_approach_and_refuses_a_tampered_row(small_runs, tmp_path):
    from test_replay import column, read_rrd                  # rerun's reader (skips without rerun.chunk)

    from dualsight.jobs.cli.main import main

    lake, runs = small_runs
    run = runs["far"].run_id
    out = tmp_path / "a.rrd"
    assert main(["rendezvous", "replay", "--lake", str(lake.root), "--run", run, "--case", "2", "-o", str(out)]) == 0
    rec = read_rrd(out)
    f = _rows(lake, run, "rendezvous_frames")
    k = f["case_id"] == 2
    T = int(k.sum())
    assert len(rec["/camera/image"]) == T
    paths = column(rec["/hill/truth"], "LineStrips3D:strips")
    assert len(paths) == T
    last = np.asarray(paths[-1][0], np.float64)               # the whole true path at the last frame
    order = np.argsort(f["frame"][k])
    want = np.stack([f[f"true_{a}"][k][order] for a in "xyz"], -1)
    np.testing.assert_allclose(last, want, rtol=1e-6, atol=1e-3)      # float32 in the recording
    est = np.asarray(column(rec["/hill/estimate"], "LineStrips3D:strips")[-1][0], np.float64)
    np.testing.assert_allclose(est, np.stack([f[f"est_{a}"][k][order] for a in "xyz"], -1), rtol=1e-6, atol=1e-3)
    # a tampered row is refused, naming the column
    bad = tmp_path / "lake"
    import shutil

    shutil.copytree(lake.root, bad)
    part = sorted((bad / "rendezvous_frames" / f"run={run}").glob("*.parquet"))[0]
    t = pq.read_table(part)
    col = t.column("nees").to_pylist()
    rows = np.flatnonzero((np.asarray(t.column("case_id").to_pylist()) == 2))
    col[int(rows[3])] = col[int(rows[3])] + 1.0
    t = t.set_column(t.schema.get_field_index("nees"), "nees", pa.array(col, pa.float64()))
    pq.write_table(t, part)
    journal = bad / "_manifests" / f"{run}.shards.jsonl"             # its byte count, so the lake serves it
    entries = [json.loads(x) for x in journal.read_text().splitlines()]
    for e in entries:
        if e["case_start"] <= 2 < e["case_stop"]:
            e["bytes"]["rendezvous_frames"] = part.stat().st_size
    journal.write_text("".join(json.dumps(e) + "\n" for e in entries))
    p = subprocess.run([sys.executable, "-m", "dualsight.jobs.cli.main", "rendezvous", "replay", "--lake", str(bad),
                        "--run", run, "--case", "2", "-o", str(tmp_path / "b.rrd")], capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 2 and "column nees" in p.stderr and "frame 3" in p.stderr, p.stderr


def test_api_run_is_the_command(tmp_path):
    import dualsight

    from dualsight.jobs.cli.main import main

    cfg = tmp_path / "small.toml"
    cfg.write_text("[rendezvous]\nduration_s = 1200.0\nframe_interval_s = 300.0\nmanoeuvre_times_s = [600.0]\n")
    rid = dualsight.run("rendezvous", str(cfg), cases=2, seed=7, lake=tmp_path / "api", workers=1)
    assert main(["rendezvous", "run", "--config", str(cfg), "--cases", "2", "--seed", "7", "--lake",
                 str(tmp_path / "cli"), "--workers", "1", "--no-progress"]) == 0
    a, c = Lake(tmp_path / "api"), Lake(tmp_path / "cli")
    assert a.read_manifest(rid)["spec_hash"] == c.read_manifest(rid)["spec_hash"]
    for ds in ("rendezvous_cases", "rendezvous_frames"):
        ta, tc = (pq.read_table(x.root / ds / f"run={rid}") for x in (a, c))
        keep = [n for n in ta.column_names if not n.startswith("t_") or n in ("t_s", "t_since_burn_s")]
        assert ta.select(keep).equals(tc.select(keep)), ds


@pytest.mark.parametrize("name,preset", [("far", "far"), ("close", "close")])
def test_the_examples_are_their_presets(name, preset):
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "examples" / "rendezvous" / f"{name}.toml"
    assert rendezvous_spec.resolve_spec(None, path) == rendezvous_spec.resolve_spec(preset, None)


def test_photocentre_table_of_a_sphere_is_the_lit_sphere_and_the_correction_moves_away_from_the_sun():
    from dualsight.scene.target_photometry import TargetShape

    R = 0.5
    sphere = TargetShape(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros((1, 3)),
                         np.array([R]), np.array([0.3]), R)
    a, mean, spread = photocentre_table(sphere, n=50)
    inner = (a > 0) & (a < np.radians(179))
    ai = a[inner]
    # Lambertian sphere's centre of brightness towards the Sun: (3 pi / 16) R sin a (1 + cos a) / (sin a + (pi - a)
    # cos a) (e.g. Lester, McCall & Tatum 1979), written out here
    want = 3 * np.pi / 16 * R * np.sin(ai) * (1 + np.cos(ai)) / (np.sin(ai) + (np.pi - ai) * np.cos(ai))
    np.testing.assert_allclose(mean[inner], want, rtol=1e-9)
    np.testing.assert_allclose(spread[inner], 0.0, atol=1e-9)     # a sphere looks the same in every attitude
    # the select hook moves the bearing by the table's offset / predicted range, away from the Sun
    spec = _spec(None)
    ctx = rendezvous_context.RendezvousContext(None, sphere, (a, mean, spread))
    s = rendezvous_truth.sun_icrs(spec)
    e = np.cross(s, [0.0, 0.0, 1.0])
    e /= np.linalg.norm(e)
    al = np.radians(60.0)
    u = -np.cos(al) * s + np.sin(al) * e                        # chaser -> target; Sun-target-chaser angle 60 deg
    m = {"u": np.full((1, 3), np.nan), "C": np.zeros((1, 3, 3)), "u_used": np.full((1, 3), np.nan),
         "C_used": np.zeros((1, 3, 3)), "target_xy": np.full((1, 2), np.nan), "bearing_used": np.zeros(1, bool),
         "found_by": np.zeros(1, np.int8), "found_true": np.zeros(1, bool)}
    m["cand"] = {"frame": np.array([0]), "u": u[None], "C": np.zeros((1, 3, 3)), "xy": np.zeros((1, 2)),
                 "true": np.array([True])}
    sel = rendezvous_filter.target_selector(spec, ctx, m)
    x = np.array([[0.0, -1000.0, 0.0, 0.0, 0.0, 0.0]])
    # a Hill -> ICRS rotation whose along-track axis is u: rho = -1000 m along-track, so the predicted line of
    # sight -R rho^ is u itself
    R_k = np.stack([np.cross(u, s) / np.linalg.norm(np.cross(u, s)), u, s], axis=1)
    R_k[:, 2] = np.cross(R_k[:, 0], R_k[:, 1])
    u2, C2, G2 = sel(0, x, np.eye(6)[None], R_k)
    assert not np.any(G2)                                       # no photocentre statistics: no bias states
    assert m["bearing_used"][0] and m["found_by"][0] in (1, 3)      # gate (star) or resolved_blob (prox)
    s_perp = (s - np.dot(s, u) * u) / np.linalg.norm(s - np.dot(s, u) * u)
    off = 3 * np.pi / 16 * R * np.sin(al) * (1 + np.cos(al)) / (np.sin(al) + (np.pi - al) * np.cos(al))
    assert np.dot(u2[0] - u, s_perp) == pytest.approx(-off / 1000.0, rel=1e-4)   # grid: 60 deg is on it
    extra = spec.cfg.cob_sigma_frac * 2 * R / 1000.0
    assert np.trace(C2[0]) / 2 == pytest.approx(extra ** 2, rel=1e-6)   # no spread for a sphere


def test_resume_keeps_shards_and_another_spec_under_the_id_is_refused(tmp_path):
    from dualsight.jobs.cli.main import main

    cfg = tmp_path / "small.toml"
    cfg.write_text("[rendezvous]\nduration_s = 600.0\nframe_interval_s = 300.0\nmanoeuvre_times_s = [300.0]\n")
    args = ["rendezvous", "run", "--config", str(cfg), "--cases", "4", "--lake", str(tmp_path / "lake"), "--run", "r",
            "--workers", "1", "--shard-size", "2", "--no-progress"]
    assert main(args) == 0
    lost = tmp_path / "lake" / "rendezvous_frames" / "run=r" / "part-000001.parquet"
    kept = tmp_path / "lake" / "rendezvous_frames" / "run=r" / "part-000000.parquet"
    before = kept.stat().st_mtime_ns
    lost.unlink()
    assert main(args) == 0
    m = Lake(tmp_path / "lake").read_manifest("r")
    assert lost.exists() and kept.stat().st_mtime_ns == before
    assert m["executions"][-1]["cases_run"] == 2 and m["status"] == "complete"
    cfg.write_text("[rendezvous]\nduration_s = 600.0\nframe_interval_s = 200.0\nmanoeuvre_times_s = [400.0]\n")
    p = subprocess.run([sys.executable, "-m", "dualsight.jobs.cli.main", *args], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1 and "other settings" in p.stderr, p.stderr


def _with_planted(det, B, extra):
    """Detections ``det`` of a batch of B frames plus ``extra`` = [(frame, x, y, flux, npix)], re-sorted by (frame,
    flux descending) as kernels.detect.Detections are."""
    import dataclasses

    case = np.concatenate([np.asarray(det.case, np.int64), [e[0] for e in extra]])
    x = np.concatenate([det.x, [e[1] for e in extra]])
    y = np.concatenate([det.y, [e[2] for e in extra]])
    flux = np.concatenate([det.flux, [e[3] for e in extra]])
    npix = np.concatenate([det.npix, [e[4] for e in extra]]).astype(np.asarray(det.npix).dtype)
    o = np.lexsort((-flux, case))
    kw = {"case": case[o].astype(np.asarray(det.case).dtype), "x": x[o], "y": y[o], "flux": flux[o], "npix": npix[o],
          "offsets": np.searchsorted(case[o], np.arange(B + 1)).astype(np.int64)}
    if det.sigma_px is not None:
        kw["sigma_px"] = np.concatenate([det.sigma_px, np.full(len(extra), 0.05)])[o]
    if det.saturated is not None:
        kw["saturated"] = np.concatenate([det.saturated, np.zeros(len(extra), bool)])[o]
    return dataclasses.replace(det, **kw)


def test_planted_fixed_false_detections_never_become_the_target(monkeypatch):
    """The far chain (stars + target rendered, identified, the target found by nav/target_finding) with a hot pixel
    (the same pixel in every frame) and an uncatalogued star (a fixed ICRS direction 0.7 deg from the target's
    first line of sight, as bright as a V 3 star) planted into the detections: neither is ever a candidate nor
    picked; the true target (known from the truth only to score) is picked in every frame where it was detected."""
    spec = _spec(None)
    spec = rz.spec_from_dict({**spec.to_dict(), "rendezvous": {**spec.to_dict()["rendezvous"],
                                                             "duration_s": 7 * spec.cfg.frame_interval_s + 1.0}})
    ctx = rz.make_context(spec)
    draw = rendezvous_truth.draw_case(spec, 3)
    truth = rendezvous_truth.truth_trajectory(spec, draw)
    geo = rendezvous_truth.geometry(spec, draw, truth)
    cam = spec.camera
    star_dir = geo["u_true"][0] + 0.012 * np.cross(geo["u_true"][0], geo["R"][0][:, 2])
    star_dir /= np.linalg.norm(star_dir)
    hot = (100.25, 600.75)
    real = star.render_and_detect
    seen = {"star": 0}

    def planted(field_, seeds, camera, sensor, detect_cfg, keep_images=False, attitude=None, **kw):
        r = real(field_, seeds, camera, sensor, detect_cfg, keep_images=keep_images, attitude=attitude, **kw)
        B = len(seeds)
        extra = [(b, hot[0], hot[1], 3e4, 9) for b in range(B)]
        for b in range(B):
            v = attitude[b] @ star_dir
            p, _ = cam.project(v[None])
            if v[2] > 0 and np.all(np.isfinite(p)) and cam.in_image(p)[0]:
                extra.append((b, p[0, 0], p[0, 1], 2e4, 9))
                seen["star"] += 1
        return type(r)(**{**{k: getattr(r, k) for k in r.__dataclass_fields__},
                          "detections": _with_planted(r.detections, B, extra)})

    monkeypatch.setattr(star, "render_and_detect", planted)
    m, _ = rendezvous_measure.measure_star(spec, ctx, draw, geo)
    xs, _ = rendezvous_filter.run_filter(spec, ctx, draw, m)
    assert seen["star"] >= 2                                      # the planted star is in at least two frames
    c = m["cand"]
    assert not np.any(np.hypot(c["xy"][:, 0] - hot[0], c["xy"][:, 1] - hot[1]) < 0.5)
    assert not np.any(c["u"] @ star_dir > math.cos(1e-4))
    assert len(c["frame"]) <= spec.cfg.frames + 1                # the catalog stars are matched, not candidates
    used = m["bearing_used"]
    assert used.sum() >= spec.cfg.frames - 1
    assert m["found_true"][used].all()
    assert np.all(used[m["detected"]])
