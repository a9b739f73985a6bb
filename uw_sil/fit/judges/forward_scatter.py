"""Diagnosis plug-in of forward-scatter blur (:mod:`uw_sil.sim.effects.forward_scatter`)."""
from __future__ import annotations

import math

import numpy as np

from .base import Judge


class ForwardScatterJudge(Judge):
    effect = "forward_scatter"
    free = ("strength", "width", "tail")
    physical_bounds = ("tail",)        # a share of 0 or 1
    saturates = {"strength": +1}       # the scattered share 1 - exp(-strength r) tends to 1
    res = "high"
    cost = 10.0

    def order(self, job):
        sig = super().order(job)              # the signature's score
        pose = job.sigs.get("pose_error")
        if pose is not None and pose.judged and pose.score >= 3.0:
            return sig            # misaligned edges also look blurred at low resolution: trust the aligned test
        return max(sig, self.proxy_share(job))

    def start(self, job):
        p = job.prox.get(self.effect)
        if p is not None and p.params.get("strength", 0) > 0.01:
            return {"strength": float(np.clip(p.params["strength"], 0.02, 1.5)),
                    "width": float(np.clip(p.params["width_mrad_per_m"], 1, 40)), "tail": 0.3}
        return {"strength": 0.1, "width": 6.0, "tail": 0.3}

    def explain(self, e, gain, sig, camera=None):
        return (f"the recording is blurred by forward scattering, more at longer range: "
                f"{100 * (1 - math.exp(-e.get('strength', 0) * 2.0)):.0f} % of the light at 2 m is spread over "
                f"~{e.get('width', 0) * 2:.0f} mrad (halo share {e.get('tail', 0):.2f}); {gain}")
