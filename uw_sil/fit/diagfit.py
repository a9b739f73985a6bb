"""Fits of the diagnosis: θ over reduced frames for the base model or the base model plus effects.

A *candidate model* maps parameter vectors ``x = (7 base parameters, effect parameters ...)`` to
simulated frames. :class:`BaseModel` is paper Eq. 1 with fog, area-exact on reduced frames
(:func:`uw_sil.fit.residuals.base_sim`); :class:`EffectModel` adds
effects of :mod:`uw_sil.sim.effects` (which parameters are free is the diagnosis plug-ins' choice,
:mod:`uw_sil.fit.judges`). :class:`FrameObjective` is mean θ over frames for batches of
such vectors (the camera noise estimated on each real frame's water is added to every candidate as a
fixed realization, as in :class:`uw_sil.fit.backward.BackwardObjective`, unless the model draws its own
noise). :func:`fit_model` maximizes it with CMA-ES and stops on convergence.

References
----------
.. [1] N. Hansen, "The CMA Evolution Strategy: A Tutorial", arXiv:1604.00772, 2016.
.. [2] T. Doernbach, A. Gomez Chavez, C. A. Mueller and A. Birk, "High-Fidelity Deep-Sea Perception
   Using Simulation in the Loop", IFAC conference paper, 2018 (θ: Eq. 4; the base model: Eq. 1).
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

from .._shared.process import default_threads
from ..sim.params import DEFAULT_RGB_BOUNDS, RGB_NAMES
from .residuals import LABEL_PANEL, ReducedFrame, base_sim

__all__ = ["BaseModel", "EffectModel", "FrameObjective", "ModelFit", "fit_model", "ls_fit", "noise_sigmas",
           "BASE_SIGMA0"]


#: Initial CMA-ES steps of the base parameters from a least-squares start (fraction of each range): small, and a
#: quarter of it for the background, which the water fixes (cf. the backward fit's measured defaults).
BASE_SIGMA0 = np.array([0.02, 0.02, 0.02, 0.005, 0.005, 0.005, 0.02])


class BaseModel:
    """Paper Eq. 1 with fog on reduced frames; parameters :data:`uw_sil.sim.params.RGB_NAMES`."""

    effects: tuple = ()
    owns_noise = False

    def __init__(self, rframes: Sequence[ReducedFrame], fog: str = "exp2"):
        self.rframes = list(rframes)
        self.fog = fog

    @property
    def names(self) -> tuple:
        return RGB_NAMES

    def bounds(self) -> tuple:
        return DEFAULT_RGB_BOUNDS[0].copy(), DEFAULT_RGB_BOUNDS[1].copy()

    def simulate(self, k: int, X: np.ndarray, out: Optional[np.ndarray] = None) -> np.ndarray:
        """Frames ``k`` for candidate vectors X (N, d): (N, h, w, 3) float32 in 0..1."""
        X = np.atleast_2d(X)
        rf = self.rframes[k]
        if out is None:
            out = np.empty((len(X),) + rf.shape + (3,), np.float32)
        for j, x in enumerate(X):
            out[j] = base_sim(rf, _clean_base(x[:7]), self.fog)
        return out

    def params_of(self, x) -> dict:
        """``{"base": {a_r: ...}, "effects": {}}`` of a vector."""
        return {"base": {n: float(v) for n, v in zip(RGB_NAMES, _clean_base(x[:7]))}, "effects": {}}


def _clean_base(p) -> np.ndarray:
    p = np.clip(np.asarray(p, dtype=float), 0.0, None)
    p[3:6] = np.clip(p[3:6], 0.0, 1.0)
    return p


#: Standard deviation of 8-bit quantization, 1/sqrt(12) grey levels: no recording is quieter than that.
QUANTIZATION_SIGMA = 12 ** -0.5


def noise_sigmas(rframes: Sequence[ReducedFrame]) -> list:
    """Camera noise per frame and channel (grey levels at the reduced size), from the real water; at least the
    8-bit quantization's (averaged over the reduction's blocks). Near-black, quantized or demosaiced water
    can read as 0 noise, and a zero noise level turned into infinite weights in the signature fits."""
    from ..sim.noise import water_noise_sigma

    return [np.maximum(np.asarray(water_noise_sigma(rf.image, rf.water), float), QUANTIZATION_SIGMA / max(1, rf.factor))
            for rf in rframes]


class FrameObjective:
    """Mean θ over reduced frames for batches of candidate vectors of a candidate model.

    Parameters
    ----------
    rframes : list of ReducedFrame
    model : BaseModel or compatible (``simulate(k, X)``, ``owns_noise``)
    noise : list of (3,) arrays
        Camera noise per frame (grey levels) added as a fixed realization (common random numbers),
        unless ``model.owns_noise``.
    seed : int
    workers : int, optional
        Threads (default: :func:`uw_sil._shared.process.default_threads`).
    """

    def __init__(self, rframes, model, noise, seed: int = 0, channels: str = "HSV", batch: int = 16,
                 workers: Optional[int] = None, pool=None):
        from ..sim.noise import NoiseField

        # with a pool of worker processes (uw_sil._shared.workers.WorkerPool) a batch is shared out among them
        # instead of among threads: the same values, without the GIL
        self._remote = (_RemoteObjective(rframes, model, noise, seed, channels, batch)
                        if pool is not None and pool.processes > 1 else None)
        self.pool = pool
        if self._remote is not None:
            workers = 1
        self.rframes = list(rframes)
        self.model = model
        self.workers = default_threads(workers)
        refs = [theta_reference(rf, channels) for rf in self.rframes]
        self._refs = [[r.fork() for r in refs] for _ in range(self.workers)]
        self.noise = [None if model.owns_noise or not np.any(np.asarray(s) > 0) else
                      NoiseField(rf.shape + (3,), s, seed=seed + 7919 * i)
                      for i, (rf, s) in enumerate(zip(self.rframes, noise))]
        self.batch = max(1, int(batch))
        self._pool = None
        self.n_calls = 0

    def per_frame(self, X) -> np.ndarray:
        """θ per candidate and frame, (N, K)."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        if self._remote is not None and len(X) > 1:
            parts = [p for p in np.array_split(np.arange(len(X)), self.pool.processes) if p.size]
            self.n_calls += len(X)
            return np.concatenate(self.pool.map(_remote_rows, [X[p] for p in parts], shared=self._remote))
        out = np.full((len(X), len(self.rframes)), np.nan)
        parts = [p for p in np.array_split(np.arange(len(X)), self.workers) if p.size]
        if len(parts) == 1:
            self._part(0, X, parts[0], out)
        else:
            if self._pool is None:
                from concurrent.futures import ThreadPoolExecutor

                self._pool = ThreadPoolExecutor(self.workers, thread_name_prefix="uw_sil-diag")
            for fut in [self._pool.submit(self._part, w, X, idx, out) for w, idx in enumerate(parts)]:
                fut.result()
        self.n_calls += len(X)
        return out

    def __call__(self, X) -> np.ndarray:
        return self.per_frame(X).mean(axis=1)

    def _part(self, w, X, idx, out):
        refs = self._refs[w]
        for k, (ref, noise) in enumerate(zip(refs, self.noise)):
            for s in range(0, len(idx), self.batch):
                sel = idx[s:s + self.batch]
                try:
                    imgs = self.model.simulate(k, X[sel])
                except (ValueError, FloatingPointError):
                    out[sel, k] = np.nan
                    continue
                imgs *= 255.0
                if noise is not None:
                    noise.apply(imgs)
                else:
                    np.clip(imgs, 0.0, 255.0, out=imgs)
                bad = ~np.isfinite(imgs).reshape(len(sel), -1).all(axis=1)
                if bad.any():
                    imgs[bad] = 0.0
                t = ref.score(imgs)
                t[bad] = np.nan
                out[sel, k] = t

    def close(self):
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class _RemoteObjective:
    """What a worker process needs to build the same :class:`FrameObjective` (on one thread); built there once
    and kept with this object, which the worker keeps while the objective's calls come."""

    def __init__(self, rframes, model, noise, seed, channels, batch):
        self.args = (list(rframes), model, noise, seed, channels, batch)
        self._objective = None

    def __getstate__(self):
        return {"args": self.args, "_objective": None}

    def objective(self) -> "FrameObjective":
        if self._objective is None:
            rframes, model, noise, seed, channels, batch = self.args
            self._objective = FrameObjective(rframes, model, noise, seed=seed, channels=channels, batch=batch,
                                             workers=1)
        return self._objective


def _remote_rows(remote: _RemoteObjective, X) -> np.ndarray:
    """θ per candidate and frame of the rows X, in a worker process."""
    return remote.objective().per_frame(X)


def theta_reference(rf: ReducedFrame, channels: str = "HSV"):
    """The θ reference of a reduced frame (its phase congruency, gradients and histograms), built once per
    frame and kept with it: every candidate model of a diagnosis is scored against the same frames, so
    objectives take :meth:`~uw_sil.metrics.theta.ThetaReference.fork` copies (bit-identical scores, own work
    buffers) instead of recomputing it. The kept reference itself is never evaluated (thread safety)."""
    from ..metrics.theta import ThetaReference

    key = ("theta_reference", channels)
    ref = rf.extra.get(key)
    if ref is None:
        ref = rf.extra[key] = ThetaReference(rf.image, channels=channels, hist_mask=_hist_masks(rf))
    return ref


def _hist_masks(rf: ReducedFrame):
    panel = rf.labels == LABEL_PANEL
    if not panel.any() or panel.all():
        return None
    return [panel, ~panel]


@dataclass
class ModelFit:
    """Result of :func:`fit_model`."""

    model: object
    x: np.ndarray
    theta_train: float
    theta_start: float
    n_evals: int
    n_iters: int
    stop_reason: str
    wall_time_s: float
    seed: int
    history: list = field(default_factory=list)

    @property
    def params(self) -> dict:
        return self.model.params_of(self.x)


def fit_model(model, rframes, noise, x0, sigma0=0.1, seed: int = 0, max_iter: int = 40, popsize: int = 16,
              tol: float = 2e-4, patience: int = 6, interrupt=None, objective: Optional[FrameObjective] = None,
              fixed: Optional[np.ndarray] = None) -> ModelFit:
    """Maximize mean θ over ``rframes`` with CMA-ES from ``x0`` (within ``model.bounds()``), stopping on
    convergence (best θ gained <= ``tol`` over ``patience`` iterations) or after ``max_iter``.

    ``sigma0``: initial step as a fraction of each parameter's range (scalar or per parameter, through
    cma's ``CMA_stds``). ``fixed``: boolean mask of parameters held at ``x0``.
    """
    from .optimize import optimize

    t0 = time.perf_counter()
    lo, hi = model.bounds()
    x0 = np.clip(np.asarray(x0, float), lo, hi)
    own = objective is None
    obj = objective or FrameObjective(rframes, model, noise, seed=seed, batch=popsize)
    free = np.ones(len(lo), bool) if fixed is None else ~np.asarray(fixed, bool)
    sig = np.broadcast_to(np.asarray(sigma0, float), lo.shape).copy()[free]
    s_ref = float(np.max(sig))

    def to_x(U):
        X = np.repeat(x0[None], len(np.atleast_2d(U)), axis=0)
        X[:, free] = np.atleast_2d(U)
        return X

    def f(U):
        return obj(to_x(U))

    def stop(it, x, f):
        if interrupt is not None:
            interrupt()
        return False

    try:
        theta_start = float(obj(x0[None])[0])
        res = optimize(f, lo[free], hi[free], method="cmaes", seed=seed, max_iter=max_iter, swarm_size=popsize,
                       x0=x0[free], sigma0=s_ref, callback=stop, tol=tol, patience=patience,
                       cma_options={"CMA_stds": list(sig / s_ref)})
    finally:
        if own:
            obj.close()
    x, f_best = to_x(res.x_best)[0], float(res.f_best)
    if not f_best >= theta_start:
        # cma's bound handling moves an injected start that lies near a bound: never return worse than it
        x, f_best = x0.copy(), theta_start
    return ModelFit(model, x, f_best, theta_start, int(res.n_evals), int(res.n_iters),
                    str(res.stop_reason), time.perf_counter() - t0, seed, [float(v) for v in res.history_best_f])


class EffectModel:
    """Base model + effects of :mod:`uw_sil.sim.effects` on reduced frames, as a candidate model.

    Parameter vector: the 7 base parameters, then the free parameters of each effect (``free[effect]``,
    default all of them), named ``<effect>.<param>``. Non-free parameters take ``values[effect]`` over the
    effect's defaults.

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
            v.update((values or {}).get(n, {}))
            vals[n] = v
        self.values = vals
        self.free = {n: tuple((free or {}).get(n, get_effect(n).param_names)) for n in self.effects}
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

    def __getstate__(self):
        # the prepared per-frame models are rebuilt where the model is unpickled (a worker process)
        return {k: v for k, v in self.__dict__.items() if k not in ("pms", "_local")}

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._local = threading.local()
        self.pms = self._prepare()

    def like(self, rframes, seed: Optional[int] = None) -> "EffectModel":
        """The same model (effects, free parameters, fixed values) on other frames."""
        return EffectModel(rframes, self.effects, self.values, self.free, self.fog,
                           self._seed if seed is None else seed)

    def with_free(self, free: dict) -> "EffectModel":
        """The same model on the same frames with other free parameters (``free``: names per effect, over its
        own)."""
        return EffectModel(self.rframes, self.effects, self.values, {**self.free, **free}, self.fog, self._seed)

    def _prepare(self) -> list:
        from ..sim.model import Geometry

        pms = []
        shared = {}                 # the frames' evaluators share what depends on the camera only (the lamps' veil)
        for k, rf in enumerate(self.rframes):
            geom = Geometry(rf.camera, rf.rgb, np.where(rf.cover > 0, rf.depth, np.inf),
                            np.where(rf.cover > 0, rf.range, np.inf), rf.labels, rf.part_ids,
                            pose=rf.frame.pose, normals=rf.normals, fine=rf.fine_geometry())
            # area-exact silhouettes at the reduced resolution, as the base model has them
            pms.append(self._model.prepare(geom, rf.camera, pose=rf.frame.pose, seed=1000 + k + 7919 * self._seed,
                                           cover=rf.cover, shared=shared))
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

    def free_index(self, effect: str) -> np.ndarray:
        """Positions of ``effect``'s free parameters in the parameter vector."""
        return np.array([i for i, n in enumerate(self.names) if n.startswith(effect + ".")], int)

    def bounds(self) -> tuple:
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


#: Grey levels below which a change of the image is none (:func:`image_change`): half a grey level, less than an
#: 8-bit frame can show.
FAINT_DN = 0.5


def image_change(model: EffectModel, x, X, batch: int = 16) -> np.ndarray:
    """The largest change of any pixel of ``model``'s frames, in grey levels, from the vector ``x`` to each of
    ``X`` (N, d): (N,), NaN where a simulation is not finite. ``batch`` vectors at a time, each beside ``x``."""
    x, X = np.asarray(x, float), np.atleast_2d(np.asarray(X, float))
    dev = np.zeros(len(X))
    for k in range(len(model.rframes)):
        for j in range(0, len(X), batch):
            img = model.simulate(k, np.concatenate([x[None], X[j:j + batch]]))
            d = np.abs(img[1:] - img[:1]).reshape(len(img) - 1, -1)
            dev[j:j + batch] = np.maximum(dev[j:j + batch], 255.0 * d.max(axis=1))     # (NaN: a change)
    return dev


def residual_energy(model, X) -> np.ndarray:
    """Mean squared residual (grey levels², every pixel, all channels) of parameter vectors ``X`` (N, d) of
    ``model`` on its frames: (N, K), the quantity :func:`ls_fit` minimizes and the held-out residual evidence
    of :mod:`uw_sil.fit.judges` compares (other frames: ``model.like(rframes)``)."""
    X = np.atleast_2d(np.asarray(X, float))
    out = np.zeros((len(X), len(model.rframes)))
    for k, rf in enumerate(model.rframes):
        sims = model.simulate(k, X) * 255.0
        out[:, k] = ((sims - rf.image[None]) ** 2).mean(axis=(1, 2, 3))
    return out


class _Subspace:
    """A model seen through some of its parameters (``idx``; the others stay at ``x``): what :func:`ls_fit`
    needs of a model."""

    def __init__(self, model, x, idx):
        self.model, self.x, self.idx = model, x, idx
        self.rframes = model.rframes

    def bounds(self):
        lo, hi = self.model.bounds()
        return lo[self.idx], hi[self.idx]

    def simulate(self, k, U):
        X = np.repeat(self.x[None], len(U), axis=0)
        X[:, self.idx] = U
        return self.model.simulate(k, X)


def ls_fit(model: "EffectModel", x0, stride: int = 2, max_nfev: int = 12, interrupt=None,
           free: Optional[np.ndarray] = None) -> np.ndarray:
    """Least-squares fit (grey levels, every ``stride``-th pixel) of a candidate model to its frames, from x0;
    ``interrupt`` is called before every evaluation (raises to stop); ``free``: indices of the parameters
    fitted (default all; the others stay at x0)."""
    from scipy.optimize import least_squares

    lo, hi = model.bounds()
    x0 = np.clip(np.asarray(x0, float), lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
    if free is not None:
        idx = np.asarray(free, int)
        x = x0.copy()
        x[idx] = ls_fit(_Subspace(model, x0, idx), x0[idx], stride=stride, max_nfev=max_nfev, interrupt=interrupt)
        return x
    reals = [rf.image[stride // 2::stride, stride // 2::stride] for rf in model.rframes]
    last = {}

    def resids(X):
        """residuals of the vectors X (N, d): (N, n), one batched simulation per frame"""
        if interrupt is not None:
            interrupt()
        out = [(model.simulate(k, X)[:, stride // 2::stride, stride // 2::stride] * 255.0 - R[None]).reshape(len(X), -1)
               for k, R in enumerate(reals)]
        return np.concatenate(out, axis=1)

    def resid(x):
        last["x"], last["f"] = x.copy(), resids(x[None])[0]
        return last["f"]

    def jac(x):
        # forward differences (relative step 2e-3, stepping away from a bound it would cross), all d steps in
        # one batched simulation instead of d separate ones; least_squares evaluates f(x) just before
        f0 = last["f"] if "x" in last and np.array_equal(last["x"], x) else resid(x)
        h = 2e-3 * np.maximum(1.0, np.abs(x))
        h = np.where(x + h > hi, -h, h)
        F = resids(x[None] + np.diag(h))
        # a form capped on one side is flat there: vignetting's falloff min(1, 1 + k1 r^2 + k2 r^4) at k = 0
        # does not change for k > 0, so its forward column is zero and the fit would never leave k = 0; such
        # parameters are stepped the other way (within the box)
        flat = ~np.any(F != f0[None], axis=1) & (x - h >= lo) & (x - h <= hi)
        if flat.any():
            h[flat] = -h[flat]
            F[flat] = resids(x[None] + np.diag(h)[flat])
        return ((F - f0[None]) / h[:, None]).T

    try:
        r = least_squares(resid, x0, jac=jac, bounds=(lo, hi), method="trf",
                          x_scale=np.maximum(hi - lo, 1e-6) * 0.1, max_nfev=max_nfev, xtol=1e-4, ftol=1e-4)
    except (ValueError, FloatingPointError):
        return x0
    return r.x
