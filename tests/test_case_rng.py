"""Vectorised per-case streams (scene/case_rng.py) against numpy's own default_rng([seed, i]), bit for bit."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from dualsight.scene.case_rng import seed_states, streams

seeds = st.integers(0, 2**64 - 1)
ids = st.lists(st.integers(0, 2**32 - 1), min_size=1, max_size=12)


@settings(max_examples=60, deadline=None)
@given(seeds, ids)
def test_seed_states_equal_numpys_seed_sequence(seed, case_ids):
    got = seed_states(seed, np.array(case_ids))
    want = np.stack([np.random.SeedSequence([seed, i]).generate_state(4, np.uint64) for i in case_ids])
    assert np.array_equal(got, want)


@settings(max_examples=60, deadline=None)
@given(seeds, ids, st.lists(st.sampled_from(["raw", "random", "uniform", "int63"]), min_size=1, max_size=8))
def test_draws_equal_numpys_generators_in_any_order(seed, case_ids, order):
    s = streams(seed, np.array(case_ids))
    gens = [np.random.default_rng([seed, i]) for i in case_ids]
    for what in order:
        if what == "raw":
            got, want = s.next_uint64(), [g.bit_generator.random_raw() for g in gens]
        elif what == "random":
            got, want = s.random(), [g.random() for g in gens]
        elif what == "uniform":
            got, want = s.uniform(-np.pi, np.pi), [g.uniform(-np.pi, np.pi) for g in gens]
        else:
            got, want = s.integers_63(), [g.integers(0, 2**63, dtype=np.uint64) for g in gens]
        assert np.array_equal(got, np.array(want, dtype=got.dtype)), what


def test_star_cases_draw_what_per_case_generators_draw():
    """jobs/kinds/star.py draw_cases against the per-case default_rng it replaced, both attitude models."""
    import dataclasses

    from dualsight.jobs.kinds import star
    from dualsight.scene.attitude import euler123_to_dcm, quat_to_dcm, random_quaternions

    spec, _ = star.resolve("paper", None, seed=11, cases=1000)
    for att in ("euler123", "uniform"):
        sp = dataclasses.replace(spec, attitudes=att)
        case_ids = np.arange(3, 1000, 37)
        d = star.draw_cases(sp, case_ids)
        for k, i in enumerate(case_ids):
            rng = np.random.default_rng([sp.seed, int(i)])
            if att == "euler123":
                ang = rng.uniform(-np.pi, np.pi, 3)
                assert np.array_equal(ang, d["angles"][k])
                A = euler123_to_dcm(ang[None])[0]
            else:
                q = random_quaternions(rng, 1)[0]
                assert np.array_equal(q, d["quat"][k])
                A = quat_to_dcm(q[None])[0]
            assert rng.integers(0, 2**63, dtype=np.uint64) == d["noise_seed"][k]
            assert np.array_equal(A, d["A_true"][k])
