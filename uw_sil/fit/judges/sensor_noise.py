"""Diagnosis plug-in of structured sensor noise (:mod:`uw_sil.sim.effects.sensor_noise`).

New in every frame, so judged by statistics, not by θ: the effect's parameters (shot gain, read noise,
correlation, fixed patterns) are chosen so that simulated frames reproduce the recording's noise
statistics. Every camera's noise has photon shot noise and read noise (EMVA 1288's photon transfer), white
where nothing mixes neighbouring pixels; what a camera adds to that (demosaicing's correlation, fixed
patterns) is the effect. So the structured model is compared with its own shot and read noise without the
structure (its white twin), and accepted when it brings the held-out frames' statistics closer to the
recording's beyond their bootstrap margin. Next to another accepted effect the noise model is kept only if it
does not lower held-out θ beyond the margin (the other effect changes the signal, hence the intensity
dependence of the noise).
"""
from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from typing import Optional

import numpy as np

from ..._shared.process import default_threads
from ..diagfit import EffectModel
from ..residuals import reduce_frame
from .base import Judge, Refit, bootstrap_se, margin_for

#: The parameters of the noise model beyond photon transfer (shot and read noise): its structure, zero in the
#: white model.
STRUCTURE = ("corr", "fpn", "col", "row")


def _noise_vector(st: dict) -> np.ndarray:
    """Comparable noise statistics: log water sigma, lag ratio, log fixed-pattern ratios, log object sigma."""
    so = st["sigma_object"]
    return np.array([math.log(max(st["sigma_water"], 1e-3)), 5.0 * st["lag_ratio"],
                     0.5 * math.log(max(st["col_ratio"], 1e-3)), 0.5 * math.log(max(st["row_ratio"], 1e-3)),
                     math.log(max(so, 1e-3)) if so is not None else np.nan])


def corr_for_lag_ratio(ratio: float) -> float:
    """The correlation width (Gaussian sigma, px) of :mod:`uw_sil.sim.effects.sensor_noise` whose noise has
    ``ratio`` = sigma of lag-1 over sigma of lag-3 pixel differences (1 for white noise): a field blurred by
    a kernel ``k`` has autocorrelation ``rho(d) = sum k_i k_(i+d) / sum k_i^2`` at lag ``d``, and the ratio is
    ``sqrt((1 - rho(1)) / (1 - rho(3)))``; 0 for a ratio of 0.98 or more, at most 2 px."""
    def lag_ratio(sigma):
        x = np.arange(-math.ceil(4 * sigma), math.ceil(4 * sigma) + 1)
        k = np.exp(-x * x / (2 * sigma * sigma))
        rho = [float(np.dot(k[:-d], k[d:]) / np.dot(k, k)) for d in (1, 3)]
        return math.sqrt((1 - rho[0]) / max(1 - rho[1], 1e-12))

    if not np.isfinite(ratio) or ratio >= 0.98:
        return 0.0
    lo, hi = 0.05, 2.0
    if lag_ratio(hi) >= ratio:
        return hi
    for _ in range(40):                     # the ratio falls as the width grows
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if lag_ratio(mid) > ratio else (lo, mid)
    return 0.5 * (lo + hi)


def noise_refit(fit_f, held_f, base_x, sig, fog, seed, ref_held_pf, base_theta_train,
                exclude: Optional[dict] = None, effects: tuple = (), values: Optional[dict] = None) -> dict:
    """Sensor noise, fitted and judged at full resolution by noise statistics (it is new in every frame).

    The effect's parameters are chosen by CMA-ES on the fit frames so that simulated frames reproduce the
    recording's noise statistics (:func:`uw_sil.fit.signatures.noise_statistics`: water sigma, lag-1/lag-3
    ratio, column and row patterns, sigma on flat object parts; the recording's particles and, with
    ``exclude`` ({id(frame): mask}), surfaces another effect adds are left out): first shot and read noise
    alone (photon transfer, white), then every parameter from there (correlation started at the width the
    recording's lag ratio gives, :func:`corr_for_lag_ratio`). The candidate's white twin is its shot and read
    noise without the structure; where the twin or the first fit is as good on the fit frames, the candidate
    is that white model (and it is not named). On held-out frames the distance between the recording's
    statistics and the simulation's is compared for the twin and the candidate. θ is
    measured on the held-out frames at full resolution for the base model (constant Gaussian noise estimated
    on the water, as the backward fit adds) and the candidate; the candidate's θ is reported as the base
    reference plus that difference."""
    from ...sim.effects.base import remembered_draws
    from ...sim.noise import NoiseField, water_noise_sigma
    from ...sim.optics import degrade
    from ..optimize import optimize
    from ..signatures import NoisePixels, luminance, particle_exclusion

    fixed = {e: () for e in effects}

    def prep(frames, mdl):
        """per frame: noise-free simulation S (the current model: base and its deterministic effects), the
        recording's statistics, and the pixels every statistic of that frame uses (NoisePixels of the model's
        pixels, leaving out the recording's particles in real and simulated). With effects, S is ``mdl`` (the
        candidate model of these frames) without noise: its simulations of the frame keep that part and add
        only their noise to it (:class:`uw_sil.sim.model.PreparedModel`)."""
        S, real, hits = [], [], []
        for k, f in enumerate(frames):
            rr = f.render
            if not effects:
                p = np.clip(base_x, 0, None)
                p[3:6] = np.clip(p[3:6], 0, 1)
                S.append(degrade(rr.rgb, rr.range, rr.depth, p, fog=fog) * 255.0)
            else:
                S.append(mdl.simulate(k, mdl.x0(base_x)[None])[0].astype(np.float64) * 255.0)
            hit = np.isfinite(rr.range)
            Y, Ys = luminance(f.image.astype(np.float32)), luminance(S[-1])
            excl = particle_exclusion(Y, Ys, hit)
            more = (exclude or {}).get(id(f))
            if more is not None:
                excl = more if excl is None else excl | more
            pix = NoisePixels(Ys, hit, excl)
            hits.append(pix)
            real.append(pix.statistics(Y))
        return S, real, hits

    def recorded(img255):
        """a simulation (grey levels) as the camera records it: clipped to 0-255 and rounded, in place"""
        np.clip(img255, 0, 255, out=img255)
        return np.rint(img255, out=img255)

    def stats_of(img255, pix):
        return pix.statistics(luminance(img255), intensities=False)      # dist() uses no intensity

    def dist(a, b):
        if a is None or b is None:
            return np.nan
        va, vb = _noise_vector(a), _noise_vector(b)
        ok = np.isfinite(va) & np.isfinite(vb)
        return float(np.abs(va[ok] - vb[ok]).sum())

    names = tuple(effects) + ("sensor_noise",)
    model = EffectModel([reduce_frame(f, 1) for f in fit_f], names, values=values, free=fixed, fog=fog, seed=seed)
    hmodel = model.like([reduce_frame(f, 1) for f in held_f], seed=seed + 50)
    Sfit, real_fit, hfit = prep(fit_f, model)
    Sheld, real_held, hheld = prep(held_f, hmodel)
    lo, hi = model.bounds()
    h = (sig.hint if sig is not None else {}) or {}
    iw = np.nanmedian([r["i_water"] for r in real_fit if r]) if any(real_fit) else 60.0
    sw = np.nanmedian([r["sigma_water"] for r in real_fit if r]) if any(real_fit) else 1.5
    shot = float(np.clip(h.get("shot_gain_dn") or 0.02, 0.0, 1.0))
    # photon transfer alone first: shot and read noise, white, no pattern (what every camera's noise has)
    pt_names = ("sensor_noise.shot", "sensor_noise.read")
    x0_pt = model.x0(base_x, {"sensor_noise": {
        "shot": shot, "read": float(np.clip(math.sqrt(max(sw * sw - shot * iw, 0.04)), 0, 5)),
        "corr": 0.0, "fpn": 0.0, "col": 0.0, "row": 0.0}})
    free = np.arange(7, len(x0_pt))
    free_pt = np.array([model.names.index(n) for n in pt_names])

    def total(X):
        """minus the distance summed over the fit frames, per candidate vector (rows of X). The frames in
        parallel (full-resolution simulations and statistics), summed in frame order: the same value with any
        number of threads (with one, in this thread: its simulations then keep the noise-free part ``prep`` made,
        as each thread has its own prepared models)"""
        frames = range(len(model.rframes))
        per_frame = [frame_dist(k, X) for k in frames] if pool is None else list(pool.map(lambda k: frame_dist(k, X),
                                                                                          frames))
        return -np.sum(per_frame, axis=0)

    def fit(free_idx, x_start, sigma0):
        def objective(U):
            X = np.repeat(x_start[None], len(U), axis=0)
            X[:, free_idx] = U
            return total(X)

        res = optimize(objective, lo[free_idx], hi[free_idx], method="cmaes", seed=seed, max_iter=8, swarm_size=6,
                       x0=x_start[free_idx], sigma0=sigma0)
        f_start = float(objective(x_start[free_idx][None])[0])
        if f_start >= res.f_best:   # CMA-ES samples around its start: none of its points may be as good as it
            return x_start.copy(), f_start
        x = x_start.copy()
        x[free_idx] = res.x_best
        return x, float(res.f_best)

    def frame_dist(k, X):
        imgs = model.simulate(k, X) * 255.0
        d = np.array([dist(real_fit[k], stats_of(recorded(imgs[j]), hfit[k])) for j in range(len(X))])
        return np.where(np.isnan(d), 0.0, d)

    threads = default_threads()
    with (ThreadPoolExecutor(threads, thread_name_prefix="uw_sil-noise") if threads > 1 else nullcontext()) as pool, \
            remembered_draws():
        # photon transfer from a two-point estimate, steps of 15 % of the box (the structured fit below refines
        # shot and read noise with every other parameter, steps of 5 %; a refinement of these two alone first
        # changed no verdict on six physical dives and cost a third of the refit)
        x_pt, f_pt = fit(free_pt, x0_pt, 0.15)
        # the structure from there: correlation at the width the recording's lag ratio gives, no pattern.
        # Correlated noise alone raises the column and row ratios (they assume white noise): on a physical dive
        # with demosaiced noise, patterns started from those ratios (0.3 of the water sigma) put the start at
        # a distance of 11.7 (photon transfer's fit 6.1; with the correlation alone 1.8) and the fit ended at
        # 5.3 with a third of that correlation. From here, steps of 15 % of the box found nothing better than
        # the start (1.73) and steps of 5 % ended at 0.86
        x0 = x_pt.copy()
        x0[model.names.index("sensor_noise.corr")] = corr_for_lag_ratio(
            np.nanmedian([r["lag_ratio"] for r in real_fit if r]) if any(real_fit) else 1.0)
        x, f_full = fit(free, x0, 0.05)
        # what the structure adds is judged against the candidate's own shot and read noise without it (its
        # white twin): shot and read noise found by the larger search then cannot count as structure, and a
        # structure that does not help on the fit frames is dropped (the candidate contains its twin). Judged
        # against the better of the two white fits instead, a dive whose camera noise is white (seed 403 of the
        # physical dives, black water at 0.5 DN) was named: the candidate (read noise 0.59 DN, with 0.03 px of
        # correlation and a row pattern of 0.03 DN, white for any purpose) fitted the held-out statistics better
        # than the white fit chosen on the fit frames (0.44 DN) by 0.078 against a margin of 0.05: its read
        # noise made the difference, not its structure
        twin = x.copy()
        twin[[model.names.index(f"sensor_noise.{p}") for p in STRUCTURE]] = 0.0
        f_twin = float(total(twin[None])[0])
        if f_twin >= f_full:
            x, f_full = twin, f_twin
    if f_pt >= f_full:              # the full model holds photon transfer: it fits at least as well as it
        x = twin = x_pt
    # held-out: statistics distance, the white twin vs the candidate; θ at full resolution
    from ...metrics.theta import ThetaReference

    def compare(frames, S_list, real, hits, mdl, statistics=True):
        """per frame: statistics distance of the white twin and of the candidate (``statistics``; else empty
        lists); θ of the base model (the camera's constant noise), of the candidate and (``statistics``) of the
        white twin"""
        ew, ec, tb, tc, tw = [], [], [], [], []
        for k, f in enumerate(frames):
            sg = water_noise_sigma(f.image, ~np.isfinite(f.render.range))
            base_img = S_list[k].astype(np.float32).copy()
            NoiseField(base_img.shape, sg, seed=seed + 17 * k).apply(base_img)
            # (each simulation draws its noise from the frame's own seed: skipping one changes no other)
            cand = recorded(mdl.simulate(k, x[None])[0] * 255.0)
            if statistics:
                # (the candidate is its white twin where the structure did not help: then the same image)
                white = cand if twin is x else recorded(mdl.simulate(k, twin[None])[0] * 255.0)
                ec.append(dist(real[k], stats_of(cand, hits[k])))
                ew.append(ec[-1] if twin is x else dist(real[k], stats_of(white, hits[k])))
            hit = hits[k].hit
            hm = [hit, ~hit] if hit.any() and not hit.all() else None
            ref = ThetaReference(f.image, hist_mask=hm)
            tb.append(float(ref.score(base_img)[0]))
            tc.append(float(ref.score(cand)[0]))
            if statistics:
                tw.append(tc[-1] if twin is x else float(ref.score(white)[0]))
        return ew, ec, np.array(tb), np.array(tc), np.array(tw)

    e_white, e_cand, tb, tc, tw = compare(held_f, Sheld, real_held, hheld, hmodel)
    _, _, tbf, tcf, _ = compare(fit_f, Sfit, real_fit, hfit, model, statistics=False)   # θ only: theta_train
    e_white, e_cand = np.array(e_white), np.array(e_cand)
    ok = np.isfinite(e_white) & np.isfinite(e_cand)
    imp = (e_white - e_cand)[ok]
    held_pf = np.asarray(ref_held_pf, float) + (np.array(tc) - np.array(tb))
    white_values = model.params_of(twin)["effects"]["sensor_noise"]
    stat = {"name": "distance of noise statistics (log sigma, lag ratio, patterns) to the recording",
            "real": 0.0, "base_sim": float(np.mean(e_white[ok])) if ok.any() else float("nan"),
            "base_label": (f"its shot and read noise alone, white: {white_values['shot']:.2f} DN/DN, "
                           f"{white_values['read']:.2f} DN"),
            "candidate_sim": float(np.mean(e_cand[ok])) if ok.any() else float("nan"),
            "improvement": float(imp.mean()) if imp.size else 0.0,
            "margin": max(0.05, 2.0 * bootstrap_se(imp, seed=seed)) if imp.size else float("inf"),
            "per_frame_improvement": imp.tolist(), "theta_full_res_base": tb.tolist(),
            "theta_full_res_candidate": tc.tolist(), "theta_full_res_white": tw.tolist(),
            "photon_transfer": {"shot": float(white_values["shot"]), "read": float(white_values["read"])}}
    return {"x": x, "theta_train": float(base_theta_train + np.mean(tcf - tbf)), "held_pf": held_pf,
            "params": model.params_of(x), "model_effects": ["sensor_noise"], "fit": None, "res": "full",
            "statistic": stat}


def camera_noise_choice(statistic: Optional[dict], seed: int = 0) -> dict:
    """The camera noise ``sim_camera`` gets where the structured noise model is not named: the white shot and
    read noise the refit found (photon transfer, EMVA 1288: variance ``read² + shot * signal``) where, drawn at
    the recording's resolution, it raises held-out θ beyond the margin over one constant sigma measured on the
    open water (the default), else that constant.

    Why: a camera's noise grows with the signal, and the open water of a lamp-lit deep-sea frame is the darkest
    part of it, so its sigma is the read noise alone and too little for the lit panel. On the seven of the nine
    physical dives where the structured model was not named, the white fit (0.06 DN/DN and 0.7 DN on four; the
    generator's camera has 0.05 and 0.75) scored +0.004 to +0.012 held-out θ at full resolution over the
    constant on five; behind a strong tone curve (sRGB) and next to a seafloor it scored 0.005 less.

    ``statistic``: the noise refit's held-out statistic (:func:`noise_refit`) or None (noise not judged).
    Returns ``{"model": "photon_transfer"|"constant", "values"}`` (``values``: the effect's parameters, white)
    with the evidence: ``delta_heldout_simulated`` (mean), ``per_frame``, ``margin``."""
    if not statistic or "theta_full_res_white" not in statistic:
        return {"model": "constant", "values": None, "reason": "the sensor noise was not refitted"}
    from ...sim.effects import get_effect

    gain = (np.asarray(statistic["theta_full_res_white"], float)
            - np.asarray(statistic["theta_full_res_base"], float))
    margin = margin_for(gain, 1, seed=seed)
    values = {**get_effect("sensor_noise").defaults(), **statistic["photon_transfer"], **dict.fromkeys(STRUCTURE, 0.0)}
    return {"model": "photon_transfer" if float(gain.mean()) > margin else "constant", "values": values,
            "delta_heldout_simulated": float(gain.mean()), "per_frame": gain.tolist(), "margin": float(margin)}


def camera_noise_words(choice: dict) -> Optional[str]:
    """The camera noise ``sim_camera`` draws, in words with its evidence (:func:`camera_noise_choice`; None
    where there was no choice to make: a named noise model, or none refitted)."""
    if not choice or choice.get("delta_heldout_simulated") is None:
        return None
    v = choice["values"]
    return (("photon transfer" if choice["model"] == "photon_transfer" else "one sigma from the open water")
            + f" (white shot {v['shot']:.3f} DN/DN and read {v['read']:.2f} DN against one sigma: held-out θ at "
            f"full resolution {choice['delta_heldout_simulated']:+.4f}, margin {choice['margin']:.4f})")


class SensorNoiseJudge(Judge):
    effect = "sensor_noise"
    free = ("shot", "read", "corr", "fpn", "col", "row")
    res = "high"
    kind = "statistic"
    least_squares = False

    def refit(self, job, current, x_starts=None, parent=None):
        # the effects the recording passed after its noise (an accepted compression) act on the candidates too
        r = noise_refit(job.fit_f, job.sel_f, current.base, self.signature(job), job.fog, job.seed, current.sel_pf,
                        current.theta_fit, exclude=job.exclude or None,
                        effects=current.effects + tuple(job.after_noise), values={**current.values, **job.after_noise})
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

    def explain(self, e, gain, sig, camera=None):
        return (f"the camera noise has structure beyond white shot and read noise (which every camera has): "
                f"shot gain {e.get('shot', 0):.2f} DN/DN and read noise {e.get('read', 0):.1f} DN, "
                f"correlated over {e.get('corr', 0):.1f} px, fixed pattern {100 * e.get('fpn', 0):.1f} % gain, "
                f"{e.get('col', 0):.1f} DN per column, {e.get('row', 0):.1f} DN per row; {gain}")
