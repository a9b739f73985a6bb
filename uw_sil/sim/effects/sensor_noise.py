"""Sensor noise: signal-dependent (Poisson-Gaussian), optionally spatially correlated, with a fixed pattern.

In grey levels (DN, 0..255) the temporal noise has variance ``shot * I + read^2`` (photon shot noise
through the camera gain, plus read noise; deep-sea HD cameras: shot 0.01-0.5 DN, read 0.5-3 DN).
Demosaicing and in-camera denoising correlate it in space: the white field is blurred with a Gaussian of
``corr`` pixels and rescaled to unit variance. The fixed pattern (photo-response non-uniformity) is a
per-pixel gain ``1 + fpn * P`` with ``P`` a standard normal field that is the same in every frame (drawn
once from a fixed seed per image size). New temporal noise every frame, from the generator given.
Not invertible.
"""
from __future__ import annotations

import cv2
import numpy as np

from .base import Effect, EffectParam

_FPN_SEED = 0x5EED_F1
_patterns: dict = {}


def fixed_pattern(shape) -> np.ndarray:
    """The (3, H, W) float32 standard-normal fixed-pattern field of an image size (cached)."""
    key = tuple(shape)
    p = _patterns.get(key)
    if p is None:
        p = np.random.default_rng(_FPN_SEED).standard_normal(key, dtype=np.float32)
        if len(_patterns) > 8:
            _patterns.clear()
        _patterns[key] = p
    return p


def correlated_normal(rng, shape, sigma_px: float) -> np.ndarray:
    """Unit-variance Gaussian noise (3, H, W) correlated by a Gaussian kernel of ``sigma_px`` pixels."""
    n = rng.standard_normal(shape, dtype=np.float32)
    if sigma_px <= 0:
        return n
    k = cv2.getGaussianKernel(int(2 * np.ceil(4 * sigma_px) + 1), sigma_px, cv2.CV_32F).ravel()
    scale = np.float32(1.0 / float((k * k).sum()))      # std of blurred white noise is sum(k^2) (separable)
    for c in range(shape[0]):
        n[c] = cv2.sepFilter2D(n[c], -1, k, k, borderType=cv2.BORDER_REFLECT) * scale
    return n


class SensorNoiseEffect(Effect):
    name = "sensor_noise"
    stage = "sensor"
    invertible = False
    random_per_frame = True
    summary = "Poisson-Gaussian noise (var = shot*I + read^2 in DN), spatially correlated, fixed-pattern gain"
    params = (
        EffectParam("shot", 0.0, 0.0, 1.0, "DN", "shot-noise gain: variance per grey level of signal"),
        EffectParam("read", 0.0, 0.0, 5.0, "DN", "read-noise standard deviation"),
        EffectParam("corr", 0.0, 0.0, 2.0, "px", "spatial correlation: Gaussian sigma of the noise field"),
        EffectParam("fpn", 0.0, 0.0, 0.05, "", "fixed-pattern gain non-uniformity (std, relative)"),
    )
    severities = {
        "mild": {"shot": 0.05, "read": 0.6, "corr": 0.6, "fpn": 0.003},
        "strong": {"shot": 0.5, "read": 3.0, "corr": 1.2, "fpn": 0.02},
    }

    def draws(self, values):
        return values["shot"] > 0 or values["read"] > 0

    def apply(self, terms, values, rng):
        I = terms.I
        if values["fpn"] > 0:
            I *= 1 + np.float32(values["fpn"]) * fixed_pattern(I.shape)
        if rng is None or not self.draws(values):
            return
        var = np.clip(I, 0, 1) * np.float32(values["shot"] / 255.0) + np.float32((values["read"] / 255.0) ** 2)
        I += np.sqrt(var) * correlated_normal(rng, I.shape, values["corr"])
