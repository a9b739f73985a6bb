"""What every diagnosis plug-in is made of: the shared job, the model selected so far, a refit's result.

A :class:`Judge` owns, for one effect of :mod:`uw_sil.sim.effects`, what the selection loop of
:func:`uw_sil.fit.diagnose.diagnose_frames` needs and must not know itself: which parameters are refitted
and at which resolution, the start values (from the residual signatures and the screening proxies of the
*fit* frames), the refit, the held-out criterion, the plain-language explanation and the physical
plausibility of the fitted values. The loop names no effect.

Two kinds of held-out criterion:

``theta``      the effect changes the expected image: accepted when held-out θ of the model with it beats
               the model without it by more than the noise margin (:func:`margin_for`), or when the
               held-out *residual* evidence does (smooth photometric effects only,
               ``residual_evidence``): the least-squares fit of the model with the effect lowers
               the held-out frames' mean squared residual, frame by frame, relative to the least-squares
               fit of the model without it, pooled over the frames, by more than its own margin
               (:func:`residual_gain`).
               Both are tried for every candidate (the margins are corrected for two tests each). θ, the
               paper's similarity, is built to rank simulations that look alike; it is nearly blind to a
               smooth change of brightness where the recording is dark and noisy (the deep sea lit by the
               vehicle's lamps: θ 0.74-0.81 for any model there), where the residual is the likelihood of
               the recording under Gaussian noise and sees it.
``statistic``  the effect draws new random numbers in every frame (particles, temporal noise): a pixel-wise
               θ cannot rise for them, since simulated particles and noise fall elsewhere than the recorded
               ones; accepted when a held-out *statistic* (speck density, noise level and correlation) moves
               towards the recording's by more than its own bootstrap margin.

The refit of a ``theta`` effect (:func:`theta_refit`) is nested: it fits the current model plus the effect
jointly, from the current optimum with the effect at its neutral values (and from the plug-in's starts), and
never ends below the current model on the fit frames at the comparison resolution (the better of the two is
kept), so a model that contains another cannot lose to it through the optimizer. The other way round, a
round's candidates are compared with the current model refitted with the same budget and starts
(:func:`reference_refit`), not with its optimum as it stands: a candidate's refit goes on optimizing the
current model's own parameters too, and must not be credited with that.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable, Optional

import numpy as np

from ...sim.params import RGB_NAMES
from ..diagfit import (BASE_SIGMA0, FAINT_DN, EffectModel, FrameObjective, ModelFit, fit_model, image_change,
                       ls_fit, noise_sigmas, residual_energy)

__all__ = ["Job", "Current", "Refit", "Judge", "theta_refit", "margin_for", "bootstrap_se", "z_multiple",
           "MIN_MARGIN", "MIN_RESIDUAL_MARGIN", "residual_gain", "residual_improvement", "current_ls"]

#: The words of a doubt about a refitted parameter on a bound of its box (:meth:`Judge.plausibility`); such doubts
#: of one effect count as one in its confidence (:func:`uw_sil.fit.diagnose._confidence`).
ON_BOUND = "sits on its bound"
#: The words of a doubt about refitted parameters the image does not depend on (:meth:`Judge.undetermined`): like a
#: bound, it says how well the values are known, not that the effect is absent or implausible.
NOT_DETERMINED = "not determined by the recording"
#: Smallest held-out θ gain accepted, whatever the bootstrap says (the spread of four frames can be tiny).
#: Measured null: on effect-free controls (bench_concealed.py, two own and two foreign seeds, 2026-11-27) the
#: 28 round-1 refits of the smooth effects (all but compression, particles and noise) gained at most 0.0004
#: held-out θ (mean -0.0003), so this floor is 7x the largest; on a misspecified dive (the physically based
#: lamp-lit ones) wrong effects gain 0.002-0.03, which is what the bootstrap term of :func:`margin_for` has to
#: stop.
MIN_MARGIN = 0.003
#: Smallest mean relative reduction of the held-out mean squared residual accepted (2 %: half the energy
#: change of a 1 % change of the residual's scale, four times its run-to-run spread between least-squares
#: fits from different starts measured on effect-free controls; the bootstrap over four frames can be tiny).
MIN_RESIDUAL_MARGIN = 0.02
#: Run-to-run spread of that reduction between least-squares fits from different starts on effect-free controls
#: (a quarter of :data:`MIN_RESIDUAL_MARGIN`): a smaller reduction is no reduction at all (:meth:`Judge.accept`).
RESIDUAL_SPREAD = MIN_RESIDUAL_MARGIN / 4


def bootstrap_se(d, n: int = 2000, seed: int = 0) -> float:
    """Bootstrap standard error of the mean of per-frame values (frames resampled with replacement)."""
    d = np.asarray(d, float)
    if d.size < 2:
        return float("inf")
    rng = np.random.default_rng(seed)
    means = d[rng.integers(0, d.size, (n, d.size))].mean(axis=1)
    return float(np.std(means))


def z_multiple(m: int, alpha: float = 0.05) -> float:
    """One-sided normal quantile for ``m`` candidates tried at once (Bonferroni: ``alpha / m`` each)."""
    from scipy.stats import norm

    return float(norm.ppf(1.0 - alpha / max(1, int(m))))


def margin_for(gain_pf, m: int = 1, seed: int = 0, floor: float = MIN_MARGIN) -> float:
    """Noise margin a mean held-out gain must beat: ``z(m)`` bootstrap standard errors of the per-frame gains
    (corrected for the ``m`` tests of the round), and at least ``floor`` (:data:`MIN_MARGIN` for θ)."""
    return max(floor, z_multiple(m) * bootstrap_se(gain_pf, seed=seed))


def residual_gain(current: "Current", r: "Refit", m: int = 1, seed: int = 0) -> Optional[tuple]:
    """``(gain, margin)`` of the held-out residual: the relative reduction of the mean squared residual pooled
    over the held-out frames, ``1 - sum E_r / sum E_current`` (the Gaussian likelihood with one noise level:
    a dark far frame, whose residual is tiny, weighs as little as it tells), and its margin: ``z(m)``
    bootstrap standard errors (frames resampled) and at least :data:`MIN_RESIDUAL_MARGIN`. None without a
    least-squares fit."""
    E = r.extra.get("ls_sel_E")
    if E is None or current.ls_sel_E is None:
        return None
    Ec, Er = np.asarray(current.ls_sel_E, float), np.asarray(E, float)
    gain = 1.0 - Er.sum() / max(Ec.sum(), 1e-9)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, Ec.size, (2000, Ec.size))
    boot = 1.0 - Er[idx].sum(axis=1) / np.maximum(Ec[idx].sum(axis=1), 1e-9)
    return float(gain), max(MIN_RESIDUAL_MARGIN, z_multiple(m) * float(np.std(boot)))


def residual_improvement(current: "Current", r: "Refit") -> Optional[np.ndarray]:
    """Per held-out frame, the relative reduction ``1 - E_r / E_current`` of the mean squared residual of the
    least-squares fits (None when the refit has no least-squares fit)."""
    E = r.extra.get("ls_sel_E")
    if E is None or current.ls_sel_E is None:
        return None
    return 1.0 - np.asarray(E, float) / np.maximum(np.asarray(current.ls_sel_E, float), 1e-9)


@dataclass
class Job:
    """What every refit of one diagnosis sees.

    Attributes
    ----------
    fit_f, sel_f : list of DiagFrame
        Fit frames and held-out (selection) frames.
    R_hi, R_lo, R_ls : dict
        ``id(frame) -> ReducedFrame`` at about 320 and 160 px wide, and about 80 px wide for the
        least-squares starts of smooth effects.
    fog, seed, max_iter, popsize, patience, ls_nfev :
        Model fog mode and the optimizer budget every candidate gets (the base fit gets the same).
    sigs, prox : dict
        Residual signatures and screening proxies of the base fit on the *fit* frames only.
    judges : dict
        ``effect -> Judge`` (the registry, so that joint models find their partners' settings).
    exclude : dict
        ``id(frame) -> (H, W) bool`` full-resolution pixels left out of noise statistics (surfaces an
        accepted geometry effect adds).
    after_noise : dict
        ``effect -> values`` of accepted effects the recording passed after the camera noise (the compression): the
        noise plug-in simulates its candidates through them, as the camera's codec took the sensor's noise.
    interrupt : callable or None
        Called between optimizer iterations (raises to stop).
    pool : WorkerPool or None
        The diagnosis's worker processes, for the fits that run in its own process (the round's winner with
        the full budget, the final polish): their θ evaluations are shared out among them (:class:`~uw_sil.fit.diagfit.
        FrameObjective`, the same values). A job sent to a worker goes without it.
    """

    fit_f: list
    sel_f: list
    R_hi: dict
    R_lo: dict
    R_ls: dict
    fog: str
    seed: int
    max_iter: int
    popsize: int
    patience: int
    sigs: dict
    prox: dict
    judges: dict
    ls_nfev: int = 12
    exclude: dict = field(default_factory=dict)
    after_noise: dict = field(default_factory=dict)
    interrupt: Optional[Callable] = None
    pool: Optional[object] = None

    # frames are keyed by id(): pickled (for a worker process) the dicts become lists in the order of
    # fit_f + sel_f, and are keyed again by the unpickled frames; ``interrupt`` and ``pool`` stay in this process
    _BY_FRAME = ("R_hi", "R_lo", "R_ls", "exclude")

    def __getstate__(self):
        state = dict(self.__dict__)
        frames = self.fit_f + self.sel_f
        for k in self._BY_FRAME:
            state[k] = [state[k].get(id(f)) for f in frames]
        state["interrupt"] = None
        state["pool"] = None
        return state

    def __setstate__(self, state):
        frames = state["fit_f"] + state["sel_f"]
        for k in self._BY_FRAME:
            state[k] = {id(f): v for f, v in zip(frames, state[k]) if v is not None}
        self.__dict__.update(state)

    def reduced(self, frames, res: str = "high") -> list:
        R = {"high": self.R_hi, "low": self.R_lo, "ls": self.R_ls}[res]
        return [R[id(f)] for f in frames]

    @property
    def camera(self):
        return self.R_lo[id(self.fit_f[0])].frame.camera

    def frame_theta(self, model: EffectModel, frames, x, seed_offset: int = 0) -> np.ndarray:
        """θ per frame (high resolution) of parameter vectors ``x`` (N, d) of ``model``'s kind on ``frames``:
        the objective every model is compared with (same noise realization for every model)."""
        rf = self.reduced(frames, "high")
        m = model.like(rf, seed=self.seed + seed_offset)
        with FrameObjective(rf, m, noise_sigmas(rf), seed=self.seed, pool=self.pool) as ob:
            return ob.per_frame(np.atleast_2d(x))


@dataclass
class Current:
    """The model selected so far: its deterministic effects (``values`` complete per effect), its 7 base
    parameters, θ on the fit frames and per held-out frame (high resolution), and the vector and model that
    give them. Effects judged by a statistic are not part of it (they cannot be compared by θ)."""

    effects: tuple
    values: dict
    base: np.ndarray
    theta_fit: float
    sel_pf: np.ndarray
    x: Optional[np.ndarray] = None
    model: Optional[EffectModel] = None
    absorbed: dict = field(default_factory=dict)     # geometry corrections applied to the frames themselves
    # the current model's least-squares fit (about 80 px wide): its parameters and per held-out frame its mean
    # squared residual (the other held-out criterion, :func:`residual_improvement`)
    ls_params: Optional[dict] = None
    ls_sel_E: Optional[np.ndarray] = None

    @property
    def name(self) -> str:
        """``base + e1 + ...``: the corrections applied to the frames (``absorbed``) first, then the effects."""
        return " + ".join(("base",) + tuple(self.absorbed) + self.effects)


@dataclass
class Refit:
    """A plug-in's refit of the current model plus its effect.

    ``params`` is ``{"base": {...}, "effects": {name: values}}`` of the whole model; ``sel_pf`` θ per
    held-out frame; ``statistic`` (``kind == "statistic"`` or a supporting statistic) ``{"name", "real",
    "base_sim", "candidate_sim", "improvement", "margin", ...}`` (``base_label``: what ``base_sim`` simulated, when
    not the model without the effect).
    """

    effect: str
    effects: tuple
    x: np.ndarray
    params: dict
    theta_fit: float
    sel_pf: np.ndarray
    model: Optional[EffectModel] = None
    statistic: Optional[dict] = None
    started_at_current: bool = False      # the refit kept the current model's optimum (no improvement found)
    extra: dict = field(default_factory=dict)


class Judge:
    """Base class of the diagnosis plug-ins (one per effect; see the module docstring).

    Attributes
    ----------
    effect : str
        Registry name of the effect in :mod:`uw_sil.sim.effects`.
    free : tuple or None
        Parameters refitted (None: all).
    fixed : dict
        Values of the parameters that are not refitted (over the effect's defaults).
    res : str
        ``"low"`` (about 160 px wide: the effect is smooth) or ``"high"`` (about 320 px).
    kind : str
        ``"theta"`` or ``"statistic"``.
    sigma : float
        Initial CMA-ES step of the effect parameters (fraction of each range).
    alt_starts : tuple of dict
        Physically far-apart configurations also tried as least-squares starts.
    least_squares : bool
        Whether a least-squares fit from the starts is tried before CMA-ES (smooth deterministic effects).
    absorb : bool
        An accepted correction is applied to the frames' geometry for the rest of the selection (pose).
    physical_bounds : tuple
        Parameters whose bounds are physical limits, not a fitter's box (a share of 0 or 1): a fitted value
        there is no reason for doubt.
    saturates : dict
        Parameters whose effect saturates towards one end of their box, by the effect's form (``+1``: the upper
        end, ``-1``: the lower): there a bound need not mean a stretched fit (:meth:`flat_bounds`).
    cost : float
        Time of a first-round refit, seconds on a 640x480 bag (measured; it only orders the refits of a round
        across the worker processes, costliest first).
    """

    effect: str = ""
    free: Optional[tuple] = None
    fixed: dict = {}
    res: str = "low"
    kind: str = "theta"
    sigma: float = 0.1
    alt_starts: tuple = ()
    least_squares: bool = True
    absorb: bool = False
    physical_bounds: tuple = ()
    saturates: dict = {}
    cost: float = 3.0
    # the effect is a smooth change of brightness or colour (no edges of its own), which θ barely sees in dark,
    # noisy frames: the held-out residual may accept it too. Not for blur, geometry or pose, whose edges θ
    # (phase congruency, gradients) sees, and whose least-squares fits also soak up leftovers of other effects
    # (measured: forward scatter "accepted" by the residual, 27 % less, next to lamps on a lamps-only trial)
    residual_evidence: bool = False
    # accepted by the held-out residual, the model adopted is its least-squares fit (the model the evidence is
    # about: a θ refit drifts back to the model without it where θ is blind); False for an effect accepted by the
    # residual only where θ rises as well (:meth:`accept` of the flat port): θ is not blind to it, and it is
    # refitted on θ with the full budget, as a θ acceptance is
    adopts_least_squares: bool = True

    # ------------------------------------------------------------------ settings

    def free_params(self) -> tuple:
        from ...sim.effects import get_effect

        names = get_effect(self.effect).param_names
        return tuple(self.free) if self.free is not None else tuple(n for n in names if n not in self.fixed)

    def neutral(self, values: dict, camera=None) -> bool:
        """Whether these values leave the image as the model without the effect renders it (``camera``: the
        frames' camera, for an effect that can leave an image of that size unchanged away from its defaults)."""
        from ...sim.effects import get_effect

        return bool(get_effect(self.effect).is_identity(values))

    def signature(self, job: Job):
        return job.sigs.get(self.effect)

    def order(self, job: Job) -> float:
        """How strongly the residual signature points at this effect (orders the work; never a veto)."""
        s = self.signature(job)
        return float(s.score) if s is not None and s.judged else 0.0

    def proxy_share(self, job: Job) -> float:
        """The screening proxy's share of the residual it explains, 25 % = 1 (the photometric effects, whose
        residual footprints overlap, are ordered by it)."""
        p = job.prox.get(self.effect)
        return p.explained / 0.25 if p is not None else 0.0

    def start(self, job: Job) -> dict:
        """Start values of the effect's parameters for the refit (physical estimates; {} = defaults)."""
        return {}

    def alt_base(self, job: Job, base: np.ndarray) -> np.ndarray:
        """The base model's parameters (:data:`~uw_sil.sim.params.RGB_NAMES`) that the :attr:`alt_starts` begin
        from, given the current ones (default: those)."""
        return base

    # ------------------------------------------------------------------ refit and criterion

    def refit(self, job: Job, current: Current, x_starts: Optional[list] = None,
              parent: Optional[dict] = None) -> Refit:
        """Refit the current model plus this effect; ``x_starts``: whole parameter vectors of the same model
        to start from too (an earlier, cheaper refit); ``parent``: the ``params`` of this effect's refit of an
        earlier, smaller model (a start too, :func:`theta_refit`)."""
        return theta_refit(job, current, self, x_starts=x_starts, parent=parent)

    def accept(self, r: Refit, current: Current, margin: float, residual: Optional[tuple] = None) -> tuple:
        """``(accepted, strength, criterion)``: held-out θ gain over the current model beyond ``margin`` (for the
        effects whose residual speaks, only where their least-squares fit lowers the held-out residual at all), or
        else (smooth photometric effects) the held-out residual gain beyond its margin, ``residual`` =
        :func:`residual_gain`; strength is the gain in margins (it ranks the accepted candidates of a round)."""
        gain = float(np.mean(r.sel_pf - current.sel_pf))
        # a fit that holds the effect at its neutral values is the model without it (``extra["neutral"]``, and
        # ``"ls_neutral"`` for the least-squares fit): what it gained went to the current model's own parameters
        # Nor is a θ gain taken where the effect's least-squares fit does not lower the held-out residual at all
        # (for the effects whose residual speaks, ``residual_evidence``): θ's region histograms count pixels in
        # bins, and in a dark frame a brightness change far below the noise moves many across a bin edge. On a
        # foreign strong β_B≠β_D trial a camera response at nearly its identity (gamma 1.00, gains 1.01/1.00/1.00)
        # gained +0.0064 held-out θ, and a vignetting whose least-squares fit stayed neutral +0.0052, while the
        # residual rose 0.5 % and stayed put; every θ acceptance of these effects in the documents looked at (that
        # trial, two physical and one own multi-effect dive) lowered it by 8 % or more. "At all" is beyond the
        # least-squares fits' own run-to-run spread (:data:`RESIDUAL_SPREAD`): on the physical vignetting dive of
        # seed 402 a camera response whose colour gains (0.79/0.89/0.93) repeated the lamps' tint (0.78, 0.93)
        # lowered the residual by 0.01 % and was named for +0.0044 held-out θ (2026-12-06).
        disowned = self.residual_evidence and residual is not None and not residual[0] > RESIDUAL_SPREAD
        if gain > margin and not r.extra.get("neutral") and not disowned:
            return True, gain / margin, "theta"
        # the residual speaks where θ is blind, not against it: an effect whose θ refit lowers held-out θ
        # beyond its margin is not taken on the residual. (Its least-squares fit, the model the residual
        # adopts, is not held to that: on the physically lit dives the lamps' fit scores θ 0.011 below the
        # base model while it removes 80 % of the residual; a wrong early acceptance is left to the
        # backward elimination.)
        if (self.residual_evidence and residual is not None and residual[0] > residual[1] and gain > -margin
                and not r.extra.get("ls_neutral")):
            return True, residual[0] / residual[1], "residual"
        return False, gain / margin, "theta"

    def absorbed_frames(self, frames: list, values: dict) -> list:
        """Frames no refit saw (the report frames) with an accepted correction (``absorb``) of ``values`` applied
        to their geometry, as :meth:`absorb_into` applied it to the selection's frames."""
        from ..residuals import corrected_frame

        return [corrected_frame(f, {self.effect: values}) for f in frames]

    # ------------------------------------------------------------------ words

    def explain(self, values: dict, gain: str, sig, camera=None) -> str:
        """The verdict's sentence for fitted ``values`` (``gain``: the evidence in words; ``sig``: the effect's
        signature; ``camera``: the frames' camera, for what the values mean in the image)."""
        return gain

    def on_bounds(self, values: dict) -> list:
        """``(name, side)`` of the refitted parameters that sit on a bound of their box (side -1: the lower,
        +1: the upper), physical limits (:attr:`physical_bounds`) and a box edge that is the default not
        counted."""
        from ...sim.effects import get_effect

        out = []
        for p in get_effect(self.effect).params:
            if p.name not in self.free_params() or p.name not in values or p.name in self.physical_bounds:
                continue
            v, span = values[p.name], p.hi - p.lo
            if v - p.lo < 0.01 * span and p.default - p.lo > 0.01 * span:
                out.append((p.name, -1))
            elif p.hi - v < 0.01 * span and p.hi - p.default > 0.01 * span:
                out.append((p.name, +1))
        return out

    def plausibility(self, values: dict, flat: tuple = (), undetermined: tuple = ()) -> list:
        """Doubts about fitted values: refitted parameters on a bound of their box (the fit wanted more;
        ``flat``: parameters that have saturated there, :meth:`flat_bounds`, not doubted), the plug-in's
        physical ranges (:meth:`ranges`), and ``undetermined`` parameters (:meth:`undetermined`), one doubt."""
        from ...sim.effects import get_effect

        box = {p.name: p for p in get_effect(self.effect).params}
        out = [f"{self.effect}.{n} = {values[n]:.3g} {ON_BOUND} [{box[n].lo:g}, {box[n].hi:g}]"
               for n, _ in self.on_bounds(values) if n not in flat and n not in undetermined]
        # a value that is no finding is not out of any range either
        known = {n: v for n, v in values.items() if n not in undetermined}
        return out + self.ranges(known) + ([self.undetermined_words(undetermined)] if undetermined else [])

    def undetermined(self, model: Optional[EffectModel], x, held: tuple = ()) -> tuple:
        """The refitted parameters of this effect that the image of ``model`` at ``x`` does not depend on: set to
        either end of its box (the rest held), no pixel of the model's frames (the fit frames) moves by
        :data:`FAINT_DN` grey levels (:func:`image_change`), below what the camera records. Their fitted values
        are no finding, and the verdict says so: β_B/β_D, for one, shapes only the ambient backscatter
        b_c (1 - e^(-β_B r)), which a scene lit by the vehicle's lamps alone fits to nothing (the lamps' veil is the
        lamp model's; the physical lamp dive 405 named β_B≠β_D with b_c below 0.001 and its ratios "held at the
        nearest physically possible values", while what changed its image was β_D falling with range).
        ``held``: parameters of the effect refitted and then held at a value (:meth:`pinned`), tested too."""
        from ...sim.effects import get_effect

        if model is None or x is None or self.effect not in model.effects:
            return ()
        x = np.asarray(x, float)
        held = tuple(n for n in held if n not in model.free[self.effect])
        if held:
            values = model.params_of(x)["effects"]
            model = model.with_free({self.effect: model.free[self.effect] + held})
            x = model.x0(x[:7], values)
        lo, hi = model.bounds()
        free = [(model.names[i].split(".", 1)[1], i) for i in model.free_index(self.effect)]
        if not free:
            return ()
        X = []
        for _, i in free:
            for v in (lo[i], hi[i]):
                X.append(x.copy())
                X[-1][i] = v
        dev = image_change(model, x, np.array(X)).reshape(-1, 2).max(axis=1)
        flat = {n for (n, _), d in zip(free, dev) if d < FAINT_DN}
        return tuple(n for n in get_effect(self.effect).param_names if n in flat)

    def undetermined_words(self, names: tuple) -> str:
        """The doubt about parameters the recording does not determine (:meth:`undetermined`)."""
        listed = ", ".join(f"{self.effect}.{n}" for n in names)
        return (f"{listed} {NOT_DETERMINED}: over {'its' if len(names) == 1 else 'their'} whole box the image changes "
                f"by less than {FAINT_DN:g} grey levels at the fitted values, so the value{'s' * (len(names) > 1)} "
                f"stated {'are' if len(names) > 1 else 'is'} no finding")

    def flat_bounds(self, job: Job, model: Optional[EffectModel], x, scale: float) -> tuple:
        """The parameters on a bound of their box (:meth:`on_bounds`) that have *saturated* there: the effect's
        form saturates towards that end (:attr:`saturates`: forward scatter's strength once nearly all the
        light at the scene's range is scattered, ``1 - exp(-strength r)`` near 1), the image depends on the
        parameter (set to the other end of its box, the model's θ on the fit frames changes by more than
        ``scale``, the held-out noise margin of the candidate), but no longer near the bound (pulled a tenth of
        the box back inside, θ changes by less than ``scale``, either way). Such a bound says nothing of a
        stretched fit: beyond it the image would not change either, so the box, not the data, set the value.
        A parameter that acts linearly (a colour gain, a lamp's power) is doubted on its bound whatever θ
        does near it: measured, a lamp tint on its bound changed θ by only 5 % of the lamps' gain over a
        tenth of its box, and the lamps, fitted to a recording without any, took the place of its camera
        response. A parameter θ hardly depends on anywhere in its box is not determined by the data at all:
        its bound stays doubted too."""
        from ...sim.effects import get_effect

        if model is None or x is None or self.effect not in model.effects:
            return ()
        x = np.asarray(x, float)
        values = model.params_of(x)["effects"][self.effect]
        edges = [(n, side) for n, side in self.on_bounds(values) if self.saturates.get(n) == side]
        if not edges:
            return ()
        box = {p.name: p for p in get_effect(self.effect).params}
        names = list(model.names)
        X = [x]
        for n, side in edges:
            i, p = names.index(f"{self.effect}.{n}"), box[n]
            pulled, far = x.copy(), x.copy()
            pulled[i] -= side * 0.1 * (p.hi - p.lo)
            far[i] = p.lo if side > 0 else p.hi
            X += [pulled, far]
        th = job.frame_theta(model, job.fit_f, np.array(X)).mean(axis=1)
        return tuple(n for k, (n, _) in enumerate(edges)
                     if abs(th[0] - th[1 + 2 * k]) < scale < abs(th[0] - th[2 + 2 * k]))

    def ranges(self, values: dict) -> list:
        """Values outside the ranges deep-sea physics allows (plug-ins override)."""
        return []

    def pinned(self, values: dict) -> dict:
        """For fitted values outside the ranges deep-sea physics allows (:meth:`ranges`): the nearest
        physically possible values of the parameters responsible, to be held there in a refit ({}: none, or
        the plug-in has no such repair; plug-ins override). Where the recording barely determines a parameter,
        the fit may wander outside its physical range along an almost flat direction; the refit with it held
        at the nearest possible value tells whether the effect needs the impossible value or not."""
        return {}

    def with_pinned(self, pins: dict) -> "Judge":
        """A copy of this plug-in that holds ``pins`` (name -> value) fixed and refits the rest."""
        import copy

        j = copy.copy(self)
        j.free = tuple(n for n in self.free_params() if n not in pins)
        j.fixed = {**self.fixed, **pins}
        return j


# ====================================================================================== the generic refit


def _sigma0(judges) -> np.ndarray:
    return np.concatenate([BASE_SIGMA0 * 1.5] + [np.full(len(j.free_params()), j.sigma) for j in judges])


def _neutral_values(effect: str) -> Optional[dict]:
    """Values of ``effect`` that leave the image as the model without it renders it (its defaults where they
    do; None for an effect that has none: a seafloor, once listed, is there)."""
    from ...sim.effects import get_effect

    fx = get_effect(effect)
    v = fx.defaults()
    return v if fx.is_identity(v) else None


def _joint_model(job: Job, names: tuple, values: dict) -> tuple:
    """``(judges, resolution, reduced fit frames, EffectModel)`` of the effects ``names`` jointly, their free
    parameters those of their plug-ins, fitted at high resolution if any of them needs it."""
    js = [job.judges[e] for e in names]
    res = "high" if any(j.res == "high" for j in js) else "low"
    rfit = job.reduced(job.fit_f, res)
    model = EffectModel(rfit, names, values={j.effect: {**j.fixed, **values.get(j.effect, {})} for j in js},
                        free={j.effect: j.free_params() for j in js}, fog=job.fog, seed=job.seed)
    return js, res, rfit, model


def _cmaes_from_best(job: Job, js: list, rfit: list, model: EffectModel, cand: list):
    """CMA-ES with the job's budget on the fit frames from the start in ``cand`` that scores highest by θ;
    with a budget of no iterations (``job.max_iter <= 0``: a round's cheap refits) that start itself."""
    noise = noise_sigmas(rfit)
    with FrameObjective(rfit, model, noise, seed=job.seed, batch=job.popsize, pool=job.pool) as of:
        th = of(np.stack(cand))
        i = int(np.nanargmax(th))
        if job.max_iter <= 0:
            return ModelFit(model, np.asarray(cand[i], float), float(th[i]), float(th[i]), len(cand), 0, "starts",
                            0.0, job.seed)
        return fit_model(model, rfit, noise, cand[i], sigma0=_sigma0(js), seed=job.seed, max_iter=job.max_iter,
                         popsize=job.popsize, patience=job.patience, interrupt=job.interrupt, objective=of)


def theta_refit(job: Job, current: Current, judge: Judge, starts: Optional[list] = None,
                x_starts: Optional[list] = None, least_squares: bool = True, parent: Optional[dict] = None) -> Refit:
    """Refit the current model plus ``judge.effect`` jointly on the fit frames (θ, CMA-ES with the common
    budget, started from the best of: the current optimum with the effect neutral, the plug-in's start, least
    squares from those and from the plug-in's alternative starts) and score it per held-out frame.

    Never ends below the current model on the fit frames at high resolution: if the fitted vector scores
    lower there than the current optimum with the effect neutral, the latter is kept. ``least_squares=False``:
    no least-squares starts (nor fit) of the plug-in's own.

    ``parent``: the ``params`` of this effect's refit of a smaller model (the previous round's, before the
    effect accepted there): the model is nested in three ways, the current model with this effect neutral, that
    refit with the newly accepted effects at their current values, and that refit itself (the newly accepted
    effects at their neutral values, where they have them), and starts from all three (the first two also as
    least-squares starts). Two effects that each explain much of the same residual alone (lamps aimed down and a
    lit seafloor below the panel) otherwise hide each other: whichever is accepted first stretches the base
    model (attenuation taking the lamps' falloff, a veil taking the floor), and the other's refit from that
    stretched optimum stays near it. With the first effect at its current values on top of the parent the
    brightening is counted twice (a camera response with gains 1.3-1.6 taking the lamps' light, then the lamps
    added at full power); from the parent itself it starts where the lamps alone were fitted. (On nine physically
    lit dives that start never scored highest: the selections were the same with it. As a least-squares start
    too it cost 10-20 % of a diagnosis's time for that, so it is a θ start only.)"""
    from ...sim.effects import EFFECT_ORDER

    names = tuple(e for e in EFFECT_ORDER if e in current.effects or e == judge.effect)
    js, res, rfit, model = _joint_model(job, names, current.values)
    cur = {e: current.values[e] for e in current.effects}
    x_id = model.x0(current.base, cur)
    s0 = judge.start(job)
    x_hint = model.x0(current.base, {**cur, judge.effect: s0})
    cand = [x_id, x_hint] + [model.x0(current.base, {**cur, judge.effect: s}) for s in (starts or [])]
    cand += [np.clip(np.asarray(x, float), *model.bounds()) for x in (x_starts or [])]
    par = []
    if parent is not None and judge.effect in parent.get("effects", {}):
        par_base = np.array([parent["base"][k] for k in RGB_NAMES], float)
        par_effects = {e: v for e, v in parent["effects"].items() if e in names}
        par = [model.x0(par_base, {**cur, **par_effects})]
        cand += par
        # that refit itself is nested too (a θ start): the effects accepted since at their neutral values
        since = {e: v for e in cur if e not in par_effects and (v := _neutral_values(e)) is not None}
        if since:
            cand.append(model.x0(par_base, {**cur, **since, **par_effects}))
    ls_extra = {}
    if judge.least_squares and least_squares and not x_starts:
        lmodel = model.like(job.reduced(job.fit_f, "ls"))
        alt_base = judge.alt_base(job, current.base)
        ls_x = [ls_fit(lmodel, xs, stride=1, max_nfev=job.ls_nfev, interrupt=job.interrupt)
                for xs in [x_hint] + [lmodel.x0(alt_base, {**cur, judge.effect: {**s0, **a}})
                                      for a in judge.alt_starts] + par]
        cand += ls_x
        if current.ls_params is not None:
            # nested: the current model's least-squares optimum with the effect neutral is a candidate too, and
            # so is a least-squares fit from it (the whole model refitted jointly, its effects and this one; also
            # a θ start); the fit with the lowest residual on the fit frames is the candidate's
            x_nest = lmodel.x0(current.ls_params["base"], current.ls_params["effects"])
            ls_x += [x_nest, ls_fit(lmodel, x_nest, stride=1, max_nfev=job.ls_nfev, interrupt=job.interrupt)]
            cand.append(ls_x[-1])
            E_fit = residual_energy(lmodel, np.stack(ls_x)).mean(axis=1)
            x_best = ls_x[int(np.nanargmin(E_fit))]
            E_sel = residual_energy(lmodel.like(job.reduced(job.sel_f, "ls")), x_best)[0]
            p = lmodel.params_of(x_best)
            ls_extra = {"ls_x": x_best, "ls_sel_E": E_sel, "ls_fit_E": float(np.nanmin(E_fit)),
                        "ls_params": {"base": np.array(list(p["base"].values())), "effects": p["effects"]},
                        "ls_neutral": judge.neutral(p["effects"][judge.effect], job.camera)}
    fit = _cmaes_from_best(job, js, rfit, model, cand)
    # the nesting invariant, judged where models are compared (fit frames, high resolution)
    # (only where the effect has neutral values: a seafloor, once listed, is there)
    # A fit at the low resolution also moves the base parameters to the low-resolution optimum, which can
    # score below the current (high-resolution) optimum where models are compared: the fitted effect with
    # the current base parameters is tried there too.
    x_mix = fit.x.copy()
    x_mix[:7] = x_id[:7]
    t_all = job.frame_theta(model, job.fit_f, np.stack([fit.x, x_id, x_mix])).mean(axis=1)
    j = 0 if t_all[0] >= t_all[2] else 2
    t_fit = np.array([t_all[j], t_all[1]])
    neutral = job.judges[judge.effect].neutral(model.params_of(x_id)["effects"][judge.effect], job.camera)
    kept_current = bool(neutral and not t_fit[0] >= t_fit[1])
    x = x_id if kept_current else (fit.x if j == 0 else x_mix)
    sel_pf = job.frame_theta(model, job.sel_f, x, seed_offset=50)[0]
    params = model.params_of(x)
    return Refit(effect=judge.effect, effects=names, x=x, params=params,
                 theta_fit=float(t_fit[1] if kept_current else t_fit[0]),
                 sel_pf=sel_pf, model=model, started_at_current=kept_current,
                 extra={"neutral": judge.neutral(params["effects"][judge.effect], job.camera),
                        "theta_fit_optimizer": float(t_all[0]), "theta_fit_nested_start": float(t_all[1]),
                        "theta_fit_effect_with_current_base": float(t_all[2]),
                        "resolution": res, "n_evals": int(fit.n_evals), **ls_extra})


def reference_refit(job: Job, current: Current) -> Optional[Refit]:
    """The current model itself refitted as a round's candidates are (the reference they are compared with):
    the same budget (``job``'s), the same resolution rule and the same nested starts, i.e. the current optimum
    and its least-squares optimum polished by least squares with every parameter free, then CMA-ES from the best
    of them by θ; kept only where it scores higher on the fit frames at high resolution. ``effect`` of the result
    is ``""``; None when there is nothing to refit from (no current vector).

    Why: a candidate's refit also goes on optimizing the current model's own parameters. Compared with the
    current optimum as it stands, a candidate is credited with that too: on a physical dive vignetting was
    "accepted" in round 2 with +0.0104 held-out θ at exactly its neutral values (k1 = k2 = cx = cy = 0), and camera
    response and a seafloor beside it with +0.0069 and +0.0101 (2026-11-28)."""
    if current.x is None:
        return None
    names = tuple(current.effects)
    js, res, rfit, model = _joint_model(job, names, current.values)
    x_cur = model.x0(current.base, {e: current.values[e] for e in names})
    cand = [x_cur]
    if current.ls_params is not None:
        lmodel = model.like(job.reduced(job.fit_f, "ls"))
        x_nest = lmodel.x0(current.ls_params["base"], current.ls_params["effects"])
        cand += [x_nest, ls_fit(lmodel, x_nest, stride=1, max_nfev=job.ls_nfev, interrupt=job.interrupt)]
    fit = _cmaes_from_best(job, js, rfit, model, cand)
    # judged where models are compared (fit frames, high resolution); a low-resolution fit moves the base
    # parameters to the low-resolution optimum: the fitted effects with the current base are tried too
    x_mix = fit.x.copy()
    x_mix[:7] = x_cur[:7]
    t_all = job.frame_theta(model, job.fit_f, np.stack([fit.x, x_mix, x_cur])).mean(axis=1)
    j = int(np.nanargmax(t_all))
    x = (fit.x, x_mix, x_cur)[j]
    sel_pf = np.asarray(current.sel_pf, float) if j == 2 else job.frame_theta(model, job.sel_f, x, seed_offset=50)[0]
    return Refit(effect="", effects=names, x=x, params=model.params_of(x), theta_fit=float(t_all[j]),
                 sel_pf=sel_pf, model=model, started_at_current=j == 2,
                 extra={"theta_fit_optimizer": float(t_all[0]), "theta_fit_current": float(t_all[2]),
                        "resolution": res, "n_evals": int(fit.n_evals)})


def least_squares_model(job: Job, r: Refit) -> Refit:
    """The refit whose model is its least-squares fit (an effect accepted by the held-out residual: that fit is
    the evidence, and a θ refit from it drifts back towards the model without the effect where θ is blind),
    scored by θ on the fit and held-out frames for the record."""
    x = np.asarray(r.extra["ls_x"], float)
    return replace(r, x=x, params=r.model.params_of(x), theta_fit=float(job.frame_theta(r.model, job.fit_f, x).mean()),
                   sel_pf=job.frame_theta(r.model, job.sel_f, x, seed_offset=50)[0], started_at_current=False)


def gain_words(b_held: float, c_held: float, statistic: Optional[dict] = None,
               residual: Optional[tuple] = None) -> str:
    """The held-out evidence in words (what every explanation ends with); ``residual``: (before, after) mean
    squared held-out residual of the least-squares fits, when the effect was accepted by it."""
    if residual is not None:
        return (f"modelling it lowers the held-out frames' mean squared residual from {residual[0]:.3g} to "
                f"{residual[1]:.3g} grey levels² ({100 * (1 - residual[1] / max(residual[0], 1e-9)):.0f} % less; "
                f"held-out θ {b_held:.3f} -> {c_held:.3f}, which a smooth brightness change in dark, noisy "
                f"frames barely moves)")
    if statistic is not None:
        base = statistic.get("base_label", "model without it")
        return (f"modelling it brings the held-out frames' {statistic['name']} from {statistic['base_sim']:.3g} "
                f"({base}) to {statistic['candidate_sim']:.3g} (recording: {statistic['real']:.3g}); "
                f"held-out θ {b_held:.3f} -> {c_held:.3f}")
    return f"modelling it raises held-out θ from {b_held:.3f} to {c_held:.3f}"


def with_effect(current: Current, r: Refit) -> Current:
    """The current model after accepting ``r`` (a ``theta`` effect)."""
    return replace(current, effects=r.effects, values={e: dict(r.params["effects"][e]) for e in r.effects},
                   base=np.array([r.params["base"][k] for k in r.params["base"]], float), theta_fit=r.theta_fit,
                   sel_pf=np.asarray(r.sel_pf, float), x=r.x, model=r.model,
                   ls_params=r.extra.get("ls_params"), ls_sel_E=r.extra.get("ls_sel_E"))


def polish_blocks(job: Job, current: Current, max_iter: int) -> tuple:
    """The selected model polished one effect at a time: CMA-ES on the free parameters of one effect with
    everything else held, effect after effect, on the fit frames (high resolution, θ as every model is compared),
    each step kept only if it raises θ there. Returns ``(current, steps)``: the polished model with its θ per
    held-out frame, and per effect ``{"effect", "theta_fit_before", "theta_fit_after", "kept"}``.

    Why: an effect accepted early was fitted in a model that lacked the later ones, and the joint refits that
    follow start from its values; a joint CMA-ES over 30 parameters barely moves them. Measured on the own
    4-effect dive (lamps, β_B≠β_D, camera response, forward scatter): the true parameters score θ 0.957 on the fit
    frames where the selection's model scored 0.946; a joint restart (step 0.2, 16 per generation) ended at
    0.947, while CMA-ES on the three forward-scatter parameters alone reached 0.951-0.952 from each of three
    starts (held-out 0.946 -> 0.949-0.952)."""
    names = tuple(current.effects)
    if not names or current.x is None or current.model is None:
        return current, []
    rfit = job.reduced(job.fit_f, "high")
    model = current.model.like(rfit, seed=job.seed)
    noise = noise_sigmas(rfit)
    x = np.asarray(current.x, float).copy()
    sigma = _sigma0([job.judges[e] for e in names])
    steps = []
    with FrameObjective(rfit, model, noise, seed=job.seed, batch=job.popsize, pool=job.pool) as ob:
        best = float(ob(x[None])[0])
        for e in names:
            fixed = np.ones(x.size, bool)
            fixed[model.free_index(e)] = False
            fit = fit_model(model, rfit, noise, x, sigma0=sigma, seed=job.seed, max_iter=max_iter,
                            popsize=job.popsize, patience=job.patience, interrupt=job.interrupt, objective=ob,
                            fixed=fixed)
            kept = bool(fit.theta_train > best)
            steps.append({"effect": e, "theta_fit_before": best, "theta_fit_after": float(fit.theta_train),
                          "kept": kept})
            if kept:
                x, best = fit.x, float(fit.theta_train)
    if not any(st["kept"] for st in steps):
        return current, steps
    p = model.params_of(x)
    sel_pf = job.frame_theta(current.model, job.sel_f, x, seed_offset=50)[0]
    return replace(current, values={e: dict(p["effects"][e]) for e in names},
                   base=np.array(list(p["base"].values()), float), theta_fit=best, sel_pf=np.asarray(sel_pf, float),
                   x=x), steps


def refit_without(job: Job, current: Current, e: str, ls_nfev: Optional[int] = None) -> Optional[Current]:
    """The current model without its effect ``e``, refitted jointly: the generic refit of its last other effect
    on top of the rest, started at the current values (θ) and at the current least-squares optimum without
    ``e`` (least squares), then polished like every current model (``ls_nfev``). What backward elimination
    compares the current model with; None when ``e`` is its only effect (the comparison that accepted it)."""
    rest = tuple(n for n in current.effects if n != e)
    if not rest or e not in current.effects:
        return None
    last = rest[-1]
    below = tuple(n for n in rest if n != last)
    ls = None
    if current.ls_params is not None:
        ls = {"base": current.ls_params["base"],
              "effects": {n: v for n, v in current.ls_params["effects"].items() if n != e}}
    base_cur = replace(current, effects=below, values={n: dict(current.values[n]) for n in below}, ls_params=ls,
                       ls_sel_E=None, x=None, model=None)
    # θ from the current values without e; least squares from the better of that and the current
    # least-squares optimum without e (the plug-in's own starts are for finding an effect, not for this)
    r = theta_refit(job, base_cur, job.judges[last], starts=[dict(current.values[last])], least_squares=False)
    return current_ls(job, replace(with_effect(base_cur, r), ls_params=ls), max_nfev=ls_nfev)


def current_ls(job: Job, current: Current, max_nfev: Optional[int] = None) -> Current:
    """The current model with its least-squares fit (about 80 px wide, fit frames; from the better of its θ
    optimum and its earlier least-squares fit, when there is one) and that fit's mean squared residual per held-out
    frame: the reference of :func:`residual_improvement`."""
    names = current.effects
    free = {e: job.judges[e].free_params() for e in names}
    lmodel = EffectModel(job.reduced(job.fit_f, "ls"), names, values=current.values, free=free, fog=job.fog,
                         seed=job.seed)
    xs = [lmodel.x0(current.base, current.values)]
    if current.ls_params is not None:
        xs.append(lmodel.x0(current.ls_params["base"], current.ls_params["effects"]))
    E0 = residual_energy(lmodel, np.stack(xs)).mean(axis=1)
    xs.append(ls_fit(lmodel, xs[int(np.nanargmin(E0))], stride=1, max_nfev=max_nfev or job.ls_nfev,
                     interrupt=job.interrupt))
    E_fit = residual_energy(lmodel, np.stack(xs)).mean(axis=1)
    x = xs[int(np.nanargmin(E_fit))]
    p = lmodel.params_of(x)
    return replace(current, ls_params={"base": np.array(list(p["base"].values())), "effects": p["effects"]},
                   ls_sel_E=residual_energy(lmodel.like(job.reduced(job.sel_f, "ls")), x)[0])
