"""Rigid transforms: 4x4 homogeneous matrices <-> (position, quaternion x y z w) as in geometry_msgs/Pose."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["pose_to_matrix", "matrix_to_pose", "look_at"]


def pose_to_matrix(position, quaternion_xyzw) -> np.ndarray:
    """4x4 transform from a position (3,) and a unit quaternion (x, y, z, w) (normalized here)."""
    q = np.asarray(quaternion_xyzw, dtype=float)
    n = np.linalg.norm(q)
    if q.shape != (4,) or not np.isfinite(q).all() or n < 1e-9:
        raise ValueError(f"invalid quaternion {quaternion_xyzw!r}")
    t = np.asarray(position, dtype=float)
    if t.shape != (3,) or not np.isfinite(t).all():
        raise ValueError(f"invalid position {position!r}")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q / n).as_matrix()
    T[:3, 3] = t
    return T


def matrix_to_pose(T) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,), quaternion x y z w (4,)) of a 4x4 rigid transform."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"expected a 4x4 matrix, got shape {T.shape}")
    return T[:3, 3].copy(), Rotation.from_matrix(T[:3, :3]).as_quat()


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """Camera-optical-frame pose (z forward, x right, y down) at ``eye`` looking at ``target``.

    Returns the 4x4 transform from the optical frame to the world frame (T_world_cam).
    ``up`` is the world direction that should appear up in the image (-y of the optical frame).
    """
    eye, target, up = (np.asarray(x, dtype=float) for x in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(-up, z)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T
