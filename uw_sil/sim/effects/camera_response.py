"""Camera response: white-balance gains, a tone curve and a black-level pedestal, applied to the linear image.

    y_c = black + (1 - black) * min(g_c x_c, 1) ** (1 / gamma)

``x`` is what the base model calls the image (a camera whose response is the identity); ``gamma`` is the
tone-curve exponent *relative* to that (1: none; an encoding gamma of 2.2 applied to linear light is
``gamma = 2.2``), ``g_c`` the white-balance gains (0.5-2.5 in cameras with automatic white balance) and
``black`` a pedestal lifting the blacks (J-EDI open-water red sits at about 60 DN, i.e. 0.23).
Invertible where not clipped: ``x_c = ((y_c - black) / (1 - black)) ** gamma / g_c``.
"""
from __future__ import annotations

import numpy as np

from .base import Effect, EffectParam


class CameraResponse(Effect):
    name = "camera_response"
    stage = "sensor"
    invertible = True
    random_per_frame = False
    summary = "tone curve x**(1/gamma), white-balance gains per channel, black-level pedestal"
    params = (
        EffectParam("gamma", 1.0, 0.5, 2.5, "", "tone-curve exponent relative to the model (y = x**(1/gamma))"),
        EffectParam("gain_r", 1.0, 0.5, 2.5, "", "white-balance gain, red"),
        EffectParam("gain_g", 1.0, 0.5, 2.5, "", "white-balance gain, green"),
        EffectParam("gain_b", 1.0, 0.5, 2.5, "", "white-balance gain, blue"),
        EffectParam("black", 0.0, 0.0, 0.3, "", "black-level pedestal (fraction of full scale)"),
    )
    severities = {
        "mild": {"gamma": 1.5, "gain_r": 1.35, "gain_b": 0.8, "black": 0.06},
        "strong": {"gamma": 2.2, "gain_r": 1.8, "gain_g": 1.0, "gain_b": 0.6, "black": 0.15},
    }

    @staticmethod
    def _gains(values):
        return np.array([values["gain_r"], values["gain_g"], values["gain_b"]], np.float32)

    def apply(self, terms, values, rng):
        I = terms.I
        g = self._gains(values)
        inv_gamma = np.float32(1.0 / values["gamma"])
        black = np.float32(values["black"])
        for c in range(3):
            x = I[c]
            x *= g[c]
            np.clip(x, 0.0, 1.0, out=x)
            if inv_gamma != 1:
                np.power(x, inv_gamma, out=x)
            if black != 0:
                x *= 1 - black
                x += black

    def invert(self, I, terms, values):
        out = np.empty_like(I)
        g = self._gains(values)
        gamma = np.float32(values["gamma"])
        black = np.float32(values["black"])
        for c in range(3):
            x = (I[c] - black) / (1 - black)
            np.clip(x, 0.0, 1.0, out=x)
            if gamma != 1:
                np.power(x, gamma, out=x)
            out[c] = x / g[c]
        return out
