"""The simulated camera: renderer + underwater model with its current parameters, one call per pose.

This is what the ``sim_camera`` ROS node and the offline tools (``uw-sil synth``) share: the node only
converts messages and parameters around it.

Examples
--------
>>> from uw_sil.sim.simcam import SimCamera
>>> from uw_sil.sim.scene import facing_pose
>>> cam = SimCamera()                       # shipped panel, 640x480, default parameters
>>> frame = cam.render(facing_pose(2.0))    # frame.image: (480, 640, 3) float32 in [0, 1]
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Optional

import numpy as np

from .camera import CameraModel
from .optics import FOG_MODES, degrade
from .effects import get_effect
from .effects.base import effect_rng
from .effects.pose_error import PoseError
from .model import UnderwaterModel, flat_to_effect_params, normalize_effects
from .params import UnderwaterParams

__all__ = ["FrameJob", "SimFrame", "SimCamera"]


@dataclass(frozen=True)
class FrameJob:
    """One frame as :meth:`SimCamera.plan` fixed it: the pose rendered (the recorded one corrected by a pose
    error), whether it has an image, the base parameters, fog, the model with its other effects (None: the base
    model alone), the seed of the effects' draws and the camera noise. The camera is the renderer's when the
    frame renders."""

    pose: np.ndarray
    image: bool
    params: np.ndarray
    fog: str
    model: Optional[UnderwaterModel]
    seed: Optional[int]
    noise_sigma: float
    noise_seed: Optional[int]


@dataclass
class SimFrame:
    """One simulated camera frame."""

    image: np.ndarray     # (H, W, 3) float32 in [0, 1]: the underwater image (None: geometry only)
    render: object        # uw_sil.sim.render.RenderResult: clean rgb, depth, range, labels
    camera: Optional[CameraModel] = None     # the camera it was rendered with

    def image_uint8(self) -> np.ndarray:
        return np.clip(np.rint(self.image * 255.0), 0, 255).astype(np.uint8)


class SimCamera:
    """Renderer plus underwater parameters. Parameters and camera can change between frames.

    Parameters
    ----------
    params : UnderwaterParams, optional
    camera : CameraModel, optional
    model : path or trimesh.Scene, optional
        Panel model (default: the shipped intervention panel).
    fog : {'exp2', 'exp', 'none'}
    noise_sigma : float
        Camera noise, standard deviation in grey levels (0..255 units), a fresh Gaussian realization per
        frame (the backward fit estimates it on the real frames). 0: noise-free images.
    seed : int, optional
        Seed of the noise (and of the random effects).
    effects : dict or str, optional
        Effects of :mod:`uw_sil.sim.effects` added to the underwater model (``{name: values or severity}``
        or ``"artificial_light=mild,vignetting"``); live through :attr:`effects` and
        :meth:`set_effect_params`. With effects the image comes from :class:`uw_sil.sim.model.UnderwaterModel`.
    """

    def __init__(self, params: Optional[UnderwaterParams] = None, camera: Optional[CameraModel] = None,
                 model=None, fog: str = "exp2", noise_sigma: float = 0.0, seed: Optional[int] = None,
                 effects=None):
        from .render import Renderer

        self.params = params or UnderwaterParams()
        self.fog = fog
        self.noise_sigma = noise_sigma
        self.effects = effects
        self._rng = np.random.default_rng(seed)
        self._gl = threading.Lock()       # the OpenGL context: one render or camera change at a time
        self.renderer = Renderer(model, camera=camera or CameraModel.from_fov())

    @property
    def fog(self) -> str:
        return self._fog

    @fog.setter
    def fog(self, mode: str):
        if mode not in FOG_MODES:
            raise ValueError(f"unknown fog mode {mode!r}; expected one of {FOG_MODES}")
        self._fog = mode

    @property
    def noise_sigma(self) -> float:
        return self._noise_sigma

    @noise_sigma.setter
    def noise_sigma(self, sigma: float):
        sigma = float(sigma)
        if not np.isfinite(sigma) or sigma < 0:
            raise ValueError(f"noise_sigma must be finite and >= 0 (grey levels), got {sigma}")
        self._noise_sigma = sigma

    @property
    def effects(self) -> dict:
        """Active effects ``{name: {param: value}}`` (a copy; assign to change)."""
        return {n: dict(v) for n, v in self._effects.items()}

    @effects.setter
    def effects(self, effects):
        self._effects = normalize_effects(effects)

    def set_effect_params(self, flat: dict):
        """Set ``<effect>.<param>`` values of active effects at once (all checked before any is set)."""
        merged = self.effects
        for key, v in flat.items():
            name = key.partition(".")[0]
            if name not in merged:
                raise ValueError(f"{key}: effect {name!r} is not active (active: {', '.join(merged) or 'none'})")
        flat_all = {f"{n}.{k}": v for n, vals in merged.items() for k, v in vals.items()}
        flat_all.update(flat)
        self._effects = flat_to_effect_params(flat_all)

    @property
    def camera(self) -> CameraModel:
        return self.renderer.camera

    @camera.setter
    def camera(self, cam: CameraModel):
        """Frames rendered from now on use ``cam`` (a new size sets up the renderer now, waiting for a render
        another thread may be running)."""
        with self._gl:
            if cam != self.renderer.camera:
                self.renderer.camera = cam

    def render(self, T_cam_panel, image: bool = True) -> SimFrame:
        """The frame seen with pose ``T_cam_panel``. ``image=False``: the render's geometry only (depth, range,
        labels: what e.g. an enhancer needs), no colour pass and no underwater model; ``image`` and ``render.rgb``
        are then None.

        With an active ``pose_error`` the frame is rendered from the corrected pose ``Delta @ T_cam_panel`` (image,
        depth and labels alike): the exact view, where a fit (which has one render per frame) warps the render
        made at the recorded pose (:func:`uw_sil.sim.effects.pose_error.warp_geometry`).

        The same as ``finish(*render_job(plan(T_cam_panel, image)))``: the three steps that
        :class:`uw_sil.sim.stream.FrameStream` runs on different threads."""
        return self.finish(*self.render_job(self.plan(T_cam_panel, image)))

    def plan(self, T_cam_panel, image: bool = True) -> FrameJob:
        """Everything a frame depends on but the camera, fixed now: the parameters and effects as they are, the
        frame's random draws (in call order) and the pose to render."""
        T = np.asarray(T_cam_panel, dtype=float)
        model, seed, noise_seed = None, None, None
        if self._effects:
            seed = int(self._rng.integers(0, 2 ** 63))
            effects = dict(self._effects)
            pe = effects.pop(PoseError.name, None)
            if pe is not None and not get_effect(PoseError.name).is_identity(pe):
                T = get_effect(PoseError.name).correction(pe, effect_rng(seed, PoseError.name)) @ T
            model = UnderwaterModel(self.params, effects, self.fog)
        if image and self._noise_sigma > 0:
            noise_seed = int(self._rng.integers(0, 2 ** 63))
        return FrameJob(T, bool(image), self.params.as_vector(), self.fog, model, seed, self._noise_sigma, noise_seed)

    def render_job(self, job: FrameJob) -> tuple:
        """The OpenGL passes of a planned frame with the current camera (:meth:`Renderer.draw
        <uw_sil.sim.render.Renderer.draw>`): ``(job, raw)`` for :meth:`finish`."""
        with self._gl:
            return job, self.renderer.draw(job.pose, colour=job.image)

    def finish(self, job: FrameJob, raw) -> SimFrame:
        """The render's geometry and shading and the underwater image of a planned frame (no OpenGL and no shared
        state: frames can finish side by side)."""
        rr, camera = self.renderer.develop(raw), raw.camera
        if not job.image:
            return SimFrame(None, rr, camera)
        if job.model is not None:
            img = job.model.prepare(rr, camera, pose=job.pose, seed=job.seed)(
                job.model.params.as_vector(), job.model.effect_vector())
        else:
            img = degrade(rr.rgb, rr.range, rr.depth, job.params, fog=job.fog)
        if job.noise_seed is not None:
            noise = np.random.default_rng(job.noise_seed).standard_normal(img.shape, dtype=np.float32)
            img += noise * np.float32(job.noise_sigma / 255.0)
            np.clip(img, 0.0, 1.0, out=img)
        return SimFrame(img, rr, camera)

    def close(self):
        self.renderer.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
