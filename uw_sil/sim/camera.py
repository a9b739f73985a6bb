"""Pinhole camera model in the OpenCV / ROS ``sensor_msgs/CameraInfo`` convention.

Pixel ``(u, v)`` has its centre at integer coordinates; the optical frame is REP 103's
``*_optical`` frame: x right, y down, z forward.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["CameraModel"]


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics of an undistorted pinhole camera.

    Parameters
    ----------
    width, height : int
        Image size in pixels.
    fx, fy : float
        Focal lengths in pixels.
    cx, cy : float
        Principal point in pixels (OpenCV convention: centre of the top-left pixel is (0, 0)).
    frame_id : str
        The optical frame the camera images are expressed in.
    """

    width: int = 640
    height: int = 480
    fx: float = 457.0
    fy: float = 457.0
    cx: float = 319.5
    cy: float = 239.5
    frame_id: str = "camera_optical_frame"

    def __post_init__(self):
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"camera size must be positive, got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        for name in ("fx", "fy", "cx", "cy"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be finite")

    @classmethod
    def from_fov(cls, width: int = 640, height: int = 480, hfov_deg: float = 70.0, **kw) -> "CameraModel":
        """Square-pixel camera with horizontal field of view ``hfov_deg`` (in water)."""
        fx = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(width, height, fx, fx, (width - 1) / 2.0, (height - 1) / 2.0, **kw)

    @classmethod
    def from_k(cls, width: int, height: int, k, frame_id: str = "camera_optical_frame") -> "CameraModel":
        """From the row-major 3x3 matrix ``K`` of ``sensor_msgs/CameraInfo`` (9 numbers)."""
        k = np.asarray(k, dtype=float).reshape(3, 3)
        return cls(int(width), int(height), float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]), frame_id)

    @classmethod
    def from_camera_info(cls, msg) -> "CameraModel":
        """From any object with the fields of ``sensor_msgs/CameraInfo`` (rclpy or rosbags message).

        The model is an undistorted pinhole: distortion coefficients ``d`` are not used (callers warn).
        """
        k = np.asarray(msg.k, dtype=float)
        if k.size != 9 or not np.isfinite(k).all() or k[0] <= 0 or k[4] <= 0:
            raise ValueError(f"camera_info has an invalid K matrix {list(k)} (uncalibrated camera?)")
        frame = str(getattr(getattr(msg, "header", None), "frame_id", "") or "camera_optical_frame")
        return cls.from_k(int(msg.width), int(msg.height), k, frame)

    def camera_info_fields(self) -> dict:
        """Fields of a ``sensor_msgs/CameraInfo`` for this camera (without header)."""
        return {
            "height": int(self.height), "width": int(self.width), "distortion_model": "plumb_bob",
            "d": [0.0] * 5, "k": [float(v) for v in self.K.ravel()],
            "r": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], "p": [float(v) for v in self.P.ravel()],
        }

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def P(self) -> np.ndarray:
        """3x4 projection matrix of a monocular camera (``CameraInfo.p``)."""
        return np.hstack([self.K, np.zeros((3, 1))])

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.height), int(self.width))

    def ray_norm(self) -> np.ndarray:
        """Per-pixel factor turning planar depth z into Euclidean range: ``r = z * ray_norm``.

        ``sqrt(((u - cx)/fx)^2 + ((v - cy)/fy)^2 + 1)``, float64 array of shape (H, W).
        """
        u = (np.arange(self.width) - self.cx) / self.fx
        v = (np.arange(self.height) - self.cy) / self.fy
        return np.sqrt(u[None, :] ** 2 + v[:, None] ** 2 + 1.0)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Project (N, 3) points in the optical frame to (N, 2) pixel coordinates."""
        p = np.asarray(points_cam, dtype=float)
        return np.stack([self.fx * p[:, 0] / p[:, 2] + self.cx, self.fy * p[:, 1] / p[:, 2] + self.cy], axis=1)

    def scaled(self, factor: float) -> "CameraModel":
        """The same camera at ``factor`` times the resolution (for fast, small test renders)."""
        w, h = max(1, round(self.width * factor)), max(1, round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return CameraModel(w, h, self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5,
                           self.frame_id)

    def binned(self, f: int) -> "CameraModel":
        """The camera of an image binned ``f x f`` from its top-left corner, the last incomplete row and column of
        blocks dropped (as :func:`uw_sil.fit.residuals.box_down` reduces): ``W // f`` x ``H // f`` pixels, each
        the mean of ``f x f``; the intrinsics scale by exactly ``1 / f`` (the crop moves no pixel). Where ``f``
        divides the size it equals ``scaled(1 / f)``; where it does not, ``scaled`` rounds the size instead
        (501 px / 6: 84 against the 83 blocks of the binned image)."""
        f = int(f)
        if f < 1 or self.width < f or self.height < f:
            raise ValueError(f"cannot bin a {self.width}x{self.height} camera by {f}")
        if f == 1:
            return self
        s = 1.0 / f
        return CameraModel(self.width // f, self.height // f, self.fx * s, self.fy * s, (self.cx + 0.5) * s - 0.5,
                           (self.cy + 0.5) * s - 0.5, self.frame_id)
