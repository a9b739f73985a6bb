"""Dive-start fit speed: this checkout's default fit against a reference checkout's, measured in the same run.

The fit of ``uw-sil demo``: CMA-ES (the library defaults of ``fit_frames``), K = 3 frames of the demo's trial
(30 frames, seed 0, 640x480, stride 10: 4.0 / 3.3 / 1.8 m), optimizer seed 0. Each fit runs in a fresh
Python process (the reference checkout's ``uw_sil`` and this one cannot share a process), the two
alternating, ``--repeats`` times; the figure is the median of ``fit_frames``' wall time (objective set-up,
least-squares start, optimizer; the frames' renders are done once by this script and handed to both as a
pickle). The machine's load (1-minute average) is printed next to every run: on a shared machine the
absolute times mean little, the ratio of the medians more, and the ratio of the CPU times (user + system
of the fit, all threads) most: it depends least on what else runs.

    .venv/bin/python bench/bench_fit_speed.py --baseline DIR [--repeats 3] [--profile]

``--baseline DIR`` is a checkout of the reference code, e.g. ``git worktree add --detach /tmp/base <commit>``
(or ``git archive <commit> | tar -x -C DIR``). ``--profile`` also runs each once under cProfile with one
θ thread (cProfile sees the main thread only) and prints where the time goes.

Last line: ``fit speed: this <t> s, reference <t> s (median of N), ratio <r>x; CPU ... ratio <r>x; θ this <θ> reference <θ>; ...``.
"""
import argparse
import json
import os
import pickle
import statistics
import subprocess
import sys
import tempfile
import time

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

HERE = os.path.dirname(os.path.abspath(__file__))
THIS = os.path.dirname(HERE)

# Runs in the child: the fit of the frames in argv[1] with the library defaults, one JSON line out.
CHILD = r"""
import json, os, pickle, sys, time
import cma  # imported outside the timing (its first import takes ~1.5 s)
import numpy as np
import uw_sil
from uw_sil.fit.backward import fit_frames
frames = pickle.load(open(sys.argv[1], "rb"))
profile = len(sys.argv) > 2
if profile:
    import cProfile, pstats, io
    prof = cProfile.Profile()
    prof.enable()
import resource
r0 = resource.getrusage(resource.RUSAGE_SELF)
fit = fit_frames(frames, method="cmaes", seed=0)
r1 = resource.getrusage(resource.RUSAGE_SELF)
cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
if profile:
    prof.disable()
    s = io.StringIO()
    pstats.Stats(prof, stream=s).sort_stats("tottime").print_stats(18)
    sys.stderr.write(s.getvalue())
o = fit.optim
print(json.dumps({"wall_s": fit.wall_time_s, "cpu_s": cpu, "theta": fit.theta_best, "theta_x0": fit.theta_x0,
                  "params": fit.params.as_vector().tolist(), "x_hex": fit.x_best.tobytes().hex(),
                  "evals": int(o.n_evals), "iterations": int(o.n_iters), "stop": o.stop_reason,
                  "module": os.path.dirname(uw_sil.__file__)}))
"""


def run(root, frames_pkl, profile=False):
    env = dict(os.environ, PYTHONPATH=root)
    if profile:
        env["UW_SIL_THREADS"] = "1"
    load = os.getloadavg()[0]
    args = [sys.executable, "-c", CHILD, frames_pkl] + (["profile"] if profile else [])
    p = subprocess.run(args, env=env, cwd=root, capture_output=True, text=True, check=False)
    if p.returncode:
        raise RuntimeError(f"fit in {root} failed:\n{p.stderr[-3000:]}")
    out = json.loads(p.stdout.strip().splitlines()[-1])
    if not out["module"].startswith(os.path.realpath(root)) and not out["module"].startswith(root):
        raise RuntimeError(f"{root}: imported uw_sil from {out['module']}")
    out["load"] = (load + os.getloadavg()[0]) / 2
    out["stderr"] = p.stderr
    return out


def errors(params, truth):
    import numpy as np

    got, want = np.asarray(params), truth.as_vector()
    return (np.abs(got[:3] - want[:3]) / want[:3], np.abs(got[3:6] - want[3:6]), abs(got[6] - want[6]) / want[6])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", required=True, help="checkout of the reference code")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--profile", action="store_true")
    args = ap.parse_args()
    import numpy as np

    from uw_sil.bags import read_samples
    from uw_sil.bags.synth import DEFAULT_TRUTH, synthesize_trial
    from uw_sil.fit.backward import select_frames
    from uw_sil.sim.render import Renderer

    base = os.path.abspath(args.baseline)
    with tempfile.TemporaryDirectory() as d:
        bag = os.path.join(d, "trial.mcap")
        synthesize_trial(bag, n_frames=30, seed=0)
        with Renderer() as r:
            frames = select_frames(read_samples(bag), r, k=3, stride=10).frames
        pkl = os.path.join(d, "frames.pkl")
        with open(pkl, "wb") as fh:
            pickle.dump(frames, fh)
        print(f"trial: 640x480, frames {[f.index for f in frames]} at {[round(f.range_median, 2) for f in frames]} m; "
              f"cores {os.cpu_count()}; {time.strftime('%Y-%m-%d %H:%M')}", flush=True)
        res = {"this": [], "reference": []}
        for k in range(args.repeats):
            for name, root in (("reference", base), ("this", THIS)) if k % 2 == 0 else \
                    (("this", THIS), ("reference", base)):
                out = run(root, pkl)
                res[name].append(out)
                ea, eb, er = errors(out["params"], DEFAULT_TRUTH)
                print(f"run {k} {name:9s}: {out['wall_s']:6.1f} s wall, {out['cpu_s']:6.1f} s CPU (load {out['load']:.1f}), "
                      f"θ {out['theta']:.6f} "
                      f"(start {out['theta_x0']:.6f}), {out['iterations']} it, {out['evals']} evals, stop "
                      f"{out['stop']}; error a {np.round(ea, 3)}, b {np.round(eb, 4)}, rho {er:.3f}", flush=True)
        if args.profile:
            for name, root in (("reference", base), ("this", THIS)):
                out = run(root, pkl, profile=True)
                print(f"--- profile {name} (one θ thread, load {out['load']:.1f}): {out['wall_s']:.1f} s")
                print(out["stderr"])
    t_this = statistics.median(r["wall_s"] for r in res["this"])
    t_ref = statistics.median(r["wall_s"] for r in res["reference"])
    c_this = statistics.median(r["cpu_s"] for r in res["this"])
    c_ref = statistics.median(r["cpu_s"] for r in res["reference"])
    same = len({r["x_hex"] for r in res["this"]}) == 1 and len({r["x_hex"] for r in res["reference"]}) == 1
    loads = [r["load"] for v in res.values() for r in v]
    print(f"fit speed: this {t_this:.1f} s, reference {t_ref:.1f} s (median of {args.repeats}), ratio "
          f"{t_ref / t_this:.1f}x; CPU this {c_this:.1f} s, reference {c_ref:.1f} s, ratio {c_ref / c_this:.1f}x; θ this {res['this'][0]['theta']:.6f} reference {res['reference'][0]['theta']:.6f}; "
          f"evals this {res['this'][0]['evals']} reference {res['reference'][0]['evals']}; repeated runs bit-identical: "
          f"{'yes' if same else 'NO'}; load {min(loads):.1f}-{max(loads):.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
