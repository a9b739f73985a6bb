"""Diagnosis plug-in of a seafloor the scene model lacks (:mod:`uw_sil.sim.effects.unmodeled_geometry`)."""
from __future__ import annotations

from .base import Judge


class UnmodeledGeometryJudge(Judge):
    effect = "unmodeled_geometry"
    free = ("floor_y", "tilt", "albedo", "contrast")
    physical_bounds = ("contrast",)        # a share of 0 or 1
    saturates = {"floor_y": -1}            # a floor far below the panel leaves the view
    res = "low"
    # a seafloor lit by the lamps, in a dark frame, is a smooth brightening of the lower frame (the sand's texture is
    # a few grey levels there): θ is nearly as blind to it as to the lamps' falloff. Measured on a physically lit
    # dive with a lit floor under 40 % of the frame, with the lamps and forward scatter already in the model: the
    # floor lowered the held-out residual by 28 % while held-out θ fell by 0.009, within its margin
    residual_evidence = True
    cost = 5.0
    sigma = 0.12
    alt_starts = ({"floor_y": -0.8, "albedo": 1.0, "contrast": 1.0},
                  {"floor_y": -2.0, "albedo": 1.0, "contrast": 0.5},
                  {"floor_y": -4.5, "albedo": 1.3, "contrast": 0.3})

    def order(self, job):
        sig = super().order(job)              # the signature's score
        return max(sig, self.proxy_share(job))

    def start(self, job):
        return {"floor_y": -0.9, "albedo": 0.8, "contrast": 0.6}

    def explain(self, e, gain, sig, camera=None):
        return (f"the recording shows structure where the scene model has open water — a seafloor about "
                f"{abs(e.get('floor_y', 0)):.1f} m below the panel origin (albedo x{e.get('albedo', 1):.2f}, texture "
                f"contrast {e.get('contrast', 1):.2f}); {gain}")
