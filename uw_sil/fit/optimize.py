"""Bounded, batched, derivative-free maximization: particle swarm (paper) or CMA-ES behind one interface.

The backward optimization of the simulator's 7 parameters maximizes an image similarity
``theta(x)`` in [0, 1]. Every candidate costs a render, so the objective here is *batched*,
``objective(X (N, d)) -> theta (N,)``, and each optimizer iteration is exactly ONE call of it.

Methods
-------
``"pso"`` (default, as in the paper)
    Particle swarm optimization by the ``pyswarm`` package (pinned 1.1.2; the paper's footnote 1
    names pyswarm as its implementation) with the paper's settings :data:`PSO_PAPER_SETTINGS`
    (Sec. 3.4, Algorithm 1): 20 particles, inertia ``omega = 0.4``, cognitive ``phi_p = 0.3`` and
    social ``phi_g = 0.3`` coefficients (pyswarm's ``omega``, ``phip``, ``phig``; the paper calls
    them agent velocity, per-agent and swarm inertia), at most ``t_max = 100`` iterations, and
    pyswarm's own stopping rules (``minstep = minfunc = 1e-8``). See "How pyswarm is driven".
``"cmaes"``
    CMA-ES by the ``cma`` package (ask/tell; one call per generation; bounds by ``cma``'s
    ``BoundTransform``), population ``4 + floor(3 ln d)`` (9 for d = 7) unless ``swarm_size``
    is given, initial step size ``sigma0 = 0.25`` of the box width, mean at the centre of the
    box unless ``x0`` is given.

Both search the box normalized to ``[0, 1]^d`` (``x = lower + u * (upper - lower)``); the
objective always receives parameters in their original units.

Conventions
-----------
* Iteration 0 is the first batch (PSO: the initial swarm; CMA-ES: the first generation);
  iterations ``1 .. max_iter`` follow. ``history_best_f[k]`` is the best theta after iteration
  ``k``, so ``len(history_best_f) == n_iters + 1``. For PSO this is pyswarm's own numbering
  (its main loop runs ``it = 1 .. maxiter`` after evaluating the initial swarm), and a full
  paper run costs ``20 * 101 = 2020`` evaluations.
* A non-finite value (NaN, +-inf) from a degenerate candidate is recorded as ``-inf`` and ranks
  below every finite value: it never becomes a particle's or the swarm's best in PSO, and it is
  replaced by a finite value worse than the batch's worst finite one before ``cma`` sees it
  (``cma`` itself would silently replace NaN by the population *median*).
* ``converged_iter`` is :func:`convergence_iteration` of the history: the first iteration after
  which the best theta improved by no more than ``tol`` in total.
* Stop on convergence (``patience > 0``): after iteration ``k >= patience`` the run stops when the
  best value gained no more than ``tol`` over the last ``patience`` iterations,
  ``history_best_f[k] - history_best_f[k - patience] <= tol`` (``stop_reason == "converged"``).
  Off by default here (``patience=0``): ``tol`` is in the objective's units, so the default belongs
  to the caller (the backward fit sets one measured on θ, see :mod:`uw_sil.fit.backward`). The same
  rule for both methods; it replaces pyswarm's own ``patience`` option (no longer passed through).

How pyswarm is driven
---------------------
pyswarm 1.1.2 has no callback, no ``processes`` option and no pool hook: its public ``pso`` runs
the whole loop in Fortran (``_pyswarm.pso``) and calls the objective once per particle. Its
loop is a *synchronous* PSO: in iteration ``it`` it first moves ALL particles (velocity
``v = omega v + phi_p r_p (p - x) + phi_g r_g (g - x)``, ``x = clip(x + v, lb, ub)``), then
evaluates particles ``1 .. S`` in order, then updates personal and global bests. So the ``S``
evaluations of one iteration are independent and can be made in one batch without changing the
algorithm. This module therefore calls that same Fortran core with exactly the inputs pyswarm's
``pso`` builds (``rng = numpy.random.default_rng(seed)``; initial positions, velocities and the
per-iteration random factors drawn in pyswarm's order), with its position array passed as a
Fortran-ordered float64 array, which f2py hands to Fortran without copying. When the core asks
for particle 1 of an iteration, all ``S`` positions of that iteration are already in that array:
they are evaluated in one batched call and returned particle by particle. Each position the core
asks for is checked to be bit-identical to the batched one (a mismatch raises ``RuntimeError``),
so the search is pyswarm's, step for step; the test-suite checks that it returns the same best
point as ``pyswarm.pso`` with the same seed. Stopping early on ``target``, on convergence or on a callback
request returns ``+inf`` (pyswarm's "infeasible") for the remaining particles, which never
changes the swarm's bests, instead of raising through Fortran. pyswarm's own ``nit``/``nfev``
are one iteration short when it stops early (minstep/minfunc); counts reported here
come from the recorded evaluations.

References
----------
.. [1] J. Kennedy and R. Eberhart, "Particle swarm optimization", Proc. ICNN, 1995.
.. [2] N. Hansen, "The CMA Evolution Strategy: A Tutorial", arXiv:1604.00772, 2016.
.. [3] pyswarm 1.1.2, https://github.com/eggzec/pyswarm ; cma, https://github.com/CMA-ES/pycma
"""
from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Callable, Optional, Sequence

import numpy as np

from .cmaes import load_cma, run_cmaes
from .pso import run_pso

__all__ = [
    "METHODS",
    "PSO_PAPER_SETTINGS",
    "CMAES_DEFAULT_SIGMA0",
    "StopOptimization",
    "Evaluations",
    "OptimResult",
    "validate_bounds",
    "convergence_iteration",
    "optimize",
    "warm_up",
]

METHODS = ("pso", "cmaes")


def warm_up(*methods: str):
    """Import the optimizer libraries of ``methods`` in a background thread, so that a fit started later does not
    wait for them: CMA-ES's ``cma`` takes 1.3-1.8 s to import, a quarter of the dive-start fit (`uw-sil fit` and the
    backward_fit node call this when they start, before the bag is read or the first frame arrives). A fit that
    starts before the import has ended waits for it (Python's import lock), as it would have without this.
    Returns the thread, or None when no method needs anything imported."""
    import threading

    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown optimizer {unknown[0]!r}; expected one of {', '.join(METHODS)}")
    if "cmaes" not in methods:
        return None                  # PSO is this package's own code (uw_sil.fit.pso)
    t = threading.Thread(target=load_cma, name="uw_sil-warm-up", daemon=True)
    t.start()
    return t


#: The paper's particle swarm settings (read-only).
PSO_PAPER_SETTINGS = MappingProxyType(
    {"swarm_size": 20, "omega": 0.4, "phi_p": 0.3, "phi_g": 0.3, "max_iter": 100}
)

#: Default initial CMA-ES step size, as a fraction of each parameter's range.
CMAES_DEFAULT_SIGMA0 = 0.25

_PSO_OPTIONS = {"minstep": 1e-8, "minfunc": 1e-8}
_CMAES_OPTIONS = {"sigma0": CMAES_DEFAULT_SIGMA0, "cma_options": None, "min_step": 0.0}
_CMA_RESERVED = ("bounds", "seed", "randn", "popsize")


class StopOptimization(Exception):
    """Raise from a ``callback`` to stop the optimization after the current iteration."""


@dataclass
class Evaluations:
    """Every objective evaluation of a run, in order.

    Attributes
    ----------
    x : ndarray, shape (n, d)
        Candidates in the original parameter units.
    f : ndarray, shape (n,)
        Their objective values; non-finite returns are stored as ``-inf``.
    iteration : ndarray of int, shape (n,)
        The iteration (batch) each candidate was evaluated in.
    """

    x: np.ndarray
    f: np.ndarray
    iteration: np.ndarray

    def __len__(self) -> int:
        return int(self.f.shape[0])

    @property
    def batch_sizes(self) -> np.ndarray:
        """Number of evaluations per iteration, shape (n_iters + 1,)."""
        if len(self) == 0:
            return np.zeros(0, dtype=int)
        return np.bincount(self.iteration)


@dataclass
class OptimResult:
    """Outcome of :func:`optimize`.

    Attributes
    ----------
    method : str
        ``"pso"`` or ``"cmaes"``.
    x_best : ndarray, shape (d,)
        Best candidate evaluated (original units); the first one evaluated on ties.
    f_best : float
        Its objective value (the best theta observed).
    n_evals : int
        Number of objective evaluations (``== len(evaluations)``).
    n_iters : int
        Index of the last iteration performed (iteration 0 is the first batch).
    history_best_f : list of float
        Best value after each iteration, length ``n_iters + 1`` (``-inf`` while nothing valid).
    history_best_x : ndarray, shape (n_iters + 1, d)
        Best candidate after each iteration (NaN rows while nothing valid).
    evaluations : Evaluations
        All candidates and values.
    n_invalid : int
        Number of evaluations that returned a non-finite value.
    converged_iter : int
        :func:`convergence_iteration` of ``history_best_f`` with ``tol``.
    tol : float
        Tolerance used for ``converged_iter`` and for the stop on convergence.
    patience : int
        Window of the stop on convergence in iterations (0: no such stop).
    target : float or None
        Requested target value.
    evals_to_target : int or None
        Number of evaluations up to and including the first one with value ``>= target``.
    stop_reason : str
        ``"max_iter"``, ``"target"``, ``"callback"``, ``"converged"`` (see ``patience``), ``"step"``
        (CMA-ES' ``min_step``),
        ``"minfunc"`` / ``"minstep"`` (pyswarm), or ``"cma:<criteria>"`` (cma's own termination).
    wall_time_s : float
        Wall-clock duration of the run.
    seed : int
        Seed actually used (drawn from OS entropy when ``seed=None`` was passed).
    settings : dict
        Method settings, JSON-serializable.
    lower, upper : ndarray, shape (d,)
        Bounds.
    names : tuple of str or None
        Parameter names.
    backend_info : dict
        Raw information from the backend (e.g. pyswarm's own ``nit``, ``nfev``, status).
    """

    method: str
    x_best: np.ndarray
    f_best: float
    n_evals: int
    n_iters: int
    history_best_f: list
    history_best_x: np.ndarray
    evaluations: Evaluations
    n_invalid: int
    converged_iter: int
    tol: float
    patience: int
    target: Optional[float]
    evals_to_target: Optional[int]
    stop_reason: str
    wall_time_s: float
    seed: int
    settings: dict
    lower: np.ndarray
    upper: np.ndarray
    names: Optional[tuple] = None
    backend_info: dict = field(default_factory=dict)

    @property
    def best_params(self) -> Optional[dict]:
        """``{name: value}`` of ``x_best`` when names were given, else None."""
        if self.names is None:
            return None
        return {n: float(v) for n, v in zip(self.names, self.x_best)}

    def to_dict(self, include_evaluations: bool = True) -> dict:
        """JSON-serializable summary (non-finite numbers become ``None``).

        Parameters
        ----------
        include_evaluations : bool, optional
            Include every evaluated candidate and value (``n_evals * (d + 2)`` numbers).
        """
        d = {
            "method": self.method,
            "x_best": _json_list(self.x_best),
            "f_best": _json_float(self.f_best),
            "best_params": self.best_params,
            "n_evals": int(self.n_evals),
            "n_iters": int(self.n_iters),
            "n_invalid": int(self.n_invalid),
            "converged_iter": int(self.converged_iter),
            "tol": float(self.tol),
            "patience": int(self.patience),
            "target": _json_float(self.target),
            "evals_to_target": None if self.evals_to_target is None else int(self.evals_to_target),
            "stop_reason": self.stop_reason,
            "wall_time_s": float(self.wall_time_s),
            "seed": int(self.seed),
            "settings": _json_value(self.settings),
            "lower": _json_list(self.lower),
            "upper": _json_list(self.upper),
            "names": None if self.names is None else list(self.names),
            "history_best_f": _json_list(self.history_best_f),
            "history_best_x": _json_list(self.history_best_x),
            "backend_info": _json_value(self.backend_info),
        }
        if include_evaluations:
            d["evaluations"] = {
                "x": _json_list(self.evaluations.x),
                "f": _json_list(self.evaluations.f),
                "iteration": [int(i) for i in self.evaluations.iteration],
            }
        return d


def _json_float(v):
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def _json_list(a):
    a = np.asarray(a, dtype=float)
    if a.ndim == 0:
        return _json_float(a)
    return [_json_list(r) for r in a] if a.ndim > 1 else [_json_float(v) for v in a]


def _json_value(v):
    if isinstance(v, dict):
        return {str(k): _json_value(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_value(x) for x in v]
    if isinstance(v, np.ndarray):
        return _json_list(v)
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return _json_float(v)
    if v is None or isinstance(v, str):
        return v
    return repr(v)


# --------------------------------------------------------------------------------------------
# Validation and pure helpers
# --------------------------------------------------------------------------------------------


def _label(i: int, names) -> str:
    return f"parameter {i} ({names[i]!r})" if names is not None else f"parameter {i}"


def _validate_names(names, d: int):
    if names is None:
        return None
    if isinstance(names, str):
        raise ValueError("names must be a sequence of strings, not a single string")
    names = tuple(names)
    if len(names) != d:
        raise ValueError(f"got {len(names)} names for {d} parameters")
    for n in names:
        if not isinstance(n, str):
            raise ValueError(f"names must be strings, got {n!r}")
    return names


def validate_bounds(lower, upper, names: Optional[Sequence[str]] = None):
    """Check a box ``lower < upper`` and return it as float arrays.

    Parameters
    ----------
    lower, upper : array_like, shape (d,)
        Finite bounds, ``lower[i] < upper[i]`` strictly for every ``i``; ``d >= 1``.
    names : sequence of str, optional
        Parameter names, used in error messages.

    Returns
    -------
    lower, upper : ndarray of float, shape (d,)
        Copies of the bounds.

    Raises
    ------
    ValueError
        Empty, not 1-D, different lengths, non-finite, or ``lower[i] >= upper[i]`` (the message
        names the offending parameter index and name).
    """
    try:
        lo = np.array(lower, dtype=float)
        hi = np.array(upper, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"bounds must be numeric vectors: {exc}") from None
    if lo.ndim != 1 or hi.ndim != 1:
        raise ValueError(f"bounds must be 1-D vectors, got shapes {lo.shape} and {hi.shape}")
    if lo.size == 0 or hi.size == 0:
        raise ValueError("bounds are empty: need at least one parameter")
    if lo.shape != hi.shape:
        raise ValueError(f"lower has {lo.size} entries but upper has {hi.size}")
    if names is not None:
        names = _validate_names(names, lo.size)
    for i in range(lo.size):
        if not (np.isfinite(lo[i]) and np.isfinite(hi[i])):
            raise ValueError(f"{_label(i, names)}: bounds must be finite, got [{lo[i]}, {hi[i]}]")
        if not lo[i] < hi[i]:
            kind = "empty" if lo[i] == hi[i] else "inverted"
            raise ValueError(
                f"{_label(i, names)}: {kind} bounds, need lower < upper, got [{lo[i]}, {hi[i]}]"
            )
    return lo, hi


def convergence_iteration(history, tol: float = 1e-4) -> int:
    """Iteration at which a best-so-far history stopped improving by more than ``tol``.

    Returns the smallest ``k`` such that ``history[-1] - history[k] <= tol``, i.e. the first
    iteration after which the best value gained at most ``tol`` in total until the end of the
    run (several small gains add up, unlike a per-step test).

    Parameters
    ----------
    history : sequence of float
        Best value after each iteration; non-decreasing, no NaN (``-inf`` allowed for
        iterations before the first valid value).
    tol : float, optional
        Non-negative absolute tolerance on the objective.

    Returns
    -------
    int
        Index into ``history`` (0 when nothing valid was ever found).

    Raises
    ------
    ValueError
        Empty history, NaN or ``+inf`` entries, a decrease, or invalid ``tol``.

    Examples
    --------
    >>> convergence_iteration([0.1, 0.5, 0.8, 0.80005, 0.80008], tol=1e-4)
    2
    """
    h = np.asarray(history, dtype=float)
    if h.ndim != 1 or h.size == 0:
        raise ValueError(f"history must be a non-empty 1-D sequence, got shape {h.shape}")
    if np.isnan(h).any() or (h == np.inf).any():
        raise ValueError("history must not contain NaN or +inf")
    down = h[1:] < h[:-1]
    if down.any():
        k = int(np.flatnonzero(down)[0]) + 1
        raise ValueError(f"history must be non-decreasing (best so far); it decreases at index {k}")
    tol = float(tol)
    if not (math.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol must be finite and >= 0, got {tol}")
    final = h[-1]
    if final == -np.inf:
        return 0
    return int(np.flatnonzero(final - h <= tol)[0])


def _check_int(name, v, minimum):
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
        raise ValueError(f"{name} must be an integer, got {v!r}")
    if v < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {v}")
    return int(v)


def _check_float(name, v, minimum=None, strict=False):
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {v!r}") from None
    if isinstance(v, (bool, np.bool_)) or not math.isfinite(f):
        raise ValueError(f"{name} must be a finite number, got {v!r}")
    if minimum is not None and (f <= minimum if strict else f < minimum):
        raise ValueError(f"{name} must be {'>' if strict else '>='} {minimum}, got {f}")
    return f


def _method_options(method: str, options: dict) -> dict:
    allowed = _PSO_OPTIONS if method == "pso" else _CMAES_OPTIONS
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise TypeError(
            f"unknown option(s) for method {method!r}: {unknown}; accepted: {sorted(allowed)}"
        )
    out = dict(allowed)
    out.update(options)
    if method == "pso":
        out["minstep"] = _check_float("minstep", out["minstep"], 0.0)
        out["minfunc"] = _check_float("minfunc", out["minfunc"], 0.0)
    else:
        out["sigma0"] = _check_float("sigma0", out["sigma0"], 0.0, strict=True)
        out["min_step"] = _check_float("min_step", out["min_step"], 0.0)
        cma_opts = out["cma_options"]
        if cma_opts is None:
            cma_opts = {}
        if not isinstance(cma_opts, dict):
            raise ValueError(f"cma_options must be a dict, got {type(cma_opts).__name__}")
        reserved = sorted(set(cma_opts) & set(_CMA_RESERVED))
        if reserved:
            raise ValueError(
                f"cma_options {reserved} are set by optimize() (bounds, seed, swarm_size); "
                "pass them through its arguments"
            )
        out["cma_options"] = dict(cma_opts)
    return out


# --------------------------------------------------------------------------------------------
# The evaluation recorder, shared by both methods
# --------------------------------------------------------------------------------------------


class _Recorder:
    """Evaluates batches of normalized candidates, records them, and handles stop requests."""

    def __init__(self, objective, lo, hi, target, callback, bar, tol=0.0, patience=0):
        self.objective = objective
        self.tol, self.patience = tol, patience
        self.lo, self.hi = lo, hi
        self.span = hi - lo
        self.d = lo.size
        self.target = target
        self.callback = callback
        self.bar = bar
        self.xs, self.fs = [], []
        self.n_evals = 0
        self.iteration = -1
        self.best_f = -np.inf
        self.best_x = np.full(self.d, np.nan)
        self.history_f, self.history_x = [], []
        self.evals_to_target = None
        self.stop_reason = None

    def to_original(self, u: np.ndarray) -> np.ndarray:
        return np.clip(self.lo + u * self.span, self.lo, self.hi)

    def evaluate(self, u: np.ndarray) -> np.ndarray:
        """theta for normalized candidates ``u`` (N, d); non-finite -> -inf. Records everything."""
        x = self.to_original(np.asarray(u, dtype=float))
        n = x.shape[0]
        out = self.objective(x.copy())
        try:
            f = np.asarray(out, dtype=float)
        except (TypeError, ValueError):
            raise TypeError(
                f"objective must return {n} real numbers, got {type(out).__name__}"
            ) from None
        if f.shape != (n,):
            raise ValueError(
                f"objective must return an array of shape ({n},) for a batch of {n} candidates, "
                f"got shape {f.shape}"
            )
        f = np.where(np.isfinite(f), f, -np.inf)
        self.iteration += 1
        self.xs.append(x)
        self.fs.append(f)
        n_before = self.n_evals
        self.n_evals += n
        j = int(np.argmax(f))  # first maximum
        if f[j] > self.best_f:
            self.best_f = float(f[j])
            self.best_x = x[j].copy()
        self.history_f.append(self.best_f)
        self.history_x.append(self.best_x.copy())
        if self.target is not None and self.evals_to_target is None:
            hit = np.flatnonzero(f >= self.target)
            if hit.size:
                self.evals_to_target = n_before + int(hit[0]) + 1
                self.stop_reason = "target"
        k = self.iteration
        if (self.patience and self.stop_reason is None and k >= self.patience
                and self.history_f[k] - self.history_f[k - self.patience] <= self.tol):
            self.stop_reason = "converged"      # -inf - -inf is NaN: never while nothing valid was seen
        if self.bar is not None:
            self.bar.set_postfix(best=f"{self.best_f:.5f}", evals=self.n_evals, refresh=False)
            self.bar.update(1)
        if self.callback is not None:
            try:
                stop = self.callback(self.iteration, self.best_x.copy(), self.best_f)
            except StopOptimization:
                stop = True
            if stop and self.stop_reason is None:
                self.stop_reason = "callback"
        return f

    @property
    def stopped(self) -> bool:
        return self.stop_reason is not None


# --------------------------------------------------------------------------------------------
# Public entry point
# --------------------------------------------------------------------------------------------


def optimize(
    objective: Callable[[np.ndarray], np.ndarray],
    lower,
    upper,
    method: str = "pso",
    seed: Optional[int] = None,
    max_iter: int = PSO_PAPER_SETTINGS["max_iter"],
    swarm_size: Optional[int] = None,
    omega: Optional[float] = None,
    phi_p: Optional[float] = None,
    phi_g: Optional[float] = None,
    tol: float = 1e-4,
    patience: int = 0,
    target: Optional[float] = None,
    progress: bool = False,
    callback: Optional[Callable[[int, np.ndarray, float], Optional[bool]]] = None,
    names: Optional[Sequence[str]] = None,
    x0=None,
    **method_options,
) -> OptimResult:
    """Maximize a batched objective in a box with PSO (paper) or CMA-ES.

    Parameters
    ----------
    objective : callable
        ``objective(X) -> f`` with ``X`` of shape (N, d) in original units (a fresh copy) and
        ``f`` of shape (N,); larger is better. Non-finite values mark degenerate candidates
        (recorded as ``-inf``, ranked worst).
    lower, upper : array_like, shape (d,)
        Finite bounds, ``lower < upper`` (see :func:`validate_bounds`).
    method : {"pso", "cmaes"}, optional
        Optimizer (see module docstring).
    seed : int, optional
        Seed (``>= 0``); ``None`` draws one from OS entropy (reported in the result).
    max_iter : int, optional
        Iterations after iteration 0 (default 100 as in the paper): at most ``max_iter + 1``
        batched calls.
    swarm_size : int, optional
        PSO swarm size (default 20) or CMA-ES population size (default ``4 + floor(3 ln d)``).
    omega, phi_p, phi_g : float, optional
        PSO inertia, cognitive and social coefficients (defaults 0.4, 0.3, 0.3). PSO only:
        passing them with ``method="cmaes"`` is an error.
    tol : float, optional
        Absolute tolerance on the objective, for ``converged_iter`` (reported) and for the stop on
        convergence (with ``patience``).
    patience : int, optional
        Stop on convergence: stop after the first iteration ``k >= patience`` with
        ``best(k) - best(k - patience) <= tol``, i.e. when the best value gained no more than
        ``tol`` over the last ``patience`` iterations (``stop_reason "converged"``). 0 (default)
        disables it: the run goes to ``max_iter`` unless another rule stops it.
    target : float, optional
        Stop after the first iteration in which a value ``>= target`` was seen.
    progress : bool, optional
        Show progress on stderr (iterations; best value and evaluations): a tqdm bar on a terminal,
        plain lines elsewhere (:func:`uw_sil._shared.progress.progress_bar`).
    callback : callable, optional
        ``callback(iteration, best_x, best_f)`` after every iteration (``best_x`` is a copy in
        original units, NaN while nothing valid was seen). Returning a true value or raising
        :class:`StopOptimization` stops the run; other exceptions (also ``KeyboardInterrupt``)
        propagate and leave no state behind.
    names : sequence of str, optional
        Parameter names, used in messages and :attr:`OptimResult.best_params`.
    x0 : array_like, optional
        Starting point(s) in original units, within the bounds. PSO: shape (d,) or (k, d) with
        ``k <= swarm_size``, replacing the first random particles of the initial swarm. CMA-ES:
        shape (d,), the initial mean (default: the centre of the box), also evaluated in the first
        generation (injected), so the result is never worse than x0.
    **method_options
        PSO: ``minstep`` and ``minfunc`` (pyswarm's stopping thresholds, default 1e-8, on the
        normalized box and on the objective). CMA-ES: ``sigma0`` (initial step size as a
        fraction of each range, default 0.25), ``cma_options`` (dict passed to
        ``cma.CMAEvolutionStrategy``, e.g. ``{"tolfun": 0}``), ``min_step`` (stop with
        ``stop_reason "step"`` once the search distribution's largest coordinate standard deviation, in
        the box normalized to [0, 1], is below it: the search has collapsed; default 0, off).

    Returns
    -------
    OptimResult

    Raises
    ------
    ValueError
        Invalid bounds, settings, ``x0`` or objective output; unknown method.
    TypeError
        Unknown ``method_options`` or a non-callable objective/callback.
    RuntimeError
        No evaluation returned a finite value, or pyswarm's core behaved unexpectedly.
    """
    t0 = time.perf_counter()
    if not callable(objective):
        raise TypeError("objective must be callable")
    if callback is not None and not callable(callback):
        raise TypeError("callback must be callable or None")
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {METHODS}")
    lo, hi = validate_bounds(lower, upper, names)
    d = lo.size
    names = _validate_names(names, d)
    max_iter = _check_int("max_iter", max_iter, 1)
    tol = _check_float("tol", tol, 0.0)
    patience = _check_int("patience", patience, 0)
    if target is not None:
        target = _check_float("target", target)
    if seed is None:
        seed = int(np.random.SeedSequence().generate_state(1)[0])
    else:
        seed = _check_int("seed", seed, 0)
    opts = _method_options(method, method_options)

    if method == "pso":
        s = _check_int("swarm_size", PSO_PAPER_SETTINGS["swarm_size"]
                       if swarm_size is None else swarm_size, 2)
        omega = _check_float("omega", PSO_PAPER_SETTINGS["omega"] if omega is None else omega)
        phi_p = _check_float("phi_p", PSO_PAPER_SETTINGS["phi_p"] if phi_p is None else phi_p)
        phi_g = _check_float("phi_g", PSO_PAPER_SETTINGS["phi_g"] if phi_g is None else phi_g)
    else:
        given = [n for n, v in (("omega", omega), ("phi_p", phi_p), ("phi_g", phi_g)) if v is not None]
        if given:
            raise ValueError(f"{given} are PSO settings; they do not apply to method 'cmaes'")
        s = None if swarm_size is None else _check_int("swarm_size", swarm_size, 2)

    u0 = None
    if x0 is not None:
        x0a = np.array(x0, dtype=float)
        if x0a.ndim == 1:
            x0a = x0a[None]
        max_rows = s if method == "pso" else 1
        if x0a.ndim != 2 or x0a.shape[1] != d or not 1 <= x0a.shape[0] <= max_rows:
            raise ValueError(
                f"x0 must have shape ({d},)" + (f" or (k, {d}) with k <= {s}" if method == "pso" else "")
                + f", got {np.shape(x0)}"
            )
        for i in range(d):
            col = x0a[:, i]
            if not np.all(np.isfinite(col)) or np.any(col < lo[i]) or np.any(col > hi[i]):
                raise ValueError(f"x0: {_label(i, names)} = {col.tolist()} outside [{lo[i]}, {hi[i]}]")
        u0 = np.clip((x0a - lo) / (hi - lo), 0.0, 1.0)

    settings = {"max_iter": max_iter, "tol": tol, "patience": patience, "search_space": "normalized to [0, 1]^d"}
    if method == "pso":
        settings.update(swarm_size=s, omega=omega, phi_p=phi_p, phi_g=phi_g,
                        minstep=opts["minstep"], minfunc=opts["minfunc"],
                        paper_settings=(s == PSO_PAPER_SETTINGS["swarm_size"]
                                        and patience == 0
                                        and omega == PSO_PAPER_SETTINGS["omega"]
                                        and phi_p == PSO_PAPER_SETTINGS["phi_p"]
                                        and phi_g == PSO_PAPER_SETTINGS["phi_g"]
                                        and max_iter == PSO_PAPER_SETTINGS["max_iter"]),
                        backend="pyswarm")
    else:
        settings.update(swarm_size=s, sigma0=opts["sigma0"], cma_options=opts["cma_options"], min_step=opts["min_step"],
                        x0="given" if u0 is not None else "centre of the bounds", backend="cma")

    bar = None
    if progress:
        from .._shared.progress import progress_bar

        # On a terminal a live bar; in logs (CI, launch files, pipes) a plain line every few seconds.
        bar = progress_bar(max_iter + 1, method, unit="it", file=sys.stderr)
    rec = _Recorder(objective, lo, hi, target, callback, bar, tol, patience)
    try:
        if method == "pso":
            info = run_pso(rec, seed, s, omega, phi_p, phi_g, max_iter, opts, u0)
        else:
            info = run_cmaes(rec, seed, s, max_iter, opts, u0)
            settings["swarm_size"] = info["popsize"]
    finally:
        if bar is not None:
            bar.close()

    if not np.isfinite(rec.best_f):
        raise RuntimeError(
            f"all {rec.n_evals} evaluations returned non-finite values; nothing to report"
        )
    x_all = np.concatenate(rec.xs, axis=0)
    f_all = np.concatenate(rec.fs, axis=0)
    it_all = np.concatenate([np.full(len(f), k, dtype=int) for k, f in enumerate(rec.fs)])
    return OptimResult(
        method=method,
        x_best=rec.best_x.copy(),
        f_best=float(rec.best_f),
        n_evals=int(rec.n_evals),
        n_iters=int(rec.iteration),
        history_best_f=[float(v) for v in rec.history_f],
        history_best_x=np.array(rec.history_x),
        evaluations=Evaluations(x=x_all, f=f_all, iteration=it_all),
        n_invalid=int(np.sum(f_all == -np.inf)),
        converged_iter=convergence_iteration(rec.history_f, tol),
        tol=tol,
        patience=patience,
        target=target,
        evals_to_target=rec.evals_to_target,
        stop_reason=rec.stop_reason,
        wall_time_s=time.perf_counter() - t0,
        seed=seed,
        settings=settings,
        lower=lo,
        upper=hi,
        names=names,
        backend_info=info,
    )
