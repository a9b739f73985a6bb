"""Write synthetic trials as ROS 2 bags (the layout ``ros2 bag record`` makes).

Layout written by :func:`write_trial` (a rosbag2 directory)::

    write_trial("trial.mcap", ...)   ->  trial/metadata.yaml + trial/trial.mcap
    write_trial("trial.db3", ...)    ->  trial/metadata.yaml + trial/trial.db3
    write_trial("trial", ...)        ->  trial/metadata.yaml + trial/trial.mcap   (storage="mcap")

so ``uw-sil synth --out trial.mcap`` gives a bag that ``ros2 bag play trial`` and ``ros2 bag info
trial`` accept; the suffix of ``--out`` only picks the storage. Messages are serialized with
``rosbags`` in CDR (rclpy's wire format) with the message definitions of ROS 2 Kilted.
"""
from __future__ import annotations

import math
import shutil
from pathlib import Path
from typing import Iterable

import numpy as np

from ..sim.camera import CameraModel
from ..sim.transforms import matrix_to_pose
from .imgmsg import rgb_to_compressed
from .records import (CAMERA_INFO_TYPE, COMPRESSED_IMAGE_TYPE, IMAGE_TYPE, POSE_TYPE, ROSBAG2_VERSION, STORAGE_SUFFIX,
                      TF_TYPE, Sample)

__all__ = ["write_trial", "MAX_STAMP_NS"]

#: Latest stamp a ROS 2 header can carry: ``builtin_interfaces/Time`` has an int32 ``sec``.
MAX_STAMP_NS = (2**31 - 1) * 1_000_000_000 + 999_999_999



def _bag_dir_and_storage(path, storage: str | None) -> tuple[Path, str]:
    p = Path(path)
    by_suffix = {".mcap": "mcap", ".db3": "sqlite3"}.get(p.suffix)
    if storage is not None and storage not in STORAGE_SUFFIX:
        raise ValueError(f"storage must be 'mcap' or 'sqlite3', got {storage!r}")
    if by_suffix is not None:
        if storage is not None and storage != by_suffix:
            raise ValueError(f"output {p.name} asks for {by_suffix} storage but storage={storage!r}")
        d = p.with_suffix("")
        if not d.name:
            raise ValueError(f"cannot name a bag after {p}")
        return d, by_suffix
    return p, storage or "mcap"


def _looks_like_bag_dir(d: Path) -> bool:
    """Only metadata.yaml and storage files (and SQLite side files) in it."""
    return d.is_dir() and all(
        f.is_file() and (f.name == "metadata.yaml" or f.suffix in (".mcap", ".db3")
                         or f.name.endswith((".db3-shm", ".db3-wal", ".db3-journal")))
        for f in d.iterdir())


#: The layout rules as public names, for other writers of bags (:mod:`uw_sil.bags.augment`).
bag_dir_and_storage = _bag_dir_and_storage
looks_like_bag_dir = _looks_like_bag_dir


def _check_sample(s: Sample, i: int) -> tuple[np.ndarray, np.ndarray]:
    if not isinstance(s, Sample):
        raise TypeError(f"sample {i} is a {type(s).__name__}, expected uw_sil.bags.Sample")
    stamp = s.stamp_ns
    if isinstance(stamp, bool) or not isinstance(stamp, (int, np.integer)) or not 0 <= stamp <= MAX_STAMP_NS:
        raise ValueError(f"sample {i}: stamp_ns must be an integer in [0, {MAX_STAMP_NS}] (a header stamp's sec is "
                         f"an int32), got {s.stamp_ns!r}")
    img = np.asarray(s.image)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"sample {i}: image must be (H, W, 3) uint8 RGB, got {img.dtype} {img.shape}")
    if not isinstance(s.camera, CameraModel):
        raise TypeError(f"sample {i}: camera must be a CameraModel")
    if img.shape[:2] != s.camera.shape:
        raise ValueError(f"sample {i}: image is {img.shape[1]}x{img.shape[0]} but the camera is "
                         f"{s.camera.width}x{s.camera.height}")
    T = np.asarray(s.pose, dtype=float)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"sample {i}: pose must be a finite 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    if (not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or not math.isclose(np.linalg.det(R), 1.0, abs_tol=1e-6)
            or not np.allclose(T[3], [0, 0, 0, 1])):
        raise ValueError(f"sample {i}: pose is not a rigid transform (rotation not orthonormal or bad last row)")
    return img, T


def write_trial(path, samples: Iterable[Sample], storage: str | None = None,
                image_topic: str = "/camera/image_raw", info_topic: str | None = "/camera/camera_info",
                pose_topic: str | None = "/panel/pose", write_tf: bool = True, camera_frame: str | None = None,
                panel_frame: str = "panel", tf_topic: str = "/tf", overwrite: bool = False,
                image_format: str = "raw", jpeg_quality: int = 95, tf_static=(), tf_dynamic=(),
                tf_static_topic: str = "/tf_static", calibration=None) -> Path:
    """Write samples to a ROS 2 bag that ``ros2 bag play`` accepts (streaming).

    Parameters
    ----------
    path : str or Path
        ``trial.mcap`` or ``trial.db3`` write the bag directory ``trial/`` (with ``trial/trial.mcap``
        or ``trial/trial.db3`` and ``metadata.yaml``), the suffix choosing the storage; a path
        without these suffixes is the bag directory itself.
    samples : iterable of Sample
        Consumed one at a time (a generator of rendered frames is never held in memory).
    storage : {'mcap', 'sqlite3'}, optional
        Default: from the suffix, else ``'mcap'``. Must agree with the suffix.
    image_topic, info_topic, pose_topic : str
        ``sensor_msgs/Image`` (rgb8) or ``sensor_msgs/CompressedImage`` (see ``image_format``),
        ``sensor_msgs/CameraInfo`` (plumb_bob, zero distortion, identity R), ``geometry_msgs/PoseStamped``
        (panel pose in the camera optical frame). All share the sample's stamp, as header stamp and as
        bag receive time. ``info_topic=None`` / ``pose_topic=None``: not written (a field bag without
        camera_info or pose).
    write_tf : bool
        Also write ``tf2_msgs/TFMessage`` on ``tf_topic``: ``camera_frame -> panel_frame``.
    image_format : {'raw', 'jpeg', 'png'}
        ``raw``: ``sensor_msgs/Image`` rgb8; otherwise ``sensor_msgs/CompressedImage`` (format ``"jpeg"`` /
        ``"png"``, as ``compressed_image_transport`` writes; JPEG at ``jpeg_quality``).
    tf_static : sequence of (parent, child, 4x4)
        Written once on ``tf_static_topic`` at the first sample's stamp.
    tf_dynamic : iterable of (stamp_ns, parent, child, 4x4), sorted by stamp
        Written on ``tf_topic``, merged in time with the samples (a transform is written before the
        first sample stamped at or after it; the rest after the last sample).
    calibration : CameraCalibration, optional
        Written into camera_info (``d``, ``r``, ``p`` and its distortion model) instead of an undistorted
        pinhole; its size and ``K`` must be the samples' camera.
    camera_frame : str, optional
        ``header.frame_id`` of all messages; default each sample's ``frame_id``.
    panel_frame : str
        ``child_frame_id`` of the transform.
    overwrite : bool
        Replace an existing bag directory (only if it holds nothing but bag files).

    Returns
    -------
    Path
        The bag directory.

    Notes
    -----
    Samples are validated as they come (RGB uint8 of the camera's size, rigid 4x4 pose, integer
    stamp). If a sample is invalid or ``samples`` raises, the exception propagates and the partial
    bag directory is removed (``rosbags`` would leave it without ``metadata.yaml`` and without the
    frames still buffered in its last chunk or transaction).
    """
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    bag_dir, storage = _bag_dir_and_storage(path, storage)
    if image_format not in ("raw", "jpeg", "png"):
        raise ValueError(f"image_format must be 'raw', 'jpeg' or 'png', got {image_format!r}")
    tf_static, tf_dynamic = list(tf_static), list(tf_dynamic)
    topics = ([image_topic] + [t for t in (info_topic, pose_topic) if t]
              + ([tf_topic] if write_tf or tf_dynamic else []) + ([tf_static_topic] if tf_static else []))
    if len(set(topics)) != len(topics):
        raise ValueError(f"topics must differ, got {topics}")
    if camera_frame is not None and not camera_frame:
        raise ValueError("camera_frame must be a non-empty frame name")
    if write_tf and not panel_frame:
        raise ValueError("panel_frame must be a non-empty frame name")
    it = iter(samples)
    first = next(it, None)
    if first is None:
        raise ValueError("write_trial got no samples")
    if bag_dir.exists():
        if not overwrite:
            raise FileExistsError(f"{bag_dir} exists (pass overwrite=True to replace it)")
        if not _looks_like_bag_dir(bag_dir):
            raise FileExistsError(f"{bag_dir} exists and holds files that are not bag files: not replacing it")
        shutil.rmtree(bag_dir)
    bag_dir.parent.mkdir(parents=True, exist_ok=True)

    ts = get_typestore(Stores.ROS2_KILTED)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    opened: list = []  # set once the writer has created bag_dir: only then is it ours to remove
    try:
        _write(Writer(bag_dir, version=ROSBAG2_VERSION, storage_plugin=plugin), opened, ts, first, it,
               image_topic, info_topic, pose_topic, tf_topic if write_tf else None, camera_frame, panel_frame,
               _ImageEncoder(image_format, jpeg_quality), tf_topic, tf_static_topic, tf_static, tf_dynamic,
               calibration)
    except BaseException:
        if opened:
            shutil.rmtree(bag_dir, ignore_errors=True)
        raise
    return bag_dir


class _ImageEncoder:
    """Sample image -> (message type, message) for the writer: raw rgb8 or compressed."""

    def __init__(self, fmt: str, quality: int):
        if not 1 <= int(quality) <= 100:
            raise ValueError(f"jpeg_quality must be in 1..100, got {quality}")
        self.fmt, self.quality = fmt, int(quality)
        self.msgtype = IMAGE_TYPE if fmt == "raw" else COMPRESSED_IMAGE_TYPE

    def __call__(self, T_, hdr, img):
        if self.fmt == "raw":
            h, wd = img.shape[:2]
            return T_[IMAGE_TYPE](header=hdr, height=h, width=wd, encoding="rgb8", is_bigendian=0, step=3 * wd,
                                  data=np.ascontiguousarray(img).reshape(-1))
        data = rgb_to_compressed(img, self.fmt, self.quality)
        return T_[COMPRESSED_IMAGE_TYPE](header=hdr, format=self.fmt, data=np.frombuffer(data, np.uint8))


def _write(writer, opened, ts, first, it, image_topic, info_topic, pose_topic, tf_topic, camera_frame, panel_frame,
           encoder, tree_tf_topic, tf_static_topic, tf_static, tf_dynamic, calibration):
    T_ = ts.types
    Header, Time = T_["std_msgs/msg/Header"], T_["builtin_interfaces/msg/Time"]
    CameraInfo, ROI = T_[CAMERA_INFO_TYPE], T_["sensor_msgs/msg/RegionOfInterest"]
    PoseStamped, Pose = T_[POSE_TYPE], T_["geometry_msgs/msg/Pose"]
    Point, Quaternion, Vector3 = (T_["geometry_msgs/msg/Point"], T_["geometry_msgs/msg/Quaternion"],
                                  T_["geometry_msgs/msg/Vector3"])
    TransformStamped, Transform, TFMessage = (T_["geometry_msgs/msg/TransformStamped"],
                                              T_["geometry_msgs/msg/Transform"], T_[TF_TYPE])

    def header(t, frame):
        return Header(stamp=Time(sec=t // 1_000_000_000, nanosec=t % 1_000_000_000), frame_id=frame)

    def transform(t, parent, child, M):
        pos, quat = matrix_to_pose(np.asarray(M, dtype=float))
        return TransformStamped(header=header(int(t), parent), child_frame_id=child,
                                transform=Transform(translation=Vector3(x=pos[0], y=pos[1], z=pos[2]),
                                                    rotation=Quaternion(x=quat[0], y=quat[1], z=quat[2], w=quat[3])))

    with writer as w:
        opened.append(True)
        w.set_custom_data("generator", "uw_sil.bags.writer.write_trial")
        c_img = w.add_connection(image_topic, encoder.msgtype, typestore=ts)
        c_info = w.add_connection(info_topic, CAMERA_INFO_TYPE, typestore=ts) if info_topic else None
        c_pose = w.add_connection(pose_topic, POSE_TYPE, typestore=ts) if pose_topic else None
        c_tf = w.add_connection(tf_topic, TF_TYPE, typestore=ts) if tf_topic is not None else None
        c_tree = c_tf
        if tf_dynamic and c_tree is None:
            c_tree = w.add_connection(tree_tf_topic, TF_TYPE, typestore=ts)
        c_static = None
        if tf_static:
            c_static = w.add_connection(tf_static_topic, TF_TYPE, typestore=ts, offered_qos_profiles=[_latched_qos()])
        pending = iter(tf_dynamic)
        nxt = next(pending, None)
        i = 0
        for s in _chain(first, it):
            img, T = _check_sample(s, i)
            frame = camera_frame if camera_frame is not None else s.frame_id
            if not frame:
                raise ValueError(f"sample {i} has an empty frame_id (and no camera_frame was given)")
            t = int(s.stamp_ns)
            if i == 0 and c_static is not None:
                msg = TFMessage(transforms=[transform(t, p, c, M) for p, c, M in tf_static])
                w.write(c_static, t, ts.serialize_cdr(msg, TF_TYPE))
            while nxt is not None and int(nxt[0]) <= t:
                w.write(c_tree, int(nxt[0]), ts.serialize_cdr(TFMessage(transforms=[transform(*nxt)]), TF_TYPE))
                nxt = next(pending, None)
            hdr = header(t, frame)
            w.write(c_img, t, ts.serialize_cdr(encoder(T_, hdr, img), encoder.msgtype))
            cam = s.camera
            if c_info is not None:
                if calibration is None:
                    model, d, r, p = "plumb_bob", np.zeros(5), np.eye(3), cam.P
                else:
                    if cam.shape != calibration.shape or not np.allclose(cam.K, calibration.K):
                        raise ValueError(f"sample {i}: its camera is not the calibration's (size or K differ)")
                    model, d, r, p = calibration.distortion_model, calibration.D, calibration.R, calibration.P
                info_msg = CameraInfo(header=hdr, height=cam.height, width=cam.width, distortion_model=model,
                                      d=np.asarray(d, dtype=float), k=cam.K.reshape(-1), r=np.asarray(r).reshape(-1),
                                      p=np.asarray(p).reshape(-1), binning_x=0, binning_y=0,
                                      roi=ROI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
                w.write(c_info, t, ts.serialize_cdr(info_msg, CAMERA_INFO_TYPE))
            pos, quat = matrix_to_pose(T)
            if c_pose is not None:
                pose_msg = PoseStamped(header=hdr, pose=Pose(position=Point(x=pos[0], y=pos[1], z=pos[2]),
                                                             orientation=Quaternion(x=quat[0], y=quat[1], z=quat[2],
                                                                                    w=quat[3])))
                w.write(c_pose, t, ts.serialize_cdr(pose_msg, POSE_TYPE))
            if c_tf is not None:
                w.write(c_tf, t, ts.serialize_cdr(TFMessage(transforms=[transform(t, frame, panel_frame, T)]), TF_TYPE))
            i += 1
        while nxt is not None:
            w.write(c_tree, int(nxt[0]), ts.serialize_cdr(TFMessage(transforms=[transform(*nxt)]), TF_TYPE))
            nxt = next(pending, None)


def _latched_qos():
    """Offered QoS of /tf_static as tf2's static broadcaster has it (transient local), so that
    ``ros2 bag play`` republishes it latched."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    zero = QosTime(0, 0)
    return Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, zero, zero,
               QosLiveliness.AUTOMATIC, zero, False)


def _chain(first, rest):
    yield first
    yield from rest
