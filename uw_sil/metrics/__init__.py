"""Image-quality criteria: FSIM/FSIMc (:mod:`.fsim`), HSV region-histogram similarity (:mod:`.histsim`)
and the paper's objective theta (:mod:`.theta`); no-reference underwater indices (UIQM, UCIQE).

Import rules: imports nothing of uw_sil but :mod:`uw_sil._shared`.
"""
from .._shared.lazy import lazy_getattr

_EXPORTS = {
    "FSIMReference": "fsim", "HistogramReference": "histsim", "ThetaReference": "theta", "ThetaScores": "theta",
    "fsim": "fsim", "hsv_histogram_similarity": "histsim", "mean_theta": "theta", "phase_congruency": "fsim",
    "uciqe": "uiqm", "uiqm": "uiqm",
}
__all__ = sorted(_EXPORTS)

__getattr__ = lazy_getattr(__name__, _EXPORTS)
