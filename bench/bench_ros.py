"""The forward graph live: a 640x480 trial replayed as a camera at 15 and 30 Hz into sim_camera + enhancer.

For each rate the graph is started fresh (`uw-sil launch forward`, no bag: a live camera), and this process
plays the camera: it renders a synthetic approach once (noisy frames, poses), then publishes
``camera/image_raw`` (best effort), ``camera/camera_info`` and ``panel/pose`` (reliable) with the current
time as stamp, looping over the frames, for ``--seconds``. It counts the enhanced frames that come back and
reads the enhancer's ``~/status`` (drops by cause, enhancer latency: from the later of its paired inputs'
arrival to publication). End to end: pose publication here to the enhanced frame's arrival here.

    PYOPENGL_PLATFORM=osmesa .venv/bin/python bench/bench_ros.py [--rates 15 30] [--seconds 30] [--frames 30]

Last line: ``ros: rate=30Hz in=N out=N drops=N enhancer_p50_ms=X e2e_p50_ms=Y`` (the highest rate).
On a shared, loaded machine the numbers are indicative only.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

import numpy as np  # noqa: E402

from uw_sil.bags.imgmsg import rgb_to_image_fields  # noqa: E402
from uw_sil.bags.synth import DEFAULT_TRUTH, SensorNoise, add_sensor_noise, approach_trajectory  # noqa: E402
from uw_sil.fit.backward import write_params_yaml  # noqa: E402
from uw_sil.nodes.graph import share_file  # noqa: E402
from uw_sil.sim.camera import CameraModel  # noqa: E402
from uw_sil.sim.simcam import SimCamera  # noqa: E402
from uw_sil.sim.transforms import matrix_to_pose  # noqa: E402


def trial_frames(n: int, camera: CameraModel):
    rng = np.random.default_rng(0)
    poses = approach_trajectory(n, 4.0, 1.2, rng)
    with SimCamera(DEFAULT_TRUTH, camera=camera) as sim:
        return [(add_sensor_noise(sim.render(T).image, SensorNoise(), rng), T) for T in poses]


def run_rate(rate: float, seconds: float, frames, camera: CameraModel, fit_yaml: Path, domain: int) -> dict:
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, qos_profile_sensor_data
    from sensor_msgs.msg import CameraInfo, Image
    from std_msgs.msg import String

    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    proc = subprocess.Popen([sys.executable, "-m", "uw_sil.cli", "launch", "forward", "--sim-params", str(fit_yaml)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    log = []
    threading.Thread(target=lambda: log.extend(iter(proc.stdout.readline, "")), daemon=True).start()
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = Node("bench_camera", context=ctx)
    pub_img = node.create_publisher(Image, "camera/image_raw", qos_profile_sensor_data)
    pub_info = node.create_publisher(CameraInfo, "camera/camera_info", 10)
    pub_pose = node.create_publisher(PoseStamped, "panel/pose", 10)
    sent, got, status = {}, {}, []
    node.create_subscription(Image, "camera/image_enhanced",
                             lambda m: got.setdefault(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec,
                                                      time.time_ns()), 50)
    node.create_subscription(String, "enhancer/status", lambda m: status.append(json.loads(m.data)),
                             QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    msgs = []
    for img, T in frames:
        pos, q = matrix_to_pose(T)
        msgs.append((rgb_to_image_fields(img), pos, q))
    info_fields = camera.camera_info_fields()
    try:
        deadline = time.monotonic() + 120
        while pub_img.get_subscription_count() == 0 or pub_pose.get_subscription_count() == 0:
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError("the forward graph did not come up:\n" + "".join(log[-30:]))
            ex.spin_once(timeout_sec=0.05)
        # camera_info first, so sim_camera renders with these intrinsics from the first pose on
        for _ in range(5):
            pub_info.publish(CameraInfo(**info_fields))
            ex.spin_once(timeout_sec=0.1)
        time.sleep(1.0)
        period = 1.0 / rate
        t_next = time.monotonic()
        end = t_next + seconds
        k = 0
        while time.monotonic() < end:
            fields, pos, q = msgs[k % len(msgs)]
            now = time.time_ns()
            stamp = node.get_clock().now().to_msg()
            stamp.sec, stamp.nanosec = divmod(now, 10**9)
            header = {"stamp": stamp, "frame_id": camera.frame_id}
            pose = PoseStamped()
            pose.header.stamp, pose.header.frame_id = stamp, camera.frame_id
            pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = (float(v) for v in pos)
            (pose.pose.orientation.x, pose.pose.orientation.y, pose.pose.orientation.z,
             pose.pose.orientation.w) = (float(v) for v in q)
            img = Image(**fields)
            img.header.stamp, img.header.frame_id = stamp, camera.frame_id
            info = CameraInfo(**info_fields)
            info.header.stamp, info.header.frame_id = header["stamp"], header["frame_id"]
            pub_img.publish(img)
            pub_info.publish(info)
            pub_pose.publish(pose)
            sent[now] = time.time_ns()
            k += 1
            t_next += period
            while True:
                left = t_next - time.monotonic()
                if left <= 0:
                    break
                ex.spin_once(timeout_sec=min(left, 0.005))
        t_drain = time.monotonic() + 3.0
        while time.monotonic() < t_drain:
            ex.spin_once(timeout_sec=0.05)
        n_status = len(status)
        t_status = time.monotonic() + 3.0
        while len(status) == n_status and time.monotonic() < t_status:
            ex.spin_once(timeout_sec=0.05)
    finally:
        ex.shutdown()
        node.destroy_node()
        ctx.try_shutdown()
        if proc.poll() is None:
            import signal

            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
    s = status[-1] if status else {}
    e2e = np.array([(got[t] - sent[t]) / 1e6 for t in got if t in sent])
    drops = s.get("dropped_queue", 0) + s.get("dropped_unpaired", 0) + s.get("dropped_bad", 0)
    return {"rate": rate, "in": len(sent), "out": sum(1 for t in got if t in sent), "drops": drops,
            "dropped_queue": s.get("dropped_queue"), "dropped_unpaired": s.get("dropped_unpaired"),
            "dropped_bad": s.get("dropped_bad"), "sim_frames": s.get("received", {}).get("depth"),
            "images_received": s.get("received", {}).get("image"),
            "enhancer_p50_ms": (s.get("latency_ms") or {}).get("p50"),
            "enhancer_p95_ms": (s.get("latency_ms") or {}).get("p95"),
            "e2e_p50_ms": float(np.percentile(e2e, 50)) if e2e.size else None,
            "e2e_p95_ms": float(np.percentile(e2e, 95)) if e2e.size else None}


def main():
    # this process exchanges 640x480 images with the nodes: the same Fast DDS profile as the graph
    os.environ.setdefault("FASTDDS_DEFAULT_PROFILES_FILE", str(share_file("config", "fastdds_shm.xml")))
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rates", type=float, nargs="+", default=[15.0, 30.0])
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--frames", type=int, default=30, help="frames of the trial (looped)")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    args = ap.parse_args()
    camera = CameraModel.from_fov(args.width, args.height, 70.0)
    print(f"rendering a {args.width}x{args.height} trial of {args.frames} frames ...", flush=True)
    frames = trial_frames(args.frames, camera)
    results = []
    with tempfile.TemporaryDirectory() as d:
        fit = write_params_yaml(Path(d) / "fit.yaml", DEFAULT_TRUTH)
        for k, rate in enumerate(args.rates):
            r = run_rate(rate, args.seconds, frames, camera, fit, domain=1 + (os.getpid() * 7 + k) % 232)
            results.append(r)
            print(json.dumps(r), flush=True)
    print("(indicative: shared, loaded 2-core machine; drops = enhancer queue + unpaired (sim_camera skipped the "
          "pose: it renders the newest) + bad)")
    for r in results:
        fmt = lambda v: "n/a" if v is None else f"{v:.1f}"  # noqa: E731
        print(f"ros: rate={r['rate']:g}Hz in={r['in']} out={r['out']} drops={r['drops']} "
              f"enhancer_p50_ms={fmt(r['enhancer_p50_ms'])} e2e_p50_ms={fmt(r['e2e_p50_ms'])}")


if __name__ == "__main__":
    main()
