"""What readers and writers of trial bags share: message type names, the one-frame record
(:class:`Sample`), where a frame's panel pose comes from (:class:`PoseFrom`) and the error they raise
(:class:`BagError`)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..sim.camera import CameraModel

__all__ = ["Sample", "BagError", "PoseFrom", "IMAGE_TYPE", "COMPRESSED_IMAGE_TYPE", "CAMERA_INFO_TYPE", "POSE_TYPE",
           "TF_TYPE", "STORAGE_SUFFIX", "ROSBAG2_VERSION"]

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
TF_TYPE = "tf2_msgs/msg/TFMessage"

STORAGE_SUFFIX = {"mcap": ".mcap", "sqlite3": ".db3"}
ROSBAG2_VERSION = 9  # metadata.yaml version of Jazzy / Kilted


class BagError(ValueError):
    """A bag cannot be read or written as asked (not a bag, missing topic, bad message...)."""


@dataclass
class Sample:
    """One time-synchronized camera frame of a trial.

    Attributes
    ----------
    stamp_ns : int
        Header stamp of the image, nanoseconds.
    image : ndarray
        (H, W, 3) uint8, RGB.
    camera : CameraModel
        Intrinsics from the paired ``camera_info``.
    pose : ndarray
        4x4 float64 ``T_cam_panel``: the panel frame expressed in the camera optical frame.
    frame_id : str
        The camera optical frame (image ``header.frame_id``).
    index : int
        Position of the frame in its image topic (-1: unknown, e.g. a sample not read from a bag).
    pose_info : dict or None
        How the pose was obtained (``source``; for markers the ids and reprojection error).
    """

    stamp_ns: int
    image: np.ndarray
    camera: CameraModel
    pose: np.ndarray
    frame_id: str = "camera_optical_frame"
    index: int = -1
    pose_info: dict | None = None


@dataclass(frozen=True)
class PoseFrom:
    """A pose source: ``kind`` is ``"topic"`` (with ``topic``), ``"tf"`` (with ``camera_frame``, which
    may be ``""`` for the images' own frame, and ``panel_frame``) or ``"markers"``."""

    kind: str
    topic: str = ""
    camera_frame: str = ""
    panel_frame: str = ""

    def __post_init__(self):
        if self.kind not in ("topic", "tf", "markers"):
            raise ValueError(f"pose source kind must be topic, tf or markers, got {self.kind!r}")
        if self.kind == "topic" and not self.topic.startswith("/"):
            raise ValueError(f"pose topic must be an absolute topic name (/...), got {self.topic!r}")
        if self.kind == "tf" and not self.panel_frame:
            raise ValueError("tf pose source needs the panel frame: tf:CAMERA_FRAME:PANEL_FRAME")

    @classmethod
    def parse(cls, text) -> "PoseFrom":
        """``topic:/panel/pose``, ``tf:CAMERA_FRAME:PANEL_FRAME`` (or ``tf::PANEL_FRAME``) or ``markers``."""
        if isinstance(text, PoseFrom):
            return text
        s = str(text).strip()
        if s == "markers":
            return cls("markers")
        kind, sep, rest = s.partition(":")
        if kind == "topic" and sep and rest:
            return cls("topic", topic=rest)
        if kind == "tf" and sep:
            cam, sep2, panel = rest.partition(":")
            if sep2 and panel and ":" not in panel:
                return cls("tf", camera_frame=cam.lstrip("/"), panel_frame=panel.lstrip("/"))
        raise ValueError(f"--pose-from: must be topic:/TOPIC, tf:CAMERA_FRAME:PANEL_FRAME or markers, got {s!r}")

    def __str__(self) -> str:
        if self.kind == "topic":
            return f"topic:{self.topic}"
        if self.kind == "tf":
            return f"tf:{self.camera_frame}:{self.panel_frame}"
        return "markers"
