"""Diagnosis plug-in of lens/port vignetting (:mod:`uw_sil.sim.effects.vignetting`)."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from .base import Judge

#: Furthest a lens's vignetting centre plausibly sits from the principal point, in image half-diagonals (40 px at
#: 640x480). The falloff is centred on the optical axis (the lens's stops and the port's aperture sit on it); the
#: axis meets the sensor at the principal point, off it by lens decentring (a few px) and, where the camera info
#: is nominal rather than calibrated, by the sensor's placement (±0.1-0.2 mm, about 0.05 half-diagonals): twice
#: that. The box (:mod:`uw_sil.sim.effects.vignetting`: ±0.2) lets a fit go further; a fit centred further off is
#: shaping something else too (the physical dives 403 and 409, whose vignetting, if any, is centred: round 2's cheap
#: refits put it 0.16 and 0.23 off, beside the lamps).
MAX_CENTRE = 0.1


class VignettingJudge(Judge):
    effect = "vignetting"
    free = ("k1", "k2", "cx", "cy", "n")
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
        # proxy: exp(k1 t^2 + k2 t^4), t = tan of the field angle. Its t^2 term as the lens's cos^n law (cos^n =
        # (1 + t^2)^(-n/2) = exp(-n t^2 / 2 + ...)), what is left as the polynomial 1 + k1 rho^2 + k2 rho^4 with rho
        # the radius over the image half-diagonal: matched at the corner and at half the radius
        n = float(np.clip(-2.0 * p.get("k1", 0.0), 0.0, 8.0))
        hd2 = ((cam.width / 2) ** 2 + (cam.height / 2) ** 2) / (cam.fx * cam.fy)

        def rest(t2):
            return math.exp(p.get("k1", 0.0) * t2 + p.get("k2", 0.0) * t2 * t2) * (1 + t2) ** (n / 2)

        K = np.linalg.solve(np.array([[1.0, 1.0], [0.25, 0.0625]]), [rest(hd2) - 1, rest(hd2 / 4) - 1])
        half_diag = math.hypot(cam.width / 2, cam.height / 2)
        return {"k1": float(np.clip(K[0], -1.2, 0.5)), "k2": float(np.clip(K[1], -0.6, 0.6)), "n": n,
                "cx": float(np.clip(p.get("cx", 0) * cam.fx / half_diag, -0.2, 0.2)),
                "cy": float(np.clip(p.get("cy", 0) * cam.fy / half_diag, -0.2, 0.2))}

    @staticmethod
    def _off(e) -> float:
        """The centre's distance from the principal point where it is beyond :data:`MAX_CENTRE`, else 0 (a centre
        held on the limit, :meth:`pinned`, is within)."""
        d = math.hypot(e.get("cx", 0.0), e.get("cy", 0.0))
        return d if d > MAX_CENTRE * (1 + 1e-6) else 0.0

    def ranges(self, e):
        d = self._off(e)
        if not d:
            return []
        return [f"vignetting centred {d:.2f} half-diagonals from the principal point: a lens's falloff is centred "
                f"on its optical axis, within {MAX_CENTRE:g} of it (so far off, it stands in for another falloff of "
                f"the light, such as the lamps' footprint)"]

    def pinned(self, e):
        """A centre fitted further from the principal point than a lens's optical axis sits: held at the
        nearest possible distance (:data:`MAX_CENTRE`) in the same direction, the falloff's shape refitted."""
        d = self._off(e)
        return {"cx": e["cx"] * MAX_CENTRE / d, "cy": e["cy"] * MAX_CENTRE / d} if d else {}

    def neutral(self, values, camera=None):
        """Also values whose falloff is 1 over the whole image of ``camera``: the polynomial is capped at 1, so
        k1 >= 0 with a k2 that does not bring it below 1 before the corners is no vignetting, whatever its
        numbers (a refit can end there: it is where the image no longer depends on them)."""
        if super().neutral(values, camera):
            return True
        return camera is not None and self.darkest(values, camera) >= 1.0

    def explain(self, e, gain, sig, camera=None):
        k1, k2, n = e.get("k1", 0), e.get("k2", 0), e.get("n", 0)
        corner = f"corner brightness {100 * self.darkest(e, camera):.0f} % of the centre, " if camera else ""
        law = f"the lens's cos^{n:.1f} law times " if n >= 0.05 else ""
        return (f"the image darkens towards the corners the same way in every frame and in the water as on the "
                f"panel (lens vignetting): {corner}{law}1 {k1:+.2f} rho² {k2:+.2f} rho⁴; {gain}")

    @staticmethod
    def darkest(e, camera) -> float:
        """The falloff's least value over ``camera``'s image (its darkest corner's relative illumination)."""
        from ...sim.effects import get_effect

        eff = get_effect("vignetting")
        state = eff.prepare(SimpleNamespace(shape=(camera.height, camera.width)), camera)
        return float(eff.falloff(state, {**eff.defaults(), **e}).min())
