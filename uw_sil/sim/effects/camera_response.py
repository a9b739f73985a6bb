"""Camera response: white-balance gains, a tone curve and a black-level pedestal, applied to the linear image.

    y_c = black + (1 - black) * f(min(g_c x_c, 1))

with the tone curve ``f`` of the video and still-image standards: a power law ``x ** (1 / gamma)`` that
turns, below a break ``toe``, into the straight line through black that meets it with the same value and
slope (ITU-R BT.709 and IEC 61966-2-1 sRGB build their OETFs so; a camera's linear toe keeps the noise of
the darkest levels from being amplified without bound)::

    f(x) = s x                        for x <  toe
    f(x) = (1 + o) x ** p - o         for x >= toe,     p = 1 / gamma,
    o = toe**p (1 - p) / (1 - toe**p (1 - p)),     s = (1 + o) p toe**(p - 1).

``toe = 0`` is the pure power law; BT.709 is ``p = 0.45, toe = 0.018`` (o = 0.099, s = 4.5) and sRGB
``p = 1 / 2.4, toe = 0.0031`` (o = 0.055, s = 12.92). The toe matters most in the dark: a pure power law
fitted to BT.709 is off by up to 6 DN below 10 % of full scale, where deep-sea footage lives.

``x`` is what the base model calls the image (a camera whose response is the identity); ``gamma`` is the
tone-curve exponent *relative* to that (1: none; an encoding gamma of 2.2 applied to linear light is
``gamma = 2.2``), ``g_c`` the white-balance gains (0.5-2.5 in cameras with automatic white balance) and
``black`` a pedestal lifting the blacks (J-EDI open-water red sits at about 60 DN, i.e. 0.23).
Invertible where not clipped: ``x_c = f^-1((y_c - black) / (1 - black)) / g_c``.
"""
from __future__ import annotations

import numpy as np

from .base import Effect, EffectParam


class CameraResponse(Effect):
    name = "camera_response"
    stage = "sensor"
    invertible = True
    random_per_frame = False
    summary = "tone curve x**(1/gamma) with a linear toe, white-balance gains per channel, black-level pedestal"
    params = (
        EffectParam("gamma", 1.0, 0.5, 2.5, "", "tone-curve exponent relative to the model (y = x**(1/gamma))"),
        EffectParam("gain_r", 1.0, 0.5, 2.5, "", "white-balance gain, red"),
        EffectParam("gain_g", 1.0, 0.5, 2.5, "", "white-balance gain, green"),
        EffectParam("gain_b", 1.0, 0.5, 2.5, "", "white-balance gain, blue"),
        EffectParam("black", 0.0, 0.0, 0.3, "", "black-level pedestal (fraction of full scale)"),
        EffectParam("toe", 0.0, 0.0, 0.1, "", "break of the linear toe of the tone curve (linear input; 0: none)"),
    )
    severities = {
        "mild": {"gamma": 1.5, "gain_r": 1.35, "gain_b": 0.8, "black": 0.06},
        "strong": {"gamma": 2.2, "gain_r": 1.8, "gain_g": 1.0, "gain_b": 0.6, "black": 0.15},
    }

    @staticmethod
    def _gains(values):
        return np.array([values["gain_r"], values["gain_g"], values["gain_b"]], np.float32)

    @staticmethod
    def curve(values) -> tuple:
        """``(p, toe, o, s)`` of the tone curve ``f`` (module docstring); ``toe = 0`` and ``o = 0`` without
        a toe (or without a curve: ``p = 1``)."""
        p = 1.0 / float(values["gamma"])
        toe = float(values.get("toe", 0.0))
        if toe <= 0 or p == 1:
            return p, 0.0, 0.0, 1.0
        tp = toe ** p * (1 - p)
        o = tp / (1 - tp)
        return p, toe, o, (1 + o) * p * toe ** (p - 1)

    def apply(self, terms, values, rng):
        I = terms.I
        g = self._gains(values)
        p, toe, o, s = self.curve(values)
        black = np.float32(values["black"])
        for c in range(3):
            x = I[c]
            x *= g[c]
            np.clip(x, 0.0, 1.0, out=x)
            if p != 1:
                low = x < toe if toe else None
                lin = x * np.float32(s) if toe else None
                np.power(x, np.float32(p), out=x)
                if toe:
                    x *= np.float32(1 + o)
                    x -= np.float32(o)
                    np.copyto(x, lin, where=low)
            if black != 0:
                x *= 1 - black
                x += black

    def invert(self, I, terms, values):
        out = np.empty_like(I)
        g = self._gains(values)
        p, toe, o, s = self.curve(values)
        black = np.float32(values["black"])
        for c in range(3):
            y = (I[c] - black) / (1 - black)
            np.clip(y, 0.0, 1.0, out=y)
            if p != 1:
                low = y < toe * s if toe else None
                lin = y / np.float32(s) if toe else None
                if toe:
                    y += np.float32(o)
                    y /= np.float32(1 + o)
                    np.maximum(y, 0.0, out=y)        # (below the toe, where o < 0: replaced by the line)
                np.power(y, np.float32(1 / p), out=y)
                if toe:
                    np.copyto(y, lin, where=low)
            out[c] = y / g[c]
        return out
