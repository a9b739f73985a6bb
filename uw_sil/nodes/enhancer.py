"""``enhancer`` node: dehazes the real camera frames with the simulated geometry rendered for the same
instant (SIL, the paper's forward half: the fitted underwater model inverted on the sim's object pixels),
or with the image-only baselines DCP / UDCP (:mod:`uw_sil.enhance.sil`).

Subscribes (sensor-data QoS; reliably with ``reliable_input``)
    ``camera/image_raw`` (rgb8, bgr8, rgba8, bgra8; grey images are refused), or with ``image_transport:=
    compressed`` ``camera/image_raw/compressed`` (sensor_msgs/CompressedImage, JPEG/PNG, image_transport's
    naming), ``sim/depth`` (32FC1),
    ``sim/mask`` (mono8 labels, 0 water), ``sim/camera_info`` (the intrinsics of the depth), paired by
    stamp with :class:`uw_sil.bags.stamps.StampSynchronizer` (tolerance ``max_dt``: an image is paired with
    the sim frame nearest in stamp, its own when sim_camera rendered its pose; when sim_camera skipped that
    pose (it renders the newest) a neighbour within ``max_dt`` is used; ``max_dt:=0.0`` demands the own).
    ``/parameter_events``: the model parameters of ``sim_node`` (``a_r a_g a_b b_r b_g b_b rho_f fog_mode``
    ``effects`` and the ``<effect>.<param>`` of the effects it lists), read from it at start and followed
    afterwards, so a backward fit (or diagnosis) that re-parameterizes ``sim_camera`` re-parameterizes the
    enhancer too. ``camera/image_raw`` is subscribed
    only once the model is known and ``sim_node`` listens on ``sim_pose_topic`` (a replayed bag waiting for
    this subscription then loses no frame to start-up).
Publishes
    ``camera/image_enhanced`` (rgb8, the real frame's header: stamp and frame), ``camera/image_enhanced/
    camera_info`` (the depth's intrinsics, the frame's header); ``~/status`` (std_msgs/String, JSON, transient
    local, every second): frames received / paired / enhanced, drops by cause, enhancer latency p50/p95 (from
    the later of the paired inputs' arrival to publication) over the last 300 frames, restored fraction,
    background source, the model in use.
Queueing
    Paired frames wait in a queue of ``queue_size``; when the enhancer cannot keep up the oldest is dropped
    and counted (``dropped_queue``). Unpaired images (no sim frame within ``max_dt``) are dropped and
    counted (``dropped_unpaired``); if images keep arriving and never pair, the offsets to the nearest sim
    stamps are logged once. Bad input (depth with NaN, 0 or -inf, object pixels without depth, sizes that
    differ, grey images, bad encodings) is logged, dropped, counted (``dropped_bad``); the node keeps running.
Parameters
    ``method`` (sil|dcp|udcp, live), ``t0`` (gain cap 1/t0, live), ``b_from_frame`` (live: re-estimate the
    background on each frame from its water), ``max_gain`` (lamp-effect gain cap, live); read-only:
    ``sim_node`` (sim_camera), ``sim_pose_topic`` (panel/pose), ``max_dt`` (0.05 s), ``queue_size`` (2),
    ``pair_queue_size`` (30 images waiting for their sim frame), ``erode_px`` (8), ``idle_timeout`` (0 = run
    until stopped; > 0: exit once no input message (camera image or sim frame: with poses from ``panel_pose`` the
    sim frames come later than the images) has come for that many seconds and the queue is empty: the end of a
    replayed bag), ``image_transport`` (raw | compressed), ``reliable_input`` (false: the inputs with
    sensor-data QoS; true, as in a replayed bag: reliably, so that no frame is lost).
"""
from __future__ import annotations

import collections
import contextlib
import json
import sys
import threading
import time

import numpy as np
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterEvent, ParameterType,
                                SetParametersResult)
from rclpy.node import Node
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import (DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_parameter_events,
                       qos_profile_sensor_data)
from rclpy.task import Future
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import String

from ..bags.imgmsg import compressed_to_rgb, image_to_depth, image_to_mono, image_to_rgb, rgb_to_image_fields
from ..bags.stamps import StampSynchronizer
from ..enhance.sil import METHODS, Enhancer, model_from_parameters
from ..sim.camera import CameraModel
from ..sim.params import RGB_NAMES
from . import AskedUntilAnswered, executor_for, run_node

MODEL_NAMES = tuple(RGB_NAMES) + ("fog_mode",)
#: ``image_transport`` values: the camera topic and message type of each (image_transport's naming).
TRANSPORTS = {"raw": ("camera/image_raw", Image), "compressed": ("camera/image_raw/compressed", CompressedImage)}
#: Images in a row without a sim partner after which the stamp offsets are logged (once per such run).
UNPAIRED_WARN = 10
LATENCY_WINDOW = 300


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _value(p):
    """Python value of an rcl_interfaces/ParameterValue (None when unset or of another type)."""
    t = p.type
    if t == ParameterType.PARAMETER_DOUBLE:
        return p.double_value
    if t == ParameterType.PARAMETER_INTEGER:
        return float(p.integer_value)
    if t == ParameterType.PARAMETER_STRING:
        return p.string_value
    if t == ParameterType.PARAMETER_BOOL:
        return p.bool_value
    return None


def _effect_keys(effects) -> list:
    """``<effect>.<param>`` of every effect an ``effects`` parameter value lists (``NAME[=preset],...``)."""
    from ..sim.effects import get_effect, parse_effects

    if not isinstance(effects, str) or not effects.strip():
        return []
    return [f"{n}.{p}" for n in parse_effects(effects) for p in get_effect(n).param_names]


def _active(values: dict) -> dict:
    """The model parameters of ``values`` without the effects sim_node declares but does not render: with an
    ``effects`` list (sim_camera's ``extensible_effects`` declares inactive ones), only the listed effects."""
    if "effects" not in values:
        return values
    keep = set(_effect_keys(values["effects"]))
    return {k: v for k, v in values.items() if "." not in k or k in keep}


class BadInput(ValueError):
    """A frame that cannot be enhanced; ``reason`` is its short category for the counters."""

    def __init__(self, reason: str, text: str):
        super().__init__(text)
        self.reason = reason


class EnhancerNode(Node):
    def __init__(self, **kwargs):
        super().__init__("enhancer", **kwargs)
        d = ParameterDescriptor
        ro = dict(read_only=True)
        self.declare_parameter("method", "sil", d(description=f"enhancement: {' | '.join(METHODS)}"))
        self.declare_parameter("t0", 0.1, d(description="lowest transmission divided by: the gain 1/T is capped at "
                                                        "1/t0 (far pixels: partial restoration, noise x 1/t0)",
                                            floating_point_range=[FloatingPointRange(from_value=0.01, to_value=1.0)]))
        self.declare_parameter("max_gain", 8.0, d(description="cap of the lamp-illumination gain (effects)",
                                                  floating_point_range=[FloatingPointRange(from_value=1.0,
                                                                                           to_value=100.0)]))
        self.declare_parameter("b_from_frame", False, d(description="re-estimate the background b on every frame "
                                                                    "from its water pixels (eroded sim mask)"))
        self.declare_parameter("sim_node", "sim_camera", d(description="node whose model parameters are followed",
                                                           **ro))
        self.declare_parameter("sim_pose_topic", "panel/pose", d(description="input of sim_node; camera/image_raw "
                                                                             "is subscribed once sim_node listens on it",
                                                                 **ro))
        self.declare_parameter("max_dt", 0.05, d(description="largest |stamp(sim) - stamp(image)| paired [s]",
                                                 floating_point_range=[FloatingPointRange(from_value=0.0,
                                                                                          to_value=10.0)], **ro))
        self.declare_parameter("queue_size", 2, d(description="paired frames waiting; beyond it the oldest is "
                                                              "dropped and counted",
                                                  integer_range=[IntegerRange(from_value=1, to_value=100)], **ro))
        self.declare_parameter("pair_queue_size", 30, d(description="images waiting for their sim frame; beyond "
                                                                   "it the oldest is decided (and dropped if unpaired)",
                                                       integer_range=[IntegerRange(from_value=1, to_value=1000)],
                                                       **ro))
        self.declare_parameter("erode_px", 8, d(description="erosion of the sim water mask for b_from_frame [px]",
                                                integer_range=[IntegerRange(from_value=0, to_value=100)], **ro))
        self.declare_parameter("idle_timeout", 0.0, d(description="> 0: exit after this many seconds without an "
                                                                  "input message, camera image or sim frame (end of "
                                                                  "a replayed bag)", **ro))
        self.declare_parameter("reliable_input", False, d(
            description="subscribe to the camera and sim/* reliably (a replayed bag: nothing lost) instead of with "
                        "sensor-data QoS", **ro))
        self.declare_parameter("image_transport", "raw", d(
            description="camera input: raw (sensor_msgs/Image on camera/image_raw) or compressed (sensor_msgs/"
                        "CompressedImage, JPEG/PNG, on camera/image_raw/compressed)",
            additional_constraints="one of " + ", ".join(TRANSPORTS), **ro))
        g = lambda n: self.get_parameter(n).value  # noqa: E731
        self.method = g("method")
        if g("image_transport") not in TRANSPORTS:
            raise ValueError(f"parameter image_transport must be one of {', '.join(TRANSPORTS)}, "
                             f"got {g('image_transport')!r}")
        if self.method not in METHODS:
            raise ValueError(f"parameter method must be one of {METHODS}, got {self.method!r}")
        self.enhancer = Enhancer(t0=g("t0"), max_gain=g("max_gain"), b_from_frame=g("b_from_frame"),
                                 erode_px=g("erode_px"))
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._lock = threading.Lock()               # the model and the live options vs the worker
        self._queue = collections.deque()
        self._cv = threading.Condition()
        self._busy = False
        self._stop = False
        self._pub_lock = threading.Lock()           # the worker's publishing vs destroy_node
        self.counts = collections.Counter()
        self.bad = collections.Counter()
        self.latency = collections.deque(maxlen=LATENCY_WINDOW)
        self.last = {}
        self.finished = Future()
        self._last_image = None
        self._last_input = None     # any input message: the sim frames of poses still coming (panel_pose) count
        self._never_paired_warned = False
        self._unpaired_run = 0
        self._dropped_seen = 0
        self._recent = {"image": collections.deque(maxlen=20), "depth": collections.deque(maxlen=20)}

        # model parameters of the sim node: read once, then followed through its parameter events
        sim = g("sim_node")
        self._sim_fqn = sim if sim.startswith("/") else (self.get_namespace().rstrip("/") + "/" + sim)
        self._sim_values = {}
        self._from_events = set()
        self.model = None
        self._param_client = AsyncParameterClient(self, sim)
        self._param_request = None
        self.create_subscription(ParameterEvent, "/parameter_events", self._on_parameter_event,
                                 qos_profile_parameter_events)

        self.sync = StampSynchronizer(4, max_dt=[g("max_dt")] * 3, queue_size=g("pair_queue_size"),
                                      buffer_size=g("pair_queue_size") + 10)
        out_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.pub_image = self.create_publisher(Image, "camera/image_enhanced", out_qos)
        self.pub_info = self.create_publisher(CameraInfo, "camera/image_enhanced/camera_info", out_qos)
        self.pub_status = self.create_publisher(String, "~/status",
                                                QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        reliability = (ReliabilityPolicy.RELIABLE if g("reliable_input")
                       else qos_profile_sensor_data.reliability)
        sensor = QoSProfile(depth=10, reliability=reliability, durability=qos_profile_sensor_data.durability)
        self._sensor = sensor
        self.create_subscription(Image, "sim/depth", lambda m: self._add(1, m), sensor)
        self.create_subscription(Image, "sim/mask", lambda m: self._add(2, m), sensor)
        self.create_subscription(CameraInfo, "sim/camera_info", lambda m: self._add(3, m), sensor)
        self._image_sub = None
        self._ready_timer = self.create_timer(0.2, self._get_ready)
        self.create_timer(1.0, self._publish_status)
        if g("idle_timeout") > 0:
            self.create_timer(0.25, self._check_idle)
        self._worker = threading.Thread(target=self._work, name="enhancer-worker", daemon=True)
        self._worker.start()
        self.get_logger().info(f"method {self.method}; waiting for the model parameters of {self._sim_fqn}")

    # ------------------------------------------------------------------ parameters

    def _on_set_parameters(self, params) -> SetParametersResult:
        changes = {p.name: p.value for p in params}
        if "method" in changes and changes["method"] not in METHODS:
            return SetParametersResult(successful=False,
                                       reason=f"method must be one of {METHODS}, got {changes['method']!r}")
        if "t0" in changes and not 0 < float(changes["t0"]) <= 1:
            return SetParametersResult(successful=False, reason=f"t0 must lie in (0, 1], got {changes['t0']}")
        if "max_gain" in changes and not float(changes["max_gain"]) >= 1:
            return SetParametersResult(successful=False, reason=f"max_gain must be >= 1, got {changes['max_gain']}")
        with self._lock:
            if "method" in changes:
                self.method = changes["method"]
            if "t0" in changes:
                self.enhancer.t0 = float(changes["t0"])
            if "max_gain" in changes:
                self.enhancer.max_gain = float(changes["max_gain"])
            if "b_from_frame" in changes:
                self.enhancer.b_from_frame = bool(changes["b_from_frame"])
        return SetParametersResult(successful=True)

    def _apply_sim_values(self, values: dict, source: str):
        merged = dict(self._sim_values)
        merged.update(values)
        try:
            model = model_from_parameters(_active(merged))
        except (ValueError, TypeError) as e:
            self.get_logger().error(f"ignoring the model parameters of {self._sim_fqn} ({source}): {e}")
            return
        with self._lock:
            self.enhancer.set_model(model)
            self.model = model
        self._sim_values = merged
        self.get_logger().info(f"model from {self._sim_fqn} ({source}): {model}")

    def _on_parameter_event(self, msg: ParameterEvent):
        if msg.node != self._sim_fqn:
            return
        values = {}
        for p in list(msg.new_parameters) + list(msg.changed_parameters):
            if p.name in MODEL_NAMES or p.name == "effects" or "." in p.name:
                v = _value(p.value)
                if v is not None:
                    values[p.name] = v
        if values:
            self._from_events.update(values)
            if self.model is not None or all(n in {**self._sim_values, **values} for n in RGB_NAMES):
                self._apply_sim_values(values, "parameter event")
            else:
                self._sim_values.update(values)

    def _get_ready(self):
        """Fetch the sim node's model once; subscribe to the camera once the sim node listens for poses."""
        if self.model is None:
            if self._param_request is None and self._param_client.services_are_ready():
                self._ask_sim(MODEL_NAMES, self._on_parameters)
            return
        if self._image_sub is not None:
            return
        topic = self.resolve_topic_name(self.get_parameter("sim_pose_topic").value)
        sim_name = self._sim_fqn.rsplit("/", 1)[-1]
        if not any(i.node_name == sim_name for i in self.get_subscriptions_info_by_topic(topic)):
            return
        topic, msg_type = TRANSPORTS[self.get_parameter("image_transport").value]
        self._image_sub = self.create_subscription(msg_type, topic, lambda m: self._add(0, m), self._sensor)
        self._ready_timer.cancel()
        self.get_logger().info(f"ready: enhancing {self._image_sub.topic_name} with {self.method}")

    def _ask_sim(self, names, then):
        """Read ``names`` of the sim node, asked again when its answer is lost; all over again from the model
        parameters when none comes at all."""
        def give_up(text):
            self.get_logger().error(f"{text}; starting over")
            self._param_request = None

        self._param_request = AskedUntilAnswered(self, lambda: self._param_client.get_parameters(list(names)), then,
                                                 f"reading the parameters of {self._sim_fqn}", on_give_up=give_up)

    def _on_parameters(self, fut, names=MODEL_NAMES, got_before=None):
        try:
            values = fut.result().values
        except Exception as e:  # the service call failed: ask again
            self.get_logger().warning(f"reading the parameters of {self._sim_fqn} failed: {e}; retrying")
            self._param_request = None
            return
        got = dict(got_before or {})
        got.update({n: _value(v) for n, v in zip(names, values)})
        got = {n: v for n, v in got.items() if v is not None and n not in self._from_events}
        if not all(n in {**self._sim_values, **got} for n in RGB_NAMES):
            self.get_logger().error(f"{self._sim_fqn} has no model parameters {list(RGB_NAMES)}; retrying",
                                    throttle_duration_sec=10.0)
            self._param_request = None
            return
        # Then the effects sim_node renders: its ``effects`` list (asked alone: a request naming a parameter the
        # node does not declare is answered with no values at all), then their parameters.
        if got_before is None:
            self._ask_sim(("effects",), lambda f: self._on_parameters(f, ("effects",), got))
            return
        if names == ("effects",):
            keys = _effect_keys(got.get("effects", self._sim_values.get("effects", "")))
            if keys:
                self._ask_sim(keys, lambda f: self._on_parameters(f, tuple(keys), got))
                return
        self._apply_sim_values(got, "parameter services")

    # ------------------------------------------------------------------ input

    def _add(self, stream: int, msg):
        now = time.monotonic()
        stamp = _stamp_ns(msg.header)
        self._last_input = now
        if stream == 0:
            self._last_image = now
            self._recent["image"].append(stamp)
        elif stream == 1:
            self._recent["depth"].append(stamp)
        self._decided(self.sync.add(stream, stamp, (msg, now)))

    def _decided(self, matches):
        """Queue the frames the synchronizer paired; notice images it gave up on."""
        before = self._dropped_seen
        self._dropped_seen = self.sync.stats.dropped
        for match in matches:
            self._unpaired_run, self._never_paired_warned = 0, False
            self._enqueue(match)
        if self._dropped_seen > before:
            self._unpaired_run += self._dropped_seen - before
            if self._unpaired_run >= UNPAIRED_WARN:
                self._warn_never_paired()

    def _warn_never_paired(self):
        """Warn once per run of UNPAIRED_WARN images in a row without a sim partner, with the offsets."""
        if self._never_paired_warned:
            return
        self._never_paired_warned = True
        st = self.sync.stats
        depth = list(self._recent["depth"])
        if not depth:
            text = "no sim/depth received at all (is sim_camera rendering the poses?)"
        else:
            offs = [min((t - s for s in depth), key=abs) / 1e9 for t in list(self._recent["image"])[-5:]]
            text = ("offsets image stamp - nearest sim stamp of the last images: "
                    + ", ".join(f"{o:+.3f} s" for o in offs))
        self.get_logger().warning(f"{st.dropped} images had no sim frame within max_dt = "
                                  f"{self.get_parameter('max_dt').value:g} s ({st.matched} paired); {text}")

    def _enqueue(self, match):
        with self._cv:
            if len(self._queue) >= self.get_parameter("queue_size").value:
                self._queue.popleft()
                self.counts["dropped_queue"] += 1
            self._queue.append(match)
            self.counts["paired"] += 1
            self._cv.notify()

    # ------------------------------------------------------------------ work

    def _work(self):
        while True:
            with self._cv:
                while not self._queue and not self._stop:
                    self._cv.wait(0.5)
                if self._stop:
                    return
                match = self._queue.popleft()
                self._busy = True
            try:
                self._process(match)
            except BadInput as e:
                self.counts["dropped_bad"] += 1
                self.bad[e.reason] += 1
                self.get_logger().error(f"frame at stamp {match.stamp_ns} dropped: {e}", throttle_duration_sec=5.0)
            except Exception as e:  # never die silently in the worker
                self.counts["dropped_bad"] += 1
                self.bad["error"] += 1
                self.get_logger().error(f"frame at stamp {match.stamp_ns} dropped: {type(e).__name__}: {e}",
                                        throttle_duration_sec=5.0)
            finally:
                with self._cv:
                    self._busy = False

    def _process(self, match):
        (img, t_img), (depth_msg, t_d), (mask_msg, t_m), (info, t_i) = match.items
        t_ready = max(t_img, t_d, t_m, t_i)
        compressed = isinstance(img, CompressedImage)
        if not compressed and str(img.encoding) in ("mono8", "8UC1", "mono16"):
            raise BadInput("mono", f"camera/image_raw is grey ({img.encoding}): the model restores each colour "
                                   f"channel with its own attenuation")
        try:
            rgb = compressed_to_rgb(img) if compressed else image_to_rgb(img)
        except ValueError as e:
            raise BadInput("image", f"{self._image_sub.topic_name}: {e}") from None
        try:
            depth = image_to_depth(depth_msg)
            mask = image_to_mono(mask_msg)
            camera = CameraModel.from_camera_info(info)
        except ValueError as e:
            raise BadInput("sim", f"sim input: {e}") from None
        if depth.shape != rgb.shape[:2] or mask.shape != rgb.shape[:2]:
            raise BadInput("size", f"camera/image_raw is {rgb.shape[1]}x{rgb.shape[0]} but sim/depth is "
                                   f"{depth.shape[1]}x{depth.shape[0]} and sim/mask {mask.shape[1]}x{mask.shape[0]}")
        with self._lock:
            method = self.method
            try:
                res = self.enhancer.enhance(rgb, method, depth=depth, mask=mask, camera=camera)
            except ValueError as e:
                raise BadInput("geometry" if "sim" in str(e) else "input", str(e)) from None
        for w in res.warnings:
            self.get_logger().warning(w, throttle_duration_sec=10.0)
        out = Image(header=img.header, **rgb_to_image_fields(res.image))
        with self._pub_lock:            # not while destroy_node tears the publishers down
            if self._stop:
                return
            self.pub_image.publish(out)
            self.pub_info.publish(CameraInfo(header=img.header, **camera.camera_info_fields()))
        self.latency.append(time.monotonic() - t_ready)
        self.counts["enhanced"] += 1
        self.last = {"restored_fraction": round(res.restored_fraction, 4), "b_source": res.b_source,
                     "background": [round(x, 4) for x in res.background]}

    # ------------------------------------------------------------------ status, idle exit

    def status(self) -> dict:
        st = self.sync.stats
        lat = np.array(self.latency) * 1e3
        return {
            "state": "running" if self._image_sub is not None else
                     ("waiting for the model of " + self._sim_fqn if self.model is None
                      else f"waiting for {self._sim_fqn} to subscribe"),
            "method": self.method,
            "received": {"image": st.received[0], "depth": st.received[1], "mask": st.received[2],
                         "camera_info": st.received[3]},
            "paired": self.counts["paired"], "enhanced": self.counts["enhanced"],
            "dropped_queue": self.counts["dropped_queue"], "dropped_unpaired": st.dropped,
            "dropped_bad": self.counts["dropped_bad"], "bad": dict(self.bad),
            "latency_ms": {"p50": round(float(np.percentile(lat, 50)), 3) if lat.size else None,
                           "p95": round(float(np.percentile(lat, 95)), 3) if lat.size else None,
                           "n": int(lat.size)},
            **self.last,
            "model": None if self.model is None else self.model.flat_params() | {"fog_mode": self.model.fog},
        }

    def _publish_status(self):
        if self.context.ok():
            self.pub_status.publish(String(data=json.dumps(self.status())))

    def _check_idle(self):
        if self._last_image is None or self.finished.done():
            return
        with self._cv:
            idle = not self._queue and not self._busy
        if not idle or time.monotonic() - self._last_input < self.get_parameter("idle_timeout").value:
            return
        if self.sync.pending:                       # the input has ended: decide what waits for partners
            self._decided(self.sync.flush())
            return
        self.get_logger().info(f"no input for {self.get_parameter('idle_timeout').value:g} s: done; "
                               f"{json.dumps(self.status())}")
        self._publish_status()
        self.finished.set_result(True)

    def destroy_node(self):
        # (also for a node whose constructor was interrupted: rclpy destroys it at shutdown, built or not)
        cv, worker = getattr(self, "_cv", None), getattr(self, "_worker", None)
        if cv is not None:
            with cv:
                self._stop = True
                cv.notify_all()
        if worker is not None:
            worker.join(timeout=5.0)
        # a frame still being restored after that finds _stop set when it would publish
        with getattr(self, "_pub_lock", None) or contextlib.nullcontext():
            super().destroy_node()


def _spin(node) -> int:
    with executor_for(node) as executor:      # shut down explicitly: a collected executor can segfault
        if node.get_parameter("idle_timeout").value > 0:
            executor.spin_until_future_complete(node.finished)
        else:
            executor.spin()
    return 0


def main(args=None):
    return run_node(EnhancerNode, _spin, args=args, name="enhancer", user_errors=(ValueError,), doc=__doc__)


if __name__ == "__main__":
    sys.exit(main())
