"""Tests of uw_sil.bags.reader, uw_sil.bags.mcap_recover and uw_sil.bags.imgmsg: ROS 2 bag round trips, rclpy wire
compatibility, recovery of cut-off MCAP files, and clear errors for bad bags."""
import logging
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from uw_sil.bags import (BagError, Sample, iter_messages, iter_raw, open_bag, read_samples, resolve_bag_path,
                         write_trial)
from uw_sil.sim.camera import CameraModel
from uw_sil.bags.imgmsg import SUPPORTED_ENCODINGS, image_to_rgb, rgb_to_image_fields
from uw_sil.bags.mcap_recover import McapScanReport, iter_mcap
from uw_sil.sim.transforms import pose_to_matrix

W, H = 64, 48
CAM = CameraModel.from_fov(W, H, 70.0)
T0 = 1_700_000_000_123_456_789
DT = 100_000_000
FRAME = "camera_optical_frame"


def make_samples(n, w=W, h=H, seed=0, t0=T0):
    rng = np.random.default_rng(seed)
    cam = CAM if (w, h) == (W, H) else CameraModel.from_fov(w, h, 70.0)
    out = []
    for i in range(n):
        q = rng.normal(size=4)
        T = pose_to_matrix([0.1 * i, -0.05, 3.0 - 0.1 * i], q)
        out.append(Sample(t0 + i * DT, rng.integers(0, 256, (h, w, 3), dtype=np.uint8), cam, T, FRAME))
    return out


def typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_KILTED)


def ros_msgs(ts, t, frame=FRAME):
    T = ts.types
    return T, T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9),
                                       frame_id=frame)


def image_msg(ts, t, arr_bytes, h, w, enc, step, frame=FRAME):
    T, hdr = ros_msgs(ts, t, frame)
    return T["sensor_msgs/msg/Image"](header=hdr, height=h, width=w, encoding=enc, is_bigendian=0, step=step,
                                      data=np.frombuffer(arr_bytes, np.uint8).copy())


def info_msg(ts, t, cam=CAM, frame=FRAME, d=None):
    T, hdr = ros_msgs(ts, t, frame)
    return T["sensor_msgs/msg/CameraInfo"](
        header=hdr, height=cam.height, width=cam.width, distortion_model="plumb_bob",
        d=np.zeros(5) if d is None else np.asarray(d, float), k=cam.K.reshape(-1), r=np.eye(3).reshape(-1),
        p=cam.P.reshape(-1), binning_x=0, binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def pose_msg(ts, t, pos=(0.0, 0.0, 2.0), quat=(0.0, 0.0, 0.0, 1.0), frame=FRAME):
    T, hdr = ros_msgs(ts, t, frame)
    p = T["geometry_msgs/msg/Point"](x=pos[0], y=pos[1], z=pos[2])
    q = T["geometry_msgs/msg/Quaternion"](x=quat[0], y=quat[1], z=quat[2], w=quat[3])
    return T["geometry_msgs/msg/PoseStamped"](header=hdr, pose=T["geometry_msgs/msg/Pose"](position=p, orientation=q))


def write_raw_bag(path, messages, storage="mcap"):
    """messages: list of (topic, msgtype, log_time, message object), written with rosbags directly."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = typestore()
    conns = {}
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        for topic, msgtype, t, msg in messages:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=ts)
            w.write(conns[topic], t, ts.serialize_cdr(msg, msgtype))
    return Path(path)


def frame_msgs(ts, t, img_bytes, enc="rgb8", h=H, w=W, step=None, cam=CAM, frames=(FRAME, FRAME, FRAME)):
    ch = {"rgb8": 3, "bgr8": 3, "mono8": 1, "rgba8": 4, "bgra8": 4}.get(enc, 3)
    return [("/camera/image_raw", "sensor_msgs/msg/Image", t,
             image_msg(ts, t, img_bytes, h, w, enc, step if step is not None else w * ch, frames[0])),
            ("/camera/camera_info", "sensor_msgs/msg/CameraInfo", t, info_msg(ts, t, cam, frames[1])),
            ("/panel/pose", "geometry_msgs/msg/PoseStamped", t, pose_msg(ts, t, frame=frames[2]))]


# ------------------------------------------------------------------------------------------------
# Round trips


@pytest.mark.parametrize("storage,suffix", [("mcap", ".mcap"), ("sqlite3", ".db3")])
def test_write_read_round_trip(tmp_path, storage, suffix):
    samples = make_samples(6)
    bag = write_trial(tmp_path / f"trial{suffix}", iter(samples))
    assert bag == tmp_path / "trial"
    assert sorted(p.name for p in bag.iterdir()) == sorted(["metadata.yaml", f"trial{suffix}"])
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["storage_identifier"] == storage and meta["version"] == 9
    assert meta["relative_file_paths"] == [f"trial{suffix}"]
    assert {e["topic_metadata"]["name"]: e["message_count"] for e in meta["topics_with_message_count"]} == {
        "/camera/image_raw": 6, "/camera/camera_info": 6, "/panel/pose": 6, "/tf": 6}

    info = open_bag(bag)
    assert info.storage == storage and not info.report.truncated
    assert {t.name: (t.msgtype, t.count) for t in info.topics.values()} == {
        "/camera/image_raw": ("sensor_msgs/msg/Image", 6), "/camera/camera_info": ("sensor_msgs/msg/CameraInfo", 6),
        "/panel/pose": ("geometry_msgs/msg/PoseStamped", 6), "/tf": ("tf2_msgs/msg/TFMessage", 6)}
    assert info.start_ns == T0 and info.end_ns == T0 + 5 * DT and info.duration_s == pytest.approx(0.5)

    # the same bag through a directory, its metadata.yaml and the bare storage file
    for p in (bag, bag / "metadata.yaml", bag / f"trial{suffix}"):
        stream = read_samples(p)
        got = list(stream)
        assert len(got) == 6
        for s, g in zip(samples, got):
            assert g.stamp_ns == s.stamp_ns and g.frame_id == FRAME
            assert g.image.dtype == np.uint8 and g.image.shape == (H, W, 3) and g.image.flags.writeable
            np.testing.assert_array_equal(g.image, s.image)
            np.testing.assert_allclose(g.camera.K, CAM.K, rtol=0, atol=1e-12)
            assert (g.camera.width, g.camera.height, g.camera.frame_id) == (W, H, FRAME)
            np.testing.assert_allclose(g.pose, s.pose, atol=1e-12)
        rep = stream.report
        assert rep.finished and not rep.truncated and rep.lost == {} and rep.samples == 6
        assert rep.sync.exact == 6 and rep.sync.dropped == 0


def test_tf_and_camera_info_contents(tmp_path):
    samples = make_samples(3)
    bag = write_trial(tmp_path / "t.mcap", samples, panel_frame="panel_link")
    tfs = list(iter_messages(bag, "/tf"))
    assert len(tfs) == 3
    for s, (t, msg) in zip(samples, tfs):
        (tf,) = msg.transforms
        assert t == s.stamp_ns and tf.header.frame_id == FRAME and tf.child_frame_id == "panel_link"
        assert tf.header.stamp.sec * 10**9 + tf.header.stamp.nanosec == s.stamp_ns
        tr, q = tf.transform.translation, tf.transform.rotation
        np.testing.assert_allclose(pose_to_matrix([tr.x, tr.y, tr.z], [q.x, q.y, q.z, q.w]), s.pose, atol=1e-12)
    (_, ci), *_ = list(iter_messages(bag, "/camera/camera_info"))
    assert ci.distortion_model == "plumb_bob" and list(ci.d) == [0.0] * 5
    np.testing.assert_array_equal(ci.r, np.eye(3).reshape(-1))
    np.testing.assert_allclose(ci.p, CAM.P.reshape(-1))
    (_, im), *_ = list(iter_messages(bag, "/camera/image_raw"))
    assert (im.encoding, im.step, im.is_bigendian, im.header.frame_id) == ("rgb8", 3 * W, 0, FRAME)
    # no /tf when not asked for; a directory path without suffix defaults to MCAP
    bag2 = write_trial(tmp_path / "plain", samples, write_tf=False, camera_frame="cam_opt")
    info = open_bag(bag2)
    assert "/tf" not in info.topics and info.storage == "mcap" and (bag2 / "plain.mcap").exists()
    assert {s.frame_id for s in read_samples(bag2)} == {"cam_opt"}


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_rclpy_wire_compatibility(tmp_path, storage):
    from rclpy.serialization import deserialize_message, serialize_message
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import CameraInfo, Image

    samples = make_samples(2)
    bag = write_trial(tmp_path / "w", samples, storage=storage)
    raws = list(iter_raw(bag, ["/camera/image_raw", "/camera/camera_info", "/panel/pose"]))
    assert [r.topic for r in raws[:3]] == ["/camera/image_raw", "/camera/camera_info", "/panel/pose"]
    img = deserialize_message(bytes(raws[0].data), Image)
    assert (img.height, img.width, img.encoding, img.step) == (H, W, "rgb8", 3 * W)
    assert img.header.frame_id == FRAME and img.header.stamp.sec * 10**9 + img.header.stamp.nanosec == T0
    np.testing.assert_array_equal(image_to_rgb(img), samples[0].image)  # rclpy's array.array data
    ci = deserialize_message(bytes(raws[1].data), CameraInfo)
    np.testing.assert_allclose(np.asarray(ci.k).reshape(3, 3), CAM.K)
    assert ci.distortion_model == "plumb_bob" and (ci.width, ci.height) == (W, H)
    ps = deserialize_message(bytes(raws[2].data), PoseStamped)
    p, q = ps.pose.position, ps.pose.orientation
    np.testing.assert_allclose(pose_to_matrix([p.x, p.y, p.z], [q.x, q.y, q.z, q.w]), samples[0].pose, atol=1e-12)
    # and back: rclpy's bytes deserialize with the reader's typestore to the same fields
    ts = typestore()
    back = ts.deserialize_cdr(serialize_message(ps), "geometry_msgs/msg/PoseStamped")
    assert (back.pose.position.x, back.pose.orientation.w, back.header.frame_id) == (p.x, q.w, FRAME)


def test_reader_matches_mcap_library_on_intact_file(tmp_path):
    from mcap.reader import make_reader

    bag = write_trial(tmp_path / "m.mcap", make_samples(5))
    f = bag / "m.mcap"
    ours = [(r.topic, r.log_time_ns, bytes(r.data)) for r in iter_raw(f)]
    with f.open("rb") as fh:
        ref = [(ch.topic, m.log_time, bytes(m.data)) for _, ch, m in make_reader(fh).iter_messages(log_time_order=False)]
    assert ours == ref and len(ours) == 20
    rep = McapScanReport(str(f))
    assert sum(1 for _ in iter_mcap(f, None, rep)) == 20
    assert rep.complete and rep.data_end_seen and rep.bytes_unreadable == 0 and rep.errors == []
    assert rep.statistics == {"/camera/image_raw": 5, "/camera/camera_info": 5, "/panel/pose": 5, "/tf": 5}


# ------------------------------------------------------------------------------------------------
# Cut-off recordings


def _cut(bag_dir, name, n_bytes):
    f = bag_dir / name
    f.write_bytes(f.read_bytes()[:n_bytes])


def test_truncated_mcap_recovers_intact_frames(tmp_path, caplog):
    samples = make_samples(20)
    bag = write_trial(tmp_path / "cut.mcap", samples)
    raw = (bag / "cut.mcap").read_bytes()
    # rosbags refuses the cut file outright; the mcap library loses the whole (only) chunk
    half = tmp_path / "half"
    shutil.copytree(bag, half)
    _cut(half, "cut.mcap", len(raw) // 2)
    from rosbags.highlevel import AnyReader
    with pytest.raises(Exception):
        with AnyReader([half]) as r:
            list(r.messages())

    with caplog.at_level(logging.WARNING, logger="uw_sil.bags.reader"):
        stream = read_samples(half)
        got = list(stream)
    assert 8 <= len(got) <= 11
    for s, g in zip(samples, got):
        assert g.stamp_ns == s.stamp_ns
        np.testing.assert_array_equal(g.image, s.image)
    rep = stream.report
    n = len(got)
    assert rep.truncated and rep.finished and 0 < rep.bytes_unreadable < len(raw) // 20
    assert rep.lost == {"/camera/image_raw": 20 - n, "/camera/camera_info": 20 - n, "/panel/pose": 20 - n}
    assert any("cut off" in r.getMessage() for r in caplog.records)
    info = open_bag(half)
    assert info.report.truncated and info.topics["/camera/image_raw"].count == n

    # exact expectation from the file layout: cut right after frame k's pixels -> frames 0..k-1 intact
    for k, delta in ((7, 0), (13, -1)):
        end_k = raw.index(samples[k].image.tobytes()) + samples[k].image.nbytes + delta
        d = tmp_path / f"cut{k}"
        shutil.copytree(bag, d)
        _cut(d, "cut.mcap", end_k)
        (d / "metadata.yaml").unlink()  # as when the recorder dies: no metadata.yaml
        stream = read_samples(d)
        got = [g.stamp_ns for g in stream]
        assert got == [s.stamp_ns for s in samples[:k]]
        assert stream.report.truncated and stream.report.metadata_missing
        assert stream.report.expected == {} and stream.report.lost == {}  # nothing tells how much is missing
        # the image of frame k itself is complete in the first case (its info/pose are not)
        assert stream.report.read["/camera/image_raw"] == (k + 1 if delta == 0 else k)


def test_truncated_multi_chunk_mcap(tmp_path):
    samples = make_samples(12, w=320, h=240)  # 230 kB per image: rosbags closes a chunk every ~5 frames
    bag = write_trial(tmp_path / "big.mcap", samples, write_tf=False)
    raw = (bag / "big.mcap").read_bytes()
    cut_at = raw.index(samples[8].image.tobytes()) + 1000  # inside frame 8's image, in the 2nd chunk
    _cut(bag, "big.mcap", cut_at)
    scan = McapScanReport("")
    assert sum(1 for _ in iter_mcap(bag / "big.mcap", None, scan)) == 8 * 3
    assert scan.partial_chunks == 1 and 0 < scan.recovered_from_cut < 8 * 3
    stream = read_samples(bag)
    got = list(stream)
    assert [g.stamp_ns for g in got] == [s.stamp_ns for s in samples[:8]]
    assert all(np.array_equal(g.image, s.image) for g, s in zip(got, samples))
    assert stream.report.lost == {t: 4 for t in ("/camera/image_raw", "/camera/camera_info", "/panel/pose")}


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_truncated_compressed_mcap_from_other_writer(tmp_path, compression):
    """A bare .mcap written by the mcap library (as rosbag2's plugin does), compressed chunks, no metadata."""
    from mcap.writer import CompressionType, Writer

    ts = typestore()
    f = tmp_path / "other.mcap"
    rng = np.random.default_rng(3)
    n = 120  # 1.1 MB: one full 768 KiB chunk (rosbag2's default chunk size) and a second one
    imgs = [rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(n)]
    with f.open("wb") as fh:
        w = Writer(fh, chunk_size=786_432, compression=getattr(CompressionType, compression.upper()))
        w.start(profile="ros2", library="test")
        ids = {}
        for topic, mt in (("/camera/image_raw", "sensor_msgs/msg/Image"),
                          ("/camera/camera_info", "sensor_msgs/msg/CameraInfo"),
                          ("/panel/pose", "geometry_msgs/msg/PoseStamped")):
            sid = w.register_schema(mt, "ros2msg", ts.generate_msgdef(mt, ros_version=2)[0].encode())
            ids[topic] = (w.register_channel(topic, "cdr", sid), mt)
        for i in range(n):
            t = T0 + i * DT
            for topic, msg in zip(ids, [image_msg(ts, t, imgs[i].tobytes(), H, W, "rgb8", 3 * W), info_msg(ts, t),
                                        pose_msg(ts, t)]):
                cid, mt = ids[topic]
                w.add_message(cid, t, bytes(ts.serialize_cdr(msg, mt)), t)
        w.finish()
    full = list(read_samples(f))
    assert len(full) == n and all(np.array_equal(g.image, im) for g, im in zip(full, imgs))
    size = f.stat().st_size
    f.write_bytes(f.read_bytes()[: size * 9 // 10])  # inside the second chunk
    stream = read_samples(f)
    got = list(stream)
    assert 0 < len(got) < n
    assert [g.stamp_ns for g in got] == [T0 + i * DT for i in range(len(got))]
    assert all(np.array_equal(g.image, im) for g, im in zip(got, imgs))
    rep = stream.report
    assert rep.truncated and not rep.metadata_missing and rep.expected == {}
    # the cut chunk still gives the messages of its complete compressed blocks (zstd: 128 kB, lz4: 64 kB)
    scan = McapScanReport(str(f))
    list(iter_mcap(f, None, scan))
    assert scan.partial_chunks == 1 and scan.skipped_chunks == 0 and scan.recovered_from_cut >= 3
    assert rep.read["/camera/image_raw"] == sum(scan.messages.values()) // 3 + (sum(scan.messages.values()) % 3 > 0)


def test_damaged_sqlite_is_an_error_or_reported(tmp_path):
    bag = write_trial(tmp_path / "s.db3", make_samples(20))
    size = (bag / "s.db3").stat().st_size
    for frac in (0.5, 0.99):
        d = tmp_path / f"s{frac}"
        shutil.copytree(bag, d)
        _cut(d, "s.db3", int(size * frac))
        try:
            stream = read_samples(d)
            got = list(stream)
        except BagError as exc:
            assert "cannot open sqlite3 bag" in str(exc) and ".recover" in str(exc)
        else:
            assert stream.report.truncated and stream.report.errors and len(got) < 20


# ------------------------------------------------------------------------------------------------
# Pairing and encodings in real bags


def test_pairing_with_slow_camera_info_jittered_and_missing_poses(tmp_path):
    ts = typestore()
    rng = np.random.default_rng(5)
    msgs, imgs = [], {}
    for i in range(30):
        t = T0 + i * 33_000_000
        imgs[t] = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        msgs.append(("/camera/image_raw", "sensor_msgs/msg/Image", t,
                     image_msg(ts, t, imgs[t].tobytes(), H, W, "rgb8", 3 * W)))
        if i % 10 == 0:
            msgs.append(("/camera/camera_info", "sensor_msgs/msg/CameraInfo", t, info_msg(ts, t)))
        if i not in (12, 13):
            tp = t + int(rng.integers(-4_000_000, 4_000_000))
            msgs.append(("/panel/pose", "geometry_msgs/msg/PoseStamped", tp + 15_000_000,
                         pose_msg(ts, tp, pos=(0.0, 0.0, float(i)))))
    bag = write_raw_bag(tmp_path / "pairing", msgs)
    stream = read_samples(bag, max_dt=0.010, info_max_dt=None)
    got = list(stream)
    assert len(got) == 28 and stream.report.sync.dropped == 2
    for g in got:
        i = round((g.stamp_ns - T0) / 33_000_000)
        assert g.pose[2, 3] == float(i)  # its own pose, not the neighbour's
        np.testing.assert_array_equal(g.image, imgs[g.stamp_ns])
    # with a 1 ms tolerance nothing pairs with the jittered poses except by chance
    assert len(list(read_samples(bag, max_dt=0.0))) == 0


@pytest.mark.parametrize("enc", ["rgb8", "bgr8", "mono8", "rgba8", "bgra8"])
def test_encodings_in_bag(tmp_path, enc):
    ts = typestore()
    rgb = np.random.default_rng(1).integers(0, 256, (H, W, 3), dtype=np.uint8)
    if enc == "mono8":
        data, expect = rgb[:, :, 0].copy(), np.repeat(rgb[:, :, :1], 3, axis=2)
    else:
        ch = [0, 1, 2] if enc.startswith("rgb") else [2, 1, 0]
        data = rgb[:, :, ch]
        if enc.endswith("a8"):
            data = np.concatenate([data, np.full((H, W, 1), 7, np.uint8)], axis=2)
        expect = rgb
    bag = write_raw_bag(tmp_path / enc, frame_msgs(ts, T0, np.ascontiguousarray(data).tobytes(), enc))
    (s,) = list(read_samples(bag))
    np.testing.assert_array_equal(s.image, expect)


def test_compressed_image_topic(tmp_path):
    import cv2

    ts = typestore()
    rgb = np.random.default_rng(2).integers(0, 256, (H, W, 3), dtype=np.uint8)
    ok, png = cv2.imencode(".png", rgb[:, :, ::-1])
    assert ok
    T, hdr = ros_msgs(ts, T0)
    comp = T["sensor_msgs/msg/CompressedImage"](header=hdr, format="rgb8; png compressed bgr8",
                                                data=png.reshape(-1))
    msgs = [("/cam/compressed", "sensor_msgs/msg/CompressedImage", T0, comp)] + frame_msgs(ts, T0, rgb.tobytes())[1:]
    bag = write_raw_bag(tmp_path / "comp", msgs, storage="sqlite3")
    (s,) = list(read_samples(bag, image_topic="/cam/compressed"))
    np.testing.assert_array_equal(s.image, rgb)


# ------------------------------------------------------------------------------------------------
# Errors


def test_missing_topic_and_wrong_type_errors(tmp_path):
    bag = write_trial(tmp_path / "e.mcap", make_samples(2))
    with pytest.raises(BagError, match=r"e: topic '/camera/nope' is not in the bag; it has: "
                                       r".*/camera/image_raw \[sensor_msgs/msg/Image\]"):
        read_samples(bag, image_topic="/camera/nope")
    with pytest.raises(BagError, match=r"'/tf' has type tf2_msgs/msg/TFMessage, expected geometry_msgs/msg/PoseStamped"):
        read_samples(bag, pose_topic="/tf")
    with pytest.raises(BagError, match="not in the bag"):
        iter_messages(bag, "/nope")
    with pytest.raises(ValueError, match="must differ"):
        read_samples(bag, info_topic="/camera/image_raw")


def test_not_a_bag_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        open_bag(tmp_path / "nothing")
    written = write_trial(tmp_path / "trial.mcap", make_samples(1))
    # --out trial.mcap wrote trial/trial.mcap: the same name reads it back
    assert written == tmp_path / "trial"
    assert resolve_bag_path(tmp_path / "trial.mcap") == tmp_path / "trial"
    assert len(list(read_samples(tmp_path / "trial.mcap"))) == 1
    with pytest.raises(FileNotFoundError, match="does not exist"):
        open_bag(tmp_path / "other.mcap")
    (tmp_path / "empty_dir").mkdir()
    with pytest.raises(BagError, match="not a ROS 2 bag: no metadata.yaml and no .mcap or .db3"):
        open_bag(tmp_path / "empty_dir")
    (tmp_path / "empty.mcap").write_bytes(b"")
    with pytest.raises(BagError, match="empty file"):
        read_samples(tmp_path / "empty.mcap")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(BagError, match="neither an MCAP nor an SQLite file"):
        open_bag(tmp_path / "notes.txt")
    bad = tmp_path / "badmeta"
    bad.mkdir()
    (bad / "metadata.yaml").write_text("just: text\n")
    with pytest.raises(BagError, match="not a readable rosbag2 metadata file"):
        open_bag(bad)
    gone = tmp_path / "gone"
    shutil.copytree(tmp_path / "trial", gone)
    (gone / "trial.mcap").unlink()
    with pytest.raises(BagError, match="storage files that do not exist"):
        open_bag(gone)
    only_magic = tmp_path / "magic.mcap"
    only_magic.write_bytes(b"\x89MCAP0\r\n")
    with pytest.raises(BagError, match="no topics"):
        read_samples(only_magic)


def test_bad_image_messages_give_clear_errors(tmp_path):
    ts = typestore()
    img = np.zeros((H, W, 3), np.uint8).tobytes()
    cases = {
        "yuv": (frame_msgs(ts, T0, img[: H * W * 2], enc="yuv422"),
                r"unsupported image encoding 'yuv422'; supported: rgb8, bgr8, rgba8, bgra8, mono8"),
        "short": (frame_msgs(ts, T0, img[:-10]), r"has 9206 bytes, expected step\*height = 192\*48 = 9216"),
        "step": (frame_msgs(ts, T0, img[: 100 * H], step=100), r"step 100 is shorter than a row of 64 rgb8 pixels"),
        "size": (frame_msgs(ts, T0, img, cam=CameraModel.from_fov(32, 24)), r"is 64x48 but /camera/camera_info says 32x24"),
        "frame": (frame_msgs(ts, T0, img, frames=(FRAME, FRAME, "map")), r"frame mismatch .* 'map'"),
    }
    for name, (msgs, pattern) in cases.items():
        bag = write_raw_bag(tmp_path / name, msgs)
        stream = read_samples(bag)
        with pytest.raises(BagError, match=pattern):
            next(stream)
    assert len(list(read_samples(tmp_path / "frame", check_frames=False))) == 1
    # an uncalibrated camera_info (K = 0)
    msgs = frame_msgs(ts, T0, img)
    msgs[1][3].k[:] = 0.0
    bag = write_raw_bag(tmp_path / "uncal", msgs)
    with pytest.raises(BagError, match="not a usable calibration"):
        list(read_samples(bag))


def test_distortion_is_rectified(tmp_path, caplog):
    """camera_info with plumb_bob distortion: the frames are rectified (K, D -> P) and the report says so."""
    import cv2

    ts = typestore()
    d = [-0.2, 0.05, 0, 0, 0]
    rng = np.random.default_rng(0)
    raw = cv2.GaussianBlur(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), (5, 5), 1.5)
    msgs = frame_msgs(ts, T0, raw.tobytes())
    msgs[1] = (msgs[1][0], msgs[1][1], T0, info_msg(ts, T0, d=d))
    bag = write_raw_bag(tmp_path / "dist", msgs)
    with caplog.at_level(logging.INFO, logger="uw_sil.bags.reader"):
        stream = read_samples(bag)
        (s,) = list(stream)
    maps = cv2.initUndistortRectifyMap(CAM.K, np.asarray(d, float), None, CAM.K, (W, H), cv2.CV_32FC1)  # P = K here
    expected = cv2.remap(raw, *maps, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    inner = (slice(3, -3), slice(3, -3))
    assert np.abs(s.image[inner].astype(int) - expected[inner]).max() <= 1
    assert np.abs(s.image[inner].astype(int) - raw[inner]).mean() > 5          # it did change the frame
    assert s.camera == CAM
    assert any("distortion" in n and "rectified" in n for n in stream.report.notes)
    assert any("rectified" in r.getMessage() for r in caplog.records)


def test_write_trial_validation(tmp_path):
    s = make_samples(2)
    write_trial(tmp_path / "a.mcap", s)
    with pytest.raises(FileExistsError, match="overwrite=True"):
        write_trial(tmp_path / "a.mcap", s)
    bag = write_trial(tmp_path / "a.db3", s[:1], overwrite=True)  # replaces the MCAP bag a/
    assert open_bag(bag).storage == "sqlite3" and sorted(p.name for p in bag.iterdir()) == ["a.db3", "metadata.yaml"]
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "thesis.tex").write_text("x")
    with pytest.raises(FileExistsError, match="not bag files"):
        write_trial(tmp_path / "docs", s, overwrite=True)
    with pytest.raises(ValueError, match="asks for mcap storage but storage='sqlite3'"):
        write_trial(tmp_path / "b.mcap", s, storage="sqlite3")
    with pytest.raises(ValueError, match="no samples"):
        write_trial(tmp_path / "c", [])
    bad = Sample(T0, np.zeros((H, W), np.uint8), CAM, np.eye(4), FRAME)
    with pytest.raises(ValueError, match=r"\(H, W, 3\) uint8"):
        write_trial(tmp_path / "d", [bad])
    skew = np.eye(4)
    skew[0, 1] = 0.3
    with pytest.raises(ValueError, match="not a rigid transform"):
        write_trial(tmp_path / "e", [Sample(T0, s[0].image, CAM, skew, FRAME)])
    with pytest.raises(ValueError, match="image is 64x48 but the camera is 32x24"):
        write_trial(tmp_path / "f", [Sample(T0, s[0].image, CameraModel.from_fov(32, 24), np.eye(4), FRAME)])
    with pytest.raises(ValueError, match="stamp_ns"):
        write_trial(tmp_path / "g", [Sample(-1, s[0].image, CAM, np.eye(4), FRAME)])
    for name in ("d", "e", "f", "g"):
        assert not (tmp_path / name).exists()

    def crashing_renderer():
        yield from make_samples(3)
        raise RuntimeError("renderer crashed")

    with pytest.raises(RuntimeError, match="renderer crashed"):
        write_trial(tmp_path / "h.db3", crashing_renderer())
    assert not (tmp_path / "h").exists()


# ------------------------------------------------------------------------------------------------
# Image message conversion


def test_image_conversion_round_trip_and_padding():
    rgb = np.random.default_rng(4).integers(0, 256, (5, 7, 3), dtype=np.uint8)
    for enc in ("rgb8", "bgr8"):
        f = rgb_to_image_fields(rgb, enc)
        assert f["step"] == 21 and f["is_bigendian"] == 0 and isinstance(f["data"], bytes)
        np.testing.assert_array_equal(image_to_rgb(SimpleNamespace(**f)), rgb)
    f = rgb_to_image_fields(rgb[:, :, 1], "mono8")
    np.testing.assert_array_equal(image_to_rgb(SimpleNamespace(**f)), np.repeat(rgb[:, :, 1:2], 3, axis=2))
    # rows padded to 24 bytes; data given as a list, as some drivers' Python bindings do
    padded = np.zeros((5, 24), np.uint8)
    padded[:, :21] = rgb.reshape(5, 21)
    msg = SimpleNamespace(height=5, width=7, encoding="rgb8", step=24, data=padded.reshape(-1).tolist())
    np.testing.assert_array_equal(image_to_rgb(msg), rgb)
    assert set(SUPPORTED_ENCODINGS) >= {"rgb8", "bgr8", "mono8", "rgba8", "bgra8"}
    with pytest.raises(ValueError, match="cannot write encoding"):
        rgb_to_image_fields(rgb, "rgba8")
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        rgb_to_image_fields(rgb[:, :, 0], "rgb8")
    with pytest.raises(ValueError, match="uint8"):
        rgb_to_image_fields(rgb.astype(np.float32))


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_a_raw_bayer_image_is_demosaiced_with_its_colours_where_they_are(pattern):
    """A camera driver's image_raw is often the sensor's Bayer mosaic: each pattern's colours must land in
    their channels (OpenCV names the patterns otherwise: a swap turns red water blue), a smooth image must come
    back close to itself, and a 16-bit mosaic keeps its high byte."""
    h, w = 24, 32
    yy, xx = np.mgrid[0:h, 0:w]
    rgb = np.stack([60 + 4 * xx, 40 + 3 * yy, 200 - 2 * xx - yy], axis=-1).astype(np.uint8)
    cell = {"r": 0, "g": 1, "b": 2}
    which = np.array([[cell[pattern[0]], cell[pattern[1]]], [cell[pattern[2]], cell[pattern[3]]]])
    chan = which[yy % 2, xx % 2]
    mosaic = np.take_along_axis(rgb, chan[..., None], axis=2)[..., 0]
    msg = SimpleNamespace(height=h, width=w, encoding=f"bayer_{pattern}8", step=w, data=mosaic.tobytes())
    out = image_to_rgb(msg)
    assert out.shape == (h, w, 3) and out.dtype == np.uint8
    inner = (slice(2, -2), slice(2, -2))
    assert np.abs(out[inner].astype(int) - rgb[inner]).max() <= 4
    wide = (mosaic.astype(np.uint16) << 8) | 0x5A                 # the low byte must not matter
    for big in (0, 1):
        data = wide.astype(">u2" if big else "<u2").tobytes()
        m16 = SimpleNamespace(height=h, width=w, encoding=f"bayer_{pattern}16", step=2 * w, data=data,
                              is_bigendian=big)
        np.testing.assert_array_equal(image_to_rgb(m16), out)


def test_sixteen_bit_images_keep_their_high_byte_in_either_byte_order():
    rgb = np.random.default_rng(5).integers(0, 256, (4, 6, 3), dtype=np.uint8)
    v = (rgb.astype(np.uint16) << 8) | np.uint16(0xA7)
    for big in (0, 1):
        dt = ">u2" if big else "<u2"
        for enc, arr in (("rgb16", v), ("bgr16", v[:, :, ::-1]), ("mono16", v[:, :, 1])):
            a = np.ascontiguousarray(arr).astype(dt)
            msg = SimpleNamespace(height=4, width=6, encoding=enc, step=a.nbytes // 4, data=a.tobytes(),
                                  is_bigendian=big)
            want = rgb if enc in ("rgb16", "bgr16") else np.repeat(rgb[:, :, 1:2], 3, axis=2)
            np.testing.assert_array_equal(image_to_rgb(msg), want, err_msg=f"{enc} big-endian={big}")
    with pytest.raises(ValueError, match="unsupported image encoding '16UC1'"):    # a depth image in mm
        image_to_rgb(SimpleNamespace(height=1, width=1, encoding="16UC1", step=2, data=bytes(2)))
    with pytest.raises(ValueError, match="unsupported image encoding 'rgb32f'"):
        image_to_rgb(SimpleNamespace(height=1, width=1, encoding="rgb32f", step=12, data=bytes(12)))
