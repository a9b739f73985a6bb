"""CMA-ES by ``cma`` (ask/tell), one batched call of the objective per generation: the faster
alternative to the paper's PSO. Called by :func:`uw_sil.fit.optimize.optimize` (``method='cmaes'``).

References
----------
.. [1] N. Hansen, "The CMA Evolution Strategy: A Tutorial", arXiv:1604.00772, 2016.
.. [2] cma, https://github.com/CMA-ES/pycma
"""
from __future__ import annotations

import numpy as np

__all__ = ["run_cmaes", "load_cma"]


def load_cma():
    """The ``cma`` module, imported on first use: its import takes 1.3-1.8 s here (it pulls in scipy.stats and
    matplotlib), which a process that never runs CMA-ES should not pay, and which a process that will should
    pay before its fit starts (:func:`uw_sil.fit.optimize.warm_up`)."""
    import cma

    return cma


def run_cmaes(rec, seed, popsize, max_iter, opts, u0):
    """CMA-ES by ``cma`` (ask/tell), one batched call per generation."""
    cma = load_cma()

    d = rec.d
    rng = np.random.default_rng(seed)
    inopts = {
        "bounds": [[0.0] * d, [1.0] * d],
        # Private generator: cma then neither seeds nor draws from numpy's global RNG.
        "randn": lambda *shape: rng.standard_normal(shape),
        "seed": np.nan,
        "verbose": -9,
        "verb_disp": 0,
        "verb_log": 0,
        "signals_filename": "",
    }
    if popsize is not None:
        inopts["popsize"] = popsize
    inopts.update(opts["cma_options"])
    mean0 = np.full(d, 0.5) if u0 is None else u0[0]
    es = cma.CMAEvolutionStrategy(mean0, opts["sigma0"], inopts)
    if u0 is not None:
        # The mean itself is never sampled; inject it so that the first generation evaluates x0
        # (a good start must not be lost: the result is never worse than x0).
        es.inject([u0[0]], force=True)
    sigmas = []     # largest coordinate-wise standard deviation of the search distribution, per generation
    while True:
        sols = es.ask()
        f = rec.evaluate(np.array(sols, dtype=float))
        # cma minimizes; invalid -> worse than the worst finite value of the batch.
        loss = -f
        bad = ~np.isfinite(loss)
        if bad.any():
            good = loss[~bad]
            worst = float(good.max()) if good.size else 0.0
            spread = float(good.max() - good.min()) if good.size else 0.0
            loss[bad] = worst + 1.0 + spread
        es.tell(sols, loss.tolist())
        sigmas.append(float(np.max(es.stds)))
        if rec.stopped:
            break
        if opts.get("min_step") and sigmas[-1] < opts["min_step"]:
            rec.stop_reason = "step"    # the search distribution has collapsed: no coordinate moves by more
            break
        if rec.iteration >= max_iter:
            rec.stop_reason = "max_iter"
            break
        stop = es.stop()
        if stop:
            rec.stop_reason = "cma:" + ",".join(sorted(str(k) for k in stop))
            break
    return {"cma_version": cma.__version__, "popsize": int(es.popsize),
            "cma_iterations": int(es.countiter), "final_sigma": float(es.sigma),
            "step_history": sigmas}
