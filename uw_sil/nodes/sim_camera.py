"""``sim_camera`` node: renders the panel at each received pose with the live underwater parameters.

Subscribes
    ``panel/pose`` (geometry_msgs/PoseStamped): the panel in the camera optical frame.
    ``camera/camera_info`` (sensor_msgs/CameraInfo, optional): intrinsics of the real camera; until one
    arrives the ``width``/``height``/``hfov_deg`` parameters define the camera.
Publishes (stamped with the pose's stamp, frame = the pose's frame)
    ``sim/image_raw`` (rgb8), ``sim/image_clean`` (rgb8), ``sim/depth`` (32FC1 planar z in metres,
    REP 118, +inf where nothing was hit), ``sim/mask`` (mono8 labels: 0 water, 1 panel, 2 seafloor),
    ``sim/camera_info``.
Parameters (live, validated; set with ``ros2 param set`` or the parameter services)
    ``a_r a_g a_b`` attenuation [1/m], ``b_r b_g b_b`` background [0..1], ``rho_f`` fog density [1/m],
    ``fog_mode`` (exp2|exp|none), ``noise_sigma`` (camera noise in grey levels); read-only: ``model_path``, ``width``, ``height``, ``hfov_deg``,
    ``queue_size`` (1: poses arriving while a frame renders replace each other, so the newest is
    rendered next; raise it to render every pose of a burst, at the cost of latency).
    ``effects`` (read-only string, default ""): effects of :mod:`uw_sil.sim.effects` added to the model,
    ``"NAME[=mild|strong],..."``; for each listed effect its parameters ``<effect>.<param>`` are declared
    (live, with ranges; initial values: the preset if given, else the effect's defaults; a params file
    overrides them).
"""
from __future__ import annotations

import sys

import numpy as np
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image

from ..sim.camera import CameraModel
from ..sim.effects import get_effect
from ..sim.model import flat_to_effect_params
from ..bags.imgmsg import depth_to_image_fields, rgb_to_image_fields
from ..sim.params import RGB_NAMES, UNITS, UnderwaterParams
from ..sim.simcam import SimCamera
from ..sim.transforms import pose_to_matrix
from . import run_node

_RANGES = {"a": (0.0, 5.0), "b": (0.0, 1.0), "rho": (0.0, 5.0)}


def _descriptor(name: str) -> ParameterDescriptor:
    lo, hi = _RANGES["rho" if name == "rho_f" else name[0]]
    return ParameterDescriptor(
        description=f"underwater model: {name} [{UNITS[name] or '0..1'}]",
        floating_point_range=[FloatingPointRange(from_value=lo, to_value=hi, step=0.0)])


class SimCameraNode(Node):
    def __init__(self, **kwargs):
        super().__init__("sim_camera", **kwargs)
        defaults = UnderwaterParams().as_dict()
        for n in RGB_NAMES:
            self.declare_parameter(n, defaults[n], _descriptor(n))
        self.declare_parameter("fog_mode", "exp2", ParameterDescriptor(description="exp2 | exp | none"))
        self.declare_parameter("noise_sigma", 0.0, ParameterDescriptor(
            description="camera noise, standard deviation in grey levels (0 = noise-free)",
            floating_point_range=[FloatingPointRange(from_value=0.0, to_value=50.0, step=0.0)]))
        ro = ParameterDescriptor(read_only=True)
        self.declare_parameter("model_path", "", ro)
        self.declare_parameter("width", 640, ro)
        self.declare_parameter("height", 480, ro)
        self.declare_parameter("hfov_deg", 70.0, ro)
        self.declare_parameter("queue_size", 1, ro)
        self.declare_parameter("effects", "", ParameterDescriptor(
            read_only=True, description="effects added to the model: NAME[=mild|strong],... (uw_sil.sim.effects)"))
        self._effect_names = self._declare_effects(self.get_parameter("effects").value)
        g = self.get_parameter
        camera = CameraModel.from_fov(g("width").value, g("height").value, g("hfov_deg").value)
        self.sim = SimCamera(self._params_from(dict()), camera=camera, model=g("model_path").value or None,
                             fog=g("fog_mode").value, noise_sigma=g("noise_sigma").value,
                             effects=self._effects_from(dict()))
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.pub_image = self.create_publisher(Image, "sim/image_raw", qos_profile_sensor_data)
        self.pub_clean = self.create_publisher(Image, "sim/image_clean", qos_profile_sensor_data)
        self.pub_depth = self.create_publisher(Image, "sim/depth", qos_profile_sensor_data)
        self.pub_mask = self.create_publisher(Image, "sim/mask", qos_profile_sensor_data)
        self.pub_info = self.create_publisher(CameraInfo, "sim/camera_info", qos_profile_sensor_data)
        self.create_subscription(CameraInfo, "camera/camera_info", self._on_camera_info, qos_profile_sensor_data)
        # Reliable; keep-last ``queue_size`` (1: when poses come faster than frames render, the newest is
        # rendered and the stale ones are dropped, which keeps the latency at about one render).
        self.create_subscription(PoseStamped, "panel/pose", self._on_pose, g("queue_size").value)
        self.frames = 0

    def _declare_effects(self, spec: str) -> list:
        names = []
        for item in (s.strip() for s in str(spec).split(",")):
            if not item:
                continue
            name, eq, level = item.partition("=")
            eff = get_effect(name.strip())
            values = eff.severity(level.strip()) if eq else eff.defaults()
            for p in eff.params:
                self.declare_parameter(f"{eff.name}.{p.name}", float(values[p.name]), ParameterDescriptor(
                    description=f"{eff.name}: {p.description}" + (f" [{p.unit}]" if p.unit else ""),
                    floating_point_range=[FloatingPointRange(from_value=float(p.lo), to_value=float(p.hi), step=0.0)]))
            names.append(eff.name)
        return names

    def _effects_from(self, changes: dict) -> dict:
        flat = {}
        for name in self._effect_names:
            for p in get_effect(name).param_names:
                key = f"{name}.{p}"
                flat[key] = float(changes.get(key, self.get_parameter(key).value))
        return flat_to_effect_params(flat)

    def _params_from(self, changes: dict) -> UnderwaterParams:
        d = {n: float(changes.get(n, self.get_parameter(n).value)) for n in RGB_NAMES}
        return UnderwaterParams.from_dict(d)

    def _on_set_parameters(self, params) -> SetParametersResult:
        changes = {p.name: p.value for p in params}
        try:
            new = self._params_from(changes)
            effects = self._effects_from(changes)
            fog = changes.get("fog_mode", self.sim.fog)
            self.sim.fog = fog
            if "noise_sigma" in changes:
                self.sim.noise_sigma = changes["noise_sigma"]
        except (ValueError, TypeError) as e:
            return SetParametersResult(successful=False, reason=str(e))
        self.sim.params = new
        self.sim.effects = effects
        return SetParametersResult(successful=True)

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
        frame = self.sim.render(T)
        header = msg.header
        for pub, fields in ((self.pub_image, rgb_to_image_fields(frame.image_uint8())),
                            (self.pub_clean, rgb_to_image_fields(
                                np.clip(np.rint(frame.render.rgb * 255), 0, 255).astype(np.uint8))),
                            (self.pub_depth, depth_to_image_fields(frame.render.depth)),
                            (self.pub_mask, rgb_to_image_fields(frame.render.labels, "mono8"))):
            out = Image(header=header, **fields)
            pub.publish(out)
        self.pub_info.publish(CameraInfo(header=header, **self.sim.camera.camera_info_fields()))
        self.frames += 1

    def destroy_node(self):
        self.sim.close()
        super().destroy_node()


def main(args=None):
    return run_node(SimCameraNode, args=args, name="sim_camera", doc=__doc__)


if __name__ == "__main__":
    sys.exit(main())
