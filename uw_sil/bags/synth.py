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

__all__ = ["SensorNoise", "approach_trajectory", "add_sensor_noise", "truth_path", "synthesize_trial",
           "load_truth", "DEFAULT_TRUTH"]

DEFAULT_TRUTH = UnderwaterParams(a=(0.42, 0.11, 0.08), b=(0.06, 0.32, 0.42), rho_f=0.08)


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


def approach_trajectory(n_frames: int, start_m: float = 4.0, end_m: float = 1.2,
                        rng: Optional[np.random.Generator] = None) -> list[np.ndarray]:
    """Panel poses in the camera optical frame for an ROV closing in on the panel.

    Range decreases smoothly from ``start_m`` to ``end_m`` while the vehicle sways and yaws a little
    (a few centimetres and degrees, as a station-keeping ROV does).
    """
    from ..sim.scene import facing_pose

    if n_frames < 1:
        raise ValueError("need at least one frame")
    if not (0 < end_m and 0 < start_m):
        raise ValueError("ranges must be positive")
    rng = np.random.default_rng(0) if rng is None else rng
    ph = rng.uniform(0, 2 * math.pi, 6)
    poses = []
    for k in range(n_frames):
        s = k / max(1, n_frames - 1)
        d = start_m + (end_m - start_m) * (0.5 - 0.5 * math.cos(math.pi * s))   # ease in/out
        t = 2 * math.pi * s
        poses.append(facing_pose(
            d,
            x=0.06 * math.sin(1.3 * t + ph[0]),
            y=0.04 * math.sin(0.9 * t + ph[1]),
            yaw=math.radians(6.0) * math.sin(0.7 * t + ph[2]),
            pitch=math.radians(4.0) * math.sin(1.1 * t + ph[3]),
            roll=math.radians(2.0) * math.sin(0.5 * t + ph[4]),
        ))
    return poses


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
                     progress: Optional[Callable[[int, int], None]] = None) -> dict:
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

    Returns
    -------
    dict
        The ground truth written to the sidecar (with ``params`` as a plain dict).
    """
    from .records import Sample
    from .writer import write_trial
    from ..sim.model import normalize_effects
    from ..sim.simcam import SimCamera

    if n_frames < 1:
        raise ValueError("n_frames must be >= 1")
    if effects is None or isinstance(effects, (str, dict)):
        effects = [effects] if effects else []
    funcs = [e for e in effects if callable(e)]
    model_effects = {}
    for e in effects:
        if not callable(e):
            model_effects.update(normalize_effects(e))
    model_effects = normalize_effects(model_effects)
    camera = camera or CameraModel.from_fov()
    rng = np.random.default_rng(seed)
    poses = approach_trajectory(n_frames, start_m, end_m, rng)
    t0_ns = 1_700_000_000_000_000_000 + int(seed) * 1_000_000_000
    dt_ns = int(round(1e9 / rate_hz))

    def samples() -> Iterator:
        # random effects get their own stream (the trial's seed, offset), so trials without them keep their noise
        with SimCamera(params, camera=camera, model=model, fog=fog, effects=model_effects, seed=int(seed) + 7919) as sim:
            for k, T in enumerate(poses):
                frame = sim.render(T)
                img = frame.image
                for eff in funcs:
                    img = eff(img, frame.render)
                yield Sample(stamp_ns=t0_ns + k * dt_ns, image=add_sensor_noise(img, noise, rng), camera=camera,
                             pose=T, frame_id=camera.frame_id)
                if progress:
                    progress(k + 1, n_frames)

    bag_path = write_trial(out, samples(), storage=storage, overwrite=overwrite)
    truth = {
        "params": params.as_dict(),
        "fog": fog,
        "noise": asdict(noise),
        "seed": int(seed),
        "n_frames": int(n_frames),
        "ranges_m": [float(np.linalg.norm(T[:3, 3])) for T in poses],
        "camera": asdict(camera),
        "effects": list(model_effects) + [getattr(e, "name", getattr(e, "__name__", repr(e))) for e in funcs],
        "effect_params": model_effects,
        "bag": str(bag_path),
    }
    write_text_atomic(truth_path(out), json.dumps(truth, indent=2))
    return truth
