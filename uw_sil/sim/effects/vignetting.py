"""Vignetting: radial falloff of the lens/port, the same in every frame and at every range.

    V = cos^n(phi) (1 + k1 rho^2 + k2 rho^4),   I <- I * V

with ``rho`` the distance of a pixel from the vignetting centre in units of the image half-diagonal (the
corners of a centred optic sit at rho = 1) and ``phi`` the field angle of its ray, taken about the same centre
(``tan phi`` from the camera's focal lengths). ``cos^n`` is the relative illumination of the lens itself: n = 4
for the natural vignetting of a thin lens (the cos⁴ law), more with pupil and port losses; the polynomial
takes the rest (mechanical vignetting of the housing and port). The cos⁴ law of a camera with a 70° horizontal
field leaves 0.32 of the light in the corners, which the polynomial alone matches only outside its box
(least squares over the radius: k1 -1.28, k2 +0.62). Deep-sea camera housings: corners at 0.3-0.8 of the
centre. The centre is the principal point moved by ``(cx, cy)`` half-diagonals.
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
    summary = ("radial falloff V = cos^n(field angle) (1 + k1 rho^2 + k2 rho^4) about a centre near the "
               "principal point")
    params = (
        EffectParam("k1", 0.0, -1.2, 0.5, "", "coefficient of rho^2 (rho: radius / image half-diagonal)"),
        EffectParam("k2", 0.0, -0.6, 0.6, "", "coefficient of rho^4"),
        EffectParam("cx", 0.0, -0.2, 0.2, "half-diagonal", "centre offset from the principal point, x (right)"),
        EffectParam("cy", 0.0, -0.2, 0.2, "half-diagonal", "centre offset from the principal point, y (down)"),
        EffectParam("n", 0.0, 0.0, 8.0, "", "exponent of the cos^n law of the field angle (4: a thin lens)"),
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
        # tan of the field angle per half-diagonal along x and y
        return u, v, np.float32(half_diag / camera.fx), np.float32(half_diag / camera.fy)

    def falloff(self, state, values) -> np.ndarray:
        """(H, W) float32 map V."""
        u, v, sx, sy = state
        du = u - np.float32(values["cx"])
        dv = v - np.float32(values["cy"])
        rho2 = du * du + dv * dv
        V = 1 + rho2 * (np.float32(values["k1"]) + np.float32(values["k2"]) * rho2)
        n = float(values["n"])
        if n:
            # cos^n(phi) = (1 + tan^2 phi)^(-n/2)
            V = V * (1 + (du * sx) ** 2 + (dv * sy) ** 2) ** np.float32(-0.5 * n)
        return np.clip(V, np.float32(V_MIN), np.float32(1.0)).astype(np.float32)

    def apply(self, terms, values, rng):
        terms.I *= self.falloff(terms.state[self.name], values)[None]

    def invert(self, I, terms, values):
        return I / self.falloff(terms.state[self.name], values)[None]
