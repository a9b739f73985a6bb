"""Sensor noise: signal-dependent (Poisson-Gaussian), optionally spatially correlated, with fixed patterns.

In grey levels (DN, 0..255) the temporal noise has variance ``shot * I + read^2`` (photon shot noise
through the camera gain, plus read noise; deep-sea HD cameras: shot 0.01-0.5 DN, read 0.5-3 DN).
Demosaicing and in-camera denoising correlate it in space: the white field is blurred with a Gaussian of
``corr`` pixels and rescaled to unit variance. Fixed patterns are the same in every frame (drawn once from
fixed seeds per image size), as EMVA 1288 separates them:

- photo-response non-uniformity, a per-pixel gain ``1 + fpn * P`` (``P`` standard normal per pixel);
- dark-signal non-uniformity of the readout chain: additive offsets per column (``col`` DN std; CMOS
  sensors read each column through its own amplifier/ADC) and per row (``row`` DN std; line-wise reset
  and reference noise), the same in all three channels (demosaicing mixes the raw columns).

New temporal noise every frame, from the generator given. Not invertible.
"""
from __future__ import annotations

import cv2
import numpy as np

from .base import Effect, EffectParam, RememberedDraws

_FPN_SEED = 0x5EED_F1
_patterns: dict = {}


def fixed_pattern(shape, kind: str = "pixel") -> np.ndarray:
    """A standard-normal fixed pattern of a (3, H, W) image size, the same on every call (cached):
    ``pixel``: (3, H, W); ``col``: (1, 1, W) offsets per column; ``row``: (1, H, 1) offsets per row."""
    key = (tuple(shape), kind)
    p = _patterns.get(key)
    if p is None:
        c, h, w = shape
        size = {"pixel": (c, h, w), "col": (1, 1, w), "row": (1, h, 1)}[kind]
        seed = {"pixel": _FPN_SEED, "col": _FPN_SEED + 1, "row": _FPN_SEED + 2}[kind]
        p = np.random.default_rng(seed).standard_normal(size, dtype=np.float32)
        if len(_patterns) > 12:
            _patterns.clear()
        _patterns[key] = p
    return p


#: The white noise fields drawn within :func:`uw_sil.sim.effects.base.remembered_draws` (up to 128 MB).
_white = RememberedDraws(128 * 2 ** 20)


def white_normal(rng: np.random.Generator, shape) -> np.ndarray:
    """``rng.standard_normal(shape, dtype=float32)``, read-only, and ``rng`` left in the state that draw leaves.

    Within :func:`~uw_sil.sim.effects.base.remembered_draws` the field is remembered by the generator's state: a
    fit draws each frame's noise from the same seed for every candidate it simulates (common random numbers), and
    the draw (11 ms for a 640x480 frame) would cost more than the rest of the effect."""
    def make(g):
        n = g.standard_normal(shape, dtype=np.float32)
        n.flags.writeable = False
        return n, n.nbytes

    return _white.draw(rng, tuple(shape), make)


def correlated_normal(rng, shape, sigma_px: float) -> np.ndarray:
    """Unit-variance Gaussian noise (3, H, W) correlated by a Gaussian kernel of ``sigma_px`` pixels (read-only
    when ``sigma_px`` is 0: see :func:`white_normal`)."""
    n = white_normal(rng, shape)
    if sigma_px <= 0:
        return n
    k = cv2.getGaussianKernel(int(2 * np.ceil(4 * sigma_px) + 1), sigma_px, cv2.CV_32F).ravel()
    scale = np.float32(1.0 / float((k * k).sum()))      # std of blurred white noise is sum(k^2) (separable)
    out = np.empty(n.shape, np.float32)
    for c in range(shape[0]):
        cv2.sepFilter2D(n[c], -1, k, k, dst=out[c], borderType=cv2.BORDER_REFLECT)
        out[c] *= scale
    return out


class SensorNoiseEffect(Effect):
    name = "sensor_noise"
    stage = "sensor"
    invertible = False
    random_per_frame = True
    summary = ("Poisson-Gaussian noise (var = shot*I + read^2 in DN), spatially correlated, fixed patterns "
               "(per-pixel gain, column and row offsets)")
    params = (
        EffectParam("shot", 0.0, 0.0, 1.0, "DN", "shot-noise gain: variance per grey level of signal"),
        EffectParam("read", 0.0, 0.0, 5.0, "DN", "read-noise standard deviation"),
        EffectParam("corr", 0.0, 0.0, 2.0, "px", "spatial correlation: Gaussian sigma of the noise field"),
        EffectParam("fpn", 0.0, 0.0, 0.05, "", "fixed-pattern gain non-uniformity (std, relative)"),
        EffectParam("col", 0.0, 0.0, 5.0, "DN", "fixed offset per column (std): column amplifier/ADC pattern"),
        EffectParam("row", 0.0, 0.0, 5.0, "DN", "fixed offset per row (std): line-wise readout pattern"),
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
            gain = np.multiply(fixed_pattern(I.shape), np.float32(values["fpn"]))
            gain += np.float32(1.0)
            I *= gain                                       # I * (1 + fpn P), in place
        for kind in ("col", "row"):
            if values[kind] > 0:
                I += np.float32(values[kind] / 255.0) * fixed_pattern(I.shape, kind)
        if rng is None or not self.draws(values):
            return
        sd = np.clip(I, 0, 1)                               # sqrt(shot I + read^2), in one buffer
        sd *= np.float32(values["shot"] / 255.0)
        sd += np.float32((values["read"] / 255.0) ** 2)
        np.sqrt(sd, out=sd)
        sd *= correlated_normal(rng, I.shape, values["corr"])
        I += sd
