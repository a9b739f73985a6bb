"""The ``enhancer`` node in-process (a stand-in sim_camera, a probe publishing frames), and the forward graph end
to end as `uw-sil launch forward` on a tiny synthetic bag.

Every test that touches DDS uses its own ROS_DOMAIN_ID and ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST.
"""
import json
import sys
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="ROS 2 Python packages (the `ros` extra) are not installed")
pytestmark = pytest.mark.filterwarnings("ignore:module 'sre_:DeprecationWarning")

from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.parameter_client import AsyncParameterClient  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402
from std_msgs.msg import Header, String  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from uw_sil.bags import iter_messages  # noqa: E402
from uw_sil.bags.imgmsg import depth_to_image_fields, image_to_rgb, rgb_to_image_fields  # noqa: E402
from uw_sil.bags.synth import synthesize_trial  # noqa: E402
from uw_sil.enhance.dcp import dehaze_dcp  # noqa: E402
from uw_sil.enhance.sil import enhance  # noqa: E402
from uw_sil.sim.camera import CameraModel  # noqa: E402
from uw_sil.sim.optics import degrade  # noqa: E402
from uw_sil.sim.params import UnderwaterParams  # noqa: E402
from uw_sil.sim.scene import facing_pose  # noqa: E402

from rosproc import Proc, call_until_answered, domain_id, logs_on_failure, ros_env, spin_until  # noqa: E402

CAM = CameraModel.from_fov(160, 120, 70.0)
TRUTH = UnderwaterParams(a=(0.40, 0.12, 0.08), b=(0.07, 0.33, 0.43), rho_f=0.10)
TIMEOUT = 20.0
START = 120.0     # a graph of node processes starting or replaying a bag, on a loaded 2-core machine


@pytest.fixture(scope="module")
def frame():
    from uw_sil.sim.render import Renderer

    with Renderer(camera=CAM) as r:
        rr = r.render(facing_pose(1.5))
    img = np.clip(np.rint(degrade(rr.rgb, rr.range, rr.depth, TRUTH.as_vector()) * 255), 0, 255).astype(np.uint8)
    return img, rr


class FakeSim(Node):
    """Stands in for sim_camera: the model parameters, a pose subscription, publishes sim frames on demand."""

    def __init__(self, context):
        super().__init__("sim_camera", context=context)
        for n, v in TRUTH.as_dict().items():
            self.declare_parameter(n, v)
        self.declare_parameter("fog_mode", "exp2")
        self.create_subscription(PoseStamped, "panel/pose", lambda m: None, 10)
        self.pubs = {t: self.create_publisher(cls, t, 10) for t, cls in
                     (("sim/depth", Image), ("sim/mask", Image), ("sim/camera_info", CameraInfo))}

    def publish(self, stamp_ns, rr, depth=None, mask=None, camera=CAM):
        h = Header(frame_id="camera_optical_frame")
        h.stamp.sec, h.stamp.nanosec = divmod(stamp_ns, 10**9)
        self.pubs["sim/depth"].publish(Image(header=h, **depth_to_image_fields(rr.depth if depth is None else depth)))
        self.pubs["sim/mask"].publish(Image(header=h, **rgb_to_image_fields(rr.labels if mask is None else mask,
                                                                            "mono8")))
        self.pubs["sim/camera_info"].publish(CameraInfo(header=h, **camera.camera_info_fields()))


class Probe(Node):
    def __init__(self, context):
        super().__init__("probe", context=context)
        self.pub = self.create_publisher(Image, "camera/image_raw", 10)
        self.got, self.info, self.status = {}, {}, []
        self.create_subscription(Image, "camera/image_enhanced", self._on_image, 10)
        self.create_subscription(CameraInfo, "camera/image_enhanced/camera_info",
                                 lambda m: self.info.__setitem__(_ns(m), m), 10)
        self.create_subscription(String, "enhancer/status", lambda m: self.status.append(json.loads(m.data)),
                                 QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.params = AsyncParameterClient(self, "enhancer")

    def _on_image(self, m):
        self.got[_ns(m)] = m

    def publish(self, stamp_ns, img, encoding="rgb8"):
        h = Header(frame_id="camera_optical_frame")
        h.stamp.sec, h.stamp.nanosec = divmod(stamp_ns, 10**9)
        self.pub.publish(Image(header=h, **rgb_to_image_fields(img, encoding)))


def _ns(m):
    return m.header.stamp.sec * 10**9 + m.header.stamp.nanosec


@pytest.fixture
def graph(ros, request):
    from uw_sil.nodes.enhancer import EnhancerNode

    overrides = [Parameter(k, value=v) for k, v in getattr(request, "param", {}).items()]
    sim, probe = FakeSim(ros), Probe(ros)
    enh = EnhancerNode(context=ros, parameter_overrides=overrides)
    ex = SingleThreadedExecutor(context=ros)
    for n in (sim, probe, enh):
        ex.add_node(n)
    spin_until(ex, lambda: probe.pub.get_subscription_count() > 0, what="the enhancer to subscribe to the camera")
    # Discovery is not matching: frames sent before both sides matched are lost (best effort). Send warm-up
    # frames until one comes back enhanced, then start from clean counters.
    img, rr = request.getfixturevalue("frame")
    deadline = time.monotonic() + TIMEOUT
    k = 0
    while not probe.got:
        assert time.monotonic() < deadline, "no warm-up frame came back from the enhancer"
        k += 1
        _send(ex, sim, probe, k * 1000, img, rr, wait=False)
        for _ in range(10):
            ex.spin_once(timeout_sec=0.02)
    spin_until(ex, lambda: not enh._queue and not enh._busy, what="the warm-up to finish")
    probe.got.clear()
    enh.counts.clear()
    enh.latency.clear()
    yield ex, sim, probe, enh
    ex.shutdown()
    for n in (enh, probe, sim):
        n.destroy_node()


def _send(ex, sim, probe, stamp, img, rr, wait=True, **kw):
    probe.publish(stamp, img, kw.pop("encoding", "rgb8"))
    sim.publish(stamp, rr, **kw)
    if wait:
        spin_until(ex, lambda: stamp in probe.got, what=f"the enhanced frame {stamp}")
        return probe.got[stamp]


def test_enhances_each_frame_with_the_sims_parameters_and_follows_them(graph, frame):
    ex, sim, probe, enh = graph
    img, rr = frame
    msg = _send(ex, sim, probe, 1_000_000_000, img, rr)
    assert msg.header.frame_id == "camera_optical_frame" and msg.encoding == "rgb8"
    want = enhance(img, depth=rr.depth, mask=rr.labels, camera=CAM, model=TRUTH).image
    np.testing.assert_array_equal(image_to_rgb(msg), want)
    spin_until(ex, lambda: 1_000_000_000 in probe.info, what="the enhanced camera_info")
    assert list(probe.info[1_000_000_000].k) == list(CAM.camera_info_fields()["k"])
    # a backward fit re-parameterizes sim_camera: the enhancer follows its parameter events
    new = UnderwaterParams(a=(0.5, 0.2, 0.1), b=(0.1, 0.3, 0.4), rho_f=0.05)
    assert all(r.successful for r in sim.set_parameters([Parameter(n, value=v) for n, v in new.as_dict().items()]))
    spin_until(ex, lambda: enh.model is not None and enh.model.params == new, what="the enhancer to follow")
    msg = _send(ex, sim, probe, 2_000_000_000, img, rr)
    np.testing.assert_array_equal(image_to_rgb(msg),
                                  enhance(img, depth=rr.depth, mask=rr.labels, camera=CAM, model=new).image)
    # an invalid value on the sim side is not taken: once the enhancer has had the parameter event of a
    # valid change that comes after it (events arrive in order), the model is still the one before
    sim.set_parameters([Parameter("b_r", value=3.0)])
    before = enh.model
    sim.set_parameters([Parameter("fog_mode", value="exp2")])      # unchanged: a new model of the same values
    spin_until(ex, lambda: enh.model is not before, what="the enhancer to take the parameter event after b_r")
    assert enh.model.params == new
    spin_until(ex, lambda: probe.status and probe.status[-1]["enhanced"] == 2, what="the status")
    s = probe.status[-1]
    assert s["model"]["a_r"] == 0.5 and s["dropped_bad"] == 0 and s["latency_ms"]["n"] == 2
    assert 0 < s["restored_fraction"] < 1 and s["b_source"] == "fit"


def test_method_is_validated_and_live(graph, frame):
    ex, sim, probe, enh = graph
    img, rr = frame
    fut = probe.params.set_parameters([Parameter("method", value="clahe")])
    spin_until(ex, fut.done, what="the parameter service")
    r = fut.result().results[0]
    assert not r.successful and "method must be one of" in r.reason
    fut = probe.params.set_parameters([Parameter("method", value="udcp")])
    spin_until(ex, fut.done, what="the parameter service")
    assert fut.result().results[0].successful
    msg = _send(ex, sim, probe, 3_000_000_000, img, rr)
    np.testing.assert_array_equal(image_to_rgb(msg), dehaze_dcp(img, variant="udcp").image)
    fut = probe.params.set_parameters([Parameter("queue_size", value=5)])
    spin_until(ex, fut.done, what="the parameter service")
    assert not fut.result().results[0].successful                       # read-only


def test_bad_input_is_dropped_counted_and_the_node_keeps_running(graph, frame):
    ex, sim, probe, enh = graph
    img, rr = frame
    nan = rr.depth.copy()
    nan[60, 80] = np.nan
    zero = rr.depth.copy()
    zero[0, 0] = 0.0
    small = CameraModel.from_fov(80, 60, 70.0)
    cases = [dict(depth=nan), dict(depth=zero), dict(encoding="mono8"),
             dict(depth=np.full((60, 80), np.inf, np.float32), mask=np.zeros((60, 80), np.uint8), camera=small)]
    for k, kw in enumerate(cases):
        frame_img = img[..., 0].copy() if kw.get("encoding") == "mono8" else img
        _send(ex, sim, probe, 10_000_000_000 + k * 100_000_000, frame_img, rr, wait=False, **kw)
        spin_until(ex, lambda: enh.counts["dropped_bad"] == k + 1, what=f"bad frame {k} counted ({enh.counts})")
    msg = _send(ex, sim, probe, 11_000_000_000, img, rr)                 # a good frame afterwards
    assert msg is not None
    assert enh.bad == {"geometry": 2, "mono": 1, "size": 1}, enh.bad
    assert set(probe.got) == {11_000_000_000}


@pytest.mark.parametrize("graph", [{"max_dt": 0.01, "pair_queue_size": 4}], indirect=True)
def test_stamps_that_never_pair_are_dropped_and_reported_once(graph, frame, capfd):
    """Images whose sim frames are always 0.463 s off: each is decided once 4 images wait (the bound), dropped
    and counted; the offsets are logged once."""
    ex, sim, probe, enh = graph
    img, rr = frame
    for k in range(20):
        t = 20_000_000_000 + k * 100_000_000
        probe.publish(t, img)
        sim.publish(t - 500_000_000 + 37_000_000, rr)            # the sim is 0.463 s behind
        for _ in range(3):
            ex.spin_once(timeout_sec=0.02)
    spin_until(ex, lambda: enh.sync.stats.dropped >= 10, what="unpaired images counted")
    assert probe.got == {} and enh.counts["enhanced"] == 0
    err = capfd.readouterr().err           # the warning was written (unbuffered stderr) in the callback
    assert err.count("had no sim frame within max_dt") == 1, err
    assert "+0.463 s" in err


@pytest.mark.parametrize("graph", [{"queue_size": 1}], indirect=True)
def test_queue_is_bounded_drops_the_oldest_and_counts(graph, frame):
    """Frames coming faster than the enhancer (slowed to 50 ms a frame here) can follow: the queue keeps the
    newest frame, the older ones are dropped and counted."""
    ex, sim, probe, enh = graph
    img, rr = frame
    fast = enh.enhancer.enhance

    def slow(*a, **k):
        time.sleep(0.05)
        return fast(*a, **k)

    enh.enhancer.enhance = slow
    stamps = [30_000_000_000 + k * 10_000_000 for k in range(15)]
    for t in stamps:
        probe.publish(t, img)
        sim.publish(t, rr)
        for _ in range(4):
            ex.spin_once(timeout_sec=0.002)
    spin_until(ex, lambda: enh.counts["paired"] == 15 and not enh._queue and not enh._busy,
               what="the burst to be processed")
    c = enh.counts
    assert c["dropped_queue"] > 0 and c["enhanced"] + c["dropped_queue"] == 15
    spin_until(ex, lambda: stamps[-1] in probe.got, what="the newest frame")
    assert len(probe.got) == c["enhanced"]


# ------------------------------------------------------------------------------------------ the graph


@pytest.mark.slow
def test_forward_graph_replays_a_trial_and_enhances_every_frame(tmp_path, monkeypatch):
    """`uw-sil launch forward --bag`: one enhanced frame per recorded frame, with its stamp; the graph ends
    by itself after the bag (the enhancer is required and exits when idle). The replay starts paused and is
    resumed once this watcher has matched the enhancer's publisher, as a recorder of the enhanced stream
    would: without that the frames sent before discovery were lost to it (3.6 s late in a loaded run)."""
    bag = tmp_path / "trial.mcap"
    synthesize_trial(bag, n_frames=12, seed=3, params=TRUTH, camera=CAM, start_m=3.0, end_m=1.2)
    stamps = sorted(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
                    for _, m in iter_messages(bag, "/camera/image_raw"))
    fit = tmp_path / "fit.yaml"
    from uw_sil.fit.backward import write_params_yaml

    write_params_yaml(fit, TRUTH, fog="exp2")
    domain = domain_id()
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = Node("watcher", context=ctx)
    got = {}
    sub = node.create_subscription(Image, "/camera/image_enhanced", lambda m: got.__setitem__(_ns(m), m), 50)
    resume = node.create_client(Trigger, "/bag_play/resume")
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    launch = Proc([sys.executable, "-m", "uw_sil.cli", "launch", "forward", "--bag", str(bag),
                   "--sim-params", str(fit), "--rate", "2", "--start-paused"], ros_env(domain),
                  name="uw-sil launch forward")
    try:
        with logs_on_failure(launch):
            spin_until(ex, lambda: sub.get_publisher_count() > 0 and resume.service_is_ready(), timeout=START,
                       what="the enhancer's publisher on /camera/image_enhanced and bag_play's ~/resume")
            # (an answer lost to discovery is asked for again: then the first call may have resumed it already)
            answer, calls = call_until_answered(ex, resume, Trigger.Request(), what="bag_play's answer to ~/resume")
            assert answer.success or (calls > 1 and answer.message == "not paused"), (answer, calls)
            # the graph ends by itself after the bag (the enhancer exits when idle); frames it lost would show
            # in its final counts, which are checked first: a lost frame fails at once, naming the cause
            missing = lambda: f"got {len(got)} of {len(stamps)}: missing stamps {sorted(set(stamps) - set(got))}"  # noqa: E731
            spin_until(ex, lambda: set(stamps) <= set(got) or launch.popen.poll() is not None, timeout=START,
                       what="the enhanced frames or the end of the graph", detail=missing)
            launch.wait_group(START)
            text = launch.text
            assert launch.popen.returncode == 0
            assert "required node enhancer ended" in text and "all nodes ended cleanly" in text
            done = json.loads(text.split("done; ", 1)[1].splitlines()[0])
            assert done["enhanced"] == 12 and done["dropped_unpaired"] == 0 and done["dropped_queue"] == 0, done
            # all 12 were published (reliably, to this watcher's reliable subscription): the rest are in flight
            spin_until(ex, lambda: set(stamps) <= set(got), what="the enhanced frames the enhancer published",
                       detail=missing)
            assert sorted(got) == stamps
            assert all(got[t].width == 160 and got[t].encoding == "rgb8" for t in stamps)
    finally:
        launch.stop()
        ex.shutdown()
        node.destroy_node()
        ctx.try_shutdown()
