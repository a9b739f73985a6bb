"""Procedural subsea intervention panel, model loading and camera poses around it.

The default scene is a model of an ROV intervention panel in the spirit of the DexROV
test panel: a 1.0 m x 0.7 m safety-yellow plate with a hazard-striped border, three rotary
valves with T-handles, two levers, a hot-stab receptacle, and printed high-contrast
markings (title plate, dials with tick marks, numbered label plates, four ArUco markers)
so that feature detectors find structure on it. :func:`build_panel` builds it with trimesh;
the same model is shipped as ``uw_sil/sim/models/intervention_panel.glb`` (installed to
``share/uw_sil/models/``), and :func:`load_model` reads it or any user mesh instead.

Panel frame
-----------
Origin at the centre of the plate's **front** face; x to the right, y **up**, z out of the
front face (towards a viewer). The plate occupies ``z in [-PANEL_THICKNESS, 0]``; handles
protrude to ``z > 0``. Units are metres. A camera looking straight at the panel from
``d`` metres therefore has ``T_cam_panel = [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, d],
[0, 0, 0, 1]]`` (see :func:`facing_pose`); poses are 4x4 ``T_cam_panel``, the panel frame
expressed in the camera optical frame (REP 103: x right, y down, z forward).

Labels
------
Every node of a model maps to a label id (what the renderer writes into its label mask):

- ``0`` water / nothing (no node has it);
- ``1`` the intervention panel: every node not matched below (plate, handles, markings,
  and every part of a user mesh);
- ``2`` the seafloor: node names starting with ``"seafloor"`` (see :func:`add_seafloor`);
- ``N`` (1..255): node names starting with ``"label<N>_"``, e.g. ``"label3_buoy"``.
  Name your nodes this way in Blender/trimesh to give extra objects their own label.

:func:`node_label` implements this; the renderer also accepts an explicit ``{node: id}``
override. Node names of the procedural panel are ``<class><index>_<part>`` (for example
``"valve2_tbar"``); :func:`part_class` returns the class (``"plate"``, ``"valve"``,
``"lever"``, ``"hotstab"``, ``"stand"``, ``"seafloor"``).

Colours
-------
Colours are stored as 8-bit RGB values (vertex colours and base-colour textures, no
lighting baked in); the renderer treats ``value / 255`` as the surface albedo.
"""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from .transforms import look_at

__all__ = [
    "PANEL_SIZE",
    "PANEL_THICKNESS",
    "LABEL_WATER",
    "LABEL_PANEL",
    "LABEL_SEAFLOOR",
    "SUPPORTED_EXTENSIONS",
    "build_panel",
    "panel_texture",
    "panel_corners",
    "add_seafloor",
    "seafloor_texture",
    "default_model_path",
    "write_default_model",
    "load_model",
    "node_label",
    "part_class",
    "facing_pose",
]

#: Plate width (x) and height (y) in metres.
PANEL_SIZE = (1.0, 0.7)
#: Plate thickness in metres (the plate occupies z in [-PANEL_THICKNESS, 0]).
PANEL_THICKNESS = 0.03

LABEL_WATER = 0
LABEL_PANEL = 1
LABEL_SEAFLOOR = 2

#: File extensions :func:`load_model` accepts.
SUPPORTED_EXTENSIONS = (".glb", ".gltf", ".obj", ".stl", ".ply")

# Texture resolution of the printed front face: 2 texels per millimetre.
_TEX_PER_MM = 2

# 8-bit RGB albedo of the paints and materials.
_YELLOW = (240, 180, 0)  # safety yellow (RAL 1003-like)
_BLACK = (25, 25, 25)  # black paint reflects a few percent
_WHITE = (235, 235, 230)
_ORANGE = (225, 75, 20)  # T-handles
_RED = (200, 30, 30)  # lever knobs
_STEEL = (160, 160, 165)
_DARK = (60, 62, 66)  # flanges, lever bases

# Layout in millimetres in the panel frame (x right, y up, origin at the plate centre).
_VALVES = (("V-101", -250.0, 40.0, 0.0), ("V-102", 0.0, 40.0, 90.0), ("V-103", 250.0, 40.0, 45.0))
_LEVERS = (("L-1", -170.0, -215.0, 30.0), ("L-2", 170.0, -215.0, -30.0))
_HOTSTABS = (("HS-1", 0.0, -205.0),)
_MARKERS = ((0, -390.0, 240.0), (1, 390.0, 240.0), (2, -390.0, -240.0), (3, 390.0, -240.0))
_BORDER_MM = 40.0

_LABEL_PREFIX = re.compile(r"^label(\d+)_")


# ----------------------------------------------------------------------------- texture


def _px(x_mm: float, y_mm: float) -> tuple[int, int]:
    """Texture pixel (column, row) of a panel point given in millimetres."""
    w_mm, h_mm = PANEL_SIZE[0] * 1000.0, PANEL_SIZE[1] * 1000.0
    return (int(round((x_mm + w_mm / 2) * _TEX_PER_MM)), int(round((h_mm / 2 - y_mm) * _TEX_PER_MM)))


def _rect(img, x0, y0, x1, y1, color):
    import cv2

    cv2.rectangle(img, _px(x0, y1), _px(x1, y0), color, thickness=-1, lineType=cv2.LINE_8)


def _text(img, text, x_mm, y_mm, height_mm, color, thickness_mm=None, font=None):
    """Hershey text centred on (x_mm, y_mm) with cap height ``height_mm``."""
    import cv2

    font = cv2.FONT_HERSHEY_DUPLEX if font is None else font
    t = max(1, int(round((thickness_mm if thickness_mm else height_mm / 8.0) * _TEX_PER_MM)))
    (w1, h1), _ = cv2.getTextSize(text, font, 1.0, t)
    scale = height_mm * _TEX_PER_MM / h1
    (w, h), _ = cv2.getTextSize(text, font, scale, t)
    c, r = _px(x_mm, y_mm)
    cv2.putText(img, text, (c - w // 2, r + h // 2), font, scale, color, t, cv2.LINE_AA)


def panel_texture() -> np.ndarray:
    """The printed front face of the panel as an RGB image.

    Returns
    -------
    image : (1400, 2000, 3) uint8
        Row 0 is the top edge of the plate (y = +0.35 m), column 0 its left edge
        (x = -0.5 m); 2 texels per millimetre.

    Notes
    -----
    Deterministic: drawn with OpenCV's Hershey fonts and primitives and ArUco markers
    (``DICT_4X4_50``, ids 0-3, 90 mm, in the four inner corners), no randomness.
    """
    import cv2

    w_mm, h_mm = PANEL_SIZE[0] * 1000.0, PANEL_SIZE[1] * 1000.0
    W, H = int(w_mm * _TEX_PER_MM), int(h_mm * _TEX_PER_MM)
    img = np.empty((H, W, 3), np.uint8)
    img[:] = _YELLOW

    # Hazard border: 45-degree black/yellow stripes, 80 mm period.
    b = int(_BORDER_MM * _TEX_PER_MM)
    rows, cols = np.mgrid[0:H, 0:W]
    border = (rows < b) | (rows >= H - b) | (cols < b) | (cols >= W - b)
    stripes = ((cols + rows) // int(40 * _TEX_PER_MM)) % 2 == 0
    img[border & stripes] = _BLACK
    hw, hh = w_mm / 2 - _BORDER_MM, h_mm / 2 - _BORDER_MM
    inner_edges = ((-hw, hh - 3, hw, hh), (-hw, -hh, hw, -hh + 3), (-hw, -hh, -hw + 3, hh), (hw - 3, -hh, hw, hh))
    for x0, y0, x1, y1 in inner_edges:  # 3 mm black line inside the striped border
        _rect(img, x0, y0, x1, y1, _BLACK)

    # Title plate and subtitle.
    _rect(img, -265, 240, 265, 300, _BLACK)
    _text(img, "INTERVENTION PANEL IP-01", 0, 270, 26, _WHITE)
    _text(img, "ROV INTERFACE  ISO 13628-8  CLASS 4", 0, 215, 15, _BLACK)

    # Valve dials: white ring, 12 ticks, OPEN/SHUT arrows, label plate.
    for name, x, y, _ in _VALVES:
        c, r = _px(x, y)
        px = _TEX_PER_MM
        cv2.circle(img, (c, r), int(110 * px), _BLACK, -1, cv2.LINE_AA)
        cv2.circle(img, (c, r), int(104 * px), _WHITE, -1, cv2.LINE_AA)
        cv2.circle(img, (c, r), int(80 * px), _YELLOW, -1, cv2.LINE_AA)
        for k in range(12):
            a = math.radians(30 * k)
            r0, r1 = (84, 103) if k % 3 == 0 else (92, 103)
            p0 = (int(round(c + r0 * px * math.cos(a))), int(round(r - r0 * px * math.sin(a))))
            p1 = (int(round(c + r1 * px * math.cos(a))), int(round(r - r1 * px * math.sin(a))))
            cv2.line(img, p0, p1, _BLACK, int(5 * px) if k % 3 == 0 else int(2.5 * px), cv2.LINE_AA)
        cv2.ellipse(img, (c, r), (int(70 * px), int(70 * px)), 0, 200, 250, _BLACK, int(4 * px), cv2.LINE_AA)
        cv2.ellipse(img, (c, r), (int(70 * px), int(70 * px)), 0, 290, 340, _BLACK, int(4 * px), cv2.LINE_AA)
        for a_deg, sgn in ((250, 1), (290, -1)):
            a = math.radians(a_deg)
            tip = np.array([c + 70 * px * math.cos(a), r + 70 * px * math.sin(a)])
            tangent = sgn * np.array([-math.sin(a), math.cos(a)])
            normal = np.array([math.cos(a), math.sin(a)])
            pts = np.array([tip + 12 * px * tangent, tip - 4 * px * tangent + 9 * px * normal,
                            tip - 4 * px * tangent - 9 * px * normal])
            cv2.fillPoly(img, [np.round(pts).astype(np.int32)], _BLACK, cv2.LINE_AA)
        _text(img, "OPEN", x - 52, y + 52, 12, _BLACK)
        _text(img, "SHUT", x + 52, y + 52, 12, _BLACK)
        _rect(img, x - 60, y - 137, x + 60, y - 93, _BLACK)
        _rect(img, x - 57, y - 134, x + 57, y - 96, _WHITE)
        _text(img, name, x, y - 115, 22, _BLACK)

    # Lever slots with 0/1 positions and label plates.
    for name, x, y, _ in _LEVERS:
        _rect(img, x - 22, y - 80, x + 22, y + 80, _BLACK)
        _rect(img, x - 14, y - 72, x + 14, y + 72, _DARK)
        side = 1 if x < 0 else -1
        _text(img, "1", x + side * 42, y + 62, 20, _BLACK)
        _text(img, "0", x + side * 42, y - 62, 20, _BLACK)
        lx = x - side * 85
        _rect(img, lx - 48, y - 22, lx + 48, y + 22, _BLACK)
        _rect(img, lx - 45, y - 19, lx + 45, y + 19, _WHITE)
        _text(img, name, lx, y, 20, _BLACK)

    # Hot-stab receptacle: black bore, white ring, caption.
    for name, x, y in _HOTSTABS:
        c, r = _px(x, y)
        cv2.circle(img, (c, r), int(72 * _TEX_PER_MM), _WHITE, -1, cv2.LINE_AA)
        cv2.circle(img, (c, r), int(62 * _TEX_PER_MM), _BLACK, -1, cv2.LINE_AA)
        _text(img, "HOT STAB " + name, x, y - 84, 12, _BLACK)

    # ArUco markers with a white quiet zone.
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    side_px = int(90 * _TEX_PER_MM)
    for marker_id, x, y in _MARKERS:
        _rect(img, x - 57, y - 57, x + 57, y + 57, _WHITE)
        m = cv2.aruco.generateImageMarker(dictionary, marker_id, side_px)
        c, r = _px(x - 45, y + 45)
        img[r:r + side_px, c:c + side_px] = np.where(m[..., None] > 127, np.array(_WHITE, np.uint8),
                                                      np.array(_BLACK, np.uint8))
    return img


# ----------------------------------------------------------------------------- geometry


def _colored(mesh, color):
    mesh.visual.vertex_colors = np.array([*color, 255], dtype=np.uint8)
    return mesh


def _translate(mesh, xyz):
    mesh.apply_translation(np.asarray(xyz, dtype=float))
    return mesh


def _textured_quad(corners, uv, image, name=None):
    """Two-triangle quad (corners counter-clockwise seen from its front) with a texture."""
    import trimesh
    from PIL import Image

    material = trimesh.visual.material.PBRMaterial(
        name=name, baseColorTexture=Image.fromarray(image), baseColorFactor=[255, 255, 255, 255],
        metallicFactor=0.0, roughnessFactor=1.0)
    visual = trimesh.visual.TextureVisuals(uv=np.asarray(uv, dtype=float), material=material)
    return trimesh.Trimesh(vertices=np.asarray(corners, dtype=float), faces=[[0, 1, 2], [0, 2, 3]],
                           visual=visual, process=False)


def panel_corners() -> np.ndarray:
    """The four corners of the plate's front face in the panel frame, (4, 3) float64.

    Order: top-left, top-right, bottom-right, bottom-left (as seen from the front).
    """
    w, h = PANEL_SIZE
    return np.array([[-w / 2, h / 2, 0.0], [w / 2, h / 2, 0.0], [w / 2, -h / 2, 0.0], [-w / 2, -h / 2, 0.0]])


def build_panel(sections: int = 48):
    """Build the procedural intervention panel.

    Parameters
    ----------
    sections : int, optional
        Number of facets around cylinders (>= 8).

    Returns
    -------
    scene : trimesh.Scene
        One node per part, every node at the identity transform (vertices are in the
        panel frame, see the module docstring). Node names are ``<class><i>_<part>``:
        ``plate_body``, ``plate_face`` (textured front), ``valve{1,2,3}_{flange,stem,hub,tbar}``,
        ``lever{1,2}_{base,arm,knob}``, ``hotstab1_receptacle``. All have label 1.

    Notes
    -----
    Deterministic: the same call returns the same vertices, faces, colours and texture.
    """
    import trimesh

    if int(sections) != sections or sections < 8:
        raise ValueError(f"sections must be an integer >= 8, got {sections!r}")
    sections = int(sections)
    w, h = PANEL_SIZE
    t = PANEL_THICKNESS
    parts: dict[str, trimesh.Trimesh] = {}

    # Plate: a box without its front face, plus the textured front quad at z = 0.
    box = trimesh.creation.box(extents=(w, h, t))
    box.apply_translation((0.0, 0.0, -t / 2))
    keep = box.face_normals[:, 2] < 0.5
    body = trimesh.Trimesh(vertices=box.vertices, faces=box.faces[keep], process=False)
    body.remove_unreferenced_vertices()
    parts["plate_body"] = _colored(body, _YELLOW)
    corners = panel_corners()[[3, 2, 1, 0]]  # bottom-left, bottom-right, top-right, top-left: CCW from +z
    uv = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]
    parts["plate_face"] = _textured_quad(corners, uv, panel_texture(), name="panel_face")

    mm = 1e-3
    for i, (_, x, y, angle) in enumerate(_VALVES, start=1):
        x, y = x * mm, y * mm
        parts[f"valve{i}_flange"] = _colored(_translate(
            trimesh.creation.cylinder(radius=0.05, height=0.02, sections=sections), (x, y, 0.01)), _DARK)
        parts[f"valve{i}_stem"] = _colored(_translate(
            trimesh.creation.cylinder(radius=0.014, height=0.08, sections=sections), (x, y, 0.06)), _STEEL)
        parts[f"valve{i}_hub"] = _colored(_translate(
            trimesh.creation.cylinder(radius=0.026, height=0.035, sections=sections), (x, y, 0.1075)), _BLACK)
        bar = trimesh.creation.box(extents=(0.20, 0.028, 0.028))
        bar.apply_transform(trimesh.transformations.rotation_matrix(math.radians(angle), (0, 0, 1)))
        parts[f"valve{i}_tbar"] = _colored(_translate(bar, (x, y, 0.107)), _ORANGE)

    for i, (_, x, y, tilt) in enumerate(_LEVERS, start=1):
        x, y = x * mm, y * mm
        parts[f"lever{i}_base"] = _colored(_translate(
            trimesh.creation.box(extents=(0.09, 0.09, 0.035)), (x, y, 0.0175)), _DARK)
        length = 0.18
        direction = np.array([0.0, math.sin(math.radians(tilt)), math.cos(math.radians(tilt))])
        arm = trimesh.creation.cylinder(radius=0.012, height=length, sections=sections)
        arm.apply_transform(trimesh.transformations.rotation_matrix(-math.radians(tilt), (1, 0, 0)))
        start = np.array([x, y, 0.035])
        parts[f"lever{i}_arm"] = _colored(_translate(arm, start + direction * length / 2), _STEEL)
        knob = trimesh.creation.uv_sphere(radius=0.03, count=(sections // 2, sections))
        parts[f"lever{i}_knob"] = _colored(_translate(knob, start + direction * length), _RED)

    for i, (_, x, y) in enumerate(_HOTSTABS, start=1):
        ring = trimesh.creation.annulus(r_min=0.031, r_max=0.055, height=0.07, sections=sections)
        parts[f"hotstab{i}_receptacle"] = _colored(_translate(ring, (x * mm, y * mm, 0.035)), _STEEL)

    scene = trimesh.Scene()
    for name, mesh in parts.items():
        scene.add_geometry(mesh, node_name=name, geom_name=name)
    return scene


def seafloor_texture(size: int = 1024, seed: int = 0) -> np.ndarray:
    """A tileable sandy-seafloor texture (``size`` x ``size`` RGB uint8).

    Fractal (1/f) noise synthesised in the Fourier domain, so the image wraps around
    seamlessly, plus sand ripples and scattered pebbles (also wrapped). Deterministic
    for a given ``seed``.
    """
    import cv2

    if int(size) != size or size < 16:
        raise ValueError(f"size must be an integer >= 16, got {size!r}")
    size = int(size)
    rng = np.random.default_rng(seed)
    f = np.fft.fftfreq(size)
    k = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    k[0, 0] = 1.0
    spectrum = (rng.standard_normal((size, size)) + 1j * rng.standard_normal((size, size))) / k ** 1.6
    spectrum[0, 0] = 0.0
    noise = np.fft.ifft2(spectrum).real
    noise /= noise.std()
    fine = rng.standard_normal((size, size))
    yy, xx = np.mgrid[0:size, 0:size] / size
    ripples = np.sin(2 * np.pi * (9 * xx + 3 * yy) + 1.5 * noise)
    shade = 1.0 + 0.12 * noise + 0.06 * ripples + 0.05 * fine
    base = np.array([150.0, 136.0, 108.0])
    img = np.clip(shade[..., None] * base, 0, 255).astype(np.uint8)
    big = np.zeros((3 * size, 3 * size, 3), np.uint8)
    big[:] = np.tile(img, (3, 3, 1))
    n_pebbles = size // 3
    centres = rng.uniform(0, size, (n_pebbles, 2)) + size
    radii = rng.gamma(2.0, size / 600.0, n_pebbles) + 1.0
    tones = rng.uniform(0.35, 1.35, n_pebbles)
    for (cx, cy), rad, tone in zip(centres, radii, tones):
        color = tuple(int(v) for v in np.clip(base * tone, 0, 255))
        for dx in (-size, 0, size):
            for dy in (-size, 0, size):
                cv2.circle(big, (int(cx + dx), int(cy + dy)), int(rad), color, -1, cv2.LINE_AA)
    return np.ascontiguousarray(big[size:2 * size, size:2 * size])


def add_seafloor(scene, y: float | None = None, clearance: float = 0.5, size: float = 40.0,
                 tile: float = 2.0, seed: int = 0, stand: bool = True):
    """Return a copy of ``scene`` with a textured, horizontal seafloor plane (label 2).

    Parameters
    ----------
    scene : trimesh.Scene
        A model in the panel frame (y up).
    y : float, optional
        Height of the seafloor in the panel frame. Default: ``clearance`` below the
        lowest point of ``scene``.
    clearance : float, optional
        Gap between the model and the seafloor when ``y`` is None, metres (>= 0).
    size : float, optional
        Side of the square seafloor, centred below the panel origin, metres.
    tile : float, optional
        Side of one repetition of the texture (:func:`seafloor_texture`), metres.
    seed : int, optional
        Texture seed.
    stand : bool, optional
        Also add two dark 60 mm square posts (``"stand_left"``, ``"stand_right"``, label 1)
        standing on the seafloor behind the model (just behind its rearmost point, at 15 %
        and 85 % of its width), up to the model's vertical centre, so that the panel does
        not float.

    Returns
    -------
    scene : trimesh.Scene
        A copy with an extra node ``"seafloor"`` (and the stand).
    """
    import trimesh

    if not isinstance(scene, trimesh.Scene):
        raise TypeError(f"scene must be a trimesh.Scene, got {type(scene).__name__}")
    if "seafloor" in scene.graph.nodes:
        raise ValueError("scene already has a 'seafloor' node")
    if not (size > 0 and tile > 0 and clearance >= 0):
        raise ValueError(f"need size > 0, tile > 0, clearance >= 0; got {size}, {tile}, {clearance}")
    if y is None:
        if scene.is_empty:
            raise ValueError("cannot place the seafloor below an empty scene; pass y")
        y = float(scene.bounds[0][1]) - clearance
    a = size / 2.0
    corners = [[-a, y, a], [a, y, a], [a, y, -a], [-a, y, -a]]  # counter-clockwise seen from +y
    uv = [[0.0, 0.0], [size / tile, 0.0], [size / tile, size / tile], [0.0, size / tile]]
    floor = _textured_quad(corners, uv, seafloor_texture(seed=seed), name="seafloor")
    out = scene.copy()
    out.add_geometry(floor, node_name="seafloor", geom_name="seafloor")
    if stand and not scene.is_empty:
        (x0, y0, z0), (x1, y1, _) = scene.bounds
        top = (y0 + y1) / 2.0
        post = 0.06
        if top > y:
            for side, xc in (("left", x0 + 0.15 * (x1 - x0)), ("right", x0 + 0.85 * (x1 - x0))):
                name = f"stand_{side}"
                if name in out.graph.nodes:
                    raise ValueError(f"scene already has a {name!r} node")
                box = trimesh.creation.box(extents=(post, top - y, post))
                box.apply_translation((xc, (top + y) / 2.0, z0 - post / 2.0))
                out.add_geometry(_colored(box, _DARK), node_name=name, geom_name=name)
    return out


# ----------------------------------------------------------------------------- files


def default_model_path() -> Path:
    """Path of the shipped panel model, ``uw_sil/sim/models/intervention_panel.glb``."""
    return Path(__file__).resolve().parent / "models" / "intervention_panel.glb"


def write_default_model(path=None) -> Path:
    """(Re)write the panel built by :func:`build_panel` as a GLB file.

    Parameters
    ----------
    path : str or Path, optional
        Output file; default :func:`default_model_path` (the shipped model).
        Run ``python -m uw_sil.sim.scene`` to regenerate the shipped file.

    Returns
    -------
    path : Path
    """
    path = default_model_path() if path is None else Path(path)
    if path.suffix.lower() != ".glb":
        raise ValueError(f"the model is written as GLB; got {path.name!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    data = build_panel().export(file_type="glb")
    path.write_bytes(data)
    return path


def load_model(path=None):
    """Load a model for rendering.

    Parameters
    ----------
    path : str or Path, optional
        A mesh file (``.glb``, ``.gltf``, ``.obj``, ``.stl``, ``.ply``) expressed in the
        panel frame (metres, y up, the camera-facing side towards +z). Default: the
        shipped intervention panel (:func:`default_model_path`).

    Returns
    -------
    scene : trimesh.Scene
        Node names are kept for glTF; other formats give one or a few generic nodes,
        which get label 1 (see :func:`node_label`).

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        If the extension is not supported, the file cannot be parsed, or it holds no
        triangles.
    """
    import trimesh

    path = default_model_path() if path is None else Path(path)
    if not path.is_file():
        hint = " (regenerate it with `python -m uw_sil.sim.scene`)" if path == default_model_path() else ""
        raise FileNotFoundError(f"model file not found: {path}{hint}")
    ext = path.suffix.lower()
    if ext not in SUPPORTED_EXTENSIONS:
        raise ValueError(f"unsupported model format {ext!r} for {path}; use one of {', '.join(SUPPORTED_EXTENSIONS)}")
    try:
        scene = trimesh.load_scene(str(path), file_type=ext[1:])
    except Exception as exc:  # trimesh raises many different types for corrupt files
        raise ValueError(f"could not read model {path}: {type(exc).__name__}: {exc}") from exc
    n_faces = sum(len(g.faces) for g in scene.geometry.values() if isinstance(g, trimesh.Trimesh))
    if n_faces == 0:
        raise ValueError(f"model {path} contains no triangles")
    return scene


# ----------------------------------------------------------------------------- labels, poses


def node_label(name: str) -> int:
    """Label id of a node from its name (see the module docstring).

    ``"label<N>_..."`` -> N (1..255), ``"seafloor..."`` -> 2, anything else -> 1.
    """
    if not isinstance(name, str):
        raise TypeError(f"node name must be a str, got {type(name).__name__}")
    m = _LABEL_PREFIX.match(name)
    if m:
        n = int(m.group(1))
        if not 1 <= n <= 255:
            raise ValueError(f"label id in node name {name!r} must be in 1..255")
        return n
    if name.startswith("seafloor"):
        return LABEL_SEAFLOOR
    return LABEL_PANEL


def part_class(name: str) -> str:
    """Part class of a node name: the leading letters, e.g. ``"valve2_tbar" -> "valve"``."""
    if not isinstance(name, str):
        raise TypeError(f"node name must be a str, got {type(name).__name__}")
    m = re.match(r"[A-Za-z]+", name)
    return m.group(0).lower() if m else ""


def facing_pose(distance: float, x: float = 0.0, y: float = 0.0, yaw: float = 0.0, pitch: float = 0.0,
                roll: float = 0.0) -> np.ndarray:
    """Camera pose looking at the panel front: ``T_cam_panel`` (4x4 float64).

    The camera looks at the panel point ``(x, y, 0)`` (which lands on the principal
    point) from ``distance`` metres away. With all angles zero it faces the plate
    squarely from ``(x, y, distance)`` in the panel frame, so ``R = diag(1, -1, -1)`` and
    ``t = (-x, y, distance)``.

    Parameters
    ----------
    distance : float
        Range from the optical centre to ``(x, y, 0)``, metres (> 0).
    x, y : float, optional
        Point of the panel plane the camera looks at, panel frame (x right, y up), metres.
    yaw : float, optional
        Viewing azimuth, radians: rotation of the viewpoint about the panel's y axis;
        positive moves the camera towards the panel's +x (right) side.
    pitch : float, optional
        Viewing elevation, radians, in (-pi/2, pi/2): positive moves the camera up
        (towards +y), looking down at the panel.
    roll : float, optional
        Rotation of the camera about its optical axis, radians. Positive turns the
        camera's x axis towards its y axis, so the panel appears rotated
        counter-clockwise in the image.

    Returns
    -------
    T_cam_panel : (4, 4) ndarray
    """
    vals = dict(distance=distance, x=x, y=y, yaw=yaw, pitch=pitch, roll=roll)
    for k, v in vals.items():
        if not isinstance(v, (int, float, np.floating, np.integer)) or not math.isfinite(v):
            raise ValueError(f"{k} must be a finite number, got {v!r}")
    if distance <= 0:
        raise ValueError(f"distance must be > 0, got {distance}")
    if not abs(pitch) < math.pi / 2:
        raise ValueError(f"pitch must be in (-pi/2, pi/2), got {pitch}")
    target = np.array([x, y, 0.0], dtype=float)
    direction = np.array([math.sin(yaw) * math.cos(pitch), math.sin(pitch), math.cos(yaw) * math.cos(pitch)])
    T_panel_cam = look_at(target + distance * direction, target, up=(0.0, 1.0, 0.0))
    c, s = math.cos(roll), math.sin(roll)
    Rz = np.eye(4)
    Rz[:2, :2] = [[c, -s], [s, c]]
    T_panel_cam = T_panel_cam @ Rz
    T = np.eye(4)
    R = T_panel_cam[:3, :3]
    T[:3, :3] = R.T
    T[:3, 3] = -R.T @ T_panel_cam[:3, 3]
    return T


if __name__ == "__main__":  # regenerate the shipped model
    print(write_default_model())
