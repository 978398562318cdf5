"""The rendezvous filter's consistency over several seeds (issue 23, point 6 c): is a failed NEES check a wrong
covariance or a non-Gaussian error?

    python benchmarks/bench_rendezvous_nees.py [--preset far|close] [--seeds 1 2 3 4 5 6] [--cases 100]

For each seed, ``--cases`` approaches of the preset are computed as ``dualsight rendezvous run`` computes them
(``jobs/kinds/rendezvous.compute_case``, one process).  Printed per seed, from the spec's
``converged_after_frames`` on:

* the frames whose mean NEES over the approaches lies outside its two-sided 95 % chi-square bounds (6 dof,
  ``nav/relative_filter.chi2_mean_bounds``: the report's check (c)), and the mean NEES over those frames;
* the mean squared normalised error per Hill axis (radial, along-track, cross-track position; 1 when the stated
  sigma of that axis is right);
* the three approaches with the largest mean NEES.

Then over all seeds: the pooled mean NEES (6 when the covariance is right on average), and the *dispersion
ratio*: the spread of the per-frame mean NEES across seeds, RMS over frames, over the spread a Gaussian error
would give (sqrt(2 x 6 / M) for a mean of M approaches).  A ratio near 1 with a pooled mean near 6 means the
bounds should hold; a ratio well above 1 means the approaches' errors have heavier tails than a Gaussian's, which
no covariance can make pass every seed.

Last, the source of such tails in the preset's geometry: the spin-averaged photocentre offset along the Sun of
the target (``scene/target_photometry.photocentre_offset``, Lambertian facets; spin axes uniform on the sphere, 24
spin phases, the preset's median phase angle) -- the per-approach bias the filter's bias states stand for
(``scene/photocentre_bias.py``) -- with its kurtosis (3 for a Gaussian) and the share beyond 2 and 3 standard
deviations (Gaussian: 4.6 % and 0.27 %).  And how that bias changes as the observer turns about the Sun over the
approach (:func:`bias_harmonics`): its Fourier harmonics in the turn angle psi, with each one's share of the variance
and kurtosis.  Where the Sun lies along the orbit normal the observer turns once per orbit, so the first harmonic
along the Sun, a_1 cos psi + b_1 sin psi in metres across the orbit plane, has the form of the Clohessy-Wiltshire
cross-track motion z(t) = A cos nt + B sin nt: no bearing separates them, and what the filter states for the
cross-track state must hold that harmonic's spread over spin axes.  Last, how much of the first harmonic the target's
light curve over the orbit tells (the spin-averaged brightness and its relative scatter over the spin, their first
4 harmonics, a linear fit on half of the spin axes): R^2 on the other half; and how far a variance set per approach
from the first frames' light curve would shorten the first harmonic's tail (:func:`light_curve_conditioning`).

    python benchmarks/bench_rendezvous_nees.py --truth-only      # the last two parts only (~30 s)

And how often would a campaign pass?  ``--bootstrap B`` pools the seeds' approaches and draws ``B`` samples of
``--cases`` approaches from them (with replacement): the share of samples whose mean NEES stays inside the bounds at
every frame from ``converged_after_frames`` on -- check (c)'s chance for a campaign of this filter on this preset,
whatever its seed.  The same for a *Gaussian twin* of the pool: errors that are exactly Gaussian with the stated
covariance (NEES chi-square(6) at every frame) and as persistent from frame to frame as the pool's (6 normalised
errors per approach, each a first-order autoregression with correlation rho per frame; a chi-square's lag-1
correlation is then rho^2, set to the pool's lag-1 NEES correlation): what a consistent filter whose errors were
Gaussian would score on the same check; and both counts with the usual reading of a 95 % bound over a run,
inside at >= 95 % of the frames.

The light-curve part uses the frames an approach really has (:func:`early_light_curve_fit`): frame k of the far
preset at turn 2 pi k / 57 and spin phase 99.6 k deg, one brightness per frame, a linear fit of the first
harmonic on the first K frames' brightnesses (K = 10, the frames before convergence, and K = 40), with the
held-out residual's kurtosis.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from dualsight.jobs.kinds import rendezvous as rz, rendezvous_spec
from dualsight.nav.relative_filter import chi2_mean_bounds
from dualsight.scene.attitude import quat_to_dcm, quaternions_from_uniforms
from dualsight.scene.rotation_vector import frame_rotation
from dualsight.scene.target_photometry import apparent_brightness, photocentre_offset


def seed_run(preset: str, seed: int, cases: int) -> dict:
    d, _ = rendezvous_spec.resolve_spec(preset, None, seed=seed, cases=cases)
    spec = rz.spec_from_dict(d)
    ctx = rz.make_context(spec)
    nees, z2, phase = [], [], []
    for i in range(cases):
        o = rz.compute_case(spec, ctx, i)
        nees.append(o["nees"])
        err = o["est"][:, :3] - o["truth"][:, :3]
        var = np.diagonal(o["cov"][:, :3, :3], axis1=1, axis2=2)
        z2.append(err ** 2 / var)
        phase.append(o["meas"]["phase"])
    return {"spec": spec, "ctx": ctx, "nees": np.array(nees), "z2": np.array(z2),
            "phase": np.nanmedian(np.concatenate(phase))}


def spin_attitudes(n_axes: int, n_phases: int, seed: int) -> np.ndarray:
    """(n_axes n_phases, 3, 3) body -> frame rotations: ``n_axes`` spin axes uniform on the sphere, each with an
    initial attitude uniform on SO(3), at ``n_phases`` even spin phases (axis-major), from ``default_rng(seed)``."""
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(n_axes, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    u = rng.random((3, n_axes))
    R0 = quat_to_dcm(quaternions_from_uniforms(u[0], u[1], u[2]))
    phi = np.arange(n_phases) * (2.0 * np.pi / n_phases)
    return frame_rotation((axes[:, None, :] * phi[None, :, None]).reshape(-1, 3)) @ np.repeat(R0, n_phases, 0)


def bias_tails(shape, alpha: float, n_axes: int = 4000, n_phases: int = 24, seed: int = 5) -> dict:
    """The spin-averaged photocentre offset along the Sun's projection (m) over spin axes uniform on the sphere and
    initial attitudes uniform on SO(3), Sun along +z, observer at ``alpha`` rad from it: std, kurtosis, tails."""
    R = spin_attitudes(n_axes, n_phases, seed)
    sun = np.array([0.0, 0.0, 1.0])
    obs = np.array([np.sin(alpha), 0.0, np.cos(alpha)])
    e_sun = sun - np.cos(alpha) * obs
    e_sun /= np.linalg.norm(e_sun)
    off = photocentre_offset(shape, R, np.tile(sun, (len(R), 1)), np.tile(obs, (len(R), 1)))
    b = (off @ e_sun).reshape(n_axes, n_phases).mean(1)
    z = (b - b.mean()) / b.std()
    return {"std_m": float(b.std()), "kurtosis": float(np.mean(z ** 4)),
            "beyond2": float(np.mean(np.abs(z) > 2)), "beyond3": float(np.mean(np.abs(z) > 3))}


def turn_offsets(shape, alpha: float, n_axes: int, n_phases: int, n_turns: int, seed: int):
    """The Lambertian photocentre offset (m) along the Sun's side and across, and the brightness (E / E_sun at
    unit distance), of :func:`spin_attitudes`' attitudes seen from far by an observer at ``alpha`` rad from the Sun
    (along +z) turned about it by ``n_turns`` even steps: (turns, axes, phases, 2) and (turns, axes, phases)."""
    R = spin_attitudes(n_axes, n_phases, seed)
    sun = np.array([0.0, 0.0, 1.0])
    turns = np.arange(n_turns) * (2.0 * np.pi / n_turns)
    obs = np.stack([np.sin(alpha) * np.cos(turns), np.sin(alpha) * np.sin(turns),
                    np.full_like(turns, np.cos(alpha))], -1)
    e_sun = sun - np.cos(alpha) * obs
    e_sun /= np.linalg.norm(e_sun, axis=-1, keepdims=True)
    e_cross = np.cross(obs, e_sun)
    far = 1e6                                             # seen from far (as photocentre_offset does)
    pos = np.repeat(-far * obs, len(R), 0)
    br = apparent_brightness(shape, np.tile(R, (n_turns, 1, 1)), pos, np.tile(sun, (n_turns * len(R), 1)), 1.0)
    off = (br.cob_cam - pos).reshape(n_turns, n_axes, n_phases, 3)
    comp = np.stack([np.einsum("tmkj,tj->tmk", off, e_sun), np.einsum("tmkj,tj->tmk", off, e_cross)], -1)
    return comp, br.ratio.reshape(n_turns, n_axes, n_phases) * far ** 2


def bias_harmonics(shape, alpha: float, n_axes: int = 2000, n_phases: int = 24, n_turns: int = 24,
                   seed: int = 5, n_light: int = 4) -> dict:
    """Spin-averaged photocentre offsets (m) along the Sun's projection and across it, Sun along +z, the observer at
    ``alpha`` rad from it turned about z by ``n_turns`` even steps, over ``n_axes`` spin axes (uniform on the sphere;
    initial attitudes uniform on SO(3); ``n_phases`` spin phases).  The bias per axis (minus the mean over axes, per
    turn) as a Fourier series in the turn psi: b(psi) = a_0 + sum_m (a_m cos m psi + b_m sin m psi).  Returns
    ``share`` (3, 2) the variance share of harmonics 0, 1, 2 (along, across; sum_m var(a_m) / var(b)),
    ``kurtosis`` (3, 2) of a_0, a_1, a_2, and ``r2_light`` (2,) the held-out R^2 of a linear fit of a_1 and b_1
    along the Sun on the first ``n_light`` harmonics of the spin-averaged brightness (relative to its mean over
    the turn) and of its relative scatter over the spin (module docstring)."""
    comp, flux = turn_offsets(shape, alpha, n_axes, n_phases, n_turns, seed)
    bias = comp.mean(2)
    bias = bias - bias.mean(1, keepdims=True)             # (turns, axes, 2)
    C = np.fft.rfft(bias, axis=0) / n_turns               # a_0 = C_0, a_m = 2 Re C_m, b_m = -2 Im C_m
    coef = [C[0].real] + [2.0 * C[m].real for m in (1, 2)]
    var_m = [np.mean(C[0].real ** 2, 0)] + [np.mean(np.abs(2.0 * C[m]) ** 2, 0) / 2.0 for m in (1, 2)]
    total = np.mean(bias ** 2, (0, 1))
    share = np.array([v / total for v in var_m])           # (a_m^2 + b_m^2) / 2 averages to var(a_m) for m >= 1
    kurt = np.array([np.mean(c ** 4, 0) / np.mean(c ** 2, 0) ** 2 for c in coef])
    F = flux.mean(2)
    light = [F / F.mean(0, keepdims=True), flux.std(2) / np.maximum(F, 1e-300)]
    X = [np.ones(n_axes)]
    for y in light:
        Cy = np.fft.rfft(y, axis=0) / n_turns
        X += [Cy[0].real] + [part for m in range(1, n_light + 1) for part in (Cy[m].real, Cy[m].imag)]
    X = np.stack(X, -1)
    fit = np.arange(n_axes) < n_axes // 2
    r2 = []
    for y in (2.0 * C[1][:, 0].real, -2.0 * C[1][:, 0].imag):
        beta, *_ = np.linalg.lstsq(X[fit], y[fit], rcond=None)
        res = y[~fit] - X[~fit] @ beta
        r2.append(1.0 - res.var() / y[~fit].var())
    return {"share": share, "kurtosis": kurt, "r2_light": np.array(r2), "sigma_m": np.sqrt(total)}


def light_curve_conditioning(shape, alpha: float, n_axes: int = 4000, n_phases: int = 24, n_turns: int = 24,
                             seed: int = 5, early_turns: int = 1, bins: int = 5) -> dict:
    """Would a filter that sets its bias states' variance per approach from the light curve it has seen remove the
    first harmonic's heavy tail?  The first harmonic along the Sun (a_1, b_1 of :func:`bias_harmonics`) over
    ``n_axes`` spin axes, and two features of the light curve over the first ``early_turns`` of the ``n_turns``
    turn steps (the first frames of an approach: the spin-phase samples at a nearly fixed geometry): the mean
    brightness (relative to its mean over the axes) and its relative scatter over the spin.  The axes binned by
    ``bins`` quantiles of each feature (``bins`` x ``bins`` cells); the conditional variance E[a_1^2 + b_1^2 | cell]
    / 2 normalises a_1 and b_1.  Returns the kurtosis of a_1 and b_1 before (3 for a Gaussian; the seeds' spread of
    a mean of M squares is sqrt((k - 1) / M)) and after, and the range of the cells' variance over the overall one."""
    comp, flux = turn_offsets(shape, alpha, n_axes, n_phases, n_turns, seed)
    bias = comp.mean(2)
    bias = bias - bias.mean(1, keepdims=True)
    C = np.fft.rfft(bias[:, :, 0], axis=0) / n_turns
    a1, b1 = 2.0 * C[1].real, -2.0 * C[1].imag
    h2 = a1 ** 2 + b1 ** 2
    f = flux[:early_turns]
    mean = f.mean((0, 2))
    feats = (mean / mean.mean(), f.std((0, 2)) / mean)
    cell = np.zeros(n_axes, np.int64)
    for x in feats:
        q = np.quantile(x, np.linspace(0.0, 1.0, bins + 1))
        cell = cell * bins + np.clip(np.searchsorted(q, x, side="right") - 1, 0, bins - 1)
    var = np.array([h2[cell == k].mean() if np.any(cell == k) else h2.mean() for k in range(bins * bins)])
    s = np.sqrt(var[cell] / 2.0)

    def kurt(x):
        z = x - x.mean()
        return float(np.mean(z ** 4) / np.mean(z ** 2) ** 2)

    return {"kurtosis": (kurt(a1), kurt(b1)), "kurtosis_conditioned": (kurt(a1 / s), kurt(b1 / s)),
            "variance_range": (float(var.min() / h2.mean()), float(var.max() / h2.mean()))}


def early_light_curve_fit(shape, alpha: float, frames: int, n_axes: int = 6000, n_phases: int = 24,
                          n_turns: int = 24, frames_orbit: int = 57, spin_step_deg: float = 99.6,
                          seed: int = 7) -> dict:
    """How much of the first harmonic along the Sun (a_1, b_1 of :func:`bias_harmonics`, over ``n_axes`` spin axes
    and initial attitudes) does the light curve of an approach's first ``frames`` frames tell?  Frame k is seen at
    turn 2 pi k / ``frames_orbit`` and spin phase k ``spin_step_deg`` (one brightness per frame, relative to its mean
    over the axes); a linear fit of a_1 and b_1 on those brightnesses over half of the axes.  Returns the held-out
    R^2 and the kurtosis before and after (the residual: what a filter that subtracted the prediction would still
    hold), each (cos, sin)."""
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(n_axes, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    u = rng.random((3, n_axes))
    R0 = quat_to_dcm(quaternions_from_uniforms(u[0], u[1], u[2]))
    sun = np.array([0.0, 0.0, 1.0])
    far = 1e6

    def seen(psi, phi):                 # comp (turns, axes, phases, 2), brightness (turns, axes, phases)
        R = frame_rotation((axes[:, None, :] * phi[None, :, None]).reshape(-1, 3)) @ np.repeat(R0, len(phi), 0)
        obs = np.stack([np.sin(alpha) * np.cos(psi), np.sin(alpha) * np.sin(psi),
                        np.full_like(psi, np.cos(alpha))], -1)
        e_sun = sun - np.cos(alpha) * obs
        e_sun /= np.linalg.norm(e_sun, axis=-1, keepdims=True)
        pos = np.repeat(-far * obs, len(R), 0)
        br = apparent_brightness(shape, np.tile(R, (len(psi), 1, 1)), pos, np.tile(sun, (len(psi) * len(R), 1)), 1.0)
        off = (br.cob_cam - pos).reshape(len(psi), n_axes, len(phi), 3)
        return np.einsum("tmkj,tj->tmk", off, e_sun), br.ratio.reshape(len(psi), n_axes, len(phi))

    along, _ = seen(np.arange(n_turns) * (2.0 * np.pi / n_turns), np.arange(n_phases) * (2.0 * np.pi / n_phases))
    bias = along.mean(2)
    bias = bias - bias.mean(1, keepdims=True)
    C = np.fft.rfft(bias, axis=0) / n_turns
    lc = np.stack([seen(np.array([2.0 * np.pi * k / frames_orbit]), np.array([np.radians(spin_step_deg * k)]))[1][0, :, 0]
                   for k in range(frames)], -1)
    X = np.concatenate([np.ones((n_axes, 1)), lc / lc.mean(0, keepdims=True)], -1)
    fit = np.arange(n_axes) < n_axes // 2

    def kurt(x):
        z = x - x.mean()
        return float(np.mean(z ** 4) / np.mean(z ** 2) ** 2)

    r2, k0, k1 = [], [], []
    for y in (2.0 * C[1].real, -2.0 * C[1].imag):
        beta, *_ = np.linalg.lstsq(X[fit], y[fit], rcond=None)
        res = y[~fit] - X[~fit] @ beta
        r2.append(1.0 - res.var() / y[~fit].var())
        k0.append(kurt(y[~fit]))
        k1.append(kurt(res))
    return {"r2": np.array(r2), "kurtosis": np.array(k0), "kurtosis_residual": np.array(k1)}


def ar1_nees(rng, shape: tuple, frames: int, rho: float) -> np.ndarray:
    """(*shape, frames) NEES of errors exactly Gaussian with the stated covariance (6 unit normals per approach and
    frame, each a first-order autoregression with correlation ``rho`` per frame): chi-square(6) at every frame."""
    e = rng.normal(size=(*shape, 6))
    out = np.empty((*shape, frames))
    for k in range(frames):                        # frames: a short recursion over whole arrays
        if k:
            e = rho * e + np.sqrt(1.0 - rho ** 2) * rng.normal(size=e.shape)
        out[..., k] = (e ** 2).sum(-1)
    return out


def check_c(means: np.ndarray, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """Check (c) on mean-NEES curves ``means`` (samples, frames): inside [lo, hi] at every frame, and at >= 95 % of
    the frames (the usual reading of a 95 % bound over a run: Bar-Shalom, Li and Kirubarajan 2001, the
    filter consistency tests)."""
    inside = (means >= lo) & (means <= hi)
    return inside.all(-1), inside.mean(-1) >= 0.95


def bootstrap_pass(nees: np.ndarray, M: int, lo: float, hi: float, B: int, seed: int = 11) -> dict:
    """How often check (c) holds for a campaign of ``M`` approaches (module docstring): ``B`` samples drawn with
    replacement from the pool ``nees`` (approaches, frames), from its Gaussian twin's pool of the same size, and
    from the twin itself (fresh draws: the probability for a consistent Gaussian filter, which the bootstrap of a
    finite pool understates).  Returns {name: (share inside at every frame, share inside at >= 95 % of frames)}
    and ``lag1``, the pool's lag-1 NEES correlation."""
    rng = np.random.default_rng(seed)
    n, F = nees.shape
    lag1 = float(np.mean([np.corrcoef(nees[:, k], nees[:, k + 1])[0, 1] for k in range(F - 1)]))
    rho = np.sqrt(max(lag1, 0.0))
    out = {"lag1": lag1}
    for name, pool in (("pool", nees), ("twin_pool", ar1_nees(rng, (n,), F, rho))):
        means = np.stack([pool[rng.integers(0, n, M)].mean(0) for _ in range(B)])
        out[name] = tuple(float(x.mean()) for x in check_c(means, lo, hi))
    out["twin"] = tuple(float(x.mean()) for x in check_c(ar1_nees(rng, (B, M), F, rho).mean(1), lo, hi))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="far", choices=sorted(rendezvous_spec.PRESETS))
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6])
    ap.add_argument("--cases", type=int, default=100)
    ap.add_argument("--truth-only", action="store_true",
                    help="only the photocentre bias's tails, harmonics and light-curve fit (no filter runs)")
    ap.add_argument("--save", metavar="FILE.npz", help="write each seed's NEES (approaches, frames >= convergence)")
    ap.add_argument("--bootstrap", type=int, default=0, metavar="B",
                    help="B samples of --cases approaches from the seeds' pool: the share passing check (c)")
    args = ap.parse_args()
    if args.truth_only:
        d, _ = rendezvous_spec.resolve_spec(args.preset, None, seed=args.seeds[0], cases=1)
        ctx = rz.make_context(rz.spec_from_dict(d))
        truth_model(ctx.shape, np.radians(90.0))
        return 0
    M = args.cases
    lo, hi = chi2_mean_bounds(6, M)
    print(f"preset {args.preset}, {M} approaches per seed, seeds {args.seeds}; 95 % bounds of a mean of {M}: "
          f"{lo:.2f}-{hi:.2f}")
    means, last, pool = [], None, []
    for seed in args.seeds:
        t0 = time.perf_counter()
        r = seed_run(args.preset, seed, M)
        conv = r["spec"].cfg.converged_after_frames
        m = r["nees"].mean(0)[conv:]
        means.append(m)
        pool.append(r["nees"][:, conv:])
        out = int(np.sum((m < lo) | (m > hi)))
        z2 = r["z2"][:, conv:].mean((0, 1))
        per = r["nees"][:, conv:].mean(1)
        print(f"seed {seed}: outside {out} of {m.size} frames, mean NEES {m.mean():.2f}; mean squared normalised "
              f"error radial / along / cross {z2[0]:.2f} / {z2[1]:.2f} / {z2[2]:.2f}; worst approaches "
              f"{np.sort(per)[-3:].round(1).tolist()} ({time.perf_counter() - t0:.0f} s)", flush=True)
        last = r
    means = np.array(means)
    print(f"pooled over {len(args.seeds)} x {M} approaches: mean NEES {means.mean():.2f} (6 expected)")
    if len(args.seeds) > 1:
        ratio = float(np.sqrt(np.mean(means.var(0, ddof=1))) / np.sqrt(12.0 / M))
        print(f"dispersion ratio across seeds: {ratio:.2f} (1 for Gaussian errors)")
    if args.save:
        np.savez_compressed(args.save, **{f"seed{seed}": p for seed, p in zip(args.seeds, pool)})
    if args.bootstrap:
        b = bootstrap_pass(np.concatenate(pool), M, lo, hi, args.bootstrap)
        n = sum(map(len, pool))
        print(f"check (c) on {args.bootstrap} samples of {M} approaches (share inside the bounds at every frame / at "
              f">= 95 % of the frames; lag-1 NEES correlation of the pool {b['lag1']:.2f}):")
        for key, what in (("pool", f"drawn from the pooled {n} approaches"),
                          ("twin_pool", f"drawn from a pool of {n} of its Gaussian twin"),
                          ("twin", "its Gaussian twin, fresh draws (a consistent Gaussian filter)")):
            print(f"  {what}: {100 * b[key][0]:.0f} % / {100 * b[key][1]:.0f} %")
    truth_model(last["ctx"].shape, float(last["phase"]))
    return 0


def truth_model(shape, alpha: float) -> None:
    """Print :func:`bias_tails` and :func:`bias_harmonics` at phase angle ``alpha`` (rad)."""
    bt = bias_tails(shape, alpha)
    print(f"spin-averaged photocentre offset along the Sun at {np.degrees(alpha):.0f} deg phase: std "
          f"{bt['std_m'] * 100:.2f} cm, kurtosis {bt['kurtosis']:.1f} (Gaussian 3), beyond 2 / 3 sigma "
          f"{bt['beyond2'] * 100:.1f} / {bt['beyond3'] * 100:.2f} % (Gaussian 4.6 / 0.27 %)")
    h = bias_harmonics(shape, alpha)
    print(f"as the observer turns about the Sun (std {h['sigma_m'][0] * 1000:.1f} / {h['sigma_m'][1] * 1000:.1f} mm "
          "along / across the Sun), its variance by harmonic of the turn:")
    for m in range(3):
        print(f"  m = {m}: share {h['share'][m, 0] * 100:.0f} / {h['share'][m, 1] * 100:.0f} %, kurtosis "
              f"{h['kurtosis'][m, 0]:.1f} / {h['kurtosis'][m, 1]:.1f}")
    print(f"  first harmonic along the Sun from the light curve (linear, held-out spin axes): R^2 "
          f"{h['r2_light'][0]:.2f} (cos), {h['r2_light'][1]:.2f} (sin)")
    lc = light_curve_conditioning(shape, alpha)
    print(f"  its variance set per approach from the first frames' light curve (mean brightness x its scatter over "
          f"the spin, 5 x 5 quantile cells, 4000 spin axes): the cells' variance {lc['variance_range'][0]:.2f}-"
          f"{lc['variance_range'][1]:.2f} x the overall; kurtosis of a_1 / b_1 {lc['kurtosis'][0]:.1f} / "
          f"{lc['kurtosis'][1]:.1f} -> {lc['kurtosis_conditioned'][0]:.1f} / {lc['kurtosis_conditioned'][1]:.1f} "
          "(Gaussian 3)")
    for K in (10, 40):
        e = early_light_curve_fit(shape, alpha, K)
        print(f"  predicted from the approach's first {K} frames' brightness (one per frame, linear, held-out axes): "
              f"R^2 {e['r2'][0]:.2f} / {e['r2'][1]:.2f} (cos / sin); kurtosis {e['kurtosis'][0]:.1f} / "
              f"{e['kurtosis'][1]:.1f} -> residual {e['kurtosis_residual'][0]:.1f} / {e['kurtosis_residual'][1]:.1f}")


if __name__ == "__main__":
    raise SystemExit(main())
