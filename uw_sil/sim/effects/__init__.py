"""Effects the base underwater model leaves out, each an optional, parameterized extension of it.

One module per effect; each defines one :class:`~uw_sil.sim.effects.base.Effect` (named parameters with
bounds and units, ``mild``/``strong`` presets, a stage in the composition order of
:class:`uw_sil.sim.model.UnderwaterModel`). The registry :data:`EFFECTS` maps names to instances:

=========================  ==========  ===========================================================
name                       stage       what
=========================  ==========  ===========================================================
pose_error                 geometry    recorded pose off by a bias (+ per-frame jitter)
unmodeled_geometry         geometry    a seafloor plane the scene lacks (placement, tilt, albedo)
artificial_light           radiance    1-2 vehicle lamps: beam, 1/R^2, exp(-a R_s), Lambert; lamp-lit veil
backscatter_coefficient    medium      beta_D != beta_B (per-channel ratio), beta_D falling with range
marine_snow                medium      sparse lit particles, new every frame
forward_scatter            direct      range-dependent blur of the direct signal
port_refraction            sensor      flat-port refraction: pincushion distortion and lateral colour (Snell)
vignetting                 sensor      radial falloff 1 + k1 rho^2 + k2 rho^4, the same every frame
camera_response            sensor      tone curve, white-balance gains, black-level pedestal
sensor_noise               sensor      Poisson-Gaussian noise, spatially correlated, fixed pattern
compression                sensor      JPEG round trip: 8x8 block DCT quantized at IJG quality q, chroma 4:2:0
=========================  ==========  ===========================================================

:func:`parse_effects` reads the command-line form ``"artificial_light=strong,vignetting"`` (a bare name
means the ``strong`` preset; ``NAME.PARAM=value`` items override single parameters).

Rules of this subpackage: modules here import only numpy, scipy, cv2 and :mod:`uw_sil.sim` (no ROS, no
rendering, no bag I/O); every effect is vectorised (no per-pixel Python loops) and deterministic given
the generator it is handed; new effects subclass :class:`Effect`, set their class attributes and are
added to :data:`EFFECT_ORDER` / :data:`EFFECTS` below.
"""
from __future__ import annotations

from .artificial_light import ArtificialLight
from .backscatter_coefficient import BackscatterCoefficient
from .base import STAGES, Effect, EffectParam, ModelTerms
from .camera_response import CameraResponse
from .compression import Compression
from .forward_scatter import ForwardScatter
from .marine_snow import MarineSnow
from .port_refraction import PortRefraction
from .pose_error import PoseError
from .sensor_noise import SensorNoiseEffect
from .unmodeled_geometry import UnmodeledGeometry
from .vignetting import Vignetting

__all__ = ["EFFECTS", "EFFECT_ORDER", "SEVERITIES", "DEFAULT_SEVERITY", "get_effect", "parse_effects",
           "Effect", "EffectParam", "ModelTerms", "STAGES"]

_ALL = (PoseError(), UnmodeledGeometry(), ArtificialLight(), BackscatterCoefficient(), MarineSnow(),
        ForwardScatter(), PortRefraction(), Vignetting(), CameraResponse(), SensorNoiseEffect(), Compression())

#: Names in composition order (stage order, then the order within a stage).
EFFECT_ORDER = tuple(e.name for e in sorted(_ALL, key=lambda e: STAGES.index(e.stage)))
#: name -> Effect instance
EFFECTS: dict = {e.name: e for e in sorted(_ALL, key=lambda e: EFFECT_ORDER.index(e.name))}
SEVERITIES = ("mild", "strong")
#: Severity of a bare effect name in :func:`parse_effects`.
DEFAULT_SEVERITY = "strong"


def get_effect(name: str) -> Effect:
    """The registered effect ``name`` (ValueError listing the known names otherwise)."""
    try:
        return EFFECTS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown effect {name!r}; known effects: {', '.join(EFFECTS)}") from None


def parse_effects(spec) -> dict:
    """``"artificial_light=strong,vignetting=mild"`` -> ``{name: complete value dict}``.

    Items are separated by commas: ``NAME`` (the :data:`DEFAULT_SEVERITY` preset), ``NAME=mild|strong``,
    or ``NAME.PARAM=value`` (overrides one parameter, on top of the preset if the effect is also named,
    else on top of the defaults). Also accepts a list of such items or an existing dict (checked).
    Raises ValueError naming the bad effect, severity, parameter or value.
    """
    if isinstance(spec, dict):
        return {n: get_effect(n).values(v) for n, v in spec.items()}
    if isinstance(spec, str):
        items = [s.strip() for s in spec.split(",")]
    else:
        items = [str(s).strip() for s in spec]
    levels: dict = {}
    overrides: dict = {}
    for item in items:
        if not item:
            continue
        key, eq, value = item.partition("=")
        key, value = key.strip(), value.strip()
        if "." in key:
            name, _, param = key.partition(".")
            eff = get_effect(name)
            if param not in eff.param_names:
                raise ValueError(f"effect {name!r} has no parameter {param!r}; parameters: {', '.join(eff.param_names)}")
            if not eq:
                raise ValueError(f"{key}: give a value ({key}=NUMBER)")
            try:
                overrides.setdefault(name, {})[param] = float(value)
            except ValueError:
                raise ValueError(f"{key}: value {value!r} is not a number") from None
            continue
        eff = get_effect(key)
        level = value if eq else DEFAULT_SEVERITY
        if level not in eff.severities:
            raise ValueError(f"effect {key!r}: unknown severity {level!r}; choose one of {', '.join(SEVERITIES)}")
        if key in levels and levels[key] != level:
            raise ValueError(f"effect {key!r} given twice with different severities")
        levels[key] = level
    out = {}
    for name in EFFECT_ORDER:
        if name in levels or name in overrides:
            eff = EFFECTS[name]
            values = eff.severity(levels[name]) if name in levels else eff.defaults()
            values.update(overrides.get(name, {}))
            out[name] = eff.values(values)
    return out
