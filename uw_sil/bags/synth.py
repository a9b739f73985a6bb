"""Synthetic field trials: an ROV approaching the panel, rendered and degraded with known parameters.

The ground truth (parameters, fog mode, noise, seed, trajectory) goes to a sidecar JSON next to the
bag, never into the bag's topics, so tools reading the bag cannot see it.
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Iterator, Optional

import numpy as np

from ..sim.camera import CameraModel
from .._shared.fileio import write_text_atomic
from ..sim.params import UnderwaterParams

__all__ = ["SensorNoise", "approach_trajectory", "approach_path", "add_sensor_noise", "truth_path", "synthesize_trial",
           "load_truth", "field_tf_tree", "DEFAULT_TRUTH", "POSE_IN", "TF_TREE_FRAMES"]

#: How :func:`synthesize_trial` records the panel pose: a PoseStamped topic (plus camera -> panel on /tf),
#: a navigation tf tree only, or nothing (field bags without any pose: use the markers).
POSE_IN = ("topic", "tf", "none")

DEFAULT_TRUTH = UnderwaterParams(a=(0.42, 0.11, 0.08), b=(0.06, 0.32, 0.42), rho_f=0.08)

#: Renders of at least this many pixels are made side by side (:func:`uw_sil.sim.stream.stream_frames`): 30 frames
#: at 640x480 took 1.25 s instead of 1.59 (base model) and 2.79 s instead of 4.92 (lamps, particles, noise); at
#: 320x240 and 160x120 the threads cost more than they gave (0.80-0.98x), so smaller frames are made one at a time.
STREAM_MIN_PIXELS = 640 * 480


@dataclass(frozen=True)
class SensorNoise:
    """Camera noise before 8-bit quantization: Poisson-Gaussian (shot + read noise), in [0, 1] units.

    ``var = read_sigma^2 + shot_gain * I``. Defaults: 1 grey level of read noise and about 2.3 levels
    at mid grey (3.3 at white), like a well-exposed HD camera before compression.
    """

    read_sigma: float = 1.0 / 255.0
    shot_gain: float = 0.04 / 255.0

    def __post_init__(self):
        if self.read_sigma < 0 or self.shot_gain < 0:
            raise ValueError("noise levels must be >= 0")


def add_sensor_noise(img: np.ndarray, noise: SensorNoise, rng: np.random.Generator) -> np.ndarray:
    """Noise and 8-bit quantization of a float image in [0, 1] -> uint8 (H, W, 3)."""
    img = np.asarray(img, dtype=np.float32)
    sigma = np.sqrt(noise.read_sigma ** 2 + noise.shot_gain * np.clip(img, 0, 1)).astype(np.float32)
    noisy = img + sigma * rng.standard_normal(img.shape, dtype=np.float32)
    return np.clip(np.rint(noisy * 255.0), 0, 255).astype(np.uint8)


def approach_path(start_m: float = 4.0, end_m: float = 1.2,
                  rng: Optional[np.random.Generator] = None) -> Callable[[float], np.ndarray]:
    """The approach of :func:`approach_trajectory` as a function of progress ``s`` (0: start, 1: end).

    Returns ``pose(s) -> T_cam_panel``, smooth in ``s`` (also outside [0, 1], e.g. for navigation
    samples recorded before the first and after the last frame).
    """
    from ..sim.scene import facing_pose

    if not (0 < end_m and 0 < start_m):
        raise ValueError("ranges must be positive")
    rng = np.random.default_rng(0) if rng is None else rng
    ph = rng.uniform(0, 2 * math.pi, 6)

    def pose(s: float) -> np.ndarray:
        d = start_m + (end_m - start_m) * (0.5 - 0.5 * math.cos(math.pi * s))   # ease in/out
        t = 2 * math.pi * s
        return facing_pose(
            d,
            x=0.06 * math.sin(1.3 * t + ph[0]),
            y=0.04 * math.sin(0.9 * t + ph[1]),
            yaw=math.radians(6.0) * math.sin(0.7 * t + ph[2]),
            pitch=math.radians(4.0) * math.sin(1.1 * t + ph[3]),
            roll=math.radians(2.0) * math.sin(0.5 * t + ph[4]),
        )
    return pose


def approach_trajectory(n_frames: int, start_m: float = 4.0, end_m: float = 1.2,
                        rng: Optional[np.random.Generator] = None) -> list[np.ndarray]:
    """Panel poses in the camera optical frame for an ROV closing in on the panel.

    Range decreases smoothly from ``start_m`` to ``end_m`` while the vehicle sways and yaws a little
    (a few centimetres and degrees, as a station-keeping ROV does).
    """
    if n_frames < 1:
        raise ValueError("need at least one frame")
    path = approach_path(start_m, end_m, rng)
    return [path(k / max(1, n_frames - 1)) for k in range(n_frames)]


#: Frames of the tf tree written by ``synthesize_trial(pose_in="tf")``: ``map -> odom -> base_link ->
#: camera_optical_frame`` (vehicle navigation on /tf, the rest on /tf_static) and ``map -> panel``.
TF_TREE_FRAMES = ("map", "odom", "base_link", "camera_optical_frame", "panel")


def _rigid(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _inv(T) -> np.ndarray:
    return _rigid(T[:3, :3].T, -T[:3, :3].T @ T[:3, 3])


def field_tf_tree(camera_frame: str = "camera_optical_frame", panel_frame: str = "panel"):
    """The static part of a field-style tf tree, and the vehicle pose that explains a camera pose.

    Returns
    -------
    static : list of (parent, child, 4x4)
        ``map -> odom`` (a fixed offset, as after a navigation reset), ``base_link -> camera_frame``
        (a camera looking forward and 10 degrees down, 0.8 m ahead of the vehicle centre), and
        ``map -> panel_frame`` (the panel on the seafloor at 45 m depth, its face towards -x).
    base_in_odom : callable(T_cam_panel) -> 4x4
        ``T_odom_base`` that places the camera at ``T_cam_panel`` from the panel.
    """
    from scipy.spatial.transform import Rotation

    T_map_odom = _rigid(Rotation.from_euler("z", 0.3).as_matrix(), [2.0, -1.5, 0.0])
    R_base_cam = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])   # optical: z fwd, x right, y down
    R_base_cam = R_base_cam @ Rotation.from_euler("x", math.radians(-10.0)).as_matrix()  # tilted 10 deg down
    T_base_cam = _rigid(R_base_cam, [0.8, 0.1, -0.2])
    R_map_panel = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])   # face (panel z) towards map -x
    T_map_panel = _rigid(R_map_panel, [12.0, -3.0, -45.0])
    static = [("map", "odom", T_map_odom), ("base_link", camera_frame, T_base_cam), ("map", panel_frame, T_map_panel)]

    def base_in_odom(T_cam_panel) -> np.ndarray:
        return _inv(T_map_odom) @ T_map_panel @ _inv(np.asarray(T_cam_panel, dtype=float)) @ _inv(T_base_cam)
    return static, base_in_odom


def truth_path(bag_path) -> Path:
    """Sidecar ground-truth file of a bag: ``trial.mcap`` -> ``trial.truth.json`` (same folder)."""
    p = Path(bag_path)
    stem = p.name
    for ext in (".mcap", ".db3", ".bag"):
        if stem.endswith(ext):
            stem = stem[: -len(ext)]
    return p.with_name(stem + ".truth.json")


def load_truth(bag_path) -> dict:
    """Read the sidecar of :func:`truth_path`; ``params`` becomes an :class:`UnderwaterParams`."""
    path = truth_path(bag_path)
    if not path.exists():
        raise FileNotFoundError(f"no ground-truth sidecar {path} for {bag_path}")
    d = json.loads(path.read_text())
    d["params"] = UnderwaterParams.from_dict(d["params"])
    return d


def synthesize_trial(out, n_frames: int = 20, seed: int = 0, params: UnderwaterParams = DEFAULT_TRUTH,
                     camera: Optional[CameraModel] = None, storage: Optional[str] = None, fog: str = "exp2",
                     noise: SensorNoise = SensorNoise(), model=None, start_m: float = 4.0, end_m: float = 1.2,
                     rate_hz: float = 10.0, effects=None, overwrite: bool = False,
                     progress: Optional[Callable[[int, int], None]] = None, image_topic: str = "/camera/image_raw",
                     info_topic: Optional[str] = "/camera/camera_info", pose_topic: str = "/panel/pose",
                     image_format: str = "raw", jpeg_quality: int = 95, pose_in: str = "topic",
                     distortion=None, camera_yaml=None, panel_frame: str = "panel", tf_rate_factor: int = 10,
                     draw_seed: Optional[int] = None) -> dict:
    """Render an approach, degrade it with ``params``, add noise, and write a ROS 2 bag plus truth sidecar.

    Parameters
    ----------
    out : path
        Bag to write (see :func:`uw_sil.bags.writer.write_trial` for the layout: ``trial.mcap`` becomes the bag
        directory ``trial/`` with ``trial/trial.mcap``; the truth goes to ``trial.truth.json``).
    effects : str, dict or list, optional
        Physics the base model lacks, injected into the recorded frames: effects of
        :mod:`uw_sil.sim.effects` as ``"artificial_light=mild,vignetting"`` or ``{name: values or
        severity}`` (rendered by :class:`uw_sil.sim.model.UnderwaterModel`; random effects draw from the
        trial's seed), and/or, in a list, callables ``effect(img, render) -> img`` applied to each degraded
        float frame. Recorded only in the truth sidecar: ``effects`` (names) and ``effect_params``
        (``{name: {param: value}}`` of the registered ones).
    progress : callable(done, total), optional
    image_topic, info_topic, pose_topic : str
        Topic names; ``info_topic=None`` writes no camera_info (a field bag: give the calibration as a
        file, see ``camera_yaml``).
    image_format : {'raw', 'jpeg', 'png'}
        ``sensor_msgs/Image`` rgb8, or ``sensor_msgs/CompressedImage``.
    pose_in : {'topic', 'tf', 'none'}
        ``topic``: ``pose_topic`` (PoseStamped) and ``camera -> panel`` on /tf, as before. ``tf``: a field
        navigation tree (:func:`field_tf_tree`): ``map -> odom`` (static), ``odom -> base_link`` on /tf at
        ``tf_rate_factor`` times the frame rate with stamps between the frames (a lookup must compose and
        interpolate), ``base_link -> camera_frame`` and ``map -> panel_frame`` on /tf_static. ``none``: no
        pose at all (the panel's markers are the only source).
    distortion : sequence of 5 floats, optional
        plumb_bob ``k1 k2 p1 p2 k3`` of the lens: frames are rendered with a wider pinhole and distorted
        (then noise is added, as on the sensor); the camera_info (if written) and ``camera_yaml`` carry
        it, with ``P`` from OpenCV's optimal new camera matrix (alpha 0).
    camera_yaml : path, optional
        Also write the calibration as a ROS ``camera_calibration`` YAML file.
    draw_seed : int, optional
        Seed of what is new in every frame (the sensor noise, random effects such as particles) instead of
        ``seed``: the same dive (path, water, fixed patterns) seen with other random draws, a twin of the
        trial (what a simulation that reproduced everything but the draws would score against it).

    Returns
    -------
    dict
        The ground truth written to the sidecar (with ``params`` as a plain dict, ``poses``: the true
        ``T_cam_panel`` of every frame).
    """
    from .camera_yaml import CameraCalibration, write_camera_yaml
    from .records import Sample
    from .writer import write_trial
    from ..sim.model import normalize_effects
    from ..sim.simcam import SimCamera
    from ..sim.stream import stream_frames

    if n_frames < 1:
        raise ValueError("n_frames must be >= 1")
    if pose_in not in POSE_IN:
        raise ValueError(f"pose_in must be one of {POSE_IN}, got {pose_in!r}")
    if effects is None or isinstance(effects, (str, dict)):
        effects = [effects] if effects else []
    funcs = [e for e in effects if callable(e)]
    model_effects = {}
    for e in effects:
        if not callable(e):
            model_effects.update(normalize_effects(e))
    model_effects = normalize_effects(model_effects)
    camera = camera or CameraModel.from_fov()
    calib = CameraCalibration.from_camera_model(camera, D=distortion, camera_name="synthetic")
    rng = np.random.default_rng(seed)
    path = approach_path(start_m, end_m, rng)
    draws = int(seed) if draw_seed is None else int(draw_seed)
    if draw_seed is not None:
        rng = np.random.default_rng([draws, 1])      # the base noise: after the path, a stream of its own
    poses = [path(k / max(1, n_frames - 1)) for k in range(n_frames)]
    t0_ns = 1_700_000_000_000_000_000 + int(seed) * 1_000_000_000
    dt_ns = int(round(1e9 / rate_hz))
    render_cam, maps, ss = camera, None, 2
    if calib.has_distortion:
        # the lens: a pinhole render at twice the resolution, warped onto a twice finer raw grid and
        # area-averaged (a pixel integrates the light falling on it)
        cover = _covering_pinhole(calib)
        render_cam = cover.scaled(ss)
        maps = calib.distortion_maps(render_cam, supersample=ss)

    def samples() -> Iterator:
        import cv2

        # random effects get their own stream (the trial's seed, offset), so trials without them keep their noise
        with SimCamera(params, camera=render_cam, model=model, fog=fog, effects=model_effects,
                       seed=draws + 7919) as sim:
            # frames side by side where that pays (the same frames: uw_sil.sim.stream)
            big = render_cam.width * render_cam.height >= STREAM_MIN_PIXELS
            frames = stream_frames(sim, poses) if big else (sim.render(T) for T in poses)
            for k, (T, frame) in enumerate(zip(poses, frames)):
                img = frame.image
                for eff in funcs:
                    img = eff(img, frame.render)
                if maps is not None:
                    img = cv2.remap(np.ascontiguousarray(img), maps[0], maps[1], cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_REPLICATE)
                    img = cv2.resize(img, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
                yield Sample(stamp_ns=t0_ns + k * dt_ns, image=add_sensor_noise(img, noise, rng), camera=camera,
                             pose=T, frame_id=camera.frame_id)
                if progress:
                    progress(k + 1, n_frames)

    tf_static, tf_dynamic = (), ()
    if pose_in == "tf":
        tf_static, base_in_odom = field_tf_tree(camera.frame_id, panel_frame)
        step = dt_ns / max(1, int(tf_rate_factor))
        span = max(1, n_frames - 1) * dt_ns
        # navigation from 0.2 s before the first frame to 0.2 s after the last, stamps between the frames
        j0, j1 = int(math.floor(-0.2e9 / step)), int(math.ceil(((n_frames - 1) * dt_ns + 0.2e9) / step))
        tf_dynamic = []
        for j in range(j0, j1 + 1):
            t_rel = j * step + step / 2
            tf_dynamic.append((t0_ns + int(round(t_rel)), "odom", "base_link", base_in_odom(path(t_rel / span))))
    bag_path = write_trial(out, samples(), storage=storage, overwrite=overwrite, image_topic=image_topic,
                           info_topic=info_topic, pose_topic=pose_topic if pose_in == "topic" else None,
                           write_tf=pose_in == "topic", panel_frame=panel_frame, image_format=image_format,
                           jpeg_quality=jpeg_quality, tf_static=tf_static, tf_dynamic=tf_dynamic, calibration=calib)
    if camera_yaml is not None:
        write_camera_yaml(camera_yaml, calib)
    truth = {
        "params": params.as_dict(),
        "fog": fog,
        "noise": asdict(noise),
        "seed": int(seed),
        **({"draw_seed": int(draw_seed)} if draw_seed is not None else {}),
        "n_frames": int(n_frames),
        "ranges_m": [float(np.linalg.norm(T[:3, 3])) for T in poses],
        "camera": asdict(camera),
        "effects": list(model_effects) + [getattr(e, "name", getattr(e, "__name__", repr(e))) for e in funcs],
        "effect_params": model_effects,
        "bag": str(bag_path),
        "image_topic": image_topic,
        "image_format": image_format,
        "info_topic": info_topic,
        "pose_in": pose_in,
        "pose_topic": pose_topic if pose_in == "topic" else None,
        "camera_frame": camera.frame_id,
        "panel_frame": panel_frame,
        "distortion": None if distortion is None else [float(v) for v in np.asarray(distortion).reshape(-1)],
        "rectified_camera": asdict(calib.rectified_camera(camera.frame_id)),
        "stamps_ns": [t0_ns + k * dt_ns for k in range(n_frames)],
        "poses": [np.asarray(T, dtype=float).tolist() for T in poses],
    }
    write_text_atomic(truth_path(out), json.dumps(truth, indent=2))
    return truth


def _covering_pinhole(calib) -> CameraModel:
    """A pinhole camera with ``calib``'s focal lengths that sees every ray of the distorted raw image."""
    import cv2

    w, h = calib.width, calib.height
    border = np.concatenate([np.stack([np.arange(w), np.zeros(w)], 1), np.stack([np.arange(w), np.full(w, h - 1)], 1),
                             np.stack([np.zeros(h), np.arange(h)], 1), np.stack([np.full(h, w - 1), np.arange(h)], 1)])
    und = cv2.undistortPointsIter(border[:, None, :].astype(np.float64), calib.K, np.asarray(calib.D, float), None,
                                  calib.K, (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)).reshape(-1, 2)
    lo = np.floor(np.minimum(und.min(axis=0), 0)) - 2
    hi = np.ceil(np.maximum(und.max(axis=0), [w - 1, h - 1])) + 2
    K = calib.K
    return CameraModel(int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1), float(K[0, 0]), float(K[1, 1]),
                       float(K[0, 2] - lo[0]), float(K[1, 2] - lo[1]))
