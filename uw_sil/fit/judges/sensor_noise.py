"""Diagnosis plug-in of structured sensor noise (:mod:`uw_sil.sim.effects.sensor_noise`).

New in every frame, so judged by statistics, not by θ: the effect's parameters (shot gain, read noise,
correlation, fixed patterns) are chosen so that simulated frames reproduce the recording's noise
statistics, and accepted when the held-out frames' statistics move towards the recording's beyond their
bootstrap margin. Next to another accepted effect the noise model is kept only if it does not lower held-out
θ beyond the margin (the other effect changes the signal, hence the intensity dependence of the noise).
"""
from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from typing import Optional

import numpy as np

from ..._shared.process import default_threads
from ..diagfit import EffectModel
from ..residuals import reduce_frame
from .base import Judge, Refit, bootstrap_se

def _noise_vector(st: dict) -> np.ndarray:
    """Comparable noise statistics: log water sigma, lag ratio, log fixed-pattern ratios, log object sigma."""
    so = st["sigma_object"]
    return np.array([math.log(max(st["sigma_water"], 1e-3)), 5.0 * st["lag_ratio"],
                     0.5 * math.log(max(st["col_ratio"], 1e-3)), 0.5 * math.log(max(st["row_ratio"], 1e-3)),
                     math.log(max(so, 1e-3)) if so is not None else np.nan])


def noise_refit(fit_f, held_f, base_x, sig, fog, seed, ref_held_pf, base_theta_train,
                exclude: Optional[dict] = None, effects: tuple = (), values: Optional[dict] = None) -> dict:
    """Sensor noise, fitted and judged at full resolution by noise statistics (it is new in every frame).

    The effect's parameters (shot gain, read noise, correlation, fixed patterns) are chosen by CMA-ES on the
    fit frames so that simulated frames reproduce the recording's noise statistics
    (:func:`uw_sil.fit.signatures.noise_statistics`: water sigma, lag-1/lag-3 ratio, column and row
    patterns, sigma on flat object parts; the recording's particles and, with ``exclude`` ({id(frame): mask}),
    surfaces another effect adds are left out). On held-out frames the distance between the recording's
    statistics and the simulation's is compared for the base model (constant Gaussian noise estimated on
    the water, as the backward fit adds) and the candidate. θ is measured on the held-out frames at full
    resolution for both; the candidate's θ is reported as the base reference plus that difference."""
    from ...sim.effects.sensor_noise import remembered_white_noise
    from ...sim.noise import NoiseField, water_noise_sigma
    from ...sim.optics import degrade
    from ..optimize import optimize
    from ..signatures import NoisePixels, luminance, particle_exclusion

    fixed = {e: () for e in effects}

    def prep(frames):
        """per frame: noise-free simulation S (the current model: base and its deterministic effects), the
        recording's statistics, and the pixels every statistic of that frame uses (NoisePixels of the model's
        pixels, leaving out the recording's particles in real and simulated)."""
        rfs = [reduce_frame(f, 1) for f in frames]
        cur = EffectModel(rfs, effects, values=values, free=fixed, fog=fog, seed=seed) if effects else None
        S, real, hits = [], [], []
        for k, f in enumerate(frames):
            rr = f.render
            if cur is None:
                p = np.clip(base_x, 0, None)
                p[3:6] = np.clip(p[3:6], 0, 1)
                S.append(degrade(rr.rgb, rr.range, rr.depth, p, fog=fog) * 255.0)
            else:
                S.append(cur.simulate(k, cur.x0(base_x)[None])[0].astype(np.float64) * 255.0)
            hit = np.isfinite(rr.range)
            Y, Ys = luminance(f.image.astype(np.float32)), luminance(S[-1])
            excl = particle_exclusion(Y, Ys, hit)
            more = (exclude or {}).get(id(f))
            if more is not None:
                excl = more if excl is None else excl | more
            pix = NoisePixels(Ys, hit, excl)
            hits.append(pix)
            real.append(pix.statistics(Y))
        return rfs, S, real, hits

    def stats_of(img255, pix):
        np.clip(img255, 0, 255, out=img255)
        np.rint(img255, out=img255)
        return pix.statistics(luminance(img255), intensities=False)      # dist() uses no intensity

    def dist(a, b):
        if a is None or b is None:
            return np.nan
        va, vb = _noise_vector(a), _noise_vector(b)
        ok = np.isfinite(va) & np.isfinite(vb)
        return float(np.abs(va[ok] - vb[ok]).sum())

    rfit, Sfit, real_fit, hfit = prep(fit_f)
    rheld, Sheld, real_held, hheld = prep(held_f)
    names = tuple(effects) + ("sensor_noise",)
    model = EffectModel(rfit, names, values=values, free=fixed, fog=fog, seed=seed)
    lo, hi = model.bounds()
    h = (sig.hint if sig is not None else {}) or {}
    iw = np.nanmedian([r["i_water"] for r in real_fit if r]) if any(real_fit) else 60.0
    sw = np.nanmedian([r["sigma_water"] for r in real_fit if r]) if any(real_fit) else 1.5
    shot = float(np.clip(h.get("shot_gain_dn") or 0.02, 0.0, 1.0))
    start = {"shot": shot, "read": float(np.clip(math.sqrt(max(sw * sw - shot * iw, 0.04)), 0, 5)),
             "corr": float(np.clip((1 - (h.get("lag_ratio") or 1.0)) * 5.0, 0, 2)), "fpn": 0.002}
    for kind in ("col", "row"):          # a fixed readout pattern shows as excess variance of column (row) medians
        ratio = np.nanmedian([r[f"{kind}_ratio"] for r in real_fit if r]) if any(real_fit) else 1.0
        start[kind] = 0.3 * sw if ratio > 1.5 else 0.0
    x0 = model.x0(base_x, {"sensor_noise": start})
    free = np.arange(7, len(x0))

    def frame_dist(k, X):
        imgs = model.simulate(k, X) * 255.0
        d = np.array([dist(real_fit[k], stats_of(imgs[j], hfit[k])) for j in range(len(X))])
        return np.where(np.isnan(d), 0.0, d)

    def objective(U):
        X = np.repeat(x0[None], len(U), axis=0)
        X[:, free] = U
        # the frames in parallel (full-resolution simulations and statistics), summed in frame order:
        # the same value with any number of threads
        per_frame = list(pool.map(lambda k: frame_dist(k, X), range(len(rfit))))
        return -np.sum(per_frame, axis=0)

    with ThreadPoolExecutor(default_threads(), thread_name_prefix="uw_sil-noise") as pool, remembered_white_noise():
        res = optimize(objective, lo[free], hi[free], method="cmaes", seed=seed, max_iter=8, swarm_size=6,
                       x0=x0[free], sigma0=0.15)
    x = x0.copy()
    x[free] = res.x_best
    # held-out: statistics distance, base (estimated constant Gaussian noise) vs candidate; θ at full resolution
    from ...metrics.theta import ThetaReference

    def compare(frames, S_list, real, hits, mdl):
        eb, ec, tb, tc = [], [], [], []
        for k, f in enumerate(frames):
            sg = water_noise_sigma(f.image, ~np.isfinite(f.render.range))
            base_img = S_list[k].astype(np.float32).copy()
            NoiseField(base_img.shape, sg, seed=seed + 17 * k).apply(base_img)
            cand = mdl.simulate(k, x[None])[0] * 255.0
            np.clip(cand, 0, 255, out=cand)
            np.rint(cand, out=cand)
            eb.append(dist(real[k], hits[k].statistics(luminance(base_img), intensities=False)))
            ec.append(dist(real[k], hits[k].statistics(luminance(cand), intensities=False)))
            hit = hits[k].hit
            hm = [hit, ~hit] if hit.any() and not hit.all() else None
            ref = ThetaReference(f.image, hist_mask=hm)
            tb.append(float(ref.score(base_img)[0]))
            tc.append(float(ref.score(cand)[0]))
        return eb, ec, np.array(tb), np.array(tc)

    hmodel = model.like(rheld, seed=seed + 50)
    e_base, e_cand, tb, tc = compare(held_f, Sheld, real_held, hheld, hmodel)
    _, _, tbf, tcf = compare(fit_f, Sfit, real_fit, hfit, model)
    e_base, e_cand = np.array(e_base), np.array(e_cand)
    ok = np.isfinite(e_base) & np.isfinite(e_cand)
    imp = (e_base - e_cand)[ok]
    held_pf = np.asarray(ref_held_pf, float) + (np.array(tc) - np.array(tb))
    stat = {"name": "distance of noise statistics (log sigma, lag ratio, patterns) to the recording",
            "real": 0.0, "base_sim": float(np.mean(e_base[ok])) if ok.any() else float("nan"),
            "candidate_sim": float(np.mean(e_cand[ok])) if ok.any() else float("nan"),
            "improvement": float(imp.mean()) if imp.size else 0.0,
            "margin": max(0.05, 2.0 * bootstrap_se(imp, seed=seed)) if imp.size else float("inf"),
            "per_frame_improvement": imp.tolist(), "theta_full_res_base": tb.tolist(),
            "theta_full_res_candidate": tc.tolist()}
    return {"x": x, "theta_train": float(base_theta_train + np.mean(tcf - tbf)), "held_pf": held_pf,
            "params": model.params_of(x), "model_effects": ["sensor_noise"], "fit": None, "res": "full",
            "statistic": stat}


class SensorNoiseJudge(Judge):
    effect = "sensor_noise"
    free = ("shot", "read", "corr", "fpn", "col", "row")
    res = "high"
    kind = "statistic"
    least_squares = False

    def refit(self, job, current, x_starts=None, parent=None):
        r = noise_refit(job.fit_f, job.sel_f, current.base, self.signature(job), job.fog, job.seed, current.sel_pf,
                        current.theta_fit, exclude=job.exclude or None, effects=current.effects,
                        values=current.values)
        return Refit(effect=self.effect, effects=(self.effect,), x=r["x"], params=r["params"],
                     theta_fit=r["theta_train"], sel_pf=r["held_pf"], statistic=r["statistic"])

    def accept(self, r, current, margin, residual=None):
        st = r.statistic
        gain = float(np.mean(r.sel_pf - current.sel_pf))
        # next to another effect (which changes the signal and with it the intensity dependence of the
        # noise) a noise model must not lower held-out θ beyond the margin
        ok = st["improvement"] > st["margin"] and (not current.effects or gain > -margin)
        return ok, st["improvement"] / (3 * st["margin"]) if ok else 0.0, "statistic"

    #: Largest photo-response non-uniformity (pixel gain pattern, std) camera data sheets give (EMVA 1288
    #: measurements of CMOS and CCD sensors: 0.3-2 %), with room for the fit's scatter (the strong preset is 2 %).
    MAX_PIXEL_PATTERN = 0.03

    def ranges(self, e):
        """A pixel gain pattern beyond any camera's. Shot noise and that pattern both grow with brightness, and
        the statistics separate them poorly: on the foreign multi-effect dive (camera response, seafloor, pose,
        noise without any pixel pattern) one run of the diagnosis fitted 3.5 % where the next fitted 0.3 %, and
        drawn, the 3.5 % cost 0.03 of held-out θ as simulated."""
        fpn = float(e.get("fpn", 0.0))
        if fpn > self.MAX_PIXEL_PATTERN:
            return [f"a pixel gain pattern of {100 * fpn:.1f} % is beyond any camera's (data sheets, EMVA 1288: "
                    f"at most ~2 %): the fit may have taken what the model lacks on bright surfaces for noise"]
        return []

    def explain(self, e, gain, sig):
        return (f"the camera noise has structure the simulation's constant noise lacks: variance rising with "
                f"brightness (shot gain {e.get('shot', 0):.2f} DN/DN, read noise {e.get('read', 0):.1f} DN), "
                f"correlation over {e.get('corr', 0):.1f} px, fixed pattern {100 * e.get('fpn', 0):.1f} % gain, "
                f"{e.get('col', 0):.1f} DN per column, {e.get('row', 0):.1f} DN per row; {gain}")
