"""Fitting the simulator to real frames: the optimizers (paper PSO, CMA-ES; :mod:`.optimize`), the
backward fit (:mod:`.backward`) and its report (:mod:`.report`).

Import rules: may import :mod:`uw_sil.sim`, :mod:`uw_sil.metrics`, :mod:`uw_sil.bags`,
:mod:`uw_sil._shared` and :mod:`uw_sil.viz`; never the ROS nodes.
"""
from .._shared.lazy import lazy_getattr

_EXPORTS = {
    "FitResult": "backward", "FrameSelector": "backward", "OptimResult": "optimize", "fit_bag": "backward",
    "fit_frames": "backward", "optimize": "optimize", "write_params_yaml": "backward", "write_report": "report",
}
__all__ = sorted(_EXPORTS)

__getattr__ = lazy_getattr(__name__, _EXPORTS)
