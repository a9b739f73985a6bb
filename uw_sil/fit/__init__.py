"""Fitting the simulator to real frames: the optimizers (paper PSO, CMA-ES; :mod:`.optimize`), the
backward fit (:mod:`.backward`) and its report (:mod:`.report`); the mismatch diagnosis (:mod:`.diagnose`:
which physics a recording holds that the model lacks) with its parts :mod:`.residuals` (frames, locate),
:mod:`.signatures` and :mod:`.screening` (effect footprints), :mod:`.diagfit` (θ fits of extended models),
:mod:`.diagnose_report` and :mod:`.imagediag` (footage without a scene model).

Import rules: may import :mod:`uw_sil.sim`, :mod:`uw_sil.metrics`, :mod:`uw_sil.bags`,
:mod:`uw_sil._shared` and :mod:`uw_sil.viz`; never the ROS nodes.
"""
from .._shared.lazy import lazy_getattr

_EXPORTS = {
    "FitResult": "backward", "FrameSelector": "backward", "OptimResult": "optimize", "fit_bag": "backward",
    "fit_frames": "backward", "optimize": "optimize", "write_params_yaml": "backward", "write_report": "report",
    "Diagnosis": "diagnose", "diagnose_bag": "diagnose", "diagnose_frames": "diagnose",
    "write_diagnosis_yaml": "diagnose", "validate_diagnosis_json": "diagnose", "diagnose_images": "imagediag",
    "write_diagnosis_report": "diagnose_report",
}
__all__ = sorted(_EXPORTS)

__getattr__ = lazy_getattr(__name__, _EXPORTS)
