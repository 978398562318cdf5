"""The Python API (``dualsight/api.py``, ``docs/api.md``) against independent truths.

* Every ```python example of docs/api.md is executed (from a scratch folder, ``examples/`` meaning the
  repository's, ``../shared/data/real`` the real images) and its results are checked: the ESA frames against
  the plate solutions of ``truth.json`` (another solver) and against the rows a ``dualsight hil star`` run
  stores; the campaign against the rows and run id of ``dualsight star run`` with the same options, the prox
  sweep against ``dualsight prox sweep``'s.
* ``solve`` on all eight ESA frames equals the ``hil star`` lake rows, column by column; without the real
  data, a frame rendered at a known attitude is solved from an array and from a file like the command.
* ``Lake.runs`` / ``Lake.sql`` are what ``dualsight runs --json`` / ``dualsight sql`` give, damaged files
  included; ``run`` has the command line's identity, resume and refusals, for every kind it starts (star, the
  prox sweep and trajectory, the self-test): the same run id, rows and seed as the command.
* ``import dualsight`` stays light (the facade resolves on first use).
"""

from __future__ import annotations

import ast
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import tomli_w

import dualsight
from dualsight.errors import ConfigError, ImageError, InputError
from dualsight.scene.camera import Camera
from helpers import ROOT, lake_rows, orion_field, run_cli, shared_real, snapshot

DOC = ROOT / "docs" / "api.md"
CAMERA = ROOT / "examples" / "cameras" / "esa_tetra3.toml"
ESA = shared_real() / "esa_tetra3"
TRUTH = ESA / "truth.json"
ARCSEC = math.pi / (180 * 3600)
needs_esa = pytest.mark.skipif(not TRUTH.exists(), reason=f"ESA tetra3 frames not found at {ESA}")

HIL_TIMING = ("t_read_ns", "t_detect_ns", "t_identify_ns", "t_attitude_ns", "t_alt_ns", "t_total_ns")
STAR_TIMING = ("t_sample_ns", "t_render_ns", "t_detect_ns", "t_identify_ns", "t_attitude_ns", "t_robust_ns",
               "t_total_ns")
STAR_ORDER = {"star_cases": "case_id", "star_detections": "case_id, det_index"}
PROX_TIMING = ("t_sample_ns", "t_render_ns", "t_blob_paper_ns", "t_blob_subpixel_ns", "t_total_ns")
PROX_ORDER = {"prox_cases": "case_id"}
TRACK_TIMING = ("t_render_ns", "t_detect_ns", "t_predict_ns", "t_track_ns", "t_lis_ns", "t_rate_ns", "t_filter_ns",
                "t_nav_ns", "t_shadow_lis_ns", "t_sample_ns", "t_total_ns")


def rotation_angle_arcsec(A: np.ndarray, B: np.ndarray) -> float:
    """Angle of the rotation between two attitudes (arcsec), from the skew part of A B^T (exact for small
    angles, where the trace formula's arccos loses the digits)."""
    D = np.asarray(A) @ np.asarray(B).T
    s = np.linalg.norm([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]]) / 2.0
    return math.degrees(math.atan2(s, (np.trace(D) - 1.0) / 2.0)) * 3600.0


def boresight_arcsec(A: np.ndarray, B: np.ndarray) -> float:
    """Angle between the two attitudes' boresights (third rows), arcsec."""
    a, b = np.asarray(A)[2], np.asarray(B)[2]
    return math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), float(np.dot(a, b)))) * 3600.0


def canonical(rows) -> str:
    """Rows as canonical JSON text: equal texts = equal values, NaN equal to NaN (which ``==`` is not)."""
    return json.dumps(rows, sort_keys=True, default=str)


def comparable(row: dict) -> dict:
    """A ``hil_star`` row without what differs by construction between a solve and a run: the case id, the
    timings, the comparison method's columns (``solve`` does not run it) and the decoding columns of the
    reader loop (width, height, bits, shift, digest: not part of ``solve_frames``)."""
    skip = {"case_id", "run", "width", "height", "bit_depth", "shift", "image_digest", *HIL_TIMING}
    return {k: v for k, v in row.items() if k not in skip and not k.startswith("alt_")}


# ============================================================================================ fixtures
@pytest.fixture(scope="module")
def esa_run(tmp_path_factory):
    """``dualsight hil star`` over the eight ESA frames at its defaults: the lake rows per image name."""
    if not TRUTH.exists():
        pytest.skip(f"ESA tetra3 frames not found at {ESA}")
    lake = tmp_path_factory.mktemp("esa") / "lake"
    rc, out, err = run_cli(["hil", "star", ESA, "--camera", CAMERA, "--lake", lake, "--run", "esa", "--workers", "1",
                            "--no-progress"])
    assert rc == 0, err
    rows = lake_rows(lake, "esa", {"hil_star": "case_id", "hil_star_stars": "case_id, det_index"})
    images = {r["image"]: r for r in rows["hil_star"]}
    stars = {name: [s for s in rows["hil_star_stars"] if s["image"] == name] for name in images}
    return {"rows": images, "stars": stars, "truth": json.loads(TRUTH.read_text())}


def check_against_run_and_truth(sol, name: str, esa_run) -> float:
    """``sol`` (a Solution of ESA frame ``name``) equals the run's row and stars, and is near the plate
    solution; returns its boresight error against truth.json (arcsec)."""
    row = esa_run["rows"][name]
    assert sol.status == "success" and sol.identified and row["identified"]
    mine, theirs = comparable(dict(sol.row)), comparable(row)
    mine.pop("path"), theirs.pop("path")
    assert mine.keys() <= theirs.keys()
    assert {k: v for k, v in mine.items()} == {k: theirs[k] for k in mine}, name
    A = np.asarray(row["A_est"]).reshape(3, 3)
    assert np.array_equal(sol.attitude, A)                           # bit for bit
    assert sol.ra_deg == math.degrees(row["ra_rad"]) and sol.roll_deg == row["roll_deg"] and sol.T == row["T"]
    stars = esa_run["stars"][name]
    assert [(s.hip, s.x_px, s.y_px, s.vmag, s.residual_arcsec * ARCSEC) for s in sol.stars] == \
        [(s["hip"], s["x_px"], s["y_px"], s["vmag"], pytest.approx(s["residual_rad"], rel=1e-12)) for s in stars]
    R = np.asarray(esa_run["truth"][name]["R_icrs_to_cam"])
    err = boresight_arcsec(sol.attitude, R)
    assert err < 30.0, (name, err)                                  # hil star's own bound (measured 0.4-6.4)
    assert rotation_angle_arcsec(sol.attitude, R) < 60.0, name      # roll included (measured 0.9-19)
    # the numbers the Solution states are the matrix's: boresight RA/Dec from its third row
    ra, dec = math.radians(sol.ra_deg), math.radians(sol.dec_deg)
    assert np.allclose(sol.attitude[2], [math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec)],
                       atol=1e-12)
    return err


# ============================================================================================ docs/api.md
def doc_examples() -> list[tuple[str, str]]:
    """(name, code) of every ```python fence of docs/api.md; the first line names it: ``# example: <name>``."""
    out = []
    for code in re.findall(r"^```python\n(.*?)^```", DOC.read_text(), flags=re.S | re.M):
        m = re.match(r"# example: ([\w-]+)\n", code)
        assert m, f"a python example of {DOC.name} does not start with '# example: <name>':\n{code[:200]}"
        out.append((m.group(1), code))
    return out


EXAMPLES = doc_examples()


def test_the_doc_has_the_five_kinds_of_example():
    assert [n for n, _ in EXAMPLES] == ["solve-esa", "solve-array", "campaign", "pandas", "prox-sweep"]


@pytest.fixture(scope="module")
def docs_dir(tmp_path_factory):
    """The scratch folder every example runs in (the campaign's lake is shared by the pandas example)."""
    return tmp_path_factory.mktemp("docs")


def run_example(code: str, folder: Path, monkeypatch) -> dict:
    code = code.replace("../shared/data/real", shared_real().as_posix()).replace(
        '"examples/', f'"{(ROOT / "examples").as_posix()}/')
    monkeypatch.chdir(folder)
    namespace: dict = {"__name__": "__main__"}
    exec(compile(code, str(DOC), "exec"), namespace)
    return namespace


@pytest.mark.parametrize("name, code", EXAMPLES, ids=[n for n, _ in EXAMPLES])
def test_doc_example(name, code, docs_dir, monkeypatch, request, capsys):
    if "../shared" in code and not TRUTH.exists():
        pytest.skip(f"needs the ESA tetra3 frames, not found at {ESA}")
    if name == "pandas":
        pytest.importorskip("pandas", reason="pandas is not installed (dualsight does not depend on it)")
    ns = run_example(code, docs_dir, monkeypatch)
    out = capsys.readouterr().out
    CHECKS[name](ns, out, request)


def check_solve_esa(ns, out, request):
    esa_run = request.getfixturevalue("esa_run")
    sol = ns["sol"]
    check_against_run_and_truth(sol, Path(ns["frame"]).name, esa_run)
    assert f"RA {sol.ra_deg:.4f} deg" in out and f"HIP {sol.stars[0].hip:6d}" in out


def check_solve_array(ns, out, request):
    esa_run = request.getfixturevalue("esa_run")
    sol, path = ns["sol"], Path(ns["path"])
    assert sol.image == "<array>" and sol.timings.read_ms is None
    from_file = dualsight.solve(path, CAMERA)
    assert np.array_equal(sol.attitude, from_file.attitude) and sol.stars == from_file.stars
    mine = comparable(dict(sol.row))
    theirs = comparable(dict(from_file.row))
    assert {k: v for k, v in mine.items() if k not in ("image", "path")} == \
        {k: v for k, v in theirs.items() if k not in ("image", "path")}
    check_against_run_and_truth(from_file, path.name, esa_run)
    # without the image's date the catalog is at J2000.0: another catalog, still the right sky (~1 arcsec)
    j2000 = dualsight.solve(ns["counts"], ns["camera"])
    assert j2000.identified and boresight_arcsec(j2000.attitude, sol.attitude) < 5.0


def check_campaign(ns, out, request):
    """The example's run is ``dualsight star run --preset paper --cases 200 --seed 1``: same id, same rows."""
    lake = request.getfixturevalue("tmp_path") / "cli-lake"
    rc, _, err = run_cli(["star", "run", "--preset", "paper", "--cases", "200", "--seed", "1", "--lake", lake,
                          "--workers", "1", "--no-progress"])
    assert rc == 0, err
    cli_id = re.search(r"^run (\S+): complete, 200 cases", err, flags=re.M).group(1)
    run_id = ns["run_id"]
    assert run_id == cli_id and re.fullmatch(r"star-1-200-[0-9a-f]{8}", run_id)
    docs_lake = Path("demo-lake").resolve()
    api_rows = lake_rows(docs_lake, run_id, STAR_ORDER, STAR_TIMING)
    cli_rows = lake_rows(lake, run_id, STAR_ORDER, STAR_TIMING)
    assert len(api_rows["star_cases"]) == 200 and canonical(api_rows) == canonical(cli_rows)
    # the manifests agree on everything that identifies the run (not on when and where it ran)
    from dualsight.warehouse.lake import Lake as Store

    m_api, m_cli = Store(docs_lake).read_manifest(run_id), Store(lake).read_manifest(run_id)
    for key in ("spec", "spec_hash", "n_cases", "shard_size", "n_shards", "seed", "kind", "catalog", "datasets"):
        assert m_api[key] == m_cli[key], key
    # Lake.sql's answers are the rows themselves, and the status table is what `dualsight sql` prints for it
    cases = ns["cases"]
    assert cases == [{k: r[k] for k in ("case_id", "T", "n_identified", "status")} for r in cli_rows["star_cases"]]
    table = ns["table"]
    rc, cli_out, err = run_cli(["sql", f"SELECT status, count(*) AS cases FROM star_cases WHERE run = '{run_id}' "
                                       "GROUP BY status ORDER BY cases DESC", "--lake", lake, "--json"])
    assert rc == 0, err
    assert [{k: r[k] for k in ("status", "cases")} for r in table.to_pylist()] == json.loads(cli_out)
    assert sum(table.column("cases").to_pylist()) == 200
    records = ns["lake"].runs()
    assert [r.run_id for r in records] == [run_id] and records[0].status == "complete"


def check_pandas(ns, out, request):
    df = ns["df"]
    table = ns["dualsight"].Lake("demo-lake").sql(f"SELECT * FROM star_cases WHERE run = '{ns['run_id']}'")
    assert len(df) == table.num_rows == 200 and list(df.columns) == table.column_names
    assert df["status"].value_counts().to_dict() == {s: table.column("status").to_pylist().count(s)
                                                     for s in set(table.column("status").to_pylist())}


def check_prox_sweep(ns, out, request):
    """The example's run is ``dualsight prox sweep --preset paper --ranges 2 10 50 --orientations 4 --seed 1``:
    same id, same rows; its query's answer is ``dualsight sql``'s, and the rows' own counts."""
    lake = request.getfixturevalue("tmp_path") / "cli-lake"
    rc, _, err = run_cli(["prox", "sweep", "--preset", "paper", "--ranges", "2", "10", "50", "--orientations", "4",
                          "--seed", "1", "--lake", lake, "--workers", "1", "--no-progress"])
    assert rc == 0, err
    run_id = ns["run_id"]
    assert run_id == "prox-sweep-paper-1-12" and f"run {run_id}: complete, 12 cases in {lake}" in err
    assert out.splitlines()[0] == run_id
    docs_lake = Path("prox-lake").resolve()
    api_rows = lake_rows(docs_lake, run_id, PROX_ORDER, PROX_TIMING)["prox_cases"]
    cli_rows = lake_rows(lake, run_id, PROX_ORDER, PROX_TIMING)["prox_cases"]
    assert len(api_rows) == 12 and canonical(api_rows) == canonical(cli_rows)
    assert [(r["true_range_m"], r["seed"]) for r in api_rows] == [(r, 1) for r in (2.0, 10.0, 50.0) for _ in range(4)]
    from dualsight.warehouse.lake import Lake as Store

    m_api, m_cli = Store(docs_lake).read_manifest(run_id), Store(lake).read_manifest(run_id)
    for key in ("spec", "spec_hash", "n_cases", "shard_size", "seed", "kind", "label"):
        assert m_api[key] == m_cli[key], key
    rows = [ast.literal_eval(line) for line in out.splitlines()[1:]]  # the printed dicts
    rc, cli_out, err = run_cli(["sql", ns["query"], "--lake", lake, "--json"])
    assert rc == 0, err
    assert rows == json.loads(cli_out) and [r["true_range_m"] for r in rows] == [2.0, 10.0, 50.0]
    for r in rows:
        mine = [c for c in cli_rows if c["true_range_m"] == r["true_range_m"]]
        assert r["cases"] == 4 and r["found"] == sum(c["found"] for c in mine)
        errs = [abs(c["subpixel_range_est_m"] / c["true_range_m"] - 1) for c in mine]
        assert r["subpixel_err_pct"] == pytest.approx(100 * sum(errs) / 4, abs=0.006)


CHECKS = {"solve-esa": check_solve_esa, "solve-array": check_solve_array, "campaign": check_campaign,
          "pandas": check_pandas, "prox-sweep": check_prox_sweep}


def test_every_example_has_a_check():
    assert {n for n, _ in EXAMPLES} == set(CHECKS)


# ============================================================================================ solve: ESA frames
@needs_esa
def test_solve_equals_hil_star_on_every_esa_frame(esa_run):
    """All eight frames: ``solve`` gives the run's rows bit for bit, and the plate solutions' attitude."""
    errors = {}
    for name in sorted(esa_run["truth"]):
        sol = dualsight.solve(ESA / name, CAMERA)
        errors[name] = check_against_run_and_truth(sol, name, esa_run)
        assert sol.timings.read_ms > 0 and sol.timings.total_ms >= sol.timings.detect_ms > 0
    assert len(errors) == 8 and max(errors.values()) < 10.0, errors     # measured 0.4-6.4 arcsec


@needs_esa
def test_settings_are_the_options_of_hil_star(esa_run, tmp_path):
    """A setting changes the answer exactly as the same option of the command does."""
    name = "2019-07-29T204726_Alt60_Azi45_Try1.tiff"
    lake = tmp_path / "lake"
    rc, _, err = run_cli(["hil", "star", ESA / name, "--camera", CAMERA, "--method", "paper", "--tolerance-arcsec",
                          "15", "--detector", "global", "--lake", lake, "--run", "x", "--workers", "1"])
    assert rc == 0, err
    row = lake_rows(lake, "x", {"hil_star": "case_id"})["hil_star"][0]
    sol = dualsight.solve(ESA / name, CAMERA, method="paper", tolerance_arcsec=15, detector="global")
    assert sol.method == "paper" and sol.detector == "global"
    mine, theirs = comparable(dict(sol.row)), comparable(row)
    assert {k: mine[k] for k in mine if k != "path"} == {k: theirs[k] for k in mine if k != "path"}
    # a config table takes effect, and the comparison method changes nothing in the answer
    table = {"method": "paper", "detector": "global", "voting": {"tolerance_arcsec": 15.0}}
    cfg = dualsight.solve(ESA / name, CAMERA, config=table)
    both = dualsight.solve(ESA / name, CAMERA, config=table, compare=True)
    assert cfg.method == "paper" and cfg.detector == "global" and cfg.identified
    assert cfg.row["tolerance_rad"] == pytest.approx(15 * ARCSEC) and "alt_T" not in cfg.row and "alt_T" in both.row
    assert np.array_equal(cfg.attitude, both.attitude) and cfg.stars == both.stars


# ============================================================================================ solve: a rendered frame
@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """A noisy frame rendered at a known attitude (tests/test_hil_star.py's round trip: sky gradient, shot and
    read noise, hot pixels), as 12-bit counts (uint16) and as a 16-bit TIFF holding them shifted by 4 like the
    ESA frames; with the attitude it was rendered at.  Needs no real data."""
    from dualsight.kernels.starfield import render_star_fields

    cam = Camera.from_toml(CAMERA)
    A, cat, sensor, f = orion_field(cam)
    img = render_star_fields(f.x, f.y, f.flux_e, f.valid, cam.width, cam.height, sensor,
                             np.array([12345], np.uint64))[0].astype(np.float64)
    img += 40.0 * np.linspace(0, 1, cam.width)[None, :]
    counts = np.clip(np.round(img), 0, 4095).astype(np.uint16)
    folder = tmp_path_factory.mktemp("rendered")
    tif = folder / "synthetic.tiff"
    cv2.imwrite(str(tif), counts << 4)
    return {"counts": counts, "tif": tif, "A": A, "camera": cam, "folder": folder}


def test_rendered_frame_from_array_and_file_as_hil_star(rendered):
    """The array, the file and ``dualsight hil star`` on the file agree bit for bit, near the rendering attitude."""
    cam = rendered["camera"]
    from_array = dualsight.solve(rendered["counts"], cam, epoch=2019.6)
    from_file = dualsight.solve(rendered["tif"], CAMERA, epoch=2019.6)
    assert from_array.identified and from_array.image == "<array>" and from_file.image == "synthetic.tiff"
    assert np.array_equal(from_array.attitude, from_file.attitude) and from_array.stars == from_file.stars
    assert boresight_arcsec(from_array.attitude, rendered["A"]) < 5.0            # measured 0.61 arcsec
    assert rotation_angle_arcsec(from_array.attitude, rendered["A"]) < 10.0      # measured 0.63 arcsec
    assert from_array.residual_median_arcsec < 5.0 and len(from_array.stars) >= 10
    lake = rendered["folder"] / "lake"
    rc, _, err = run_cli(["hil", "star", rendered["tif"], "--camera", CAMERA, "--epoch", "2019.6", "--lake", lake,
                          "--run", "r", "--workers", "1", "--no-progress"])
    assert rc == 0, err
    rows = lake_rows(lake, "r", {"hil_star": "case_id", "hil_star_stars": "case_id, det_index"})
    mine, theirs = comparable(dict(from_file.row)), comparable(rows["hil_star"][0])
    assert mine == {k: theirs[k] for k in mine}
    assert [s.hip for s in from_file.stars] == [s["hip"] for s in rows["hil_star_stars"]]
    # the whole record is typed and consistent
    sol = from_array
    assert sol.attitude.shape == (3, 3) and not sol.attitude.flags.writeable
    assert np.allclose(sol.attitude @ sol.attitude.T, np.eye(3), atol=1e-12)
    assert sol.xy_px.shape == (len(sol.stars), 2) and sol.hip.dtype == np.int64
    assert np.array_equal(sol.residuals_arcsec, [s.residual_arcsec for s in sol.stars])
    assert sol.T > 0 and 0 <= sol.p_chance < 1e-6 and sol.stars_used <= sol.stars_detected
    # exactly the sum (to 1 ns): no reference method ran, so no time is booked for it
    assert sol.timings.read_ms is None and sol.timings.total_ms == pytest.approx(
        sol.timings.detect_ms + sol.timings.identify_ms + sol.timings.attitude_ms, abs=1e-6)
    with pytest.raises(Exception):
        sol.T = 0                                                # frozen


def test_any_integer_or_float_dtype(rendered):
    counts, cam = rendered["counts"], rendered["camera"]
    ref = dualsight.solve(counts, cam, epoch=2019.6)
    for dtype in (np.int32, np.int64, np.uint32, np.float32, np.float64):   # the same values: bit for bit
        sol = dualsight.solve(counts.astype(dtype), cam, epoch=2019.6)
        assert np.array_equal(sol.attitude, ref.attitude) and sol.stars == ref.stars, dtype
    for dtype in (np.float16,):                                 # values above 2048 rounded to even: ~ the same
        sol = dualsight.solve(counts.astype(dtype), cam, epoch=2019.6)
        assert sol.identified and boresight_arcsec(sol.attitude, ref.attitude) < 1.0, dtype
        assert {s.hip for s in sol.stars} == {s.hip for s in ref.stars}, dtype
    signed = counts.astype(np.int32) - 100                      # negative values: float64, still solved
    assert dualsight.solve(signed, cam, epoch=2019.6).identified
    assert dualsight.solve(np.asfortranarray(counts), cam, epoch=2019.6).stars == ref.stars
    strided = np.pad(counts, ((0, 0), (0, 1)))[:, :-1]         # a view with a row stride of 1025 values
    assert not strided.flags.c_contiguous and dualsight.solve(strided, cam, epoch=2019.6).stars == ref.stars


@pytest.mark.parametrize("image, message", [
    (np.zeros((768, 1024, 3), np.uint16), "must be a 2-D (H, W) array"),
    (np.zeros((100, 100), np.uint16), "is 100 x 100 px, the camera says 1024 x 768"),
    (np.zeros((768, 1024), bool), "integer or float pixel values"),
    (np.zeros((768, 1024), np.complex64), "integer or float pixel values"),
    (np.full((768, 1024), np.nan), "non-finite pixels"),
    (np.full((768, 1024), 2**60, np.int64), "beyond 2^53"),
    ([[1, 2], [3, 4]], "must be an image file path or a 2-D numpy array"),
])
def test_bad_images_are_one_line_image_errors(image, message):
    with pytest.raises(ImageError) as e:
        dualsight.solve(image, CAMERA)
    assert message in str(e.value) and "\n" not in str(e.value)


def test_bad_files_cameras_and_settings_are_one_line_errors(tmp_path):
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + b"x" * 100)
    frame = np.zeros((768, 1024), np.uint16)
    cases = [
        (lambda: dualsight.solve(tmp_path / "missing.tiff", CAMERA), ImageError, "missing.tiff: file not found"),
        (lambda: dualsight.solve(bad, CAMERA), ImageError, "broken.png"),
        (lambda: dualsight.solve(frame, tmp_path / "nocam.toml"), ConfigError, "nocam.toml: file not found"),
        (lambda: dualsight.solve(frame, 42), ConfigError, "camera: must be a camera file"),
        (lambda: dualsight.solve(frame, {"width": 1024}), ConfigError, "camera table"),
        (lambda: dualsight.solve(frame, CAMERA, tolerance=20), ConfigError, "unknown setting 'tolerance'"),
        (lambda: dualsight.solve(frame, CAMERA, max_stars=2.5), ConfigError, "[max_stars]: must be"),
        (lambda: dualsight.solve(frame, CAMERA, compare=1), ConfigError, "[compare]"),
        (lambda: dualsight.solve(frame, CAMERA, tolerance_arcsec=float("nan")), ConfigError, "finite"),
        (lambda: dualsight.solve(frame, CAMERA, method="best"), ConfigError, "method"),
        (lambda: dualsight.solve(frame, CAMERA, max_stars=1), ConfigError, "max_stars"),
        (lambda: dualsight.solve(frame, CAMERA, method="paper", config={"method": "robust"}), ConfigError,
         "contradicts"),
        (lambda: dualsight.solve(frame, CAMERA, config={"voting": {"bogus": 1}}), ConfigError, "voting.bogus"),
        (lambda: dualsight.solve(frame, CAMERA, config=tmp_path / "nocfg.toml"), ConfigError, "nocfg.toml"),
    ]
    for call, kind, text in cases:
        with pytest.raises(kind) as e:
            call()
        assert text in str(e.value) and "\n" not in str(e.value), (text, str(e.value))


def test_a_frame_without_stars_is_no_solution():
    sol = dualsight.solve(np.full((768, 1024), 200, np.uint16), CAMERA)
    assert sol.status == "no_solution" and not sol.identified and sol.attitude is None
    assert sol.ra_deg is None and sol.stars == () and sol.T == 0 and sol.xy_px.shape == (0, 2)


# ============================================================================================ Lake
@pytest.fixture(scope="module")
def small_lake(make_lake):
    """Three self-test runs; one manifest and one shard file damaged afterwards."""
    root = make_lake("api-lake", ["selftest", "run", "--cases", "50", "--seed", "1", "--run", "good"],
                     ["selftest", "run", "--cases", "60", "--seed", "3", "--run", "dmg-shard", "--shard-size", "20"],
                     ["selftest", "run", "--cases", "10", "--seed", "4", "--run", "dmg-man"])
    shard = sorted((root / "selftest_cases" / "run=dmg-shard").glob("*.parquet"))[1]
    shard.write_bytes(shard.read_bytes()[:100])
    (root / "_manifests" / "dmg-man.json").write_text('{"broken')
    return root


def test_lake_runs_is_what_dualsight_runs_lists(small_lake):
    rc, out, err = run_cli(["runs", "--lake", small_lake, "--json"])
    assert rc == 0, err
    docs = json.loads(out)
    records = dualsight.Lake(small_lake).runs()
    assert [r.run_id for r in records] == [d["run_id"] for d in docs] == ["dmg-man", "dmg-shard", "good"]
    damaged, dmg_shard, good = records
    assert damaged.damaged and damaged.status == "damaged" and damaged.manifest is None
    assert docs[0] == {"run_id": "dmg-man", "status": "damaged", "problem": damaged.problems[0]}
    assert "manifest is damaged" in damaged.problems[0]
    for r, d in zip(records[1:], docs[1:]):
        assert not r.damaged and r.manifest == {k: v for k, v in d.items() if k != "problems"}
        assert list(r.problems) == d["problems"] and r.kind == d["kind"] == "selftest"
        assert (r.n_cases, r.seed, r.spec_hash) == (d["n_cases"], d["seed"], d["spec_hash"])
    assert dmg_shard.status == "complete (damaged files)" and "part-000001.parquet" in dmg_shard.problems[0]
    assert good.status == "complete" and good.shards == "2/2" and good.problems == ()
    rc, table, _ = run_cli(["runs", "--lake", small_lake])
    for r in records:
        assert re.search(rf"^\s*{re.escape(r.run_id)}\s.*{re.escape(r.status.upper() if r.damaged else r.status)}",
                         table, flags=re.M), r.run_id


def test_lake_sql_is_dualsight_sql(small_lake):
    lake = dualsight.Lake(small_lake, warn=lambda m: None)
    for query in ("SELECT 1", "SELECT run, case_id, x, k FROM selftest_cases ORDER BY run, case_id",
                  "SELECT run, count(*) AS n, sum(x) AS sx FROM selftest_cases GROUP BY run ORDER BY run",
                  "SELECT 1 AS a; SELECT 2 AS b, [1, 2] AS l, NULL AS z", "SELECT * FROM selftest_items WHERE false",
                  "EXPLAIN SELECT count(*) FROM selftest_cases"):
        table = lake.sql(query)
        rc, out, err = run_cli(["sql", query, "--lake", small_lake, "--json"])
        assert rc == 0, err
        assert table.to_pylist() == json.loads(out), query
    # every row of every readable shard, none of the damaged one's (40 of dmg-shard's 60)
    counts = lake.sql("SELECT run, count(*) AS n FROM selftest_cases GROUP BY run").to_pylist()
    assert {r["run"]: r["n"] for r in counts} == {"good": 50, "dmg-shard": 40}


def test_lake_sql_is_read_only_with_one_line_errors(small_lake, tmp_path):
    lake = dualsight.Lake(small_lake, warn=lambda m: None)
    before = snapshot(small_lake)
    for query, text in [("CREATE TABLE t (x INT)", "refused a CREATE statement"),
                        (f"COPY selftest_cases TO '{tmp_path}/x.csv'", "refused a COPY statement"),
                        ("SELECT * FROM read_csv('/etc/passwd')", "Permission Error"),
                        (f"SELECT * FROM read_json('{small_lake}/_manifests/good.json')", "Permission"),
                        ("ATTACH 'x.db'", "refused an ATTACH statement"), ("INSTALL httpfs", "refused"),
                        ("SET enable_external_access = true", "refused"), ("SELEC 1", "syntax error"),
                        ("", "the query is empty"), ("SELECT * FROM nosuch", "nosuch")]:
        with pytest.raises(InputError) as e:
            lake.sql(query)
        assert text in str(e.value) and "\n" not in str(e.value), (query, str(e.value))
        rc, _, err = run_cli(["sql", query, "--lake", small_lake])
        assert rc == 2 and f"dualsight: error: {e.value}" in err, query
    assert snapshot(small_lake) == before and not (tmp_path / "x.csv").exists()


def test_lake_names_damaged_files_like_the_cli(small_lake, tmp_path):
    _, _, err = run_cli(["sql", "SELECT 1", "--lake", small_lake])
    cli = [line.removeprefix("dualsight: warning: ") for line in err.splitlines()]
    seen = []
    dualsight.Lake(small_lake, warn=seen.append).sql("SELECT 1")
    assert seen == cli and len(seen) == 2
    with pytest.warns(UserWarning) as caught:
        dualsight.Lake(small_lake).sql("SELECT 1")
    assert [str(w.message) for w in caught] == [f"dualsight: {m}" for m in cli]
    assert {Path(w.filename).name for w in caught} == {Path(__file__).name}     # named at the caller's line
    with pytest.warns(UserWarning), pytest.raises(InputError):
        dualsight.Lake(small_lake).sql("SELECT * FROM nosuch")                  # named before the error
    missing = dualsight.Lake(tmp_path / "none")                 # like the CLI: an empty lake, nothing created
    assert missing.runs() == [] and missing.sql("SELECT 42 AS x").to_pylist() == [{"x": 42}]
    assert not (tmp_path / "none").exists()
    assert repr(missing) == f"dualsight.Lake({str(tmp_path / 'none')!r})"


def test_lake_defaults_to_the_environment(small_lake, monkeypatch):
    monkeypatch.setenv("DUALSIGHT_LAKE", str(small_lake))
    assert dualsight.Lake().root == small_lake and len(dualsight.Lake().runs()) == 3


def test_pandas_flag(small_lake):
    lake = dualsight.Lake(small_lake, warn=lambda m: None)
    try:
        import pandas  # noqa: F401
    except ImportError:
        with pytest.raises(InputError, match="pandas is not installed"):
            lake.sql("SELECT 1", pandas=True)
        return
    df = lake.sql("SELECT run, case_id FROM selftest_cases ORDER BY run, case_id", pandas=True)
    assert len(df) == 90 and list(df.columns) == ["run", "case_id"]


# ============================================================================================ run
def test_run_identity_resume_and_refusal_as_the_cli(tmp_path):
    lake = tmp_path / "lake"
    rid = dualsight.run("star", "paper", cases=50, seed=3, lake=lake, workers=1)
    assert re.fullmatch(r"star-3-50-[0-9a-f]{8}", rid)
    manifest = json.loads((lake / "_manifests" / f"{rid}.json").read_text())
    assert manifest["status"] == "complete" and manifest["n_cases"] == 50 and manifest["catalog"]["stars"] > 2000
    # the same spec as a table, a TOML file and the CLI's --config: the same run (resumed, nothing recomputed)
    toml = tmp_path / "paper.toml"
    toml.write_text('preset = "paper"\n[voting]\ntolerance_arcsec = 10.0\n')
    assert dualsight.run("star", {"preset": "paper"}, cases=50, seed=3, lake=dualsight.Lake(lake), workers=1) == rid
    assert dualsight.run("star", toml, cases=50, seed=3, lake=lake, workers=1) == rid
    assert dualsight.run("star", str(toml), cases=50, seed=3, lake=lake, workers=1) == rid
    rc, _, err = run_cli(["star", "run", "--config", toml, "--cases", "50", "--seed", "3", "--lake", lake,
                          "--workers", "1", "--no-progress"])
    assert rc == 0 and f"run {rid}: complete" in err, err
    manifest = json.loads((lake / "_manifests" / f"{rid}.json").read_text())
    assert [e["resumed_shards"] for e in manifest["executions"]] == [0, 2, 2, 2, 2]
    assert len(lake_rows(lake, rid, {"star_cases": "case_id"})["star_cases"]) == 50
    # another spec is another run; an id with another spec is refused (one line), the lake untouched
    other = dualsight.run("star", {"voting": {"tolerance_arcsec": 12.0}}, cases=50, seed=3, lake=lake, workers=1)
    assert other != rid and other.startswith("star-3-50-")
    before = snapshot(lake)
    with pytest.raises(InputError) as e:
        dualsight.run("star", "paper", cases=60, seed=3, lake=lake, run_id=rid, workers=1)
    assert "was made with other settings (cases 50 -> 60" in str(e.value) and "\n" not in str(e.value)
    assert snapshot(lake) == before
    assert [r.run_id for r in dualsight.Lake(lake).runs()] == sorted([rid, other])


# kind: (spec, cases, seed, shard size, the same run on the command line, its run id, datasets {name: ORDER BY},
#        timing columns, another spec)
RUNS = {
    "prox_sweep": ({"preset": "paper", "ranges_m": [3.0, 20.0]}, 6, 5, 2,
                   ["prox", "sweep", "--preset", "paper", "--ranges", "3", "20", "--orientations", "3", "--seed", "5"],
                   r"prox-sweep-paper-5-6", PROX_ORDER, PROX_TIMING, {"preset": "accurate", "ranges_m": [3.0, 20.0]}),
    "prox_trajectory": ("paper", 7, 4, 3, ["prox", "trajectory", "--preset", "paper", "--frames", "7", "--seed", "4"],
                        r"prox-trajectory-paper-4-7", PROX_ORDER, PROX_TIMING, "accurate"),
    "star_track": ({"preset": "paper", "sequence": {"frames": 8}}, 4, 3, 2, None, r"star_track-3-4-[0-9a-f]{8}",
                   {"star_sequences": "case_id", "star_frames": "case_id, frame"}, TRACK_TIMING,
                   {"preset": "paper", "sequence": {"frames": 9}}),
    "selftest": (None, 40, 7, 10, ["selftest", "run", "--cases", "40", "--seed", "7"], r"selftest-[0-9a-f]{16}",
                 {"selftest_cases": "case_id", "selftest_items": "case_id, item"}, (), {"lam": 5.0}),
}


@pytest.mark.parametrize("kind", list(RUNS))
def test_every_kind_runs_as_its_command(kind, tmp_path):
    """run() of each other kind against its command: the same run id, seed and rows (every column but the
    timings); a second call resumes (a lost shard is recomputed, the others kept); another spec under the same
    id is refused with one line, the lake untouched."""
    spec, cases, seed, shard, argv, id_pattern, order, timing, other = RUNS[kind]
    api_lake, cli_lake = tmp_path / "api", tmp_path / "cli"
    if argv is None:                      # a spec the command takes as --config
        cfg = tmp_path / "spec.toml"
        cfg.write_text(tomli_w.dumps({k: v for k, v in spec.items() if k != "preset"}))
        argv = ["star", "track", "--preset", spec["preset"], "--config", cfg, "--cases", str(cases), "--seed", str(seed)]
    call = dict(cases=cases, seed=seed, lake=api_lake, workers=1, shard_size=shard)
    rid = dualsight.run(kind, spec, **call)
    rc, _, err = run_cli([*argv, "--lake", cli_lake, "--workers", "1", "--shard-size", shard, "--no-progress"])
    assert rc == 0, err
    assert re.fullmatch(id_pattern, rid) and re.search(rf"^run {re.escape(rid)}: complete, {cases} "
                                                       "(cases|sequences)", err, flags=re.M), (rid, err)
    from dualsight.warehouse.lake import Lake as Store

    m_api, m_cli = Store(api_lake).read_manifest(rid), Store(cli_lake).read_manifest(rid)
    for key in ("kind", "spec", "spec_hash", "n_cases", "seed", "shard_size", "n_shards", "datasets", "label"):
        assert m_api[key] == m_cli[key], key
    n_shards = -(-cases // shard)
    assert (m_api["kind"], m_api["n_cases"], m_api["seed"], m_api["status"], m_api["n_shards"]) == \
        (kind, cases, seed, "complete", n_shards)
    cli_rows = lake_rows(cli_lake, rid, order, timing)
    primary = next(iter(order))
    assert [r["case_id"] for r in cli_rows[primary]] == list(range(cases))
    assert {r["seed"] for r in cli_rows[primary]} == {seed}
    assert canonical(lake_rows(api_lake, rid, order, timing)) == canonical(cli_rows)
    # resume: complete, nothing recomputed; then a lost shard is recomputed, the others kept
    assert dualsight.run(kind, spec, **call) == rid
    lost = [f for ds in order for f in (api_lake / ds / f"run={rid}").glob("part-000001.parquet")]
    assert lost
    for f in lost:
        f.unlink()
    assert dualsight.run(kind, spec, **call) == rid
    executions = Store(api_lake).read_manifest(rid)["executions"]
    assert [e["resumed_shards"] for e in executions] == [0, n_shards, n_shards - 1]
    assert executions[-1]["cases_run"] == shard and all(f.exists() for f in lost)
    assert canonical(lake_rows(api_lake, rid, order, timing)) == canonical(cli_rows)
    # another spec under this id: refused with one line, nothing written
    before = snapshot(api_lake)
    with pytest.raises(InputError) as e:
        dualsight.run(kind, other, run_id=rid, **call)
    assert f"run {rid!r} in {api_lake} was made with other settings (" in str(e.value) and "\n" not in str(e.value)
    assert snapshot(api_lake) == before


@pytest.mark.parametrize("kwargs, kind, text", [
    ({"kind": "nope"}, InputError, "kind: unknown or unsupported job kind 'nope'; dualsight.run starts star, "
                                   "star_track, prox_sweep, prox_trajectory, selftest, rendezvous (hil_star, hil_prox and calibrate "
                                   "take images"),
    ({"kind": "hil_star"}, InputError, "dualsight.run starts star, star_track, prox_sweep, prox_trajectory, selftest, "
                                       "rendezvous"),
    ({"kind": "calibrate"}, InputError, "unknown or unsupported job kind 'calibrate'"),
    ({"kind": "prox_sweep", "cases": 10}, InputError, "cases: must be a multiple of the sweep's 11 ranges"),
    ({"kind": "prox_sweep", "spec": "noisy"}, ConfigError, "unknown preset 'noisy'; known presets: accurate, paper"),
    ({"kind": "prox_trajectory", "spec": {"orbit": 1}}, ConfigError, "config table [orbit]: unknown key"),
    ({"kind": "selftest"}, ConfigError, "unknown preset 'paper'; known presets: default"),
    ({"kind": "selftest", "spec": {"lam": 99}}, ConfigError, "config table [lam]"),
    ({"spec": "nope"}, ConfigError, "unknown preset 'nope'; known presets: ideal, noisy, paper, realistic"),
    ({"spec": 7}, ConfigError, "must be a preset name, a TOML file path or a dict"),
    ({"spec": "missing.toml"}, ConfigError, "missing.toml: file not found"),
    ({"spec": {"voting": {"bogus": 1}}}, ConfigError, "config table [voting.bogus]: unknown key"),
    ({"spec": {"preset": "nope"}}, ConfigError, "unknown preset 'nope'"),
    ({"spec": {"camera": {"width": np.int64(5)}}}, ConfigError, "camera.width"),
    ({"cases": 0}, InputError, "cases: must be an integer in [1, 1,000,000,000], got 0"),
    ({"cases": 2.5}, InputError, "cases: must be an integer"),
    ({"cases": True}, InputError, "cases: must be an integer"),
    ({"seed": -1}, InputError, "seed: must be an integer"),
    ({"workers": 0}, InputError, "workers: must be an integer"),
    ({"shard_size": 0}, InputError, "shard_size: must be an integer"),
    ({"run_id": "a b"}, InputError, "run_id: run id 'a b' must match"),
    ({"lake": 3}, InputError, "lake: must be a dualsight.Lake or a folder path"),
    ({"scheduler": 5}, InputError, "scheduler: must be a Dask scheduler address"),
])
def test_run_refuses_bad_arguments_before_touching_the_lake(tmp_path, kwargs, kind, text, monkeypatch):
    monkeypatch.chdir(tmp_path)
    args = {"kind": "star", "spec": "paper", "cases": 10, "seed": 1, "lake": tmp_path / "lake", "workers": 1,
            **kwargs}
    with pytest.raises(kind) as e:
        dualsight.run(args.pop("kind"), args.pop("spec"), **args)
    assert text in str(e.value) and "\n" not in str(e.value), str(e.value)
    assert not (tmp_path / "lake").exists()


# ============================================================================================ the root facade
def test_import_dualsight_stays_light_and_the_facade_resolves_on_use():
    code = """
import sys
import dualsight
loaded = lambda *p: sorted(m for m in sys.modules if m.startswith(p))
assert loaded("dualsight.api", "dualsight.jobs", "dualsight.warehouse", "pyarrow", "duckdb") == [], loaded("dualsight")
assert dualsight.allocator._done is not None                  # the allocator was tuned by the import
import dualsight.kernels.rng
assert loaded("dualsight.api", "dualsight.jobs", "dualsight.warehouse", "dualsight.catalogs") == []
assert {"solve", "Lake", "run", "Solution", "Star", "Timings", "RunRecord"} <= set(dir(dualsight))
assert set(dualsight.__all__) >= {"solve", "Lake", "run", "Solution", "Star", "Timings", "RunRecord"}
solve = dualsight.solve
import dualsight.api, dualsight.warehouse.lake
assert solve is dualsight.api.solve and dualsight.Lake is dualsight.api.Lake and dualsight.run is dualsight.api.run
assert dualsight.RunRecord is dualsight.warehouse.lake.RunRecord
from dualsight import Solution, allocator
assert Solution is dualsight.api.Solution
try:
    dualsight.no_such_name
except AttributeError as e:
    assert "no_such_name" in str(e)
else:
    raise AssertionError("no AttributeError")
print("ok")
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-3000:]


def test_public_names_have_type_hints_and_docstrings():
    import inspect
    import typing

    import dualsight.api as api

    for name in api.__all__:
        obj = getattr(api, name)
        if name.isupper():
            continue
        assert inspect.getdoc(obj), name
        if inspect.isfunction(obj):
            hints = typing.get_type_hints(obj, globalns=vars(api))
            params = [p for p in inspect.signature(obj).parameters if p != "settings"]
            assert set(params) | {"return"} <= set(hints), (name, set(params) | {"return"} - set(hints))
    for cls in (api.Lake,):
        for meth in ("runs", "sql"):
            assert inspect.getdoc(getattr(cls, meth)) and "return" in getattr(cls, meth).__annotations__
