"""Where a bag's frames, intrinsics and panel poses come from: topics by name, a calibration file, and
one of three pose sources.

A field bag is described by a :class:`BagSource`:

- ``image_topic``: any ``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage`` topic;
- intrinsics: ``info_topic`` (``sensor_msgs/CameraInfo``), or ``camera_info``, a ROS
  ``camera_calibration`` YAML file (:mod:`uw_sil.bags.camera_yaml`) when the bag has none; distorted
  frames are rectified before use;
- ``pose_from`` (:class:`PoseFrom`), the panel pose ``T_cam_panel`` per frame:

  ``topic:/panel/pose``
      ``geometry_msgs/PoseStamped`` of the panel in the camera optical frame, paired by stamp;
  ``tf:CAMERA_FRAME:PANEL_FRAME``
      composed from ``/tf`` and ``/tf_static`` and interpolated to each image stamp
      (:mod:`uw_sil.bags.tf`); ``tf::PANEL_FRAME`` takes the camera frame from the images' headers.
      CAMERA_FRAME must be the *optical* frame (z forward, x right, y down; REP 103);
  ``markers``
      the panel's ArUco markers detected in each frame (:mod:`uw_sil.sim.markers`); frames without
      one are skipped with the reason.

:meth:`BagSource.read` yields :class:`~uw_sil.bags.records.Sample` objects (see
:func:`uw_sil.bags.reader.read_samples`); :func:`describe_sources` tells what a bag offers.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .reader import iter_messages, load_tf, open_bag, read_samples
from .records import CAMERA_INFO_TYPE, COMPRESSED_IMAGE_TYPE, IMAGE_TYPE, POSE_TYPE, TF_TYPE, BagError, PoseFrom
from .tf import TF_TOPICS

__all__ = ["PoseFrom", "BagSource", "describe_sources", "DEFAULT_IMAGE_TOPIC", "DEFAULT_INFO_TOPIC",
           "DEFAULT_POSE_TOPIC"]

DEFAULT_IMAGE_TOPIC = "/camera/image_raw"
DEFAULT_INFO_TOPIC = "/camera/camera_info"
DEFAULT_POSE_TOPIC = "/panel/pose"
IMAGE_TYPES = (IMAGE_TYPE, COMPRESSED_IMAGE_TYPE)


@dataclass(frozen=True)
class BagSource:
    """How to read one camera stream of a bag (see the module docstring).

    Attributes
    ----------
    image_topic : str
    info_topic : str or None
        Ignored when ``camera_info`` is given.
    camera_info : str, Path, CameraCalibration or None
        A ROS ``camera_calibration`` YAML file (or a loaded calibration) used instead of ``info_topic``.
    pose_from : PoseFrom or str
    model : str, Path or None
        The panel mesh (its ``.markers.yaml`` is the marker layout); None: the shipped panel.
    tf_extrapolation_s : float
        tf lookups may lie this far outside the recorded transforms (the nearest one is held).
    max_dt : float
        Largest |pose stamp - image stamp| (s) for ``topic:`` poses.
    check_frames : bool
        Require camera_info and pose ``header.frame_id`` to equal the image's.
    refine_pose : {'none', 'ecc'}
        Refine topic / tf poses by aligning the rendered panel face with each frame (see
        :func:`uw_sil.bags.reader.read_samples`); marker poses always are.
    """

    image_topic: str = DEFAULT_IMAGE_TOPIC
    info_topic: str | None = DEFAULT_INFO_TOPIC
    camera_info: object = None
    pose_from: object = PoseFrom("topic", topic=DEFAULT_POSE_TOPIC)
    model: object = None
    tf_extrapolation_s: float = 0.1
    max_dt: float = 0.05
    check_frames: bool = True
    refine_pose: str = "none"

    def __post_init__(self):
        object.__setattr__(self, "pose_from", PoseFrom.parse(self.pose_from))
        if not str(self.image_topic).startswith("/"):
            raise ValueError(f"image topic must be an absolute topic name (/...), got {self.image_topic!r}")
        if self.camera_info is None and not self.info_topic:
            raise ValueError("no camera intrinsics: give a camera_info topic or a camera_calibration YAML file")

    def calibration(self):
        """The calibration file's :class:`~uw_sil.bags.camera_yaml.CameraCalibration` (None: from the topic)."""
        from .camera_yaml import CameraCalibration, load_camera_yaml

        if self.camera_info is None or isinstance(self.camera_info, CameraCalibration):
            return self.camera_info
        return load_camera_yaml(self.camera_info)

    def read(self, bag, **kw):
        """Samples of ``bag`` (lazy, with a ``.report``): :func:`uw_sil.bags.reader.read_samples` with this
        source. Extra keywords go to it."""
        pf = self.pose_from
        opts = dict(image_topic=self.image_topic,
                    info_topic=None if self.camera_info is not None else self.info_topic,
                    pose_topic=pf.topic if pf.kind == "topic" else None, pose_from=pf,
                    calibration=self.calibration(), model=self.model, tf_extrapolation=self.tf_extrapolation_s,
                    max_dt=self.max_dt, check_frames=self.check_frames, refine_pose=self.refine_pose)
        opts.update(kw)
        return read_samples(bag, **opts)

    def describe(self) -> str:
        """One line: what is read from where."""
        cal = getattr(self.camera_info, "source", None) or self.camera_info
        cam = f"camera_info file {cal}" if self.camera_info is not None else f"{self.info_topic}"
        refine = ", refined by ECC face alignment" if self.refine_pose == "ecc" and self.pose_from.kind != "markers" else ""
        return f"images {self.image_topic}, intrinsics {cam}, pose {self.pose_from}{refine}"


def _first_message(bag, topic):
    stream = iter_messages(bag, topic)
    try:
        for _, msg in stream:
            return msg
    finally:
        stream.close()
    return None


def describe_sources(bag) -> str:
    """What a bag offers to ``--image-topic``, ``--info-topic`` and ``--pose-from``, as text lines.

    Lists the image-like topics (with size, encoding or compression format and frame of their first
    message), the ``camera_info`` topics (with size and distortion), and the pose sources: every
    ``PoseStamped`` topic, the frames of ``/tf`` and ``/tf_static`` (with a suggested
    ``tf:CAMERA_FRAME:PANEL_FRAME``), and ``markers`` (with the shipped panel's layout).
    """
    info = open_bag(bag)
    topics = sorted(info.topics.values(), key=lambda t: t.name)
    lines = ["image topics (--image-topic):"]
    image_frames = []
    images = [t for t in topics if t.msgtype in IMAGE_TYPES]
    for t in images:
        detail = ""
        try:
            msg = _first_message(bag, t.name) if t.count else None
        except (BagError, ValueError) as exc:
            msg, detail = None, f"  (first message unreadable: {exc})"
        if msg is not None:
            frame = str(msg.header.frame_id)
            image_frames.append(frame)
            if t.msgtype == IMAGE_TYPE:
                detail = f"  {msg.width}x{msg.height} {msg.encoding}, frame {frame!r}"
            else:
                detail = f"  compressed ({msg.format}), frame {frame!r}"
        lines.append(f"  {t.name} [{t.msgtype.split('/')[-1]}] {t.count if t.count is not None else '?'}{detail}")
    if not images:
        lines.append("  none (no sensor_msgs/Image or CompressedImage topic)")
    lines.append("camera_info topics (--info-topic; or --camera-info camera.yaml):")
    infos = [t for t in topics if t.msgtype == CAMERA_INFO_TYPE]
    for t in infos:
        detail = ""
        try:
            msg = _first_message(bag, t.name) if t.count else None
        except (BagError, ValueError):
            msg = None
        if msg is not None:
            import numpy as np

            dist = np.any(np.asarray(msg.d, dtype=float) != 0)
            detail = (f"  {msg.width}x{msg.height}, {msg.distortion_model or 'no model'}"
                      f"{' with distortion (frames are rectified)' if dist else ', no distortion'}")
        lines.append(f"  {t.name} {t.count if t.count is not None else '?'}{detail}")
    if not infos:
        lines.append("  none: pass the camera's calibration with --camera-info camera.yaml")
    lines.append("pose sources (--pose-from):")
    for t in topics:
        if t.msgtype == POSE_TYPE:
            lines.append(f"  topic:{t.name}   ({t.count} PoseStamped; must be the panel in the camera optical frame)")
    tf_topics = [t.name for t in topics if t.msgtype == TF_TYPE]
    if tf_topics:
        if any(t in TF_TOPICS for t in tf_topics):
            try:
                buf = load_tf(bag)
                frames = buf.frames
                cam = next((f for f in image_frames if f.lstrip("/") in frames), None)
                panel = next((f for f in frames if "panel" in f.lower()), None)
                example = f"tf:{cam or 'CAMERA_FRAME'}:{panel or 'PANEL_FRAME'}"
                lines.append(f"  {example}   (frames in {' and '.join(t for t in TF_TOPICS if t in tf_topics)}: "
                             f"{', '.join(frames)})")
            except BagError as exc:
                lines.append(f"  tf: unusable ({exc})")
        other = [t for t in tf_topics if t not in TF_TOPICS]
        if other:
            lines.append(f"  (TFMessage topics not read as tf: {', '.join(other)})")
    else:
        lines.append("  tf: none (no /tf or /tf_static)")
    try:
        from ..sim.markers import default_marker_layout

        layout = default_marker_layout()
        lines.append(f"  markers   (ArUco {layout.dictionary} ids {layout.ids} of the shipped panel, "
                     f"{Path(layout.source).name}; another panel: --model my_panel.glb with my_panel.markers.yaml)")
    except (FileNotFoundError, ValueError) as exc:
        lines.append(f"  markers   (shipped layout unreadable: {exc})")
    return "\n".join(lines)
