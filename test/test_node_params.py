"""Node parameters that hold: every parameter has its own descriptor (description, range, read-only
where a change cannot take effect), a batch of changes is checked whole before any of it applies,
backward_fit refuses bad values with reasons and survives its service calls, and says when no frames
arrive. In-process nodes, one rclpy Context per test on its own domain."""
import math
import time

import numpy as np
import pytest

from conftest import import_or_skip  # noqa: E402  (skips locally, fails in CI when rclpy is missing)

rclpy = import_or_skip("rclpy", reason="ROS 2 Python packages (the `ros` extra) are not installed")

pytestmark = pytest.mark.filterwarnings("ignore:module 'sre_:DeprecationWarning")

from rcl_interfaces.msg import ParameterType  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.parameter_client import AsyncParameterClient  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from uw_sil.bags.synth import synthesize_trial  # noqa: E402
from uw_sil.sim.camera import CameraModel  # noqa: E402
from uw_sil.sim.params import RGB_NAMES  # noqa: E402
from uw_sil.sim.scene import facing_pose  # noqa: E402

from rosproc import spin_until, wait_future  # noqa: E402

SMALL = CameraModel.from_fov(160, 120, 70.0)
TIMEOUT = 15.0
ROS_OWN = {"use_sim_time", "start_type_description_service"}    # declared by rclpy itself


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory):
    out = tmp_path_factory.mktemp("bag") / "trial.mcap"
    synthesize_trial(out, n_frames=4, seed=5, camera=SMALL, start_m=2.5, end_m=1.5)
    return out


def _nodes(ros, small_bag):
    from uw_sil.nodes.backward_fit import BackwardFitNode
    from uw_sil.nodes.bag_play import BagPlayNode
    from uw_sil.nodes.sim_camera import SimCameraNode

    small = [Parameter("width", value=SMALL.width), Parameter("height", value=SMALL.height)]
    return [SimCameraNode(context=ros, parameter_overrides=small),
            BackwardFitNode(context=ros, parameter_overrides=[Parameter("auto_start", value=False)]),
            BagPlayNode(context=ros, parameter_overrides=[Parameter("bag", value=str(small_bag))])]


READ_ONLY = {
    "sim_camera": {"model_path", "width", "height", "hfov_deg", "queue_size", "effects", "extensible_effects",
                   "camera_info_file", "reliable_output", "workers"},
    "backward_fit": {"sim_node", "max_dt", "auto_start", "model_path", "exit_when_done", "reliable_input",
                     "image_transport", "camera_info_file"},
    "bag_play": {"bag", "rate", "loop", "start_paused", "delay", "wait_timeout", "clock_hz", "topics",
                 "wait_for_topics", "wait_for_nodes"},
}


def test_every_parameter_has_its_own_descriptor(ros, small_bag):
    """What `ros2 param describe` shows: each parameter's own name and type (rclpy writes them into the
    descriptor object, so a shared object showed the last parameter's for all), a description, a range
    for numbers, and read-only exactly where a change cannot take effect."""
    nodes = _nodes(ros, small_bag)
    try:
        for node in nodes:
            names = sorted(set(node._parameters) - ROS_OWN)
            assert len(names) == {"sim_camera": 19, "backward_fit": 26, "bag_play": 10}[node.get_name()], names
            descriptors = node.describe_parameters(names)
            ids = {id(node._descriptors[n]) for n in names}
            assert len(ids) == len(names), f"{node.get_name()}: descriptor objects shared between parameters"
            for name, d in zip(names, descriptors):
                value = node.get_parameter(name)
                where = f"{node.get_name()}.{name}"
                assert d.name == name and d.type == value.type_.value, where
                assert d.type != ParameterType.PARAMETER_NOT_SET, f"{where} has no value"
                assert len(d.description) > 15, where
                if d.type == ParameterType.PARAMETER_DOUBLE and name != "rate" or d.type == ParameterType.PARAMETER_INTEGER:
                    assert d.floating_point_range or d.integer_range, f"{where} has no range"
            assert {n for n, d in zip(names, descriptors) if d.read_only} == READ_ONLY[node.get_name()]
    finally:
        for node in nodes:
            node.destroy_node()


def test_bag_play_string_arrays_have_a_value(ros, small_bag):
    """`ros2 param get /bag_play topics` said "Parameter not set", and the get service then answered
    nothing at all for a request naming it (so `ros2 param dump /bag_play` came back empty)."""
    from uw_sil.nodes.bag_play import BagPlayNode

    player = BagPlayNode(context=ros, parameter_overrides=[
        Parameter("bag", value=str(small_bag)), Parameter("wait_for_nodes", value=["backward_fit"])])
    client_node = Node("client", context=ros)
    client = AsyncParameterClient(client_node, "bag_play")
    ex = SingleThreadedExecutor(context=ros)
    ex.add_node(player)
    ex.add_node(client_node)
    try:
        assert client.wait_for_services(timeout_sec=TIMEOUT), f"parameter services of {client.remote_node_name}"
        names = ["topics", "wait_for_topics", "wait_for_nodes", "bag", "rate"]
        values = wait_future(ex, client.get_parameters(names)).values
        assert [v.type for v in values[:3]] == [ParameterType.PARAMETER_STRING_ARRAY] * 3
        assert [list(v.string_array_value) for v in values[:3]] == [[], [], ["backward_fit"]]
        assert values[3].string_value == str(small_bag) and values[4].double_value == 1.0
    finally:
        ex.shutdown()
        player.destroy_node()
        client_node.destroy_node()


def test_sim_camera_batch_with_a_bad_last_entry_changes_nothing(ros):
    """A batch is checked whole in the on-set callback and applied only in the post-set callback: a batch
    rejected by its last entry leaves the parameters, the simulator (fog mode, noise, the 7 parameters)
    and the rendered frame as they were."""
    from uw_sil.nodes.sim_camera import SimCameraNode

    sim = SimCameraNode(context=ros, parameter_overrides=[Parameter("width", value=SMALL.width),
                                                          Parameter("height", value=SMALL.height)])
    client_node = Node("client", context=ros)
    client = AsyncParameterClient(client_node, "sim_camera")
    ex = SingleThreadedExecutor(context=ros)
    ex.add_node(sim)
    ex.add_node(client_node)
    T = facing_pose(1.8)
    names = list(RGB_NAMES) + ["fog_mode", "noise_sigma"]
    try:
        before_values = [p.value for p in sim.get_parameters(names)]
        before = (sim.sim.params, sim.sim.fog, sim.sim.noise_sigma)
        before_image = sim.sim.render(T).image_uint8()
        assert client.wait_for_services(timeout_sec=TIMEOUT), f"parameter services of {client.remote_node_name}"
        good = [Parameter("fog_mode", value="exp"), Parameter("noise_sigma", value=2.0), Parameter("a_r", value=0.9)]
        for last, why in ((Parameter("b_g", value=1.5), "out of range"),           # the descriptor's range
                          (Parameter("fog_mode", value="bogus"), "bogus"),         # the node's own check
                          (Parameter("width", value=320), "read-only")):
            result = wait_future(ex, client.set_parameters_atomically(good + [last])).result
            assert not result.successful and why in result.reason, result.reason
        # the on-set callback alone (without rclpy's checks in front): a valid fog mode first, then an
        # invalid noise value must not leave the fog mode changed
        result = sim._on_set_parameters([Parameter("fog_mode", value="exp"), Parameter("noise_sigma", value=math.nan)])
        assert not result.successful and "noise_sigma" in result.reason
        assert [p.value for p in sim.get_parameters(names)] == before_values
        assert (sim.sim.params, sim.sim.fog, sim.sim.noise_sigma) == before
        np.testing.assert_array_equal(sim.sim.render(T).image_uint8(), before_image)

        # the same batch without the bad entry applies whole
        result = wait_future(ex, client.set_parameters_atomically(good)).result
        assert result.successful, result.reason
        assert sim.sim.fog == "exp" and sim.sim.noise_sigma == 2.0 and sim.sim.params.a[0] == 0.9
    finally:
        ex.shutdown()
        sim.destroy_node()
        client_node.destroy_node()


def test_sim_camera_refuses_bad_start_values(ros):
    from uw_sil.nodes.sim_camera import SimCameraNode

    with pytest.raises(ValueError, match="fog_mode.*'fo'"):
        SimCameraNode(context=ros, parameter_overrides=[Parameter("fog_mode", value="fo")])


def test_backward_fit_checks_parameters_when_set_and_survives_start(ros):
    """`ros2 param set /backward_fit frames -3` and `optimizer bogus` reported success, and the next
    ~/start killed the node (the service call hung)."""
    from uw_sil.nodes.backward_fit import BackwardFitNode

    fit = BackwardFitNode(context=ros, parameter_overrides=[Parameter("auto_start", value=False)])
    client_node = Node("client", context=ros)
    client = AsyncParameterClient(client_node, "backward_fit")
    start = client_node.create_client(Trigger, "/backward_fit/start")
    ex = SingleThreadedExecutor(context=ros)
    ex.add_node(fit)
    ex.add_node(client_node)
    try:
        assert client.wait_for_services(timeout_sec=TIMEOUT) and start.wait_for_service(timeout_sec=TIMEOUT), \
            "backward_fit's parameter services and ~/start"
        for bad, why in ((Parameter("frames", value=-3), "out of range"), (Parameter("stride", value=0), "out of range"),
                         (Parameter("optimizer", value="bogus"), "'bogus' is not one of pso, cmaes"),
                         (Parameter("color_model", value="lab"), "not one of rgb, hsv"),
                         (Parameter("fog_mode", value="fo"), "not one of exp2"),
                         (Parameter("channels", value="HXV"), "subset of 'HSV'"),
                         (Parameter("min_coverage", value=1.5), "out of range"),
                         (Parameter("seed", value=-1), "out of range"),
                         (Parameter("sim_node", value="other"), "read-only"),
                         (Parameter("exit_when_done", value=True), "read-only"),
                         (Parameter("frames", value="3"), "type")):
            r = wait_future(ex, client.set_parameters([bad])).results[0]
            assert not r.successful and why in r.reason, (bad.name, r.reason)
        values = wait_future(ex, client.get_parameters(["frames", "optimizer", "channels"])).values
        assert (values[0].integer_value, values[1].string_value, values[2].string_value) == (3, "pso", "HSV")
        ok = wait_future(ex, client.set_parameters([Parameter("frames", value=2), Parameter("optimizer", value="cmaes"),
                                             Parameter("channels", value="hs")])).results
        assert all(r.successful for r in ok), [r.reason for r in ok]
        resp = wait_future(ex, start.call_async(Trigger.Request()))
        assert resp.success and resp.message == "collecting frames"
        assert fit.selector is not None and fit.selector.k == 2
        # a collection is running, no fit: a second ~/start restarts the collection (nothing to refuse)
        assert wait_future(ex, start.call_async(Trigger.Request())).success
    finally:
        ex.shutdown()
        fit.destroy_node()
        client_node.destroy_node()


def test_backward_fit_says_when_no_frames_arrive(ros):
    """With no input at all, the collection fails after ``first_frame_timeout`` naming the topics."""
    from uw_sil.nodes.backward_fit import BackwardFitNode

    fit = BackwardFitNode(context=ros, parameter_overrides=[Parameter("first_frame_timeout", value=1.0),
                                                            Parameter("idle_timeout", value=0.5),
                                                            Parameter("exit_when_done", value=True)])
    statuses = []
    status = fit._status
    fit._status = lambda text: (statuses.append(text), status(text))
    ex = SingleThreadedExecutor(context=ros)
    ex.add_node(fit)
    try:
        t0 = time.monotonic()
        spin_until(ex, fit.finished.done, what="backward_fit to give up")
        assert 0.9 <= time.monotonic() - t0 < 5
        assert fit.finished.result() is False
        assert statuses[-1] == ("failed: no frames arrived: no message on /camera/image_raw, /camera/camera_info, "
                                "/panel/pose in 1 s"), statuses
    finally:
        ex.shutdown()
        fit.destroy_node()


def test_backward_fit_renders_at_the_size_of_its_camera_info_file(ros, tmp_path):
    """With ``camera_info_file`` the renderer's context is made (and warmed) at the calibration's size, not at
    a default 640x480 that the first fit would throw away."""
    from uw_sil.bags.camera_yaml import CameraCalibration, write_camera_yaml
    from uw_sil.nodes.backward_fit import BackwardFitNode

    path = write_camera_yaml(tmp_path / "cam.yaml", CameraCalibration.from_camera_model(SMALL))
    fit = BackwardFitNode(context=ros, parameter_overrides=[Parameter("auto_start", value=False),
                                                            Parameter("camera_info_file", value=str(path))])
    try:
        cam = fit.renderer.camera
        assert (cam.width, cam.height, cam.fx) == (SMALL.width, SMALL.height, pytest.approx(SMALL.fx)), cam
    finally:
        fit.destroy_node()


def test_backward_fit_rejects_bad_start_values(ros):
    from uw_sil.nodes.backward_fit import BackwardFitNode

    with pytest.raises(ValueError, match="optimizer: 'nelder' is not one of"):
        BackwardFitNode(context=ros, parameter_overrides=[Parameter("optimizer", value="nelder")])


def test_nodes_interrupted_while_starting_shut_down_cleanly(ros, monkeypatch):
    """Ctrl-C while a node builds its renderer: rclpy still destroys the half-built node at shutdown, which
    raised AttributeError (no renderer yet) and made the node exit 1 with a traceback."""
    import uw_sil.nodes.sim_camera as sim_camera
    import uw_sil.sim.render as render
    from uw_sil.nodes.backward_fit import BackwardFitNode

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(render, "Renderer", interrupted)
    monkeypatch.setattr(sim_camera, "SimCamera", interrupted)
    with pytest.raises(KeyboardInterrupt):
        BackwardFitNode(context=ros)
    with pytest.raises(KeyboardInterrupt):
        sim_camera.SimCameraNode(context=ros)
    ros.try_shutdown()          # destroys both half-built nodes


def test_an_enhancer_interrupted_while_starting_is_destroyed_cleanly(ros):
    """The enhancer's destroy_node stops its worker and guards its publishers; interrupted in its constructor
    right after the node itself exists (no worker, no queue yet), destroying it must not raise."""
    from rclpy.node import Node

    from uw_sil.nodes.enhancer import EnhancerNode

    node = EnhancerNode.__new__(EnhancerNode)
    Node.__init__(node, "enhancer", context=ros)
    node.destroy_node()


@pytest.mark.parametrize("replay", [False, True])
def test_replay_flags_make_the_forward_topics_reliable(ros, replay):
    """A live sim_camera is a camera (sensor-data QoS, best effort) and so are the enhancer's readers; in a replay
    (``reliable_output`` / ``reliable_input``, set by the replay graphs) both are reliable, so that no frame is
    lost between them."""
    from rclpy.qos import ReliabilityPolicy

    from uw_sil.nodes.enhancer import EnhancerNode
    from uw_sil.nodes.sim_camera import SimCameraNode

    small = [Parameter("width", value=SMALL.width), Parameter("height", value=SMALL.height)]
    sim = SimCameraNode(context=ros, parameter_overrides=small + [Parameter("reliable_output", value=replay)])
    enh = EnhancerNode(context=ros, parameter_overrides=[Parameter("reliable_input", value=replay)])
    want = ReliabilityPolicy.RELIABLE if replay else ReliabilityPolicy.BEST_EFFORT
    try:
        for topic in ("/sim/depth", "/sim/mask", "/sim/camera_info", "/sim/image_raw"):
            pubs = sim.get_publishers_info_by_topic(topic)
            assert [p.qos_profile.reliability for p in pubs] == [want], (topic, pubs)
        for topic in ("/sim/depth", "/sim/mask", "/sim/camera_info"):
            subs = [s for s in enh.get_subscriptions_info_by_topic(topic) if s.node_name == "enhancer"]
            assert [s.qos_profile.reliability for s in subs] == [want], (topic, subs)
        assert enh._sensor.reliability == want          # the camera subscription, made once the model is known
    finally:
        enh.destroy_node()
        sim.destroy_node()
