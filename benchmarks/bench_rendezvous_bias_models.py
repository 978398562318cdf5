"""The rendezvous filter's consistency (issue 23, point 6 c) with other models of the centre of brightness's bias:
the same approaches, measured once, filtered by each model (``jobs/kinds/rendezvous_filter.CobBias``).

    python benchmarks/bench_rendezvous_bias_models.py [--preset far] [--seeds 1 2 3 4 5 6] [--cases 100]

Models:

* ``product``: the filter's own (``rendezvous_filter.gauss_markov_cob``): two first-order Gauss-Markov states along the
  Sun's side and across, decaying with the line of sight's turn at the correlation's integral scale; the scatter
  about the spin average white.
* ``turn harmonics, white spin``: the spin-averaged offset as a Fourier series of the line of sight's turn psi about
  the Sun, harmonics 0-3 along and across as random constants (variances from the Monte Carlo of
  ``bench_rendezvous_nees.bias_harmonics``: the first harmonic along the Sun, 72 % of it, has the form of the
  Clohessy-Wiltshire cross-track motion); the scatter about the spin average white (as the product).
* ``turn harmonics, spin harmonics``: the same, and the scatter about the spin average as harmonics 1-``--spin``
  of the target's known spin phase omega t (it is a fixed function of the spin phase: sampled once a frame its
  running mean falls as ~1/N, which a white model overstates), their coefficients first-order Gauss-Markov in psi
  (``--psi-c`` deg), variances from the same Monte Carlo; what the harmonics leave, white.
* ``first harmonic + Gauss-Markov``: the product, with the first harmonic of the turn (along and across, as random
  constants: the part whose persistence the Gauss-Markov states cut short) split off its states.

Printed per model and seed (frames from the spec's ``converged_after_frames``): the frames whose mean NEES over the
approaches lies outside its 95 % chi-square bounds, the mean NEES (min-max over frames) and the mean squared
position error over its stated sigma per Hill axis (radial / along-track / cross-track; 1 where the sigma is
right); then over the seeds the pooled mean NEES (6 expected), the frames outside in all and the per-axis means.
Noise-free images (the presets').
"""

from __future__ import annotations

import argparse
import copy
import math
import time

import numpy as np

from bench_rendezvous_nees import turn_offsets
from dualsight.jobs.kinds import (rendezvous as rz, rendezvous_filter, rendezvous_measure, rendezvous_spec,
                                  rendezvous_truth)
from dualsight.nav.relative_filter import chi2_mean_bounds, nees
from dualsight.scene.units import DEG


def offset_harmonics(shape, alpha: float, turn_harmonics: int = 3, spin_harmonics: int = 4, n_axes: int = 1000,
                     n_phases: int = 24, n_turns: int = 24, seed: int = 5) -> dict:
    """Monte Carlo (spin axes uniform on the sphere, initial attitudes uniform on SO(3); Sun along +z, the observer
    at ``alpha`` rad turned about z) of the Lambertian photocentre offset, along the Sun's side and across (m):
    ``turn`` (H + 1, 2) the variance of each Fourier coefficient in the turn of the spin-averaged offset minus the
    mean over axes (a_0; a_m = b_m for m >= 1), ``turn_total`` (2,) its whole variance; ``spin`` (J, 2) the variance
    of each coefficient of the spin phase's harmonics j = 1..J of the offset minus its spin average, ``spin_total``
    (2,) that scatter's whole variance."""
    comp, _ = turn_offsets(shape, alpha, n_axes, n_phases, n_turns, seed)
    avg = comp.mean(2)
    bias = avg - avg.mean(1, keepdims=True)                              # (turns, axes, 2)
    Ct = np.fft.rfft(bias, axis=0) / n_turns                             # a_0 = C_0, a_m = 2 Re C_m
    turn = np.array([np.mean(Ct[0].real ** 2, 0)]
                    + [np.mean(np.abs(2.0 * Ct[m]) ** 2, 0) / 2.0 for m in range(1, turn_harmonics + 1)])
    dev = comp - avg[:, :, None, :]
    Cs = np.fft.rfft(dev, axis=2) / n_phases
    spin = np.array([np.mean(np.abs(2.0 * Cs[:, :, j]) ** 2, (0, 1)) / 2.0 for j in range(1, spin_harmonics + 1)])
    return {"turn": turn, "turn_total": np.mean(bias ** 2, (0, 1)), "spin": spin.reshape(-1, 2),
            "spin_total": np.mean(dev ** 2, (0, 1, 2))}


def harmonic_cob(spec, ctx, stats: dict, spin_harmonics: int, psi_c_rad: float) -> rendezvous_filter.CobBias:
    """The ``turn harmonics`` models of the module docstring as a ``CobBias`` (states: the turn's coefficients along
    and across, then the spin phase's along and across), from :func:`offset_harmonics` at the preset's phase."""
    s = rendezvous_truth.sun_icrs(spec)
    e1 = np.cross(s, [1.0, 0.0, 0.0]) if abs(s[0]) < 0.9 else np.cross(s, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(s, e1)
    H = stats["turn"].shape[0] - 1
    J = spin_harmonics
    turn_sd = np.sqrt(np.concatenate([stats["turn"][:1], np.repeat(stats["turn"][1:], 2, 0)]))     # (2H + 1, 2)
    spin_sd = np.sqrt(np.repeat(stats["spin"][:J], 2, 0))                                          # (2J, 2)
    rest = (np.maximum(stats["turn_total"] - stats["turn"].sum(0), 0.0)
            + np.maximum(stats["spin_total"] - (stats["spin"][:J].sum(0) if J else 0.0), 0.0))
    nt, nsp = 2 * H + 1, 2 * J
    omega = spec.cfg.target_rate_deg_s * DEG
    t0 = spec.times[0]

    def columns(k, v, D, alpha, r):
        obs = -v
        psi = np.arctan2(obs @ e2, obs @ e1)
        h = np.stack([np.ones_like(psi)] + [f(m * psi) for m in range(1, H + 1) for f in (np.cos, np.sin)], -1)
        phi = omega * (spec.times[k] - t0)
        g = np.array([f(j * phi) for j in range(1, J + 1) for f in (np.cos, np.sin)])
        cols = [D[:, :, i:i + 1] * (h * turn_sd[:, i])[:, None, :] for i in (0, 1)]
        cols += [D[:, :, i:i + 1] * (g * spin_sd[:, i])[None, None, :] for i in (0, 1)]
        return np.concatenate(cols, -1), np.tile(np.sqrt(rest), (len(v), 1))

    turn, start = rendezvous_filter.line_of_sight_turn()

    def decay(k, x, R_k):
        dpsi, _ = turn(x, R_k)
        d = np.ones((1, 2 * nt + 2 * nsp))
        if dpsi is not None and nsp:
            d[0, 2 * nt:] = math.exp(-dpsi / psi_c_rad)
        return d

    return rendezvous_filter.CobBias(2 * nt + 2 * nsp, columns, decay, start)


def first_harmonic_cob(spec, ctx, stats: dict, harmonics: int = 1) -> rendezvous_filter.CobBias:
    """The ``first harmonic + Gauss-Markov`` model of the module docstring: harmonics 1-``harmonics`` of the line of
    sight's turn along the Sun and across as random constants (variances from :func:`offset_harmonics`), the
    product's two Gauss-Markov states for the rest of the spin-averaged variance (scaled by the share the harmonics
    leave), the spin scatter white (as the product)."""
    prod = rendezvous_filter.gauss_markov_cob(spec, ctx)
    s = rendezvous_truth.sun_icrs(spec)
    e1 = np.cross(s, [1.0, 0.0, 0.0]) if abs(s[0]) < 0.9 else np.cross(s, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(s, e1)
    var_h = stats["turn"][1:harmonics + 1]                                   # (H, 2)
    rest = np.sqrt(np.clip(1.0 - var_h.sum(0) / stats["turn_total"], 0.0, 1.0))
    sd = np.repeat(np.sqrt(var_h), 2, 0)                                      # (2H, 2): cos and sin
    nh = 4 * harmonics

    def columns(k, v, D, alpha, r):
        G, white = prod.columns(k, v, D, alpha, r)
        obs = -v
        psi = np.arctan2(obs @ e2, obs @ e1)
        h = np.stack([f(m * psi) for m in range(1, harmonics + 1) for f in (np.cos, np.sin)], -1)
        cols = [D[:, :, i:i + 1] * (h * sd[:, i])[:, None, :] for i in (0, 1)]
        return np.concatenate([G * rest[None, None, :]] + cols, -1), white

    def decay(k, x, R_k):
        return np.concatenate([prod.decay(k, x, R_k), np.ones((1, nh))], -1)

    return rendezvous_filter.CobBias(prod.n + nh, columns, decay, prod.start)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="far", choices=sorted(rendezvous_spec.PRESETS))
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6])
    ap.add_argument("--cases", type=int, default=100)
    ap.add_argument("--spin", type=int, default=4, help="spin-phase harmonics of the third model (default 4)")
    ap.add_argument("--psi-c", type=float, default=27.0,
                    help="their coefficients' correlation angle over the turn, deg (default 27: the Monte Carlo's "
                         "integral scale along the Sun)")
    args = ap.parse_args()
    M = args.cases
    lo, hi = chi2_mean_bounds(6, M)
    print(f"preset {args.preset}, {M} approaches per seed, seeds {args.seeds}; 95 % bounds of a mean of {M}: "
          f"{lo:.2f}-{hi:.2f}; noise-free images")
    names = ["product", "turn harmonics, white spin", "turn harmonics, spin harmonics", "first harmonic + Gauss-Markov"]
    means = {n: [] for n in names}
    axes = {n: [] for n in names}
    for seed in args.seeds:
        t0 = time.perf_counter()
        d, _ = rendezvous_spec.resolve_spec(args.preset, None, seed=seed, cases=M)
        spec = rz.spec_from_dict(d)
        ctx = rz.make_context(spec)
        if not spec.is_star or not spec.cfg.phase_correction:
            raise SystemExit("bench_rendezvous_bias_models: a star-camera preset with phase_correction (e.g. far)")
        draw0 = rendezvous_truth.draw_case(spec, 0)                 # the preset's phase angle, from its first approach
        geo0 = rendezvous_truth.geometry(spec, draw0, rendezvous_truth.truth_trajectory(spec, draw0))
        alpha = float(np.nanmedian(geo0["targets"].phase_rad))
        stats = offset_harmonics(ctx.shape, alpha, spin_harmonics=args.spin)
        models = {"product": None,
                  "turn harmonics, white spin": lambda: harmonic_cob(spec, ctx, stats, 0, 1.0),
                  "turn harmonics, spin harmonics": lambda: harmonic_cob(spec, ctx, stats, args.spin,
                                                                         math.radians(args.psi_c)),
                  "first harmonic + Gauss-Markov": lambda: first_harmonic_cob(spec, ctx, stats)}
        N = {n: [] for n in names}
        Z = {n: [] for n in names}
        for i in range(M):
            draw = rendezvous_truth.draw_case(spec, i)
            truth = rendezvous_truth.truth_trajectory(spec, draw)
            m, _ = rendezvous_measure.measure_star(spec, ctx, draw, rendezvous_truth.geometry(spec, draw, truth), False)
            for n in names:
                xs, Ps = rendezvous_filter.run_filter(spec, ctx, draw, copy.deepcopy(m),
                                                      models[n]() if models[n] else None)
                N[n].append(nees(xs, Ps, truth))
                Z[n].append((xs[:, :3] - truth[:, :3]) ** 2 / np.diagonal(Ps[:, :3, :3], axis1=1, axis2=2))
        conv = spec.cfg.converged_after_frames
        for n in names:
            mean = np.array(N[n]).mean(0)[conv:]
            means[n].append(mean)
            z = np.array(Z[n])[:, conv:].mean((0, 1))
            axes[n].append(z)
            print(f"seed {seed}, {n}: outside {int(np.sum((mean < lo) | (mean > hi)))} of {mean.size} frames, mean "
                  f"NEES {mean.mean():.2f} ({mean.min():.2f}-{mean.max():.2f}); radial / along / cross "
                  f"{z[0]:.2f} / {z[1]:.2f} / {z[2]:.2f}", flush=True)
        print(f"  ({time.perf_counter() - t0:.0f} s)", flush=True)
    for n in names:
        a = np.array(means[n])
        z = np.mean(axes[n], 0)
        print(f"{n}: pooled mean NEES {a.mean():.2f} (6 expected), outside {int(np.sum((a < lo) | (a > hi)))} of "
              f"{a.size} frames; radial / along / cross {z[0]:.2f} / {z[1]:.2f} / {z[2]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
