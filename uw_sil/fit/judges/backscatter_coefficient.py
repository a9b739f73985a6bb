"""Diagnosis plug-in of β_B ≠ β_D (:mod:`uw_sil.sim.effects.backscatter_coefficient`)."""
from __future__ import annotations

from .base import Judge

#: β_B/β_D beyond which a fit is doubted: Akkaynak & Treibitz (CVPR 2018) measured the two coefficients
#: differing by tens of percent, not by factors of several; a larger ratio means the effect absorbs
#: something else (often lamp falloff).
RATIO_RANGE = (0.5, 2.5)


class BackscatterCoefficientJudge(Judge):
    effect = "backscatter_coefficient"
    free = ("ratio_r", "ratio_g", "ratio_b", "decay")
    res = "low"
    residual_evidence = True

    def order(self, job):
        return self.proxy_share(job)

    def start(self, job):
        p = job.prox.get(self.effect)
        if p is not None and p.params:
            return {"ratio_r": p.params["ratio_r"], "ratio_g": p.params["ratio_g"], "ratio_b": p.params["ratio_b"],
                    "decay": 0.2}
        return {}

    def explain(self, e, gain, sig, camera=None):
        return (f"the backscatter builds up with other coefficients than the direct signal fades "
                f"(β_B/β_D = {e.get('ratio_r', 1):.2f}, {e.get('ratio_g', 1):.2f}, {e.get('ratio_b', 1):.2f} "
                f"for r, g, b; β_D falls with range by factor {1 + e.get('decay', 0):.1f} near the camera): an "
                f"additive bias on the panel that the water does not show; {gain}")

    @staticmethod
    def _outside(e) -> dict:
        """The ratios of ``e`` outside :data:`RATIO_RANGE`, by channel (what is doubted and what is held)."""
        lo, hi = RATIO_RANGE
        return {c: e.get(f"ratio_{c}", 1.0) for c in "rgb" if not lo <= e.get(f"ratio_{c}", 1.0) <= hi}

    def ranges(self, e):
        bad = [f"{c} {v:.2f}" for c, v in self._outside(e).items()]
        return [f"β_B/β_D outside {RATIO_RANGE[0]}-{RATIO_RANGE[1]} ({', '.join(bad)}): more than the two "
                f"coefficients differ in measured water"] if bad else []

    def pinned(self, e):
        """Ratios fitted outside the range measured water shows: each held at the nearest end of it, the others
        refitted (:meth:`~uw_sil.fit.judges.base.Judge.pinned`): whether the recording needs the impossible
        ratio, or β_B ≠ β_D within the range explains it too."""
        lo, hi = RATIO_RANGE
        return {f"ratio_{c}": float(min(max(v, lo), hi)) for c, v in self._outside(e).items()}
