"""Diagnosis plug-in of a recorded pose that is off (:mod:`uw_sil.sim.effects.pose_error`).

Fitted by least squares on the fit frames from the edge shifts of the signature test (both directions
tried), judged on the held-out frames by θ with the frames rendered at the corrected pose, or by the
held-out residual (mean squared real - sim, relative improvement per frame, bootstrapped) when θ on reduced
frames cannot see a sub-pixel shift (θ must then not fall beyond the margin). A correction that moves the
panel's image by less than :data:`MIN_SHIFT_PX` is not named: warping the geometry by a fraction ``d`` of a
pixel interpolates its colours bilinearly, which blurs them by ``d (1 - d)`` px², and that blur alone lowers the
residual of a blurred recording (a 0.1 px "correction" took 8 % of the held-out residual of a trial with
mild forward scatter and no pose error). An accepted correction is applied to the frames themselves (rendered
at the corrected pose, :func:`~uw_sil.fit.residuals.corrected_frame`) for the rest of the selection.

A navigation pose is off by a new error in every frame as well (USBL/DVL noise): the jitter. A bias fitted on the fit
frames cannot predict it on the held-out ones, and where it is large the bias alone is not accepted (a literature
trial of 6 cm / 0.6 deg bias with 8 mm / 0.15 deg jitter per frame: the bias lowered the held-out residual of its
nearest frame from 1334 to 791 grey levels², registering that frame alone to 35). So every frame is also registered
on its own (:func:`~uw_sil.fit.residuals.registered_pose`: the panel face aligned by ECC, which the water's gain and
offset do not move), and where the frames rendered at their own poses score a held-out θ above the bias's by a
margin, the correction is per frame: the bias is the one correction nearest to all of theirs in the image, the
jitter the rest, and the frames keep their own poses for the rest of the selection (the report frames too). A
registration reads the geometry of a frame, not its photometry; what a held-out frame then shows of the water and the
other effects is still predicted by parameters fitted on the fit frames.

With the lamps in the model, the least-squares fit and the held-out residual take the lamps' cast shadows of the
recorded view through the warps (:func:`uw_sil.sim.effects.pose_error.carrying_shadows`) instead of testing
every warped view again (such a refit took 12-18 s, now 5-7 s); held-out θ is scored on frames rendered
at the corrected pose, with shadows of their own.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import replace

import numpy as np

from ...sim.effects.pose_error import PoseError, carrying_shadows
from ..diagfit import EffectModel, ls_fit, residual_energy
from ..residuals import corrected_frame, reduce_frame, registered_pose
from .base import Judge, Refit, bootstrap_se, margin_for

#: Smallest image displacement (full-resolution pixels, the largest over the panel's pixels in the fit frames)
#: of a correction that is named: a quarter of a pixel. Below it a registration cannot be told from the
#: resampling's own blur (``d (1 - d)`` px² at a shift ``d``); the spurious correction above moved the image by
#: 0.10 px at most, our mild pose error preset moves it by 1.4 px.
MIN_SHIFT_PX = 0.25


def image_shift(frames, values: dict, rms: bool = False) -> float:
    """Largest displacement (pixels) of the model's surface points in the frames' images under the correction
    ``values`` (bias only); ``rms``: their root mean square over the points instead (of the last frame)."""
    from ...sim.effects import get_effect

    eff = get_effect("pose_error")
    D = eff.correction(eff.values({**values, "jitter_t": 0.0, "jitter_r": 0.0}))
    out = 0.0
    for f in frames:
        X = _surface_points(f, 4000)
        Y = _moved(D, X)
        ok = Y[:, 2] > 1e-6
        if ok.any():
            d = f.camera.project(Y[ok]) - f.camera.project(X[ok])
            d2 = (d * d).sum(axis=1)
            out = float(np.sqrt(d2.mean())) if rms else max(out, float(np.sqrt(d2.max())))
    return out


_REGISTERED = {}
_REGISTERED_MAX = 256
#: The effect's box, ``name -> (lo, hi)``.
_BOX = {p.name: (p.lo, p.hi) for p in PoseError.params}


def registration(frame):
    """:func:`~uw_sil.fit.residuals.registered_pose` of a frame as the effect's bias values, None where refused or
    outside the effect's box (the homography of a far panel splits a sideways shift from a turn at random: a
    physical dive's frame at 4 m came out 16 cm off, beyond the box's 15 cm); kept per process: it depends on the
    frame's image and recorded pose alone, not on the model being fitted."""
    key = (frame.index, np.asarray(frame.pose, float).tobytes(),
           hashlib.blake2b(np.ascontiguousarray(frame.image).tobytes(), digest_size=16).digest())
    if key not in _REGISTERED:
        if len(_REGISTERED) >= _REGISTERED_MAX:     # a live node diagnoses again and again: keep the latest frames'
            _REGISTERED.clear()
        D, _ = registered_pose(frame)
        v = None if D is None else PoseError.bias_of(D)
        _REGISTERED[key] = v if v is not None and all(_BOX[k][0] <= x <= _BOX[k][1] for k, x in v.items()) else None
    return _REGISTERED[key]


def shift_between(frame, a: dict, b: dict, rms: bool = False) -> float:
    """Largest image displacement (pixels; ``rms``: root mean square) of ``frame``'s surface points between the
    corrections ``a`` and ``b`` (bias values)."""
    from ...sim.effects import get_effect

    eff = get_effect("pose_error")
    D = eff.correction(eff.values({**a, "jitter_t": 0.0, "jitter_r": 0.0})) @ \
        np.linalg.inv(eff.correction(eff.values({**b, "jitter_t": 0.0, "jitter_r": 0.0})))
    return image_shift([frame], PoseError.bias_of(D), rms=rms)


def per_frame(job, current, bias: dict, sel_bias: np.ndarray) -> dict:
    """Every frame at its own registered pose (:func:`registration`; the bias where refused): the per-frame values
    (``values``) and the held-out frames' displacement from the bias (``shift_px``, px); where that is
    :data:`MIN_SHIFT_PX` or more (median), the held-out frames scored with the current model: ``sel_pf`` (θ per
    frame), the frames (``sel``), the gain over the bias and its margin (``gain``, ``margin``); where the gain beats
    the margin, the fit frames (``fit``, their θ ``theta_fit``), the bias (``bias``, the one correction nearest to
    the frames' own) and the rest as ``jitter_r`` (rad per axis: the turn that displaces the images alike;
    ``jitter_t`` 0)."""
    frames = list(job.fit_f) + list(job.sel_f)
    vals = [registration(f) for f in frames]
    corr = [v if v is not None else bias for v in vals]
    got = [v for v in vals if v is not None]
    out = {"values": vals, "refused": len(vals) - len(got),
           "shift_px": [shift_between(f, v, bias) for f, v in zip(job.sel_f, corr[len(job.fit_f):])]}
    if not got or float(np.median(out["shift_px"])) < MIN_SHIFT_PX:
        return out           # the frames' own poses are the bias's, within the resampling's blur: nothing to score
    sel_c = [corrected_frame(f, {"pose_error": v}) for f, v in zip(job.sel_f, corr[len(job.fit_f):])]
    sel_pf = _score_current(job, current, sel_c, 50)
    out.update(sel_pf=sel_pf, sel=sel_c, gain=float(np.mean(sel_pf - sel_bias)),
               margin=margin_for(sel_pf - sel_bias, 2, seed=job.seed))
    if out["gain"] > out["margin"]:
        # (the fit frames are rendered and scored only then: on the lamp-lit physical dives the frames' own poses
        # lie 0.3-1.8 px from the bias and lower held-out θ in every round)
        fit_c = [corrected_frame(f, {"pose_error": v}) for f, v in zip(job.fit_f, corr)]
        out.update(fit=fit_c, theta_fit=float(_score_current(job, current, fit_c, 0).mean()))
        # one frame cannot tell a sideways shift from a turn: its homography splits them at random (an effect-free
        # control's registrations spread by 10 mm and 0.13° per axis, which cancel to 0.14-0.33 px in the image).
        # So the bias is the one correction that moves every frame's points nearest to where its registration put
        # them, and the jitter the turn that displaces the images alike (a displacement of two Gaussian axes of
        # sigma fx * jitter_r has a mean square of 2 (fx jitter_r)²)
        bias, rms = bias_of_registrations([f for f, v in zip(frames, vals) if v is not None], got)
        out["bias"] = {k: float(np.clip(v, *_BOX[k])) for k, v in bias.items()}
        out["jitter_t"] = 0.0
        out["jitter_r"] = float(np.clip(np.sqrt(np.mean(np.square(rms)) / 2.0), *_BOX["jitter_r"]))
    return out


def _surface_points(frame, n: int = 600) -> np.ndarray:
    """About ``n`` of the frame's surface points (recorded camera frame, metres)."""
    from ...sim.model import Geometry

    g = Geometry.from_render(frame.render, frame.camera, frame.pose)      # cached per render (reduce_frame's too)
    X = g.X[g.hit].astype(float)
    return X[::max(1, len(X) // n)]


def _moved(D, X) -> np.ndarray:
    return X @ D[:3, :3].T + D[:3, 3]


def bias_of_registrations(frames, values) -> tuple:
    """The one correction (bias values) that moves the frames' surface points in their images nearest, in the least
    squares sense, to where each frame's own correction (``values``) moves them, and the remaining displacement per
    frame (rms over its points, in units of the focal length: radians)."""
    from scipy.optimize import least_squares

    eff = PoseError()
    pts, goal = [], []
    for f, v in zip(frames, values):
        X = _surface_points(f)
        Y = _moved(eff.correction(eff.values(v)), X)
        ok = (X[:, 2] > 1e-6) & (Y[:, 2] > 1e-6)
        pts.append((f.camera, X[ok]))
        goal.append(f.camera.project(Y[ok]) / f.camera.fx)
    keys = ("tx", "ty", "tz", "rx", "ry", "rz")

    def resid(p):
        D = eff.correction(eff.values(dict(zip(keys, p))))
        return np.concatenate([(cam.project(_moved(D, X)) / cam.fx - g).ravel() for (cam, X), g in zip(pts, goal)])

    p0 = np.mean([[v[k] for k in keys] for v in values], axis=0)
    p = least_squares(resid, p0, x_scale=[0.01, 0.01, 0.01, 0.003, 0.003, 0.003]).x
    r = resid(p)
    rms, i = [], 0
    for (_, X) in pts:
        k = 2 * len(X)
        rms.append(float(np.sqrt(np.mean(r[i:i + k].reshape(-1, 2) ** 2) * 2.0)) if k else 0.0)
        i += k
    return dict(zip(keys, map(float, p))), rms


def pose_hint(motion, sign: float = 1.0) -> dict:
    """Pose correction from per-frame image motion of the object (ECC: shift dx, dy and rotation, pixels):
    for a bias ``X_true = R X_rec + t`` a point near the axis at range z moves by about
    ``du = fx (ry + tx / z)``, ``dv = fy (-rx + ty / z)``, and the image turns by ``rz``; least squares over
    the frames (ranges differ, which separates rotation from translation). ``sign`` flips the direction
    (the alignment's convention); both are tried."""
    if len(motion) < 2:
        return {}
    z = np.array([m[0] for m in motion])
    du = np.array([m[1] / m[4] for m in motion]) * sign
    dv = np.array([m[2] / m[5] for m in motion]) * sign
    ang = np.array([m[3] for m in motion]) * sign
    A = np.stack([np.ones_like(z), 1.0 / z], 1)
    (ry, tx), *_ = np.linalg.lstsq(A, du, rcond=None)
    (mrx, ty), *_ = np.linalg.lstsq(A, dv, rcond=None)

    def clip(v, b):
        return float(np.clip(v, -b, b))

    return {"tx": clip(tx, 0.15), "ty": clip(ty, 0.15), "rx": clip(-mrx, 0.06), "ry": clip(ry, 0.06),
            "rz": clip(float(np.median(ang)), 0.06)}


class PoseErrorJudge(Judge):
    effect = "pose_error"
    free = ("tx", "ty", "tz", "rx", "ry", "rz")
    fixed = {"jitter_t": 0.0, "jitter_r": 0.0}
    res = "high"
    cost = 11.0
    sigma = 0.03
    absorb = True

    def start(self, job):
        s = self.signature(job)
        return pose_hint((s.hint.get("motion") if s is not None else None) or [])

    def refit(self, job, current, x_starts=None, parent=None):
        from ...sim.effects import EFFECT_ORDER

        names = tuple(e for e in EFFECT_ORDER if e in current.effects or e == self.effect)
        values = {e: dict(current.values.get(e, {})) for e in current.effects}
        values[self.effect] = dict(self.fixed)
        free = {e: () for e in current.effects}
        free[self.effect] = self.free_params()
        rfit = job.reduced(job.fit_f)
        rsel = job.reduced(job.sel_f)
        model = EffectModel(rfit, names, values=values, free=free, fog=job.fog, seed=job.seed)
        fit_idx = {f.index for f in job.fit_f}
        s = self.signature(job)
        motion = [m for m in ((s.hint if s is not None else {}).get("motion") or []) if m[6] in fit_idx]

        xs = [model.x0(current.base)] + [model.x0(current.base, {self.effect: pose_hint(motion, sg)})
                                         for sg in (1.0, -1.0)]
        # only the pose moves: the rest stays at the current model's θ optimum, which is the reference of the
        # held-out residual below. (With everything free, the least-squares refit of the photometric
        # parameters alone lowered an effect-free control's held-out residual by 6 %, and a 0.3 mm "pose
        # error" was accepted on it.) The fit's warped views carry the lamps' shadows of the recorded pose
        # (carrying_shadows: an approximation for a correction of centimetres; a lamp-lit refit 12-18 -> 5-7 s);
        # held-out θ below is scored on frames rendered at the corrected pose, with shadows of their own
        with carrying_shadows():
            e = residual_energy(model, np.stack(xs)).mean(axis=1)
            x = ls_fit(model, xs[int(np.argmin(e))], stride=1, max_nfev=10, interrupt=job.interrupt,
                       free=model.free_index(self.effect))
            hmodel = model.like(rsel, seed=job.seed + 50)
            eh = residual_energy(hmodel, np.stack([hmodel.x0(current.base), x]))
        imp = (eh[0] - eh[1]) / np.maximum(eh[0], 1e-9)
        pose = model.params_of(x)["effects"][self.effect]
        # held-out θ of the corrected pose: the frames rendered at it (full resolution), reduced as every frame
        # is, scored with the current model
        sel_c = [corrected_frame(f, {self.effect: pose}) for f in job.sel_f]
        fit_c = [corrected_frame(f, {self.effect: pose}) for f in job.fit_f]
        sel_pf = _score_current(job, current, sel_c, 50)
        theta_fit = float(_score_current(job, current, fit_c, 0).mean())
        stat = {"name": "mean squared residual (grey levels²)", "real": 0.0, "base_sim": float(eh[0].mean()),
                "candidate_sim": float(eh[1].mean()), "improvement": float(imp.mean()),
                "margin": max(0.02, 2.0 * bootstrap_se(imp, seed=job.seed)), "per_frame_improvement": imp.tolist(),
                "shift_px": image_shift(job.fit_f, pose)}
        params = model.params_of(x)
        extra = {"corrected": (fit_c, sel_c)}
        # every frame at its own pose: taken where it beats the bias on the held-out frames by a margin and moves
        # them by more than the resampling's blur from it
        pf = per_frame(job, current, pose, sel_pf)
        stat["per_frame"] = {"shift_px": pf["shift_px"], "refused": pf["refused"],
                             **{k: pf[k] for k in ("jitter_t", "jitter_r") if k in pf},
                             **({"theta_gain_over_bias": pf["gain"], "margin": pf["margin"]} if "gain" in pf else {})}
        if "bias" in pf:
            x = model.x0(current.base, {self.effect: pf["bias"]})
            params = model.params_of(x)
            params["effects"][self.effect].update(jitter_t=pf["jitter_t"], jitter_r=pf["jitter_r"])
            sel_pf, theta_fit = pf["sel_pf"], pf["theta_fit"]
            stat["shift_px"] = max(image_shift([f], v) for f, v in zip(job.fit_f + job.sel_f, pf["values"]) if v)
            extra = {"corrected": (pf["fit"], pf["sel"]), "per_frame": True}
        return Refit(effect=self.effect, effects=names, x=x, params=params, theta_fit=theta_fit, sel_pf=sel_pf,
                     model=model, statistic=stat, extra=extra)

    def accept(self, r, current, margin, residual=None):
        gain = float(np.mean(r.sel_pf - current.sel_pf))
        st = r.statistic
        if st.get("shift_px", np.inf) < MIN_SHIFT_PX:
            return False, 0.0, "residual"
        if gain > margin:
            return True, gain / margin, "theta"
        # by its residual only where θ does not fall: a correction aligns edges, which θ's phase congruency and
        # gradients see, so a "correction" that lowers held-out θ took something else (a 0.25 px shift taking part of
        # the glow of forward scatter written from Wells' MTF: residual -5.8 %, held-out θ -0.0019; physical dive 406,
        # no pose error: 0.28-0.35 px, held-out θ -0.0011 to -0.0023 in every round it was tried)
        # (the bias's residual: not a test of frames at their own poses)
        ok = st["improvement"] > st["margin"] and gain >= 0.0 and not r.extra.get("per_frame")
        return ok, st["improvement"] / st["margin"] if ok else 0.0, "residual"

    def absorb_into(self, job, current, r):
        """Job and current model with the correction applied to every frame's geometry."""
        fit_c, sel_c = r.extra["corrected"]
        R = {"R_hi": dict(job.R_hi), "R_lo": dict(job.R_lo), "R_ls": dict(job.R_ls)}
        for old, new in zip(job.fit_f + job.sel_f, fit_c + sel_c):
            for key, d in R.items():
                src = getattr(job, key).get(id(old))
                if src is not None:
                    d[id(new)] = reduce_frame(new, src.factor)
        job2 = replace(job, fit_f=list(fit_c), sel_f=list(sel_c), **R)
        absorbed = {**current.absorbed, self.effect: r.params["effects"][self.effect]}
        return job2, replace(current, theta_fit=r.theta_fit, sel_pf=np.asarray(r.sel_pf), absorbed=absorbed)

    def absorbed_frames(self, frames, values):
        """Frames no refit saw (the report frames) corrected as the selection's were: each at its own registered
        pose where the correction is per frame (jitter), else at the bias."""
        if PoseError().draws({"jitter_t": 0.0, "jitter_r": 0.0, **values}):
            return [corrected_frame(f, {self.effect: registration(f) or values}) for f in frames]
        return super().absorbed_frames(frames, values)

    def explain(self, e, gain, sig, camera=None):
        t = 100 * math.sqrt(sum(e.get(k, 0) ** 2 for k in ("tx", "ty", "tz")))
        rot = math.degrees(math.sqrt(sum(e.get(k, 0) ** 2 for k in ("rx", "ry", "rz"))))
        sh = sig.stats.get("shift_px_median") if sig is not None else None
        extra = f"; edges in the recording are shifted by ~{sh:.1f} px against the simulation" if sh else ""
        if e.get("jitter_r", 0) > 0:
            px = f"{math.sqrt(2.0) * camera.fx * e['jitter_r']:.1f} px rms, " if camera is not None else ""
            return (f"the recorded panel pose is off by a new error in every frame ({px}as a turn of "
                    f"{math.degrees(e['jitter_r']):.2f}° per axis) around {t:.1f} cm and {rot:.2f}°{extra}: a fit "
                    f"wants each frame's pose refined (--refine-pose ecc); {gain}")
        return f"the recorded panel pose is off by about {t:.1f} cm and {rot:.2f}°{extra}; {gain}"


def _score_current(job, current, frames, seed_offset) -> np.ndarray:
    """θ per frame of the current model on (corrected) frames at the high resolution."""
    from ..diagfit import FrameObjective, noise_sigmas

    factor = job.R_hi[id(job.fit_f[0])].factor
    rf = [reduce_frame(f, factor) for f in frames]
    m = EffectModel(rf, current.effects, values=current.values, free={e: () for e in current.effects}, fog=job.fog,
                    seed=job.seed + seed_offset)
    with FrameObjective(rf, m, noise_sigmas(rf), seed=job.seed) as ob:
        return ob.per_frame(m.x0(current.base)[None])[0]
