"""Vignetting: radial falloff of the lens/port, the same in every frame and at every range.

    V(rho) = 1 + k1 rho^2 + k2 rho^4,   I <- I * V

with ``rho`` the distance of a pixel from the vignetting centre in units of the image half-diagonal (the
corners of a centred optic sit at rho = 1, where the relative illumination is ``1 + k1 + k2``; deep-sea
camera housings: 0.3-0.8). The centre is the principal point moved by ``(cx, cy)`` half-diagonals.
``V`` is floored at 0.02 so the inverse (``I / V``) stays finite, and capped at 1: a lens or port only loses
light away from its centre (cos^4 law, the port's aperture), it never gains it; a polynomial that would brighten
the corners (as the beams of several spot lamps can) is no vignetting, and is not one here.
"""
from __future__ import annotations

import numpy as np

from .base import Effect, EffectParam

V_MIN = 0.02


class Vignetting(Effect):
    name = "vignetting"
    stage = "sensor"
    invertible = True
    random_per_frame = False
    summary = "radial falloff V = 1 + k1 rho^2 + k2 rho^4 about a centre near the principal point"
    params = (
        EffectParam("k1", 0.0, -1.2, 0.5, "", "coefficient of rho^2 (rho: radius / image half-diagonal)"),
        EffectParam("k2", 0.0, -0.6, 0.6, "", "coefficient of rho^4"),
        EffectParam("cx", 0.0, -0.2, 0.2, "half-diagonal", "centre offset from the principal point, x (right)"),
        EffectParam("cy", 0.0, -0.2, 0.2, "half-diagonal", "centre offset from the principal point, y (down)"),
    )
    severities = {
        "mild": {"k1": -0.25, "k2": 0.0},                         # corner relative illumination 0.75
        "strong": {"k1": -0.75, "k2": 0.15, "cx": 0.04, "cy": -0.03},   # corners ~0.4
    }

    def prepare(self, geom, camera):
        h, w = geom.shape
        half_diag = 0.5 * float(np.hypot(w, h))
        u = ((np.arange(w) - camera.cx) / half_diag).astype(np.float32)[None, :]
        v = ((np.arange(h) - camera.cy) / half_diag).astype(np.float32)[:, None]
        return u, v

    def falloff(self, state, values) -> np.ndarray:
        """(H, W) float32 map V."""
        u, v = state
        du = u - np.float32(values["cx"])
        dv = v - np.float32(values["cy"])
        rho2 = du * du + dv * dv
        V = 1 + rho2 * (np.float32(values["k1"]) + np.float32(values["k2"]) * rho2)
        return np.clip(V, np.float32(V_MIN), np.float32(1.0)).astype(np.float32)

    def apply(self, terms, values, rng):
        terms.I *= self.falloff(terms.state[self.name], values)[None]

    def invert(self, I, terms, values):
        return I / self.falloff(terms.state[self.name], values)[None]
