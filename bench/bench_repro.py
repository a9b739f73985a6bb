"""Robustness of the default fit over optimizer seeds, on one synthetic trial.

The trial is the one of the issue "Same input, same result" (``uw-sil synth --frames 8 --seed 11``: the
default ground truth, an approach from 4 m to 1.2 m), rendered at 320x240 instead of 640x480 to keep
ten fits affordable on two cores (the fit is the same code at both sizes; 320x240 is the harder case,
see the README's recovery numbers). The same bag is then fitted with ``fit_bag(bag, seed=s)`` for ten
seeds, with the library's defaults unless options are given here, and each fit is compared with the
truth: success = attenuation within 5 % relative, background within 0.01, fog density within 10 %.
The first seed is fitted twice, and the two results must be bit-identical.

    .venv/bin/python bench/bench_repro.py [--seeds 10] [--method pso|cmaes] [--frames K] [--stride S]
                                          [--max-iter N] [--tol T] [--patience P] [--restarts R]
                                          [--swarm-size N]

Last line: ``repro: seeds_ok=N/10 ...``.
"""
import argparse
import os
import sys
import tempfile
import time

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np  # noqa: E402

from uw_sil.fit.backward import fit_bag  # noqa: E402
from uw_sil.sim.camera import CameraModel  # noqa: E402
from uw_sil.bags.synth import load_truth, synthesize_trial  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_recovery import errors  # noqa: E402  -- the same recovery criterion


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--trial-frames", type=int, default=8)
    ap.add_argument("--trial-seed", type=int, default=11)
    ap.add_argument("--method", help="optimizer (default: the library's default)")
    ap.add_argument("--frames", type=int, help="K (default: fit_bag's)")
    ap.add_argument("--stride", type=int, help="(default: fit_bag's)")
    ap.add_argument("--max-iter", type=int)
    ap.add_argument("--tol", type=float)
    ap.add_argument("--patience", type=int)
    ap.add_argument("--restarts", type=int)
    ap.add_argument("--swarm-size", type=int, help="population (default: fit_frames', 20)")
    args = ap.parse_args()
    options = {k: v for k, v in (("method", args.method), ("k", args.frames), ("stride", args.stride),
                                 ("max_iter", args.max_iter), ("tol", args.tol), ("patience", args.patience),
                                 ("restarts", args.restarts), ("swarm_size", args.swarm_size)) if v is not None}
    cam = CameraModel.from_fov(args.width, args.width * 3 // 4, 70.0)
    with tempfile.TemporaryDirectory() as d:
        bag = os.path.join(d, "trial.mcap")
        synthesize_trial(bag, n_frames=args.trial_frames, seed=args.trial_seed, camera=cam)
        truth = load_truth(bag)["params"]
        print(f"trial: {args.width}x{cam.height}, {args.trial_frames} frames, seed {args.trial_seed}, truth "
              + ", ".join(f"{k}={v:.3f}" for k, v in truth.as_dict().items()), flush=True)
        print(f"fit options: {options or 'library defaults'}", flush=True)
        n_ok, iters, evals, walls, identical = 0, [], [], [], None
        for seed in range(args.seeds):
            t = time.perf_counter()
            fit = fit_bag(bag, seed=seed, **options)
            walls.append(time.perf_counter() - t)
            if seed == 0:
                again = fit_bag(bag, seed=seed, **options)
                identical = (again.x_best.tobytes() == fit.x_best.tobytes()
                             and again.optim.history_best_f == fit.optim.history_best_f)
            rel_a, abs_b, rel_rho, ok = errors(fit.params, truth)
            n_ok += ok
            iters.append(fit.optim.n_iters)
            evals.append(fit.optim.n_evals)
            print(f"seed {seed}: {'OK  ' if ok else 'MISS'} a rel err {np.round(rel_a, 3)}, b abs err "
                  f"{np.round(abs_b, 4)}, rho rel err {rel_rho:.3f}; θ {fit.theta_start:.4f} -> {fit.theta_best:.5f}, "
                  f"{fit.optim.method}, {fit.optim.n_iters} it ({fit.optim.stop_reason}), {fit.optim.n_evals} evals, "
                  f"frames {[f.index for f in fit.frames]}, {walls[-1]:.1f} s", flush=True)
    print(f"repro: seeds_ok={n_ok}/{args.seeds} method={fit.optim.method} frames={len(fit.frames)} "
          f"iterations_mean={np.mean(iters):.1f} evals_mean={np.mean(evals):.0f} wall_mean_s={np.mean(walls):.1f} "
          f"bit_identical={'yes' if identical else 'NO'} size={args.width}x{cam.height}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
