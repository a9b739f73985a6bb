"""Parameter recovery on synthetic trials where the model is exactly right (truth in the sidecar).

For each seed: synthesize a trial (random ground truth within realistic ranges), fit K frames spread
over the approach, compare with the truth. Success = attenuation within 5 % relative, background
within 0.01, fog density within 10 % (issue 4). Prints per-seed errors and the success rate.

    .venv/bin/python bench/bench_recovery.py [--seeds 10] [--width 640] [--method cmaes] [--hist-pixels panel]
"""
import argparse
import os
import sys
import tempfile
import time

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np  # noqa: E402

from uw_sil.fit.backward import fit_frames, select_frames  # noqa: E402
from uw_sil.bags import read_samples  # noqa: E402
from uw_sil.sim.camera import CameraModel  # noqa: E402
from uw_sil.sim.params import UnderwaterParams  # noqa: E402
from uw_sil.sim.render import Renderer  # noqa: E402
from uw_sil.bags.synth import load_truth, synthesize_trial  # noqa: E402


def random_truth(rng) -> UnderwaterParams:
    """Deep-sea-like water: red attenuates most, blue-green veiling light."""
    a = (rng.uniform(0.25, 0.6), rng.uniform(0.06, 0.2), rng.uniform(0.05, 0.15))
    b = (rng.uniform(0.02, 0.12), rng.uniform(0.2, 0.45), rng.uniform(0.3, 0.55))
    return UnderwaterParams(a, b, rng.uniform(0.03, 0.2))


def errors(params, truth):
    """Recovery criterion: attenuation within 5 % relative, background within 0.01, fog within 10 %."""
    got, want = params.as_vector(), truth.as_vector()
    rel_a = np.abs(got[:3] - want[:3]) / want[:3]
    abs_b = np.abs(got[3:6] - want[3:6])
    rel_rho = abs(got[6] - want[6]) / want[6]
    ok = bool((rel_a <= 0.05).all() and (abs_b <= 0.01).all() and rel_rho <= 0.10)
    return rel_a, abs_b, rel_rho, ok


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--frames", type=int, default=3, help="K")
    ap.add_argument("--method", default="cmaes")
    ap.add_argument("--max-iter", type=int, default=60)
    ap.add_argument("--start", default="linear", choices=["linear", "water", "centre"])
    ap.add_argument("--hist-pixels", default="split", choices=["split", "panel", "all"])
    ap.add_argument("--color-model", default="rgb")
    args = ap.parse_args()
    cam = CameraModel.from_fov(args.width, args.width * 3 // 4, 70.0)
    n_ok = 0
    per = {"a": [], "b": [], "rho": []}
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        rng = np.random.default_rng(1000 + seed)
        truth = random_truth(rng)
        with tempfile.TemporaryDirectory() as d:
            bag = os.path.join(d, "trial.mcap")
            synthesize_trial(bag, n_frames=11, seed=seed, params=truth, camera=cam, start_m=3.5, end_m=1.2)
            assert np.allclose(load_truth(bag)["params"].as_vector(), truth.as_vector())
            with Renderer(camera=cam) as r:
                frames = select_frames(read_samples(bag), r, k=args.frames, stride=max(1, 11 // max(1, args.frames - 1))).frames
        t = time.perf_counter()
        fit = fit_frames(frames, method=args.method, seed=seed, max_iter=args.max_iter,
                         hist_pixels=args.hist_pixels, color_model=args.color_model,
                         x0=None if args.start == "centre" else args.start)
        rel_a, abs_b, rel_rho, ok = errors(fit.params, truth)
        n_ok += ok
        per["a"].append((rel_a <= 0.05).all())
        per["b"].append((abs_b <= 0.01).all())
        per["rho"].append(rel_rho <= 0.10)
        print(f"seed {seed}: {'OK  ' if ok else 'MISS'} a rel err {np.round(rel_a, 3)}, b abs err {np.round(abs_b, 4)}, "
              f"rho rel err {rel_rho:.3f}; θ {fit.theta_best:.4f}, {fit.optim.n_evals} evals, "
              f"{time.perf_counter() - t:.1f} s", flush=True)
    print(f"criteria met separately: a {np.mean(per['a']):.0%}, b {np.mean(per['b']):.0%}, rho {np.mean(per['rho']):.0%}")
    print(f"recovery success rate ({args.method}, start {args.start}, K={args.frames}, {args.width}px, hist {args.hist_pixels}): "
          f"{n_ok}/{args.seeds}")


if __name__ == "__main__":
    sys.exit(main())
