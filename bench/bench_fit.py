"""Backward optimization speed: the paper's PSO (20 particles x 100 iterations, random swarm) on 640x480
frames with K = 1 and K = 3, CMA-ES (from the centre of the bounds, like the PSO) run until it reaches
the PSO's final θ (evaluations, wall time, ratio), and the default fit (CMA-ES from the linear start; its
speed against earlier code: bench_fit_speed.py).

    .venv/bin/python bench/bench_fit.py [--frames-in-trial 30] [--seed 0]

Goals (issue 4): paper PSO <= 30 s wall on 2 cores; CMA-ES reaching the same θ at least 5x sooner.
The last line prints the ratio PSO wall time / CMA-ES wall time to the PSO's θ (K = 1).
"""
import argparse
import os
import sys
import tempfile
import time

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import cma  # noqa: E402,F401  -- imported once here, outside the timings (its first import takes ~1.5 s)
import numpy as np  # noqa: E402

from uw_sil.fit.backward import fit_frames, select_frames  # noqa: E402
from uw_sil.bags import read_samples  # noqa: E402
from uw_sil.sim.render import Renderer  # noqa: E402
from uw_sil.bags.synth import DEFAULT_TRUTH, synthesize_trial  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames-in-trial", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        bag = os.path.join(d, "trial.mcap")
        t = time.perf_counter()
        synthesize_trial(bag, n_frames=args.frames_in_trial, seed=args.seed)
        print(f"synthesized {args.frames_in_trial} frames 640x480 in {time.perf_counter() - t:.1f} s")
        with Renderer() as r:
            samples = list(read_samples(bag))
            sel3 = select_frames(samples, r, k=3, stride=max(1, args.frames_in_trial // 3)).frames
            sel1 = select_frames(samples[args.frames_in_trial // 2:], r, k=1).frames
    truth = DEFAULT_TRUTH.as_vector()
    ratio1 = None
    for name, frames in (("K=1", sel1), ("K=3", sel3)):
        pso = fit_frames(frames, method="pso", seed=args.seed, x0=None)          # the paper: random swarm
        err = np.abs(pso.params.as_vector() - truth)
        print(f"[{name}] paper PSO (20 x {pso.optim.n_iters} it, {pso.optim.n_evals} evals): "
              f"{pso.wall_time_s:.1f} s wall, θ = {pso.theta_best:.5f}, converged at iteration "
              f"{pso.optim.converged_iter}, stop: {pso.optim.stop_reason}; |error| a {err[:3].round(3)}, "
              f"b {err[3:6].round(3)}, rho {err[6]:.3f}  ({1e3 * pso.wall_time_s / pso.optim.n_evals:.1f} ms/eval)")
        cmaes_fit = fit_frames(frames, method="cmaes", seed=args.seed, max_iter=1000, target=pso.theta_best, x0=None)
        reached = cmaes_fit.optim.evals_to_target
        err = np.abs(cmaes_fit.params.as_vector() - truth)
        print(f"[{name}] CMA-ES to the PSO's θ: {'reached' if reached else 'NOT reached'} after "
              f"{reached or cmaes_fit.optim.n_evals} evaluations, {cmaes_fit.wall_time_s:.1f} s wall, θ = {cmaes_fit.theta_best:.5f}; "
              f"|error| a {err[:3].round(3)}, b {err[3:6].round(3)}, rho {err[6]:.3f}")
        ratio = pso.wall_time_s / cmaes_fit.wall_time_s
        evals_ratio = pso.optim.n_evals / (reached or cmaes_fit.optim.n_evals)
        print(f"[{name}] PSO/CMA-ES: wall time ratio {ratio:.1f}x, evaluations ratio {evals_ratio:.1f}x")
        if name == "K=1":
            ratio1 = ratio
        lin = fit_frames(frames, method="cmaes", seed=args.seed, max_iter=40)
        err = np.abs(lin.params.as_vector() - truth)
        print(f"[{name}] CMA-ES from the linear start (default stop, at most 40 iterations): {lin.optim.n_iters} it "
              f"({lin.optim.stop_reason}), {lin.optim.n_evals} evals, {lin.wall_time_s:.1f} s, "
              f"θ = {lin.theta_best:.5f}; |error| a {err[:3].round(3)}, b {err[3:6].round(3)}, rho {err[6]:.3f}")
    print(f"ratio PSO wall / CMA-ES wall to the same θ (K=1): {ratio1:.1f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
