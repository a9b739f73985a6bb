"""The diagnosis in the live graph (issue 19): backward_fit collects frames, diagnoses them with the library call
of `uw-sil diagnose`, publishes /diagnostics and ~/diagnosis and re-parameterizes sim_camera with the extended
model; sim_camera takes new effects atomically (extensible_effects); the nodes read compressed images, a camera
YAML instead of camera_info, and poses from the panel's markers (panel_pose).

The trials are small (160x120; 320x240 where markers must be read) and the diagnosis budget is small (one
effect, three candidates, few iterations) so that a graph test takes about a minute."""
import json
import re
import sys
import time

import numpy as np
import pytest

from conftest import import_or_skip  # noqa: E402  (skips locally, fails in CI when rclpy is missing)

try:   # the session's colcon workspace with the real ros2 tools (skips where they or rclpy are missing)
    from test_ros2_tools import ws  # noqa: F401
except pytest.skip.Exception as _why:
    _skip_reason = str(_why)

    @pytest.fixture(scope="session")
    def ws():
        pytest.skip(_skip_reason)

SMALL = (160, 120)
#: The diagnosis budget of the graph tests (a lamp-lit trial: the lamps win against these two).
BUDGET = {"diagnose_frames": 6, "diagnose_max_effects": 1, "max_iter": 6,
          "diagnose_effects": "artificial_light,vignetting,forward_scatter"}


@pytest.fixture(scope="module")
def lamp_bag(tmp_path_factory):
    """12 frames at 160x120 from 4 m to 1.2 m, lit by strong vehicle lamps the truth conceals."""
    from uw_sil.bags.synth import synthesize_trial, truth_path
    from uw_sil.sim.camera import CameraModel

    bag = tmp_path_factory.mktemp("lamps") / "lamps.mcap"
    synthesize_trial(bag, n_frames=12, seed=3, camera=CameraModel.from_fov(*SMALL),
                     effects={"artificial_light": "strong"})
    truth_path(bag).unlink()
    return bag


# ------------------------------------------------------------------------------------------ no ROS


def test_the_collector_takes_the_frames_uw_sil_diagnose_takes(lamp_bag):
    """Frames offered one by one (as the node receives them) give the diagnosis the frames `uw-sil diagnose`
    reads from the bag: the same indices, images and poses, the k of the diagnosis and its report frames."""
    from uw_sil.bags import read_samples
    from uw_sil.fit.diagnose import REPORT_FRAMES, report_count
    from uw_sil.fit.live import SpreadCollector
    from uw_sil.fit.residuals import load_frames

    offline = load_frames(lamp_bag, k=6 + REPORT_FRAMES)      # what diagnose_bag(k=6) reads
    col = SpreadCollector(k=6)
    for s in read_samples(lamp_bag):
        assert col.offer(s)
    live = col.frames()
    assert [f.index for f in live] == [f.index for f in offline] == [0, 2, 3, 5, 6, 8, 9, 11]
    assert report_count(len(live), col.k) == REPORT_FRAMES == 2
    for a, b in zip(live, offline):
        assert np.array_equal(a.image, b.image) and np.array_equal(a.pose, b.pose)
        assert np.array_equal(a.render.range, b.render.range)
    with pytest.raises(ValueError, match="at least 3"):
        SpreadCollector(k=2)
    full = SpreadCollector(k=3, max_scan=3)
    assert all(full.offer(s) for s in [offline[0]] * 3) and full.done and not full.offer(offline[0])
    with pytest.raises(ValueError, match="no image could be paired"):
        SpreadCollector(k=3).frames()


def _doc(verdict=True):
    lamp = {"effect": "artificial_light", "round": 1, "theta_train": 0.9, "theta_heldout": 0.89,
            "delta_heldout": 0.17, "margin": 0.03, "accepted": True, "params": {"artificial_light.power": 1.3}}
    vig = {"effect": "vignetting", "round": 1, "theta_train": 0.8, "theta_heldout": 0.78, "delta_heldout": 0.01,
           "margin": 0.03, "accepted": False, "params": {"vignetting.k1": -0.1}}
    return {"verdict": [{"effect": "artificial_light", "confidence": 0.95, "explanation": "lit by vehicle lamps",
                         "params": {"artificial_light.power": 1.3, "a_r": 0.4}, "doubts": []}] if verdict else [],
            "candidates": [lamp, vig] if verdict else [{**lamp, "accepted": False, "delta_heldout": 0.001}, vig],
            "base": {"theta_heldout": 0.72, "theta_train": 0.73, "params": {}},
            "final": {"theta_heldout": 0.89 if verdict else 0.72, "effects": ["artificial_light"] if verdict else []},
            "timing": {"total_s": 34.0}}


def test_statuses_say_what_the_diagnosis_found():
    from uw_sil.fit.live import ERROR, OK, WARN, diagnostic_statuses, failure_statuses

    st = diagnostic_statuses(_doc(), "backward_fit")
    assert [(s["level"], s["name"]) for s in st] == [
        (WARN, "uw_sil diagnosis"), (WARN, "uw_sil diagnosis: artificial_light"), (OK, "uw_sil diagnosis: vignetting")]
    assert "artificial_light" in st[0]["message"] and "0.7200 -> 0.8900" in st[0]["message"]
    assert st[1]["message"] == "lit by vehicle lamps"
    assert st[1]["values"] == {"confidence": "0.95", "artificial_light.power": "1.3", "a_r": "0.4"}
    assert "below its margin" in st[2]["message"] and st[2]["values"]["margin"] == "0.03"
    assert all(s["hardware_id"] == "backward_fit" and all(isinstance(v, str) for v in s["values"].values())
               for s in st)
    assert "theta_heldout_simulated_final" not in st[0]["values"]      # a document from before that number
    doc = _doc()
    doc["base"]["theta_heldout_simulated"], doc["final"]["theta_heldout_simulated"] = 0.61, 0.83
    values = diagnostic_statuses(doc)[0]["values"]
    assert values["theta_heldout_simulated_base"] == "0.61" and values["theta_heldout_simulated_final"] == "0.83"
    assert "camera_noise" not in values
    doc["final"]["camera_noise"] = {"model": "photon_transfer", "values": {"shot": 0.06, "read": 0.7}}
    assert diagnostic_statuses(doc)[0]["values"]["camera_noise"] == "photon_transfer"
    doc = _doc()
    doc["undecided"] = [{"effect": "vignetting", "round": 1, "delta_heldout": 0.04, "margin": 0.03,
                         "explanation": "vignetting: beat its margin in round 1 (...); then dropped (...)"}]
    und = diagnostic_statuses(doc)[2]
    assert und["level"] == OK and und["message"].startswith("undecided, not named: vignetting: beat its margin")
    assert und["values"] == {"delta_heldout": "0.04", "margin": "0.03", "round": "1"}
    none = diagnostic_statuses(_doc(verdict=False))
    assert [s["level"] for s in none] == [OK, OK, OK] and none[0]["message"].startswith("none")
    (err,) = failure_statuses("only 1 usable frame(s)")
    assert err["level"] == ERROR and "only 1 usable frame" in err["message"]


def test_graphs_with_diagnose_compressed_images_markers_and_a_camera_file():
    from uw_sil.nodes import graph

    specs = {s.name: s for s in graph.backward_graph(bag="/d/t.mcap", diagnose=True, diagnose_frames=6,
                                                     image_transport="compressed", pose_source="markers",
                                                     camera_info_file="/d/cam.yaml", output_json="/d/diag.json")}
    assert list(specs) == ["sim_camera", "backward_fit", "panel_pose", "bag_play"]
    assert specs["sim_camera"].parameters == {"extensible_effects": "all", "camera_info_file": "/d/cam.yaml"}
    fit = specs["backward_fit"].parameters
    assert fit["diagnose"] is True and fit["diagnose_frames"] == 6 and fit["output_json"] == "/d/diag.json"
    assert fit["image_transport"] == "compressed" and fit["camera_info_file"] == "/d/cam.yaml"
    # a replay is read reliably (bag_play publishes reliably: nothing lost)
    assert specs["panel_pose"].parameters == {"image_transport": "compressed", "camera_info_file": "/d/cam.yaml",
                                              "reliable_input": True}
    play = specs["bag_play"].parameters
    assert play["wait_for_topics"] == ["/camera/image_raw/compressed"]      # no /panel/pose in such a bag
    assert play["wait_for_nodes"] == ["backward_fit", "panel_pose"]
    # without diagnose nothing changes for sim_camera; the sil graph's enhancer reads the same transport
    assert graph.backward_graph()[0].parameters == {}
    sil = {s.name: s for s in graph.sil_graph(bag="t.mcap", diagnose=True, image_transport="compressed")}
    assert sil["enhancer"].parameters["image_transport"] == "compressed"
    assert sil["sim_camera"].parameters["extensible_effects"] == "all" and "panel_pose" not in sil
    assert sil["sim_camera"].parameters["reliable_output"] is True and sil["enhancer"].parameters["reliable_input"]
    # the launch argument and the uw-sil launch option
    g = graph.GRAPHS["backward"]
    assert g.nodes({"diagnose": "true"})[1].parameters["diagnose"] is True
    with pytest.raises(ValueError, match="diagnose_frames"):
        g.parse({"diagnose_frames": "2"})
    with pytest.raises(ValueError, match="pose_source"):
        g.parse({"pose_source": "gps"})


def test_forward_graph_reads_compressed_images_markers_and_a_camera_file():
    """The forward graph takes a field recording as the backward graph does: the enhancer on
    camera/image_raw/compressed, panel_pose for the pose, sim_camera's intrinsics from the calibration file."""
    from uw_sil.nodes import graph

    specs = {s.name: s for s in graph.forward_graph(bag="/d/t.mcap", sim_params="/d/fit.yaml",
                                                    image_transport="compressed", pose_source="markers",
                                                    camera_info_file="/d/cam.yaml")}
    assert list(specs) == ["sim_camera", "enhancer", "panel_pose", "bag_play"]
    assert specs["sim_camera"].parameters == {**graph.REPLAY_SIM_CAMERA, "camera_info_file": "/d/cam.yaml",
                                              "reliable_output": True}
    assert specs["enhancer"].parameters["image_transport"] == "compressed" and specs["enhancer"].required
    assert specs["enhancer"].parameters["reliable_input"] is True      # sim/* and the camera: nothing lost
    assert specs["enhancer"].parameters["queue_size"] == graph.REPLAY_ENHANCER_QUEUE
    assert specs["enhancer"].parameters["idle_timeout"] == graph.MARKER_IDLE_TIMEOUT   # the poses come later
    # a replay is read reliably (bag_play publishes reliably: nothing lost)
    assert specs["panel_pose"].parameters == {"image_transport": "compressed", "camera_info_file": "/d/cam.yaml",
                                              "reliable_input": True}
    play = specs["bag_play"].parameters
    assert play["wait_for_topics"] == ["/camera/image_raw/compressed"]       # no /panel/pose in such a bag
    assert play["wait_for_nodes"] == ["enhancer", "panel_pose"]
    # a recorded pose topic: bag_play waits for the pose reader too, as before
    live = {s.name: s for s in graph.forward_graph(image_transport="compressed", pose_source="markers")}
    assert "reliable_input" not in live["panel_pose"].parameters      # a live camera: sensor-data QoS
    assert "reliable_input" not in live["enhancer"].parameters and "reliable_output" not in live["sim_camera"].parameters
    assert "queue_size" not in live["enhancer"].parameters          # a live camera: the queue of 2, for latency
    plain = {s.name: s for s in graph.forward_graph(bag="/d/t.mcap", image_transport="compressed")}
    assert plain["bag_play"].parameters["wait_for_topics"] == ["/camera/image_raw/compressed", "/panel/pose"]
    assert "panel_pose" not in plain
    g = graph.GRAPHS["forward"]
    nodes = {s.name: s for s in g.nodes({"image_transport": "compressed", "pose_source": "markers"})}
    assert "panel_pose" in nodes and nodes["enhancer"].parameters["image_transport"] == "compressed"
    with pytest.raises(ValueError, match="image_transport"):
        g.parse({"image_transport": "theora"})


def test_enhancer_renders_only_the_effects_sim_camera_lists():
    import_or_skip("rclpy", reason="ROS 2 Python packages (the `ros` extra) are not installed")
    from uw_sil.nodes.enhancer import _active

    values = {"a_r": 0.4, "fog_mode": "exp2", "effects": "artificial_light", "artificial_light.power": 1.0,
              "vignetting.k1": -0.3}
    assert _active(values) == {k: v for k, v in values.items() if k != "vignetting.k1"}
    assert _active({**values, "effects": ""}) == {"a_r": 0.4, "fog_mode": "exp2", "effects": ""}
    without = {k: v for k, v in values.items() if k != "effects"}
    assert _active(without) == without           # a sim node without an effects list: every effect it names


# ------------------------------------------------------------------------------------------ sim_camera in-process


def test_sim_camera_takes_new_effects_in_one_batch_only_when_extensible(ros):
    """With extensible_effects the effects list and the new effect's parameters are set in one atomic batch and
    sim_camera renders exactly what the offline model with that effect renders; an effect it did not declare,
    or a preset, is refused with the reason; without extensible_effects the list stays read-only."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    from rosproc import wait_future
    from uw_sil.nodes.sim_camera import SimCameraNode
    from uw_sil.sim.camera import CameraModel
    from uw_sil.sim.effects import get_effect
    from uw_sil.sim.params import UnderwaterParams
    from uw_sil.sim.scene import facing_pose
    from uw_sil.sim.simcam import SimCamera

    cam = CameraModel.from_fov(*SMALL)
    size = [Parameter("width", value=SMALL[0]), Parameter("height", value=SMALL[1])]
    sim = SimCameraNode(context=ros, parameter_overrides=size + [Parameter("extensible_effects",
                                                                           value="artificial_light")])
    client_node = Node("client", context=ros)
    client = AsyncParameterClient(client_node, "sim_camera")
    ex = SingleThreadedExecutor(context=ros)
    ex.add_node(sim)
    ex.add_node(client_node)
    T = facing_pose(1.8)
    lamp = dict(get_effect("artificial_light").severity("strong"))
    try:
        assert sim.sim.effects == {} and not sim.describe_parameter("effects").read_only
        assert client.wait_for_services(timeout_sec=15.0)
        for bad, why in (("vignetting", "not declared"), ("artificial_light=strong", "presets")):
            r = wait_future(ex, client.set_parameters_atomically([Parameter("effects", value=bad)])).result
            assert not r.successful and why in r.reason, r.reason
        batch = [Parameter("effects", value="artificial_light")]
        batch += [Parameter(f"artificial_light.{k}", value=float(v)) for k, v in lamp.items()]
        r = wait_future(ex, client.set_parameters_atomically(batch)).result
        assert r.successful, r.reason
        assert sim.get_parameter("artificial_light.power").value == lamp["power"]
        ref = SimCamera(UnderwaterParams(), camera=cam, effects={"artificial_light": lamp})
        try:
            assert np.array_equal(sim.sim.render(T).image_uint8(), ref.render(T).image_uint8())
        finally:
            ref.close()
        # and back to no effect
        r = wait_future(ex, client.set_parameters_atomically([Parameter("effects", value="")])).result
        assert r.successful and sim.sim.effects == {}
    finally:
        ex.shutdown()
        sim.destroy_node()
        client_node.destroy_node()
    plain = SimCameraNode(context=ros, parameter_overrides=size)
    try:
        assert plain.describe_parameter("effects").read_only and not plain.has_parameter("artificial_light.power")
    finally:
        plain.destroy_node()


# ------------------------------------------------------------------------------------------ the graph, as processes

rclpy = None


def _ros():
    global rclpy
    rclpy = import_or_skip("rclpy", reason="ROS 2 Python packages (the `ros` extra) are not installed")
    return rclpy


class Watcher:
    """A node of the test process on the graph's domain: /diagnostics, backward_fit's status and diagnosis,
    sim_camera's parameters and rendered frames."""

    def __init__(self, domain: int):
        _ros()
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.parameter_client import AsyncParameterClient
        from rclpy.qos import DurabilityPolicy, QoSProfile, qos_profile_sensor_data
        from geometry_msgs.msg import PoseStamped
        from sensor_msgs.msg import Image
        from std_msgs.msg import String

        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.node = Node("watcher", context=self.ctx)
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.status, self.diagnosis, self.diagnostics, self.frames = [], [], [], {}
        # depth 10: the statuses that follow one another quickly (stopping, stopped) are all kept
        self.node.create_subscription(String, "/backward_fit/status", lambda m: self.status.append(m.data),
                                      QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.node.create_subscription(String, "/backward_fit/diagnosis", lambda m: self.diagnosis.append(m.data),
                                      latched)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self.diagnostics.append, 10)
        self.node.create_subscription(Image, "/sim/image_raw", self._on_frame, qos_profile_sensor_data)
        self.pose_pub = self.node.create_publisher(PoseStamped, "/panel/pose", 10)
        self.sim_params = AsyncParameterClient(self.node, "/sim_camera")
        from std_srvs.srv import Trigger

        self.start = self.node.create_client(Trigger, "/backward_fit/start")
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)

    def _on_frame(self, m):
        self.frames[m.header.stamp.sec * 10**9 + m.header.stamp.nanosec] = m

    def spin_until(self, cond, timeout, what, detail=None):
        from rosproc import spin_until

        spin_until(self.ex, cond, timeout=timeout, what=what, detail=detail)

    def call_start(self, timeout: float = 30.0):
        """The ~/start service of backward_fit, answered (the Trigger response)."""
        from std_srvs.srv import Trigger

        from rosproc import wait_future

        self.spin_until(self.start.service_is_ready, timeout, "backward_fit's ~/start service")
        return wait_future(self.ex, self.start.call_async(Trigger.Request()), timeout=timeout,
                           what="the answer of backward_fit's ~/start")

    def wait_status(self, prefix: str, timeout: float, since: int = 0, proc=None) -> tuple:
        """(index, text) of the first status from ``since`` on that starts with ``prefix``; AssertionError at once
        when ``proc`` (backward_fit's Proc) has ended."""
        def found():
            return next(((i, t) for i, t in enumerate(self.status[since:], since) if t.startswith(prefix)), None)

        def ended():
            return proc is not None and proc.popen.poll() is not None

        what = f"a backward_fit status starting with {prefix!r}"
        self.spin_until(lambda: found() is not None or ended(), timeout, what,
                        detail=lambda: f"statuses received: {self.status}")
        assert found() is not None, f"{proc and proc.name} ended while waiting for {what}; statuses: {self.status}"
        return found()

    def params(self, names) -> dict:
        from rosproc import wait_future

        assert self.sim_params.wait_for_services(timeout_sec=30.0), "sim_camera's parameter services"
        values = wait_future(self.ex, self.sim_params.get_parameters(list(names))).values
        from rclpy.parameter import parameter_value_to_python

        return {n: parameter_value_to_python(v) for n, v in zip(names, values)}

    def render_at(self, pose, stamp_ns: int, timeout: float = 30.0):
        """sim_camera's frame for ``pose`` (published until sim_camera has matched and answered)."""
        from geometry_msgs.msg import PoseStamped
        from uw_sil.bags.imgmsg import image_to_rgb
        from uw_sil.sim.transforms import matrix_to_pose

        msg = PoseStamped()
        msg.header.frame_id = "camera_optical_frame"
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 10**9)
        (msg.pose.position.x, msg.pose.position.y, msg.pose.position.z), q = matrix_to_pose(pose)
        msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z, msg.pose.orientation.w = map(float, q)
        self.spin_until(lambda: self.pose_pub.get_subscription_count() > 0, timeout, "sim_camera's pose subscription")
        deadline = time.monotonic() + timeout
        while stamp_ns not in self.frames:
            assert time.monotonic() < deadline, "no sim/image_raw for the held-out pose"
            self.pose_pub.publish(msg)
            self.spin_until(lambda: stamp_ns in self.frames or time.monotonic() > deadline, timeout + 1, "a frame")
        return np.array(image_to_rgb(self.frames[stamp_ns]))

    def close(self):
        self.ex.shutdown()
        self.node.destroy_node()
        self.ctx.try_shutdown()


def _theta(reference, image) -> float:
    from uw_sil.metrics.theta import ThetaReference

    return float(ThetaReference(reference).score(image[None])[0])


def _check_live_diagnosis(watch, launch, out, samples, what):
    """What the graph must have done once backward_fit reports done: /diagnostics names the lamps, sim_camera holds
    the lamp parameters of the extended model, and sim_camera's frame at a held-out pose is closer (θ) to the
    recording than the base model's. Returns the diagnosis JSON."""
    from uw_sil.fit.diagnose import validate_diagnosis_json
    from uw_sil.sim.params import RGB_NAMES, UnderwaterParams
    from uw_sil.sim.simcam import SimCamera
    import yaml

    doc = json.loads(watch.diagnosis[-1])
    validate_diagnosis_json(doc)
    assert doc == json.loads((out / "diag.json").read_text())            # the document the node wrote
    assert [v["effect"] for v in doc["verdict"]] == ["artificial_light"], doc["verdict"]
    statuses = {s.name: s for arr in watch.diagnostics for s in arr.status}
    lamp = statuses["uw_sil diagnosis: artificial_light"]
    assert lamp.level == lamp.WARN and "lamps" in lamp.message
    keys = {kv.key: kv.value for kv in lamp.values}
    assert "artificial_light.power" in keys and "confidence" in keys
    assert statuses["uw_sil diagnosis"].level == lamp.WARN
    ext = yaml.safe_load((out / "ext.yaml").read_text())["/**"]["ros__parameters"]
    lamp_keys = sorted(k for k in ext if k.startswith("artificial_light."))
    held = watch.params(["effects", *lamp_keys, *RGB_NAMES, "noise_sigma"])
    assert held["effects"] == "artificial_light" and ext["effects"] == "artificial_light"
    for k in lamp_keys + list(RGB_NAMES):
        assert held[k] == pytest.approx(ext[k], rel=1e-12), k
    # a held-out frame: sim_camera's render vs the base model's, both against the recording
    idx = next(f["index"] for f in doc["frames"] if f["role"] == "heldout")
    s = samples[idx]
    live = watch.render_at(s.pose, 4_000_000_000 + idx)
    base = SimCamera(UnderwaterParams.from_dict(doc["base"]["params"]), camera=s.camera,
                     noise_sigma=ext["noise_sigma"], seed=0)
    try:
        base_img = base.render(s.pose).image_uint8()
    finally:
        base.close()
    t_ext, t_base = _theta(s.image, live), _theta(s.image, base_img)
    print(f"{what}: held-out frame #{idx}: θ extended {t_ext:.4f}, base {t_base:.4f}")
    assert t_ext > t_base + 0.02, (t_ext, t_base)
    m = re.search(r"extended model in sim_camera ([\d.]+) s after the last input message, ([\d.]+) s after the "
                  r"collection ended", launch.text)
    assert m, launch.tail()
    print(f"{what}: {m.group(0)}; diagnosis {doc['timing']['total_s']:.1f} s")
    return doc


def _launch_diagnose_args(graph: str, bag, tmp_path) -> list:
    """`uw-sil launch <graph> --diagnose` on ``bag`` with the tests' budget, outputs into ``tmp_path``."""
    args = [sys.executable, "-m", "uw_sil.cli", "launch", graph, "--bag", str(bag), "--diagnose",
            "--keep-running", "--output-yaml", str(tmp_path / "ext.yaml"), "--output-json", str(tmp_path / "diag.json")]
    for k, v in BUDGET.items():
        args += ["--" + k.replace("_", "-"), str(v)]
    return args


@pytest.mark.slow
def test_uw_sil_launch_backward_diagnose(lamp_bag, tmp_path):
    """`uw-sil launch backward --diagnose` on a lamp-lit trial (raw images, recorded poses)."""
    _ros()
    from uw_sil.bags import read_samples

    from rosproc import Proc, assert_clean_output, domain_id, logs_on_failure, ros_env

    domain = domain_id()
    args = _launch_diagnose_args("backward", lamp_bag, tmp_path)
    watch = Watcher(domain)
    launch = Proc(args, ros_env(domain), name="uw-sil launch backward --diagnose")
    try:
        with logs_on_failure(launch):
            watch.spin_until(lambda: any(t.startswith(("done:", "failed:")) for t in watch.status), 400,
                             "backward_fit to finish the diagnosis", detail=launch.tail)
            assert watch.status[-1].startswith("done: diagnosis: artificial_light"), watch.status[-1]
            watch.spin_until(lambda: watch.diagnosis and watch.diagnostics, 30, "the diagnosis messages")
            samples = list(read_samples(lamp_bag))
            _check_live_diagnosis(watch, launch, tmp_path, samples, "uw-sil launch")
            # the pilot's steps are printed as the CLI prints them
            for step in ("diagnosing: base fit on 3 frames", "diagnosing: round 1: refitting base + each of",
                         "diagnosing: round 1: base + artificial_light refitted",
                         "diagnosing: round 1: accepted artificial_light"):
                assert step in launch.text, step
            launch.signal(2)
            launch.wait_group(60)
        assert launch.popen.returncode == 0, launch.tail()
        assert_clean_output(launch.text, "uw-sil launch")
    finally:
        launch.stop()
        watch.close()


def test_params_file_of_the_diagnosis_renders_the_offline_extended_model(ros, tmp_path):
    """`sim_camera --ros-args --params-file` of the diagnosis YAML renders pixel-identically to the offline
    extended model (SimCamera with the same effects) at the same pose."""
    from uw_sil.fit.backward import read_params_yaml
    from uw_sil.fit.diagnose import write_diagnosis_yaml
    from uw_sil.fit.live import extended_parameters
    from uw_sil.nodes.sim_camera import SimCameraNode
    from uw_sil.sim.camera import CameraModel
    from uw_sil.sim.effects import get_effect
    from uw_sil.sim.scene import facing_pose
    from uw_sil.sim.simcam import SimCamera
    from types import SimpleNamespace

    lamp = dict(get_effect("artificial_light").severity("strong"))
    base = {"a_r": 0.41, "a_g": 0.12, "a_b": 0.09, "b_r": 0.06, "b_g": 0.31, "b_b": 0.43, "rho_f": 0.05}
    diag = SimpleNamespace(final_params={"base": base, "effects": {"artificial_light": lamp}},
                           final={"effects": ["artificial_light"]},
                           noise={"camera_noise_dn_full_resolution": [[0.0, 0.0, 0.0]]})
    path = write_diagnosis_yaml(tmp_path / "ext.yaml", diag)
    assert extended_parameters(diag) == __import__("yaml").safe_load(path.read_text())["/**"]["ros__parameters"]
    node = SimCameraNode(context=ros, cli_args=["--ros-args", "-p", f"width:={SMALL[0]}", "-p", f"height:={SMALL[1]}",
                                                "--params-file", str(path)])
    f = read_params_yaml(path)
    ref = SimCamera(f["params"], camera=CameraModel.from_fov(*SMALL), effects=f["effects"], fog=f["fog"])
    try:
        assert node.get_parameter("effects").value == "artificial_light"
        for T in (facing_pose(1.5), facing_pose(3.0)):
            assert np.array_equal(node.sim.render(T).image_uint8(), ref.render(T).image_uint8())
    finally:
        ref.close()
        node.destroy_node()


@pytest.fixture(scope="module")
def field_bag(tmp_path_factory):
    """A lamp-lit trial as a field recording: JPEG on camera/image_raw/compressed, no pose (the panel's markers
    only), no camera_info (a calibration file); 320x240 so that the markers can be read, 2.8 m to 1.2 m."""
    from uw_sil.bags.synth import synthesize_trial, truth_path
    from uw_sil.sim.camera import CameraModel

    d = tmp_path_factory.mktemp("field")
    bag, cam = d / "field.mcap", d / "camera.yaml"
    synthesize_trial(bag, n_frames=12, seed=3, camera=CameraModel.from_fov(320, 240),
                     effects={"artificial_light": "strong"}, image_format="jpeg", pose_in="none", info_topic=None,
                     image_topic="/camera/image_raw/compressed", camera_yaml=cam, start_m=2.8, end_m=1.2)
    truth_path(bag).unlink()
    return bag, cam


@pytest.mark.slow
def test_ros2_launch_backward_diagnose_on_a_field_recording(ws, field_bag, tmp_path):
    """The real `ros2 launch uw_sil backward.launch.py diagnose:=true` (colcon build, as test_ros2_tools) on a
    recording of compressed images without pose or camera_info: panel_pose publishes the marker poses, the
    calibration comes from camera_info_file; /diagnostics names the lamps, sim_camera holds them, and its frame at
    a held-out pose is closer to the recording than the base model's."""
    _ros()
    from uw_sil.bags import read_samples
    from uw_sil.bags.camera_yaml import load_camera_yaml
    from uw_sil.bags.source import PoseFrom

    from rosproc import assert_clean_output, domain_id, logs_on_failure

    bag, cam = field_bag
    domain = domain_id()
    watch = Watcher(domain)
    args = ["launch", "uw_sil", "backward.launch.py", f"bag:={bag}", "diagnose:=true", "keep_running:=true",
            "image_transport:=compressed", "pose_source:=markers", f"camera_info_file:={cam}",
            f"output_yaml:={tmp_path / 'ext.yaml'}", f"output_json:={tmp_path / 'diag.json'}",
            *(f"{k}:={v}" for k, v in BUDGET.items())]
    launch = ws.start(domain, *args, name="ros2 launch backward diagnose:=true")
    try:
        with logs_on_failure(launch):
            watch.spin_until(lambda: any(t.startswith(("done:", "failed:")) for t in watch.status), 900,
                             "backward_fit to finish the diagnosis", detail=launch.tail)
            assert watch.status[-1].startswith("done: diagnosis: artificial_light"), watch.status[-1]
            watch.spin_until(lambda: watch.diagnosis and watch.diagnostics, 30, "the diagnosis messages")
            assert re.search(r"\[panel_pose-\d\]", launch.text), "panel_pose did not run"
            samples = list(read_samples(bag, image_topic="/camera/image_raw/compressed", info_topic=None,
                                        pose_topic=None, pose_from=PoseFrom.parse("markers"),
                                        calibration=load_camera_yaml(cam)))
            _check_live_diagnosis(watch, launch, tmp_path, samples, "ros2 launch (compressed, markers)")
            launch.signal(2)
            launch.wait_group(60)
        assert_clean_output(launch.text, "ros2 launch")
    finally:
        launch.stop()
        watch.close()


#: Seconds within which a running diagnosis must have stopped after ~/start: it stops at its next optimizer iteration
#: or step (3-4 s on the loaded 2-core machine); a least-squares stage between two of them is not interruptible.
STOP_DEADLINE = 20.0
#: Seconds within which backward_fit must have ended after Ctrl-C (it waits backward_fit.STOP_WAIT for the diagnosis).
EXIT_DEADLINE = 10.0


@pytest.mark.slow
def test_start_or_ctrl_c_stops_a_running_diagnosis(lamp_bag, tmp_path):
    """A diagnosis is stopped by ~/start (the node answers at once, the diagnosis ends within STOP_DEADLINE, its
    status says so, nothing is written or published, and the new collection diagnoses the next replay), then the
    new diagnosis by Ctrl-C (the node exits with 0 within STOP_DEADLINE, says it stopped, writes nothing)."""
    _ros()
    from uw_sil.nodes import graph

    from rosproc import Proc, assert_clean_output, domain_id, logs_on_failure, ros_env

    out_yaml, out_json = tmp_path / "ext.yaml", tmp_path / "diag.json"
    budget = {k: v for k, v in BUDGET.items() if k != "max_iter"}   # the diagnosis' own budget: it runs long enough
    specs = {s.name: s for s in graph.backward_graph(bag=str(lamp_bag), diagnose=True, keep_running=True,
                                                     output_yaml=str(out_yaml), output_json=str(out_json),
                                                     **budget)}
    specs["bag_play"].parameters["wait_for_nodes"] = ["backward_fit"]     # no sim_camera here: not waited for
    domain = domain_id()
    env = ros_env(domain)
    watch = Watcher(domain)
    fit = Proc(graph.command_line(specs["backward_fit"]), env, name="backward_fit")
    plays = [Proc(graph.command_line(specs["bag_play"]), env, name="bag_play (first replay)")]

    def nothing_out(when: str):
        assert not list(tmp_path.iterdir()), f"{when}: written (or left partly written): {list(tmp_path.iterdir())}"
        assert not watch.diagnosis and not watch.diagnostics, f"{when}: a diagnosis was published"

    try:
        with logs_on_failure(fit, plays):
            # 1. ~/start during the base fit of the diagnosis
            i, _ = watch.wait_status("diagnosing: base fit", 400, proc=fit)
            t_ask = time.monotonic()
            resp = watch.call_start()
            t_answer = time.monotonic()
            assert resp.success and resp.message.startswith("stopping the running diagnosis"), resp.message
            j, stopped = watch.wait_status("stopped: the diagnosis, by ~/start", STOP_DEADLINE, since=i, proc=fit)
            t_stopped = time.monotonic()
            assert "nothing written or sent" in stopped, stopped
            print(f"backward_fit ~/start: answered in {t_answer - t_ask:.2f} s; the diagnosis stopped {t_stopped - t_ask:.2f} s "
                  f"after the call ({stopped})")
            # the new collection takes the next replay and diagnoses it from the start
            plays.append(Proc(graph.command_line(specs["bag_play"]), env, name="bag_play (second replay)"))
            k, _ = watch.wait_status("diagnosing 6 frames", 400, since=j, proc=fit)
            assert not [t for t in watch.status[j + 1:k] if t.startswith("diagnosing")], watch.status
            nothing_out("after ~/start")
            # 2. Ctrl-C during the first candidate's refit
            watch.wait_status("diagnosing: round 1: refitting", 600, since=k, proc=fit)
            t_sig = time.monotonic()
            fit.signal(2)
            fit.wait_group(EXIT_DEADLINE)
            assert fit.popen.returncode == 0, fit.tail()
            assert "stopping the running diagnosis: nothing will be written or sent" in fit.text, fit.tail()
            # the diagnosis stopped at its next iteration, or (inside a least-squares stage) ended with the process
            how = re.search(r"stopped: the diagnosis, by the node's shutdown.*nothing written or sent|"
                            r"the diagnosis did not stop within .* it ends with the process, nothing written", fit.text)
            assert how, fit.tail()
            print(f"Ctrl-C: backward_fit ended {time.monotonic() - t_sig:.2f} s after SIGINT; {how.group(0)}")
            assert_clean_output(fit.text, "backward_fit")
            assert "Failed to publish" not in fit.text, fit.tail()
            nothing_out("after Ctrl-C")
    finally:
        fit.stop()
        for p in plays:
            p.stop()
        watch.close()


@pytest.mark.slow
def test_uw_sil_launch_sil_diagnose_restores_with_the_extended_model(lamp_bag, tmp_path):
    """`uw-sil launch sil --diagnose`: the diagnosis re-parameterizes sim_camera and, through its parameter events,
    the enhancer, which then restores a frame with the extended model (the lamp parameters sim_camera holds)."""
    _ros()
    from uw_sil.bags import read_samples
    from rclpy.qos import DurabilityPolicy, QoSProfile
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    from rosproc import Proc, assert_clean_output, domain_id, logs_on_failure, ros_env
    from uw_sil.bags.imgmsg import rgb_to_image_fields

    domain = domain_id()
    args = _launch_diagnose_args("sil", lamp_bag, tmp_path)
    watch = Watcher(domain)
    enh_status, enhanced = [], {}
    watch.node.create_subscription(String, "/enhancer/status", lambda m: enh_status.append(json.loads(m.data)),
                                   QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    watch.node.create_subscription(Image, "/camera/image_enhanced",
                                   lambda m: enhanced.__setitem__(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec,
                                                                  m), 10)
    pub_img = watch.node.create_publisher(Image, "/camera/image_raw", 10)
    launch = Proc(args, ros_env(domain), name="uw-sil launch sil --diagnose")
    try:
        with logs_on_failure(launch):
            watch.spin_until(lambda: any(t.startswith(("done:", "failed:")) for t in watch.status), 400,
                             "backward_fit to finish the diagnosis", detail=launch.tail)
            assert watch.status[-1].startswith("done: diagnosis: artificial_light"), watch.status[-1]
            held = watch.params(["effects", "artificial_light.power"])
            assert held["effects"] == "artificial_light"
            # the enhancer follows sim_camera: its model (on its status) holds the lamps sim_camera holds
            watch.spin_until(lambda: enh_status and (enh_status[-1].get("model") or {}).get("artificial_light.power")
                             == pytest.approx(held["artificial_light.power"], rel=1e-12), 30,
                             "the enhancer's model with sim_camera's artificial_light.power",
                             detail=lambda: f"enhancer status: {enh_status[-1] if enh_status else None}")
            # and restores a frame with it: a recorded frame and its pose, published now, come back enhanced
            samples = list(read_samples(lamp_bag))
            s = samples[5]
            # after the bag's stamps: the enhancer pairs by stamp, and a stamp before the newest it saw is stale
            stamp = max(x.stamp_ns for x in samples) + 10_000_000_000
            img = Image(**rgb_to_image_fields(s.image))
            img.header.stamp.sec, img.header.stamp.nanosec = divmod(stamp, 10**9)
            img.header.frame_id = "camera_optical_frame"
            watch.spin_until(lambda: pub_img.get_subscription_count() > 0, 30, "the enhancer's camera subscription")
            deadline = time.monotonic() + 60
            while stamp not in enhanced:
                assert time.monotonic() < deadline, f"no camera/image_enhanced for stamp {stamp}"
                pub_img.publish(img)
                watch.render_at(s.pose, stamp, timeout=30)
                watch.spin_until(lambda: stamp in enhanced or time.monotonic() > deadline, 61, "an enhanced frame")
            out = enhanced[stamp]
            assert (out.width, out.height, out.encoding) == (SMALL[0], SMALL[1], "rgb8")
            print(f"uw-sil launch sil --diagnose: enhancer model holds artificial_light.power "
                  f"{held['artificial_light.power']:.4g}; frame {stamp} enhanced")
            launch.signal(2)
            launch.wait_group(60)
        assert launch.popen.returncode == 0, launch.tail()
        assert_clean_output(launch.text, "uw-sil launch sil")
    finally:
        launch.stop()
        watch.close()


@pytest.mark.slow
def test_uw_sil_launch_forward_on_a_field_recording(field_bag, tmp_path):
    """`uw-sil launch forward` on a recording of JPEG images without pose or camera_info: the enhancer reads
    camera/image_raw/compressed, panel_pose publishes the marker poses, sim_camera takes the calibration file; the
    graph enhances the frames and ends by itself after the bag."""
    _ros()
    from uw_sil.bags import read_samples
    from uw_sil.bags.camera_yaml import load_camera_yaml
    from uw_sil.bags.source import PoseFrom
    from uw_sil.bags.synth import DEFAULT_TRUTH
    from uw_sil.fit.backward import write_params_yaml

    from rosproc import Proc, assert_clean_output, domain_id, logs_on_failure, ros_env

    bag, cam = field_bag
    fit = write_params_yaml(tmp_path / "fit.yaml", DEFAULT_TRUTH)
    args = [sys.executable, "-m", "uw_sil.cli", "launch", "forward", "--bag", str(bag), "--sim-params", str(fit),
            "--image-transport", "compressed", "--pose-source", "markers", "--camera-info-file", str(cam)]
    launch = Proc(args, ros_env(domain_id()), name="uw-sil launch forward (compressed, markers)")
    try:
        with logs_on_failure(launch):
            launch.wait_group(300)
            text = launch.text
            assert launch.popen.returncode == 0
            assert "required node enhancer ended" in text and "all nodes ended cleanly" in text
            assert re.search(r"\[panel_pose\s*\]", text), "panel_pose did not run"
            done = json.loads(text.split("done; ", 1)[1].splitlines()[0])
            # every frame on which the markers give a pose offline (the reader of uw-sil fit --pose-from markers)
            # is enhanced; the others have no pose, so no sim frame to pair with
            posed = len(list(read_samples(bag, image_topic="/camera/image_raw/compressed", info_topic=None,
                                          pose_topic=None, pose_from=PoseFrom.parse("markers"),
                                          calibration=load_camera_yaml(cam))))
            print(f"uw-sil launch forward (compressed, markers): {done['enhanced']} of 12 frames enhanced, "
                  f"{posed} with a marker pose offline")
            assert posed >= 6, posed
            # what panel_pose received and posed (its last log line), to name where a frame went missing
            pp = re.search(r"\[panel_pose\s*\].*done; (\{.*\})", text)
            pp = json.loads(pp.group(1)) if pp else "no final line of panel_pose"
            # read reliably (a replay), panel_pose gets every image, and poses the frames the reader poses offline
            assert isinstance(pp, dict) and pp.get("images") == 12 and pp.get("poses") == posed, (posed, pp)
            assert done["enhanced"] == posed and done["dropped_unpaired"] == 12 - posed, (
                f"{done['enhanced']} of {posed} frames with a marker pose offline enhanced; enhancer {done}; "
                f"panel_pose {pp}")
            assert done["dropped_bad"] == 0 and done["dropped_queue"] == 0, done
        assert_clean_output(text, "uw-sil launch forward")
    finally:
        launch.stop()
