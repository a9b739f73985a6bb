"""``panel_pose`` node: the panel pose from its fiducial markers in each camera frame, published on
``panel/pose`` for recordings and vehicles without a pose source (``pose_source: markers``), so that
``sim_camera``, ``backward_fit`` and ``enhancer`` keep their one pose input.

Subscribes ``camera/image_raw`` (Image; with ``image_transport:=compressed``: ``camera/image_raw/compressed``,
CompressedImage, JPEG/PNG) and ``camera/camera_info`` (CameraInfo; not with ``camera_info_file``). Each image
is handed to :class:`uw_sil.sim.markers.MarkerPoseEstimator` (ArUco detection, IPPE, Levenberg-Marquardt and,
with ``refine:=ecc``, alignment of the rendered panel face: the detector of ``uw-sil fit --pose-from markers``);
the pose ``T_cam_panel`` is published as ``panel/pose`` (geometry_msgs/PoseStamped) with the image's header
(stamp and optical frame), so it pairs with its image by stamp. Images without a pose (no marker of the layout
in view, ambiguous, misdetected) are counted and the reason logged; nothing is published for them. Images that
arrive before the first camera_info wait for it (``pending_images`` at most).

Publishes ``~/status`` (std_msgs/String, JSON, transient local, every 2 s: images, poses, images without pose
and the last reason, mean reprojection error).

Parameters (read at start): ``image_transport`` (raw | compressed), ``camera_info_file`` (camera calibration
YAML without distortion, instead of camera/camera_info), ``model_path`` (panel mesh; its ``.markers.yaml`` is
the marker layout; empty: the shipped panel), ``refine`` (ecc | lm), ``max_rms_px`` (corner reprojection error
above which a pose is refused), ``pending_images``.
"""
from __future__ import annotations

import collections
import json
import sys

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import String

from ..bags.imgmsg import compressed_to_rgb, image_to_rgb
from ..sim.camera import CameraModel
from ..sim.transforms import matrix_to_pose
from . import camera_from_file, executor_for, run_node

TRANSPORTS = {"raw": ("camera/image_raw", Image), "compressed": ("camera/image_raw/compressed", CompressedImage)}
REFINE = ("ecc", "lm")


class PanelPoseNode(Node):
    def __init__(self, **kwargs):
        super().__init__("panel_pose", **kwargs)
        d = ParameterDescriptor
        for name, default, description, fields in (
                ("image_transport", "raw", "camera input: raw (sensor_msgs/Image on camera/image_raw) or compressed "
                 "(sensor_msgs/CompressedImage on camera/image_raw/compressed)",
                 {"additional_constraints": "one of " + ", ".join(TRANSPORTS)}),
                ("camera_info_file", "", "camera calibration YAML (no distortion) used instead of "
                 "camera/camera_info (empty: subscribe camera/camera_info)", {}),
                ("model_path", "", "panel mesh whose .markers.yaml declares the markers (empty: the shipped panel)",
                 {}),
                ("refine", "ecc", "pose refinement: ecc (align the rendered panel face) or lm (marker corners only)",
                 {"additional_constraints": "one of " + ", ".join(REFINE)}),
                ("max_rms_px", 2.0, "largest marker-corner reprojection error of an accepted pose [px]",
                 {"floating_point_range": [FloatingPointRange(from_value=0.1, to_value=100.0, step=0.0)]}),
                ("pending_images", 30, "images kept waiting for the first camera_info",
                 {"integer_range": [IntegerRange(from_value=1, to_value=1000, step=1)]}),
                ("reliable_input", False, "subscribe to the camera reliably (a replayed bag: nothing lost) instead "
                 "of with sensor-data QoS (best effort: matches any camera driver)", {})):
            self.declare_parameter(name, default, d(description=f"{description}; read at start", read_only=True,
                                                    **fields))
        g = lambda n: self.get_parameter(n).value  # noqa: E731
        if g("image_transport") not in TRANSPORTS:
            raise ValueError(f"image_transport must be one of {', '.join(TRANSPORTS)}, got {g('image_transport')!r}")
        if g("refine") not in REFINE:
            raise ValueError(f"refine must be one of {', '.join(REFINE)}, got {g('refine')!r}")
        from ..sim.markers import MarkerPoseEstimator

        self.camera = camera_from_file(g("camera_info_file")) if g("camera_info_file") else None
        self.estimator = MarkerPoseEstimator(model=g("model_path") or None, refine=g("refine"),
                                             max_rms_px=g("max_rms_px"))
        self.counts = collections.Counter()
        self.last_reason = ""
        self._rms = []
        self._pending = collections.deque(maxlen=g("pending_images"))
        self.pub_pose = self.create_publisher(PoseStamped, "panel/pose", 10)
        self.pub_status = self.create_publisher(String, "~/status",
                                                QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        # a deep queue: a pose takes tens of ms (ECC refinement), images of a replayed burst must not be lost;
        # a replay is read reliably, as backward_fit reads it (under load best effort lost frames there)
        reliability = ReliabilityPolicy.RELIABLE if g("reliable_input") else qos_profile_sensor_data.reliability
        sensor = QoSProfile(depth=100, reliability=reliability, durability=qos_profile_sensor_data.durability)
        topic, msg_type = TRANSPORTS[g("image_transport")]
        self.sub_image = self.create_subscription(msg_type, topic, self._on_image, sensor)
        if self.camera is None:
            self.create_subscription(CameraInfo, "camera/camera_info", self._on_camera_info, qos_profile_sensor_data)
        self.create_timer(2.0, self._publish_status)
        self.get_logger().info(f"markers of {self.estimator.layout.source}: {self.estimator.layout.dictionary} ids "
                               f"{self.estimator.layout.ids}; poses of {self.sub_image.topic_name} on "
                               f"{self.pub_pose.topic_name}")

    def _on_camera_info(self, msg: CameraInfo):
        try:
            camera = CameraModel.from_camera_info(msg)
        except ValueError as e:
            self.get_logger().error(f"ignoring camera_info: {e}", throttle_duration_sec=5.0)
            return
        first = self.camera is None
        self.camera = camera
        if first:
            while self._pending:
                self._estimate(self._pending.popleft())

    def _on_image(self, msg):
        self.counts["images"] += 1
        if self.camera is None:
            if len(self._pending) == self._pending.maxlen:
                self.counts["dropped_no_camera_info"] += 1
            self._pending.append(msg)
            return
        self._estimate(msg)

    def _estimate(self, msg):
        try:
            rgb = compressed_to_rgb(msg) if isinstance(msg, CompressedImage) else image_to_rgb(msg)
            mp = self.estimator.estimate(rgb, self.camera)
        except ValueError as e:
            self.counts["bad_image"] += 1
            self.get_logger().error(f"image skipped: {e}", throttle_duration_sec=5.0)
            return
        if mp.T is None:
            self.counts["without_pose"] += 1
            self.last_reason = mp.reason
            self.get_logger().info(f"no pose: {mp.reason}", throttle_duration_sec=5.0)
            return
        pos, quat = matrix_to_pose(mp.T)
        out = PoseStamped(header=msg.header)
        out.pose.position.x, out.pose.position.y, out.pose.position.z = map(float, pos)
        (out.pose.orientation.x, out.pose.orientation.y, out.pose.orientation.z,
         out.pose.orientation.w) = map(float, quat)
        self.pub_pose.publish(out)
        self.counts["poses"] += 1
        self._rms.append(float(mp.rms_px))

    def status(self) -> dict:
        return {**self.counts, "last_reason": self.last_reason,
                "reprojection_rms_px_mean": round(sum(self._rms) / len(self._rms), 3) if self._rms else None}

    def _publish_status(self):
        if self.context.ok():
            self.pub_status.publish(String(data=json.dumps(self.status())))

    def destroy_node(self):
        if getattr(self, "counts", None) is not None:
            # what it received and posed, once at the end: a graph test names where a frame went missing
            self.get_logger().info(f"done; {json.dumps(self.status())}")
        if getattr(self, "estimator", None) is not None:
            self.estimator.close()
        super().destroy_node()


def _spin(node) -> int:
    # Single-threaded: the OpenGL context of the ECC refinement's renderer belongs to this thread.
    with executor_for(node) as executor:
        executor.spin()
    return 0


def main(args=None):
    return run_node(PanelPoseNode, _spin, args=args, name="panel_pose", user_errors=(ValueError, FileNotFoundError),
                    doc=__doc__)


if __name__ == "__main__":
    sys.exit(main())
