"""Detection and identification rates on frames rendered with each sensor-realism feature, default settings
(issue 11, "Done when").

Every variant is the ``realistic`` star preset (jobs/kinds/star.py: a CMV4000-like 12-bit CMOS star camera on the
reference's 1024 x 768, 17 mm optics, V 5.5 catalog; defocus-disk PSF, shot + read + dark noise, sky, hot
pixels 1e-4) with ONE feature changed or strengthened, and nothing else: no detection or identification
setting is touched (the detector is the spec's ``auto`` choice, the identification the robust method's
defaults).  Truth is independent of the detector: the rendered stars' positions and fluxes.

* **detection completeness**: of the stars inside the frame whose optimal integrated SNR is >= 10, the
  fraction matched by a detection within 2 px.  The SNR is the analytic one of a PSF-weighted sum on white
  noise, F / sqrt(F + n_eff var), with var = read^2 + dark t + sky (+ stray light, + gain^2 / 12 for the ADC)
  per pixel and n_eff = (sum p)^2 / sum p^2 the noise-equivalent area of the variant's own PSF (rendered
  once, noise-free);
* **identification**: among the cases with >= 4 such stars, the fraction answered with every accepted
  identity right (target >= 95 %, the issue's ~10 true + ~5 false target); wrong answers <= 1 % of all cases.
  An accepted identity is right when that catalog star was rendered within 1 px of the detection;
* **centroids**: the median distance of a matched detection from its star, against the Cramér-Rao scale;
* frames with as many false stars as true ones: >= 90 % identified, <= 1 % wrong; ~10 true + 5 false: >= 95 %.

Measured (64 cases per variant, V 5.5, this code): completeness 0.978-0.994, identified 96.8-100 % of the
eligible cases, 0 wrong, in every variant; the stray-light variant with the reference's one global threshold
(what ``detector = "global"`` does) finds 12 % of the stars: that is why ``auto`` picks the local detector.
Seen failing on broken implementations: the PSF-width measurement taking hot-pixel clusters (completeness
0.60 with hot pixels 1e-3), ``auto`` resolving to the global detector (stray light: 0.12), the Moon's
glare taken as stars (large-blob test disabled).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from dualsight.jobs.kinds import star
from dualsight.kernels import psf_models
from dualsight.kernels import starfield as kstar
from dualsight.scene.psf_file import sensor_psf

N_CASES = 64
BATCH = 16


def _asym_psf():
    """An asymmetric 9 x 13 measured-PSF stamp: a tilted elliptical core and a side lobe (coma-like)."""
    j, i = np.mgrid[0:9, 0:13].astype(float)
    u, v = i - 6.3, j - 3.8
    core = np.exp(-0.5 * ((0.9 * u + 0.3 * v) ** 2 / 1.3 ** 2 + (-0.3 * u + 0.9 * v) ** 2 / 0.9 ** 2))
    return core + 0.2 * np.exp(-0.5 * ((i - 8.5) ** 2 + (j - 2.5) ** 2) / 0.6 ** 2)


def _moons(spec, case_ids, dx=250.0, dy=-150.0):
    """One full Moon (V -12.7, 16.6 px radius) per case, placed at pixel (cx + dx, cy + dy) of that case's
    frame: its direction (pinhole camera, no distortion) rotated to the sky with the case's true attitude."""
    cam = spec.camera
    A = star.draw_cases(spec, np.asarray(case_ids))["A_true"]
    v = np.array([dx / cam.fx, dy / cam.fy, 1.0])
    u = np.einsum("bji,j->bi", A, v / np.linalg.norm(v))             # A^T v: camera -> inertial
    ra = np.degrees(np.arctan2(u[:, 1], u[:, 0])) % 360.0
    dec = np.degrees(np.arcsin(np.clip(u[:, 2], -1, 1)))
    return [{"ra_deg": float(r), "dec_deg": float(d), "vmag": -12.7, "radius_px": 16.6} for r, d in zip(ra, dec)]


VARIANTS = {
    "realistic": {},
    "gaussian_psf": {"sensor.psf_model": "gaussian", "sensor.psf_sigma_px": 1.0, "sensor.defocus_gaussian": False},
    "measured_psf": {"sensor.psf_model": "image", "sensor.defocus_gaussian": False},       # psf_image: tmp file
    "smear": {"sensor.rate_deg_s": [0.0, 0.5, 0.3]},                     # ~5 px along x, roll arcs to ~3 px
    "stray_light": {"sensor.stray_light_e": [200.0, 0.3, 0.2]},          # 200 e- at the centre, 0-430 e-
    "moon": {},                                                          # bright_objects: one Moon per case
    "hot_pixels": {"sensor.hot_pixel_fraction": 1e-3},                   # 786 hot pixels per frame
    "8bit": {"sensor.bit_depth": 8, "sensor.gain_e_per_adu": 13500.0 / 255, "sensor.bias_adu": 2.0},
    "16bit": {"sensor.bit_depth": 16, "sensor.gain_e_per_adu": 0.25, "sensor.bias_adu": 100.0},
    "saturation": {"sensor.full_well_e": 3000.0, "sensor.gain_e_per_adu": 3000.0 / 4095},
}


def _spec(over: dict, psf_path=None, moons_for=None):
    d, _ = star.resolve_spec("realistic", None, cases=N_CASES)
    for k, v in over.items():
        sec, key = k.split(".")
        d[sec][key] = v
    if over.get("sensor.psf_model") == "image":
        d["sensor"]["psf_image"] = str(psf_path)
    spec = star.spec_from_dict(d)
    if moons_for is not None:
        d["sensor"]["bright_objects"] = _moons(spec, moons_for)
        spec = star.spec_from_dict(d)
    return spec


def _n_eff(spec) -> float:
    """Noise-equivalent area (px) of the spec's PSF: one noise-free star rendered near the centre."""
    s = dataclasses.replace(spec.sensor, shot_noise=False, read_noise_e=0.0, dark_current_e_per_s=0.0,
                            sky_background_e=0.0, hot_pixel_fraction=0.0, stray_light_e=(0.0, 0.0, 0.0),
                            bright_objects=(), quantize=False, full_well_e=1e12, bit_depth=24, bias_adu=0.0,
                            gain_e_per_adu=1.0)
    cam = spec.camera
    img = kstar.render_star_fields(np.array([[cam.cx + 0.3]]), np.array([[cam.cy - 0.2]]), np.array([[1e5]]), None,
                                   cam.width, cam.height, s, np.array([1], np.uint64), camera=cam,
                                   attitude=np.eye(3)[None], dtype=np.float32,
                                   psf=sensor_psf(spec.sensor))[0].astype(np.float64)
    return float(img.sum() ** 2 / (img ** 2).sum())


def _pixel_var(s, x, y):
    """Analytic per-pixel noise variance (e-^2) at (x, y): read^2 + dark t + sky + stray light + ADC."""
    cam_cx, cam_cy = 512.0, 384.0
    e0, gx, gy = s.stray_light_e
    stray = np.maximum(e0 + gx * (x - cam_cx) + gy * (y - cam_cy), 0.0)
    return s.read_noise_e ** 2 + s.base_e + stray + s.gain_e_per_adu ** 2 / 12.0


def _n_wrong(ident, obs, f, radius_px: float = 1.0) -> np.ndarray:
    """(B,) accepted identities whose catalog star was not rendered within ``radius_px`` of the detection's
    centroid.  Not "nearest star" (``nav.truth_match``): of a blend closer than the PSF (measured here: a
    13,600 e- and a 1,600 e- star 0.47 and 0.25 px from one centroid) either identity is right."""
    S = min(ident.ids.shape[1], obs.x.shape[1])
    ids, acc = ident.ids[:, :S], ident.accepted[:, :S] & (ident.ids[:, :S] >= 0)
    same = (f.cat_row[:, None, :] == ids[:, :, None]) & f.valid[:, None, :]              # (B, S, N)
    d = np.hypot(f.x[:, None, :] - obs.x[:, :S, None], f.y[:, None, :] - obs.y[:, :S, None])
    near = (same & (d <= radius_px)).any(-1)
    return (acc & ~near).sum(1)


def _run(spec, case_ids=None):
    """Render, detect and identify; per-variant rates."""
    ctx = star.make_context(spec)
    ne = _n_eff(spec)
    case_ids = np.arange(N_CASES) if case_ids is None else case_ids
    found, eligible, right, wrong, dist, large = [], [], [], [], [], []
    for s in range(0, len(case_ids), BATCH):
        out = star.compute_batch(spec, ctx, case_ids[s:s + BATCH])
        f, tr = out["field"], out["truth"]
        W, H = spec.camera.width, spec.camera.height
        snr = f.flux_e / np.sqrt(f.flux_e + ne * _pixel_var(spec.sensor, f.x, f.y))
        good = f.valid & (f.x > 5) & (f.x < W - 5) & (f.y > 5) & (f.y < H - 5) & (snr >= 10)
        if spec.sensor.bright_objects:      # stars on or next to the Moon's disk are not expected
            bx, by, _, br, _ = psf_models.bright_object_sources(spec.sensor.bright_objects, spec.sensor,
                                                                spec.camera, out["draw"]["A_true"])
            dm = np.hypot(f.x[:, :, None] - bx[:, None, :], f.y[:, :, None] - by[:, None, :]) - br[:, None, :]
            good &= dm.min(-1) > 25
            large.append(out["rendered"].detections.large_blobs)
        for b in range(f.x.shape[0]):
            hit = set(tr.obs_true_row[b][tr.obs_true_row[b] >= 0].tolist())
            found += [r in hit for r in f.cat_row[b][good[b]].tolist()]
        eligible.append(good.sum(1) >= 4)
        ident, _ = out["alt"]
        ans = ident.T > 0
        nw = _n_wrong(ident, out["obs"], f)
        right.append(ans & (nw == 0))
        wrong.append(ans & (nw > 0))
        dist.append(tr.dist_px[np.isfinite(tr.dist_px)])
    cat = np.concatenate
    el, ok, bad = cat(eligible), cat(right), cat(wrong)
    return dict(spec=spec, completeness=float(np.mean(found)), n_stars=len(found), eligible=int(el.sum()),
                ident=float(ok[el].mean()), wrong=float(bad.mean()), median_dist=float(np.median(cat(dist))),
                large=cat(large) if large else None, n_eff=ne)


@pytest.fixture(scope="module")
def psf_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("psf") / "measured_psf.npy"
    np.save(p, _asym_psf())
    return p


@pytest.mark.parametrize("name", list(VARIANTS))
def test_detection_and_identification_rates_with_default_settings(name, psf_file):
    over = VARIANTS[name]
    spec = _spec(over, psf_path=psf_file, moons_for=np.arange(N_CASES) if name == "moon" else None)
    assert spec.detector == "local"          # the realistic preset's: what `hil star` runs on real frames
    r = _run(spec)
    print(name, {k: v for k, v in r.items() if k not in ("spec", "large")})
    assert r["eligible"] >= 0.9 * N_CASES and r["n_stars"] >= 8 * N_CASES      # ~11 stars of V <= 5.5 per field
    assert r["completeness"] >= 0.97, r
    assert r["ident"] >= 0.95 and r["wrong"] <= 0.01, r
    # centroids: the stars here have SNR ~20-1000; the Cramér-Rao scale sqrt(2) s / SNR is <= 0.07 px at the
    # median star (SNR ~40, s ~0.9 px); the measured PSF's own centroid offset (its light's mean, ~0.3 px
    # from the stamp's centre) and a 5 px smear (centroid = mid-exposure position) are allowed for
    limit = {"measured_psf": 0.6, "smear": 0.5}.get(name, 0.15)
    assert r["median_dist"] <= limit, r
    if name == "moon":   # the Moon is one large component in every frame, counted, never a star
        assert (r["large"] >= 1).all()


def test_global_threshold_fails_under_stray_light_so_auto_picks_local():
    """The reference's one threshold per frame under a stray-light gradient finds few of the stars that are
    plainly there (measured 12 %); ``detector = "auto"`` resolves to the local detector for such a sensor and to
    the reference's global one for the paper and noisy presets (uniform background)."""
    spec = _spec(VARIANTS["stray_light"])
    glob = _run(dataclasses.replace(spec, detector="global"), np.arange(32))
    assert glob["completeness"] < 0.5
    for preset, want in (("paper", "global"), ("noisy", "global"), ("ideal", "global"), ("realistic", "local")):
        assert star.resolve(preset, None)[0].detector == want, preset
    for sensor, want in (({"stray_light_e": [5.0, 0.0, 0.0]}, "local"), ({"hot_pixel_fraction": 1e-3}, "global"),
                         ({"bright_objects": [{"ra_deg": 1.0, "dec_deg": 2.0, "vmag": -4.0, "radius_px": 0.0}]},
                          "local")):
        d, _ = star.resolve_spec("paper", None)
        d["sensor"].update(sensor)
        d["detector"] = "auto"                                  # a spec's dict holds the resolved choice
        assert star.spec_from_dict(d).detector == want, sensor
    d, _ = star.resolve_spec("realistic", None)
    d["detector"] = "global"                                   # an explicit choice is kept
    assert star.spec_from_dict(d).detector == "global"


@pytest.mark.parametrize("n_false,target", [(11, 0.90), (5, 0.95)])
def test_realistic_frames_with_false_stars(n_false, target):
    """As many false stars as true ones (~11 + 11; >= 90 % identified, <= 1 % wrong) and ~11 true + 5 false
    (>= 95 %), on the realistic sensor with its default settings."""
    spec = _spec({"sensor.false_stars_per_frame": n_false})
    r = _run(spec)
    print(n_false, {k: v for k, v in r.items() if k not in ("spec", "large")})
    assert r["ident"] >= target and r["wrong"] <= 0.01, r
    assert r["completeness"] >= 0.97, r


def test_snr_model_matches_the_detections_noise():
    """The analytic SNR the rates above rely on: for the realistic preset the per-pixel variance is
    read^2 + dark t + sky + gain^2/12 = 169 + 12.5 + 0.8 + 0.9 e-^2, i.e. 3.9 ADU at 3.3 e-/ADU; the local
    detector's measured noise agrees within 3 %."""
    spec = _spec({})
    out = star.compute_batch(spec, star.make_context(spec), np.arange(4))
    want = math.sqrt(_pixel_var(spec.sensor, 512.0, 384.0)) / spec.sensor.gain_e_per_adu
    assert np.allclose(out["rendered"].detections.noise_adu, want, rtol=0.03), (out["rendered"].detections.noise_adu, want)
