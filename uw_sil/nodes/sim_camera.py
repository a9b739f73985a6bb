"""``sim_camera`` node: renders the panel at each received pose with the live underwater parameters.

Subscribes
    ``panel/pose`` (geometry_msgs/PoseStamped): the panel in the camera optical frame.
    ``camera/camera_info`` (sensor_msgs/CameraInfo, optional): intrinsics of the real camera; until one
    arrives the ``width``/``height``/``hfov_deg`` parameters define the camera. Not subscribed with
    ``camera_info_file`` (read-only: a camera calibration YAML without distortion, for recordings without
    camera_info), which then defines the camera.
Publishes (stamped with the pose's stamp, frame = the pose's frame)
    ``sim/image_raw`` (rgb8), ``sim/image_clean`` (rgb8), ``sim/depth`` (32FC1 planar z in metres,
    REP 118, +inf where nothing was hit), ``sim/mask`` (mono8 labels: 0 water, 1 panel, 2 seafloor),
    ``sim/camera_info``. A topic nobody subscribes to is not published; while nobody takes either image, the
    frame's colour and underwater model are not computed at all (an enhancer takes only depth and mask).
Parameters (live, validated; set with ``ros2 param set`` or the parameter services)
    ``a_r a_g a_b`` attenuation [1/m], ``b_r b_g b_b`` background [0..1], ``rho_f`` fog density [1/m],
    ``fog_mode`` (exp2|exp|none), ``noise_sigma`` (camera noise in grey levels); read-only: ``model_path``, ``width``, ``height``, ``hfov_deg``,
    ``queue_size`` (1: poses arriving while a frame renders replace each other, so the newest is
    rendered next; raise it to render every pose of a burst, at the cost of latency), ``workers`` (default 0:
    each frame rendered, modelled and published in its pose's callback; N > 0: N threads run the underwater
    model of frames side by side while the next one renders, :mod:`uw_sil.sim.stream`, frames published in
    pose order, with ``queue_size`` 1 the newest pose rendered as soon as fewer than N + 1 frames are on their
    way: more frames per second at more latency, see the README), ``reliable_output``
    (false: the sim/* topics with sensor-data QoS; true, as in a replayed bag: reliable, keep-last 10,
    so that no rendered frame is lost).
    ``effects`` (string, default ""): effects of :mod:`uw_sil.sim.effects` added to the model,
    ``"NAME[=mild|strong],..."``; for each listed effect its parameters ``<effect>.<param>`` are declared
    (live, with ranges; initial values: the preset if given, else the effect's defaults; a params file
    overrides them). Read-only unless ``extensible_effects`` is given.
    ``extensible_effects`` (read-only string, default ""): effects a re-parameterization may add later
    (``NAME,...`` or ``all``): their parameters are declared too (at the effect's defaults, inactive), and
    ``effects`` is live, taking names of these (no presets), so that e.g. the diagnosis of ``backward_fit``
    sets ``effects`` and the accepted effects' parameters in one atomic batch.
"""
from __future__ import annotations

import sys

import numpy as np
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image

from ..sim.camera import CameraModel
from ..sim.effects import get_effect
from ..sim.model import flat_to_effect_params
from ..bags.imgmsg import depth_to_image_fields, rgb_to_image_fields
from ..sim.optics import FOG_MODES
from ..sim.params import RGB_NAMES, UNITS, UnderwaterParams
from ..sim.simcam import SimCamera
from ..sim.stream import FrameStream
from ..sim.transforms import pose_to_matrix
from . import camera_from_file, run_node

_RANGES = {"a": (0.0, 5.0), "b": (0.0, 1.0), "rho": (0.0, 5.0)}
#: Largest image side ``width``/``height`` accept, and the camera noise range [grey levels].
MAX_SIDE = 8192
NOISE_RANGE = (0.0, 50.0)


def _float_range(lo: float, hi: float) -> list:
    return [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]


def _int_range(lo: int, hi: int) -> list:
    return [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]


def _descriptor(name: str) -> ParameterDescriptor:
    """A fresh descriptor per parameter: rclpy writes the parameter's name and type into it."""
    if name in RGB_NAMES:
        lo, hi = _RANGES["rho" if name == "rho_f" else name[0]]
        what = {"a": "attenuation", "b": "background (veiling light)", "r": "fog density"}[name[0]]
        return ParameterDescriptor(description=f"underwater model: {what} {name} [{UNITS[name] or '0..1'}]",
                                   floating_point_range=_float_range(lo, hi))
    return {
        "fog_mode": lambda: ParameterDescriptor(
            description=f"fog model, one of {', '.join(FOG_MODES)} (exp2: Gazebo's, f(z) = exp(-(rho_f z)^2))",
            additional_constraints=f"one of {', '.join(FOG_MODES)}"),
        "noise_sigma": lambda: ParameterDescriptor(
            description="camera noise, standard deviation in grey levels (0 = noise-free)",
            floating_point_range=_float_range(*NOISE_RANGE)),
        "model_path": lambda: ParameterDescriptor(
            description="panel model (.glb/.obj/...; empty: the procedural panel); read at start",
            read_only=True),
        "width": lambda: ParameterDescriptor(
            description="image width [px] until a camera_info arrives; read at start", read_only=True,
            integer_range=_int_range(8, MAX_SIDE)),
        "height": lambda: ParameterDescriptor(
            description="image height [px] until a camera_info arrives; read at start", read_only=True,
            integer_range=_int_range(8, MAX_SIDE)),
        "hfov_deg": lambda: ParameterDescriptor(
            description="horizontal field of view [deg] until a camera_info arrives; read at start",
            read_only=True, floating_point_range=_float_range(1.0, 179.0)),
        "effects": lambda: ParameterDescriptor(
            description="effects added to the model: NAME[=mild|strong],... (uw_sil.sim.effects); read at start "
                        "(live with extensible_effects: names of those, no presets)", read_only=True),
        "extensible_effects": lambda: ParameterDescriptor(
            description="effects that a re-parameterization may add later: NAME,... or all (their parameters are "
                        "declared, inactive; effects is then live); read at start", read_only=True),
        "camera_info_file": lambda: ParameterDescriptor(
            description="camera calibration YAML (no distortion) used instead of camera/camera_info (empty: "
                        "subscribe camera/camera_info); read at start", read_only=True),
        "reliable_output": lambda: ParameterDescriptor(
            description="publish sim/* reliably, keeping the last 10 frames (a replayed bag: no "
                        "rendered frame lost; reliable writers serve best-effort readers too) instead of with "
                        "sensor-data QoS; read at start", read_only=True),
        "queue_size": lambda: ParameterDescriptor(
            description="poses queued while a frame renders (1: the newest replaces older ones); read at start",
            read_only=True, integer_range=_int_range(1, 1000)),
        "workers": lambda: ParameterDescriptor(
            description="threads running the underwater model of frames side by side while the next frame renders "
                        "(uw_sil.sim.stream; more frames per second, more latency); 0: one frame at a time in the "
                        "pose callback; read at start", read_only=True,
            integer_range=_int_range(0, 16)),
    }[name]()


def _effect_list(spec: str, what: str) -> list:
    """Effect names of a comma-separated list (``all``: every effect); ValueError naming ``what``. Presets
    (``NAME=mild``) are refused here: only the start-up ``effects`` takes them."""
    from ..sim.effects import EFFECTS

    items = [s.strip() for s in str(spec).split(",") if s.strip()]
    if items == ["all"]:
        return list(EFFECTS)
    names = []
    for item in items:
        if "=" in item:
            raise ValueError(f"{what}: {item!r}: presets are taken only at start; set <effect>.<param> instead")
        if item not in EFFECTS:
            raise ValueError(f"{what}: unknown effect {item!r}; known: {', '.join(EFFECTS)}")
        names.append(item)
    return names


class SimCameraNode(Node):
    def __init__(self, **kwargs):
        super().__init__("sim_camera", **kwargs)
        defaults = UnderwaterParams().as_dict()
        for n in RGB_NAMES:
            self.declare_parameter(n, defaults[n], _descriptor(n))
        for n, default in (("fog_mode", "exp2"), ("noise_sigma", 0.0), ("model_path", ""), ("width", 640),
                           ("height", 480), ("hfov_deg", 70.0), ("queue_size", 1), ("extensible_effects", ""),
                           ("camera_info_file", ""), ("reliable_output", False), ("workers", 0)):
            self.declare_parameter(n, default, _descriptor(n))
        self._extensible = _effect_list(self.get_parameter("extensible_effects").value, "extensible_effects")
        effects = _descriptor("effects")
        effects.read_only = not self._extensible
        self.declare_parameter("effects", "", effects)
        self._effect_names = self._declare_effects(self.get_parameter("effects").value)
        self._effect_names_at_start = list(self._effect_names)
        for name in self._extensible:     # the others: declared at their defaults, inactive until listed
            if name not in self._effect_names:
                self._declare_effect(get_effect(name), get_effect(name).defaults())
        g = self.get_parameter
        # Start-up values (parameter files, -p) pass the same checks as later changes.
        reason = self._check({n: g(n).value for n in (*RGB_NAMES, "fog_mode", "noise_sigma", *self._effect_keys)})
        if reason:
            raise ValueError(f"sim_camera: {reason}")
        camera_file = g("camera_info_file").value
        camera = (camera_from_file(camera_file) if camera_file
                  else CameraModel.from_fov(g("width").value, g("height").value, g("hfov_deg").value))
        self.sim = SimCamera(self._params_from(dict()), camera=camera, model=g("model_path").value or None,
                             fog=g("fog_mode").value, noise_sigma=g("noise_sigma").value,
                             effects=self._effects_from(dict()))
        # workers > 0: the render of the next pose while the model of the last ones runs, frames published in pose
        # order; a live camera (queue_size 1) renders the newest pose, older waiting poses dropped. 0: each frame
        # rendered, modelled and published in the pose's callback (the least latency).
        workers = g("workers").value
        self.stream = (FrameStream(self.sim, self._publish, workers=workers, newest_only=g("queue_size").value == 1)
                       if workers > 0 else None)
        # Check a whole batch first, apply it only once every entry has passed (and rclpy has stored it):
        # a batch rejected by its last entry changes nothing.
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        # reliable: keep-last 10, as the enhancer's readers (a deeper history would hold up to 3.3 MB per frame
        # of 640x480 renders in this process; the readers only pair and queue in their callbacks)
        out = (QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
               if g("reliable_output").value else qos_profile_sensor_data)
        self.pub_image = self.create_publisher(Image, "sim/image_raw", out)
        self.pub_clean = self.create_publisher(Image, "sim/image_clean", out)
        self.pub_depth = self.create_publisher(Image, "sim/depth", out)
        self.pub_mask = self.create_publisher(Image, "sim/mask", out)
        self.pub_info = self.create_publisher(CameraInfo, "sim/camera_info", out)
        if not camera_file:
            self.create_subscription(CameraInfo, "camera/camera_info", self._on_camera_info, qos_profile_sensor_data)
        # Reliable; keep-last ``queue_size`` (1: when poses come faster than frames render, the newest is
        # rendered and the stale ones are dropped, which keeps the latency at about one render).
        pose_sub = self.create_subscription(PoseStamped, "panel/pose", self._on_pose, g("queue_size").value)
        self.frames = 0
        until = f"from {camera_file}" if camera_file else "until a camera_info arrives"
        self.get_logger().info(f"ready: {camera.width}x{camera.height} {until}, fog "
                               f"{self.sim.fog}; rendering each pose on {pose_sub.topic_name}")

    def _declare_effects(self, spec: str) -> list:
        names = []
        for item in (s.strip() for s in str(spec).split(",")):
            if not item:
                continue
            name, eq, level = item.partition("=")
            eff = get_effect(name.strip())
            self._declare_effect(eff, eff.severity(level.strip()) if eq else eff.defaults())
            names.append(eff.name)
        return names

    def _declare_effect(self, eff, values: dict):
        for p in eff.params:
            self.declare_parameter(f"{eff.name}.{p.name}", float(values[p.name]), ParameterDescriptor(
                description=f"{eff.name}: {p.description}" + (f" [{p.unit}]" if p.unit else ""),
                floating_point_range=[FloatingPointRange(from_value=float(p.lo), to_value=float(p.hi), step=0.0)]))

    def _effects_from(self, changes: dict) -> dict:
        flat = {}
        names = self._effect_names
        if "effects" in changes:
            names = _effect_list(changes["effects"], "effects")
        for name in names:
            for p in get_effect(name).param_names:
                key = f"{name}.{p}"
                flat[key] = float(changes.get(key, self.get_parameter(key).value))
        return flat_to_effect_params(flat)

    @property
    def _effect_keys(self) -> list:
        return [f"{name}.{p}" for name in self._effect_names for p in get_effect(name).param_names]

    def _check_effects(self, value) -> str:
        """Why ``effects`` cannot be set live to ``value`` ('' if it can)."""
        try:
            names = _effect_list(value, "effects")
        except ValueError as e:
            return str(e)
        declared = set(self._extensible) | set(self._effect_names_at_start)
        missing = [n for n in names if n not in declared]
        if missing:
            return (f"effects: {', '.join(missing)} not declared (start sim_camera with extensible_effects "
                    f"naming them, or all)")
        return ""

    def _params_from(self, changes: dict) -> UnderwaterParams:
        d = {n: float(changes.get(n, self.get_parameter(n).value)) for n in RGB_NAMES}
        return UnderwaterParams.from_dict(d)

    def _check(self, changes: dict) -> str:
        """Why ``changes`` (name -> value, on top of the current values) cannot be applied; '' if they can.

        Changes nothing. Ranges and types are also enforced by rclpy from the descriptors, before this."""
        if "effects" in changes:
            reason = self._check_effects(changes["effects"])
            if reason:
                return reason
        try:
            self._params_from(changes)
            self._effects_from(changes)
        except (ValueError, TypeError) as e:
            return str(e)
        fog = changes.get("fog_mode")
        if fog is not None and fog not in FOG_MODES:
            return f"fog_mode: unknown fog mode {fog!r}; expected one of {', '.join(FOG_MODES)}"
        sigma = changes.get("noise_sigma")
        if sigma is not None and not (np.isfinite(sigma) and NOISE_RANGE[0] <= sigma <= NOISE_RANGE[1]):
            return f"noise_sigma must be finite and in [{NOISE_RANGE[0]:g}, {NOISE_RANGE[1]:g}] grey levels, got {sigma}"
        return ""

    def _on_set_parameters(self, params) -> SetParametersResult:
        reason = self._check({p.name: p.value for p in params})
        return SetParametersResult(successful=not reason, reason=reason)

    def _apply_parameters(self, params) -> None:
        """After rclpy stored an accepted batch: the simulator takes the new values (all checked)."""
        names = {p.name for p in params}
        if names & set(RGB_NAMES):
            self.sim.params = self._params_from(dict())
        if "fog_mode" in names:
            self.sim.fog = self.get_parameter("fog_mode").value
        if "noise_sigma" in names:
            self.sim.noise_sigma = self.get_parameter("noise_sigma").value
        if "effects" in names:
            self._effect_names = _effect_list(self.get_parameter("effects").value, "effects")
        if "effects" in names or names & set(self._effect_keys):
            self.sim.effects = self._effects_from(dict())

    def _on_camera_info(self, msg: CameraInfo):
        try:
            self.sim.camera = CameraModel.from_camera_info(msg)
        except ValueError as e:
            self.get_logger().error(f"ignoring camera_info: {e}", throttle_duration_sec=5.0)

    def _on_pose(self, msg: PoseStamped):
        p, q = msg.pose.position, msg.pose.orientation
        try:
            T = pose_to_matrix([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])
        except ValueError as e:
            self.get_logger().error(f"ignoring pose: {e}", throttle_duration_sec=5.0)
            return
        # Images nobody subscribes to are neither rendered nor converted: an enhancer takes only the depth and the
        # mask (the colour pass, the shading and the underwater model are most of a 640x480 frame's time).
        wanted = [p for p in (self.pub_image, self.pub_clean, self.pub_depth, self.pub_mask)
                  if p.get_subscription_count() > 0]
        image = self.pub_image in wanted or self.pub_clean in wanted
        if self.stream is None:
            self._publish((msg.header, wanted), self.sim.render(T, image=image), None)
        else:
            self.stream.submit(T, image=image, tag=(msg.header, wanted))

    def _publish(self, tag, frame, error):
        """A finished frame (in pose order; from the stream's threads with ``workers`` > 0)."""
        header, wanted = tag
        if error is not None:
            self.get_logger().error(f"frame at {header.stamp.sec}.{header.stamp.nanosec:09d} failed: {error!r}",
                                    throttle_duration_sec=5.0)
            return
        fields = {self.pub_image: lambda: rgb_to_image_fields(frame.image_uint8()),
                  self.pub_clean: lambda: rgb_to_image_fields(
                      np.clip(np.rint(frame.render.rgb * 255), 0, 255).astype(np.uint8)),
                  self.pub_depth: lambda: depth_to_image_fields(frame.render.depth),
                  self.pub_mask: lambda: rgb_to_image_fields(frame.render.labels, "mono8")}
        try:
            for pub in wanted:
                pub.publish(Image(header=header, **fields[pub]()))
            self.pub_info.publish(CameraInfo(header=header, **frame.camera.camera_info_fields()))
        except Exception:           # noqa: BLE001 - rclpy's RCLError once the context is shut down
            if self.context.ok():
                raise
            return                  # shutting down: the frames still on their way are not published
        self.frames += 1

    def destroy_node(self):
        # Also for a node whose constructor was interrupted (Ctrl-C while the renderer starts): rclpy
        # destroys the nodes of a context at shutdown, built or not.
        try:
            if getattr(self, "stream", None) is not None:
                self.stream.close(cancel=True)       # raises what publishing a frame raised
        finally:
            if getattr(self, "sim", None) is not None:
                self.sim.close()
            super().destroy_node()


def main(args=None):
    return run_node(SimCameraNode, args=args, name="sim_camera", user_errors=(ValueError,), doc=__doc__)


if __name__ == "__main__":
    sys.exit(main())
