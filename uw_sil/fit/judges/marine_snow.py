"""Diagnosis plug-in of marine snow (:mod:`uw_sil.sim.effects.marine_snow`).

Particles are new in every frame: a simulation with snow puts its specks where the recording has none, so a
pixel-wise θ cannot rise for it (it falls). It is judged on the held-out frames by the density of small
bright specks instead (:func:`uw_sil.fit.signatures.speck_sizes`).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..diagfit import EffectModel, FrameObjective, noise_sigmas
from ..residuals import base_sim
from .base import Judge, Refit, margin_for

def snow_refit(R_hi, fit_f, held_f, base_x, fog, seed, effects: tuple = (), values: Optional[dict] = None) -> dict:
    """Marine snow, fitted and judged by the density of small bright specks (new in every frame).

    Density, brightness and size of the particles are chosen on the fit frames so that simulated frames (the
    current model + snow + the estimated camera noise) show as many bright specks per megapixel as the recording,
    of the same mean area, over the same haze between them (:func:`uw_sil.fit.signatures.speck_sizes`; a grid
    over the three); on the held-out frames the specks of the recording are compared with the current model's
    and the candidate's, pooled over the frames (:func:`pooled_count_gain`). Specks that are not particles
    (:func:`not_particles`: the sensor's, at the same pixel in several frames of the recording, and the scene's, a
    still point the model lacks seen again where the frames' poses put it) are counted neither in the recording nor
    in the simulation. θ is also reported (it cannot rise: particles are at random places).

    ``effects``/``values``: the current model's effects, held at their values. The particles are lit by the
    model's lamps when it has them (else by a camera-mounted lamp) and pass through its camera response: fitted
    without them, their brightness was that of another light, and the model the diagnosis hands to
    ``sim_camera`` rendered other particles (on the physically lit multi-effect dive of seed 500, as simulated,
    held-out θ 0.82 without the snow, 0.67 with it, while the recording's twin with other particles scores 0.83).
    Fitted on the count alone in that model, its 1,500 particles per m³ of 2 mm claimed 96 % of the pixels (a
    veil, rejected; the recording's specks are 1.6-2.1 px); with their size and the haze between them: 40 per m³
    of 5 mm, 37 % of the pixels, as simulated 0.77."""
    from ...sim.effects.base import remembered_draws
    from ...sim.noise import NoiseField
    from ..signatures import luminance, speck_sizes

    effects = tuple(effects)
    fixed = {e: () for e in effects}

    def simulated(k, rf, eff_model, x_none):
        return luminance(255.0 * (eff_model.simulate(k, x_none[None])[0] if effects else base_sim(rf, base_x, fog)))

    def frames_stats(rfs, x_list, eff_model, refs, noise, excluded):
        """per frame: the recording's :func:`~uw_sil.fit.signatures.speck_sizes` (specks per megapixel, mean
        speck area, haze between them, tested megapixels), and the simulation's for each parameter vector in
        x_list: arrays (K, 4) and (K, N, 4) (``refs``: per frame, the model without particles, the noise-free
        simulation the specks are found against; ``noise``: the frames' :func:`~uw_sil.fit.diagfit.noise_sigmas`;
        ``excluded``: per frame, the pixels of specks that are not particles' or None)."""
        out_real, out_sim = [], []
        for k, rf in enumerate(rfs):
            S = refs[k]
            hit = rf.cover > 0
            ex = excluded[k]
            out_real.append(speck_sizes(luminance(rf.image), S, hit, ex))
            nf = NoiseField(rf.shape + (3,), noise[k], seed=seed + 31 * k)
            sims = eff_model.simulate(k, np.stack(x_list)) * 255.0
            row = []
            for img in sims:
                nf.apply(img)
                row.append(speck_sizes(luminance(img), S, hit, ex))
            out_sim.append(row)
        return np.array(out_real), np.array(out_sim)

    rfit = [R_hi[id(f)] for f in fit_f]
    rheld = [R_hi[id(f)] for f in held_f]
    noise_fit, noise_held = noise_sigmas(rfit), noise_sigmas(rheld)
    names = effects + ("marine_snow",)
    model = EffectModel(rfit, names, values=values, free=fixed, fog=fog, seed=seed)
    x_base = model.x0(base_x, {"marine_snow": {"density": 0.0}})
    hmodel = model.like(rheld, seed=seed + 50)
    s_fit = [simulated(k, rf, model, x_base) for k, rf in enumerate(rfit)]
    s_held = [simulated(k, rf, hmodel, x_base) for k, rf in enumerate(rheld)]
    excluded, sensor, scene_n = not_particles(list(fit_f) + list(held_f), rfit + rheld, s_fit + s_held)
    # number, size and brightness of the particles: the speck count per megapixel and the specks' mean area (log
    # ratios; the area where both show specks), and the haze of the faint ones between them
    grid = [(d, b, z) for d in (0.0, 15.0, 40.0, 100.0, 250.0, 600.0, 1500.0, 3000.0) for b in (0.3, 0.75, 1.5, 3.0)
            for z in (0.5, 1.0, 2.0, 5.0)]
    xs = [model.x0(base_x, {"marine_snow": {"density": d, "brightness": b, "size": z}}) for d, b, z in grid]
    with remembered_draws():        # the grid's candidates of one density share their particles' places and light
        real, sim = frames_stats(rfit, xs, model, s_fit, noise_fit, excluded[:len(rfit)])
    e_count = np.abs(np.log1p(sim[..., 0]) - np.log1p(real[:, None, 0]))
    e_area = np.abs(np.log(sim[..., 1]) - np.log(real[:, None, 1]))
    # the haze between the specks, in units of the frame's camera noise (luminance)
    sig = np.array([max(float(np.mean(n)), 0.5) for n in noise_fit])
    e_haze = np.abs(sim[..., 2] - real[:, None, 2]) / sig[:, None]
    err = sum(np.where(np.isfinite(e), e, 0.0) for e in (e_count, e_area, e_haze)).mean(axis=0)
    j = int(np.argmin(err))
    x = xs[j]
    real_h, sim_h = frames_stats(rheld, [x_base, x], hmodel, s_held, noise_held, excluded[len(rfit):])
    # judged on the count of specks, pooled over the held-out frames: a frame of a sparse snow shows 0-4 of them at
    # this resolution, and a frame's log count (0 or 1 speck: a log density of 0 or 2.6) says more of chance than of
    # the particles; pooled, the counts are compared as Poisson counts are, the margin bootstrapped over frames
    c_real = real_h[:, 0] * real_h[:, 3]
    c_sim = sim_h[..., 0] * sim_h[..., 3]
    imp, imp_pf, boot = pooled_count_gain(c_real, c_sim[:, 0], c_sim[:, 1], seed=seed)
    with FrameObjective(rheld, hmodel, noise_held, seed=seed) as oh:
        held_pf = oh.per_frame(x[None])[0]
    unclaimed = unclaimed_theta(rheld, hmodel, x_base, x, seed=seed)
    with FrameObjective(rfit, model, noise_fit, seed=seed) as of:
        th_train = float(of(x[None])[0])
    stat = {"name": "density of bright specks per megapixel", "real": float(np.mean(real_h[:, 0])),
            "base_sim": float(np.mean(sim_h[:, 0, 0])), "candidate_sim": float(np.mean(sim_h[:, 1, 0])),
            "specks": {"real": float(c_real.sum()), "base_sim": float(c_sim[:, 0].sum()),
                       "candidate_sim": float(c_sim[:, 1].sum())},
            "not_particles": {"sensor_pixels": int(sensor[0].sum()), "scene_specks": scene_n},
            "improvement": imp, "margin": max(0.15, 2.0 * float(np.std(boot))),
            "per_frame_improvement": imp_pf.tolist(), "theta_unclaimed": unclaimed}
    return {"x": x, "theta_train": th_train, "held_pf": held_pf, "params": model.params_of(x),
            "model_effects": ["marine_snow"], "fit": None, "res": "high", "statistic": stat}


def not_particles(frames, rframes, sims) -> tuple:
    """Per reduced frame, the pixels of the recording's specks that are not particles, or None: the sensor's
    (:func:`~uw_sil.fit.signatures.persistent_specks`, at the same pixel frame after frame, found at full
    resolution) and the scene's (:func:`~uw_sil.fit.signatures.scene_specks`, a still point the model lacks, seen
    again where the other frames' poses put it), each grown by a pixel. ``frames``: the full-resolution frames,
    ``rframes`` their reduced frames, ``sims`` the noise-free simulation (luminance) each is compared with. Returns
    ``(excluded, sensor, scene_count)``: the union and the sensor's masks per frame, and how many specks were the
    scene's."""
    import cv2

    from ..residuals import box_down, dilate
    from ..signatures import luminance, persistent_specks, scene_specks, speck_masks

    fixed = persistent_specks([f.image for f in frames])
    # (a reduced pixel is the sensor's where any full-resolution pixel of its block is)
    sensor = [np.zeros(rf.shape, bool) if fixed is None else dilate(box_down(fixed, rf.factor) > 0, 1)
              for rf in rframes]
    labels, points = [], []
    for rf, S, sen in zip(rframes, sims, sensor):
        pos = speck_masks(luminance(rf.image), S, rf.cover > 0)[0] & ~sen
        n, lab, _, cen = cv2.connectedComponentsWithStats(pos.astype(np.uint8), 8)
        labels.append(lab)
        points.append((cen[1:] + 0.5) * rf.factor - 0.5)           # full-resolution pixel coordinates
    scene = scene_specks(points, [f.pose for f in frames], frames[0].camera, [f.range_median for f in frames])
    excluded = []
    for lab, flags, sen in zip(labels, scene, sensor):
        ex = sen.copy()
        if flags.any():
            ex |= dilate(np.isin(lab, 1 + np.flatnonzero(flags)), 1)
        excluded.append(ex if ex.any() else None)
    return excluded, sensor, int(sum(int(f.sum()) for f in scene))


def pooled_count_gain(real, base, cand, n: int = 2000, seed: int = 0) -> tuple:
    """How much closer the candidate's speck count comes to the recording's than the base model's, pooled over
    frames: ``|log((B + 1/2) / (C_r + 1/2))| - |log((C + 1/2) / (C_r + 1/2))|`` with the sums ``C_r``, ``B``,
    ``C`` of the per-frame counts ``real``, ``base``, ``cand`` (half a speck keeps an empty count finite); the
    same per frame, and ``n`` bootstrap replicates (frames resampled with replacement): ``(gain, per_frame,
    replicates)``."""
    real, base, cand = (np.asarray(v, float) for v in (real, base, cand))

    def gain(r, b, c):
        r = r + 0.5
        return np.abs(np.log((b + 0.5) / r)) - np.abs(np.log((c + 0.5) / r))

    idx = np.random.default_rng(seed).integers(0, real.size, (n, real.size))
    boot = gain(real[idx].sum(1), base[idx].sum(1), cand[idx].sum(1))
    return float(gain(real.sum(), base.sum(), cand.sum())), gain(real, base, cand), boot


#: A pixel is claimed by the particles where they change the noise-free simulation by more than this (grey levels).
CLAIM_DN = 1.0
#: Below this share of unclaimed pixels (the particles change nearly every pixel) the check has nothing to
#: compare: that is a veil over the whole frame, not particles, and the candidate is not accepted.
MIN_UNCLAIMED = 0.2
#: Claimed pixels are grown by this many pixels: FSIMc's phase congruency (smallest log-Gabor wavelength 6 px)
#: and gradients carry a speck into its neighbours. Grown by 1, sixty specks that were not the recording's
#: lowered θ on a 128x96 frame's other pixels by 0.012; by 2, by 0.001 (below the smallest margin).
CLAIM_GROW = 2


def unclaimed_theta(rframes, model, x_base, x_cand, seed: int = 0) -> dict:
    """θ of the base model and of the snow candidate on the pixels the particles do not claim, per frame.

    Particles are at random places, so θ on their pixels cannot rise; on the other pixels a particle model
    changes nothing, unless it acts as something else (a faint haze of sub-visible specks over the whole
    frame, i.e. a veil the base model lacks or overdoes). There θ must not fall. Claimed: where the candidate's
    noise-free simulation differs from the base model's by more than :data:`CLAIM_DN`, grown by
    :data:`CLAIM_GROW` pixels (a speck's reach in FSIMc's filters). Both are scored with the same camera-noise
    realization against the recording, FSIMc and the histograms on the unclaimed pixels only (panel and water
    apart, as the fit does). Held: the mean fall over frames does not exceed its bootstrap margin."""
    from ...metrics.theta import ThetaReference
    from ...sim.noise import NoiseField
    from ..residuals import LABEL_PANEL
    from scipy.ndimage import binary_dilation

    noise = noise_sigmas(rframes)
    base, cand, share = [], [], []
    for k, rf in enumerate(rframes):
        sims = model.simulate(k, np.stack([x_base, x_cand])) * 255.0
        claimed = binary_dilation(np.abs(sims[1] - sims[0]).max(axis=-1) > CLAIM_DN, iterations=CLAIM_GROW)
        free = ~claimed
        share.append(float(free.mean()))
        if share[-1] < MIN_UNCLAIMED:
            base.append(np.nan)
            cand.append(np.nan)
            continue
        panel = rf.labels == LABEL_PANEL
        masks = [m for m in (panel & free, ~panel & free) if m.sum() >= 64]
        ref = ThetaReference(rf.image, mask=free, hist_mask=masks or None)
        NoiseField(rf.shape + (3,), noise[k], seed=seed + 31 * k).apply(sims)
        b, c = ref.score(sims)
        base.append(float(b))
        cand.append(float(c))
    base, cand = np.array(base), np.array(cand)
    ok_frames = np.isfinite(base) & np.isfinite(cand)
    out = {"base": None, "candidate": None, "fall": None, "margin": None,
           "unclaimed_share": float(np.mean(share)), "frames_checked": int(ok_frames.sum()), "held": False}
    if ok_frames.any():
        fall_pf = (base - cand)[ok_frames]
        fall, margin = float(fall_pf.mean()), margin_for(-fall_pf, seed=seed)
        out.update(base=float(base[ok_frames].mean()), candidate=float(cand[ok_frames].mean()), fall=fall,
                   margin=margin, held=not fall > margin)
    return out


class MarineSnowJudge(Judge):
    effect = "marine_snow"
    free = ("density", "brightness", "size")
    res = "high"
    kind = "statistic"
    least_squares = False

    def refit(self, job, current, x_starts=None, parent=None):
        r = snow_refit(job.R_hi, job.fit_f, job.sel_f, current.base, job.fog, job.seed,
                       effects=current.effects, values=current.values)
        return Refit(effect=self.effect, effects=(self.effect,), x=r["x"], params=r["params"],
                     theta_fit=r["theta_train"], sel_pf=r["held_pf"], statistic=r["statistic"])

    def accept(self, r, current, margin, residual=None):
        st = r.statistic
        # better speck statistics, and no worse elsewhere: θ on the pixels the particles leave alone holds
        ok = st["improvement"] > st["margin"] and st["theta_unclaimed"]["held"]
        return ok, st["improvement"] / (3 * st["margin"]) if ok else 0.0, "statistic"

    def explain(self, e, gain, sig, camera=None):
        dens = sig.stats.get("positive_per_mpx") if sig is not None else None
        extra = f" ({dens:.0f} bright specks per megapixel, new in every frame)" if dens is not None else ""
        return (f"marine snow: small bright particles in the lit water{extra}, about {e.get('density', 0):.0f} "
                f"per m³ of {e.get('size', 0):.1f} mm; {gain}")
