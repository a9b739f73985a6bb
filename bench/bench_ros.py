"""The graphs live. By default the forward graph: a 640x480 trial replayed as a camera at 15 and 30 Hz into
sim_camera + enhancer. With ``--diagnose`` the live diagnosis at dive start (issue 19) against the offline one.

For each rate the graph is started fresh (`uw-sil launch forward`, no bag: a live camera), and this process
plays the camera: it renders a synthetic approach once (noisy frames, poses), then publishes
``camera/image_raw`` (best effort), ``camera/camera_info`` and ``panel/pose`` (reliable) with the current
time as stamp, looping over the frames, for ``--seconds``. It counts the enhanced frames that come back and
reads the enhancer's ``~/status`` (drops by cause, enhancer latency: from the later of its paired inputs'
arrival to publication). End to end: pose publication here to the enhanced frame's arrival here. ``missing_at``:
the send indices (first 20) of the frames that did not come back: start-up losses show as small indices.

    PYOPENGL_PLATFORM=osmesa .venv/bin/python bench/bench_ros.py [--rates 15 30] [--seconds 30] [--frames 30]

Last line: ``ros: rate=30Hz in=N out=N drops=N enhancer_p50_ms=X e2e_p50_ms=Y`` (the highest rate).
On a shared, loaded machine the numbers are indicative only.

``--diagnose``: one lamp-lit trial (``--width``/``--height``, default 160x120, ``--frames`` 12) is diagnosed twice in
the same run, one after the other: offline, ``uw-sil diagnose --bag`` as a process (its wall time: what the user
waits for; with ``--effects`` or ``--max-iter``, options the command does not have, the same library call,
``diagnose_bag``, with them), then live, ``uw-sil launch backward --bag ... --diagnose`` with the same frames and
budget, where this process times the last frame of the replay arriving (``camera/image_raw``) and the extended
model arriving in ``sim_camera`` (its parameter event). The live figure includes the graph's ``idle_timeout``
(3 s: how a replayed bag's end is noticed), not the nodes' start-up.

    PYOPENGL_PLATFORM=osmesa .venv/bin/python bench/bench_ros.py --diagnose [--diagnose-frames 6 --max-effects 1
        --effects artificial_light,vignetting,forward_scatter --max-iter 6]

Last line: ``ros-diagnose: live_s=X offline_s=Y diff_s=X-Y ratio=X/Y goal(diff<=2s)=met|missed``.
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


def close_graph(ex, node, ctx, proc):
    """Shut the bench's own node down, then stop the graph process (SIGINT, killed after 30 s). Also used by
    ``bench_simcam.py --ros``."""
    import signal

    ex.shutdown()
    node.destroy_node()
    ctx.try_shutdown()
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()


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
        close_graph(ex, node, ctx, proc)
    s = status[-1] if status else {}
    e2e = np.array([(got[t] - sent[t]) / 1e6 for t in got if t in sent])
    drops = s.get("dropped_queue", 0) + s.get("dropped_unpaired", 0) + s.get("dropped_bad", 0)
    # which frames did not come back: at start-up, at the end, or spread over the run
    missing = [i for i, t in enumerate(sent) if t not in got]
    return {"rate": rate, "in": len(sent), "out": sum(1 for t in got if t in sent), "drops": drops,
            "missing_at": missing[:20],
            "dropped_queue": s.get("dropped_queue"), "dropped_unpaired": s.get("dropped_unpaired"),
            "dropped_bad": s.get("dropped_bad"), "sim_frames": s.get("received", {}).get("depth"),
            "images_received": s.get("received", {}).get("image"),
            "enhancer_p50_ms": (s.get("latency_ms") or {}).get("p50"),
            "enhancer_p95_ms": (s.get("latency_ms") or {}).get("p95"),
            "e2e_p50_ms": float(np.percentile(e2e, 50)) if e2e.size else None,
            "e2e_p95_ms": float(np.percentile(e2e, 95)) if e2e.size else None}


def _lamp_trial(path: Path, n: int, camera: CameraModel) -> Path:
    from uw_sil.bags.synth import synthesize_trial, truth_path

    synthesize_trial(path, n_frames=n, seed=3, camera=camera, effects={"artificial_light": "strong"})
    truth_path(path).unlink()
    return path


def diagnose_offline(bag: Path, out: Path, k: int, max_effects: int, effects: str, max_iter: int) -> dict:
    """``uw-sil diagnose`` as a process (or, with options it does not have, its library call); wall time."""
    if not effects and not max_iter:
        cmd = [sys.executable, "-m", "uw_sil.cli", "diagnose", "--bag", str(bag), "--frames", str(k),
               "--max-effects", str(max_effects), "--json", str(out)]
        what = "uw-sil diagnose"
    else:
        allowed = [e.strip() for e in effects.split(",") if e.strip()] or None
        budget = {"max_iter": max_iter} if max_iter else {}
        code = ("import json, sys\n"
                "from uw_sil.fit.backward import write_json_atomic\n"
                "from uw_sil.fit.diagnose import diagnose_bag\n"
                f"d = diagnose_bag({str(bag)!r}, k={k}, max_effects={max_effects}, effects_allowed={allowed!r}, "
                f"**{budget!r})\n"
                f"write_json_atomic({str(out)!r}, d.to_json())\n")
        cmd = [sys.executable, "-c", code]
        what = "diagnose_bag (the call of uw-sil diagnose) with --effects/--max-iter"
    t0 = time.monotonic()
    r = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    wall = time.monotonic() - t0
    if r.returncode != 0:
        raise RuntimeError(f"{what} failed ({r.returncode}):\n{r.stdout[-3000:]}")
    doc = json.loads(out.read_text())
    return {"what": what, "wall_s": wall, "diagnosis_s": doc["timing"]["total_s"],
            "effects": doc["final"].get("effects", []), "theta_heldout": doc["final"]["theta_heldout"]}


def diagnose_live(bag: Path, out: Path, k: int, max_effects: int, effects: str, max_iter: int, domain: int) -> dict:
    """``uw-sil launch backward --bag --diagnose``: the last replayed frame here -> sim_camera's parameter event."""
    import re

    import rclpy
    from rcl_interfaces.msg import ParameterEvent
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, qos_profile_parameter_events, qos_profile_sensor_data
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    cmd = [sys.executable, "-m", "uw_sil.cli", "launch", "backward", "--bag", str(bag), "--diagnose", "--keep-running",
           "--diagnose-frames", str(k), "--diagnose-max-effects", str(max_effects), "--output-json", str(out)]
    if effects:
        cmd += ["--diagnose-effects", effects]
    if max_iter:
        cmd += ["--max-iter", str(max_iter)]
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = Node("bench_watcher", context=ctx)
    frames, model, status = [], [], []
    node.create_subscription(Image, "/camera/image_raw", lambda m: frames.append(time.monotonic()),
                             qos_profile_sensor_data)
    node.create_subscription(ParameterEvent, "/parameter_events",
                             lambda m: model.append(time.monotonic()) if m.node == "/sim_camera"
                             and m.changed_parameters else None, qos_profile_parameter_events)
    node.create_subscription(String, "/backward_fit/status", lambda m: status.append(m.data),
                             QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    log = []
    threading.Thread(target=lambda: log.extend(iter(proc.stdout.readline, "")), daemon=True).start()
    try:
        deadline = time.monotonic() + 3600
        while not any(t.startswith(("done:", "failed:")) for t in status):
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError("the live diagnosis did not finish:\n" + "".join(log[-40:]))
            ex.spin_once(timeout_sec=0.05)
        t_end = time.monotonic() + 5.0           # the parameter event may come just after the status
        while not model and time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.05)
    finally:
        close_graph(ex, node, ctx, proc)
    final = next(t for t in status if t.startswith(("done:", "failed:")))
    if not final.startswith("done:") or not model or not frames:
        raise RuntimeError(f"live diagnosis: {final}; frames seen {len(frames)}, sim_camera events {len(model)}\n"
                           + "".join(log[-40:]))
    doc = json.loads(out.read_text())
    m = re.search(r"extended model in sim_camera ([\d.]+) s after the last input message, ([\d.]+) s after the "
                  r"collection ended", "".join(log))
    return {"what": "uw-sil launch backward --diagnose", "last_frame_to_model_s": model[0] - frames[-1],
            "frames_seen": len(frames), "diagnosis_s": doc["timing"]["total_s"],
            "node_last_input_to_model_s": float(m.group(1)) if m else None,
            "node_collection_end_to_model_s": float(m.group(2)) if m else None,
            "effects": doc["final"].get("effects", []), "theta_heldout": doc["final"]["theta_heldout"]}


def main_diagnose(args):
    camera = CameraModel.from_fov(args.width or 160, args.height or 120, 70.0)
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        print(f"synthesizing a lamp-lit {camera.width}x{camera.height} trial of {args.frames} frames ...", flush=True)
        bag = _lamp_trial(d / "lamps.mcap", args.frames, camera)
        budget = dict(k=args.diagnose_frames, max_effects=args.max_effects, effects=args.effects,
                      max_iter=args.max_iter)
        off = diagnose_offline(bag, d / "offline.json", **budget)
        print(json.dumps({"offline": off}), flush=True)
        live = diagnose_live(bag, d / "live.json", domain=1 + (os.getpid() * 7) % 232, **budget)
        print(json.dumps({"live": live}), flush=True)
    same = off["effects"] == live["effects"]
    print(f"verdicts: offline {', '.join(off['effects']) or 'none'}, live {', '.join(live['effects']) or 'none'}"
          f"{'' if same else ' (DIFFER)'}; diagnosis itself: offline {off['diagnosis_s']:.1f} s, live "
          f"{live['diagnosis_s']:.1f} s; offline wall includes start-up and bag reading, live includes the 3 s "
          "idle_timeout (indicative: shared, loaded 2-core machine)")
    x, y = live["last_frame_to_model_s"], off["wall_s"]
    print(f"ros-diagnose: live_s={x:.1f} offline_s={y:.1f} diff_s={x - y:+.1f} ratio={x / y:.2f} "
          f"goal(diff<=2s)={'met' if x - y <= 2.0 else 'missed'}")


def main():
    # this process exchanges 640x480 images with the nodes: the same Fast DDS profile as the graph
    os.environ.setdefault("FASTDDS_DEFAULT_PROFILES_FILE", str(share_file("config", "fastdds_shm.xml")))
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rates", type=float, nargs="+", default=[15.0, 30.0])
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--frames", type=int, default=None, help="frames of the trial (default 30, looped; --diagnose: 12)")
    ap.add_argument("--width", type=int, default=None, help="default 640 (forward), 160 (--diagnose)")
    ap.add_argument("--height", type=int, default=None, help="default 480 (forward), 120 (--diagnose)")
    ap.add_argument("--diagnose", action="store_true", help="the live diagnosis against uw-sil diagnose instead")
    ap.add_argument("--diagnose-frames", type=int, default=8, help="--diagnose: frames diagnosed (uw-sil diagnose "
                    "--frames)")
    ap.add_argument("--max-effects", type=int, default=4, help="--diagnose: effects the greedy selection adds at most")
    ap.add_argument("--effects", default="", help="--diagnose: candidate effects, comma-separated (default all)")
    ap.add_argument("--max-iter", type=int, default=0, help="--diagnose: CMA-ES budget (default the diagnosis' own)")
    args = ap.parse_args()
    if args.diagnose:
        args.frames = args.frames or 12
        return main_diagnose(args)
    args.frames, args.width, args.height = args.frames or 30, args.width or 640, args.height or 480
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
