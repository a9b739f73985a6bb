"""The paper's optimizer: particle swarm optimization by pyswarm 1.1.2, driven with batched evaluations.

pyswarm evaluates one particle at a time through its Fortran core; :func:`run_pso` gives it the
whole swarm's values from one batched call of the objective per iteration (the core moves all
particles in place before asking for the first one), and checks that assumption at every call.
Called by :func:`uw_sil.fit.optimize.optimize` (``method='pso'``), which owns the recording of
evaluations, the stop on convergence and the result.

References
----------
.. [1] J. Kennedy and R. Eberhart, "Particle swarm optimization", Proc. ICNN, 1995.
.. [2] pyswarm 1.1.2, https://github.com/eggzec/pyswarm
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["run_pso", "PYSWARM_VERSION"]

PYSWARM_VERSION = "1.1.2"


def run_pso(rec, seed, s, omega, phi_p, phi_g, max_iter, opts, u0):
    """Drive pyswarm's Fortran core with batched evaluations; returns pyswarm's own counts.

    ``rec`` is the recorder of :func:`uw_sil.fit.optimize.optimize` (``d``, ``evaluate(batch)``,
    ``stopped``, ``stop_reason``, ``best_f``); positions are on the normalized box [0, 1]^d.
    """
    import pyswarm
    from pyswarm._pyswarm import pso as pyswarm_core

    if pyswarm.__version__ != PYSWARM_VERSION:
        raise RuntimeError(
            f"uw_sil.fit.optimize drives the core of pyswarm {PYSWARM_VERSION}, found "
            f"pyswarm {pyswarm.__version__}"
        )
    d = rec.d
    lb, ub = np.zeros(d), np.ones(d)
    # Exactly pyswarm.pso's set-up (1.1.2), on the normalized box.
    rng = np.random.default_rng(seed)
    vhigh = np.abs(ub - lb)
    x = lb + rng.random((s, d)) * (ub - lb)
    if u0 is not None:
        x[: u0.shape[0]] = u0  # as pyswarm's ``init``: the first particles start at x0
    x = np.asfortranarray(x, dtype=np.float64)
    v = np.asfortranarray(rng.uniform(-vhigh, vhigh, size=(s, d)))
    rnd_p = np.asfortranarray(rng.random((max_iter, s, d)))
    rnd_g = np.asfortranarray(rng.random((max_iter, s, d)))

    state = {"calls": 0, "batch": None, "f": None}

    def particle_value(xtmp, ndim):
        k = state["calls"]
        state["calls"] = k + 1
        if rec.stopped:
            # pyswarm treats values >= 1e300 as infeasible: never a personal or global best
            return math.inf
        i = k % s
        if i == 0:
            # All S positions of this iteration are already in ``x`` (Fortran works in place).
            batch = np.array(x, dtype=float, order="C")
            state["batch"] = batch
            state["f"] = rec.evaluate(batch)
        if not np.array_equal(xtmp, state["batch"][i]):
            raise RuntimeError(
                "pyswarm asked for a position that differs from the batched one "
                f"(call {k}, particle {i}); its core no longer works in place as expected"
            )
        fi = state["f"][i]
        return -float(fi) if np.isfinite(fi) else math.inf

    x_out, _, _, fg, _, _, niters, status = pyswarm_core(
        particle_value, lb, ub, x, v, rnd_p, rnd_g,
        float(omega), float(phi_p), float(phi_g),
        float(opts["minstep"]), float(opts["minfunc"]), 0, 0,  # pyswarm's patience: see _Recorder
        np.empty(0, dtype=np.int32),
    )
    if not np.shares_memory(x_out, x):
        raise RuntimeError("pyswarm's core copied the position array; batched evaluation invalid")
    reason = {0: "max_iter", 1: "minstep", 2: "minfunc", 3: "patience"}.get(int(status))
    if reason is None:
        raise RuntimeError(f"unknown pyswarm status {status}")
    if not rec.stopped:
        rec.stop_reason = reason
        if np.isfinite(rec.best_f) and -fg != rec.best_f:
            raise RuntimeError(
                f"pyswarm's best {-fg} differs from the best recorded evaluation {rec.best_f}"
            )
    info = {
        "pyswarm_version": pyswarm.__version__,
        "pyswarm_nit": int(niters),
        "pyswarm_nfev": int(s + niters * s),
        "pyswarm_status": int(status),
        "pyswarm_calls": int(state["calls"]),
    }
    return info
