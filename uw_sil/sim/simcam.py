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

from dataclasses import dataclass
from typing import Optional

import numpy as np

from .camera import CameraModel
from .optics import FOG_MODES, degrade
from .model import UnderwaterModel, flat_to_effect_params, normalize_effects
from .params import UnderwaterParams

__all__ = ["SimFrame", "SimCamera"]


@dataclass
class SimFrame:
    """One simulated camera frame."""

    image: np.ndarray     # (H, W, 3) float32 in [0, 1]: the underwater image (None: geometry only)
    render: object        # uw_sil.sim.render.RenderResult: clean rgb, depth, range, labels

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
        if cam != self.renderer.camera:
            self.renderer.camera = cam

    def render(self, T_cam_panel, image: bool = True) -> SimFrame:
        """The frame seen with pose ``T_cam_panel``. ``image=False``: the render's geometry only (depth, range,
        labels: what e.g. an enhancer needs), no colour pass and no underwater model; ``image`` and ``render.rgb``
        are then None."""
        rr = self.renderer.render(T_cam_panel, colour=image)
        if not image:
            return SimFrame(None, rr)
        if self._effects:
            img = UnderwaterModel(self.params, self._effects, self.fog).degrade(
                rr, self.camera, rng=self._rng, pose=T_cam_panel)
        else:
            img = degrade(rr.rgb, rr.range, rr.depth, self.params.as_vector(), fog=self.fog)
        if self._noise_sigma > 0:
            img += self._rng.standard_normal(img.shape, dtype=np.float32) * np.float32(self._noise_sigma / 255.0)
            np.clip(img, 0.0, 1.0, out=img)
        return SimFrame(img, rr)

    def close(self):
        self.renderer.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
