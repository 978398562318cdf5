"""Hypothesis fuzzing of every config reader and of the CLI's parsing: bad input is one InputError (or an
argparse exit 2), never another exception, and nothing is written before validation ends."""

from __future__ import annotations

import copy
import io
import contextlib
from pathlib import Path

import pytest
import tomli_w
from hypothesis import HealthCheck, given, settings, strategies as st

from dualsight.errors import InputError
from dualsight.jobs.kinds import prox, selftest, star
from dualsight.jobs.cli.main import build_parser, main
from dualsight.scene.camera import Camera, read_toml
from dualsight.scene.satellite import satellite_from_dict

SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                           HealthCheck.too_slow])

scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**20, 10**20), st.floats(allow_nan=True),
                    st.text(max_size=8), st.just(1e300), st.just(-0.0), st.just(2**63))
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                      st.dictionaries(st.text(max_size=6), inner, max_size=4)),
                      max_leaves=12)


def _paths(d, prefix=()):
    """Every key path of a nested dict."""
    for k, v in d.items():
        yield prefix + (k,)
        if isinstance(v, dict):
            yield from _paths(v, prefix + (k,))


@st.composite
def mutated(draw, base: dict):
    """``base`` with 1-3 values replaced by arbitrary values, or unknown keys added, or tables deleted."""
    d = copy.deepcopy(base)
    paths = list(_paths(d))
    for _ in range(draw(st.integers(1, 3))):
        path = draw(st.sampled_from(paths))
        node = d
        for k in path[:-1]:
            node = node.get(k) if isinstance(node, dict) else None
            if not isinstance(node, dict):
                break
        if not isinstance(node, dict):
            continue
        action = draw(st.sampled_from(["replace", "add", "delete"]))
        if action == "replace":
            node[path[-1]] = draw(values)
        elif action == "add":
            node[draw(st.text(min_size=1, max_size=6))] = draw(values)
        else:
            node.pop(path[-1], None)
    return d


def _only_input_errors(fn, arg):
    try:
        fn(arg)
    except InputError as e:
        assert str(e) and "\n" not in str(e).strip(), repr(str(e))


STAR = star.PRESETS["paper"]
PROX = prox.resolve_spec("paper", None)


@SETTINGS
@given(mutated(STAR))
def test_star_spec_reader(d):
    _only_input_errors(lambda x: star.spec_from_dict(x, source="fuzz.toml"), d)


@SETTINGS
@given(mutated(PROX))
def test_prox_spec_reader(d):
    _only_input_errors(lambda x: prox.spec_from_dict(x, source="fuzz.toml"), d)


@SETTINGS
@given(mutated({"seed": 1, "lam": 3.0, "sleep_ms": 0.0}))
def test_selftest_spec_reader(d):
    _only_input_errors(lambda x: selftest.spec_from_dict(x, source="fuzz.toml"), d)


@SETTINGS
@given(mutated({"width": 1024, "height": 768, "pixel_pitch_um": 4.65, "focal_length_mm": 17.0}))
def test_camera_reader(d):
    _only_input_errors(lambda x: Camera.from_dict(x, source="fuzz.toml"), d)


@SETTINGS
@given(mutated(PROX["satellite"]))
def test_satellite_reader(d):
    _only_input_errors(lambda x: satellite_from_dict(x, source="fuzz.toml"), d)


@SETTINGS
@given(st.binary(max_size=300))
def test_toml_file_reader(tmp_path_factory, data):
    p = tmp_path_factory.mktemp("t") / "c.toml"
    p.write_bytes(data)
    _only_input_errors(read_toml, p)


def test_special_files_are_refused_quickly():
    for path in ("/dev/zero", "/dev/null", "/", "/proc/self/status"):
        with pytest.raises(InputError):
            read_toml(Path(path))


def test_deep_nesting_is_refused_not_recursed(tmp_path):
    p = tmp_path / "deep.toml"
    p.write_text("a = " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(InputError):
        star.resolve_spec(None, p)


TOKENS = ["star", "run", "prox", "sweep", "trajectory", "report", "replay", "sql", "runs", "lake", "check",
          "selftest", "--cases", "--seed", "--run", "--workers", "--shard-size", "--preset", "--config",
          "--lake", "--case", "--orientations", "--ranges", "0", "-1", "1e9", "1e99", "2", "x\n", "", "paper",
          "accurate", "nonsense", "--no-progress", "/dev/zero", "3.5", "-5", "🙂", "--json"]


@SETTINGS
@given(st.lists(st.sampled_from(TOKENS), max_size=8))
def test_cli_parsing_never_tracebacks(tmp_path_factory, argv):
    """Parse any argv; for a run command that parses, resolve and validate its spec (no run, no lake)."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            args = build_parser().parse_args(argv)
        except SystemExit as e:
            assert e.code in (0, 2)
            assert "Traceback" not in err.getvalue()
            return
    if getattr(args, "command", None) == "star" and getattr(args, "action", None) == "run":
        try:
            star.resolve_spec(args.preset, args.config, seed=args.seed, cases=args.cases)
        except InputError:
            pass


def test_config_over_1_mib_is_refused(tmp_path):
    p = tmp_path / "big.toml"
    p.write_text(tomli_w.dumps({"seed": 1, "pad": "x" * (1 << 20)}))
    with pytest.raises(InputError, match="larger than"):
        read_toml(p)


@pytest.mark.parametrize("over, field", [
    ({"camera": {"width": 100_000}}, "width"),
    ({"catalog": {"mag_limit": 9.0}, "camera": {"focal_length_mm": 0.2}}, "GiB"),
    ({"batch_size": 10**6}, "batch_size"),
    ({"seed": "3"}, "seed"),
])
def test_impossible_star_specs_fail_before_the_lake(tmp_path, over, field, capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text(tomli_w.dumps(over))
    lake = tmp_path / "lake"
    rc = main(["star", "run", "--config", str(cfg), "--cases", "10", "--lake", str(lake), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and field in err and len(err.strip().splitlines()) == 1, err
    assert not lake.exists()
