"""What a stop on convergence (tol, patience) would save, and cost, on full-length backward fits.

For each seed: synthesize a trial (random ground truth, as bench_recovery.py), fit it to ``--max-iter``
iterations without any early stop (``patience=0``), once per method, and record the best θ and the best
parameters after every iteration. Then, for each (tol, patience) of a grid, replay the rule of
:func:`uw_sil.fit.optimize.optimize` on the recorded history: where it would have stopped, the θ it would have
given up (final best minus best at the stop), how far the parameters at the stop are from the final ones
(in units of the recovery tolerances: a 5 %, b 0.01, fog 10 %) and whether recovery (all three within
tolerance) changes. Histories are saved as JSON (``--save``) and can be re-analysed (``--load``).

    .venv/bin/python bench/bench_convergence.py [--seeds 4] [--width 320] [--methods cmaes,pso] [--sigma0 S] [--save h.json]
    .venv/bin/python bench/bench_convergence.py --load h.json
"""
import argparse
import json
import os
import sys
import tempfile
import time

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np  # noqa: E402

TOLS = (1e-5, 3e-5, 1e-4, 3e-4)
PATIENCES = (5, 10, 15, 20, 30)


def stop_iteration(h, tol, patience):
    h = np.asarray(h)
    for k in range(patience, len(h)):
        if h[k] - h[k - patience] <= tol:
            return k
    return len(h) - 1


def run(args):
    from bench_recovery import random_truth

    from uw_sil.fit.backward import fit_frames, select_frames
    from uw_sil.bags import read_samples
    from uw_sil.sim.camera import CameraModel
    from uw_sil.sim.render import Renderer
    from uw_sil.bags.synth import synthesize_trial

    cam = CameraModel.from_fov(args.width, args.width * 3 // 4, 70.0)
    runs = []
    for seed in range(args.seeds):
        truth = random_truth(np.random.default_rng(1000 + seed))
        with tempfile.TemporaryDirectory() as d:
            bag = os.path.join(d, "trial.mcap")
            synthesize_trial(bag, n_frames=11, seed=seed, params=truth, camera=cam, start_m=3.5, end_m=1.2)
            with Renderer(camera=cam) as r:
                frames = select_frames(read_samples(bag), r, k=3, stride=5).frames
        for method in args.methods.split(","):
            t = time.perf_counter()
            extra = {}
            if method == "cmaes" and args.sigma0 is not None:
                extra["sigma0"] = args.sigma0
            if method == "cmaes" and args.cma_stds:
                extra["cma_options"] = {"CMA_stds": [float(v) for v in args.cma_stds.split(",")]}
            fit = fit_frames(frames, method=method, seed=seed, max_iter=args.max_iter, patience=0, **extra)
            wall = time.perf_counter() - t
            o = fit.optim
            runs.append({"seed": seed, "method": method + "".join(f" {k}={v}" for k, v in extra.items()), "truth": truth.as_vector().tolist(), "wall_s": wall,
                         "n_iters": o.n_iters, "stop_reason": o.stop_reason,
                         "history_best_f": list(o.history_best_f), "history_best_x": o.history_best_x.tolist()})
            print(f"seed {seed} {method}: θ {o.history_best_f[0]:.5f} -> {o.f_best:.5f}, {o.n_iters} it "
                  f"({o.stop_reason}), {wall:.1f} s", flush=True)
    return runs


def tolerances(truth):
    """The recovery tolerances per parameter: a 5 % relative, b 0.01, fog 10 % relative."""
    truth = np.asarray(truth)
    return np.concatenate([0.05 * truth[:3], [0.01] * 3, [0.10 * truth[6]]])


def scaled_error(x, truth):
    """Errors in units of the recovery tolerances (<= 1: within)."""
    return np.abs(np.asarray(x) - np.asarray(truth)) / tolerances(truth)


def analyse(runs):
    for method in sorted({r["method"] for r in runs}):
        rs = [r for r in runs if r["method"] == method]
        print(f"\n{method}: {len(rs)} runs of up to {max(r['n_iters'] for r in rs)} iterations, "
              f"{np.mean([r['wall_s'] / (r['n_iters'] + 1) for r in rs]):.2f} s per iteration; recovered at the end: "
              f"{sum(bool((scaled_error(r['history_best_x'][-1], r['truth']) <= 1).all()) for r in rs)}/{len(rs)}")
        print("   tol  patience | stop it (mean, max) | saved it | θ given up (max) | param move / tolerance (max) | recovery changed")
        for tol in TOLS:
            for p in PATIENCES:
                stops, lost, moved, changed = [], [], [], 0
                for r in rs:
                    h, X = r["history_best_f"], np.asarray(r["history_best_x"])
                    k = stop_iteration(h, tol, p)
                    stops.append(k)
                    lost.append(h[-1] - h[k])
                    e_stop, e_end = scaled_error(X[k], r["truth"]), scaled_error(X[-1], r["truth"])
                    moved.append(float(np.max(np.abs(X[k] - X[-1]) / tolerances(r["truth"]))))
                    changed += bool((e_stop <= 1).all()) != bool((e_end <= 1).all())
                full = np.mean([r["n_iters"] for r in rs])
                print(f"{tol:8.0e} {p:5d}    | {np.mean(stops):6.1f} {max(stops):4d}       | {full - np.mean(stops):6.1f}   "
                      f"| {max(lost):.1e}          | {max(moved):5.2f}                        | {changed}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--methods", default="cmaes,pso")
    ap.add_argument("--max-iter", type=int, default=100)
    ap.add_argument("--sigma0", type=float, help="CMA-ES initial step size (default: fit_frames')")
    ap.add_argument("--cma-stds", help="CMA-ES per-parameter step factors, 7 comma-separated numbers")
    ap.add_argument("--save")
    ap.add_argument("--load")
    args = ap.parse_args()
    if args.load:
        with open(args.load) as f:
            runs = json.load(f)
    else:
        sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
        runs = run(args)
        if args.save:
            with open(args.save, "w") as f:
                json.dump(runs, f)
    analyse(runs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
