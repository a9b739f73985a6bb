"""Mismatch diagnosis: which physics does the recording hold that the simulation leaves out?

Pipeline (:func:`diagnose_bag`, ``uw-sil diagnose --bag``), from what a real user has (the bag's images,
camera info and panel poses, and the scene model; never a ground-truth sidecar):

1. **frames**: up to K frames spread over the recording, each rendered at its recorded pose; split into
   fit frames and *held-out* frames interleaved over range (:func:`uw_sil.fit.residuals.split_frames`).
2. **base fit**: the 7 parameters of paper Eq. 1 with fog, by CMA-ES on θ over the fit frames (from the
   least-squares start of :func:`uw_sil.fit.backward.linear_start`, stopped on convergence), on frames
   box-downsampled to about 320 px wide (θ's FSIMc downsamples 640x480 by 2 anyway).
3. **locate**: residual maps real - sim per frame and channel, and where they are large (object / water /
   silhouette, 3x3 image regions, panel parts, range bins): :func:`uw_sil.fit.residuals.locate`.
4. **signatures**: each effect's footprint tested on the residuals (:mod:`uw_sil.fit.signatures`) and
   the share of the residual each effect's physics can explain (:mod:`uw_sil.fit.screening`; without the
   recording's particles when the marine snow signature finds them).
5. **model and refit** the leading candidates: base + that effect (:mod:`uw_sil.sim.effects`), jointly,
   CMA-ES on θ over the fit frames from the base fit.
6. **decide on held-out frames only**: an effect is accepted only if it raises held-out θ by more than
   the run-to-run noise of the fit, estimated honestly by refitting the base model with another seed
   and start (optimizer noise) combined with a bootstrap over held-out frames of the per-frame gains
   (frame-sampling noise). ``none`` (an empty verdict) is a valid outcome. Two accepted effects are
   refitted together and kept as a pair if that beats the best single effect by the same margin.
7. **say it**: a plain-language verdict with numbers, the JSON document (:data:`SCHEMA_VERSION`), a
   params YAML for ``sim_camera`` with the extended model, and an HTML/PNG report.

JSON schema (``schema_version`` 1)::

    {"schema_version": 1,
     "verdict":    [{"effect", "confidence", "explanation", "params"}, ...],   # [] = no effect; best first
     "candidates": [{"effect", "theta_train", "theta_heldout", "delta_heldout", "params"}, ...],
     "base":       {"theta_train", "theta_heldout", "params"},
     "final":      {"theta_heldout"},
     "mismatch":   {"regions": [{"kind", "name", "pixels", "rms", "mean", "rms_rgb", "share"}, ...]},
     ... extra keys: "noise", "signatures", "frames", "timing", "not_judged", "source"}

``effect`` names are those of :data:`uw_sil.sim.effects.EFFECTS`; ``params`` of a verdict or candidate are
``{"<effect>.<param>": value}`` for the effect and the refitted base parameters ``a_r ... rho_f``.
"""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Callable, Optional

import numpy as np

from ..sim.params import RGB_NAMES
from .diagfit import BASE_SIGMA0, BaseModel, FrameObjective, fit_model, noise_sigmas
from .residuals import (LABEL_PANEL, ReducedFrame, base_sim, load_frames, locate, reduce_frame,
                        reduction_factor, residual_maps, split_frames)

__all__ = ["SCHEMA_VERSION", "Diagnosis", "diagnose_frames", "diagnose_bag", "EffectModel", "FIT_SETTINGS",
           "write_diagnosis_yaml", "validate_diagnosis_json", "DiagnosisError"]

SCHEMA_VERSION = 1

#: Smallest held-out θ gain accepted (also when the bootstrap spread is smaller).
MIN_MARGIN = 0.003
#: Effects judged on held-out frames by a statistic instead of θ: random ones (new particles, new noise in
#: every frame cannot raise a pixel-wise similarity) and pose error (sub-pixel edge shifts that θ on reduced
#: frames barely sees; judged by the held-out residual).
STATISTICAL = ("marine_snow", "sensor_noise", "pose_error")


class DiagnosisError(ValueError):
    """The recording could not be diagnosed (the message says why)."""


#: Per effect: the parameters refitted (the others stay at their defaults or the given values),
#: the resolution class of the refit ("low": ~160 px wide, the effect is smooth; "high": ~320 px) and
#: fixed values.
FIT_SETTINGS = {
    # power is free: how bright the lamps are against the render's light level is the recording's, not ours
    # (fixed at 1, a foreign rig normalized at 2.5 m instead of 2 m could not be fitted: held-out θ fell)
    "artificial_light": {"free": ("offset_x", "offset_y", "toe_in", "half_angle", "shape", "balance", "fill", "power",
                                  "veil"), "res": "low", "fixed": {}},
    "forward_scatter": {"free": ("strength", "width", "tail"), "res": "high", "fixed": {}},
    "backscatter_coefficient": {"free": ("ratio_r", "ratio_g", "ratio_b", "decay"), "res": "low", "fixed": {}},
    "vignetting": {"free": ("k1", "k2", "cx", "cy"), "res": "low", "fixed": {}},
    "sensor_noise": {"free": ("shot", "read", "corr", "fpn", "col", "row"), "res": "high", "fixed": {}},
    "marine_snow": {"free": ("density", "brightness", "size"), "res": "high", "fixed": {}},
    "camera_response": {"free": ("gamma", "gain_r", "gain_g", "gain_b", "black"), "res": "low", "fixed": {}},
    "unmodeled_geometry": {"free": ("floor_y", "tilt", "albedo", "contrast"), "res": "low", "fixed": {}},
    "pose_error": {"free": ("tx", "ty", "tz", "rx", "ry", "rz"), "res": "high",
                   "fixed": {"jitter_t": 0.0, "jitter_r": 0.0}},
}


#: Alternative start configurations tried before the least-squares start of a refit (physical extremes of
#: effects whose least-squares landscape has several basins).
ALT_STARTS = {
    "unmodeled_geometry": [{"floor_y": -0.8, "albedo": 1.0, "contrast": 1.0},
                           {"floor_y": -2.0, "albedo": 1.0, "contrast": 0.5},
                           {"floor_y": -4.5, "albedo": 1.3, "contrast": 0.3}],
    "artificial_light": [{"offset_x": 0.5, "offset_y": -0.1, "toe_in": 0.2, "half_angle": 0.45, "balance": 0.5,
                          "fill": 0.2},
                         {"offset_x": 0.8, "offset_y": -0.3, "toe_in": 0.0, "half_angle": 0.7, "balance": 0.1,
                          "fill": 0.3}],
}


# ================================================================================== extended model


class EffectModel:
    """Base model + effects of :mod:`uw_sil.sim.effects` on reduced frames, as a candidate model.

    Parameter vector: the 7 base parameters, then the free parameters of each effect (``FIT_SETTINGS``
    or ``free``), named ``<effect>.<param>``. Non-free parameters take ``values`` (default: the effect's
    defaults updated with the fixed values of ``FIT_SETTINGS``).

    On reduced frames the model runs on block-averaged geometry; the fraction of each block covered by
    the model (``cover``) scales the transmission so that silhouettes are area-exact as in
    :func:`uw_sil.fit.residuals.base_sim` (not for geometry effects, which re-project the geometry).
    """

    def __init__(self, rframes, effects, values: Optional[dict] = None, free: Optional[dict] = None,
                 fog: str = "exp2", seed: int = 0):
        from ..sim.effects import EFFECT_ORDER, get_effect
        from ..sim.model import UnderwaterModel
        from ..sim.params import UnderwaterParams

        self.rframes = list(rframes)
        self.fog = fog
        self.effects = tuple(n for n in EFFECT_ORDER if n in effects)
        unknown = set(effects) - set(self.effects)
        if unknown:
            raise ValueError(f"unknown effects {sorted(unknown)}")
        vals = {}
        for n in self.effects:
            v = get_effect(n).defaults()
            v.update(FIT_SETTINGS[n]["fixed"])
            v.update((values or {}).get(n, {}))
            vals[n] = v
        self.values = vals
        self.free = {n: tuple((free or {}).get(n, FIT_SETTINGS[n]["free"])) for n in self.effects}
        model = UnderwaterModel(UnderwaterParams(), vals, fog)
        self.template = model.effect_vector()
        self.pnames = model.effect_param_names()
        self.idx = np.array([self.pnames.index(f"{n}.{p}") for n in self.effects for p in self.free[n]], int)
        lo, hi = model.effect_bounds()
        self._elo, self._ehi = lo[self.idx], hi[self.idx]
        self.owns_noise = "sensor_noise" in self.effects
        self._model = model
        self._seed = seed
        self._local = threading.local()          # PreparedModel is not thread-safe: one set per thread
        self.pms = self._prepare()

    def _prepare(self) -> list:
        from ..sim.model import Geometry

        pms = []
        for k, rf in enumerate(self.rframes):
            geom = Geometry(rf.camera, rf.rgb, np.where(rf.cover > 0, rf.depth, np.inf),
                            np.where(rf.cover > 0, rf.range, np.inf), rf.labels, rf.part_ids,
                            pose=rf.frame.pose)
            # area-exact silhouettes at the reduced resolution, as the base model has them
            pms.append(self._model.prepare(geom, rf.camera, pose=rf.frame.pose, seed=1000 + k + 7919 * self._seed,
                                           cover=rf.cover))
        return pms

    def _thread_pms(self) -> list:
        if threading.current_thread() is threading.main_thread():
            return self.pms
        pms = getattr(self._local, "pms", None)
        if pms is None:
            pms = self._local.pms = self._prepare()
        return pms

    @property
    def names(self) -> tuple:
        return RGB_NAMES + tuple(f"{n}.{p}" for n in self.effects for p in self.free[n])

    def bounds(self) -> tuple:
        from ..sim.params import DEFAULT_RGB_BOUNDS

        return (np.concatenate([DEFAULT_RGB_BOUNDS[0], self._elo]), np.concatenate([DEFAULT_RGB_BOUNDS[1], self._ehi]))

    def effect_vectors(self, X) -> np.ndarray:
        X = np.atleast_2d(X)
        ev = np.repeat(self.template[None], len(X), axis=0)
        ev[:, self.idx] = np.clip(X[:, 7:], self._elo, self._ehi)
        return ev

    def simulate(self, k: int, X, out=None) -> np.ndarray:
        X = np.atleast_2d(np.asarray(X, float))
        base = np.clip(X[:, :7], 0, None)
        base[:, 3:6] = np.clip(base[:, 3:6], 0, 1)
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            return self._thread_pms()[k](base, self.effect_vectors(X), out=out)

    def x0(self, base_x, start: Optional[dict] = None) -> np.ndarray:
        """Start vector: base parameters and effect values (``start`` over the model's values)."""
        ev = []
        for n in self.effects:
            for p in self.free[n]:
                v = (start or {}).get(n, {}).get(p, self.values[n][p])
                ev.append(v)
        lo, hi = self.bounds()
        return np.clip(np.concatenate([np.asarray(base_x, float)[:7], ev]), lo, hi)

    def params_of(self, x) -> dict:
        x = np.asarray(x, float)
        base = np.clip(x[:7], 0, None)
        base[3:6] = np.clip(base[3:6], 0, 1)
        ev = self.effect_vectors(x[None])[0]
        eff = {}
        for n in self.effects:
            eff[n] = {p: float(ev[self.pnames.index(f"{n}.{p}")]) for p in self.values[n]}
        return {"base": {k: float(v) for k, v in zip(RGB_NAMES, base)}, "effects": eff}


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
    source: str = ""
    figures: dict = field(default_factory=dict)    # data for the report (not serialized)

    def to_json(self) -> dict:
        """The documented JSON document (numpy numbers converted; non-finite numbers become null)."""
        from .signatures import jsonable

        return jsonable({
            "schema_version": SCHEMA_VERSION,
            "verdict": self.verdict,
            "candidates": self.candidates,
            "base": self.base,
            "final": self.final,
            "mismatch": self.mismatch,
            "noise": self.noise,
            "signatures": self.signatures,
            "not_judged": self.not_judged,
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
        for c in self.candidates:
            lines.append(f"  candidate {c['effect']:<40s} held-out θ {c['theta_heldout']:.4f} "
                         f"(Δ {c['delta_heldout']:+.4f})")
        return lines


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
    from ..sim.noise import estimate_noise_sigma

    out = []
    for f in frames:
        water = ~np.isfinite(f.render.range)
        try:
            out.append([float(v) for v in estimate_noise_sigma(f.image, water)])
        except ValueError:
            out.append([float(v) for v in estimate_noise_sigma(f.image)])
    return out


def _bootstrap_se(d: np.ndarray, n: int = 2000, seed: int = 0) -> float:
    """Bootstrap standard error of the mean of per-frame values (frames resampled with replacement)."""
    d = np.asarray(d, float)
    if d.size < 2:
        return float("inf")
    rng = np.random.default_rng(seed)
    means = d[rng.integers(0, d.size, (n, d.size))].mean(axis=1)
    return float(np.std(means))


def _screen_score(effect: str, sigs: dict, prox: dict) -> float:
    """Candidate score from the residual signatures and the proxies' explained shares (1 = worth a refit).

    Effects whose residual test is specific (vignetting: achromatic, frame-invariant, in water and on the
    object; pose error: edge shifts; marine snow: sparse positive outliers; sensor noise: noise structure;
    unmodeled geometry: structure in open water; forward scatter: edges matching a blurred simulation) are
    scored by that test, the photometric ones (lamps, backscatter coefficient, camera response), whose
    residual footprints overlap, by the share of the residual their physics explains (25 % = 1).
    """
    s = sigs.get(effect)
    sig = s.score if s is not None and s.judged else 0.0
    p = prox.get(effect)
    ex = p.explained / 0.25 if p is not None else 0.0
    if effect == "vignetting":
        return sig * (0.5 + min(1.0, p.explained * 2)) if p is not None else sig
    if effect == "forward_scatter":
        pose = sigs.get("pose_error")
        if pose is not None and pose.judged and pose.score >= 3.0:
            return sig            # misaligned edges also look blurred at low resolution: trust the aligned test
        return max(sig, ex)
    if effect == "unmodeled_geometry":
        return max(sig, ex)
    if effect in ("artificial_light", "backscatter_coefficient", "camera_response"):
        return ex
    return sig


def _explain(effect: str, params: dict, b_held: float, c_held: float, sig, statistic=None) -> str:
    e = params["effects"].get(effect, {})
    gain = f"modelling it raises held-out θ from {b_held:.3f} to {c_held:.3f}"
    if statistic is not None:
        gain = (f"modelling it brings the held-out frames' {statistic['name']} from {statistic['base_sim']:.3g} "
                f"(base model) to {statistic['candidate_sim']:.3g} (recording: {statistic['real']:.3g}); held-out θ "
                f"{b_held:.3f} -> {c_held:.3f}")
    st = sig.stats if sig is not None else {}
    if effect == "artificial_light":
        side, other = ("right", "left") if e.get("offset_x", 0) >= 0 else ("left", "right")
        bal = e.get("balance", 0)
        off = abs(e.get("offset_x", 0))
        if bal > 0.35:
            lamp = f"two lamps about {off:.2f} m left and right of the camera"
        elif bal > 0.05:
            lamp = (f"a lamp about {off:.2f} m {side} of the camera (and a weaker one, {100 * bal:.0f} % of the "
                    f"light, {other})")
        else:
            lamp = f"a lamp about {off:.2f} m {side} of the camera"
        return (f"the recording is lit by vehicle lamps the simulation lacks: brightness on the panel falls "
                f"~1/r² from {lamp} ({100 * (1 - e.get('fill', 1)):.0f} % of the light from the lamps, beam half "
                f"width {math.degrees(e.get('half_angle', 0)):.0f}°); {gain}")
    if effect == "vignetting":
        k1, k2 = e.get("k1", 0), e.get("k2", 0)
        corner = 1 + k1 + k2
        return (f"the image darkens towards the corners the same way in every frame and in the water as on the "
                f"panel (lens vignetting): corner brightness {100 * corner:.0f} % of the centre "
                f"(k1 {k1:.2f}, k2 {k2:.2f}); {gain}")
    if effect == "forward_scatter":
        return (f"the recording is blurred by forward scattering, more at longer range: "
                f"{100 * (1 - math.exp(-e.get('strength', 0) * 2.0)):.0f} % of the light at 2 m is spread over "
                f"~{e.get('width', 0) * 2:.0f} mrad (halo share {e.get('tail', 0):.2f}); {gain}")
    if effect == "backscatter_coefficient":
        return (f"the backscatter builds up with other coefficients than the direct signal fades "
                f"(β_B/β_D = {e.get('ratio_r', 1):.2f}, {e.get('ratio_g', 1):.2f}, {e.get('ratio_b', 1):.2f} "
                f"for r, g, b; β_D falls with range by factor {1 + e.get('decay', 0):.1f} near the camera): an "
                f"additive bias on the panel that the water does not show; {gain}")
    if effect == "sensor_noise":
        return (f"the camera noise has structure the simulation's constant noise lacks: variance rising with "
                f"brightness (shot gain {e.get('shot', 0):.2f} DN/DN, read noise {e.get('read', 0):.1f} DN), "
                f"correlation over {e.get('corr', 0):.1f} px, fixed pattern {100 * e.get('fpn', 0):.1f} % gain, "
                f"{e.get('col', 0):.1f} DN per column, {e.get('row', 0):.1f} DN per row; {gain}")
    if effect == "marine_snow":
        dens = st.get("positive_per_mpx")
        extra = f" ({dens:.0f} bright specks per megapixel, new in every frame)" if dens is not None else ""
        return (f"marine snow: small bright particles in the lit water{extra}, about {e.get('density', 0):.0f} "
                f"per m³ of {e.get('size', 0):.1f} mm; {gain}")
    if effect == "camera_response":
        return (f"the camera maps light to grey levels differently: tone curve gamma {e.get('gamma', 1):.2f}, "
                f"white-balance gains r/g/b {e.get('gain_r', 1):.2f}/{e.get('gain_g', 1):.2f}/"
                f"{e.get('gain_b', 1):.2f}, black level {255 * e.get('black', 0):.0f} DN; {gain}")
    if effect == "unmodeled_geometry":
        return (f"the recording shows structure where the scene model has open water — a seafloor about "
                f"{abs(e.get('floor_y', 0)):.1f} m below the panel origin (albedo x{e.get('albedo', 1):.2f}, texture "
                f"contrast {e.get('contrast', 1):.2f}); {gain}")
    if effect == "pose_error":
        t = 100 * math.sqrt(sum(e.get(k, 0) ** 2 for k in ("tx", "ty", "tz")))
        r = math.degrees(math.sqrt(sum(e.get(k, 0) ** 2 for k in ("rx", "ry", "rz"))))
        sh = st.get("shift_px_median")
        extra = f"; edges in the recording are shifted by ~{sh:.1f} px against the simulation" if sh else ""
        return (f"the recorded panel pose is off by about {t:.1f} cm and {r:.2f}°{extra}; {gain}")
    return gain


def _start_values(effect: str, sig, prox, camera=None) -> dict:
    """Effect start values for the refit from signature and proxy estimates (physical terms)."""
    s = sig.hint if sig is not None else {}
    p = prox.params if prox is not None else {}
    if effect == "vignetting":
        if p and camera is not None:
            # proxy: exp(k1 t^2 + k2 t^4), t = tan of the field angle; effect: 1 + k1 rho^2 + k2 rho^4 with rho
            # the radius over the image half-diagonal: match value and curvature at the corner (first order)
            hd2 = ((camera.width / 2) ** 2 + (camera.height / 2) ** 2) / (camera.fx * camera.fy)
            k1, k2 = p.get("k1", 0.0) * hd2, p.get("k2", 0.0) * hd2 * hd2
            corner = math.exp(k1 + k2)
            mid = math.exp(k1 * 0.25 + k2 * 0.0625)
            # solve 1 + K1 + K2 = corner, 1 + K1/4 + K2/16 = mid
            A = np.array([[1.0, 1.0], [0.25, 0.0625]])
            K = np.linalg.solve(A, [corner - 1, mid - 1])
            return {"k1": float(np.clip(K[0], -1.2, 0.5)), "k2": float(np.clip(K[1], -0.6, 0.6)),
                    "cx": float(np.clip(p.get("cx", 0) * camera.fx / math.hypot(camera.width / 2, camera.height / 2), -0.2, 0.2)),
                    "cy": float(np.clip(p.get("cy", 0) * camera.fy / math.hypot(camera.width / 2, camera.height / 2), -0.2, 0.2))}
        return {"k1": -0.2}
    if effect == "artificial_light":
        if p:
            return {"offset_x": float(np.clip(p["offset_x"], 0.05, 1.5)), "offset_y": float(p["offset_y"]),
                    "half_angle": float(p["half_angle"]), "balance": float(p["balance"]),
                    "fill": float(np.clip(p["fill"], 0.0, 0.95)), "veil": 0.002}
        return {"fill": 0.8}
    if effect == "forward_scatter":
        if p and p.get("strength", 0) > 0.01:
            return {"strength": float(np.clip(p["strength"], 0.02, 1.5)), "width": float(np.clip(p["width_mrad_per_m"], 1, 40)),
                    "tail": 0.3}
        return {"strength": 0.1, "width": 6.0, "tail": 0.3}
    if effect == "backscatter_coefficient":
        if p:
            return {"ratio_r": p["ratio_r"], "ratio_g": p["ratio_g"], "ratio_b": p["ratio_b"], "decay": 0.2}
        return {}
    if effect == "camera_response":
        return {"gamma": 1.1, "black": 0.01}
    if effect == "sensor_noise":
        shot = s.get("shot_gain_dn") or 0.05
        sd = s.get("sigma_dn") or 1.0
        lag = s.get("lag_ratio") or 1.0
        return {"shot": float(np.clip(shot, 0.0, 1.0)), "read": float(np.clip(sd * 0.7, 0.2, 5.0)),
                "corr": float(np.clip((1 - lag) * 4.0, 0.0, 2.0)), "fpn": 0.002}
    if effect == "marine_snow":
        return {"density": 80.0, "brightness": 0.6, "size": 2.0}
    if effect == "unmodeled_geometry":
        return {"floor_y": -0.9, "albedo": 0.8, "contrast": 0.6}
    if effect == "pose_error":
        return _pose_hint(s.get("motion") or [])
    return {}


def _pose_hint(motion, sign: float = 1.0) -> dict:
    """Pose correction from per-frame image motion of the object (ECC: shift dx, dy and rotation, pixels):
    for a bias ``X_true = R X_rec + t`` a point near the axis at range z moves by about
    ``du = fx (ry + tx / z)``, ``dv = fy (-rx + ty / z)``, and the image turns by ``rz``; least squares over
    the frames (ranges differ, which separates rotation from translation). ``sign`` flips the direction
    (the alignment's convention), both are tried by the refit."""
    if len(motion) < 2:
        return {}
    z = np.array([m[0] for m in motion])
    du = np.array([m[1] / m[4] for m in motion]) * sign
    dv = np.array([m[2] / m[5] for m in motion]) * sign
    ang = np.array([m[3] for m in motion]) * sign
    A = np.stack([np.ones_like(z), 1.0 / z], 1)
    (ry, tx), *_ = np.linalg.lstsq(A, du, rcond=None)
    (mrx, ty), *_ = np.linalg.lstsq(A, dv, rcond=None)
    clip = lambda v, b: float(np.clip(v, -b, b))
    return {"tx": clip(tx, 0.15), "ty": clip(ty, 0.15), "rx": clip(-mrx, 0.06), "ry": clip(ry, 0.06),
            "rz": clip(float(np.median(ang)), 0.06)}


def _sigma0(effect: str, free) -> np.ndarray:
    """Initial CMA-ES steps (fraction of each range) for base then effect parameters."""
    base = BASE_SIGMA0 * 1.5
    eff = {"pose_error": 0.03, "artificial_light": 0.12, "unmodeled_geometry": 0.12}.get(effect, 0.1)
    return np.concatenate([base, np.full(len(free), eff)])


def _particle_blocks(ctx, sigs: dict, factor: int):
    """Per frame, the low-resolution pixels (``factor`` blocks) that hold a particle of the recording, when
    the marine snow signature found particles (else None: the proxies see every pixel)."""
    from .residuals import box_down
    from .signatures import particle_masks

    snow = sigs.get("marine_snow")
    if snow is None or not snow.judged or snow.score < 1.0:
        return None
    return [box_down(m, factor) > 0 for m in particle_masks(ctx)]


def diagnose_frames(frames: list, fog: str = "exp2", seed: int = 0, max_candidates: int = 3,
                    max_iter: int = 30, popsize: int = 12, progress: Optional[Callable[[str], None]] = None,
                    interrupt: Optional[Callable] = None, effects_allowed=None, source: str = "") -> Diagnosis:
    """Diagnose already loaded frames (:func:`uw_sil.fit.residuals.load_frames`); see the module docstring."""
    from ..sim.effects import EFFECTS, get_effect
    from ..sim.params import ParamSpace
    from .backward import linear_start
    from .screening import screen_proxies
    from .signatures import SignatureContext, run_signatures

    say = progress or (lambda msg: None)
    t_all = time.perf_counter()
    timing = {}
    if len(frames) < 3:
        raise DiagnosisError(f"need at least 3 frames that show the scene model, got {len(frames)}")
    fit_f, held_f = split_frames(frames)
    W = frames[0].image.shape[1]
    f_hi = reduction_factor(W, 320)
    f_lo = max(f_hi, reduction_factor(W, 160))
    R_hi = {id(f): reduce_frame(f, f_hi) for f in frames}
    R_lo = {id(f): reduce_frame(f, f_lo) for f in frames}
    rfit, rheld = [R_hi[id(f)] for f in fit_f], [R_hi[id(f)] for f in held_f]
    nfit, nheld = noise_sigmas(rfit), noise_sigmas(rheld)

    # ---------------------------------------------------------------- base fit (+ a second one for the noise)
    t0 = time.perf_counter()
    say(f"base fit on {len(fit_f)} frames ({rfit[0].shape[1]}x{rfit[0].shape[0]}), "
        f"{len(held_f)} held out")
    x_lin = linear_start([_ls_frame(r) for r in rfit], ParamSpace("rgb"), fog=fog)
    base_model = BaseModel(rfit, fog)
    base_fit = fit_model(base_model, rfit, nfit, x_lin, sigma0=BASE_SIGMA0, seed=seed, max_iter=max_iter,
                         popsize=popsize, interrupt=interrupt)
    with FrameObjective(rheld, BaseModel(rheld, fog), nheld, seed=seed) as oh:
        base_held_pf = oh.per_frame(base_fit.x[None])[0]
    timing["base_fit_s"] = time.perf_counter() - t0

    # ---------------------------------------------------------------- run-to-run noise of the fit
    t0 = time.perf_counter()
    say("second base fit (other seed): the fit's run-to-run noise")
    base_fit2 = fit_model(base_model, rfit, nfit, x_lin, sigma0=BASE_SIGMA0, seed=seed + 1, max_iter=max_iter,
                          popsize=popsize, interrupt=interrupt)
    with FrameObjective(rheld, BaseModel(rheld, fog), nheld, seed=seed) as oh:
        base2_held_pf = oh.per_frame(base_fit2.x[None])[0]
    opt_noise = abs(float(base2_held_pf.mean() - base_held_pf.mean()))
    # the reference is the better of the two base fits on the held-out frames (a candidate must beat the
    # base model as well as the optimizer can fit it); candidates start from the better one on the fit frames
    if base_fit2.theta_train > base_fit.theta_train:
        base_fit, base_fit2 = base_fit2, base_fit
        base_held_pf, base2_held_pf = base2_held_pf, base_held_pf
    ref_held_pf = base_held_pf if base_held_pf.mean() >= base2_held_pf.mean() else base2_held_pf
    timing["noise_fit_s"] = time.perf_counter() - t0

    # ---------------------------------------------------------------- locate + signatures
    t0 = time.perf_counter()
    say("locating the mismatch and testing signatures")
    rall = [R_hi[id(f)] for f in frames]
    sims = [base_sim(rf, base_fit.x, fog) for rf in rall]
    nall = noise_sigmas(rall)
    res = residual_maps(rall, sims)
    mismatch = locate(rall, res, nall)
    ctx = SignatureContext(rall, sims, nall, base_fit.x, fog)
    sigs = run_signatures(ctx)
    rlo_all = [R_lo[id(f)] for f in frames]
    prox = screen_proxies(rlo_all, base_fit.x, noise_sigmas(rlo_all), fog=fog,
                          exclude=_particle_blocks(ctx, sigs, f_lo))
    timing["signatures_s"] = time.perf_counter() - t0

    allowed = [e for e in EFFECTS if effects_allowed is None or e in effects_allowed]
    scores = {e: _screen_score(e, sigs, prox) for e in allowed}
    ranked = sorted(allowed, key=lambda e: -scores[e])
    cands = [e for e in ranked if scores[e] >= 1.0][:max_candidates]

    # ---------------------------------------------------------------- candidate refits
    candidates, fits = [], {}
    base_params = BaseModel(rheld, fog).params_of(base_fit.x)
    t0 = time.perf_counter()
    for eff in cands:
        say(f"refitting base + {eff}")
        if eff == "marine_snow":
            fits[eff] = _snow_refit(R_hi, fit_f, held_f, base_fit.x, fog, seed)
        elif eff == "sensor_noise":
            fits[eff] = _noise_refit(fit_f, held_f, base_fit.x, sigs.get(eff), fog, seed, ref_held_pf,
                                     base_fit.theta_train)
        elif eff == "pose_error":
            fits[eff] = _pose_refit(R_hi, fit_f, held_f, base_fit.x, sigs.get(eff), fog, seed)
        else:
            fits[eff] = _refit([eff], R_hi, R_lo, fit_f, held_f, base_fit.x, sigs, prox, fog, seed, max_iter,
                               popsize, interrupt)
    timing["refits_s"] = time.perf_counter() - t0

    def margin_for(d_pf):
        return max(MIN_MARGIN, 2.0 * _bootstrap_se(d_pf, seed=seed))

    def candidate_entry(eff, r, m):
        """The JSON candidate of a single-effect refit ``r`` with its noise margin ``m``."""
        entry = {"effect": eff, "theta_train": r["theta_train"], "theta_heldout": float(r["held_pf"].mean()),
                 "delta_heldout": float((r["held_pf"] - ref_held_pf).mean()),
                 "params": _effect_flat(r["params"], [eff]), "margin": m, "screen_score": scores[eff]}
        if "statistic" in r:
            entry["heldout_statistic"] = r["statistic"]
        return entry

    def stat_rank(e):
        """Rank of an effect accepted on its held-out statistic: how clearly it improved, and its signature."""
        st = fits[e]["statistic"]
        return 0.4 * min(1.0, st["improvement"] / max(3 * st["margin"], 1e-9)) + 0.6 * min(1.0, scores[e] / 10.0)

    b_held = float(ref_held_pf.mean())
    accepted, stat_accepted = [], []
    for eff in cands:
        r = fits[eff]
        d_pf = r["held_pf"] - ref_held_pf
        m = margin_for(d_pf)
        r["margin"] = m
        candidates.append(candidate_entry(eff, r, m))
        if eff in STATISTICAL:
            # random effects (particles, noise at random places) cannot be matched pixel by pixel: judged by how
            # well the fitted model reproduces the held-out frames' statistic (θ is reported); pose error also
            # must not lower θ
            st = r["statistic"]
            theta_ok = eff in ("marine_snow", "sensor_noise") or d_pf.mean() > -m
            if (st["improvement"] > st["margin"] and theta_ok) or (eff == "pose_error" and d_pf.mean() > m):
                stat_accepted.append(eff)
        elif d_pf.mean() > m:
            accepted.append(eff)
    # which accepted effect leads: its held-out gain relative to the best gain, and how specific and strong
    # its residual signature is (a trial-level pose correction cannot undo per-frame pose jitter, which a
    # blur then partly hides: the edge-shift signature still says which physics it is)
    gains = {e: float(fits[e]["held_pf"].mean() - b_held) for e in accepted}
    gmax = max(gains.values()) if gains else 1.0
    rank = {e: 0.4 * gains[e] / gmax + 0.6 * min(1.0, scores[e] / 10.0) for e in accepted}
    for e in stat_accepted:
        rank[e] = stat_rank(e)
    accepted.sort(key=lambda e: -rank[e])
    if len(accepted) >= 2:
        # the held-out frames have the last word: a lower-ranked effect that beats the leading one on them by
        # more than its noise margin leads (a signature alone must not keep a clearly worse model)
        held = {e: float(fits[e]["held_pf"].mean()) for e in accepted}
        best = max(accepted, key=held.get)
        if held[best] - held[accepted[0]] > fits[best]["margin"]:
            accepted.remove(best)
            accepted.insert(0, best)
    final_effects = accepted[:1]
    if len(accepted) >= 2:
        pair = accepted[:2]
        say(f"refitting base + {' + '.join(pair)}")
        t0 = time.perf_counter()
        first = fits[pair[0]]
        fp = _refit(pair, R_hi, R_lo, fit_f, held_f, first["x"][:7], sigs, prox, fog, seed, max_iter, popsize,
                    interrupt, starts={e: fits[e]["params"]["effects"][e] for e in pair},
                    keep={pair[0]: first["params"]["effects"][pair[0]]})
        timing["pair_refit_s"] = time.perf_counter() - t0
        fits["+".join(pair)] = fp
        best1 = first["held_pf"]
        d_pair = fp["held_pf"] - best1
        m2 = margin_for(d_pair)
        candidates.append({"effect": "+".join(pair), "theta_train": fp["theta_train"],
                           "theta_heldout": float(fp["held_pf"].mean()),
                           "delta_heldout": float((fp["held_pf"] - ref_held_pf).mean()),
                           "params": _effect_flat(fp["params"], pair), "margin": m2, "screen_score": None})
        if d_pair.mean() > m2:
            final_effects = pair

    verdict = []
    final_key = "+".join(final_effects) if final_effects else None
    final_fit = fits.get(final_key) if final_key else None
    for eff in final_effects:
        single = fits[eff]
        d = float(single["held_pf"].mean() - b_held)
        m = single["margin"]
        # confidence: the ranking score, scaled down when the held-out gain is within 3 margins
        conf = float(np.clip((0.4 + 0.6 * rank[eff]) * min(1.0, d / (3 * m)), 0.05, 0.99))
        src = final_fit if final_fit is not None else single
        verdict.append({"effect": eff, "confidence": conf,
                        "explanation": _explain(eff, src["params"], b_held, float(src["held_pf"].mean()),
                                                sigs.get(eff)),
                        "params": _effect_flat(src["params"], [eff])})
    if final_effects and "sensor_noise" in stat_accepted:
        lead_geo = [e for e in final_effects if get_effect(e).stage == "geometry"]
        if lead_geo:
            # the leading effect puts surfaces where the base model saw open water (a seafloor): the noise is
            # judged again with those pixels left out of its statistics (their texture is not noise)
            say(f"judging sensor_noise again without the surfaces {' + '.join(lead_geo)} adds")
            src = final_fit if final_fit is not None else fits[final_effects[0]]
            extra = {id(f): _added_surface(f, {e: src["params"]["effects"][e] for e in lead_geo}) for f in frames}
            r = fits["sensor_noise"] = _noise_refit(fit_f, held_f, base_fit.x, sigs.get("sensor_noise"), fog, seed,
                                                    ref_held_pf, base_fit.theta_train, exclude=extra)
            r["margin"] = margin_for(r["held_pf"] - ref_held_pf)
            st = r["statistic"]
            k = next(i for i, c in enumerate(candidates) if c["effect"] == "sensor_noise")
            candidates[k] = {**candidate_entry("sensor_noise", r, r["margin"]), "rejudged_without": lead_geo}
            if st["improvement"] > st["margin"]:
                rank["sensor_noise"] = stat_rank("sensor_noise")
            else:
                stat_accepted.remove("sensor_noise")
    if final_effects:
        # next to an effect that changes the expected image, a noise model is kept only if it does not lower
        # held-out θ (the other effect changes the signal, hence the intensity dependence of the noise)
        stat_accepted = [e for e in stat_accepted if e != "sensor_noise" or fits[e]["held_pf"].mean() - b_held
                         > -fits[e]["margin"]]
    stat_accepted.sort(key=lambda e: -rank[e])
    for eff in stat_accepted[:max(0, 2 - len(final_effects))]:
        r = fits[eff]
        st = r["statistic"]
        strength = st["improvement"] / (3 * st["margin"])
        if eff == "pose_error":
            strength = max(strength, float(r["held_pf"].mean() - b_held) / (3 * r["margin"]))
        conf = float(np.clip((0.4 + 0.6 * rank[eff]) * min(1.0, strength), 0.05, 0.99))
        verdict.append({"effect": eff, "confidence": conf,
                        "explanation": _explain(eff, r["params"], b_held, float(r["held_pf"].mean()), sigs.get(eff),
                                                statistic=st),
                        "params": _effect_flat(r["params"], [eff])})
        final_effects = list(final_effects) + [eff]
    verdict.sort(key=lambda v: -v["confidence"])
    final_params = final_fit["params"] if final_fit is not None else base_params
    final_theta = float(final_fit["held_pf"].mean()) if final_fit is not None else b_held
    stat_in = [e for e in final_effects if e in STATISTICAL]
    if stat_in:
        final_params = {"base": dict(final_params["base"]), "effects": dict(final_params["effects"])}
        for e in stat_in:
            final_params["effects"][e] = fits[e]["params"]["effects"][e]
        if final_fit is None:
            final_theta = float(np.mean([fits[e]["held_pf"].mean() for e in stat_in]))
    timing["total_s"] = time.perf_counter() - t_all
    not_judged = [{"effect": e, "reason": s.reason} for e, s in sigs.items() if not s.judged]
    diag = Diagnosis(
        verdict=verdict, candidates=candidates,
        base={"theta_train": float(base_fit.theta_train), "theta_heldout": b_held,
              "params": dict(base_params["base"])},
        final={"theta_heldout": final_theta, "effects": list(final_effects), "params": _flat(final_params)},
        mismatch=mismatch,
        signatures={e: {**sigs[e].to_dict(), "screen_score": scores.get(e),
                        "explained_share": (prox[e].explained if e in prox else None)} for e in sigs},
        noise={"optimizer_heldout_theta": opt_noise, "margin": margin_for(np.zeros(len(held_f))),
               "camera_noise_dn": [list(map(float, n)) for n in nall],
               "camera_noise_dn_full_resolution": _full_res_noise(frames),
               "base_refit_theta_heldout": float(base2_held_pf.mean())},
        frames=[{"index": f.index, "role": f.role, "range_m": f.range_median, "coverage": f.coverage}
                for f in sorted(frames, key=lambda f: f.index)],
        timing=timing, final_params=final_params, not_judged=not_judged, source=source,
        figures={"rframes": rall, "sims": sims, "res": res, "sigs": sigs, "prox": prox, "fits": fits,
                 "base_x": base_fit.x, "fog": fog, "held": [R_hi[id(f)] for f in held_f],
                 "base_held_pf": ref_held_pf,
                 "final_key": final_key if final_key in fits else (final_effects[0] if final_effects else None)})
    return diag


def _refit(effects, R_hi, R_lo, fit_f, held_f, base_x, sigs, prox, fog, seed, max_iter, popsize, interrupt,
           starts=None, keep=None) -> dict:
    """Fit base + ``effects`` on the fit frames; θ per held-out frame at the high resolution."""
    from ..sim.effects import get_effect

    res_class = "high" if any(FIT_SETTINGS[e]["res"] == "high" for e in effects) else "low"
    R = R_hi if res_class == "high" else R_lo
    rfit = [R[id(f)] for f in fit_f]
    model = EffectModel(rfit, effects, fog=fog, seed=seed)
    start = {e: (starts or {}).get(e) or _start_values(e, sigs.get(e), prox.get(e), rfit[0].frame.camera)
             for e in effects}
    noise = noise_sigmas(rfit)
    x_id = model.x0(base_x)
    x_hint = model.x0(base_x, start)
    starts_x = [x_id, x_hint]
    if keep:
        # a pair starts from the leading effect's own fit with the other effect absent (never worse than it)
        starts_x.append(model.x0(base_x, keep))
    if effects == ["pose_error"] and sigs.get("pose_error") is not None:
        starts_x.append(model.x0(base_x, {"pose_error": _pose_hint(sigs["pose_error"].hint.get("motion") or [], -1.0)}))
    if not any(get_effect(e).random_per_frame and e != "pose_error" for e in effects):
        # least-squares fit of the same model on the low-resolution fit frames: a start near the optimum (for a
        # pair from both effects' own fits: each alone has absorbed part of the other, jointly they separate)
        lmodel = EffectModel([R_lo[id(f)] for f in fit_f], effects, fog=fog, seed=seed)
        alts = ALT_STARTS.get(effects[0]) if len(effects) == 1 and not starts else None
        # effects with far-apart plausible configurations: least squares from each of them, and θ below picks
        # (picking one raw start by its squared error first lost a foreign lamp rig: a start with the right
        # geometry but the wrong brightness looked worse than a wrong geometry)
        for xs in [x_hint] + [lmodel.x0(base_x, {effects[0]: a}) for a in alts or []]:
            starts_x.append(_ls_fit(lmodel, xs))
    # start from the best of "effect absent" (its identity values), the signature estimate and the LS fit
    with FrameObjective(rfit, model, noise, seed=seed) as of:
        th = of(np.stack(starts_x))
    x0 = starts_x[int(np.nanargmax(th))]
    sig0 = np.concatenate([_sigma0(effects[0], [])[:7]] + [_sigma0(e, model.free[e])[7:] for e in effects])
    fit = fit_model(model, rfit, noise, x0, sigma0=sig0, seed=seed, max_iter=max_iter, popsize=popsize,
                    interrupt=interrupt, patience=8)
    rheld = [R_hi[id(f)] for f in held_f]
    hmodel = EffectModel(rheld, effects, fog=fog, seed=seed + 50)
    with FrameObjective(rheld, hmodel, noise_sigmas(rheld), seed=seed) as oh:
        held_pf = oh.per_frame(fit.x[None])[0]
    return {"x": fit.x, "theta_train": float(fit.theta_train), "held_pf": held_pf, "params": model.params_of(fit.x),
            "model_effects": list(effects), "fit": fit, "res": res_class}


def _snow_refit(R_hi, fit_f, held_f, base_x, fog, seed) -> dict:
    """Marine snow, fitted and judged by the density of small bright specks (new in every frame).

    Density and brightness of the particles are chosen on the fit frames so that simulated frames (base
    model + snow + the estimated camera noise) show as many bright specks per megapixel as the recording
    (:func:`uw_sil.fit.signatures.speck_density`); on the held-out frames the same statistic of the
    recording is compared with the base model's and the candidate's (log densities), and the improvement
    is bootstrapped over frames. θ is also reported (it cannot rise: particles are at random places)."""
    from ..sim.noise import NoiseField
    from .signatures import luminance, speck_density

    def frames_stats(rfs, x_list, eff_model):
        """per frame: real density, and the simulated density for each parameter vector in x_list."""
        noise = noise_sigmas(rfs)
        out_real, out_sim = [], []
        for k, rf in enumerate(rfs):
            S = luminance(255.0 * base_sim(rf, base_x, fog))
            hit = rf.cover > 0
            out_real.append(speck_density(luminance(rf.image), S, hit)[0])
            nf = NoiseField(rf.shape + (3,), noise[k], seed=seed + 31 * k)
            sims = eff_model.simulate(k, np.stack(x_list)) * 255.0
            row = []
            for img in sims:
                nf.apply(img)
                row.append(speck_density(luminance(img), S, hit)[0])
            out_sim.append(row)
        return np.array(out_real), np.array(out_sim)

    rfit = [R_hi[id(f)] for f in fit_f]
    rheld = [R_hi[id(f)] for f in held_f]
    model = EffectModel(rfit, ["marine_snow"], fog=fog, seed=seed)
    grid = [(d, b) for d in (0.0, 15.0, 40.0, 100.0, 250.0, 600.0, 1500.0) for b in (0.3, 0.6, 1.2)]
    xs = [model.x0(base_x, {"marine_snow": {"density": d, "brightness": b, "size": 2.0}}) for d, b in grid]
    real, sim = frames_stats(rfit, xs, model)
    err = np.abs(np.log1p(sim) - np.log1p(real)[:, None]).mean(axis=0)
    j = int(np.argmin(err))
    x = xs[j]
    hmodel = EffectModel(rheld, ["marine_snow"], fog=fog, seed=seed + 50)
    x_base = hmodel.x0(base_x, {"marine_snow": {"density": 0.0}})
    real_h, sim_h = frames_stats(rheld, [x_base, x], hmodel)
    e_base = np.abs(np.log1p(sim_h[:, 0]) - np.log1p(real_h))
    e_cand = np.abs(np.log1p(sim_h[:, 1]) - np.log1p(real_h))
    imp = e_base - e_cand
    with FrameObjective(rheld, hmodel, noise_sigmas(rheld), seed=seed) as oh:
        held_pf = oh.per_frame(x[None])[0]
    with FrameObjective(rfit, model, noise_sigmas(rfit), seed=seed) as of:
        th_train = float(of(x[None])[0])
    stat = {"name": "density of bright specks per megapixel", "real": float(np.mean(real_h)),
            "base_sim": float(np.mean(sim_h[:, 0])), "candidate_sim": float(np.mean(sim_h[:, 1])),
            "improvement": float(imp.mean()), "margin": max(0.15, 2.0 * _bootstrap_se(imp, seed=seed)),
            "per_frame_improvement": imp.tolist()}
    return {"x": x, "theta_train": th_train, "held_pf": held_pf, "params": model.params_of(x),
            "model_effects": ["marine_snow"], "fit": None, "res": "high", "statistic": stat}


def _noise_vector(st: dict) -> np.ndarray:
    """Comparable noise statistics: log water sigma, lag ratio, log fixed-pattern ratios, log object sigma."""
    so = st["sigma_object"]
    return np.array([math.log(max(st["sigma_water"], 1e-3)), 5.0 * st["lag_ratio"],
                     0.5 * math.log(max(st["col_ratio"], 1e-3)), 0.5 * math.log(max(st["row_ratio"], 1e-3)),
                     math.log(max(so, 1e-3)) if so is not None else np.nan])


def _frame_geometry(frame, geo_effects: dict) -> tuple:
    """(as rendered, with the geometry effects) full-resolution geometry of a frame: geometry-stage effects
    (a seafloor, a pose correction) applied to its render, as the simulator applies them before shading."""
    from ..sim.effects import get_effect
    from ..sim.model import Geometry

    rr = frame.render
    geom = Geometry(frame.camera, rr.rgb, rr.depth, rr.range, rr.labels, rr.part_ids, pose=frame.pose)
    t = SimpleNamespace(geom=geom)
    for name, values in geo_effects.items():
        eff = get_effect(name)
        eff.apply(t, eff.values(values), None)
    return geom, t.geom


def _added_surface(frame, geo_effects: dict) -> np.ndarray:
    """Pixels (full resolution, grown by the 24 px margin of the noise statistics) where geometry effects
    with these values add surfaces to what the frame's render saw."""
    from .residuals import dilate

    before, after = _frame_geometry(frame, geo_effects)
    return dilate(after.hit & ~before.hit, 24)


def _corrected_frame(frame, geo_effects: dict):
    """The frame with its render replaced by the full-resolution geometry the effects give (for a pose
    correction: the render warped to the corrected pose at full resolution, then reduced like any frame;
    warping the reduced geometry instead interpolates away a sub-pixel shift's worth of detail)."""
    import dataclasses

    from ..sim.render import RenderResult

    _, g = _frame_geometry(frame, geo_effects)
    rr = RenderResult(rgb=g.rgb, depth=g.depth, range=g.range, labels=g.labels, part_ids=g.part_ids)
    return dataclasses.replace(frame, render=rr, coverage=float(np.mean(g.hit)))


def _noise_refit(fit_f, held_f, base_x, sig, fog, seed, ref_held_pf, base_theta_train,
                 exclude: Optional[dict] = None) -> dict:
    """Sensor noise, fitted and judged at full resolution by noise statistics (it is new in every frame).

    The effect's parameters (shot gain, read noise, correlation, fixed patterns) are chosen by CMA-ES on the
    fit frames so that simulated frames reproduce the recording's noise statistics
    (:func:`uw_sil.fit.signatures.noise_statistics`: water sigma, lag-1/lag-3 ratio, column and row
    patterns, sigma on flat object parts; the recording's particles and, with ``exclude`` ({id(frame): mask}),
    surfaces another effect adds are left out). On held-out frames the distance between the recording's
    statistics and the simulation's is compared for the base model (constant Gaussian noise estimated on
    the water, as the backward fit adds) and the candidate. θ is measured on the held-out frames at full
    resolution for both; the candidate's θ is reported as the base reference plus that difference."""
    from ..sim.noise import NoiseField, estimate_noise_sigma
    from ..sim.optics import degrade
    from .optimize import optimize
    from .signatures import luminance, noise_statistics, particle_exclusion

    def prep(frames):
        """per frame: noise-free simulation S, the recording's statistics, and the pixels every statistic of
        that frame uses (hit: the model; excl: the recording's particles, left out of real and simulated)."""
        rfs = [reduce_frame(f, 1) for f in frames]
        S, real, hits = [], [], []
        for f in frames:
            rr = f.render
            p = np.clip(base_x, 0, None)
            p[3:6] = np.clip(p[3:6], 0, 1)
            S.append(degrade(rr.rgb, rr.range, rr.depth, p, fog=fog) * 255.0)
            hit = np.isfinite(rr.range)
            Y, Ys = luminance(f.image.astype(np.float32)), luminance(S[-1])
            excl = particle_exclusion(Y, Ys, hit)
            more = (exclude or {}).get(id(f))
            if more is not None:
                excl = more if excl is None else excl | more
            hits.append((hit, excl))
            real.append(noise_statistics(Y, Ys, hit, excl))
        return rfs, S, real, hits

    def stats_of(img255, S, pix):
        np.clip(img255, 0, 255, out=img255)
        np.rint(img255, out=img255)
        return noise_statistics(luminance(img255), luminance(S), *pix)

    def dist(a, b):
        if a is None or b is None:
            return np.nan
        va, vb = _noise_vector(a), _noise_vector(b)
        ok = np.isfinite(va) & np.isfinite(vb)
        return float(np.abs(va[ok] - vb[ok]).sum())

    rfit, Sfit, real_fit, hfit = prep(fit_f)
    rheld, Sheld, real_held, hheld = prep(held_f)
    model = EffectModel(rfit, ["sensor_noise"], fog=fog, seed=seed)
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

    def objective(U):
        X = np.repeat(x0[None], len(U), axis=0)
        X[:, free] = U
        out = np.zeros(len(U))
        for k in range(len(rfit)):
            imgs = model.simulate(k, X) * 255.0
            for j in range(len(U)):
                d = dist(real_fit[k], stats_of(imgs[j], Sfit[k], hfit[k]))
                out[j] += 0.0 if np.isnan(d) else d
        return -out

    res = optimize(objective, lo[free], hi[free], method="cmaes", seed=seed, max_iter=8, swarm_size=6,
                   x0=x0[free], sigma0=0.15)
    x = x0.copy()
    x[free] = res.x_best
    # held-out: statistics distance, base (estimated constant Gaussian noise) vs candidate; θ at full resolution
    from ..metrics.theta import ThetaReference

    def compare(frames, S_list, real, hits, mdl):
        eb, ec, tb, tc = [], [], [], []
        for k, f in enumerate(frames):
            water = ~np.isfinite(f.render.range)
            try:
                sg = estimate_noise_sigma(f.image, water)
            except ValueError:
                sg = estimate_noise_sigma(f.image)
            base_img = S_list[k].astype(np.float32).copy()
            NoiseField(base_img.shape, sg, seed=seed + 17 * k).apply(base_img)
            cand = mdl.simulate(k, x[None])[0] * 255.0
            np.clip(cand, 0, 255, out=cand)
            np.rint(cand, out=cand)
            eb.append(dist(real[k], noise_statistics(luminance(base_img), luminance(S_list[k]), *hits[k])))
            ec.append(dist(real[k], noise_statistics(luminance(cand), luminance(S_list[k]), *hits[k])))
            hit = hits[k][0]
            hm = [hit, ~hit] if hit.any() and not hit.all() else None
            ref = ThetaReference(f.image, hist_mask=hm)
            tb.append(float(ref.score(base_img)[0]))
            tc.append(float(ref.score(cand)[0]))
        return eb, ec, np.array(tb), np.array(tc)

    hmodel = EffectModel(rheld, ["sensor_noise"], fog=fog, seed=seed + 50)
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
            "margin": max(0.05, 2.0 * _bootstrap_se(imp, seed=seed)) if imp.size else float("inf"),
            "per_frame_improvement": imp.tolist(), "theta_full_res_base": tb.tolist(),
            "theta_full_res_candidate": tc.tolist()}
    return {"x": x, "theta_train": float(base_theta_train + np.mean(tcf - tbf)), "held_pf": held_pf,
            "params": model.params_of(x), "model_effects": ["sensor_noise"], "fit": None, "res": "full",
            "statistic": stat}


def _pose_refit(R_hi, fit_f, held_f, base_x, sig, fog, seed) -> dict:
    """Pose error, fitted by least squares on the fit frames from the edge shifts of the signature test
    (:func:`_pose_hint` of the fit frames only, both directions tried) and judged by the residual on the
    held-out frames (mean squared residual real - sim, noise-free simulation; relative improvement per
    frame, bootstrapped over frames). θ on the held-out frames is also reported (it must not drop)."""
    rfit = [R_hi[id(f)] for f in fit_f]
    rheld = [R_hi[id(f)] for f in held_f]
    model = EffectModel(rfit, ["pose_error"], fog=fog, seed=seed)
    fit_idx = {f.index for f in fit_f}
    motion = [m for m in ((sig.hint if sig is not None else {}).get("motion") or []) if m[6] in fit_idx]

    def mse(mdl, rfs, X):
        out = np.zeros((len(X), len(rfs)))
        for k, rf in enumerate(rfs):
            sims = mdl.simulate(k, X) * 255.0
            out[:, k] = ((sims - rf.image[None]) ** 2).mean(axis=(1, 2, 3))
        return out

    xs = [model.x0(base_x)] + [model.x0(base_x, {"pose_error": _pose_hint(motion, sg)}) for sg in (1.0, -1.0)]
    e = mse(model, rfit, np.stack(xs)).mean(axis=1)
    x = _ls_fit(model, xs[int(np.argmin(e))], stride=1, max_nfev=10)
    hmodel = EffectModel(rheld, ["pose_error"], fog=fog, seed=seed + 50)
    eh = mse(hmodel, rheld, np.stack([hmodel.x0(base_x), x]))
    imp = (eh[0] - eh[1]) / np.maximum(eh[0], 1e-9)
    # held-out θ of the corrected pose: the frames' geometry moved at full resolution and reduced as the base
    # model's frames are, scored with the same objective as the base (the camera noise of the recording)
    corr = {"pose_error": model.params_of(x)["effects"]["pose_error"]}
    rcorr = [reduce_frame(_corrected_frame(f, corr), R_hi[id(f)].factor) for f in held_f]
    with FrameObjective(rcorr, BaseModel(rcorr, fog), noise_sigmas(rheld), seed=seed) as oh:
        held_pf = oh.per_frame(x[None, :7])[0]
    with FrameObjective(rfit, model, noise_sigmas(rfit), seed=seed) as of:
        th_train = float(of(x[None])[0])
    stat = {"name": "mean squared residual (grey levels²)", "real": 0.0, "base_sim": float(eh[0].mean()),
            "candidate_sim": float(eh[1].mean()), "improvement": float(imp.mean()),
            "margin": max(0.02, 2.0 * _bootstrap_se(imp, seed=seed)), "per_frame_improvement": imp.tolist()}
    return {"x": x, "theta_train": th_train, "held_pf": held_pf, "params": model.params_of(x),
            "model_effects": ["pose_error"], "fit": None, "res": "high", "statistic": stat}


def _ls_fit(model: "EffectModel", x0, stride: int = 2, max_nfev: int = 12) -> np.ndarray:
    """Least-squares fit (grey levels, every ``stride``-th pixel) of a candidate model to its frames, from x0."""
    from scipy.optimize import least_squares

    lo, hi = model.bounds()
    x0 = np.clip(np.asarray(x0, float), lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
    reals = [rf.image[stride // 2::stride, stride // 2::stride] for rf in model.rframes]

    def resid(x):
        out = []
        for k, R in enumerate(reals):
            I = model.simulate(k, x[None])[0][stride // 2::stride, stride // 2::stride]
            out.append((I * 255.0 - R).ravel())
        return np.concatenate(out)

    try:
        r = least_squares(resid, x0, bounds=(lo, hi), method="trf", x_scale=np.maximum(hi - lo, 1e-6) * 0.1,
                          diff_step=2e-3, max_nfev=max_nfev, xtol=1e-4, ftol=1e-4)
    except (ValueError, FloatingPointError):
        return x0
    return r.x


def diagnose_bag(bag, k: int = 8, model=None, image_topic: str = "/camera/image_raw", **kw) -> Diagnosis:
    """Read ``k`` frames of a recording and diagnose them (see :func:`diagnose_frames`)."""
    try:
        frames = load_frames(bag, k=k, model=model, image_topic=image_topic)
    except ValueError as e:
        raise DiagnosisError(str(e)) from e
    return diagnose_frames(frames, source=str(bag), **kw)


def write_diagnosis_yaml(path, diag: Diagnosis, node_name: str = "/**", fog: str = "exp2", comment: str = ""):
    """ROS 2 parameters file for ``sim_camera`` with the final (extended) model: base parameters, the
    estimated camera noise, and ``<effect>.<param>`` of the accepted effects (a parameter ``effects``
    lists them)."""
    import yaml

    from .._shared.fileio import write_text_atomic

    p = dict(diag.final_params["base"])
    p["fog_mode"] = fog
    full = diag.noise.get("camera_noise_dn_full_resolution")
    p["noise_sigma"] = float(np.mean(full)) if full else 0.0
    eff = diag.final.get("effects", [])
    if eff:
        p["effects"] = ",".join(eff)
        for n in eff:
            for k, v in diag.final_params["effects"][n].items():
                p[f"{n}.{k}"] = float(v)
    body = {node_name: {"ros__parameters": p}}
    text = "".join(f"# {line}\n" for line in comment.splitlines()) + yaml.safe_dump(body, sort_keys=False)
    return write_text_atomic(path, text)
