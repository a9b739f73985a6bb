"""The simulated camera's frame rate (issue 20, goal 3): each effect's cost per frame, and frames side by side.

For the base model, each effect alone (its ``strong`` preset) and every effect at once: the frames of a
640x480 approach (``--frames`` poses from 4.0 m to 1.3 m with yaw and pitch) rendered one at a time as
:meth:`uw_sil.sim.simcam.SimCamera.render` does (ms per frame, and the cost of the effect: that minus the base
model's), and through :class:`uw_sil.sim.stream.FrameStream` with ``--workers`` model threads (frames per
second), as ``uw-sil synth`` and ``sim_camera`` with ``workers`` make them; the better of two passes of
each. Each checkout runs in a fresh Python process; with ``--baseline DIR`` (a checkout of the reference
code, e.g. ``git worktree add --detach /tmp/base <commit>``) the reference runs too, alternating, and the
ratios are taken within the run. A reference without the stream gets only the one-at-a-time figures.

    .venv/bin/python bench/bench_simcam.py [--baseline DIR] [--repeats 1] [--frames 24] [--workers 2]

Last line: ``simcam: every effect <hz> Hz streamed (<ms> ms/frame one at a time; reference <ms> ms, <r>x);
base model <hz> Hz streamed (...)``. The ratio ``<r>`` (and the table's ``ratio``) compares like with like: the
reference's ms per frame one at a time over this checkout's ms per frame one at a time (the streamed rates are
shown beside it, not in it).

``--ros RATE``: the node itself. ``sim_camera`` of each checkout is started (``python -m uw_sil.nodes.entry``,
``reliable_output``, otherwise its defaults: ``queue_size`` 1, a live camera that renders the newest pose;
this checkout's with ``workers`` = ``--workers``),
and this process publishes the approach's poses at RATE Hz for ``--seconds`` and counts the ``sim/image_raw``
frames that come back and their latency (pose publication to arrival). ``--effects`` (default none: the base
model) is the node's ``effects`` parameter. Last line: ``simcam-ros: rate=<R>Hz this out=<n>/<N> (<hz> Hz,
p50 <ms> ms) reference out=<n>/<N> (...)``.
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
with SimCamera(DEFAULT_TRUTH, effects=configs[-1][1], seed=0) as cam:     # the process warmed up: every path once
    for T in poses[:4]:
        cam.render(T)
for name, effects in configs:
    seq, hz = float("inf"), None
    with SimCamera(DEFAULT_TRUTH, effects=effects, seed=0) as cam:
        cam.render(poses[0]); cam.render(poses[-1])          # warm: shaders, caches, first allocations
        for _ in range(2):                                   # the better of two passes of each kind
            t = time.perf_counter()
            for T in poses:
                cam.render(T)
            seq = min(seq, (time.perf_counter() - t) / n)
            if FrameStream is not None:
                got = []
                t = time.perf_counter()
                with FrameStream(cam, lambda tag, f, e: got.append(e), workers=workers) as stream:
                    for T in poses:
                        stream.submit(T)
                hz = max(hz or 0.0, n / (time.perf_counter() - t))
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


def run_ros(root: str, rate: float, seconds: float, frames: int, effects: str, domain: int, workers=None) -> dict:
    """The ``sim_camera`` node of ``root`` fed poses at ``rate``: frames out, output rate, latency."""
    import threading
    import time

    import numpy as np
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    from bench_ros import close_graph     # this directory: the scripts' own (sys.path[0] when run)
    from uw_sil.nodes import use_fastdds_profile
    from uw_sil.sim.scene import facing_pose
    from uw_sil.sim.transforms import matrix_to_pose

    env = dict(os.environ, PYTHONPATH=root, ROS_DOMAIN_ID=str(domain))
    use_fastdds_profile(env)
    use_fastdds_profile()
    cmd = [sys.executable, "-m", "uw_sil.nodes.entry", "sim_camera", "--ros-args", "-p", "reliable_output:=true"]
    if effects:
        cmd += ["-p", f"effects:={effects}"]
    if workers:
        cmd += ["-p", f"workers:={workers}"]
    proc = subprocess.Popen(cmd, env=env, cwd=root, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    log = []
    threading.Thread(target=lambda: log.extend(iter(proc.stdout.readline, "")), daemon=True).start()
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = Node("bench_simcam", context=ctx)
    pub = node.create_publisher(PoseStamped, "panel/pose", 10)
    sent, got = {}, {}
    node.create_subscription(Image, "sim/image_raw",
                             lambda m: got.setdefault(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec,
                                                      time.monotonic_ns()),
                             QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    poses = [matrix_to_pose(facing_pose(4.0 - 2.7 * k / max(frames - 1, 1), yaw=0.12 * np.sin(k / 4)))
             for k in range(frames)]
    try:
        deadline = time.monotonic() + 120
        while pub.get_subscription_count() == 0 or node.count_publishers("sim/image_raw") == 0:
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError(f"{root}: sim_camera did not come up:\n" + "".join(log[-30:]))
            ex.spin_once(timeout_sec=0.05)
        time.sleep(1.0)
        period, k = 1.0 / rate, 0
        t_next = time.monotonic()
        end = t_next + seconds
        while time.monotonic() < end:
            pos, q = poses[k % len(poses)]
            msg = PoseStamped()
            ns = time.monotonic_ns()
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 10**9)
            msg.header.frame_id = "camera_optical_frame"
            msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in pos)
            (msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z,
             msg.pose.orientation.w) = (float(v) for v in q)
            pub.publish(msg)
            sent[ns] = ns
            k += 1
            t_next += period
            while time.monotonic() < t_next:
                ex.spin_once(timeout_sec=max(0.0, t_next - time.monotonic()))
        t_drain = time.monotonic() + 5.0
        while time.monotonic() < t_drain:
            ex.spin_once(timeout_sec=0.05)
    finally:
        close_graph(ex, node, ctx, proc)
    lat = sorted((got[t] - t) / 1e6 for t in got if t in sent)
    stamps = sorted(got)
    span = (stamps[-1] - stamps[0]) / 1e9 if len(stamps) > 1 else float("nan")
    return {"sent": len(sent), "out": len(lat), "hz": (len(stamps) - 1) / span if len(stamps) > 1 else 0.0,
            "p50_ms": lat[len(lat) // 2] if lat else float("nan"),
            "p95_ms": lat[int(len(lat) * 0.95)] if lat else float("nan")}


def main_ros(a, roots) -> int:
    runs = {k: [] for k in roots}
    for rep in range(a.repeats):
        for i, (k, root) in enumerate(roots.items()):
            r = run_ros(root, a.ros, a.seconds, a.frames, a.effects, 170 + (os.getpid() + 2 * rep + i) % 60,
                        a.workers if k == "this" else None)
            runs[k].append(r)
            print(f"# run {rep + 1}/{a.repeats} {k}: out {r['out']}/{r['sent']}, {r['hz']:.1f} Hz, "
                  f"latency p50 {r['p50_ms']:.0f} ms p95 {r['p95_ms']:.0f} ms, load {os.getloadavg()[0]:.2f}",
                  flush=True)

    def summary(k):
        rs = runs[k]
        med = lambda f: statistics.median(r[f] for r in rs)       # noqa: E731
        return (f"out={'/'.join(str(r['out']) for r in rs)}/{rs[0]['sent']} ({med('hz'):.1f} Hz, "
                f"p50 {med('p50_ms'):.0f} ms)")

    print(f"simcam-ros: rate={a.ros:g}Hz effects={a.effects or 'none'} "
          + " ".join(f"{k} {summary(k)}" for k in roots))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--baseline", help="checkout of the reference code")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--ros", type=float, default=0.0, help="the node fed poses at this rate (Hz)")
    ap.add_argument("--seconds", type=float, default=20.0, help="--ros: how long the poses come")
    ap.add_argument("--effects", default="", help="--ros: the node's effects parameter (default: none)")
    a = ap.parse_args(argv)
    roots = {"this": THIS} | ({"reference": os.path.abspath(a.baseline)} if a.baseline else {})
    if a.ros:
        return main_ros(a, roots)
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
            line += f" {rseq:13.1f} {rhz or float('nan'):8.1f} {rseq / seq:5.2f}x"      # one at a time, both
        print(line)

    def headline(c):
        seq, hz = med("this", c, "seq_ms"), med("this", c, "stream_hz")
        s = f"{hz:.1f} Hz streamed ({seq:.0f} ms/frame one at a time"
        if ref:
            rseq = med("reference", c, "seq_ms")
            s += f"; reference {rseq:.0f} ms, {rseq / seq:.2f}x"       # one at a time against one at a time
        return s + ")"

    print(f"simcam: every effect {headline('every effect')}; base model {headline('base')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
