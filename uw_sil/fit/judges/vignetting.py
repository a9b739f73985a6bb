"""Diagnosis plug-in of lens/port vignetting (:mod:`uw_sil.sim.effects.vignetting`)."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from .base import Judge


class VignettingJudge(Judge):
    effect = "vignetting"
    free = ("k1", "k2", "cx", "cy")
    res = "low"
    residual_evidence = True

    def order(self, job):
        sig, p = super().order(job), job.prox.get(self.effect)
        return sig * (0.5 + min(1.0, p.explained * 2)) if p is not None else sig

    def start(self, job):
        p = job.prox.get(self.effect)
        cam = job.camera
        if p is None or not p.params:
            return {"k1": -0.2}
        p = p.params
        # proxy: exp(k1 t^2 + k2 t^4), t = tan of the field angle; effect: 1 + k1 rho^2 + k2 rho^4 with rho the
        # radius over the image half-diagonal: match value at the corner and at half the radius
        hd2 = ((cam.width / 2) ** 2 + (cam.height / 2) ** 2) / (cam.fx * cam.fy)
        k1, k2 = p.get("k1", 0.0) * hd2, p.get("k2", 0.0) * hd2 * hd2
        corner, mid = math.exp(k1 + k2), math.exp(k1 * 0.25 + k2 * 0.0625)
        K = np.linalg.solve(np.array([[1.0, 1.0], [0.25, 0.0625]]), [corner - 1, mid - 1])
        half_diag = math.hypot(cam.width / 2, cam.height / 2)
        return {"k1": float(np.clip(K[0], -1.2, 0.5)), "k2": float(np.clip(K[1], -0.6, 0.6)),
                "cx": float(np.clip(p.get("cx", 0) * cam.fx / half_diag, -0.2, 0.2)),
                "cy": float(np.clip(p.get("cy", 0) * cam.fy / half_diag, -0.2, 0.2))}

    def neutral(self, values, camera=None):
        """Also values whose falloff is 1 over the whole image of ``camera``: the polynomial is capped at 1, so
        k1 >= 0 with a k2 that does not bring it below 1 before the corners is no vignetting, whatever its
        numbers (a refit can end there: it is where the image no longer depends on them)."""
        if super().neutral(values, camera):
            return True
        if camera is None:
            return False
        from ...sim.effects import get_effect

        eff = get_effect("vignetting")
        state = eff.prepare(SimpleNamespace(shape=(camera.height, camera.width)), camera)
        return bool(eff.falloff(state, {**eff.defaults(), **values}).min() >= 1.0)

    def explain(self, e, gain, sig):
        k1, k2 = e.get("k1", 0), e.get("k2", 0)
        return (f"the image darkens towards the corners the same way in every frame and in the water as on the "
                f"panel (lens vignetting): corner brightness {100 * (1 + k1 + k2):.0f} % of the centre "
                f"(k1 {k1:.2f}, k2 {k2:.2f}); {gain}")
