"""The pair catalog's bounded-memory build (catalogs/pairs.py: an external bucket sort) and its cache.

Independent truth: a brute-force O(N^2) reference over a few hundred unit vectors (every pair i < j, its
``angle_between``, kept below the limit, sorted by (angle, i, j) with numpy's lexsort) — what the previous
in-memory build computed.  The bucketed build must equal it element for element, dtypes included, for
any bucket count and budget, down to a budget of two pairs per bucket (every chunk spread over many
buckets, every bucket split again).  Inputs with exactly equal angles (a cube's vertices, the axes,
duplicated stars) check the (i, j) tie-break.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from dualsight.catalogs import pairs as pairs_mod
from dualsight.catalogs.cache import short_hash
from dualsight.catalogs.pair_cache import load_pair_catalog, pair_cache_files, pair_cache_path
from dualsight.catalogs.pairs import PairCatalog, build_pair_catalog
from dualsight.scene.units import angle_between


# ------------------------------------------------------------------------------------ reference
def reference_pairs(u: np.ndarray, theta: float):
    """Every pair i < j with angle < theta, sorted by (angle, i, j): O(N^2), no dualsight code but the
    angle function the catalog is defined with."""
    n = len(u)
    i, j = np.triu_indices(n, 1)
    ang = angle_between(u[i], u[j]) if n > 1 else np.zeros(0)
    keep = ang < theta
    i, j, ang = i[keep], j[keep], ang[keep]
    s = np.lexsort((j, i, ang))
    return i[s].astype(np.int32), j[s].astype(np.int32), ang[s]


def _random_unit(seed, n):
    u = np.random.default_rng(seed).normal(size=(n, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def _symmetric_unit():
    """Many exactly equal angles: the 6 axis directions, the 8 cube vertices, the 12 edge midpoints,
    and three of them twice (angle 0 between the copies)."""
    axes = np.array([[s * (k == a) for k in range(3)] for a in range(3) for s in (1.0, -1.0)])
    cube = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)]) / np.sqrt(3.0)
    edges = np.array([np.roll([x, y, 0.0], r) for x in (-1.0, 1.0) for y in (-1.0, 1.0) for r in range(3)]) \
        / np.sqrt(2.0)
    u = np.concatenate([axes, cube, edges, axes[:2], cube[:1]])
    return u[np.random.default_rng(3).permutation(len(u))]


INPUTS = {
    "random-400-0.4": (lambda: _random_unit(0, 400), 0.4),
    "random-600-0.05": (lambda: _random_unit(1, 600), 0.05),
    "random-150-3.0": (lambda: _random_unit(2, 150), 3.0),
    "symmetric-ties-pi": (_symmetric_unit, np.pi),
    "symmetric-ties-1.0": (_symmetric_unit, 1.0),
}
SETTINGS = {
    "default": {},
    "one-bucket": {"n_buckets": 1},
    "7-buckets": {"n_buckets": 7},
    "256-buckets": {"n_buckets": 256},
    "small-chunks": {"max_block": 50, "n_buckets": 3},
    "budget-16-pairs": {"max_bytes": 16 * pairs_mod.SORT_BYTES_PER_PAIR},
    "budget-2-pairs": {"max_bytes": 2 * pairs_mod.SORT_BYTES_PER_PAIR, "max_block": 64},
}


def _assert_same(pc: PairCatalog, ref) -> None:
    for name, r in zip(("i", "j", "angle"), ref):
        got = getattr(pc, name)
        assert got.dtype == r.dtype and got.shape == r.shape, (name, got.dtype, got.shape, r.dtype, r.shape)
        assert np.array_equal(got, r), name
        assert got.tobytes() == r.tobytes(), name                           # bit for bit (angles included)


@pytest.mark.parametrize("setting", list(SETTINGS))
@pytest.mark.parametrize("inp", list(INPUTS))
def test_bucketed_build_equals_the_brute_force_reference(inp, setting, tmp_path):
    make, theta = INPUTS[inp]
    u = make()
    ref = reference_pairs(u, theta)
    if inp.startswith("symmetric"):
        a = ref[2]
        assert np.count_nonzero(a[1:] == a[:-1]) > 50                      # the input does test ties
    pc = build_pair_catalog(u, theta, work_dir=tmp_path, **SETTINGS[setting])
    _assert_same(pc, ref)
    assert pc.max_angle == theta and list(tmp_path.iterdir()) == []           # bucket files removed


def test_a_tiny_budget_splits_every_chunk_and_every_bucket(tmp_path, monkeypatch):
    """Two pairs per bucket: each chunk's pairs go to many buckets and every bucket is split again,
    recursively; the result is still the reference."""
    u, theta = _random_unit(4, 300), 0.5
    calls = {"route": [], "split": 0, "sorted": []}
    route, split, sort_order = pairs_mod._append_routed, pairs_mod._Builder._split, pairs_mod._sort_order

    def counting_sort(rec):
        calls["sorted"].append(rec.size)
        return sort_order(rec)

    def counting_route(rec, edges, paths, files, counts):
        if not calls["split"]:                                               # the first pass: the chunks
            calls["route"].append(np.unique(np.searchsorted(edges, rec["angle"], side="right")).size)
        return route(rec, edges, paths, files, counts)

    def counting_split(self, path, count):
        calls["split"] += 1
        assert count > self.cap
        return split(self, path, count)
    monkeypatch.setattr(pairs_mod, "_append_routed", counting_route)
    monkeypatch.setattr(pairs_mod._Builder, "_split", counting_split)
    monkeypatch.setattr(pairs_mod, "_sort_order", counting_sort)
    pc = build_pair_catalog(u, theta, max_bytes=2 * pairs_mod.SORT_BYTES_PER_PAIR, max_block=200,
                            work_dir=tmp_path)
    _assert_same(pc, reference_pairs(u, theta))
    assert len(calls["route"]) > 20 and min(calls["route"]) > 1              # every chunk spans buckets
    assert calls["split"] >= pairs_mod.MAX_OPEN_BUCKETS                       # every first-pass bucket split
    assert max(calls["sorted"]) <= 2 and sum(calls["sorted"]) == len(pc)      # buckets of <= 2 pairs at the end


def test_budget_bounds_the_sorted_buckets(tmp_path, monkeypatch):
    """No bucket sorted in memory holds more pairs than the budget allows (max_bytes / SORT_BYTES_PER_PAIR),
    and every pair is sorted exactly once."""
    u, theta, budget = _random_unit(6, 500), 0.6, 40 * pairs_mod.SORT_BYTES_PER_PAIR
    seen = {"sorted": []}

    def spy_sort(rec):
        seen["sorted"].append(rec.size)
        return np.lexsort((rec["j"], rec["i"], rec["angle"]))
    monkeypatch.setattr(pairs_mod, "_sort_order", spy_sort)
    pc = build_pair_catalog(u, theta, max_bytes=budget, work_dir=tmp_path)
    _assert_same(pc, reference_pairs(u, theta))
    assert max(seen["sorted"]) <= budget // pairs_mod.SORT_BYTES_PER_PAIR and sum(seen["sorted"]) == len(pc)
    assert len(seen["sorted"]) > len(pc) // (budget // pairs_mod.SORT_BYTES_PER_PAIR)


def test_sort_order_breaks_ties_by_i_then_j():
    rec = np.zeros(7, pairs_mod._REC)
    rec["angle"] = [0.5, 0.1, 0.5, 0.5, 0.1, 0.2, 0.5]
    rec["i"] = [3, 9, 3, 1, 2, 0, 0]
    rec["j"] = [7, 10, 5, 8, 4, 1, 9]
    s = pairs_mod._sort_order(rec)
    got = [(float(rec["angle"][k]), int(rec["i"][k]), int(rec["j"][k])) for k in s]
    assert got == sorted(got)


# ------------------------------------------------------------------------------------ cache
class FakeStars:
    """What load_pair_catalog reads of a StarCatalog: ``unit``, ``fingerprint()``, ``len()``."""

    def __init__(self, unit):
        self.unit = unit

    def fingerprint(self):
        return short_hash(np.ascontiguousarray(self.unit).tobytes())

    def __len__(self):
        return len(self.unit)


@pytest.fixture()
def cached(tmp_path):
    stars, theta = FakeStars(_random_unit(7, 500)), 0.35
    ref = reference_pairs(stars.unit, theta)
    pc = load_pair_catalog(stars, theta, cache_dir=tmp_path)
    return stars, theta, ref, pc, tmp_path


def test_cache_round_trip_is_memory_mapped(cached, no_rebuild, capsys):
    stars, theta, ref, pc, d = cached
    _assert_same(pc, ref)
    files = pair_cache_files(stars, theta, d)
    assert all(p.is_file() for p in files) and files[-1] == pair_cache_path(stars, theta, d)
    assert f"pairs-v{pairs_mod.FORMAT_VERSION}-" in files[-1].name
    man = json.loads(files[-1].read_text())
    assert man["pairs"] == len(ref[0]) and man["format"] == pairs_mod.FORMAT_VERSION
    assert not [p for p in d.iterdir() if p.name.startswith(".")]            # no temporary left
    no_rebuild(pairs_mod, "build_pair_catalog")
    again = load_pair_catalog(stars, theta, cache_dir=d)
    _assert_same(again, ref)
    for name in ("i", "j", "angle"):
        a = getattr(again, name)
        assert isinstance(a, np.memmap) and not a.flags.writeable
    assert again.max_angle == theta and again.nbytes == 16 * len(ref[0])
    assert capsys.readouterr().err == ""
    assert pair_cache_path(stars, theta * 0.5, d) != files[-1]


def _replace(path, data: bytes) -> None:
    """Put ``data`` at ``path`` as a new file (the old one may still be memory-mapped by the fixture's
    catalog: truncating it in place would make reading those pages a SIGBUS)."""
    tmp = path.with_name(path.name + ".new")
    tmp.write_bytes(data)
    tmp.replace(path)


@pytest.mark.parametrize("damage", ["truncate-angle", "truncate-i", "grow-j", "zero-angle", "delete-j",
                                    "garbage-manifest", "header-only"])
def test_damaged_cache_is_rebuilt_with_one_warning(cached, damage, capsys):
    stars, theta, ref, _, d = cached
    fi, fj, fa, man = pair_cache_files(stars, theta, d)
    capsys.readouterr()
    if damage == "truncate-angle":
        _replace(fa, fa.read_bytes()[:-24])
    elif damage == "truncate-i":
        _replace(fi, fi.read_bytes()[:200])
    elif damage == "grow-j":
        _replace(fj, fj.read_bytes() + b"\0" * 8)
    elif damage == "zero-angle":
        raw = bytearray(fa.read_bytes())
        raw[128:] = b"\0" * (len(raw) - 128)
        _replace(fa, bytes(raw))
    elif damage == "delete-j":
        fj.unlink()
    elif damage == "garbage-manifest":
        _replace(man, b"{not json")
    elif damage == "header-only":
        _replace(fa, fa.read_bytes()[:128])
    pc = load_pair_catalog(stars, theta, cache_dir=d)
    _assert_same(pc, ref)
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "damaged" in err and "rebuilding" in err, err
    again = load_pair_catalog(stars, theta, cache_dir=d)                    # whole again: no second warning
    _assert_same(again, ref)
    assert capsys.readouterr().err == ""


def test_a_killed_build_is_cleaned_up_and_rebuilt(cached, capsys):
    """Arrays without a manifest (a build killed before its last rename) and a killed build's leftovers
    (its bucket folder, temporary arrays): rebuilt with one warning, the leftovers removed."""
    stars, theta, ref, _, d = cached
    fi, fj, fa, man = pair_cache_files(stars, theta, d)
    stem = man.with_suffix("")
    (d / f".{stem.name}.build-dead").mkdir()
    (d / f".{stem.name}.build-dead" / "b00000001.rec").write_bytes(b"\0" * 160)
    (d / f".{fi.name}.x1y2.tmp").write_bytes(b"partial")
    (d / ".other-entry.build-live").mkdir()                                  # another entry's: kept
    man.unlink()
    capsys.readouterr()
    pc = load_pair_catalog(stars, theta, cache_dir=d)
    _assert_same(pc, ref)
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "incomplete" in err, err
    left = sorted(p.name for p in d.iterdir() if p.name.startswith("."))
    assert left == [".other-entry.build-live"], left


def test_memory_mapped_pairs_vote_like_in_memory_ones(tmp_path):
    """identify() over the read-only memory-mapped arrays (VotingIndex, numpy votes, the Taichi kernels)
    gives exactly what the in-memory copies give."""
    from helpers import CAM, TOL, sphere_catalog, star_fields

    from dualsight.nav.starid import identify
    from dualsight.nav.voting_config import VotingConfig

    cat = sphere_catalog(11, 3000)
    pc = load_pair_catalog(FakeStars(cat), CAM.fov_rad[2], cache_dir=tmp_path)
    assert isinstance(pc.angle, np.memmap)
    _, obs, valid, _ = star_fields(np.random.default_rng(2), cat, 12)
    mem = [np.array(getattr(pc, f)) for f in ("i", "j", "angle")]
    fields = ("ids", "accepted", "T", "vote_ids", "votes")
    for cfg in (VotingConfig.paper(TOL), VotingConfig.robust(TOL)):
        for engine in ("numpy", "taichi"):
            a = identify(obs, valid, cat, pc.i, pc.j, pc.angle, cfg, engine=engine)
            b = identify(obs, valid, cat, *mem, cfg, engine=engine)
            for f in fields:
                assert np.array_equal(getattr(a, f), getattr(b, f)), (cfg, engine, f)
            assert np.count_nonzero(a.ids[valid] >= 0) > 0.5 * valid.sum()


@pytest.mark.parametrize("bad", [0, -5, 1.5, None])
def test_bad_budget(bad):
    with pytest.raises(ValueError):
        build_pair_catalog(np.eye(3), 0.5, max_bytes=bad)


# ------------------------------------------------------------------------- the voting's derived arrays
def test_derived_voting_arrays_in_chunks_equal_the_in_memory_derivation(cached):
    """``prev`` written chunk by chunk (the last pair of each star carried between chunks: chunks of 7, 64 and
    all pairs) equals the one-sort derivation, and the interleaved stars are i + 1, j + 1 then zeros."""
    from dualsight.catalogs import pair_voting_cache as pvc
    from dualsight.nav.pair_index import PAD, previous_occurrence

    stars, theta, ref, pc, d = cached
    want = previous_occurrence(np.asarray(pc.i), np.asarray(pc.j))
    assert (want >= 0).sum() > 1000 and (want == -1).any()
    for chunk in (7, 64, len(pc)):
        pvc.write_prev(d / f"p{chunk}.npy", pc.i, pc.j, np.int32, PAD, chunk=chunk)
        got = np.load(d / f"p{chunk}.npy")
        np.testing.assert_array_equal(got[:-PAD], want)
        assert not got[-PAD:].any()
        pvc.write_stars_plus_one(d / f"s{chunk}.npy", pc.i, pc.j, np.int32, PAD, chunk=chunk)
        s = np.load(d / f"s{chunk}.npy")
        np.testing.assert_array_equal(s[0:-PAD:2], np.asarray(pc.i) + 1)
        np.testing.assert_array_equal(s[1:-PAD:2], np.asarray(pc.j) + 1)
        assert not s[-PAD:].any()


def test_a_cached_catalogs_index_maps_its_derived_files_and_rebuilds_damaged_ones(cached):
    """VotingIndex.load_or_build of a cached catalog maps ``<stem>.vstars.npy`` / ``.vprev.npy`` (built once, then
    reused by every process) with the same values as an in-memory index; a truncated or foreign file is rebuilt.
    The constructor alone writes no file."""
    from dualsight.catalogs import pair_voting_cache as pvc
    from dualsight.nav.pair_index import VotingIndex

    stars, theta, ref, pc, d = cached
    mem = VotingIndex(np.array(pc.i), np.array(pc.j), np.array(pc.angle))
    VotingIndex(pc.i, pc.j, pc.angle)
    vs, vp = pvc.derived_paths(pc.i)
    assert not vs.exists() and not vp.exists()
    idx = VotingIndex.load_or_build(pc.i, pc.j, pc.angle)
    assert vs.exists() and vp.exists()
    assert isinstance(idx.stars_plus_one, np.memmap) and isinstance(idx.prev_padded, np.memmap)
    np.testing.assert_array_equal(idx.stars_plus_one, mem.stars_plus_one)
    np.testing.assert_array_equal(idx.prev_padded, mem.prev_padded)
    t0 = vs.stat().st_mtime_ns
    VotingIndex.load_or_build(pc)                            # the catalog object too; the files are reused
    assert vs.stat().st_mtime_ns == t0
    with open(vp, "r+b") as f:                               # truncated (a killed copy, a full disk)
        f.truncate(vp.stat().st_size - 8)
    np.save(vs, np.zeros_like(np.load(vs)))                  # another catalog's stars
    again = VotingIndex.load_or_build(pc.i, pc.j, pc.angle)
    np.testing.assert_array_equal(again.stars_plus_one, mem.stars_plus_one)
    np.testing.assert_array_equal(again.prev_padded, mem.prev_padded)
