"""The simulated camera's frame rate (issue 20, goal 3): each effect's cost per frame, and frames side by side.

For the base model, each effect alone (its ``strong`` preset) and every effect at once: the frames of a
640x480 approach (``--frames`` poses from 4.0 m to 1.3 m with yaw and pitch) rendered one at a time as
:meth:`uw_sil.sim.simcam.SimCamera.render` does (ms per frame, and the cost of the effect: that minus the base
model's), and through :class:`uw_sil.sim.stream.FrameStream` with ``--workers`` model threads (frames per
second), as ``sim_camera`` renders them. Each checkout runs in a fresh Python process; with ``--baseline DIR``
(a checkout of the reference code, e.g. ``git worktree add --detach /tmp/base <commit>``) the reference
runs too, alternating, and the ratios are taken within the run. A reference without the stream gets only
the one-at-a-time figures.

    .venv/bin/python bench/bench_simcam.py [--baseline DIR] [--repeats 1] [--frames 24] [--workers 2]

Last line: ``simcam: every effect <hz> Hz streamed (<ms> ms/frame one at a time; reference <ms> ms, <r>x);
base model <hz> Hz streamed (...)``.
"""
import argparse
import json
import os
import statistics
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
THIS = os.path.dirname(HERE)

# Runs in the child (with the checkout's uw_sil first on the path): one JSON line per configuration.
CHILD = r"""
import json, os, sys, time
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
import numpy as np
from uw_sil.bags.synth import DEFAULT_TRUTH
from uw_sil.sim.effects import EFFECTS
from uw_sil.sim.scene import facing_pose
from uw_sil.sim.simcam import SimCamera
try:
    from uw_sil.sim.stream import FrameStream
except ImportError:
    FrameStream = None
n, workers = int(sys.argv[1]), int(sys.argv[2])
poses = [facing_pose(4.0 - 2.7 * k / max(n - 1, 1), x=0.05 * np.sin(k / 3), yaw=0.12 * np.sin(k / 4),
                     pitch=0.06 * np.cos(k / 5)) for k in range(n)]
configs = [("base", None)] + [(e, f"{e}=strong") for e in EFFECTS]
configs.append(("every effect", ",".join(f"{e}=strong" for e in EFFECTS)))
for name, effects in configs:
    with SimCamera(DEFAULT_TRUTH, effects=effects, seed=0) as cam:
        cam.render(poses[0]); cam.render(poses[-1])          # warm: shaders, caches, first allocations
        t = time.perf_counter()
        for T in poses:
            cam.render(T)
        seq = (time.perf_counter() - t) / n
        hz = None
        if FrameStream is not None:
            got = []
            t = time.perf_counter()
            with FrameStream(cam, lambda tag, f, e: got.append(e), workers=workers) as stream:
                for T in poses:
                    stream.submit(T)
            hz = n / (time.perf_counter() - t)
            assert len(got) == n and not any(got), got
    print(json.dumps({"config": name, "seq_ms": seq * 1e3, "stream_hz": hz}), flush=True)
"""


def run(root: str, frames: int, workers: int) -> dict:
    env = dict(os.environ, PYTHONPATH=root)
    out = subprocess.run([sys.executable, "-c", CHILD, str(frames), str(workers)], env=env, cwd=root,
                         capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"{root}: exit {out.returncode}\n{out.stderr[-3000:]}")
    return {r["config"]: r for r in map(json.loads, out.stdout.split("\n")[:-1])}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--baseline", help="checkout of the reference code")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--workers", type=int, default=2)
    a = ap.parse_args(argv)
    roots = {"this": THIS} | ({"reference": os.path.abspath(a.baseline)} if a.baseline else {})
    runs = {k: [] for k in roots}
    for rep in range(a.repeats):
        for k, root in roots.items():
            runs[k].append(run(root, a.frames, a.workers))
            print(f"# run {rep + 1}/{a.repeats} {k}: load {os.getloadavg()[0]:.2f}", flush=True)

    def med(k, config, field):
        vals = [r[config][field] for r in runs[k] if r[config][field] is not None]
        return statistics.median(vals) if vals else None

    configs = list(runs["this"][0])
    base = med("this", "base", "seq_ms")
    ref = "reference" in runs
    print(f"640x480, {a.frames} frames, {a.workers} model threads, median of {a.repeats}")
    print(f"{'model':26s} {'ms/frame':>9s} {'effect ms':>10s} {'streamed Hz':>12s}"
          + (f" {'reference ms':>13s} {'ref. Hz':>8s} {'ratio':>6s}" if ref else ""))
    for c in configs:
        seq, hz = med("this", c, "seq_ms"), med("this", c, "stream_hz")
        line = f"{c:26s} {seq:9.1f} {seq - base if c != 'base' else 0:10.1f} {hz or 0:12.1f}"
        if ref:
            rseq, rhz = med("reference", c, "seq_ms"), med("reference", c, "stream_hz")
            line += f" {rseq:13.1f} {rhz or float('nan'):8.1f} {rseq / (1e3 / hz if hz else seq):5.2f}x"
        print(line)

    def headline(c):
        seq, hz = med("this", c, "seq_ms"), med("this", c, "stream_hz")
        s = f"{hz:.1f} Hz streamed ({seq:.0f} ms/frame one at a time"
        if ref:
            rseq = med("reference", c, "seq_ms")
            s += f"; reference {rseq:.0f} ms, {rseq / (1e3 / hz):.2f}x"
        return s + ")"

    print(f"simcam: every effect {headline('every effect')}; base model {headline('base')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
