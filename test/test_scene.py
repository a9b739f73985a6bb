"""Tests of uw_sil.sim.scene: the procedural panel, the shipped model, loading, labels and poses."""
import math

import numpy as np
import pytest
import trimesh

from uw_sil.sim import scene as S
from uw_sil.sim.camera import CameraModel

EXPECTED_NODES = {
    "plate_body", "plate_face",
    *(f"valve{i}_{p}" for i in (1, 2, 3) for p in ("flange", "stem", "hub", "tbar")),
    *(f"lever{i}_{p}" for i in (1, 2) for p in ("base", "arm", "knob")),
    "hotstab1_receptacle",
}


@pytest.fixture(scope="module")
def panel():
    return S.build_panel()


def _texture(scene, node):
    geom = scene.geometry[scene.graph[node][1]]
    return np.asarray(geom.visual.material.baseColorTexture.convert("RGB"))


def test_panel_nodes_classes_and_labels(panel):
    names = set(panel.graph.nodes_geometry)
    assert names == EXPECTED_NODES
    assert {S.part_class(n) for n in names} == {"plate", "valve", "lever", "hotstab"}
    assert all(S.node_label(n) == S.LABEL_PANEL for n in names)
    # every node sits at the identity: vertices are already in the panel frame
    for n in names:
        assert np.allclose(panel.graph[n][0], np.eye(4))


def test_panel_frame_convention(panel):
    w, h = S.PANEL_SIZE
    lo, hi = panel.bounds
    assert np.allclose(lo, [-w / 2, -h / 2, -S.PANEL_THICKNESS])
    assert np.allclose(hi[:2], [w / 2, h / 2])
    assert 0.1 < hi[2] < 0.3  # handles protrude towards the viewer (+z)
    face = panel.geometry[panel.graph["plate_face"][1]]
    assert np.allclose(face.vertices[:, 2], 0.0)
    assert np.allclose(face.face_normals, [0, 0, 1])  # front face points to +z
    for n in panel.graph.nodes_geometry:
        if not n.startswith("plate"):
            assert panel.geometry[panel.graph[n][1]].bounds[0][2] >= -1e-12, n
    assert np.allclose(S.panel_corners()[:, :2], [[-w / 2, h / 2], [w / 2, h / 2], [w / 2, -h / 2], [-w / 2, -h / 2]])


def test_build_is_deterministic(panel):
    again = S.build_panel()
    for n in panel.graph.nodes_geometry:
        a, b = panel.geometry[panel.graph[n][1]], again.geometry[again.graph[n][1]]
        assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces), n
    assert np.array_equal(_texture(panel, "plate_face"), _texture(again, "plate_face"))


def test_shipped_glb_matches_build_panel(panel):
    assert S.default_model_path().is_file(), "run `python -m uw_sil.sim.scene` to write the shipped model"
    shipped = S.load_model()
    assert set(shipped.graph.nodes_geometry) == set(panel.graph.nodes_geometry)
    for n in panel.graph.nodes_geometry:
        a = panel.geometry[panel.graph[n][1]]
        b = shipped.geometry[shipped.graph[n][1]]
        Ta, Tb = panel.graph[n][0], shipped.graph[n][0]
        assert len(a.vertices) == len(b.vertices) and len(a.faces) == len(b.faces), n
        va = trimesh.transform_points(a.vertices, Ta)
        vb = trimesh.transform_points(b.vertices, Tb)
        assert np.abs(va - vb).max() < 1e-6, n  # GLB stores float32
        if a.visual.kind == "vertex":
            assert np.array_equal(a.visual.vertex_colors, b.visual.vertex_colors), n
    assert np.allclose(shipped.bounds, panel.bounds, atol=1e-6)
    assert np.array_equal(_texture(shipped, "plate_face"), _texture(panel, "plate_face"))


def test_write_default_model_roundtrip(tmp_path, panel):
    path = S.write_default_model(tmp_path / "panel.glb")
    loaded = S.load_model(path)
    assert set(loaded.graph.nodes_geometry) == EXPECTED_NODES
    with pytest.raises(ValueError, match="GLB"):
        S.write_default_model(tmp_path / "panel.obj")


def test_texture_markers_are_detectable():
    import cv2

    tex = S.panel_texture()
    assert tex.shape == (1400, 2000, 3) and tex.dtype == np.uint8
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
    corners, ids, _ = detector.detectMarkers(cv2.cvtColor(tex, cv2.COLOR_RGB2GRAY))
    assert ids is not None and sorted(ids.ravel().tolist()) == [0, 1, 2, 3]
    # marker 0 is top-left: its centre at (-390, +240) mm -> texture pixel (220, 220)
    c0 = corners[list(ids.ravel()).index(0)][0].mean(axis=0)
    assert np.allclose(c0, [220, 220], atol=1.5)
    # a saturated industrial colour dominates the plate
    hsv = cv2.cvtColor(tex, cv2.COLOR_RGB2HSV)
    assert np.mean((hsv[..., 1] > 200) & (hsv[..., 2] > 200)) > 0.4


@pytest.mark.parametrize("ext", [".stl", ".obj", ".ply"])
def test_load_user_mesh(tmp_path, ext):
    box = trimesh.creation.box(extents=(0.4, 0.3, 0.05))
    path = tmp_path / f"user{ext}"
    box.export(path)
    scene = S.load_model(path)
    assert isinstance(scene, trimesh.Scene)
    assert np.allclose(scene.bounds, box.bounds, atol=1e-6)
    assert all(S.node_label(n) == 1 for n in scene.graph.nodes_geometry)


def test_load_model_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        S.load_model(tmp_path / "missing.glb")
    bad_ext = tmp_path / "model.txt"
    bad_ext.write_text("not a mesh")
    with pytest.raises(ValueError, match="unsupported"):
        S.load_model(bad_ext)
    corrupt = tmp_path / "corrupt.glb"
    corrupt.write_bytes(b"\x00\x01garbage" * 10)
    with pytest.raises(ValueError, match="could not read"):
        S.load_model(corrupt)
    empty = tmp_path / "empty.stl"
    empty.write_text("solid empty\nendsolid empty\n")
    with pytest.raises(ValueError):
        S.load_model(empty)


def test_node_label_and_part_class():
    assert S.node_label("valve1_tbar") == 1
    assert S.node_label("seafloor") == 2
    assert S.node_label("seafloor_rocks") == 2
    assert S.node_label("label7_buoy") == 7
    assert S.node_label("labels_plate") == 1  # no number: ordinary panel part
    with pytest.raises(ValueError):
        S.node_label("label300_x")
    with pytest.raises(TypeError):
        S.node_label(3)
    assert S.part_class("valve2_tbar") == "valve"
    assert S.part_class("hotstab1_receptacle") == "hotstab"
    assert S.part_class("seafloor") == "seafloor"


def test_add_seafloor(panel):
    out = S.add_seafloor(panel, clearance=0.4, size=10.0)
    assert "seafloor" not in panel.graph.nodes  # input untouched
    names = set(out.graph.nodes_geometry)
    assert names == EXPECTED_NODES | {"seafloor", "stand_left", "stand_right"}
    assert S.node_label("seafloor") == 2 and S.node_label("stand_left") == 1
    floor = out.geometry[out.graph["seafloor"][1]]
    y_floor = panel.bounds[0][1] - 0.4
    assert np.allclose(floor.vertices[:, 1], y_floor)
    assert np.allclose(floor.face_normals, [0, 1, 0])
    assert np.allclose(floor.bounds[:, [0, 2]], [[-5, -5], [5, 5]])
    stand = out.geometry[out.graph["stand_left"][1]]
    assert np.isclose(stand.bounds[0][1], y_floor) and stand.bounds[1][2] <= panel.bounds[0][2] + 1e-12
    no_stand = S.add_seafloor(panel, y=-2.0, stand=False)
    assert set(no_stand.graph.nodes_geometry) == EXPECTED_NODES | {"seafloor"}
    with pytest.raises(ValueError):
        S.add_seafloor(out)
    with pytest.raises(TypeError):
        S.add_seafloor(trimesh.creation.box())


def test_seafloor_texture_tiles_seamlessly():
    tex = S.seafloor_texture(256, seed=3).astype(float)
    assert np.array_equal(tex, S.seafloor_texture(256, seed=3).astype(float))
    inner = np.abs(np.diff(tex, axis=1)).mean()
    seam = np.abs(tex[:, 0] - tex[:, -1]).mean()
    assert seam < 1.5 * inner
    inner_v = np.abs(np.diff(tex, axis=0)).mean()
    assert np.abs(tex[0] - tex[-1]).mean() < 1.5 * inner_v
    assert tex.std() > 5  # has texture


def _cam_point(T, p):
    return T[:3, :3] @ np.asarray(p, float) + T[:3, 3]


def test_facing_pose_straight_on():
    T = S.facing_pose(2.0)
    assert np.allclose(T[:3, :3], np.diag([1.0, -1.0, -1.0]))
    assert np.allclose(T[:3, 3], [0, 0, 2.0])
    T = S.facing_pose(1.5, x=0.2, y=-0.1)
    assert np.allclose(T[:3, 3], [-0.2, -0.1, 1.5])
    cam = CameraModel()
    # panel right edge appears on the image right, the panel top at the image top
    uv = cam.project(np.array([_cam_point(S.facing_pose(2.0), p) for p in S.panel_corners()]))
    assert uv[0, 0] < cam.cx < uv[1, 0] and uv[0, 1] < cam.cy < uv[3, 1]


def test_facing_pose_angles():
    cam = CameraModel()
    d, yaw, pitch = 2.5, 0.4, 0.3
    T = S.facing_pose(d, x=0.1, y=0.05, yaw=yaw, pitch=pitch, roll=0.2)
    R = T[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    target = _cam_point(T, [0.1, 0.05, 0.0])
    assert np.allclose(target, [0, 0, d])  # target on the optical axis at the distance
    # camera position in the panel frame
    c = -R.T @ T[:3, 3]
    expected = np.array([0.1, 0.05, 0]) + d * np.array([math.sin(yaw) * math.cos(pitch), math.sin(pitch),
                                                          math.cos(yaw) * math.cos(pitch)])
    assert np.allclose(c, expected)
    # positive roll: a point right of the target moves up in the image
    p0 = cam.project(_cam_point(S.facing_pose(2.0), [0.3, 0, 0])[None])[0]
    p1 = cam.project(_cam_point(S.facing_pose(2.0, roll=0.3), [0.3, 0, 0])[None])[0]
    assert p1[1] < p0[1] - 10
    # positive yaw: the panel's right side comes closer to the camera
    Ty = S.facing_pose(2.0, yaw=0.5)
    assert _cam_point(Ty, [0.5, 0, 0])[2] < _cam_point(Ty, [-0.5, 0, 0])[2]


@pytest.mark.parametrize("kw", [dict(distance=0), dict(distance=-1), dict(distance=float("nan")),
                                dict(distance=1, pitch=math.pi / 2), dict(distance=1, yaw="a")])
def test_facing_pose_rejects(kw):
    with pytest.raises(ValueError):
        S.facing_pose(**kw)
