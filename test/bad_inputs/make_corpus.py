"""The bad-input corpus: damaged, odd or wrong inputs of the ``uw-sil`` command, each with what must happen.

Every case is *generated* (no binaries are kept in the repository): bags are written with
``rosbags`` message by message (so encodings, stamps, calibrations and poses can be anything a
driver or a damaged disk produces), then cut, flipped or emptied as the case says. A case knows the
command line it is tried with and the outcome:

* refused: ``uw-sil`` exits with status 2 and writes exactly one line
  ``uw-sil: error: <input>: <what is wrong>`` (no traceback), matching ``message``, and leaves no
  output behind;
* accepted: ``uw-sil`` exits with status 0 and its output (stdout + stderr) matches ``message``.

``test/test_bad_inputs.py`` runs every case. To look at the files::

    python test/bad_inputs/make_corpus.py [OUT_DIR [CASE ...]]   # default: test/bad_inputs/generated/ (git-ignored)

which writes one folder per case with the inputs and a ``command.txt``.
"""
from __future__ import annotations

import math
import shlex
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

W, H = 64, 48                      # the corpus' camera: small, so fits of accepted cases take a second
T0 = 1_700_000_000_000_000_000     # first stamp (ns)
DT = 100_000_000                   # 10 Hz
IMAGE, INFO, POSE = "/camera/image_raw", "/camera/camera_info", "/panel/pose"
IMAGE_T, CIMAGE_T, INFO_T, POSE_T = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage",
                                     "sensor_msgs/msg/CameraInfo", "geometry_msgs/msg/PoseStamped")
FRAME = "camera_optical_frame"
#: Options that keep the fit of an accepted case short (one frame, two CMA-ES generations).
QUICK_FIT = ["--frames", "1", "--optimizer", "cmaes", "--max-iter", "1"]


@dataclass(frozen=True)
class Case:
    """One corpus entry.

    Attributes
    ----------
    name : str
        Folder name of the case.
    what : str
        The input, in words.
    build : callable(Path) -> list of str
        Writes the inputs into the given (empty) folder; returns the ``uw-sil`` arguments.
    accepted : bool
        True: exit 0 and ``message`` in the output. False: exit 2, one error line matching ``message``.
    message : str
        Regular expression (``re.search``).
    """

    name: str
    what: str
    build: Callable[[Path], list]
    accepted: bool
    message: str


# ------------------------------------------------------------------------------------------ messages


def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_KILTED)


TS = None


def _ts():
    global TS
    if TS is None:
        TS = _typestore()
    return TS


def _header(t: int, frame: str = FRAME):
    T = _ts().types
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9),
                                    frame_id=frame)


def camera(w: int = W, h: int = H):
    from uw_sil.sim.camera import CameraModel

    return CameraModel.from_fov(w, h, 70.0)


def image_msg(t: int, data: bytes, w: int, h: int, encoding: str, step: int, bigendian: int = 0):
    return _ts().types[IMAGE_T](header=_header(t), height=h, width=w, encoding=encoding, is_bigendian=bigendian,
                                step=step, data=np.frombuffer(bytes(data), np.uint8).copy())


def compressed_msg(t: int, data: bytes, fmt: str):
    return _ts().types[CIMAGE_T](header=_header(t), format=fmt, data=np.frombuffer(bytes(data), np.uint8).copy())


def info_msg(t: int, w: int = W, h: int = H, k=None):
    T = _ts().types
    cam = camera(w, h)
    k = cam.K.reshape(-1) if k is None else np.asarray(k, float)
    return T[INFO_T](header=_header(t), height=h, width=w, distortion_model="plumb_bob", d=np.zeros(5), k=k,
                     r=np.eye(3).reshape(-1), p=cam.P.reshape(-1), binning_x=0, binning_y=0,
                     roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                               do_rectify=False))


def pose_msg(t: int, pos, quat):
    T = _ts().types
    p = T["geometry_msgs/msg/Point"](x=float(pos[0]), y=float(pos[1]), z=float(pos[2]))
    q = T["geometry_msgs/msg/Quaternion"](x=float(quat[0]), y=float(quat[1]), z=float(quat[2]), w=float(quat[3]))
    return T[POSE_T](header=_header(t), pose=T["geometry_msgs/msg/Pose"](position=p, orientation=q))


def facing(distance: float = 2.0):
    """Position and quaternion of the panel seen face-on from ``distance`` metres."""
    from uw_sil.sim.scene import facing_pose
    from uw_sil.sim.transforms import matrix_to_pose

    pos, quat = matrix_to_pose(facing_pose(distance))
    return list(pos), list(quat)


def water_image(w: int = W, h: int = H, seed: int = 0) -> np.ndarray:
    """An (h, w, 3) uint8 frame that looks like turbid water with some texture."""
    rng = np.random.default_rng(seed)
    base = np.array([20, 85, 110], float)
    img = base + rng.normal(0, 12, (h, w, 3))
    return np.clip(img, 0, 255).astype(np.uint8)


def frames(n: int = 3, w: int = W, h: int = H, image=None, stamps=None, pos_quat=None, info_k=None,
           info_size=None, topics=(IMAGE, INFO, POSE)):
    """Messages ``(topic, type, log_time, msg)`` of ``n`` frames: image, camera_info and pose per stamp.

    ``image(i, t)`` returns an image message (default: rgb8 water); ``stamps`` the header stamps
    (default every 0.1 s; the log time is always increasing); ``pos_quat`` the pose.
    """
    stamps = [T0 + i * DT for i in range(n)] if stamps is None else stamps
    pos, quat = facing() if pos_quat is None else pos_quat
    iw, ih = info_size or (w, h)
    out = []
    for i, t in enumerate(stamps):
        log = T0 + i * DT
        if image is None:
            img = water_image(w, h, seed=i)
            msg = image_msg(t, img.tobytes(), w, h, "rgb8", 3 * w)
        else:
            msg = image(i, t)
        typ = CIMAGE_T if hasattr(msg, "format") else IMAGE_T
        row = [(IMAGE, typ, log, msg), (INFO, INFO_T, log, info_msg(t, iw, ih, info_k)),
               (POSE, POSE_T, log, pose_msg(t, pos, quat))]
        out += [r for r in row if r[0] in topics]
    return out


def write_bag(path: Path, messages, storage: str = "mcap", topics=None) -> Path:
    """A rosbag2 directory with these messages (``topics``: (name, type) connections to add even if empty)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = _ts()
    conns = {}
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        for topic, typ in topics or ():
            conns[topic] = w.add_connection(topic, typ, typestore=ts)
        for topic, typ, t, msg in messages:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=ts)
            w.write(conns[topic], t, ts.serialize_cdr(msg, typ))
    return path


def storage_file(bag: Path) -> Path:
    (f,) = [p for p in bag.iterdir() if p.suffix in (".mcap", ".db3")]
    return f


# ------------------------------------------------------------------------------------------ argument helpers


def fit(bag, d: Path, *extra) -> list:
    """``uw-sil fit`` of ``bag`` with outputs under ``d/out`` (which must stay absent when refused; no HTML report:
    its figures would take most of the time of an accepted case)."""
    return ["fit", "--bag", str(bag), *QUICK_FIT, "--out", str(d / "out" / "fit.yaml"), *extra]


def synth(d: Path, params: str) -> list:
    return ["synth", "--out", str(d / "out" / "t.mcap"), "--frames", "1", "--width", "32", "--height", "24",
            "--params", params]


def _fit_bag(messages, storage="mcap", topics=None):
    def build(d: Path):
        return fit(write_bag(d / "bag", messages(), storage, topics), d)
    return build


def _encoded(encoding: str, channels: int, step_pad: int = 0, bigendian: int = 0, data_len=None):
    """Images in ``encoding`` (data of ``channels`` bytes per pixel, rows padded by ``step_pad`` bytes)."""
    def image(i, t):
        rng = np.random.default_rng(i)
        step = W * channels + step_pad
        data = rng.integers(0, 256, H * step, dtype=np.uint8).tobytes()
        return image_msg(t, data[: data_len] if data_len else data, W, H, encoding, step, bigendian)
    return lambda: frames(2, image=image)


def _compressed(kind: str):
    def image(i, t):
        import cv2

        rgb = water_image(seed=i)
        if kind == "garbage":
            return compressed_msg(t, b"\xff\xd8\xff\xe0 this is not a JPEG" * 4, "jpeg")
        ok, buf = cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
        assert ok
        return compressed_msg(t, buf.tobytes(), "rgb8; jpeg compressed bgr8")
    return lambda: frames(2, image=image)


def _uniform(value: int, w: int = W, h: int = H):
    def image(i, t):
        return image_msg(t, bytes([value]) * (3 * w * h), w, h, "rgb8", 3 * w)
    return lambda: frames(2, w=w, h=h, image=image)


# ------------------------------------------------------------------------------------------ damaged files


def _standard_bag(d: Path, n: int = 6, storage: str = "mcap", name: str = "bag") -> Path:
    return write_bag(d / name, frames(n), storage)


def truncated_mcap(d: Path, keep: float = 0.6) -> Path:
    bag = _standard_bag(d)
    f = storage_file(bag)
    f.write_bytes(f.read_bytes()[: int(f.stat().st_size * keep)])
    return bag


def _build_truncated_mcap_info(d):
    return ["info", str(truncated_mcap(d))]


def _build_truncated_mcap_fit(d):
    return fit(truncated_mcap(d), d)


def _build_truncated_sqlite(d):
    bag = _standard_bag(d, storage="sqlite3")
    f = storage_file(bag)
    f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
    return fit(bag, d)


def write_mcap_with_crc(path: Path, messages, chunk_size: int = 1024 * 1024) -> Path:
    """A bare .mcap written with the ``mcap`` library, as rosbag2's recorder does: chunks carry a CRC."""
    from mcap.writer import CompressionType, Writer

    ts = _ts()
    with path.open("wb") as fh:
        w = Writer(fh, chunk_size=chunk_size, compression=CompressionType.NONE)
        w.start(profile="ros2", library="uw_sil corpus")
        channels = {}
        for topic, typ, t, msg in messages:
            if topic not in channels:
                sid = w.register_schema(typ, "ros2msg", ts.generate_msgdef(typ, ros_version=2)[0].encode())
                channels[topic] = w.register_channel(topic, "cdr", sid)
            w.add_message(channels[topic], t, bytes(ts.serialize_cdr(msg, typ)), t)
        w.finish()
    return path


def _flip_pixels(f: Path, frame: int, n: int = 8) -> None:
    raw = bytearray(f.read_bytes())
    at = raw.index(water_image(seed=frame).tobytes()) + 100      # inside that frame's pixels
    for k in range(n):
        raw[at + k] ^= 0xFF
    f.write_bytes(bytes(raw))


def _build_flipped_crc_single(d):
    f = write_mcap_with_crc(d / "bag.mcap", frames(4))            # all 4 frames in one chunk
    _flip_pixels(f, 2)
    return fit(f, d)


def _build_flipped_crc_multi(d):
    f = write_mcap_with_crc(d / "bag.mcap", frames(6), chunk_size=4096)   # about one message per chunk
    _flip_pixels(f, 2)
    return fit(f, d, "--frames", "6")


def _build_flipped_record_header(d):
    """A bag written by rosbags (no chunk CRC): the length field of frame 2's image record is flipped."""
    import struct

    bag = _standard_bag(d, n=4)
    f = storage_file(bag)
    raw = bytearray(f.read_bytes())
    pos = 8
    while raw[pos] != 0x06:                                      # the first (only) chunk record
        pos += 9 + struct.unpack_from("<Q", raw, pos + 1)[0]
    c = pos + 9 + 8 + 8 + 8 + 4
    c += 4 + struct.unpack_from("<I", raw, c)[0]                 # compression string
    c += 8                                                       # records length
    n_msg = 0
    while True:
        op, length = raw[c], struct.unpack_from("<Q", raw, c + 1)[0]
        if op == 0x05:
            if n_msg == 6:                                       # image, info, pose per frame: frame 2's image
                raw[c + 8] ^= 0xFF                               # the top byte of the record length
                break
            n_msg += 1
        c += 9 + length
    f.write_bytes(bytes(raw))
    return fit(bag, d, "--frames", "4")


def _build_zero_length(d):
    (d / "t.mcap").write_bytes(b"")
    return fit(d / "t.mcap", d)


def _build_not_a_bag(d):
    (d / "notes.mcap").write_text("field notes, not a recording\n")
    return ["info", str(d / "notes.mcap")]


def _build_no_such_bag(d):
    return fit(d / "nowhere.mcap", d)


def _build_missing_metadata(d):
    bag = _standard_bag(d)
    (bag / "metadata.yaml").unlink()
    return ["info", str(bag)]


def _build_bad_metadata(d):
    bag = _standard_bag(d, n=1)
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [this is: not, {valid\n")
    return ["info", str(bag)]


def _build_4k(d):
    w, h = 3840, 2160
    def image(i, t):
        return image_msg(t, water_image(w, h).tobytes(), w, h, "rgb8", 3 * w)
    return ["info", str(write_bag(d / "bag", frames(1, w=w, h=h, image=image)))]


def _build_panel_behind(d):
    pos, quat = facing(2.0)
    pos = [pos[0], pos[1], -pos[2]]                       # the same distance, behind the camera (z < 0)
    return fit(write_bag(d / "bag", frames(3, pos_quat=(pos, quat))), d)


def _build_zero_frames(d):
    return fit(write_bag(d / "bag", [], topics=[(IMAGE, IMAGE_T), (INFO, INFO_T), (POSE, POSE_T)]), d)


def _swapped_stamps():
    """Neighbours swapped: stamps go back by 0.1 s, within the reader's out-of-order tolerance (lateness)."""
    return frames(5, stamps=[T0 + k * DT for k in (1, 0, 3, 2, 4)])


def _shuffled_stamps():
    """Stamps going back by up to 0.2 s: beyond the tolerance, so some images lose their partners."""
    return frames(5, stamps=[T0 + k * DT for k in (2, 0, 3, 1, 4)])


def _duplicated_stamps():
    return frames(4, stamps=[T0, T0 + DT, T0 + DT, T0 + 2 * DT])


def _poses_late():
    msgs = frames(3)
    out = []
    for topic, typ, t, msg in msgs:
        if topic == POSE:
            late = t + 10 * DT
            msg = pose_msg(late, *facing())
        out.append((topic, typ, t, msg))
    return out


def _noisy_black():
    def image(i, t):
        data = np.random.default_rng(i).integers(0, 2, 3 * W * H, dtype=np.uint8)    # values 0 and 1
        return image_msg(t, data.tobytes(), W, H, "rgb8", 3 * W)
    return frames(2, image=image)


def _build_params_yaml(text: str):
    def build(d: Path):
        (d / "params.yaml").write_text(text)
        return synth(d, str(d / "params.yaml"))
    return build


GOOD_YAML = """# written by uw-sil fit
/**:
  ros__parameters:
    a_r: 0.4
    a_g: 0.12
    a_b: 0.08
    b_r: 0.07
    b_g: 0.33
    b_b: 0.43
    rho_f: 0.1
    fog_mode: exp2
    noise_sigma: 1.5
"""


def _nan_quat():
    pos, _ = facing()
    return frames(2, pos_quat=(pos, [math.nan, 0.0, 0.0, 1.0]))


def _scaled_quat():
    pos, quat = facing()
    return frames(2, pos_quat=(pos, [2.0 * q for q in quat]))


def _zero_quat():
    pos, _ = facing()
    return frames(2, pos_quat=(pos, [0.0, 0.0, 0.0, 0.0]))


BAG = r"\S*bag"        # the bag's path as it appears in messages

CASES = [
    # --- damaged or missing files -------------------------------------------------------------------------
    Case("mcap_truncated_info", "MCAP bag cut at 60 % (recorder lost power)", _build_truncated_mcap_info, True,
         r"TRUNCATED/DAMAGED: \d+ of \d+ bytes unreadable(.|\n)*lost: \{'/camera/image_raw': 3, '/camera/camera_info': 3"),
    Case("mcap_truncated_fit", "fit on the cut MCAP bag: the intact frames are used, the loss reported",
         _build_truncated_mcap_fit, True, r"warning: \S*bag: cut off or damaged: \d+ of \d+ bytes unreadable; lost "
                                         r"\{'/camera/image_raw': 3, .*; fitting the intact frames"),
    Case("sqlite_truncated", "sqlite3 bag cut in half", _build_truncated_sqlite, False,
         BAG + r": cannot open sqlite3 bag: .*\.recover"),
    Case("mcap_flipped_crc_single", "8 pixel bytes flipped in the only chunk of an MCAP file with chunk CRCs",
         _build_flipped_crc_single, False, BAG + r"\.mcap: no frame could be read: .*CRC mismatch; chunk skipped"),
    Case("mcap_flipped_crc_multi", "8 pixel bytes flipped in one of many CRC-checked chunks: that frame is lost",
         _build_flipped_crc_multi, True, r"warning: \S*bag\.mcap is cut off or damaged: read \d+ complete messages.*"
                                         r"CRC mismatch; chunk skipped"),
    Case("mcap_flipped_record_header", "a flipped record length inside the chunk of a bag without chunk CRCs",
         _build_flipped_record_header, True, r"warning: \S*bag\.mcap is cut off or damaged: .*malformed records"),
    Case("zero_length", "a zero-length .mcap file", _build_zero_length, False,
         r"t\.mcap: not a ROS 2 bag: an empty file"),
    Case("not_a_bag", "a text file named .mcap", _build_not_a_bag, False,
         r"notes\.mcap: not a ROS 2 bag: neither an MCAP nor an SQLite file"),
    Case("no_such_bag", "a bag that does not exist", _build_no_such_bag, False, r"nowhere\.mcap: does not exist \(expected a bag directory"),
    Case("missing_metadata", "bag directory without metadata.yaml (recording not closed)", _build_missing_metadata,
         True, r"metadata\.yaml missing: storage files read directly"),
    Case("bad_metadata", "metadata.yaml that is not YAML", _build_bad_metadata, False,
         r"metadata\.yaml: not a readable rosbag2 metadata file: YAML syntax error: expected ',' or '}', but got "
         r"'<stream end>' \(line 2, column 1\)"),
    # --- topics and frame counts -------------------------------------------------------------------------
    Case("no_images", "bag without the image topic", _fit_bag(lambda: frames(2, topics=(INFO, POSE))), False,
         BAG + r": topic '/camera/image_raw' is not in the bag; it has: /camera/camera_info"),
    Case("no_poses", "bag without the pose topic", _fit_bag(lambda: frames(2, topics=(IMAGE, INFO))), False,
         BAG + r": topic '/panel/pose' is not in the bag; it has: /camera/camera_info"),
    Case("zero_frames", "bag with the three topics and no message", _build_zero_frames, False,
         BAG + r": topic '/camera/image_raw' has no messages"),
    Case("one_frame", "bag of a single frame", _fit_bag(lambda: frames(1)), True, r"wrote .*fit\.yaml"),
    # --- image encodings and layouts ---------------------------------------------------------------------
    Case("enc_bgr8", "bgr8 images", _fit_bag(_encoded("bgr8", 3)), True, r"wrote .*fit\.yaml"),
    Case("enc_mono8", "mono8 images", _fit_bag(_encoded("mono8", 1)), True, r"wrote .*fit\.yaml"),
    Case("enc_rgba8", "rgba8 images", _fit_bag(_encoded("rgba8", 4)), True, r"wrote .*fit\.yaml"),
    Case("enc_16UC1", "16UC1 (16-bit depth) images on the image topic", _fit_bag(_encoded("16UC1", 2)), False,
         BAG + r": /camera/image_raw at stamp \d+ ns: unsupported image encoding '16UC1'; supported: rgb8, bgr8"),
    Case("enc_yuv422", "yuv422 images", _fit_bag(_encoded("yuv422", 2)), False,
         BAG + r": /camera/image_raw at stamp \d+ ns: unsupported image encoding 'yuv422'"),
    Case("enc_compressed", "sensor_msgs/CompressedImage (JPEG) on the image topic", _fit_bag(_compressed("jpeg")),
         True, r"wrote .*fit\.yaml"),
    Case("compressed_garbage", "CompressedImage whose bytes are not an image", _fit_bag(_compressed("garbage")),
         False, BAG + r": /camera/image_raw at stamp \d+ ns: OpenCV could not decode the compressed image"),
    Case("row_padding", "rgb8 rows padded to step = width*3 + 16", _fit_bag(_encoded("rgb8", 3, step_pad=16)), True,
         r"wrote .*fit\.yaml"),
    Case("is_bigendian", "rgb8 with is_bigendian = 1 (byte order does not apply to 8-bit data)",
         _fit_bag(_encoded("rgb8", 3, bigendian=1)), True, r"wrote .*fit\.yaml"),
    Case("short_data", "rgb8 image with 10 bytes missing", _fit_bag(_encoded("rgb8", 3, data_len=3 * W * H - 10)),
         False, BAG + r": /camera/image_raw at stamp \d+ ns: image data has 9206 bytes, expected step\*height"),
    # --- calibration and poses ---------------------------------------------------------------------------
    Case("info_size_mismatch", "camera_info says 32x24, images are 64x48",
         _fit_bag(lambda: frames(2, info_size=(32, 24))), False,
         BAG + r": /camera/image_raw at stamp \d+ ns is 64x48 but /camera/camera_info says 32x24"),
    Case("zero_K", "camera_info with an all-zero K (uncalibrated)", _fit_bag(lambda: frames(2, info_k=np.zeros(9))),
         False, BAG + r": /camera/camera_info at stamp \d+ ns is not a usable calibration .*fx"),
    Case("nan_quaternion", "pose with a NaN quaternion", _fit_bag(_nan_quat), False,
         BAG + r": /panel/pose at stamp \d+ ns: invalid quaternion"),
    Case("zero_quaternion", "pose with the quaternion (0, 0, 0, 0)", _fit_bag(_zero_quat), False,
         BAG + r": /panel/pose at stamp \d+ ns: invalid quaternion"),
    Case("scaled_quaternion", "pose with a non-unit quaternion (2x a unit one): normalized",
         _fit_bag(_scaled_quat), True, r"wrote .*fit\.yaml"),
    Case("panel_behind_camera", "the panel 2 m behind the camera", _build_panel_behind, False,
         BAG + r": panel not visible in any of the first 3 frames; 3 skipped, e.g. frame 0: the panel is behind "
               r"the camera \(its origin at z = -2\.00 m"),
    # --- stamps ------------------------------------------------------------------------------------------
    Case("stamps_out_of_order", "header stamps of neighbours swapped (0.1 s back; log times increasing)",
         _fit_bag(_swapped_stamps), True, r"wrote .*fit\.yaml"),
    Case("stamps_far_out_of_order", "header stamps 0.2 s back: beyond the out-of-order tolerance",
         lambda d: fit(write_bag(d / "bag", _shuffled_stamps()), d, "--frames", "5"), True,
         r"warning: /camera/image_raw: header stamps go back in time by more than the out-of-order tolerance "
         r"\(0\.1 s; first at stamp \d+ ns, 0\.200 s back\)(.|\n)*warning: \S*bag: 2 of 5 images had no "
         r"camera_info/pose within tolerance and were dropped"),
    Case("stamps_duplicated", "two frames with the same stamp", _fit_bag(_duplicated_stamps), True,
         r"wrote .*fit\.yaml"),
    Case("stamps_no_partner", "poses stamped 1 s after their images", _fit_bag(_poses_late), False,
         BAG + r": no frame could be read: none of the 3 images has a camera_info and a pose within the stamp "
               r"tolerance"),
    # --- image sizes and contents ------------------------------------------------------------------------
    Case("tiny_8x8", "8x8 images", _fit_bag(lambda: frames(2, w=8, h=8, image=lambda i, t: image_msg(
        t, water_image(8, 8, i).tobytes(), 8, 8, "rgb8", 24))), False,
         BAG + r": image 8x8 is too small for 10x10 regions"),
    Case("image_4k", "one 3840x2160 frame (info; fitting it takes minutes)", _build_4k, True,
         r"/camera/image_raw \[sensor_msgs/msg/Image\] 1"),
    Case("all_black", "all-black frames", _fit_bag(_uniform(0)), False,
         BAG + r": no usable frame among the first 2 frames; 2 skipped, e.g. frame 0: the frame is uniform "
               r"\(every pixel 0, 0, 0\): nothing to fit"),
    Case("nearly_black", "black frames with 1 grey level of noise", _fit_bag(_noisy_black), False,
         BAG + r": no usable frame among the first 2 frames; 2 skipped, e.g. frame 0: the frame is nearly "
               r"uniform \(mean 0\.\d, 0\.\d, 0\.\d, standard deviation below 1 grey level\): nothing to fit"),
    Case("all_white", "all-white (saturated) frames", _fit_bag(_uniform(255)), False,
         BAG + r": no usable frame among the first 2 frames; 2 skipped, e.g. frame 0: the frame is uniform "
               r"\(every pixel 255, 255, 255\): nothing to fit"),
    # --- parameters --------------------------------------------------------------------------------------
    Case("params_not_a_number", "--params a_r=abc", lambda d: synth(d, "a_r=abc"), False,
         r"--params: a_r must be a number, got 'abc'"),
    Case("params_unknown_name", "--params a_x=0.1", lambda d: synth(d, "a_x=0.1"), False,
         r"--params: unknown parameter 'a_x'; known: a_r, a_g, a_b, b_r, b_g, b_b, rho_f"),
    Case("params_out_of_bounds", "--params b_g=1.5", lambda d: synth(d, "b_g=1.5"), False,
         r"--params: parameter b_g = 1\.5 outside \[0, 1\]"),
    Case("params_nan", "--params rho_f=nan", lambda d: synth(d, "rho_f=nan"), False,
         r"--params: parameter rho_f is not finite"),
    Case("params_count", "--params with 3 numbers", lambda d: synth(d, "0.1,0.2,0.3"), False,
         r"--params: 3 numbers given, 7 needed \(a_r, a_g, a_b, b_r, b_g, b_b, rho_f\)"),
    Case("params_yaml_good", "a parameters file written by uw-sil fit", _build_params_yaml(GOOD_YAML), True,
         r"wrote bag .*\(1 frames\)"),
    Case("params_yaml_malformed", "parameters file that is not YAML", _build_params_yaml("/**: [ros__parameters: {\n"),
         False, r"params\.yaml: not a valid YAML file"),
    Case("params_yaml_out_of_bounds", "parameters file with b_r: 1.5",
         _build_params_yaml(GOOD_YAML.replace("b_r: 0.07", "b_r: 1.5")), False,
         r"params\.yaml: parameter b_r = 1\.5 outside \[0, 1\]"),
    Case("params_yaml_missing", "parameters file without rho_f",
         _build_params_yaml(GOOD_YAML.replace("    rho_f: 0.1\n", "")), False,
         r"params\.yaml: missing parameters: rho_f"),
    Case("params_yaml_not_ros", "YAML that is not a ROS 2 parameters file", _build_params_yaml("a_r: 0.4\n"), False,
         r"params\.yaml: not a ROS 2 parameters file: expected <node>: \{ros__parameters: \{\.\.\.\}\}"),
    Case("params_yaml_not_number", "parameters file with a_g: high",
         _build_params_yaml(GOOD_YAML.replace("a_g: 0.12", "a_g: high")), False,
         r"params\.yaml: a_g must be a number, got 'high'"),
    # --- option values -----------------------------------------------------------------------------------
    Case("fit_frames_zero", "fit --frames 0", lambda d: fit(_standard_bag(d, n=1), d, "--frames", "0"), False,
         r"--frames: must be >= 1, got 0"),
    Case("fit_sim_noise_word", "fit --sim-noise loud", lambda d: fit(_standard_bag(d, n=1), d, "--sim-noise", "loud"),
         False, r"--sim-noise: must be 'estimate', 'none' or a number of grey levels, got 'loud'"),
]


# ------------------------------------------------------------------------------------------ library inputs


@dataclass(frozen=True)
class LibraryCase:
    """Bad input of a library function (no file involved): ``call()`` raises ValueError matching ``message``,
    or, when ``message`` is None, returns a value for which ``check(value)`` is true."""

    name: str
    what: str
    call: Callable[[], object]
    message: str | None
    check: Callable[[object], bool] | None = None


def _scene(depth_value=None, range_value=None):
    """A 2x2 clean render at 2 m with one pixel's depth (and range) replaced."""
    rgb = np.full((2, 2, 3), 0.5, np.float32)
    depth = np.full((2, 2), 2.0, np.float32)
    rng = depth.copy()
    if depth_value is not None:
        depth[0, 1] = depth_value
    if range_value is not None:
        rng[0, 1] = range_value
    return rgb, rng, depth


PARAMS = [0.4, 0.1, 0.08, 0.05, 0.3, 0.4, 0.1]


def _degrade(**kw):
    from uw_sil.sim.optics import degrade

    return degrade(*_scene(**kw), PARAMS)


def _transmission(r, a=(0.4, 0.1, 0.08)):
    from uw_sil.sim.optics import transmission

    return transmission(np.asarray(r, float), a)


def _fog(z):
    from uw_sil.sim.optics import fog_factor

    return fog_factor(np.asarray(z, float), 0.1)


def _space(lower, upper):
    from uw_sil.sim.params import ParamSpace

    return ParamSpace("rgb", lower, upper)


def _optimize(lower, upper):
    from uw_sil.fit.optimize import optimize

    return optimize(lambda X: -np.sum(X ** 2, axis=1), lower, upper, names=["x", "y"])


_LO, _HI = [0.0] * 7, [1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.5]

LIBRARY_CASES = [
    LibraryCase("depth_nan", "degrade() with a NaN depth", lambda: _degrade(depth_value=np.nan),
                r"depth has 1 NaN and 0 negative value\(s\) \(first at index \(0, 1\): nan\): must be >= 0 metres"),
    LibraryCase("depth_negative", "degrade() with a depth of -1 m", lambda: _degrade(depth_value=-1.0),
                r"depth has 0 NaN and 1 negative value\(s\) \(first at index \(0, 1\): -1\.0\)"),
    LibraryCase("depth_minus_inf", "degrade() with a depth of -inf", lambda: _degrade(depth_value=-np.inf),
                r"depth has 0 NaN and 1 negative value\(s\) \(first at index \(0, 1\): -inf\)"),
    LibraryCase("range_nan", "degrade() with a NaN range", lambda: _degrade(range_value=np.nan),
                r"range has 1 NaN and 0 negative value\(s\)"),
    LibraryCase("depth_inf", "degrade() with +inf range and depth (nothing hit): the background",
                lambda: _degrade(depth_value=np.inf, range_value=np.inf), None,
                lambda out: np.allclose(out[0, 1], PARAMS[3:6]) and np.isfinite(out).all()),
    LibraryCase("transmission_negative_range", "transmission() of a range of -2 m", lambda: _transmission([1.0, -2.0]),
                r"range has 0 NaN and 1 negative value\(s\) \(first at index \(1,\): -2\.0\)"),
    LibraryCase("transmission_negative_attenuation", "transmission() with a_g = -0.1",
                lambda: _transmission([1.0], (0.4, -0.1, 0.08)), r"attenuation must be finite and >= 0"),
    LibraryCase("fog_nan_depth", "fog_factor() of a NaN depth", lambda: _fog([np.nan]), r"depth has 1 NaN"),
    LibraryCase("bounds_inverted", "ParamSpace with lower and upper swapped", lambda: _space(_HI, _LO),
                r"empty or inverted bounds for a_r: \[1, 0\]"),
    LibraryCase("bounds_empty", "ParamSpace with lower = upper for rho_f",
                lambda: _space(_LO, _HI[:6] + [0.0]), r"empty or inverted bounds for rho_f: \[0, 0\]"),
    LibraryCase("bounds_unphysical", "ParamSpace with b_g up to 2", lambda: _space(_LO, _HI[:4] + [2.0] + _HI[5:]),
                r"bounds of b_g \[0, 2\] leave the physical range \[0, 1\]"),
    LibraryCase("optimize_inverted", "optimize() with y in [1, 0]", lambda: _optimize([0.0, 1.0], [1.0, 0.0]),
                r"y\b.*inverted bounds, need lower < upper, got \[1\.0, 0\.0\]"),
]


def build(case: Case, root: Path) -> list:
    """Generate ``case`` into ``root / case.name`` (emptied first); return its ``uw-sil`` arguments."""
    d = Path(root) / case.name
    if d.exists():
        shutil.rmtree(d)
    d.mkdir(parents=True)
    args = case.build(d)
    (d / "command.txt").write_text("uw-sil " + " ".join(shlex.quote(a) for a in args) + "\n"
                                   + f"# {case.what}\n# expected: {'accepted' if case.accepted else 'refused'}: "
                                     f"{case.message}\n")
    return args


def main(argv=None) -> int:
    """``make_corpus.py [OUT_DIR [CASE ...]]``: generate all cases, or the named ones."""
    argv = sys.argv[1:] if argv is None else argv
    root = Path(argv[0]) if argv else Path(__file__).resolve().parent / "generated"
    names = set(argv[1:])
    unknown = names - {c.name for c in CASES}
    if unknown:
        print(f"make_corpus.py: error: unknown case(s): {', '.join(sorted(unknown))}", file=sys.stderr)
        return 2
    chosen = [c for c in CASES if not names or c.name in names]
    for case in chosen:
        build(case, root)
        print(f"{case.name:28s} {'accepted' if case.accepted else 'refused '}  {case.what}")
    print(f"{len(chosen)} cases in {root}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))   # the repository's uw_sil
    sys.exit(main())
