"""Field-trial bags as they are recorded: any image topic, compressed images, intrinsics from a
camera_calibration YAML (distortion rectified), the panel pose from a topic, from /tf + /tf_static, or
from the panel's ArUco markers; bad input gives one clear line and writes nothing."""
from __future__ import annotations

import math
import re
import shutil

import numpy as np
import pytest
import yaml

from uw_sil.bags import open_bag
from uw_sil.bags.camera_yaml import CameraCalibration, load_camera_yaml, write_camera_yaml
from uw_sil.bags.source import BagSource, PoseFrom, describe_sources
from uw_sil.bags.synth import synthesize_trial
from uw_sil.bags.tf import TfError, TfExtrapolationError, TransformBuffer, slerp
from uw_sil.cli import EXIT_BAD_INPUT, main
from uw_sil.sim.camera import CameraModel
from uw_sil.sim.transforms import pose_to_matrix
from scipy.spatial.transform import Rotation

CAM = CameraModel.from_fov(320, 240)
FIELD_TOPIC = "/rov/front_cam/image_raw/compressed"
DIST = [-0.12, 0.03, 0.0005, -0.0003, 0.0]


def pose_error(T, T_true):
    """(translation error in mm, rotation error in degrees)."""
    dR = np.asarray(T_true)[:3, :3].T @ T[:3, :3]
    ang = math.degrees(Rotation.from_matrix(dR).magnitude())
    return 1000 * float(np.linalg.norm(T[:3, 3] - np.asarray(T_true)[:3, 3])), ang


# ------------------------------------------------------------------------------------------------ camera YAML


def test_camera_yaml_round_trip_and_default_projection(tmp_path):
    calib = CameraCalibration.from_camera_model(CAM, D=DIST, camera_name="front_cam")
    write_camera_yaml(tmp_path / "cam.yaml", calib)
    doc = yaml.safe_load((tmp_path / "cam.yaml").read_text())
    assert doc["image_width"] == 320 and doc["distortion_model"] == "plumb_bob"
    assert doc["camera_matrix"]["rows"] == 3 and len(doc["projection_matrix"]["data"]) == 12
    back = load_camera_yaml(tmp_path / "cam.yaml")
    np.testing.assert_allclose(back.K, calib.K)
    np.testing.assert_allclose(back.D, DIST)
    np.testing.assert_allclose(back.P, calib.P)
    assert back.has_distortion and back.camera_name == "front_cam"
    # P was computed with alpha = 0: every rectified pixel sees the raw image; undistorted, a barrel lens'
    # image is wider than K's pinhole at the edge centres, so P's focal length is shorter
    assert back.rectifier().outside_fraction < 0.002
    assert back.rectified_camera().fx < CAM.fx
    # without distortion P is K
    plain = CameraCalibration.from_camera_model(CAM)
    assert not plain.has_distortion and plain.rectified_camera() == CAM


@pytest.mark.parametrize("text, message", [
    ("%YAML:1.0\ncamera_matrix: !!opencv-matrix\n", "OpenCV FileStorage"),
    ("image_width: 320\n", "lacks image_height, camera_matrix"),
    ("image_width: 320\nimage_height: 240\ncamera_matrix: {rows: 3, cols: 3, data: [1, 2, 3]}\n", "must be 3x3"),
    ("image_width: 320\nimage_height: 240\ncamera_matrix: {rows: 3, cols: 3, data: [200, 0, 160, 0, 200, 120, 0, 0, 1]}\n"
     "distortion_model: equidistant\ndistortion_coefficients: {rows: 1, cols: 4, data: [0.1, 0, 0, 0]}\n",
     "'equidistant' is not supported"),
    ("[1, 2]\n", "not a camera_calibration YAML"),
])
def test_bad_camera_yaml_is_a_clear_error(tmp_path, text, message):
    (tmp_path / "c.yaml").write_text(text)
    with pytest.raises(ValueError, match=message):
        load_camera_yaml(tmp_path / "c.yaml")


def test_rectified_frame_is_the_pinhole_image_of_p():
    """Distort a pinhole render with the calibration, rectify it: the result is the render at P's camera."""
    from uw_sil.bags.synth import _covering_pinhole  # noqa: PLC2701 (test of the synthesizer's helper)
    import cv2
    from uw_sil.sim.render import Renderer
    from uw_sil.sim.scene import facing_pose

    calib = CameraCalibration.from_camera_model(CAM, D=DIST)
    wide = _covering_pinhole(calib)
    T = facing_pose(1.5, x=0.05, yaw=0.2)
    with Renderer(camera=wide) as r:
        src = r.render(T).rgb
        raw = cv2.remap(src, *calib.distortion_maps(wide), cv2.INTER_LINEAR)
        r.camera = calib.rectified_camera()
        direct = r.render(T).rgb
    rect = calib.rectifier()(raw)
    inner = (slice(10, -10), slice(10, -10))
    err = np.abs(rect[inner] - direct[inner]).mean()
    err_unrectified = np.abs(cv2.resize(raw, (320, 240))[inner] - direct[inner]).mean()
    assert err < 0.02 and err < err_unrectified / 3, (err, err_unrectified)


# ------------------------------------------------------------------------------------------------ tf


def _tree():
    """world -> base (dynamic: turns 90 deg about z and moves 1 m in x between t = 1 s and 2 s),
    base -> cam (static), world -> panel (static)."""
    buf = TransformBuffer(extrapolation_s=0.1, max_gap_s=0.6)
    for k in range(5):
        t = 1_000_000_000 + k * 250_000_000
        q = Rotation.from_euler("z", 90.0 * k / 4, degrees=True).as_quat()
        buf.add("/world", "base", t, (k / 4, 0.0, 0.0), q)
    buf.add("base", "cam", 0, (0.5, 0.0, 0.2), Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_quat(),
            static=True)
    buf.add("world", "panel", 0, (5.0, 1.0, 0.0), Rotation.from_euler("z", 180, degrees=True).as_quat(), static=True)
    return buf


def test_tf_chain_and_slerp_interpolation():
    buf = _tree()
    t = 1_100_000_000                              # between two samples: 9 degrees and 0.1 m
    T_world_base = pose_to_matrix((0.1, 0, 0), Rotation.from_euler("z", 9.0, degrees=True).as_quat())
    T_base_cam = pose_to_matrix((0.5, 0, 0.2), Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_quat())
    T_world_panel = pose_to_matrix((5, 1, 0), Rotation.from_euler("z", 180, degrees=True).as_quat())
    expected = np.linalg.inv(T_world_base @ T_base_cam) @ T_world_panel
    np.testing.assert_allclose(buf.lookup("cam", "panel", t), expected, atol=1e-12)
    np.testing.assert_allclose(buf.lookup("panel", "cam", t), np.linalg.inv(expected), atol=1e-12)
    up, down = buf.chain("cam", "panel")
    assert up == ["cam", "base", "world"] and down == ["panel", "world"]
    # slightly outside the recording: held; beyond the tolerance: refused, naming the edge and the times
    np.testing.assert_allclose(buf.lookup("world", "base", 2_050_000_000)[:3, 3], [1, 0, 0], atol=1e-12)
    with pytest.raises(TfExtrapolationError, match=r"world -> base is recorded from 1.000 s to 2.000 s; stamp "
                                                   r"2.500 s is 0.500 s after \(extrapolation refused beyond 0.1 s\)"):
        buf.lookup("cam", "panel", 2_500_000_000)
    assert buf.span_ns("cam", "panel") == (1_000_000_000, 2_000_000_000)


def test_slerp_takes_the_short_arc_and_is_exact_about_one_axis():
    q0 = Rotation.from_euler("y", 10, degrees=True).as_quat()
    q1 = -Rotation.from_euler("y", 70, degrees=True).as_quat()      # same rotation, other hemisphere
    q = slerp(q0, q1, 0.25)
    assert Rotation.from_quat(q).magnitude() == pytest.approx(math.radians(25.0), abs=1e-12)
    np.testing.assert_allclose(slerp(q0, q0, 0.7), q0, atol=1e-15)


def test_tf_structure_errors_are_clear():
    buf = _tree()
    with pytest.raises(TfError, match=r"frame 'camera_link' is not in tf; its frames are: base, cam, panel, world"):
        buf.lookup("camera_link", "panel", 1_500_000_000)
    buf.add("odom", "rov", 0, (0, 0, 0), (0, 0, 0, 1), static=True)
    with pytest.raises(TfError, match=r"tf tree has a gap: no chain of transforms connects 'rov' and 'panel'"):
        buf.lookup("rov", "panel", 1_500_000_000)
    with pytest.raises(TfError, match="two parents"):
        buf.add("odom", "base", 0, (0, 0, 0), (0, 0, 0, 1))
    gappy = TransformBuffer(max_gap_s=0.5)
    gappy.add("a", "b", 0, (0, 0, 0), (0, 0, 0, 1))
    gappy.add("a", "b", 2_000_000_000, (1, 0, 0), (0, 0, 0, 1))
    with pytest.raises(TfExtrapolationError, match="2.000 s gap"):
        gappy.lookup("a", "b", 1_000_000_000)


# ------------------------------------------------------------------------------------------------ markers


def test_marker_layout_matches_the_printed_markers():
    """The shipped layout YAML says where the texture has the markers: detected corners of a clean render
    coincide with the layout's corners projected at the true pose."""
    from uw_sil.sim.markers import MarkerPoseEstimator, default_marker_layout
    from uw_sil.sim.render import Renderer
    from uw_sil.sim.scene import facing_pose

    cam = CameraModel.from_fov(640, 480)
    T = facing_pose(1.3, x=0.03, yaw=0.15, pitch=-0.1, roll=0.2)
    layout = default_marker_layout()
    assert layout.dictionary == "DICT_4X4_50" and layout.ids == [0, 1, 2, 3] and layout.planar
    with Renderer(camera=cam) as r:
        img = np.clip(r.render(T).rgb * 255 + 0.5, 0, 255).astype(np.uint8)
    with MarkerPoseEstimator(layout, refine="lm") as est:
        ids, corners = est.detect(img)
    assert sorted(ids) == [0, 1, 2, 3]
    for i, c in zip(ids, corners):
        p = layout.spec(i).corners() @ T[:3, :3].T + T[:3, 3]
        assert np.abs(cam.project(p) - c).max() < 0.5, i


@pytest.mark.parametrize("text, message", [
    ("dictionary: DICT_9X9_1\nmarkers: [{id: 0, size: 0.1, position: [0, 0, 0]}]\n", "unknown ArUco dictionary"),
    ("dictionary: DICT_4X4_50\nmarkers: [{id: 50, size: 0.1, position: [0, 0, 0]}]\n", r"id 50 is not in DICT_4X4_50"),
    ("dictionary: DICT_4X4_50\nmarkers: [{id: 1, size: 0.1, position: [0, 0, 0]}, {id: 1, size: 0.1, "
     "position: [1, 0, 0]}]\n", "declared twice"),
    ("dictionary: DICT_4X4_50\nmarkers: [{id: 1, size: -1, position: [0, 0, 0]}]\n", "size must be > 0"),
    ("dictionary: DICT_4X4_50\nmarkers: [{id: 1, size: 0.1, position: [0, 0]}]\n", "invalid position"),
    ("dictionary: DICT_4X4_50\nmarkers: []\n", "non-empty 'markers' list"),
])
def test_bad_marker_layout_is_a_clear_error(tmp_path, text, message):
    from uw_sil.sim.markers import load_marker_layout

    (tmp_path / "p.markers.yaml").write_text(text)
    with pytest.raises(ValueError, match=message):
        load_marker_layout(tmp_path / "p.markers.yaml")


def test_marker_pose_through_the_underwater_model():
    """Noisy, attenuated, foggy frames at 2 m (320x240): the pose within 1 cm and 0.5 degrees."""
    from uw_sil.bags.synth import DEFAULT_TRUTH, SensorNoise, add_sensor_noise
    from uw_sil.sim.markers import MarkerPoseEstimator
    from uw_sil.sim.scene import facing_pose
    from uw_sil.sim.simcam import SimCamera

    rng = np.random.default_rng(3)
    errs = []
    with SimCamera(DEFAULT_TRUTH, camera=CAM) as sim, MarkerPoseEstimator() as est:
        for yaw, pitch in ((0.2, 0.05), (-0.15, -0.1), (0.05, 0.15)):
            T = facing_pose(2.0, x=0.04, yaw=yaw, pitch=pitch, roll=0.05)
            mp = est.estimate(add_sensor_noise(sim.render(T).image, SensorNoise(), rng), CAM)
            assert mp.T is not None, mp.reason
            assert mp.refinement == "ecc" and mp.rms_px < 1.0 and mp.ids
            errs.append(pose_error(mp.T, T))
        # a frame without markers in view is skipped with that reason
        away = est.estimate(add_sensor_noise(sim.render(facing_pose(2.0, x=3.0)).image, SensorNoise(), rng), CAM)
    errs = np.array(errs)
    assert errs[:, 0].max() < 10.0 and errs[:, 1].max() < 0.5, errs
    assert away.T is None and "no marker of the layout" in away.reason


def test_face_alignment_refines_a_pose_that_is_centimetres_off():
    """A pose 1.5 cm / 0.7 deg off (navigation-like) is brought to sub-millimetre by aligning the rendered
    face with the frame."""
    from uw_sil.bags.synth import DEFAULT_TRUTH, SensorNoise, add_sensor_noise
    from uw_sil.sim.align import FaceAligner
    from uw_sil.sim.scene import facing_pose
    from uw_sil.sim.simcam import SimCamera

    rng = np.random.default_rng(5)
    T = facing_pose(1.5, x=0.05, yaw=0.2, pitch=-0.05)
    off = pose_to_matrix((0.009, -0.009, 0.009), Rotation.from_euler("xyz", [0.4, -0.4, 0.4], degrees=True).as_quat())
    with SimCamera(DEFAULT_TRUTH, camera=CAM) as sim, FaceAligner() as al:
        img = add_sensor_noise(sim.render(T).image, SensorNoise(), rng)
        T0 = off @ T
        t0, r0 = pose_error(T0, T)
        res = al.refine(img, CAM, T0, levels=(2, 1, 1))
        assert res.T is not None and res.ecc > 0.9, res.reason
        t1, r1 = pose_error(res.T, T)
        assert t1 < 1.0 and r1 < 0.1 and t0 > 10 * t1, (t0, r0, t1, r1)
        # a pose whose panel is out of view cannot be aligned: refused with the reason
        away = al.refine(img, CAM, facing_pose(1.5, x=5.0), levels=(1,))
    assert away.T is None and "face covers" in away.reason


# ------------------------------------------------------------------------------------------------ synthetic field bags


COMBOS = [(fmt, pose_in) for fmt in ("jpeg", "png", "raw") for pose_in in ("topic", "tf", "none")]


class _FieldBags(dict):
    """Field-style bags made on first use, one per (image format, pose recording): 4 frames, 320x240,
    2.0 m -> 1.2 m (the markers are 9 px at 2 m), a distorted lens, no camera_info (the calibration YAML ``cam.yaml`` instead)."""

    def __init__(self, d):
        super().__init__()
        self.d = d

    def __missing__(self, key):
        fmt, pose_in = key
        topic = "/rov/front_cam/image_raw" + ("/compressed" if fmt != "raw" else "")
        bag = self.d / f"{fmt}_{pose_in}.mcap"
        truth = synthesize_trial(bag, n_frames=4, camera=CAM, start_m=2.0, end_m=1.2, image_topic=topic,
                                 info_topic=None, image_format=fmt, pose_in=pose_in, distortion=DIST,
                                 camera_yaml=self.d / "cam.yaml", seed=1)
        self[key] = (bag, truth)
        return self[key]


@pytest.fixture(scope="module")
def field_bags(tmp_path_factory):
    d = tmp_path_factory.mktemp("field")
    return d, _FieldBags(d)


@pytest.mark.parametrize("fmt, pose_in", COMBOS)
def test_field_bag_poses_from_each_source(field_bags, fmt, pose_in):
    d, bags = field_bags
    bag, truth = bags[fmt, pose_in]
    info = open_bag(bag)
    topics = {t.name: t.msgtype for t in info.topics.values()}
    assert topics[truth["image_topic"]] == ("sensor_msgs/msg/Image" if fmt == "raw"
                                            else "sensor_msgs/msg/CompressedImage")
    assert "/camera/camera_info" not in topics
    assert ("/panel/pose" in topics) == (pose_in == "topic")
    assert ("/tf_static" in topics) == (pose_in == "tf")
    pose_from = {"topic": "topic:/panel/pose", "tf": "tf:camera_optical_frame:panel", "none": "markers"}[pose_in]
    stream = BagSource(image_topic=truth["image_topic"], camera_info=d / "cam.yaml", pose_from=pose_from).read(bag)
    samples = list(stream)
    assert len(samples) == 4 and [s.index for s in samples] == [0, 1, 2, 3], stream.report.skipped
    rect = CameraModel(**truth["rectified_camera"])
    tol = {"topic": (1e-6, 1e-6), "tf": (8.0, 0.2), "none": (10.0, 0.5)}[pose_in]
    for s in samples:
        assert s.camera == rect                       # rectified frames, simulated with P's pinhole
        t_err, r_err = pose_error(s.pose, truth["poses"][s.index])
        assert t_err <= tol[0] and r_err <= tol[1], (s.index, t_err, r_err)
    assert any("rectified" in n for n in stream.report.notes)
    if pose_in == "none":
        assert all(s.pose_info["reprojection_rms_px"] < 1.5 for s in samples)


def test_tf_bag_needs_composition_and_interpolation(field_bags):
    """The synthesized tree: navigation between the frames on /tf, the rest on /tf_static; the pose at a
    frame is not any single recorded transform."""
    from uw_sil.bags.reader import load_tf

    _, bags = field_bags
    bag, truth = bags["jpeg", "tf"]
    buf = load_tf(bag)
    assert buf.frames == ["base_link", "camera_optical_frame", "map", "odom", "panel"]
    edges = {(p, c): (static, n) for p, c, static, n in buf.edges()}
    assert edges[("odom", "base_link")][0] is False and edges[("odom", "base_link")][1] > 4 * 3
    assert all(edges[e][0] for e in [("map", "odom"), ("base_link", "camera_optical_frame"), ("map", "panel")])
    nav = buf._edges["base_link"].arrays()[0]                      # noqa: SLF001 (inspecting the test bag)
    assert not set(nav.tolist()) & set(truth["stamps_ns"])        # no navigation sample at a frame stamp


def test_info_lists_image_topics_and_pose_sources(field_bags, capsys):
    d, bags = field_bags
    bag, truth = bags["jpeg", "tf"]
    text = describe_sources(bag)
    assert f"{FIELD_TOPIC} [CompressedImage] 4  compressed (jpeg)" in text
    assert "none: pass the camera's calibration with --camera-info" in text
    assert "tf:camera_optical_frame:panel" in text and "markers" in text
    assert main(["info", str(bag), "--image-topic", FIELD_TOPIC, "--camera-info", str(d / "cam.yaml"),
                 "--pose-from", "markers", "--check", "2"]) == 0
    out = capsys.readouterr().out
    assert "pose sources (--pose-from):" in out and "refined by ecc" in out
    assert main(["info", str(bag), "--image-topic", FIELD_TOPIC, "--camera-info", str(d / "cam.yaml"),
                 "--pose-from", "tf:camera_optical_frame:panel", "--refine-pose", "ecc", "--check", "1"]) == 0
    out = capsys.readouterr().out
    assert "image #0: 320x240, panel at" in out and "refined by ECC: moved" in out


def test_pose_from_parsing():
    assert PoseFrom.parse("tf:cam_optical:panel") == PoseFrom("tf", camera_frame="cam_optical", panel_frame="panel")
    assert PoseFrom.parse("tf::panel").camera_frame == ""
    assert PoseFrom.parse("topic:/a/b").topic == "/a/b" and str(PoseFrom.parse("markers")) == "markers"
    for bad in ("tf:cam", "pose", "topic:", "tf:a:b:c"):
        with pytest.raises(ValueError, match="--pose-from: must be"):
            PoseFrom.parse(bad)


# ------------------------------------------------------------------------------------------------ bad input (CLI)


def _run_bad(capsys, tmp_path, args):
    out = tmp_path / "o" / "fit.yaml"
    rc = main(["fit", *args, "--out", str(out), "--max-iter", "1"])
    err = capsys.readouterr().err.strip()
    assert rc == EXIT_BAD_INPUT
    assert not (tmp_path / "o").exists()
    lines = [line for line in err.splitlines() if not line.startswith("fitting with")]
    assert len(lines) == 1, err
    return lines[0]


def test_bad_field_input_one_line_nothing_written(field_bags, tmp_path, capsys):
    d, bags = field_bags
    bag, _ = bags["jpeg", "tf"]
    base = ["--bag", str(bag), "--image-topic", FIELD_TOPIC, "--camera-info", str(d / "cam.yaml")]
    # a topic that does not exist: the bag's topics are listed
    msg = _run_bad(capsys, tmp_path, ["--bag", str(bag), "--image-topic", "/camera/image_raw/compressed",
                                      "--camera-info", str(d / "cam.yaml"), "--pose-from", "markers"])
    assert "topic '/camera/image_raw/compressed' is not in the bag; it has:" in msg and FIELD_TOPIC in msg
    assert "/tf_static" in msg
    # a frame missing from /tf: the frames are listed
    msg = _run_bad(capsys, tmp_path, base + ["--pose-from", "tf:camera_link:panel"])
    assert "frame 'camera_link' is not in /tf and /tf_static" in msg and "base_link, camera_optical_frame, map" in msg
    # a camera YAML whose size differs from the images
    big = CameraCalibration.from_camera_model(CameraModel.from_fov(640, 480))
    write_camera_yaml(tmp_path / "big.yaml", big)
    msg = _run_bad(capsys, tmp_path, ["--bag", str(bag), "--image-topic", FIELD_TOPIC, "--camera-info",
                                      str(tmp_path / "big.yaml"), "--pose-from", "tf:camera_optical_frame:panel"])
    assert "is 320x240 but camera calibration" in msg and "is for 640x480" in msg
    # a pose topic that is not there
    msg = _run_bad(capsys, tmp_path, base + ["--pose-from", "topic:/panel/pose"])
    assert "topic '/panel/pose' is not in the bag" in msg


def test_tf_tree_with_a_gap_and_extrapolation(tmp_path, capsys):
    """The camera's branch is not connected to the panel's; and images outside the navigation record."""
    from uw_sil.bags import Sample, write_trial

    img = np.zeros((24, 32, 3), np.uint8)
    cam = CameraModel.from_fov(32, 24)
    samples = [Sample(10**9 + k * 10**8, img, cam, np.eye(4), "cam") for k in range(3)]
    eye = np.eye(4)
    write_trial(tmp_path / "gap.mcap", samples, pose_topic=None, write_tf=False,
                tf_static=[("base_link", "cam", eye), ("map", "panel", eye)],
                tf_dynamic=[(10**9 + k * 10**8, "odom", "base_link", eye) for k in range(3)])
    msg = _run_bad(capsys, tmp_path, ["--bag", str(tmp_path / "gap.mcap"), "--pose-from", "tf:cam:panel"])
    assert msg.startswith(f"uw-sil: error: {tmp_path / 'gap'}: tf tree has a gap: no chain of transforms connects "
                          f"'cam' and 'panel'")
    assert "tree of 'odom'" in msg and "tree of 'map'" in msg
    # connected, but the navigation stops before the images: every frame refused, one line says why
    far = [(5 * 10**8 + k * 10**7, "odom", "base_link", eye) for k in range(3)]
    write_trial(tmp_path / "early.mcap", samples, pose_topic=None, write_tf=False,
                tf_static=[("base_link", "cam", eye), ("odom", "panel", pose_to_matrix((0, 0, 2), (0, 0, 0, 1)))],
                tf_dynamic=far)
    msg = _run_bad(capsys, tmp_path, ["--bag", str(tmp_path / "early.mcap"), "--pose-from", "tf:cam:panel"])
    assert "no frame of /camera/image_raw has a panel pose from tf:cam:panel: 3 skipped" in msg
    assert "extrapolation refused beyond 0.1 s" in msg


def test_jpeg_that_does_not_decode(tmp_path, capsys):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_KILTED)
    T = ts.types
    hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="cam")
    msg = T["sensor_msgs/msg/CompressedImage"](header=hdr, format="jpeg",
                                                data=np.frombuffer(b"\xff\xd8\xff\xe0garbage", np.uint8).copy())
    with Writer(tmp_path / "bad", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection(FIELD_TOPIC, "sensor_msgs/msg/CompressedImage", typestore=ts)
        w.write(c, 10**9, ts.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage"))
    write_camera_yaml(tmp_path / "cam.yaml", CameraCalibration.from_camera_model(CAM))
    line = _run_bad(capsys, tmp_path, ["--bag", str(tmp_path / "bad"), "--image-topic", FIELD_TOPIC,
                                       "--camera-info", str(tmp_path / "cam.yaml"), "--pose-from", "markers"])
    assert f"{FIELD_TOPIC} at stamp 1000000000 ns: OpenCV could not decode the compressed image" in line
    assert line.endswith("(image #0)")


def test_markers_with_unexpected_ids(field_bags, tmp_path, capsys):
    """A user's panel whose layout declares ids 10-13 while the frames show 0-3: a clear error naming both."""
    from uw_sil.sim.scene import default_model_path

    d, bags = field_bags
    bag, _ = bags["png", "none"]
    shutil.copy(default_model_path(), tmp_path / "my_panel.glb")
    (tmp_path / "my_panel.markers.yaml").write_text(
        "dictionary: DICT_4X4_50\nmarkers:\n" + "".join(
            f"  - {{id: {10 + k}, size: 0.09, position: [{x}, {y}, 0.0]}}\n"
            for k, (x, y) in enumerate([(-0.39, 0.24), (0.39, 0.24), (-0.39, -0.24), (0.39, -0.24)])))
    line = _run_bad(capsys, tmp_path, ["--bag", str(bag), "--image-topic", FIELD_TOPIC, "--camera-info",
                                       str(d / "cam.yaml"), "--pose-from", "markers", "--model",
                                       str(tmp_path / "my_panel.glb")])
    assert re.search(r"image #0: ArUco markers \[[0-3, ]+\] \(DICT_4X4_50\) found but the marker layout", line), line
    assert "declares ids [10, 11, 12, 13]" in line
    # a model without a layout: the file to write is named
    (tmp_path / "my_panel.markers.yaml").unlink()
    line = _run_bad(capsys, tmp_path, ["--bag", str(bag), "--image-topic", FIELD_TOPIC, "--camera-info",
                                       str(d / "cam.yaml"), "--pose-from", "markers", "--model",
                                       str(tmp_path / "my_panel.glb")])
    assert "has no marker layout" in line and "my_panel.markers.yaml" in line


# ------------------------------------------------------------------------------------------------ the fit, end to end


def _recovered(fit_yaml, truth):
    got = yaml.safe_load(fit_yaml.read_text())["/**"]["ros__parameters"]
    want = truth["params"]
    rel_a = [abs(got[k] - want[k]) / want[k] for k in ("a_r", "a_g", "a_b")]
    abs_b = [abs(got[k] - want[k]) for k in ("b_r", "b_g", "b_b")]
    rel_rho = abs(got["rho_f"] - want["rho_f"]) / want["rho_f"]
    return max(rel_a) <= 0.05 and max(abs_b) <= 0.01 and rel_rho <= 0.10, (rel_a, abs_b, rel_rho)


@pytest.mark.parametrize("pose_in, pose_from", [("none", "markers"), ("tf", "tf:camera_optical_frame:panel")])
def test_fit_field_bag_recovers_the_parameters(tmp_path, capsys, pose_in, pose_from):
    """`uw-sil fit --bag field.mcap --image-topic /rov/front_cam/image_raw/compressed --camera-info cam.yaml
    --pose-from markers|tf:...` on a bag without pose topic and camera_info (PNG) recovers the parameters
    within the recovery tolerances (a 5 %, b 0.01, fog 10 %).
    Small: 320x240 with a 40 degree lens (markers readable at 4 m), K = 2 frames at 4.0 and 1.6 m."""
    import json

    bag, cam_yaml = tmp_path / "field.mcap", tmp_path / "cam.yaml"
    synth = ["synth", "--out", str(bag), "--frames", "6", "--width", "320", "--height", "240", "--hfov", "40",
             "--end", "1.6", "--image-topic", FIELD_TOPIC, "--compressed", "png", "--pose-in", pose_in,
             "--info-topic", "none", "--camera-yaml", str(cam_yaml)]
    assert main(synth) == 0
    topics = set(open_bag(bag).topics)
    assert "/panel/pose" not in topics and not any("camera_info" in t for t in topics)
    out = tmp_path / "fit.yaml"
    assert main(["fit", "--bag", str(bag), "--image-topic", FIELD_TOPIC, "--camera-info", str(cam_yaml),
                 "--pose-from", pose_from, "--optimizer", "cmaes", "--frames", "2", "--stride", "5",
                 "--max-iter", "25", "--out", str(out)]) == 0
    truth = json.loads((tmp_path / "field.truth.json").read_text())
    ok, detail = _recovered(out, truth)
    assert ok, detail
    summary = json.loads((tmp_path / "fit.json").read_text())
    assert summary["pose_source"] == pose_from
    assert [f["image_index"] for f in summary["frames"]] == [0, 5]
    err = capsys.readouterr().err
    if pose_in == "none":
        for f in summary["frames"]:
            assert f["pose"]["source"] == "markers" and f["pose"]["reprojection_rms_px"] < 1.5
        assert "pose from markers" in err and "px RMS" in err
