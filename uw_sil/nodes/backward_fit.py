"""``backward_fit`` node: at dive start, fit the simulator's 7 parameters to the first real frames and
re-parameterize the ``sim_camera`` node through its parameter services; with ``diagnose``, find the physics
the simulation lacks and re-parameterize it with the extended model.

Subscribes ``camera/image_raw`` (Image; with ``image_transport:=compressed``: ``camera/image_raw/compressed``,
CompressedImage, JPEG/PNG), ``camera/camera_info`` (CameraInfo; not with ``camera_info_file``), ``panel/pose``
(PoseStamped), paired by stamp (:class:`uw_sil.bags.stamps.StampSynchronizer`). The first ``frames``
usable frames (:class:`uw_sil.fit.backward.FrameSelector`) are fitted in a worker thread
(:func:`uw_sil.fit.backward.fit_frames`); the result is sent atomically to
``<sim_node>/set_parameters_atomically`` and optionally written as a parameters YAML.

With ``diagnose`` (read when a collection starts) the node instead keeps the paired frames until the input
ends (``idle_timeout``) or ``max_scan`` came, takes ``diagnose_frames`` spread over them as ``uw-sil diagnose``
does over a bag, and up to 2 more set aside as report frames when enough came
(:class:`uw_sil.fit.live.SpreadCollector`), and runs the same library call as ``uw-sil
diagnose`` (:func:`uw_sil.fit.diagnose.diagnose_frames`) in its worker thread, each step on ``~/status``. The
result: ``~/diagnosis`` (std_msgs/String, transient local: the JSON document of ``uw-sil diagnose --json``),
``/diagnostics`` (diagnostic_msgs/DiagnosticArray: a summary and one status per effect judged, WARN for an
accepted effect with its parameters as key/values, OK for one not needed, ERROR when it could not diagnose),
the extended model (base, ``noise_sigma``, ``effects`` and every accepted ``<effect>.<param>``) sent atomically
to ``sim_node`` (which must be started with ``extensible_effects`` to take new effects) and written to
``output_yaml`` (the file of ``uw-sil diagnose --params-out``) and ``output_json``. ``~/start`` during a
diagnosis answers at once, stops it at its next optimizer iteration or step (nothing written or sent; then
``stopped: ...`` on ``~/status``) and starts a new collection, paired afresh (a bag replayed again starts at its
first stamp). Ctrl-C stops it too: the node waits ``STOP_WAIT`` s for it, and one inside a step without an
interrupt check (a least-squares stage) ends with the process; nothing is written either way.

Publishes ``~/status`` (std_msgs/String, transient local: ``collecting ...``, ``fitting ...``, then
``done: ...`` or ``failed: ...``; with ``diagnose`` also ``diagnosing: <step>`` and ``stopped: ...``) and ``~/theta``
(std_msgs/Float64, best θ per iteration of the plain fit). Service
``~/start`` (std_srvs/Trigger) starts a new collection and fit (answered ``success: false`` with the
reason when a fit is running or the parameters do not make a valid selection).

Parameters (``ros2 param describe /backward_fit`` lists each with its range): the frame selection
(``frames``, ``stride``, ``min_coverage``, ``max_scan``) and the fit (``optimizer``, ``color_model``,
``channels``, ``fog_mode``, ``seed``, ``max_iter``, ``output_yaml``) are checked when set and used by the
next collection / fit; ``idle_timeout`` and ``first_frame_timeout`` take effect at once; ``sim_node``,
``max_dt``, ``auto_start``, ``model_path``, ``image_transport``, ``camera_info_file`` and ``exit_when_done``
are read-only (read at start). The diagnosis takes ``diagnose_frames``, ``diagnose_max_effects``,
``diagnose_effects``, ``output_json`` and, of the fit's, ``fog_mode``, ``seed`` and ``max_iter`` (0: its own).
With ``idle_timeout`` > 0 the frames taken so far are fitted once no input message has arrived for
that many seconds (a replayed bag has ended); with ``first_frame_timeout`` > 0 the collection fails
("no frames arrived ...") when no input message at all arrived that long after it started. With
``exit_when_done`` the node exits after the fit (status 0 when done, 1 when failed): an offline
replay graph ends with it.
"""
from __future__ import annotations

import inspect
import json
import sys
import threading
import time

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
import numpy as np
from rclpy.node import Node
from rclpy.task import Future
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Float64, String
from std_srvs.srv import Trigger

try:
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
except ImportError as _e:  # a missing dependency is an installation error, not a reason to publish less
    raise ImportError("backward_fit needs diagnostic_msgs (pip install ros-kilted-diagnostic-msgs, in the `ros` "
                      f"extra of uw_sil; in a ROS 2 workspace: the diagnostic_msgs package): {_e}") from _e

from ..fit.backward import FrameSelector, fit_frames, write_json_atomic, write_params_yaml
from ..fit.optimize import warm_up
from ..fit.diagnose import diagnose_frames, report_count, write_diagnosis_yaml
from ..fit.live import SpreadCollector, diagnostic_statuses, extended_parameters, failure_statuses
from ..bags import Sample
from ..fit.optimize import METHODS
from ..sim.camera import CameraModel
from ..sim.optics import FOG_MODES
from ..bags.imgmsg import compressed_to_rgb, image_to_rgb
from ..bags.stamps import StampSynchronizer
from ..sim.transforms import pose_to_matrix
from . import AskedUntilAnswered, camera_from_file, executor_for, run_node

#: ``image_transport`` values: the camera topic and message type of each (image_transport's naming).
TRANSPORTS = {"raw": ("camera/image_raw", Image), "compressed": ("camera/image_raw/compressed", CompressedImage)}


#: Seconds a shutdown waits for a running fit or diagnosis to stop (at its next optimizer iteration).
STOP_WAIT = 3.0


class _Cancelled(Exception):
    """A running diagnosis was stopped (Ctrl-C, or ~/start for a new one): nothing is written or sent."""


def _defaults(fn) -> dict:
    return {n: p.default for n, p in inspect.signature(fn).parameters.items() if p.default is not p.empty}


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


#: Values the string parameters accept (the core's names).
_CHOICES = {"optimizer": METHODS, "color_model": ("rgb", "hsv"), "fog_mode": FOG_MODES,
            "image_transport": tuple(TRANSPORTS)}


def _float_range(lo: float, hi: float) -> dict:
    return {"floating_point_range": [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]}


def _int_range(lo: int, hi: int) -> dict:
    return {"integer_range": [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]}


def _parameters(sel: dict, fit: dict, diag: dict) -> list:
    """(name, default, description, descriptor fields) of every parameter; defaults are the core's."""
    live = "; used by the next collection (~/start)"
    return [
        ("diagnose", False, "diagnose instead of fitting: the physics the simulation lacks, and the extended model "
         "sent to sim_node (as uw-sil diagnose)" + live, {}),
        ("diagnose_frames", 8, "frames the diagnosis takes, spread over the frames received (uw-sil diagnose "
         "--frames; up to 2 more, when enough came, are set aside as report frames)" + live, _int_range(3, 100)),
        ("diagnose_max_effects", diag["max_effects"], "effects the greedy selection adds at most (uw-sil diagnose "
         "--max-effects; particles, noise and compression, judged on statistics, come on top)" + live,
         _int_range(1, 10)),
        ("diagnose_effects", "", "effects the diagnosis considers, comma-separated (empty: every effect it can "
         "judge)" + live, {}),
        ("output_json", "", "write the diagnosis JSON here (the document of uw-sil diagnose --json; empty: do not)"
         + live, {}),
        ("frames", sel["k"], "K: usable frames to fit" + live, _int_range(1, 1000)),
        ("stride", sel["stride"], "consider every n-th frame (spreads the K frames over more ranges)" + live,
         _int_range(1, 1000)),
        ("min_coverage", sel["min_coverage"], "smallest image fraction the panel must cover to take a frame"
         + live, _float_range(0.0, 0.999)),
        ("max_scan", sel["max_scan"], "frames looked at, at most" + live, _int_range(1, 1_000_000)),
        ("optimizer", fit["method"], f"one of {', '.join(METHODS)}; used by the next fit", {}),
        ("color_model", fit["color_model"], "parameterization searched: rgb or hsv; used by the next fit", {}),
        ("channels", fit["channels"], "HSV channels of the histogram criterion (a subset of 'HSV', e.g. HS); "
         "used by the next fit", {}),
        ("fog_mode", fit["fog"], f"fog model, one of {', '.join(FOG_MODES)}; used by the next fit", {}),
        ("seed", fit["seed"], "seed of the optimizer; used by the next fit", _int_range(0, 2**31 - 1)),
        ("max_iter", 0, "optimizer iterations (0: the optimizer's default; the diagnosis: its own); used by "
         "the next fit",
         _int_range(0, 100_000)),
        ("output_yaml", "", "write the fitted parameters (with diagnose: the extended model) here as a ROS 2 "
         "parameters file (empty: do not); used by the next fit", {}),
        ("idle_timeout", 0.0, "fit the frames taken when no input message arrived for this long [s] "
         "(0: wait for all frames)", _float_range(0.0, 3600.0)),
        ("first_frame_timeout", 0.0, "fail the collection when no input message arrived this long after it "
         "started [s] (0: wait)", _float_range(0.0, 3600.0)),
        ("sim_node", "sim_camera", "node whose parameters the fit sets; read at start",
         {"read_only": True}),
        ("max_dt", 0.05, "largest stamp difference of a paired image and pose [s]; read at start",
         {"read_only": True, **_float_range(0.0, 10.0)}),
        ("auto_start", True, "start collecting at start (else on ~/start); read at start", {"read_only": True}),
        ("model_path", "", "panel model for frame selection (empty: the procedural panel); read at start",
         {"read_only": True}),
        ("reliable_input", False, "subscribe to images and camera_info reliably (a replayed bag: nothing lost) "
         "instead of best effort (matches any camera driver); read at start", {"read_only": True}),
        ("exit_when_done", False, "exit after the fit: status 0 when done, 1 when failed; read at start",
         {"read_only": True}),
        ("image_transport", "raw", "camera input: raw (sensor_msgs/Image on camera/image_raw) or compressed "
         "(sensor_msgs/CompressedImage, JPEG/PNG, on camera/image_raw/compressed); read at start",
         {"read_only": True, "additional_constraints": "one of " + ", ".join(TRANSPORTS)}),
        ("camera_info_file", "", "camera calibration YAML (camera_calibration format, no distortion) used instead "
         "of camera/camera_info, for recordings without it (empty: subscribe camera/camera_info); read at start",
         {"read_only": True}),
    ]


def _check(name: str, value) -> str:
    """Why ``value`` is not acceptable for parameter ``name`` beyond its descriptor ('' when it is)."""
    if name in _CHOICES and value not in _CHOICES[name]:
        return f"{name}: {value!r} is not one of {', '.join(_CHOICES[name])}"
    if name == "channels":
        chans = str(value).upper()
        if not chans or not set(chans) <= set("HSV") or len(set(chans)) != len(chans):
            return f"channels: {value!r} is not a non-empty subset of 'HSV' without repeats (e.g. HSV, HS, V)"
    if name == "min_coverage" and not 0.0 <= value < 1.0:
        return f"min_coverage: {value} is not in [0, 1)"
    if name == "diagnose_effects" and value.strip():
        from ..fit.judges import JUDGES

        unknown = [e.strip() for e in value.split(",") if e.strip() and e.strip() not in JUDGES]
        if unknown:
            return f"diagnose_effects: {', '.join(unknown)} not judged by the diagnosis (it judges {', '.join(JUDGES)})"
    return ""


class BackwardFitNode(Node):
    def __init__(self, **kwargs):
        super().__init__("backward_fit", **kwargs)
        # Defaults are the core's (uw-sil fit uses the same), so the node and the CLI cannot drift apart.
        declared = _parameters(_defaults(FrameSelector), _defaults(fit_frames), _defaults(diagnose_frames))
        for name, default, description, fields in declared:
            self.declare_parameter(name, default, ParameterDescriptor(description=description, **fields))
        reasons = [r for r in (_check(n, self.get_parameter(n).value) for n, *_ in declared) if r]
        if reasons:   # values given at start (parameter files, -p) pass the same checks as later changes
            raise ValueError("backward_fit: " + "; ".join(reasons))
        self.add_on_set_parameters_callback(self._on_set_parameters)
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.pub_status = self.create_publisher(String, "~/status", latched)
        self.pub_theta = self.create_publisher(Float64, "~/theta", 10)
        self.pub_diagnosis = self.create_publisher(String, "~/diagnosis", latched)
        self.pub_diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._run_cancel = threading.Event()   # the running diagnosis' own: set by ~/start for a new one
        self._stop_asked = None                # monotonic time a stop of the running diagnosis was asked
        self._stop_said = False                # the shutdown's stop of the running diagnosis was logged
        self._sent_effects = False             # whether this node has set sim_node's effects
        camera_file = self.get_parameter("camera_info_file").value
        self.camera = camera_from_file(camera_file) if camera_file else None
        self.sim_params = AsyncParameterClient(self, self.get_parameter("sim_node").value)
        from ..sim.render import Renderer

        # the context is made (and warmed) at the camera's size when the calibration file gives it
        self.renderer = Renderer(self.get_parameter("model_path").value or None, camera=self.camera)
        # and the optimizer's library is imported now, not when the dive-start fit begins (cma: 1.3-1.8 s)
        warm_up(self.get_parameter("optimizer").value)
        self._lock = threading.Lock()
        self._stopping = threading.Event()   # set by destroy_node: the fit thread ends without touching the node
        self.selector = None
        self.fit_thread = None
        self.result = None
        self.finished = Future()   # result: True when done, False when failed (for exit_when_done)
        # streams: 0 image (primary), 1 camera_info (any age: often latched or slow), 2 pose (max_dt); with
        # camera_info_file: 0 image, 1 pose
        self._pose_stream = 2 if self.camera is None else 1
        self._last_info = None       # (stamp, message) of the newest camera_info
        self.sync = self._new_sync()
        # Sensor-data QoS (best effort: matches any camera driver), but a deeper queue than its 5: frame
        # selection renders in the callback, and the first frames of a dive should not be dropped. A
        # replayed bag is played reliably and read reliably: under load best effort lost frames, and the
        # fit then took other frames than `uw-sil fit` takes from the same bag.
        reliability = (ReliabilityPolicy.RELIABLE if self.get_parameter("reliable_input").value
                       else qos_profile_sensor_data.reliability)
        sensor = QoSProfile(depth=30, reliability=reliability, durability=qos_profile_sensor_data.durability)
        # Poses (reliable) queue as deep as the images: the first frame's render (a new OpenGL context at the
        # camera's size) took up to 1.2 s under load, and with a queue of 10 the 11th pose arriving meanwhile
        # pushed out pose #1, so image #1 found no partner and was dropped.
        poses = QoSProfile(depth=sensor.depth, reliability=ReliabilityPolicy.RELIABLE)
        topic, msg_type = TRANSPORTS[self.get_parameter("image_transport").value]
        self.subs = [self.create_subscription(msg_type, topic, lambda m: self._add(0, m), sensor)]
        if self.camera is None:
            self.subs.append(self.create_subscription(CameraInfo, "camera/camera_info", lambda m: self._add(1, m),
                                                      sensor))
        self.subs.append(self.create_subscription(PoseStamped, "panel/pose",
                                                  lambda m: self._add(self._pose_stream, m), poses))
        self.create_service(Trigger, "~/start", self._on_start)
        self._last_progress = None
        self._collect_start = None   # monotonic time the current collection started
        self._last_input = None      # monotonic time of the last input message of the current collection
        self._idle_from = None       # monotonic time the last input callback ended (what idle_timeout counts from)
        self.create_timer(2.0, self._log_progress)
        self.create_timer(0.5, self._check_idle)
        if self.get_parameter("auto_start").value:
            started, reason = self._start()
            if not started:
                raise ValueError(f"backward_fit: {reason}")
        else:
            self._status("idle: call ~/start to fit")

    def _new_sync(self) -> StampSynchronizer:
        """The pairing of a new collection: it pairs the messages that arrive from now on (a bag replayed again
        starts over at its first stamp, which the previous collection's pairing took for stale), and the newest
        camera_info (a camera that sends it once, or slowly)."""
        max_dt = self.get_parameter("max_dt").value
        if self.camera is not None:
            return StampSynchronizer(2, max_dt=[max_dt])
        sync = StampSynchronizer(3, max_dt=[None, max_dt])
        if self._last_info is not None:
            sync.add(1, *self._last_info)
        return sync

    def _on_set_parameters(self, params) -> SetParametersResult:
        for p in params:
            reason = _check(p.name, p.value)
            if reason:
                return SetParametersResult(successful=False, reason=reason)
        for p in params:
            if p.name == "optimizer":
                warm_up(p.value)
        return SetParametersResult(successful=True)

    def _log(self):
        """The node's logger; once the context is shut down (Ctrl-C), a child logger that does not try rosout
        (the node's own printed "Failed to publish log message to rosout" after each line)."""
        if self.context.ok():
            return self.get_logger()
        import rclpy.logging

        return rclpy.logging.get_logger(f"{self.get_name()}.stop")

    def _status(self, text: str):
        self._log().info(text)
        if self.context.ok():   # the fit thread may report after Ctrl-C
            self.pub_status.publish(String(data=text))

    def _finish(self, ok: bool, text: str):
        self._status(text)
        if not self.finished.done():
            self.finished.set_result(ok)

    def _start(self) -> tuple:
        """Start a new collection; (True, what it does) or (False, why not)."""
        stopped = ""
        with self._lock:
            running = self.fit_thread is not None and self.fit_thread.is_alive()
            if running and not self._diagnosing:
                return False, "a fit is running"
            if running and not self._run_cancel.is_set():
                # a diagnosis: stop it (at its next optimizer iteration; nothing written or sent); its thread
                # says when it has stopped (status "stopped: ...")
                self._stop_asked = time.monotonic()
                self._run_cancel.set()
                stopped = "stopping the running diagnosis (nothing will be written or sent); "
            g = lambda n: self.get_parameter(n).value  # noqa: E731
            try:
                if g("diagnose"):
                    selector = SpreadCollector(k=g("diagnose_frames"), max_scan=max(g("max_scan"),
                                                                                    g("diagnose_frames")))
                else:
                    selector = FrameSelector(self.renderer, k=g("frames"), min_coverage=g("min_coverage"),
                                             max_scan=g("max_scan"), stride=g("stride"))
            except ValueError as e:   # the parameters are checked when set: this is a safety net
                return False, str(e)
            self.selector = selector
            self.sync = self._new_sync()
            self._collect_start, self._last_input, self._idle_from = time.monotonic(), None, None
        if isinstance(selector, SpreadCollector):
            text = (f"{stopped}collecting frames for the diagnosis ({selector.k} of them, spread over those "
                    f"received until the input pauses or {selector.max_scan} came)")
        else:
            text = f"{stopped}collecting {selector.k} frames with the panel in view"
        self._status(text)
        return True, f"{stopped}collecting frames"

    def _log_progress(self):
        sel, st = self.selector, self.sync.stats
        if sel is None or sel.done:
            return
        text = f"collecting: {self._taken(sel)}; {self._inputs()}, {st.dropped} images without partner"
        if text != self._last_progress:
            self._last_progress = text
            self.get_logger().info(text)

    def _inputs(self) -> str:
        st = self.sync.stats
        info = f"{st.received[1]} camera_info, " if self.camera is None else ""
        return (f"received {st.received[0]} images, {info}{st.received[self._pose_stream]} poses; "
                f"{st.matched} matched")

    @staticmethod
    def _taken(sel) -> str:
        if isinstance(sel, SpreadCollector):
            return f"{sel.scanned} frames kept (of at most {sel.max_scan}) for the diagnosis of {sel.k}"
        return f"{len(sel.frames)}/{sel.k} frames taken of {sel.scanned} looked at"

    @property
    def _diagnosing(self) -> bool:
        return getattr(self.fit_thread, "name", "") == "diagnosis"

    def _check_idle(self):
        """The input has stopped (end of a bag) before ``frames`` were taken, or never started."""
        sel = self.selector
        if sel is None or sel.done:
            return
        now = time.monotonic()
        if self._last_input is None:
            wait = self.get_parameter("first_frame_timeout").value
            if wait > 0 and now - self._collect_start >= wait:
                self.selector = None
                topics = ", ".join(s.topic_name for s in self.subs)
                self._finish(False, f"failed: no frames arrived: no message on {topics} in {wait:g} s")
            return
        wait = self.get_parameter("idle_timeout").value
        if wait > 0 and now - max(self._last_input, self._idle_from or 0.0) >= wait:
            what = (f"diagnosing: {self._taken(sel)}" if isinstance(sel, SpreadCollector)
                    else f"fitting the {len(sel.frames)} of {sel.k} frames taken so far")
            self.get_logger().warning(f"no input for {wait:g} s: {what} ({self._inputs()})")
            self._fit_selection(sel)

    def _on_start(self, _req, resp):
        resp.success, resp.message = self._start()
        return resp

    def _add(self, stream: int, msg):
        if self.selector is not None:
            self._last_input = time.monotonic()
        stamp = _stamp_ns(msg.header)
        if stream == 1 and self.camera is None:
            self._last_info = (stamp, msg)
        for match in self.sync.add(stream, stamp, msg):
            self._offer(match)
        # idle time counts from the end of the callback: while a frame renders (the first one took over 3 s
        # under load) the input waits in the queues, and the idle timer, served before them, would take the
        # node's own stall for the end of the bag
        if self.selector is not None:
            self._idle_from = time.monotonic()

    def _offer(self, match):
        sel = self.selector
        if sel is None or sel.done:
            return
        img, pose = match.items[0], match.items[self._pose_stream]
        p, q = pose.pose.position, pose.pose.orientation
        try:
            camera = self.camera if self.camera is not None else CameraModel.from_camera_info(match.items[1])
            rgb = compressed_to_rgb(img) if isinstance(img, CompressedImage) else image_to_rgb(img)
            if self.camera is not None and rgb.shape[:2] != camera.shape:
                raise ValueError(f"image is {rgb.shape[1]}x{rgb.shape[0]} but camera_info_file is for "
                                 f"{camera.width}x{camera.height}")
            if isinstance(sel, SpreadCollector):
                rgb = np.array(rgb)     # kept until the selection: not a view of the message's buffer
            sample = Sample(stamp_ns=match.stamp_ns, image=rgb, camera=camera,
                            pose=pose_to_matrix([p.x, p.y, p.z], [q.x, q.y, q.z, q.w]), frame_id=img.header.frame_id)
            sel.offer(sample)
        except ValueError as e:
            self.get_logger().error(f"frame skipped: {e}", throttle_duration_sec=5.0)
            return
        if sel.done:
            self._fit_selection(sel)

    def _fit_selection(self, sel):
        self.selector = None
        if sel.scanned == 0:
            self._finish(False, f"failed: no frames arrived: {self._inputs()} (images are paired with a "
                                "camera_info and a pose by stamp)")
            if isinstance(sel, SpreadCollector):
                self._publish_failure(f"no frames arrived: {self._inputs()}")
            return
        if isinstance(sel, SpreadCollector):
            self._start_diagnosis(sel)
            return
        try:
            selection = sel.result()
        except ValueError as e:
            self._finish(False, f"failed: {e} ({self._inputs()})")
            return
        # The options of this fit: parameters set while it runs apply to the next one.
        options = {n: self.get_parameter(n).value for n in ("optimizer", "color_model", "channels", "fog_mode",
                                                            "seed", "max_iter", "output_yaml", "sim_node")}
        self.fit_thread = threading.Thread(target=self._fit, args=(selection, options), daemon=True)
        self.fit_thread.start()

    def _fit(self, selection, options: dict):
        """The fit thread: never dies with a traceback (a shutdown under it ends it quietly)."""
        try:
            self._fit_and_apply(selection, options)
        except Exception as e:
            if not self.context.ok():   # Ctrl-C: the node's handles went away under the fit; nothing to report
                return
            try:
                self._finish(False, f"failed: {type(e).__name__}: {e}")
            except Exception:           # the node itself is gone
                pass

    def _fit_and_apply(self, selection, options: dict):
        g = options.__getitem__
        frames = ", ".join(f"#{f.index} ({f.range_median:.2f} m, {100 * f.coverage:.0f}% panel)"
                           for f in selection.frames)
        self._status(f"fitting {len(selection.frames)} frames with {g('optimizer')}: {frames} ...")
        for index, reason in selection.skipped:
            self.get_logger().info(f"frame #{index} skipped: {reason}")

        def on_iteration(it, _x, best):
            if self._stopping.is_set() or not self.context.ok():
                return True  # shutting down: stop the optimizer
            self.pub_theta.publish(Float64(data=float(best)))

        try:
            optim = {"max_iter": g("max_iter")} if g("max_iter") > 0 else {}
            fit = fit_frames(selection.frames, method=g("optimizer"), color_model=g("color_model"),
                             channels=g("channels"), fog=g("fog_mode"), seed=g("seed"), callback=on_iteration,
                             skipped=selection.skipped, **optim)
            if self._stopping.is_set() or not self.context.ok():
                return  # interrupted: the partial result is not written anywhere
            self.result = fit
            if g("output_yaml"):
                write_params_yaml(g("output_yaml"), fit.params, fog=g("fog_mode"), noise_sigma=fit.noise_level)
        except Exception as e:  # report, never die silently in a thread
            self._finish(False, f"failed: {type(e).__name__}: {e}")
            return
        summary = f"theta {fit.theta_start:.4f} -> {fit.theta_best:.4f} in {fit.wall_time_s:.1f} s"
        values = [Parameter(n, value=float(v)) for n, v in fit.params.as_dict().items()]
        values.append(Parameter("fog_mode", value=g("fog_mode")))
        values.append(Parameter("noise_sigma", value=fit.noise_level))
        self._send_parameters(values, summary, g("sim_node"))

    def _send_parameters(self, values: list, summary: str, sim: str, on_done=None, what: str = "parameters"):
        """Set ``values`` on ``sim`` in one atomic batch; the status says done or why not."""
        self.get_logger().info(f"{summary}: setting the {what} of {sim}")
        deadline = time.monotonic() + 10.0
        while not self.sim_params.services_are_ready():
            if self._stopping.is_set() or not self.context.ok():
                return
            if time.monotonic() > deadline:
                self._finish(False, f"failed: {summary}, but the parameter services of {sim} are not available")
                return
            self._stopping.wait(0.1)

        def on_response(f):
            try:
                res = f.result().result
            except Exception as e:  # the service call itself failed
                self._finish(False, f"failed: {summary}, but setting the parameters of {sim} failed: {e}")
                return
            if res.successful:
                if on_done is not None:
                    on_done()
                self._finish(True, f"done: {summary}; {sim} re-parameterized"
                                   + (f" with the {what}" if what != "parameters" else ""))
            else:
                self._finish(False, f"failed: {summary}, but {sim} rejected the parameters: {res.reason}")

        # asked again when the answer is lost (setting the same values twice is harmless)
        self._set_request = AskedUntilAnswered(
            self, lambda: self.sim_params.set_parameters_atomically(values), on_response,
            f"setting the {what} of {sim}",
            on_give_up=lambda text: self._finish(False, f"failed: {summary}, but {text}"))

    # ------------------------------------------------------------------ the diagnosis

    def _start_diagnosis(self, collector):
        """Render the frames spread over those collected (here: the renderer belongs to this thread), then
        diagnose them in the worker thread."""
        t_collected = time.monotonic()
        try:
            # the model too: a pose correction of the diagnosis renders the frames' scene again
            frames = collector.frames(model=self.get_parameter("model_path").value or None, renderer=self.renderer)
        except ValueError as e:
            self._publish_failure(str(e))
            self._finish(False, f"failed: {e} ({self._inputs()})")
            return
        g = lambda n: self.get_parameter(n).value  # noqa: E731
        options = {n: g(n) for n in ("fog_mode", "seed", "max_iter", "output_yaml", "output_json", "sim_node",
                                     "diagnose_max_effects", "diagnose_effects")}
        options["t_collected"], options["t_last_input"] = t_collected, self._last_input or t_collected
        options["k"] = collector.k        # the frames beyond it are the report frames
        self._run_cancel = cancel = threading.Event()
        self._stop_asked, self._stop_said = None, False     # (a stop asked of the previous diagnosis is not this one's)
        self.fit_thread = threading.Thread(target=self._diagnose, args=(frames, options, cancel), daemon=True,
                                           name="diagnosis")
        self.fit_thread.start()

    def _diagnose(self, frames, options: dict, cancel):
        """The diagnosis thread: never dies with a traceback (a shutdown under it ends it quietly)."""
        try:
            self._diagnose_and_apply(frames, options, cancel)
        except _Cancelled:
            self._report_stopped(options)
        except Exception as e:
            if not self.context.ok() or self._stopping.is_set():
                return
            try:
                self._publish_failure(f"{type(e).__name__}: {e}")
                self._finish(False, f"failed: diagnosis: {type(e).__name__}: {e}")
            except Exception:           # the node itself is gone
                pass

    def _diagnose_and_apply(self, frames, options: dict, cancel):
        g = options.__getitem__
        listed = ", ".join(f"#{f.index} ({f.range_median:.2f} m)" for f in frames)
        n_report = report_count(len(frames), g("k"))
        self._status(f"diagnosing {len(frames) - n_report} frames"
                     + (f" and setting {n_report} report frame(s) aside" if n_report else "") + f": {listed}")

        def interrupt(*_):
            if cancel.is_set() or self._stopping.is_set() or not self.context.ok():
                raise _Cancelled

        def progress(msg: str):
            interrupt()
            self._status(f"diagnosing: {msg}")

        effects = [e.strip() for e in g("diagnose_effects").split(",") if e.strip()] or None
        budget = {"max_iter": g("max_iter")} if g("max_iter") > 0 else {}
        try:
            diag = diagnose_frames(frames, fog=g("fog_mode"), seed=g("seed"), max_effects=g("diagnose_max_effects"),
                                   report_frames=n_report,
                                   progress=progress, interrupt=interrupt, effects_allowed=effects,
                                   source=f"live: {self.subs[0].topic_name}", **budget)
        except ValueError as e:     # DiagnosisError among them: the frames cannot be diagnosed
            self._publish_failure(str(e))
            self._finish(False, f"failed: diagnosis: {e}")
            return
        interrupt()                 # stopped after the last iteration: still nothing written
        doc = diag.to_json()
        effects_found = ", ".join(diag.final.get("effects", [])) or "none"
        summary = (f"diagnosis: {effects_found}; held-out θ {diag.base['theta_heldout']:.4f} -> "
                   f"{diag.final['theta_heldout']:.4f} in {diag.timing['total_s']:.0f} s")
        for line in diag.summary_lines():
            self.get_logger().info(line)
        if g("output_json"):
            write_json_atomic(g("output_json"), doc)
        if g("output_yaml"):
            write_diagnosis_yaml(g("output_yaml"), diag, fog=g("fog_mode"),
                                 comment=f"uw_sil backward_fit diagnosis: effects {effects_found}; held-out theta "
                                         f"{diag.base['theta_heldout']:.4f} -> {diag.final['theta_heldout']:.4f}")
        self.result = diag
        self.pub_diagnosis.publish(String(data=json.dumps(doc, indent=2)))
        self._publish_statuses(diagnostic_statuses(doc, self.get_name()))
        params = extended_parameters(diag, fog=g("fog_mode"))
        if "effects" not in params and self._sent_effects:
            params["effects"] = ""  # a previous diagnosis' effects are no longer rendered
        values = [Parameter(n, value=v) for n, v in params.items()]
        sent = "effects" in params

        def done():
            self._sent_effects = self._sent_effects or sent
            after = time.monotonic()
            self.get_logger().info(f"extended model in {g('sim_node')} {after - g('t_last_input'):.1f} s after the "
                                   f"last input message, {after - g('t_collected'):.1f} s after the collection ended")
        self._send_parameters(values, summary, g("sim_node"), on_done=done, what="extended model")

    def _report_stopped(self, options: dict):
        """The diagnosis thread ended on a stop request (~/start, Ctrl-C): say so, on ~/status while the node runs."""
        shutdown = self._stopping.is_set() or not self.context.ok()
        if shutdown:    # Ctrl-C shuts the context down first: this thread may see it before destroy_node runs
            self._say_stopping()
        asked = self._stop_asked
        after = f"{time.monotonic() - asked:.1f} s after it was asked, " if asked is not None else ""
        ran = time.monotonic() - options["t_collected"]
        if shutdown:
            text = f"stopped: the diagnosis, by the node's shutdown, {after}after {ran:.0f} s; nothing written or sent"
        else:
            text = (f"stopped: the diagnosis, by ~/start, {after}after {ran:.0f} s; nothing written or sent; "
                    "collecting frames for the new one")
        try:
            self._status(text)
        except Exception:   # the node's handles are gone (the shutdown went on without this thread)
            pass

    def _say_stopping(self):
        """Log, once per diagnosis, that the shutdown stops it: from destroy_node, or from the diagnosis thread
        when it saw the shut-down context first (Ctrl-C), whichever comes first."""
        with self._lock:
            if self._stop_said:
                return
            self._stop_said = True
            if self._stop_asked is None:
                self._stop_asked = time.monotonic()
        self._log().info("stopping the running diagnosis: nothing will be written or sent")

    def _publish_statuses(self, statuses: list):
        levels = {"OK": DiagnosticStatus.OK, "WARN": DiagnosticStatus.WARN, "ERROR": DiagnosticStatus.ERROR}
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [DiagnosticStatus(level=levels[st["level"]], name=st["name"], message=st["message"],
                                       hardware_id=st["hardware_id"],
                                       values=[KeyValue(key=k, value=v) for k, v in st["values"].items()])
                      for st in statuses]
        if self.context.ok():
            self.pub_diagnostics.publish(msg)

    def _publish_failure(self, reason: str):
        self._publish_statuses(failure_statuses(reason, self.get_name()))

    def destroy_node(self):
        # The fit thread first: it uses the node's publishers and parameter client (stopping it ends the
        # optimizer at its next iteration; a fit interrupted so is not written anywhere).
        stopping, thread = getattr(self, "_stopping", None), getattr(self, "fit_thread", None)
        alive = thread is not None and thread.is_alive() and thread is not threading.current_thread()
        if alive and self._diagnosing and not self._run_cancel.is_set():
            self._say_stopping()
        if stopping is not None:
            stopping.set()
        if alive:
            thread.join(timeout=STOP_WAIT)
            if thread.is_alive():
                self._log().warning(f"the {'diagnosis' if self._diagnosing else 'fit'} did not stop within "
                                       f"{STOP_WAIT:g} s (it is in a step that cannot be interrupted): it ends with the "
                                       "process, nothing written or sent")
        # Also for a node whose constructor was interrupted (Ctrl-C while the renderer starts): rclpy
        # destroys the nodes of a context at shutdown, built or not.
        if getattr(self, "renderer", None) is not None:
            self.renderer.close()
        super().destroy_node()


def _spin(node) -> int:
    # Single-threaded on purpose: the OpenGL context of the renderer belongs to this thread.
    # The fit itself runs in a worker thread and needs no rendering.
    with executor_for(node) as executor:
        if node.get_parameter("exit_when_done").value:
            executor.spin_until_future_complete(node.finished)
            return 0 if not node.finished.done() or node.finished.result() else 1
        executor.spin()
    return 0


def main(args=None):
    return run_node(BackwardFitNode, _spin, args=args, name="backward_fit", user_errors=(ValueError,),
                    doc=__doc__)


if __name__ == "__main__":
    sys.exit(main())
