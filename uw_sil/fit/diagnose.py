"""Mismatch diagnosis: which physics does the recording hold that the simulation leaves out?

Pipeline (:func:`diagnose_bag`, ``uw-sil diagnose --bag``), from what a real user has (the bag's images,
camera info and panel poses, and the scene model; never a ground-truth sidecar):

1. **frames**: up to K frames spread over the recording, each rendered at its recorded pose; split into
   fit frames and *held-out* frames interleaved over range (:func:`uw_sil.fit.residuals.split_frames`).
   When the recording has more usable frames, up to :data:`REPORT_FRAMES` more are read and set aside as
   *report* frames (:func:`uw_sil.fit.residuals.set_aside`): no fit and no choice sees them; the base and
   the final model are scored on them at the end (held-out θ chose among the models, so it flatters the
   one chosen).
2. **base fit**: the 7 parameters of paper Eq. 1 with fog, by CMA-ES on θ over the fit frames (from the
   least-squares start of :func:`uw_sil.fit.backward.linear_start`, stopped on convergence), on frames
   box-downsampled to about 320 px wide (θ's FSIMc downsamples 640x480 by 2 anyway).
3. **evidence that orders the work**: residual signatures (:mod:`uw_sil.fit.signatures`) and screening
   proxies (:mod:`uw_sil.fit.screening`) on the *fit* frames only; they order the refits and give their
   starts, they decide nothing. Residual maps over every frame (:func:`uw_sil.fit.residuals.locate`) say
   where the mismatch is, for the reader.
4. **greedy forward selection on held-out frames**: in the first round *every* effect with a plug-in
   (:mod:`uw_sil.fit.judges`) is refitted jointly with the current model, cheaply (least squares at about 80 px
   from the plug-in's starts and the nested ones, the best of them by θ: :data:`ROUND_ITER`), and so is the
   current model itself with the same budget (:func:`uw_sil.fit.judges.base.reference_refit`: where that
   scores higher on the fit frames it is what the round's candidates are compared with, since their refits go on
   optimizing its parameters too; a fit holding its effect neutral is never accepted); the effect that raises
   held-out θ most beyond its noise margin joins the model (the margin:
   a bootstrap over held-out frames of the per-frame gains, with the normal quantile corrected for the
   number of candidates of the round, and at least :data:`uw_sil.fit.judges.base.MIN_MARGIN`); the model
   is refitted jointly with it, and the next round tries every remaining effect (:data:`LATER_CANDIDATES`),
   until none beats its margin or ``max_effects`` are in. A refit
   never ends below the model it contains on the fit frames (:func:`uw_sil.fit.judges.base.theta_refit`), and
   it starts from both models it contains: the current one with the effect neutral, and the effect's own refit
   of the previous round with the effect accepted since at its current values (two effects that explain much
   of the same residual, lamps aimed down and a lit seafloor, otherwise hide each other). A
   pose correction, once accepted, is applied to the frames' geometry. A round's refits run side by side in
   worker processes (:mod:`uw_sil._shared.workers`; the GIL kept threads to 1.15x), and so do the base fit's
   θ evaluations. Then **backward elimination**: every
   effect of the model must still beat its margin against the model without it, refitted
   (:func:`uw_sil.fit.judges.base.refit_without`); of those that do not, the one with the least evidence is
   dropped, and the smaller model is tested again (a lamp footprint first taken for vignetting, then
   explained by the lamps), provided the effects dropped so far and it, removed together, do not lose beyond
   the margin against the model the elimination started from (effects that only help together stay).
   The selected model is then polished one effect at a time (:func:`uw_sil.fit.judges.base.polish_blocks`).
5. **effects new in every frame** (particles, temporal noise) are judged last, on held-out *statistics*
   (speck density, noise level, correlation and fixed patterns): a pixel-wise θ cannot rise for them.
6. **say it**: a plain-language verdict with numbers and doubts (parameters on a bound or outside deep-sea
   ranges lower the confidence), every selection step, the JSON document (:data:`SCHEMA_VERSION`), a params
   YAML for ``sim_camera`` with the extended model, and an HTML/PNG report.

JSON schema (``schema_version`` 1)::

    {"schema_version": 1,
     "verdict":    [{"effect", "confidence", "explanation", "params", "doubts"}, ...],   # [] = none; best first
     "candidates": [{"effect", "theta_train", "theta_heldout", "delta_heldout", "params",
                     "round", "model", "margin", "accepted", "doubts", ...}, ...],        # every refit
                                                    # ("flat_bounds": parameters saturated on their bound)
     "selection":  [{"round", "model", "theta_heldout", "tried", "chosen", "time_s"}, ...],
     "base":       {"theta_train", "theta_heldout", "theta_heldout_simulated", "theta_report", "params", "doubts"},
     "final":      {"theta_heldout", "theta_heldout_simulated", "theta_report", "effects", "params", "statistics",
                    "camera_noise"},
                                                    # theta_report: θ on the report frames (null: none)
                                                    # theta_heldout_simulated: theta_as_simulated()
                                                    # camera_noise: what sim_camera draws, {"model": "constant" |
                                                    # "photon_transfer" | "sensor_noise", "values", ...}
                                                    # (judges.sensor_noise.camera_noise_choice)
     "mismatch":   {"regions": [{"kind", "name", "pixels", "rms", "mean", "rms_rgb", "share"}, ...]},
     "undecided":  [{"effect", "round", "model", "criterion", "strength", "delta_heldout", "margin", "last",
                     "explanation"}, ...],          # beat a margin, not in the final model: undecided_effects()
     ... extra keys: "noise", "signatures", "frames", "timing", "not_judged", "source"}

``effect`` names are those of :data:`uw_sil.sim.effects.EFFECTS`; ``params`` of a verdict or candidate are
``{"<effect>.<param>": value}`` for the effect and the refitted base parameters ``a_r ... rho_f``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from types import SimpleNamespace
from typing import Callable, Optional

import numpy as np

from ..sim.params import RGB_NAMES
from .diagfit import BASE_SIGMA0, FAINT_DN, BaseModel, EffectModel, FrameObjective, fit_model, noise_sigmas
from .residuals import (LABEL_PANEL, ReducedFrame, base_sim, locate, load_frames, reduce_frame,
                        reduction_factor, residual_maps, set_aside, split_frames)

__all__ = ["SCHEMA_VERSION", "Diagnosis", "diagnose_frames", "diagnose_bag", "write_diagnosis_yaml",
           "validate_diagnosis_json", "without_times", "DiagnosisError", "REPORT_FRAMES", "report_count"]

SCHEMA_VERSION = 1


class DiagnosisError(ValueError):
    """The recording could not be diagnosed (the message says why)."""


# ================================================================================== result


@dataclass
class Diagnosis:
    """Outcome of :func:`diagnose_frames` (``to_json()`` gives the documented schema)."""

    verdict: list
    candidates: list
    base: dict
    final: dict
    mismatch: dict
    signatures: dict
    noise: dict
    frames: list
    timing: dict
    final_params: dict                  # {"base": {...}, "effects": {...}} of the final model
    not_judged: list = field(default_factory=list)
    undecided: list = field(default_factory=list)  # :func:`undecided_effects`
    source: str = ""
    selection: list = field(default_factory=list)  # the greedy selection's rounds
    figures: dict = field(default_factory=dict)    # data for the report (not serialized)

    def to_json(self) -> dict:
        """The documented JSON document (numpy numbers converted; non-finite numbers become null)."""
        from .signatures import jsonable

        return jsonable({
            "schema_version": SCHEMA_VERSION,
            "verdict": self.verdict,
            "candidates": self.candidates,
            "selection": self.selection,
            "base": self.base,
            "final": self.final,
            "mismatch": self.mismatch,
            "noise": self.noise,
            "signatures": self.signatures,
            "not_judged": self.not_judged,
            "undecided": self.undecided,
            "frames": self.frames,
            "timing": self.timing,
            "source": self.source,
        })

    def summary_lines(self) -> list:
        lines = []
        if not self.verdict:
            lines.append(f"verdict: none — no effect raised held-out θ beyond the fit's noise "
                         f"(held-out θ {self.base['theta_heldout']:.4f}, noise margin {self.noise['margin']:.4f})")
        for v in self.verdict:
            lines.append(f"verdict: {v['effect']} (confidence {v['confidence']:.2f}): {v['explanation']}")
        for u in self.undecided:
            lines.append(f"undecided, not named (the final model's effects explain it as well): {u['explanation']}")
        from .judges.sensor_noise import camera_noise_words

        words = camera_noise_words(self.final.get("camera_noise"))
        if words:
            lines.append(f"camera noise for sim_camera: {words}")
        if self.final.get("theta_report") is not None:
            n = sum(f["role"] == "report" for f in self.frames)
            lines.append(f"on {n} report frame(s) that no fit or choice saw: θ {self.base['theta_report']:.4f} (base) "
                         f"-> {self.final['theta_report']:.4f} (final model)")
        for c in self.candidates:
            if c.get("elimination"):
                lines.append(f"  elimination: {c['model']} + {c['effect']:<13s} against the model without it: "
                             f"held-out θ {c['theta_heldout']:.4f} (Δ {c['delta_heldout']:+.4f}, margin "
                             f"{c.get('margin', 0):.4f}) "
                             + ("kept" if c.get("accepted") else "dropped" if c.get("dropped") else
                                f"kept: without {' and '.join(c['joint']['without'])} together it loses beyond the "
                                f"margin against {c['joint']['model']}" if c.get("joint", {}).get("kept") else
                                "not beyond its margin (another had less evidence)"))
                continue
            lines.append(f"  round {c.get('round', 1)}: {c.get('model', 'base')} + {c['effect']:<24s} held-out θ "
                         f"{c['theta_heldout']:.4f} (Δ {c['delta_heldout']:+.4f}, margin {c.get('margin', 0):.4f})"
                         + outcome_words(c, self.selection))
        return lines


def outcome_words(c: dict, selection: list) -> str:
    """What became of a round's candidate, for the summary: nothing where it did not beat its margin; else by which
    held-out evidence it did, and whether it was the round's choice (a row accepted by the held-out residual shows a
    θ change of 0 where its θ refit kept the effect neutral: the residual numbers say why it passed)."""
    if not c.get("accepted"):
        if c.get("declined"):
            return " declined (its least-squares fit lowers held-out θ)"
        if not c.get("delta_heldout", 0.0) > c.get("margin", np.inf):
            return ""
        # a θ gain beyond the margin that was not taken: say by which rule (:meth:`~.judges.base.Judge.accept`)
        if c.get("criterion") == "statistic":
            return " not named: judged by its held-out statistics"
        if (c.get("fit") or {}).get("neutral"):
            return " not taken: its fit holds the effect neutral (the gain is the current model's own)"
        shift = (c.get("heldout_statistic") or {}).get("shift_px")
        if shift is not None:
            from .judges.pose_error import MIN_SHIFT_PX

            if shift < MIN_SHIFT_PX:
                return f" not taken: the correction moves the image by {shift:.2f} px, below {MIN_SHIFT_PX} px"
        h = c.get("heldout_residual") or {}
        if h.get("improvement") is not None:
            imp = 100 * h["improvement"]
            moves = f"{'lowers' if imp >= 0 else 'raises'} the held-out residual by {abs(imp):.1f} %"
            return f" not taken: its least-squares fit {moves}, not beyond the fits' spread"
        return " not taken"
    if c.get("full_refit"):
        return " chosen (refitted with the full budget)"
    if c.get("criterion") == "statistic":
        return " named (held-out statistics)"
    h = c.get("heldout_residual") or {}
    how = (f"held-out residual {100 * h['improvement']:.0f} % lower, margin {100 * h['margin']:.0f} %"
           if c.get("criterion") == "residual" and h.get("improvement") is not None else "held-out θ")
    chosen = [s.get("chosen") for s in selection if s.get("round") == c.get("round") and s.get("chosen")]
    return f" beyond its margin ({how}): " + ("chosen" if c["effect"] in chosen else
                                             f"not chosen ({chosen[0]} was)" if chosen else "not chosen")


#: Keys of the document that hold times (and where the recording was read): what differs between two runs
#: that computed the same diagnosis.
RUN_KEYS = ("timing", "time_s", "refit_s", "source")


def without_times(doc):
    """The diagnosis document (or a part of it) without :data:`RUN_KEYS`, to compare two runs' results."""
    if isinstance(doc, dict):
        return {k: without_times(v) for k, v in doc.items() if k not in RUN_KEYS}
    if isinstance(doc, list):
        return [without_times(v) for v in doc]
    return doc


def validate_diagnosis_json(d: dict) -> None:
    """Raise ValueError naming the first part of ``d`` that does not follow the schema (module docstring)."""
    def need(obj, key, types, where):
        if not isinstance(obj, dict) or key not in obj:
            raise ValueError(f"{where}: missing key {key!r}")
        if not isinstance(obj[key], types):
            raise ValueError(f"{where}.{key}: expected {types}, got {type(obj[key]).__name__}")
        return obj[key]

    num = (int, float)
    if d.get("mode") == "images":          # footage without a scene model: nothing was fitted, θ is null
        num = (int, float, type(None))
    need(d, "schema_version", int, "diagnosis")
    for i, v in enumerate(need(d, "verdict", list, "diagnosis")):
        w = f"verdict[{i}]"
        need(v, "effect", str, w)
        c = need(v, "confidence", num, w)
        if not 0 <= c <= 1:
            raise ValueError(f"{w}.confidence must be in [0, 1], got {c}")
        need(v, "explanation", str, w)
        need(v, "params", dict, w)
    conf = [v["confidence"] for v in d["verdict"]]
    if conf != sorted(conf, reverse=True):
        raise ValueError("verdict must be ordered by confidence, highest first")
    for i, c in enumerate(need(d, "candidates", list, "diagnosis")):
        w = f"candidates[{i}]"
        need(c, "effect", str, w)
        for k in ("theta_train", "theta_heldout", "delta_heldout"):
            need(c, k, num, w)
        need(c, "params", dict, w)
    b = need(d, "base", dict, "diagnosis")
    for k in ("theta_train", "theta_heldout"):
        need(b, k, num, "base")
    need(b, "params", dict, "base")
    need(need(d, "final", dict, "diagnosis"), "theta_heldout", num, "final")
    regions = need(need(d, "mismatch", dict, "diagnosis"), "regions", list, "mismatch")
    for i, r in enumerate(regions):
        for k in ("kind", "name"):
            need(r, k, str, f"mismatch.regions[{i}]")
        for k in ("rms", "share"):
            need(r, k, num, f"mismatch.regions[{i}]")
    named = {v["effect"] for v in d["verdict"]}
    for i, u in enumerate(need(d, "undecided", list, "diagnosis") if "undecided" in d else []):
        w = f"undecided[{i}]"
        if need(u, "effect", str, w) in named:
            raise ValueError(f"{w}: {u['effect']} is named in the verdict")
        need(u, "explanation", str, w)


# ================================================================================== pipeline


def _ls_frame(rf: ReducedFrame):
    """A FitFrame-like view of a reduced frame for :func:`uw_sil.fit.backward.linear_start`: only pure
    panel blocks count as panel, only open water as water."""
    lab = np.where(rf.obj, LABEL_PANEL, np.where(rf.water, 0, 255)).astype(np.uint8)
    return SimpleNamespace(image=rf.image, render=SimpleNamespace(rgb=rf.rgb, range=rf.range, depth=rf.depth,
                                                                  labels=lab))


def _flat(params: dict) -> dict:
    out = dict(params["base"])
    for n, v in params["effects"].items():
        for p, x in v.items():
            out[f"{n}.{p}"] = float(x)
    return out


def _effect_flat(params: dict, names) -> dict:
    out = {}
    for n in names:
        for p, x in params["effects"].get(n, {}).items():
            out[f"{n}.{p}"] = float(x)
    out.update(params["base"])
    return out


def _full_res_noise(frames) -> list:
    """Camera noise (grey levels, per channel) of each frame at its own resolution, from its open water."""
    from ..sim.noise import water_noise_sigma

    return [[float(v) for v in water_noise_sigma(f.image, ~np.isfinite(f.render.range))] for f in frames]


def theta_as_simulated(frames, R_hi: dict, base: dict, effects: dict, fog: str, seed: int) -> np.ndarray:
    """θ per frame of a model (``base``: the 7 parameters by name; ``effects``: ``{effect: values}`` applied to
    the frames' geometry) as ``sim_camera`` renders it with the diagnosis' params file: at the recording's
    resolution, every effect applied and those new in every frame (sensor noise, particles) drawn; without a
    sensor-noise effect, the camera's constant noise estimated on the frame's water (the params file sets its
    mean over the frames); rounded to grey levels and reduced as the recording is, then scored against the
    reduced recording (``R_hi[id(frame)]``, the reference every model is scored with).

    Held-out θ of a fit leaves the per-frame effects out (they cannot be compared pixel by pixel) and adds the
    constant noise at the reduced resolution; this is the number to hold against a recording of the same dive
    with other draws of its noise and particles (``bench/bench_concealed.py``'s ceiling), which is made the
    same way. A correction of the frames' geometry the model holds (a pose correction) is already in ``frames``,
    not in ``effects``."""
    from ..sim.noise import NoiseField, water_noise_sigma
    from .diagfit import theta_reference
    from .residuals import box_down

    full = [reduce_frame(f, 1) for f in frames]
    model = EffectModel(full, tuple(effects), values=effects, free={e: () for e in effects}, fog=fog, seed=seed)
    x = model.x0([base[k] for k in RGB_NAMES])[None]
    out = np.empty(len(frames))
    for k, f in enumerate(frames):
        img = model.simulate(k, x)[0] * np.float32(255.0)
        if not model.owns_noise:
            NoiseField(img.shape, water_noise_sigma(f.image, ~np.isfinite(f.render.range)),
                       seed=seed + 7919 * k).apply(img)
        np.rint(np.clip(img, 0.0, 255.0, out=img), out=img)
        R = R_hi[id(f)]
        out[k] = float(theta_reference(R).fork().score(box_down(img, R.factor)[None])[0])
    return out


def _particle_blocks(ctx, sigs: dict, factor: int):
    """Per frame, the low-resolution pixels (``factor`` blocks) that hold a particle of the recording, when
    the marine snow signature found particles (else None: the proxies see every pixel)."""
    from .residuals import box_down
    from .signatures import particle_masks

    snow = sigs.get("marine_snow")
    if snow is None or not snow.judged or snow.score < 1.0:
        return None
    return [box_down(m, factor) > 0 for m in particle_masks(ctx)]


#: Frames read beyond the K of a diagnosis, when the recording has them, and set aside as report frames.
REPORT_FRAMES = 2
#: Seed offset of the simulations scored on the report frames (the held-out frames': 50).
REPORT_SEED_OFFSET = 100

#: Patience of every optimizer run of the diagnosis (base and candidates alike: a fair comparison).
PATIENCE = 6
#: Candidates of the rounds after the first: the remaining effects with the best held-out evidence in their
#: latest refit, best first; None: every remaining effect, as in the first round (since 2026-12-07; 3 before).
#: An effect that gains nothing beside the base model can be what the next model needs: on a physically lit dive
#: (lamps, a mild camera response, forward scatter, a seafloor) the camera response's round-1 refit stayed at its
#: neutral values (held-out θ +0.0000), so beside the seafloor it was not among the three tried, and the lamps'
#: fit, extrapolating their brightening to the nearest held-out frame without the response's compression, lost
#: there; with every effect tried the camera response came in round 2 (held-out residual 27.5 -> 14.8 grey
#: levels², θ 0.8064 -> 0.8206) and the lamps in round 3 (θ -> 0.8363). The three were also chosen on the held-out
#: frames that then judged them, corrected for three tests. More tests widen the margins (a literature dive's forward
#: scatter beside its port: +0.0085 held-out θ against 0.0089 with seven candidates; it was named with three).
LATER_CANDIDATES = None
#: Least-squares iterations of the current model's fit, the reference of the held-out residual criterion
#: (the candidates' least-squares fits start from it with their effect neutral, and from their own starts).
LS_BASE_NFEV = 30
#: CMA-ES iterations of the candidates' first, cheap refit in each round (and of the current model's own refit,
#: the reference they are compared with): none. The cheap refit is the candidate's least-squares fits (about 80 px
#: wide, from the plug-in's starts and the nested ones), and θ on the fit frames picks the best of those and of the
#: nested starts; the round's winner is then refitted with the base fit's full budget from that point. Six
#: iterations until 2026-11-30: on the nine physical dives of seeds 401-409 one and none gave the same verdicts as
#: six (bench/README.md, "The rounds' cheap refits without CMA-ES").
ROUND_ITER = 0
#: CMA-ES iterations of backward elimination's refits (the model without one effect: its θ refit has no
#: least-squares fit of its own) and of each effect's step of the final polish (6 until 2026-11-30).
CHEAP_ITER = 1


def _confidence(strength: float, doubts: list) -> float:
    """Confidence of an accepted effect from its held-out evidence in margins (1 = just beyond the margin:
    0.5; 3 margins and more: 0.95), lowered by 0.6 for each value outside a physical range (:func:`out_of_range`:
    a finding of its own, that the fit mimics something else) and by 0.8 once for parameters on a bound of their
    box, however many: they are one finding, a form the box cannot draw, which says how well the values are known
    rather than that the effect is absent (so do parameters the recording does not determine, counted with them).
    Counted as 0.6 each, the literature generator's four flat-top lamps (offset, toe-in and tilt on their bounds;
    81 % less held-out residual at over 3 margins) ranked below a vignetting of one margin, and its strong
    vignetting (+0.153 held-out θ at 6.4 margins, k2 on its bound: the corners darker than the polynomial's box)
    below lamps accepted at 1.35 margins beside it (0.7-0.9 rank those documents alike)."""
    c = 0.05 + 0.9 * float(np.clip(0.5 + (strength - 1.0) / 4.0, 0.0, 1.0))
    implausible = len(out_of_range(doubts))
    bound = len(doubts) > implausible
    return float(np.clip(c * 0.6 ** implausible * (0.8 if bound else 1.0), 0.05, 0.99))


def base_doubts(base: dict) -> list:
    """Doubts about a fitted base model: attenuation far below any water's (deep sea: red 0.35-0.6, green
    0.07-0.2, blue 0.03-0.15 per metre in clear water) means the fit absorbed something else, most often the
    falloff of the vehicle's own lamps (brightness falling with range as 1/r², not as exp(-a r))."""
    low = [f"a_{c} = {base[f'a_{c}']:.3f} /m" for c in "rgb" if base[f"a_{c}"] < 0.01]
    if not low:
        return []
    return [f"fitted attenuation {', '.join(low)} is far below any water's (clear deep-sea water: red 0.35-0.6, "
            f"green 0.07-0.2, blue 0.03-0.15 /m): the base model absorbs physics it lacks"]


def _candidate_row(rnd, current, e: str, r, margin: float, ok: bool, strength: float, criterion: str,
                   imp=None, rgain=None) -> dict:
    gain_pf = r.sel_pf - current.sel_pf
    row = {"round": rnd, "model": current.name, "effect": e, "theta_train": r.theta_fit,
           "theta_heldout": float(np.mean(r.sel_pf)), "delta_heldout": float(np.mean(gain_pf)),
           "delta_heldout_per_frame": gain_pf.tolist(), "margin": margin, "accepted": bool(ok),
           "criterion": criterion, "strength": float(strength), "params": _effect_flat(r.params, [e]),
           "kept_current_optimum": bool(r.started_at_current)}
    if imp is not None:
        row["heldout_residual"] = {"improvement": rgain[0] if rgain else None,
                                   "per_frame_improvement": np.asarray(imp).tolist(),
                                   "margin": rgain[1] if rgain else None, "current": float(np.mean(current.ls_sel_E)),
                                   "candidate": float(np.mean(r.extra["ls_sel_E"]))}
    if r.statistic is not None:
        row["heldout_statistic"] = r.statistic
    if r.extra:
        row["fit"] = {k: v for k, v in r.extra.items() if isinstance(v, (int, float, str))}
    return row


def _evidence_words(c: dict) -> str:
    """A candidate row's held-out evidence, by the rule that judged it, in words."""
    h = c.get("heldout_residual") or {}
    if h.get("improvement") is None:
        h = c.get("heldout_statistic") or {}     # a pose correction's own residual test
    if c.get("criterion") == "residual" and h.get("improvement") is not None:
        ev = f"held-out residual {100 * h['improvement']:.0f} % lower, margin {100 * h['margin']:.0f} %"
    elif c.get("criterion") == "statistic":
        ev = f"held-out statistics {c['strength']:.2f} margins nearer the recording's"
    else:
        ev = f"held-out θ {c['delta_heldout']:+.4f}, margin {c['margin']:.4f}"
    return f"added to {c['model']}: {ev}"


def undecided_effects(candidates: list, final_effects, held_neutral_at_end=()) -> list:
    """The effects the held-out frames could not tell from the final model's: each beat its margin at a step of
    the forward selection (its refit, not held at its neutral values, raised held-out θ, lowered the held-out
    residual or moved the held-out statistics beyond the margin) and is not in the final model, because other
    effects explain as much of the same mismatch: another was chosen that round and it no longer beat its margin
    beside it, or the backward elimination dropped it (the model without it, refitted, was as good), or it
    joined the model and the final model holds it at its neutral values (``held_neutral_at_end``; or
    :func:`held_faint`).

    Not a verdict: the frames hold evidence for it that the final model's effects account for too. Lamps and
    lens vignetting are the common case: a rig of lamps around the camera lights a facing panel with a falloff
    from its centre that, seen from the camera, is nearly a function of the angle off the optical axis, as
    vignetting is; which of the two it is, or how much of each, takes frames that move them apart (lamps dimmed
    or off, a flat field). Returns one entry per effect, strongest evidence first, with the step that showed it
    (``round``, ``model``, ``criterion``, ``strength`` in margins, ``delta_heldout``, ``margin``), how it ended
    (``last``: its latest row) and ``explanation``."""
    final = set(final_effects)
    rows = {}
    for c in candidates:
        if c["effect"] not in final:
            rows.setdefault(c["effect"], []).append(c)
    out = []
    for e, rs in rows.items():
        beat = [c for c in rs if c.get("accepted") and not c.get("neutral") and not c.get("elimination")]
        if not beat:
            continue
        best = max(beat, key=lambda c: c.get("strength", 0.0))
        last = rs[-1]
        if last.get("elimination"):
            end = (f"then dropped by the backward elimination: the model without it was as good ("
                   f"{_evidence_words(last)})")
        elif e in held_neutral_at_end:
            end = ("it joined the model, and the final model holds it at its neutral values or within half a grey "
                   "level of them (the model without it)")
        elif last.get("round") == best.get("round"):
            end = "it was not refitted beside the effects chosen after it"
        else:
            end = f"beside the effects chosen since, it fell below its margin ({_evidence_words(last)})"
        out.append({"effect": e, "round": best["round"], "model": best["model"], "criterion": best.get("criterion"),
                    "strength": float(best.get("strength", 0.0)), "delta_heldout": best["delta_heldout"],
                    "margin": best.get("margin"),
                    "last": {k: last.get(k) for k in ("round", "model", "delta_heldout", "margin", "criterion")},
                    "explanation": f"{e}: beat its margin in round {best['round']} ({_evidence_words(best)}); {end}"})
    out.sort(key=lambda u: -u["strength"])
    return out


def _without_one(shared, e):
    """The current model without its effect ``e``, refitted (:func:`uw_sil.fit.judges.base.refit_without`), in a
    worker process or here; its time in ``(refit, seconds)``."""
    from .judges import base as jb

    job, current = shared
    t = time.perf_counter()
    r = jb.refit_without(job, current, e, LS_BASE_NFEV)
    return r, time.perf_counter() - t


def _eliminate(job, current, accepted: list, seed: int, say, candidates: list, steps: list, fits: dict,
               earlier: dict, workers=None) -> tuple:
    """Backward elimination on held-out frames: an accepted effect may be explained by others (the footprint of
    lamps accepted as vignetting, then the lamps; lamp falloff on the panel, once β_B ≠ β_D and a seafloor are
    in, by them). Every effect of the model, the last accepted included, is tested: it must still beat its
    margin against the model without it, refitted (:func:`uw_sil.fit.judges.base.refit_without`), by the rule
    that accepted it (θ, else the residual). Of those that do not, the one with the least evidence (its held-out
    θ gain or, where its judge takes the residual as evidence, its residual gain, whichever is larger, in its
    margins) is dropped (removed from ``accepted``), and the smaller model is tested again, until every effect
    beats its margin or one is left.

    Why every effect and the weakest first: two effects can each explain what the other does. Testing only
    the earlier ones dropped whichever came first, whatever the evidence: on a physically lit dive with a
    seafloor the lamps (accepted first, held-out residual 194 -> 36 grey levels²) were dropped for β_B ≠ β_D
    accepted last, although the model without β_B ≠ β_D lost less held-out θ (0.0026) than the one without
    the lamps (0.0055).

    Why against the model the pass started from as well: removing one effect at a time loses effects that only
    help together. On a physically lit dive (lamps, camera response, forward scatter, snow) forward scatter went
    first (+0.0024 held-out θ), then the lamps, each below its own margin in the model it was tested in (+0.0074
    against 0.0087), although the model with all three scored 0.817 held out and the one left 0.807. So a drop
    after the first must also leave a model as good as the one the pass started from (``top``): the effects
    dropped so far and this one, removed together, must not lose beyond the margin of that comparison (by the
    dropped effect's rule, θ else the residual). If they do, this effect stays and the next weakest is tried
    (the comparison with the largest model of stepwise regression, which keeps a set of terms each too weak
    alone).

    The model without an effect is the better, on the fit frames, of that refit and an earlier fit of the same
    model in the forward selection (``earlier``: effect set -> (model it was added to, refit); a model
    containing another is not judged against a worse fit of that one than the selection already had), unless
    that earlier fit holds one of its effects at its neutral values: it is then a fit of a smaller model. (On a
    physically lit dive the lamps were accepted by the held-out residual, θ being blind to them in the dark
    frames; their round-1 θ refit had stayed at the base model, lamps neutral, and its θ on the fit frames
    beat the elimination's refit of the lamps by 0.001. Taken as "the model without forward scatter" it dropped
    forward scatter and then left the lamps unnamed: verdict none.) The refits of one pass run side by side in
    ``workers``. Appends to ``candidates``, ``steps`` and ``fits``;
    returns ``(current, dropped)``."""
    from .judges import JUDGES, margin_for
    from .judges.base import current_ls, residual_gain, residual_improvement, with_effect

    cheap = replace(job, max_iter=min(job.max_iter, CHEAP_ITER))
    dropped = False
    top = current
    n_top = sum(a["effect"] in top.effects for a in accepted)
    while True:
        tested = [a for a in accepted if a["effect"] in current.effects]
        if len(tested) < 2:
            return current, dropped
        names = [a["effect"] for a in tested]
        say(f"elimination: refitting {current.name} without each of {', '.join(names)}")
        shared = (cheap, current)
        if workers is not None:
            res = workers.map(_without_one, names, shared=shared, interrupt=job.interrupt)
        else:
            res = [_without_one(shared, e) for e in names]
        weak = []
        for a, (reduced, took) in zip(tested, res):
            e = a["effect"]
            if reduced is None:
                continue
            known = earlier.get(frozenset(reduced.effects))
            if known is not None and known[1].theta_fit > reduced.theta_fit:
                better = (f"elimination: the forward selection's fit of {reduced.name} is better on the fit frames "
                          f"(θ {known[1].theta_fit:.4f} vs {reduced.theta_fit:.4f})")
                idle = held_neutral(known[1].params["effects"], job.camera)
                if idle:
                    say(f"{better} but holds {', '.join(idle)} at its neutral values (a fit of the model without "
                        f"it): the refit is compared")
                else:
                    say(f"{better}: that one is compared")
                    reduced = current_ls(job, with_effect(*known), max_nfev=LS_BASE_NFEV)
            full = _as_refit(current, e)
            margin = margin_for(current.sel_pf - reduced.sel_pf, 2 * len(tested), seed=seed)
            rgain = residual_gain(reduced, full, 2 * len(tested), seed=seed)
            ok, strength, crit = JUDGES[e].accept(full, reduced, margin, rgain)
            candidates.append({**_candidate_row("elimination", reduced, e, full, margin, ok, strength, crit,
                                                residual_improvement(reduced, full), rgain), "elimination": True})
            steps.append({"round": "elimination", "model": reduced.name,
                          "theta_heldout": float(reduced.sel_pf.mean()),
                          "residual_heldout": float(np.mean(reduced.ls_sel_E)), "theta_train": reduced.theta_fit,
                          "tried": [e], "chosen": None, "time_s": took})
            if ok:
                say(f"elimination: {e} kept (held-out {'residual' if crit == 'residual' else 'θ'} beyond its "
                    f"margin without it)")
                continue
            # its evidence for staying, in margins: its held-out θ gain, or its residual gain where that is
            # evidence for it (:attr:`~uw_sil.fit.judges.base.Judge.residual_evidence`), whichever is more
            evidence = float(strength)
            if rgain and JUDGES[e].residual_evidence:
                evidence = max(evidence, rgain[0] / rgain[1])
            weak.append((evidence, a, reduced, len(steps) - 1, len(candidates) - 1))
        weak.sort(key=lambda w: w[0])
        for evidence, a, reduced, step, row in weak:
            e = a["effect"]
            if current is top:
                break
            # the effects dropped in this pass and this one, removed together, against the model it started from
            gone = [x for x in top.effects if x not in reduced.effects]
            full = _as_refit(top, e)
            margin = margin_for(top.sel_pf - reduced.sel_pf, 2 * n_top, seed=seed)
            ok, strength, crit = JUDGES[e].accept(full, reduced, margin, residual_gain(reduced, full, 2 * n_top,
                                                                                      seed=seed))
            steps[step]["joint"] = candidates[row]["joint"] = {
                "without": gone, "model": top.name, "theta_heldout": float(top.sel_pf.mean()), "margin": margin,
                "kept": bool(ok), "criterion": crit}
            if not ok:
                break
            say(f"elimination: {e} kept: without {' and '.join(gone)} together the model loses beyond its margin "
                f"against {top.name} (held-out θ {reduced.sel_pf.mean():.4f} vs {top.sel_pf.mean():.4f}, "
                f"margin {margin:.4f})")
        else:
            return current, dropped
        others = [w[1]["effect"] for w in weak if w[1] is not a]
        say(f"elimination: {e} dropped: the model without it, refitted, is as good on the held-out frames "
            f"(θ {reduced.sel_pf.mean():.4f} vs {current.sel_pf.mean():.4f}; its evidence {evidence:.2f} margins"
            + (f", the least of {', '.join([e] + others)})" if others else ")"))
        steps[step]["chosen"] = f"-{e}"
        candidates[row]["dropped"] = True
        accepted.remove(a)
        current, dropped = reduced, True
        fits[current.name] = {"x": current.x, "held_pf": np.asarray(current.sel_pf), "model": current.model,
                              "model_effects": list(current.effects), "held_E": np.asarray(current.ls_sel_E)}


def held_neutral(values: dict, camera=None) -> list:
    """The effects of ``values`` (``{effect: its complete parameter values}``) held at their neutral values
    (:meth:`~uw_sil.fit.judges.base.Judge.neutral`, on images of ``camera``): a model holding them so is the
    model without them, whatever its name."""
    from .judges import JUDGES

    return [e for e, v in values.items() if JUDGES[e].neutral(v, camera)]


def held_faint(current, floor: float = FAINT_DN) -> list:
    """The effects of the model ``current`` (a :class:`~uw_sil.fit.judges.base.Current`) whose fitted values change
    no pixel of its fit frames by ``floor`` grey levels against the same vector with the effect's free parameters
    at their defaults, where those are the effect's identity: the model without it in all but name. A fit can end
    a hair from neutral, which :func:`held_neutral` does not catch (the literature generator's strong vignetting:
    lamps accepted by the held-out residual of their least-squares fit, whose θ fit ended at fill 0.999999, a
    millionth of the light from the lamps, and were named first)."""
    from ..sim.effects import get_effect
    from .diagfit import image_change

    if current.model is None or current.x is None:
        return []
    m, x = current.model, np.asarray(current.x, float)
    names = m.names
    out = []
    for e in current.effects:
        eff, idx = get_effect(e), m.free_index(e)
        d = eff.defaults()
        if idx.size == 0 or not eff.is_identity(d):
            continue
        xn = x.copy()
        xn[idx] = [d[names[i].split(".", 1)[1]] for i in idx]
        if image_change(m, x, xn)[0] < floor:
            out.append(e)
    return out


def _as_refit(model, e: str):
    """``model`` (a :class:`~uw_sil.fit.judges.base.Current`) as the refit of its effect ``e``: what a judge's
    ``accept`` compares the model without ``e`` with."""
    from .judges.base import Refit

    params = {"base": dict(zip(RGB_NAMES, map(float, model.base))),
              "effects": {n: dict(v) for n, v in model.values.items()}}
    return Refit(effect=e, effects=model.effects, x=model.x, params=params, theta_fit=model.theta_fit,
                 sel_pf=model.sel_pf, model=model.model, extra={"ls_sel_E": model.ls_sel_E})


def out_of_range(doubts: list) -> list:
    """The doubts that make a fit physically implausible: its values outside deep-sea ranges (β_B/β_D = 6 taking
    the veil of lamps, lamps on the camera), not its parameters on a bound of their box (:data:`~uw_sil.fit.
    judges.base.ON_BOUND`): the box cut a fit whose form differs from the scene's, which says how well the values
    are known, not that the effect is not there (the literature generator's flat-top lamps put the rig's toe-in
    and height on their bounds at 88 % less held-out residual and +0.034 held-out θ; ranked as implausible,
    a camera response of +0.000 held-out θ was chosen before them), nor parameters the image does not depend on
    (:data:`~uw_sil.fit.judges.base.NOT_DETERMINED`), which say the same."""
    from .judges.base import NOT_DETERMINED, ON_BOUND

    return [d for d in doubts if ON_BOUND not in d and NOT_DETERMINED not in d]


def _rank(plausible: bool, strength: float, r, current) -> tuple:
    """Order of a round's accepted candidates, best last. A physically plausible explanation first (no doubt of
    :func:`out_of_range`): a fit with its values outside deep-sea ranges is stretched to mimic something else
    (β_B/β_D = 6 taking the veil of lamps). Then θ, the paper's criterion: every accepted candidate that raises
    held-out θ, by its gain, whichever held-out test accepted it (the test says the effect is there; the gain says
    how much of the mismatch it takes). The residual's strength ranks only those that do not raise θ (the dark,
    noisy frames θ is blind to). Ranked by gain over margin, a steadier effect a tenth as large won (vignetting's
    +0.014 over the lamps' +0.144 on a lamp-lit field recording, and on a physical dive camera_response's +0.0069
    over forward scatter's +0.0265). Ranked with θ's acceptances first, a flat port that raised held-out θ most
    (+0.029, every held-out frame up, more the nearer: a wide bootstrap margin; its residual 76 % lower) came after
    a forward scatter's +0.012 on a literature dive, and a pose bias then took its place."""
    gain = float(np.mean(r.sel_pf - current.sel_pf))
    return (plausible, gain > 0.0, gain if gain > 0.0 else strength)


def _refit_pinned(cheap, current, oks: list, n_cands: int, candidates: list, rnd: int, seed: int,
                  say) -> tuple:
    """A round's accepted candidates fitted outside the ranges deep-sea physics allows (doubts) that would rank
    above every plausible one without their doubts: each is refitted (cheap budget, as the round's refits) with
    the parameters responsible held at their nearest possible values (:meth:`~uw_sil.fit.judges.base.Judge.
    pinned`: mild lamps barely fix their position, and the fit can put them 0.08 m from the camera with the
    same held-out θ as at 0.3 m). If that refit still beats its margin it replaces the stretched one in
    ``oks``; its row is appended to ``candidates`` (``pinned``). Returns ``(oks, jobs)``: ``jobs`` maps such an
    effect to the job whose plug-in holds the values (its full-budget refit must hold them too)."""
    from .judges import JUDGES
    from .judges.base import residual_gain, residual_improvement

    plausible = max((c[5][1:] for c in oks if c[5][0]), default=(False, -np.inf))
    out, jobs = [], {}
    for choice in oks:
        e, r, strength, margin, crit, rank = choice
        judge = JUDGES[e]
        values = r.params["effects"].get(e, {})
        pins = judge.pinned(values) if not rank[0] and rank[1:] > plausible and judge.kind == "theta" else {}
        if not pins:
            out.append(choice)
            continue
        because = "; ".join(judge.ranges(values)) or "outside its physical range"
        say(f"round {rnd}: {e} refitted with " + ", ".join(f"{n} {v:.3g}" for n, v in pins.items())
            + f" held ({because})")
        job_e = replace(cheap, judges={**cheap.judges, e: judge.with_pinned(pins)})
        # started also from the stretched fit itself with those values moved to the nearest possible ones (its
        # least-squares fit where the residual accepted it: the model that acceptance adopts); from the plug-in's
        # starts alone, the off-centre vignetting of physical dive 403 held 0.1 from the principal point lowered
        # the held-out residual by 0.5 % where the fit it came from lowered it by 19 %; from the fit moved, by 30 %
        # and +0.0042 held-out θ (the stretched fit +0.0021: it was not the better fit, only the one found)
        src = r.extra.get("ls_params") if crit == "residual" else None
        src = ({"base": dict(zip(RGB_NAMES, np.asarray(src["base"], float))), "effects": src["effects"]}
               if src is not None else r.params)
        moved = {"base": src["base"], "effects": {**src["effects"], e: {**src["effects"].get(e, {}), **pins}}}
        rp = job_e.judges[e].refit(job_e, current, parent=moved)
        rp.extra["pinned"] = {"values": pins, "because": because}
        rgain = residual_gain(current, rp, 2 * n_cands, seed=seed)
        ok, s2, c2 = judge.accept(rp, current, margin, rgain)
        doubts = judge.plausibility(rp.params["effects"].get(e, {}), ()) if ok else []
        candidates.append({**_candidate_row(rnd, current, e, rp, margin, ok, s2, c2,
                                            residual_improvement(current, rp), rgain),
                           "doubts": doubts, "pinned": dict(pins)})
        if ok and not out_of_range(doubts):
            out.append((e, rp, s2, margin, c2, _rank(True, s2, rp, current)))
            jobs[e] = job_e
        else:
            out.append(choice)
    return out, jobs


#: The item of a round's refits that is the current model itself (:func:`uw_sil.fit.judges.base.reference_refit`).
REFERENCE = ""


def _refit_one(shared, effect):
    """One candidate's refit (:meth:`uw_sil.fit.judges.base.Judge.refit`), or the current model's own
    (``effect`` :data:`REFERENCE`), in a worker process or here; its time in ``extra["refit_s"]``."""
    from .judges.base import reference_refit

    job, current, parents = shared
    t = time.perf_counter()
    if effect == REFERENCE:
        r = reference_refit(job, current)
    else:
        r = job.judges[effect].refit(job, current, parent=parents.get(effect))
    if r is not None:
        r.extra["refit_s"] = time.perf_counter() - t
    return r


def _refit_all(workers, cands: list, job, current, say, label: str, took: dict,
               parents: Optional[dict] = None, reference: bool = True) -> dict:
    """Every candidate's refit of a round and (``reference``) the current model's own with the same budget (the
    candidates' reference, key :data:`REFERENCE`; None where there is none), side by side in the diagnosis's worker
    processes (the results of one after the other: :func:`diagnose_frames`); ``{effect: Refit}``
    in the order of ``cands``, the reference last. The costliest refits first (their time in an earlier round,
    ``took``, updated here; else the plug-in's :attr:`~uw_sil.fit.judges.base.Judge.cost`). ``parents``: each
    candidate's refit of the previous round's model, a start of its refit here
    (:func:`~uw_sil.fit.judges.base.theta_refit`)."""
    from .judges import JUDGES

    items = list(cands) + ([REFERENCE] if reference else [])
    n = min(workers.processes, len(items))
    say(f"{label}: refitting {current.name} + each of {', '.join(cands)}{f', and {current.name} itself' * reference} "
        f"({f'{n} processes side by side' if n > 1 else 'one after the other'})")

    def done(i, r):
        took[items[i]] = r.extra["refit_s"] if r is not None else 0.0
        what = f"{current.name} + {items[i]}" if items[i] != REFERENCE else current.name
        say(f"{label}: {what} refitted ({took[items[i]]:.1f} s)")

    parents = {e: p for e, p in (parents or {}).items() if e in cands}
    res = workers.map(_refit_one, items, shared=(job, current, parents), interrupt=job.interrupt, done=done,
                      cost=[took.get(e, JUDGES[e].cost if e != REFERENCE else 1.0) for e in items])
    return dict(zip(items, res))


def _adopt_reference(current, ref, say, label: str):
    """The current model refitted with a candidate's budget (:func:`uw_sil.fit.judges.base.reference_refit`)
    replaces it where it scores higher on the fit frames (the held-out frames do not choose it): the round's
    candidates are compared with that. The held-out residual's reference (the least-squares fit) stays.
    Returns ``(current, record)``, the record for the round's step (None: no reference refit)."""
    from .judges.base import with_effect

    if ref is None:
        return current, None
    adopted = bool(ref.theta_fit > current.theta_fit)
    rec = {"theta_train_before": current.theta_fit, "theta_train": ref.theta_fit,
           "theta_heldout_before": float(np.mean(current.sel_pf)), "theta_heldout": float(np.mean(ref.sel_pf)),
           "adopted": adopted}
    if adopted:
        say(f"{label}: {current.name} refitted as the candidates are: θ on the fit frames {current.theta_fit:.4f} -> "
            f"{ref.theta_fit:.4f} (held-out {rec['theta_heldout_before']:.4f} -> {rec['theta_heldout']:.4f}); "
            f"the candidates are compared with it")
        current = replace(with_effect(current, ref), ls_params=current.ls_params, ls_sel_E=current.ls_sel_E)
    return current, rec


def _keep_better(earlier: dict, current, r):
    """Remember the refit ``r`` of ``current`` + its effect under its effect set, if it is the best on the fit
    frames so far (what backward elimination compares a model without an effect with)."""
    key = frozenset(r.effects)
    if key not in earlier or r.theta_fit > earlier[key][1].theta_fit:
        earlier[key] = (current, r)


def report_count(n_frames: int, k: int) -> int:
    """Report frames of a diagnosis of ``k`` frames that got ``n_frames`` usable ones (it asked for
    ``k +`` :data:`REPORT_FRAMES`): the surplus, so that a short recording gives the selection all it has."""
    return int(min(REPORT_FRAMES, max(0, n_frames - k)))


def diagnose_frames(frames: list, fog: str = "exp2", seed: int = 0, max_effects: int = 4, max_iter: int = 30,
                    popsize: int = 12, progress: Optional[Callable[[str], None]] = None,
                    interrupt: Optional[Callable] = None, effects_allowed=None, source: str = "",
                    later_candidates: Optional[int] = LATER_CANDIDATES, processes: Optional[int] = None,
                    report_frames: int = 0) -> Diagnosis:
    """Diagnose already loaded frames (:func:`uw_sil.fit.residuals.load_frames`); see the module docstring.

    ``report_frames``: frames of ``frames`` set aside (:func:`uw_sil.fit.residuals.set_aside`), only scored
    with the base and the final model (``theta_report``);
    ``max_effects``: effects the greedy forward selection adds at most (it stops there); the effects new in
    every frame, judged on their statistics after it, come on top;
    ``max_iter``/``popsize``: the CMA-ES budget of the base fit and of each round's winner's full refit (a round's
    cheap refits take :data:`ROUND_ITER` iterations, the elimination's and the polish's :data:`CHEAP_ITER`);
    ``effects_allowed``: names of the effects considered (default all with a plug-in);
    ``processes``: worker processes refitting a round's candidates side by side (default: the thread budget,
    :func:`uw_sil._shared.process.default_threads`; 1 = all in this process). The document is the same:
    two-process diagnoses of the physical dives 405 (lamps) and 407 (lamps, a seafloor) are identical to the
    one-process ones. (They were not on seafloor dives until 2026-11-30: the seafloor's texture pyramid, built
    lazily by whichever θ thread came first, could get two threads' levels in the main process, which refits a
    round's winner on two threads; :func:`uw_sil.sim.effects.unmodeled_geometry._texture_mips`.)

    BLAS runs on one thread meanwhile (the diagnosis evaluates θ on threads of its own; OpenBLAS threads on
    top of them oversubscribe the cores: a least-squares step's SVD took 12x longer on a busy machine)."""
    from threadpoolctl import threadpool_limits

    from .._shared.workers import WorkerPool

    # the workers start (and import the diagnosis) while the base fit runs here
    with threadpool_limits(limits=1, user_api="blas"), \
            WorkerPool(processes, preload=("uw_sil.fit.diagnose", "uw_sil.fit.judges")).start() as workers:
        return _diagnose(frames, fog, seed, max_effects, max_iter, popsize, progress, interrupt, effects_allowed,
                         source, later_candidates, workers, report_frames)


def _diagnose(frames, fog, seed, max_effects, max_iter, popsize, progress, interrupt, effects_allowed, source,
              later_candidates, workers, report_frames=0) -> Diagnosis:
    from ..sim.effects import get_effect
    from ..sim.params import ParamSpace
    from .backward import linear_start
    from .judges import JUDGES, Current, Job, margin_for
    from .judges.base import (MIN_MARGIN, current_ls, gain_words, least_squares_model, polish_blocks, residual_gain,
                              residual_improvement, with_effect)
    from .judges.sensor_noise import camera_noise_choice, camera_noise_words
    from .residuals import added_surface
    from .screening import screen_proxies
    from .signatures import SignatureContext, run_signatures

    say = progress or (lambda msg: None)
    t_all = time.perf_counter()
    timing = {}
    if len(frames) - max(0, report_frames) < 3:
        raise DiagnosisError(f"need at least 3 frames that show the scene model besides {report_frames} report "
                             f"frame(s), got {len(frames)}")
    frames, report_f = set_aside(frames, report_frames)
    fit_f, held_f = split_frames(frames)
    W = frames[0].image.shape[1]
    f_hi = reduction_factor(W, 320)
    f_lo = max(f_hi, reduction_factor(W, 160))
    R_hi = {id(f): reduce_frame(f, f_hi) for f in frames}
    R_lo = {id(f): reduce_frame(f, f_lo) for f in frames}
    f_ls = max(f_lo, reduction_factor(W, 80))
    R_ls = {id(f): reduce_frame(f, f_ls) for f in frames}
    rfit = [R_hi[id(f)] for f in fit_f]
    nfit = noise_sigmas(rfit)

    # ---------------------------------------------------------------- base fit
    t0 = time.perf_counter()
    say(f"base fit on {len(fit_f)} frames ({rfit[0].shape[1]}x{rfit[0].shape[0]}), {len(held_f)} held out")
    x_lin = linear_start([_ls_frame(r) for r in rfit], ParamSpace("rgb"), fog=fog)
    base_model = BaseModel(rfit, fog)
    with FrameObjective(rfit, base_model, nfit, seed=seed, batch=popsize, pool=workers) as objective:
        base_fit = fit_model(base_model, rfit, nfit, x_lin, sigma0=BASE_SIGMA0, seed=seed, max_iter=max_iter,
                             popsize=popsize, patience=PATIENCE, interrupt=interrupt, objective=objective)
    timing["base_fit_s"] = time.perf_counter() - t0

    # ---------------------------------------------------------------- evidence that orders the work (fit frames)
    t0 = time.perf_counter()
    say("residual signatures and screening proxies on the fit frames (they order the refits; they veto none)")
    ctx = SignatureContext(rfit, [base_sim(rf, base_fit.x, fog) for rf in rfit], nfit, base_fit.x, fog)
    sigs = run_signatures(ctx)
    rlo_fit = [R_lo[id(f)] for f in fit_f]
    prox = screen_proxies(rlo_fit, base_fit.x, noise_sigmas(rlo_fit), fog=fog,
                          exclude=_particle_blocks(ctx, sigs, f_lo))
    # where the recording and the base model differ, over every frame (for the reader, not for the selection)
    rall = [R_hi[id(f)] for f in frames]
    sims = [base_sim(rf, base_fit.x, fog) for rf in rall]
    nall = noise_sigmas(rall)
    res = residual_maps(rall, sims)
    mismatch = locate(rall, res, nall)
    timing["evidence_s"] = time.perf_counter() - t0

    job = Job(fit_f=list(fit_f), sel_f=list(held_f), R_hi=R_hi, R_lo=R_lo, R_ls=R_ls, fog=fog, seed=seed, max_iter=max_iter,
              popsize=popsize, patience=PATIENCE, sigs=sigs, prox=prox, judges=JUDGES, interrupt=interrupt,
              pool=workers)
    empty = EffectModel(rfit, (), fog=fog, seed=seed)
    current = Current(effects=(), values={}, base=np.asarray(base_fit.x[:7], float),
                      theta_fit=float(job.frame_theta(empty, fit_f, base_fit.x[None]).mean()),
                      sel_pf=job.frame_theta(empty, held_f, base_fit.x[None], 50)[0], x=base_fit.x, model=empty)
    current = current_ls(job, current, max_nfev=LS_BASE_NFEV)
    base_sel_pf = current.sel_pf.copy()
    base_sel_E = current.ls_sel_E.copy()
    base_params = {"base": {k: float(v) for k, v in zip(RGB_NAMES, current.base)}, "effects": {}}
    base_x, base_theta_train = base_fit.x, float(base_fit.theta_train)

    # ---------------------------------------------------------------- greedy forward selection on held-out frames
    allowed = [e for e in JUDGES if effects_allowed is None or e in effects_allowed]
    order = {e: JUDGES[e].order(job) for e in allowed}
    pool = sorted((e for e in allowed if JUDGES[e].kind == "theta"), key=lambda e: -order[e])
    stat_effects = [e for e in allowed if JUDGES[e].kind == "statistic"]
    candidates, steps, accepted, latest, earlier, took, parents = [], [], [], {}, {}, {}, {}
    fits = {"base": {"x": base_fit.x, "held_pf": base_sel_pf, "model": empty, "model_effects": [],
                     "held_E": base_sel_E}}
    rnd = 0
    checked = ()
    while True:
        while pool and len(accepted) < max_effects:
            rnd += 1
            # later rounds: the remaining effects (LATER_CANDIDATES of them, None: all) with the best evidence of
            # their latest refit, whatever its sign (an effect can hide behind a stronger one until that one is
            # modelled: β_B ≠ β_D behind strong lamps)
            cands = pool if rnd == 1 else sorted(pool, key=lambda e: -latest.get(e, -np.inf))[:later_candidates]
            if not cands:
                break
            t0 = time.perf_counter()
            cheap = replace(job, max_iter=min(job.max_iter, ROUND_ITER))
            results = _refit_all(workers, cands, cheap, current, say, f"round {rnd}", took, parents)
            current, reference = _adopt_reference(current, results.pop(REFERENCE, None), say, f"round {rnd}")
            if rnd == 1 and reference and reference["adopted"]:
                # the base model refitted: that is its fit (what a verdict of none leaves, what the report shows)
                base_x, base_theta_train, base_sel_pf = current.x, current.theta_fit, current.sel_pf.copy()
                base_params = {"base": {k: float(v) for k, v in zip(RGB_NAMES, current.base)}, "effects": {}}
                fits["base"].update(x=base_x, held_pf=base_sel_pf)
            parents = {e: r.params for e, r in results.items() if r.params}
            for e in cands:
                if not JUDGES[e].absorb:
                    _keep_better(earlier, current, results[e])
            oks, rows = [], []
            for e, r in results.items():
                # two held-out tests per candidate (θ and the residual): both margins corrected for 2 x candidates
                margin = margin_for(r.sel_pf - current.sel_pf, 2 * len(cands), seed=seed)
                imp = residual_improvement(current, r)
                rgain = residual_gain(current, r, 2 * len(cands), seed=seed)
                ok, strength, crit = JUDGES[e].accept(r, current, margin, rgain)
                latest[e] = float(np.mean(r.sel_pf - current.sel_pf)) if not ok else max(strength, 1e-6)
                flat = JUDGES[e].flat_bounds(job, r.model, r.x, margin) if ok else ()
                doubts = JUDGES[e].plausibility(r.params["effects"].get(e, {}), flat) if ok else []
                rows.append({**_candidate_row(rnd, current, e, r, margin, ok, strength, crit, imp, rgain),
                             "doubts": doubts, **({"flat_bounds": list(flat)} if flat else {}),
                             **({"neutral": True} if r.extra.get("neutral") else {})})
                rank = _rank(not out_of_range(doubts), strength, r, current)
                if ok:
                    oks.append((e, r, strength, margin, crit, rank))
            candidates += rows
            oks, pinned_jobs = _refit_pinned(cheap, current, oks, len(rows), candidates, rnd, seed, say)
            oks.sort(key=lambda c: c[5], reverse=True)
            best, r_full = None, None
            for choice in oks:
                e, r, strength, margin, crit, _ = choice
                if crit == "residual" and "ls_x" in r.extra and JUDGES[e].adopts_least_squares:
                    # (pose_error's own residual: it is absorbed)
                    # the model a residual acceptance adopts is the least-squares fit. The residual decides only
                    # where θ is blind; θ scores that fit too, and where it falls by more than the least change a
                    # θ gain is ever credited with (MIN_MARGIN), θ is not blind there: it says the simulation got
                    # worse, and no residual gain outweighs that (a wide forward-scatter glow, written from Wells'
                    # MTF, taken as a camera response: residual -39 %, 8.9 margins, held-out θ -0.035, per frame
                    # -0.075 to +0.025; weighed in its own bootstrap margin, as until 2026-12-06, it was 0.7 of it)
                    r_full = least_squares_model(job, r)
                    fall = float(np.mean(current.sel_pf - r_full.sel_pf))
                    if fall > MIN_MARGIN:
                        say(f"round {rnd}: {e} declined: its least-squares fit lowers held-out θ "
                            f"{current.sel_pf.mean():.4f} -> {r_full.sel_pf.mean():.4f} (more than {MIN_MARGIN}: θ is "
                            f"not blind to it) while it lowers the residual ({strength:.1f} margins)")
                        for row in rows:
                            if row["effect"] == e:
                                row.update(accepted=False, declined={"theta_fall": fall, "theta_floor": MIN_MARGIN,
                                                                     "residual_margins": float(strength)})
                        latest[e] = -fall
                        r_full = None
                        continue
                best = choice
                break
            steps.append({"round": rnd, "model": current.name, "theta_heldout": float(current.sel_pf.mean()),
                          "residual_heldout": float(np.mean(current.ls_sel_E)),
                          "theta_train": current.theta_fit, "tried": [row["effect"] for row in rows],
                          "chosen": best[0] if best else None, "time_s": time.perf_counter() - t0,
                          **({"reference": reference} if reference else {})})
            timing[f"round_{rnd}_s"] = time.perf_counter() - t0
            if best is None:
                say(f"round {rnd}: no effect raised held-out θ or lowered the held-out residual beyond its margin; "
                    f"selection ends")
                break
            e, r, strength, margin, crit, _ = best
            passed = [row["effect"] for row in rows if row["accepted"] and out_of_range(row["doubts"])
                      and row["effect"] != e and row["strength"] > strength]
            if passed:
                say(f"round {rnd}: {', '.join(passed)} passed over: fitted out of physical range ("
                    + "; ".join(out_of_range(row["doubts"])[0] for row in rows if row["effect"] in passed) + ")")
            before = float(current.sel_pf.mean())
            before_E = current.ls_sel_E
            judge = JUDGES[e]
            t_adopt = time.perf_counter()
            keep = r_full is not None
            if e in pinned_jobs:
                # the refit accepted holds values at their nearest physically possible ones: so do its full-budget
                # refit and every later fit of a model with it (the next rounds, the elimination, the polish)
                job = replace(job, judges={**job.judges, e: pinned_jobs[e].judges[e]})
                # and the forward selection's fits of models with it made without the hold are not the fits the
                # elimination compares (their plug-in had more free parameters: an own four-effect dive's
                # elimination took such a fit of lamps + β_B≠β_D + camera response, and the polish failed on its
                # parameter count)
                for k in [k for k in earlier if e in k]:
                    del earlier[k]
            if judge.kind == "theta" and not judge.absorb and job.max_iter > cheap.max_iter and not keep:
                say(f"round {rnd}: refitting {current.name} + {e} with the full budget")
                starts = ([r.extra["ls_x"]] if "ls_x" in r.extra else []) + ([] if r.started_at_current else [r.x])
                r_full = job.judges[e].refit(job, current, x_starts=starts)
                r_full.extra.update({k: v for k, v in r.extra.items() if k.startswith("ls_") or k == "pinned"})
            if keep or (judge.kind == "theta" and not judge.absorb and job.max_iter > cheap.max_iter):
                candidates.append({**_candidate_row(rnd, current, e, r_full, margin, True, strength, crit,
                                                    residual_improvement(current, r_full),
                                                    residual_gain(current, r_full)), "full_refit": True})
                r = r_full
            if judge.absorb:
                job, current = judge.absorb_into(job, current, r)
                current = current_ls(job, current, max_nfev=LS_BASE_NFEV)
                # the fits so far saw the frames before the correction: not comparable with the ones after
                # (backward elimination took a fit of the uncorrected frames, and with it lost the correction)
                earlier.clear()
                parents = {}
            else:
                # the reference of the next round's residual evidence: the new model's least-squares fit polished
                # with the base fit's least-squares budget (a candidate's fit must not win by a longer polish alone)
                current = current_ls(job, with_effect(current, r), max_nfev=LS_BASE_NFEV)
            # the winner's full-budget refit and the new model's least-squares fit (after the round's own time)
            timing[f"round_{rnd}_adopt_s"] = time.perf_counter() - t_adopt
            how = "residual" if crit == "residual" else "θ"
            say(f"round {rnd}: accepted {e} by held-out {how} (held-out θ {before:.4f} -> "
                f"{current.sel_pf.mean():.4f}, residual {np.mean(before_E):.3g} -> {np.mean(current.ls_sel_E):.3g} grey levels²)")
            accepted.append({"effect": e, "refit": r, "strength": strength, "margin": margin, "before": before,
                             "pinned": r.extra.get("pinned"),
                             "after": float(current.sel_pf.mean()), "criterion": crit,
                             "residual_before": float(np.mean(before_E)),
                             "residual_after": float(np.mean(current.ls_sel_E))})
            fits[current.name] = {"x": r.x, "held_pf": np.asarray(r.sel_pf), "model": r.model,
                                  "model_effects": list(r.effects), "held_E": np.asarray(current.ls_sel_E)}
            pool.remove(e)

        # ---------------------------------------------------------------- backward elimination on held-out frames
        dropped = False
        if len(current.effects) > 1 and tuple(current.effects) != checked:
            t_el = time.perf_counter()
            current, dropped = _eliminate(job, current, accepted, seed, say, candidates, steps, fits, earlier,
                                          workers)
            checked = tuple(current.effects)        # (judged: a later elimination only after a new effect)
            timing["elimination_s"] = timing.get("elimination_s", 0.0) + time.perf_counter() - t_el
        # a dropped effect frees a place: the forward selection goes on from the smaller model
        if not (dropped and pool and len(accepted) < max_effects):
            break

    # ---------------------------------------------------------------- the selected model polished effect by effect
    if len(current.effects) > 1:
        t0 = time.perf_counter()
        before = float(current.sel_pf.mean())
        say(f"polishing {current.name} one effect at a time on the fit frames")
        current, polished = polish_blocks(job, current, max_iter=min(job.max_iter, CHEAP_ITER))
        for st in polished:
            say(f"polish: {st['effect']} " + (f"θ on the fit frames {st['theta_fit_before']:.4f} -> "
                                              f"{st['theta_fit_after']:.4f}" if st["kept"] else "unchanged"))
        steps.append({"round": "polish", "model": current.name, "theta_heldout": float(current.sel_pf.mean()),
                      "residual_heldout": float(np.mean(current.ls_sel_E)), "theta_train": current.theta_fit,
                      "tried": [st["effect"] for st in polished], "chosen": None,
                      "time_s": time.perf_counter() - t0, "polish": polished})
        if any(st["kept"] for st in polished):
            say(f"polish: held-out θ {before:.4f} -> {current.sel_pf.mean():.4f}")
            fits[current.name] = {**fits.get(current.name, {}), "x": current.x, "held_pf": np.asarray(current.sel_pf),
                                  "model": current.model, "model_effects": list(current.effects)}
        timing["polish_s"] = time.perf_counter() - t0

    # ---------------------------------------------------------------- effects new in every frame: statistics
    t0 = time.perf_counter()
    geo = {e: current.values[e] for e in current.effects if get_effect(e).keeps_scene}
    if geo:
        # surfaces an accepted geometry effect adds (a seafloor) are not noise: left out of its statistics
        job.exclude = {id(f): added_surface(f, geo) for f in job.fit_f + job.sel_f}
    # side by side in the worker processes, as a round's refits (each judge refits only its own effect)
    stat_results = {}

    def judged(e, r):
        """``(margin, ok, strength, criterion)`` of a statistics plug-in's refit (corrected for their number)"""
        margin = margin_for(r.sel_pf - current.sel_pf, len(stat_effects), seed=seed)
        return (margin,) + tuple(JUDGES[e].accept(r, current, margin))

    if stat_effects:
        say(f"judging {', '.join(stat_effects)} on the held-out frames' statistics (new in every frame: θ "
            f"cannot rise)")
        # the compression first: where it is accepted, the camera noise is judged through it. The recording's noise
        # passed the codec, whose quantization smooths it within its blocks: a correlation the sensor did not make,
        # which a noise model judged on uncompressed simulations takes as its own (the literature generator's JPEG
        # at quality 75 over white shot and read noise was named structured sensor noise first, at 0.95)
        codec = [e for e in stat_effects if e == "compression" and "sensor_noise" in stat_effects]
        if codec:
            stat_results = _refit_all(workers, codec, job, current, say, "statistics", took, reference=False)
            r = stat_results["compression"]
            if judged("compression", r)[1]:
                job = replace(job, after_noise={"compression": dict(r.params["effects"]["compression"])})
        rest = [e for e in stat_effects if e not in codec]
        if rest:
            stat_results.update(_refit_all(workers, rest, job, current, say, "statistics", took, reference=False))
    for e, r in stat_results.items():
        timing[f"statistics_{e}_s"] = r.extra["refit_s"]
        margin, ok, strength, crit = judged(e, r)
        row = _candidate_row(rnd + 1, current, e, r, margin, ok, strength, crit)
        candidates.append(row)
        # not held to ``max_effects``: that bounds the greedy search over the smooth effects; each of these is
        # one test of its own statistic (on a foreign four-effect trial the selection's fourth place went to lamps
        # the recording lacked, and strong sensor noise, accepted here at 3.3 margins, was dropped unsaid)
        if ok:
            accepted.append({"effect": e, "refit": r, "strength": strength, "margin": margin,
                             "before": float(current.sel_pf.mean()), "after": float(np.mean(r.sel_pf))})
    timing["statistics_s"] = time.perf_counter() - t0

    # ---------------------------------------------------------------- the final model and the verdict
    # an effect the final model holds at its neutral values is the model without it: it is not named (a refit
    # can end where it started)
    idle = held_neutral(current.values, job.camera)
    faint = [e for e in held_faint(current) if e not in idle]
    neutral = [a for a in accepted if a["effect"] in idle or a["effect"] in faint]
    for a in neutral:
        accepted.remove(a)
        say(f"{a['effect']} not named: the final model holds it at its neutral values" if a["effect"] in idle else
            f"{a['effect']} not named: the final model holds it at values that change no pixel of the fit frames by "
            f"{FAINT_DN} grey levels")
        steps.append({"round": "final", "model": current.name, "theta_heldout": float(current.sel_pf.mean()),
                      "residual_heldout": float(np.mean(current.ls_sel_E)), "theta_train": current.theta_fit,
                      "tried": [a["effect"]], "chosen": f"-{a['effect']}", "time_s": 0.0})
    final_effects = [a["effect"] for a in accepted]
    eff_values = {e: dict(v) for e, v in current.values.items() if e not in {a["effect"] for a in neutral}}
    eff_values.update({e: dict(v) for e, v in current.absorbed.items()})
    for a in accepted:
        if JUDGES[a["effect"]].kind == "statistic":
            eff_values[a["effect"]] = dict(a["refit"].params["effects"][a["effect"]])
    # the camera's own noise in sim_camera: the named noise model, else photon transfer where it beats one sigma
    camera_noise = ({"model": "sensor_noise", "values": eff_values["sensor_noise"]} if "sensor_noise" in final_effects
                    else camera_noise_choice(getattr(stat_results.get("sensor_noise"), "statistic", None), seed))
    if camera_noise["model"] == "photon_transfer":
        eff_values["sensor_noise"] = dict(camera_noise["values"])
    noise_words = camera_noise_words(camera_noise)
    if noise_words:
        say(f"camera noise for sim_camera: {noise_words}")
    final_params = {"base": {k: float(v) for k, v in zip(RGB_NAMES, current.base)}, "effects": eff_values}
    verdict = []
    for a in accepted:
        e, r = a["effect"], a["refit"]
        judge = JUDGES[e]
        vals = eff_values[e]
        flat = judge.flat_bounds(job, current.model, current.x, a["margin"]) if e in current.effects else ()
        pins = a.get("pinned") or {}
        undetermined = judge.undetermined(current.model, current.x, held=tuple(pins.get("values", ())))
        doubts = judge.plausibility(vals, flat, undetermined)
        words = gain_words(a["before"], a["after"], r.statistic if judge.kind == "statistic" else None,
                           (a["residual_before"], a["residual_after"]) if a.get("criterion") == "residual" else None)
        text = judge.explain(vals, words, sigs.get(e), camera=job.camera)
        # (values held where the image does not depend on them: neither the free fit nor the held value is a finding)
        if (pins and all(abs(vals.get(n, np.inf) - v) < 1e-9 for n, v in pins["values"].items())
                and not set(pins["values"]) <= set(undetermined)):
            text += (" — held at the nearest physically possible values ("
                     + ", ".join(f"{n} {v:.3g}" for n, v in pins["values"].items())
                     + f"): fitted freely, {pins['because']}")
        if doubts:
            text += " — doubt: " + "; ".join(doubts)
        verdict.append({"effect": e, "confidence": _confidence(a["strength"], doubts), "explanation": text,
                        "params": _effect_flat(final_params, [e]), "doubts": doubts})
    verdict.sort(key=lambda v: -v["confidence"])
    final_theta = float(current.sel_pf.mean())
    # the held-out frames as sim_camera renders the base and the final model (noise and particles drawn)
    t0 = time.perf_counter()
    drawn = {e: current.values[e] for e in current.effects}
    drawn.update({a["effect"]: eff_values[a["effect"]] for a in accepted if JUDGES[a["effect"]].kind == "statistic"})
    if camera_noise["model"] == "photon_transfer":
        drawn["sensor_noise"] = eff_values["sensor_noise"]
    as_sim = {"base": theta_as_simulated(held_f, R_hi, base_params["base"], {}, fog, seed + 50),
              "final": theta_as_simulated(job.sel_f, job.R_hi, final_params["base"], drawn, fog, seed + 50)}
    timing["as_simulated_s"] = time.perf_counter() - t0
    report = {"base": None, "final": None}
    if report_f:
        # frames no fit and no choice saw: the base and the final model scored on them (a pose correction the
        # final model holds is applied to their geometry, as to the others')
        t0 = time.perf_counter()
        rep_final = list(report_f)
        for e, values in current.absorbed.items():
            rep_final = JUDGES[e].absorbed_frames(rep_final, values)
        job.R_hi.update({id(f): reduce_frame(f, f_hi) for f in {id(f): f for f in report_f + rep_final}.values()})
        report = {"base": job.frame_theta(empty, report_f, base_x[None], REPORT_SEED_OFFSET)[0],
                  "final": job.frame_theta(current.model, rep_final, np.asarray(current.x, float)[None],
                                           REPORT_SEED_OFFSET)[0]}
        say(f"report frames {[f.index for f in report_f]} (no fit or choice saw them): θ "
            f"{report['base'].mean():.4f} (base) -> {report['final'].mean():.4f} (final model)")
        timing["report_s"] = time.perf_counter() - t0
    timing["total_s"] = time.perf_counter() - t_all
    not_judged = [{"effect": e, "reason": s.reason} for e, s in sigs.items() if not s.judged]
    final_key = current.name if current.effects or current.absorbed else None
    diag = Diagnosis(
        verdict=verdict, candidates=candidates,
        base={"theta_train": base_theta_train, "theta_heldout": float(base_sel_pf.mean()),
              "theta_heldout_simulated": float(as_sim["base"].mean()),
              "theta_report": _mean_or_none(report["base"]),
              "residual_heldout": float(np.mean(base_sel_E)),
              "params": dict(base_params["base"]), "doubts": base_doubts(base_params["base"])},
        final={"theta_heldout": final_theta, "theta_heldout_simulated": float(as_sim["final"].mean()),
               "residual_heldout": float(np.mean(current.ls_sel_E)),
               "theta_report": _mean_or_none(report["final"]),
               "effects": final_effects, "params": _flat(final_params), "camera_noise": camera_noise,
               "statistics": {a["effect"]: a["refit"].statistic for a in accepted
                              if JUDGES[a["effect"]].kind == "statistic"}},
        mismatch=mismatch,
        signatures={e: {**sigs[e].to_dict(), "order_score": order.get(e),
                        "explained_share": (prox[e].explained if e in prox else None)} for e in sigs},
        noise={"margin": margin_for(np.zeros(len(held_f))), "camera_noise_dn": [list(map(float, n)) for n in nall],
               "camera_noise_dn_full_resolution": _full_res_noise(frames)},
        frames=[{"index": f.index, "role": f.role, "range_m": f.range_median, "coverage": f.coverage}
                for f in sorted(frames + report_f, key=lambda f: f.index)],
        timing=timing, final_params=final_params, not_judged=not_judged, source=source, selection=steps,
        undecided=undecided_effects(candidates, final_effects, [a["effect"] for a in neutral]),
        figures={"rframes": rall, "sims": sims, "res": res, "sigs": sigs, "prox": prox, "fits": fits,
                 "base_x": base_x, "fog": fog, "held": [R_hi[id(f)] for f in held_f],
                 # the final model and the held-out frames it is scored on (corrected where it absorbed a pose)
                 "final": (current.model, np.asarray(current.x, float), [job.R_hi[id(f)] for f in job.sel_f]),
                 "base_held_pf": base_sel_pf, "final_key": final_key})
    return diag


def _mean_or_none(pf) -> Optional[float]:
    return None if pf is None else float(np.mean(pf))


def diagnose_bag(bag, k: int = 8, model=None, image_topic: str = "/camera/image_raw", **kw) -> Diagnosis:
    """Read ``k`` frames of a recording (and up to :data:`REPORT_FRAMES` more, the report frames, when it has
    them) and diagnose them (see :func:`diagnose_frames`)."""
    try:
        frames = load_frames(bag, k=k + REPORT_FRAMES, model=model, image_topic=image_topic)
    except ValueError as e:
        raise DiagnosisError(str(e)) from e
    return diagnose_frames(frames, source=str(bag), report_frames=report_count(len(frames), k), **kw)


def write_diagnosis_yaml(path, diag: Diagnosis, node_name: str = "/**", fog: str = "exp2", comment: str = ""):
    """ROS 2 parameters file for ``sim_camera`` with the final (extended) model: base parameters, the
    camera noise, and ``<effect>.<param>`` of the accepted effects (a parameter ``effects`` lists them).

    The camera noise (``final["camera_noise"]``): where the sensor noise effect is named, or photon transfer was
    chosen for it (:func:`~uw_sil.fit.judges.sensor_noise.camera_noise_choice`), the effect ``sensor_noise``
    draws it (listed in ``effects`` then, ``noise_sigma`` 0: sim_camera adds ``noise_sigma`` on top of its
    effects); else ``noise_sigma``, the constant sigma measured on the recording's open water."""
    import yaml

    from .._shared.fileio import write_text_atomic

    p = dict(diag.final_params["base"])
    p["fog_mode"] = fog
    eff = list(diag.final.get("effects", []))
    cn = diag.final.get("camera_noise") or {}
    if cn.get("model") == "photon_transfer" and "sensor_noise" not in eff:
        eff.append("sensor_noise")
        pt = cn["values"]
        comment = "\n".join([comment] * bool(comment) + [
            f"camera noise: photon transfer, the effect sensor_noise without structure (shot {pt['shot']:.3f} DN/DN, "
            f"read {pt['read']:.2f} DN; not a named effect)"])
    full = diag.noise.get("camera_noise_dn_full_resolution")
    p["noise_sigma"] = float(np.mean(full)) if full and "sensor_noise" not in eff else 0.0
    if eff:
        p["effects"] = ",".join(eff)
        for n in eff:
            for k, v in diag.final_params["effects"][n].items():
                p[f"{n}.{k}"] = float(v)
    body = {node_name: {"ros__parameters": p}}
    text = "".join(f"# {line}\n" for line in comment.splitlines()) + yaml.safe_dump(body, sort_keys=False)
    return write_text_atomic(path, text)
