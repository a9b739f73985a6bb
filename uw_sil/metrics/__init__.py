"""Image-quality criteria: FSIM/FSIMc (:mod:`.fsim`), HSV region-histogram similarity (:mod:`.histsim`)
and the paper's objective theta (:mod:`.theta`); no-reference underwater indices (UIQM, UCIQE).

Import rules: imports nothing of uw_sil but :mod:`uw_sil._shared`.
"""
from importlib import import_module

_EXPORTS = {
    "FSIMReference": "fsim", "HistogramReference": "histsim", "ThetaReference": "theta", "ThetaScores": "theta",
    "fsim": "fsim", "hsv_histogram_similarity": "histsim", "mean_theta": "theta", "phase_congruency": "fsim",
    "uciqe": "uiqm", "uiqm": "uiqm",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        return getattr(import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
