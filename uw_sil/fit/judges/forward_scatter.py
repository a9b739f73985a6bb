"""Diagnosis plug-in of forward-scatter blur (:mod:`uw_sil.sim.effects.forward_scatter`)."""
from __future__ import annotations

import math

import numpy as np

from .base import Judge, theta_refit

#: θ starts of the refit besides the plug-in's: blurs too fine for the least-squares fit (about 80 px wide, where
#: a PSF below ~5 mrad/m at 1-3 m is under a pixel) to see, at the fit frames' resolution (320 px) where θ does;
#: a few scattered shares and both PSF forms. (On a recording blurred by Wells' small-angle MTF the least-squares
#: fit took a 7.5 mrad/m blur that lowered θ, and the refit ended at its start, while a 1 mrad/m one raised θ on
#: the fit frames by 0.014.)
FINE_STARTS = tuple({"strength": s, "width": w, "tail": t} for s in (0.15, 0.5) for w in (1.0, 3.0) for t in (0.0, 1.0))


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

    def refit(self, job, current, x_starts=None, parent=None):
        return theta_refit(job, current, self, starts=list(FINE_STARTS), x_starts=x_starts, parent=parent)

    def explain(self, e, gain, sig, camera=None):
        return (f"the recording is blurred by forward scattering, more at longer range: "
                f"{100 * (1 - math.exp(-e.get('strength', 0) * 2.0)):.0f} % of the light at 2 m is spread over "
                f"~{e.get('width', 0) * 2:.0f} mrad (share in Jaffe's halo {e.get('tail', 0):.2f}); {gain}")
