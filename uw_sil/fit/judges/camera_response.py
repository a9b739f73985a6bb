"""Diagnosis plug-in of the camera's tone curve and white balance (:mod:`uw_sil.sim.effects.camera_response`)."""
from __future__ import annotations

from .base import Judge


class CameraResponseJudge(Judge):
    effect = "camera_response"
    free = ("gamma", "gain_r", "gain_g", "gain_b", "black", "toe")
    res = "low"
    cost = 4.0
    residual_evidence = True

    def order(self, job):
        return self.proxy_share(job)

    def start(self, job):
        return {"gamma": 1.1, "black": 0.01, "toe": 0.01}

    def explain(self, e, gain, sig, camera=None):
        toe = e.get("toe", 0.0)
        return (f"the camera maps light to grey levels differently: tone curve gamma {e.get('gamma', 1):.2f}"
                + (f" (linear below {toe:.3f} of full scale)" if toe > 0 else "") + ", "
                f"white-balance gains r/g/b {e.get('gain_r', 1):.2f}/{e.get('gain_g', 1):.2f}/"
                f"{e.get('gain_b', 1):.2f}, black level {255 * e.get('black', 0):.0f} DN; {gain}")
