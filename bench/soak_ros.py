"""Soak test of the ROS 2 graph: a bag replayed in a loop at 15 Hz into sim_camera and backward_fit.

Run standalone (not part of CI)::

    .venv/bin/python bench/soak_ros.py [--minutes 10] [--width 640 --height 480] [--rate-hz 15]

It synthesizes a trial (``--frames`` frames at ``--rate-hz``), starts ``uw-sil launch backward --bag
trial --loop --keep-running`` (sim_camera, backward_fit fitting once at the start, bag_play replaying the
bag in a loop) on its own ROS_DOMAIN_ID, and watches the graph from a probe node in this process:

* every replayed pose (``/panel/pose``) and every simulated frame (``/sim/image_raw``), matched by stamp:
  a pose whose frame never came (before the same stamp came round again in the next loop, or within
  2 s at the end) is a drop; latency = arrival of the frame - arrival of its pose, at the probe
  (sim_camera's render + degrade + publish of four images, plus transport);
* the resident memory (VmRSS) of every process of the graph (the launcher and each node) every
  ``--sample-s`` seconds.

One line per sample, then the per-process RSS table and the summary, whose last line is::

    soak: minutes=M rss_growth_max=X% drops=N p95_ms=Y

``rss_growth_max``: over the processes, the largest RSS after the first minute relative to the RSS at
the first minute (the goal is < 5 %); ``drops``: over the whole run, fit included (the drops after the
fit are also printed); ``p95_ms``: 95th percentile latency. Timing numbers depend on the machine's load.
"""
from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np


def rss_mb(pid: int) -> float:
    """VmRSS of a process in MiB (nan when it has ended)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


class Probe:
    """Matches replayed poses with the simulated frames rendered from them (by stamp)."""

    def __init__(self, domain: int):
        import rclpy
        from geometry_msgs.msg import PoseStamped
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from sensor_msgs.msg import Image
        from std_msgs.msg import String
        from rclpy.qos import DurabilityPolicy

        from uw_sil.nodes import use_fastdds_profile

        use_fastdds_profile()          # the probe receives 640x480 images too
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.node = Node("soak_probe", context=self.ctx)
        self.lock = threading.Lock()
        self.pending: dict = {}        # stamp -> arrival time of the pose, waiting for its frame
        self.poses = self.frames = self.drops = 0
        self.latencies: list = []      # (arrival time, latency s)
        self.drop_times: list = []
        self.status: list = []
        self.node.create_subscription(PoseStamped, "/panel/pose", self._on_pose,
                                      QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        sensor = QoSProfile(depth=100, reliability=qos_profile_sensor_data.reliability)
        self.node.create_subscription(Image, "/sim/image_raw", self._on_frame, sensor)
        self.node.create_subscription(String, "/backward_fit/status", lambda m: self.status.append(
            (time.monotonic(), m.data)), QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        while self.ctx.ok():
            try:
                self.executor.spin_once(timeout_sec=0.1)
            except Exception:   # shut down under us
                break

    @staticmethod
    def _stamp(msg) -> int:
        return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec

    def _on_pose(self, msg):
        now, s = time.monotonic(), self._stamp(msg)
        with self.lock:
            self.poses += 1
            if s in self.pending:                  # the same stamp again (next loop): its frame never came
                self.drops += 1
                self.drop_times.append(self.pending[s])
            self.pending[s] = now

    def _on_frame(self, msg):
        now, s = time.monotonic(), self._stamp(msg)
        with self.lock:
            self.frames += 1
            t = self.pending.pop(s, None)
            if t is not None:
                self.latencies.append((now, now - t))

    def finish(self, grace_s: float = 2.0):
        time.sleep(grace_s)
        with self.lock:
            cutoff = time.monotonic() - grace_s
            late = [t for t in self.pending.values() if t < cutoff]
            self.drops += len(late)
            self.drop_times += late
            self.pending.clear()
        self.ctx.try_shutdown()
        self.thread.join(timeout=5)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--rate-hz", type=float, default=15.0, help="frame rate of the replayed bag")
    ap.add_argument("--frames", type=int, default=60, help="frames in the bag (it loops)")
    ap.add_argument("--sample-s", type=float, default=10.0, help="RSS sampling period")
    ap.add_argument("--max-iter", type=int, default=40, help="iterations of the one backward fit (CMA-ES)")
    ap.add_argument("--domain", type=int, default=200 + os.getpid() % 30)
    ap.add_argument("--keep", help="write the bag and logs here instead of a temporary directory")
    args = ap.parse_args(argv)

    from uw_sil.bags.synth import synthesize_trial
    from uw_sil.sim.camera import CameraModel

    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="soak_ros_"))
    work.mkdir(parents=True, exist_ok=True)
    bag = work / "trial.mcap"
    t0 = time.perf_counter()
    synthesize_trial(bag, n_frames=args.frames, seed=7, camera=CameraModel.from_fov(args.width, args.height, 70.0),
                     rate_hz=args.rate_hz, start_m=3.5, end_m=1.5, overwrite=True)
    print(f"bag: {args.frames} frames {args.width}x{args.height} at {args.rate_hz:g} Hz, "
          f"written in {time.perf_counter() - t0:.1f} s", flush=True)

    env = dict(os.environ, ROS_DOMAIN_ID=str(args.domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYOPENGL_PLATFORM=os.environ.get("PYOPENGL_PLATFORM", "osmesa"), PYTHONUNBUFFERED="1")
    os.environ.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    cmd = [sys.executable, "-m", "uw_sil.cli", "launch", "backward", "--bag", str(bag), "--loop", "--keep-running",
           "--optimizer", "cmaes", "--max-iter", str(args.max_iter), "--stride", str(max(1, args.frames // 6)),
           "--output-yaml", str(work / "fit.yaml")]
    log = open(work / "launch.log", "w")
    launch = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                              start_new_session=True)
    pids = {"launcher": launch.pid}
    started = threading.Event()

    def pump():
        for line in launch.stdout:
            log.write(line)
            m = re.match(r"\[launch\] started (\w+) \(pid (\d+)\)", line)
            if m:
                pids[m.group(1)] = int(m.group(2))
            if "]: ready:" in line:
                started.set()
        log.flush()
    threading.Thread(target=pump, daemon=True).start()
    probe = Probe(args.domain)
    samples = []      # (t, {name: rss})
    duration = args.minutes * 60
    try:
        deadline = time.monotonic() + 120
        while not started.wait(0.5):
            if launch.poll() is not None or time.monotonic() > deadline:
                raise SystemExit(f"the graph did not start (launch status {launch.poll()}); see {work / 'launch.log'}")
        t_start = time.monotonic()
        while True:
            t = time.monotonic() - t_start
            rss = {name: rss_mb(pid) for name, pid in pids.items()}
            samples.append((t, rss))
            with probe.lock:
                lat = [x for _, x in probe.latencies]
                line = (f"t={t:6.0f}s poses={probe.poses} frames={probe.frames} drops={probe.drops} "
                        f"p50_ms={1e3 * np.median(lat) if lat else float('nan'):.1f} "
                        + " ".join(f"{n}={v:.0f}MB" for n, v in rss.items()))
            print(line, flush=True)
            if launch.poll() is not None:
                raise SystemExit(f"the graph ended early (status {launch.returncode}); see {work / 'launch.log'}")
            if t >= duration:
                break
            time.sleep(min(args.sample_s, duration - t + 0.01))
    finally:
        launch.send_signal(signal.SIGINT)
        probe.finish()
        try:
            launch.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(launch.pid, signal.SIGKILL)

    fit_done = next((ts - t_start for ts, s in probe.status if s.startswith(("done", "failed"))), None)
    fit_status = next((s for _, s in probe.status if s.startswith(("done", "failed"))), "no fit result")
    lat = np.array([x for _, x in probe.latencies]) * 1e3
    lat_after = np.array([x for t, x in probe.latencies if fit_done is not None and t - t_start > fit_done]) * 1e3
    drops_after = sum(1 for t in probe.drop_times if fit_done is not None and t - t_start > fit_done)
    growth = {}
    base_i = next((i for i, (t, _) in enumerate(samples) if t >= 60), None)
    for name in pids:
        series = [(t, r[name]) for t, r in samples if name in r and np.isfinite(r[name])]
        if base_i is not None and len(series) > base_i:
            base = series[base_i][1]
            growth[name] = 100 * (max(v for _, v in series[base_i:]) - base) / base
        first = series[0][1] if series else float("nan")
        last = series[-1][1] if series else float("nan")
        print(f"rss {name:<13} first {first:7.1f} MB  last {last:7.1f} MB  growth after 1 min "
              f"{growth.get(name, float('nan')):+.2f} %")
    minutes = (samples[-1][0] if samples else 0) / 60
    p = (lambda a, q: float(np.percentile(a, q)) if len(a) else float("nan"))
    print(f"fit: {fit_status} (at {fit_done if fit_done is not None else float('nan'):.0f} s)")
    print(f"poses {probe.poses}, frames {probe.frames}, drops {probe.drops} ({drops_after} after the fit); "
          f"rate {probe.poses / max(1e-9, samples[-1][0] if samples else 1):.2f} poses/s")
    print(f"latency ms: p50 {p(lat, 50):.1f} p95 {p(lat, 95):.1f} p99 {p(lat, 99):.1f} max "
          f"{lat.max() if len(lat) else float('nan'):.1f}; after the fit: p50 {p(lat_after, 50):.1f} "
          f"p95 {p(lat_after, 95):.1f}")
    print(f"launch exit status {launch.returncode}; logs in {work}")
    growth_max = max(growth.values()) if growth else float("nan")
    print(f"soak: minutes={minutes:.1f} rss_growth_max={growth_max:.1f}% drops={probe.drops} p95_ms={p(lat, 95):.1f}")


if __name__ == "__main__":
    main()
