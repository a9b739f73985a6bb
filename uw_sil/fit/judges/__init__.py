"""Diagnosis plug-ins: one :class:`~uw_sil.fit.judges.base.Judge` per effect of :mod:`uw_sil.sim.effects`.

Each module owns, for its effect, the refitted parameters and resolution, the start values, the refit, the
held-out criterion (θ, or a statistic for effects new in every frame), the explanation in words and the
physical plausibility of fitted values. :func:`uw_sil.fit.diagnose.diagnose_frames` runs every plug-in
through one selection loop that names no effect. Adding an effect to the diagnosis is one module here (and
its effect in :mod:`uw_sil.sim.effects`); :data:`JUDGES` must cover every registered effect (a test checks).

Rules of this subpackage: modules import numpy/scipy, :mod:`uw_sil.sim` and :mod:`uw_sil.fit` below
:mod:`uw_sil.fit.diagnose` (never the pipeline itself, nor ROS).
"""
from __future__ import annotations

from .artificial_light import ArtificialLightJudge
from .backscatter_coefficient import BackscatterCoefficientJudge
from .base import Current, Job, Judge, Refit, margin_for, theta_refit
from .camera_response import CameraResponseJudge
from .compression import CompressionJudge
from .forward_scatter import ForwardScatterJudge
from .marine_snow import MarineSnowJudge
from .port_refraction import PortRefractionJudge
from .pose_error import PoseErrorJudge
from .sensor_noise import SensorNoiseJudge
from .unmodeled_geometry import UnmodeledGeometryJudge
from .vignetting import VignettingJudge

__all__ = ["JUDGES", "Current", "Job", "Judge", "Refit", "get_judge", "margin_for", "theta_refit"]


def _registry() -> dict:
    from ...sim.effects import EFFECT_ORDER

    made = {j.effect: j for j in (ArtificialLightJudge(), BackscatterCoefficientJudge(), CameraResponseJudge(),
                                  CompressionJudge(), ForwardScatterJudge(), MarineSnowJudge(), PortRefractionJudge(),
                                  PoseErrorJudge(), SensorNoiseJudge(), UnmodeledGeometryJudge(), VignettingJudge())}
    return {n: made[n] for n in EFFECT_ORDER if n in made}


#: effect name -> Judge, in the effects' composition order
JUDGES: dict = _registry()


def get_judge(name: str) -> Judge:
    try:
        return JUDGES[name]
    except KeyError:
        raise ValueError(f"no diagnosis plug-in for effect {name!r}; plug-ins: {', '.join(JUDGES)}") from None
