"""Separate attenuation of the direct signal and of the backscatter (Akkaynak & Treibitz, CVPR 2018).

The base model uses one coefficient per channel for both terms. Here::

    T_D,c = exp(-beta_D,c(r) r) f(z),   beta_D,c(r) = a_c (1 + decay exp(-r / R0))     (R0 = 2 m)
    T_B,c = exp(-ratio_c a_c r) f(z)
    I_c   = i_c T_D,c + b_c (1 - T_B,c)

``ratio_c = beta_B / beta_D`` per channel (1: the base model); ``decay`` lets the effective direct
coefficient fall with range (Sea-thru's two-exponential ``beta_D(z)``, to first order). The signature is
a range-dependent bias that differs between object and water and depends on reflectance. Invertible
(``i = (I - b (1 - T_B)) / T_D``).
"""
from __future__ import annotations

import numpy as np

from .base import Effect, EffectParam

R0 = 2.0


class BackscatterCoefficient(Effect):
    name = "backscatter_coefficient"
    stage = "medium"
    invertible = True
    random_per_frame = False
    summary = "beta_D != beta_B: per-channel ratio beta_B/beta_D, beta_D falling with range"
    params = (
        EffectParam("ratio_r", 1.0, 0.2, 6.0, "", "beta_B / beta_D, red"),
        EffectParam("ratio_g", 1.0, 0.2, 6.0, "", "beta_B / beta_D, green"),
        EffectParam("ratio_b", 1.0, 0.2, 6.0, "", "beta_B / beta_D, blue"),
        EffectParam("decay", 0.0, 0.0, 3.0, "", f"beta_D(r) = a (1 + decay exp(-r/{R0:g} m))"),
    )
    severities = {
        "mild": {"ratio_r": 0.5, "ratio_g": 0.5, "ratio_b": 0.5, "decay": 1.0},
        "strong": {"ratio_r": 0.3, "ratio_g": 0.25, "ratio_b": 0.25, "decay": 2.5},
    }

    def _transmission(self, terms, coef) -> np.ndarray:
        """(3, H, W) exp(-coef_c(r) r - fz) * mask for per-channel coefficient arrays/scalars."""
        h, w = terms.shape
        T = np.empty((3, h, w), np.float32)
        for c in range(3):
            t = T[c]
            np.multiply(terms.r, coef[c], out=t)
            if terms.fz is not None:
                t += terms.fz
            np.negative(t, out=t)
            np.exp(t, out=t)
            t *= terms.mask
        return T

    def apply(self, terms, values, rng):
        a = terms.a
        ratio = np.array([values["ratio_r"], values["ratio_g"], values["ratio_b"]], np.float32)
        TD = terms.T_D
        if values["decay"] != 0:
            boost = 1 + np.float32(values["decay"]) * np.exp(-terms.r / np.float32(R0))
            TD = self._transmission(terms, [a[c] * boost for c in range(3)])
        TB = self._transmission(terms, a * ratio) if np.any(ratio != 1) else TD
        terms.T_D = TD
        terms.T_B = TB
