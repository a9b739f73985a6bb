"""Benchmark: the paper's PSO vs CMA-ES on noisy 7-D test functions shaped like the backward problem.

Each test function is a similarity-like score in [0, 1] (maximum 1 at a known point ``c``) over the
simulator's default 7-parameter box ``[0, 1]^6 x [0, 0.5]``, observed with additive Gaussian noise.
For every function and seed:

* ``pso``: the paper's settings (20 particles, omega 0.4, phi_p = phi_g = 0.3, 100 iterations,
  i.e. at most 2020 evaluations; pyswarm may stop earlier on its minstep/minfunc rules);
* ``cmaes``: defaults of :func:`uw_sil.fit.optimize.optimize` with the same 2020-evaluation budget;
* ``cmaes->pso``: CMA-ES with ``target`` = the PSO run's final (observed, noisy) best theta, i.e.
  "evaluations CMA-ES needs to reach what the paper's PSO ends with"; compared with the
  evaluations PSO itself needed to first reach that value.

Evaluations-to-target use the noise-free score of the incumbent (the best *observed* candidate so
far), so noise luck does not count as progress. Run::

    .venv/bin/python bench/bench_optimizers.py [--seeds 10] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from uw_sil.fit.optimize import PSO_PAPER_SETTINGS, optimize  # noqa: E402

LO = np.zeros(7)
HI = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.5])
SPAN = HI - LO
C = np.array([0.35, 0.62, 0.18, 0.41, 0.73, 0.55, 0.08])
BUDGET = PSO_PAPER_SETTINGS["swarm_size"] * (PSO_PAPER_SETTINGS["max_iter"] + 1)  # 2020
LEVELS = (0.9, 0.95, 0.99)


def _rotation(d, seed):
    q, r = np.linalg.qr(np.random.default_rng(seed).standard_normal((d, d)))
    return q * np.sign(np.diag(r))


_R = _rotation(7, 42)
_SCALES = 0.4 * np.logspace(0, -0.5, 7)  # widths 0.4 .. 0.13 of the range: condition 10


def peak(X):
    """Isotropic Gaussian peak, width 0.3 of each range."""
    return np.exp(-np.sum(((X - C) / (0.3 * SPAN)) ** 2, axis=-1))


def coupled(X):
    """Rotated, ill-conditioned, heavy-tailed peak (coupled parameters, like attenuation vs background)."""
    z = ((X - C) / SPAN) @ _R.T / _SCALES
    return 1.0 / (1.0 + np.sum(z**2, axis=-1))


def bowl(X):
    """Concave quadratic, broad."""
    return 1.0 - np.mean(((X - C) / SPAN) ** 2, axis=-1)


def rippled(X):
    """Gaussian peak with cosine ripples (local maxima)."""
    z = (X - C) / SPAN
    return np.exp(-np.sum((z / 0.4) ** 2, axis=-1)) * (0.85 + 0.15 * np.prod(np.cos(12 * np.pi * z), axis=-1))


FUNCTIONS = {"peak": peak, "coupled": coupled, "bowl": bowl, "rippled": rippled}


def noisy(f, sd, seed):
    rng = np.random.default_rng(seed)
    return lambda X: f(X) + sd * rng.standard_normal(len(X))


def incumbent_true(res, f):
    """Noise-free score of the best observed candidate after each evaluation."""
    ev = res.evaluations
    best_idx = np.zeros(len(ev), dtype=int)
    b = 0
    for i in range(len(ev)):
        if ev.f[i] > ev.f[b]:
            b = i
        best_idx[i] = b
    return f(ev.x)[best_idx]


def evals_to(curve, level):
    hit = np.flatnonzero(curve >= level)
    return int(hit[0]) + 1 if hit.size else None


def run(seeds, sd):
    rows = []
    for fi, (fname, f) in enumerate(FUNCTIONS.items()):
        for seed in range(seeds):
            row = {"function": fname, "seed": seed}
            nseed = 10000 * (fi + 1) + seed  # noise stream per function and seed
            pso = optimize(noisy(f, sd, nseed), LO, HI, method="pso", seed=seed)
            cm = optimize(noisy(f, sd, nseed), LO, HI, method="cmaes", seed=seed,
                          max_iter=BUDGET // 9 - 1)
            for tag, res in (("pso", pso), ("cmaes", cm)):
                curve = incumbent_true(res, f)
                row[tag] = {
                    "n_evals": res.n_evals, "stop": res.stop_reason,
                    "final_true": float(curve[-1]), "f_best_observed": res.f_best,
                    "converged_iter": res.converged_iter, "wall_s": res.wall_time_s,
                    **{f"evals_to_{lv}": evals_to(curve, lv) for lv in LEVELS},
                }
            # CMA-ES evaluations to reach the PSO's final observed best theta
            tgt = optimize(noisy(f, sd, nseed + 5000), LO, HI, method="cmaes", seed=seed,
                           target=pso.f_best, max_iter=BUDGET // 9 - 1)
            row["target"] = pso.f_best
            row["pso_evals_to_own_final"] = int(np.argmax(pso.evaluations.f)) + 1
            row["cmaes_evals_to_pso_final"] = tgt.evals_to_target
            rows.append(row)
    return rows


def _median(vals):
    v = [x for x in vals if x is not None]
    return (float(np.median(v)) if v else None), len(v)


def summarize(rows, seeds):
    lines = [f"{'function':9s} {'method':6s} {'final true theta (median, min)':>31s}  "
             + "  ".join(f"evals->{lv} (med, hits)" for lv in LEVELS)]
    for fname in FUNCTIONS:
        rs = [r for r in rows if r["function"] == fname]
        for m in ("pso", "cmaes"):
            fin = [r[m]["final_true"] for r in rs]
            cols = []
            for lv in LEVELS:
                med, n = _median([r[m][f"evals_to_{lv}"] for r in rs])
                cols.append(f"{'-' if med is None else f'{med:.0f}':>8s} ({n}/{seeds})       ")
            lines.append(f"{fname:9s} {m:6s} {np.median(fin):20.4f} {min(fin):10.4f}  " + "  ".join(cols))
        pso_med, _ = _median([r["pso_evals_to_own_final"] for r in rs])
        cm_med, n = _median([r["cmaes_evals_to_pso_final"] for r in rs])
        stops = sorted({r["pso"]["stop"] for r in rs})
        lines.append(f"{'':9s} to PSO's final observed theta: PSO {pso_med:.0f} evals, CMA-ES "
                     f"{'-' if cm_med is None else f'{cm_med:.0f}'} evals ({n}/{seeds} reached); "
                     f"PSO stops: {stops}")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--noise", type=float, default=0.005, help="sd of the additive noise on theta")
    ap.add_argument("--json", type=Path, help="write all per-run numbers here")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = run(a.seeds, a.noise)
    print(f"7-D, noise sd {a.noise}, {a.seeds} seeds, budget {BUDGET} evaluations "
          f"(PSO paper settings {dict(PSO_PAPER_SETTINGS)}; CMA-ES popsize 9, sigma0 0.25)")
    print(summarize(rows, a.seeds))
    print(f"[{time.perf_counter() - t0:.1f} s]")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
