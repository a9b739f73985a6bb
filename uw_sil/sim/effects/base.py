"""What every effect is made of: named, bounded parameters, severity presets and a stage hook.

An effect is an optional extension of the underwater model (:class:`uw_sil.sim.model.UnderwaterModel`).
It owns a few named parameters (:class:`EffectParam`: default, bounds, unit, description), two severity
presets (``mild``: subtle, 1 - FSIMc about 0.01-0.02 against the frame without it; ``strong``: clearly
visible) and acts in one stage of the model's composition order:

``geometry``  what the camera sees: :meth:`Effect.apply` replaces ``terms.geom`` (a :class:`Geometry`)
``radiance``  light arriving at the surfaces: multiplies ``terms.illum`` (i' = i * illumination)
``medium``    the water between surface and camera: edits ``terms.T_D`` / ``terms.T_B``, adds to ``terms.veil``
``direct``    filters of the direct signal ``terms.D`` (forward scatter)
``sensor``    lens and camera: edits the image ``terms.I``; invertible ones also provide :meth:`Effect.invert`

All arrays in :class:`ModelTerms` are float32; per-channel arrays are channel-first ``(3, H, W)``
("planar": whole-plane operations are about 4x faster than over a trailing axis of 3).
Effect values are plain dicts ``{param: float}``; the parameter vector of an effect is their values in
the order of :attr:`Effect.params` (:meth:`Effect.vector`, :meth:`Effect.from_vector`).
"""
from __future__ import annotations

import contextlib
import math
import threading
import zlib
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

__all__ = ["EffectParam", "Effect", "ModelTerms", "STAGES", "effect_rng", "RememberedDraws", "remembered_draws"]

#: Stages in composition order.
STAGES = ("geometry", "radiance", "medium", "direct", "sensor")


@dataclass(frozen=True)
class EffectParam:
    """One named parameter of an effect: default (the value that leaves the image unchanged where such a
    value exists), bounds ``[lo, hi]`` (a fitter's box), unit and a one-line description."""

    name: str
    default: float
    lo: float
    hi: float
    unit: str = ""
    description: str = ""

    def __post_init__(self):
        if not self.name.isidentifier():
            raise ValueError(f"parameter name {self.name!r} is not an identifier")
        for v in (self.default, self.lo, self.hi):
            if not math.isfinite(v):
                raise ValueError(f"parameter {self.name}: default and bounds must be finite")
        if not self.lo <= self.default <= self.hi or not self.lo < self.hi:
            raise ValueError(f"parameter {self.name}: need lo < hi and lo <= default <= hi, "
                             f"got [{self.lo}, {self.hi}] default {self.default}")


class ModelTerms:
    """The intermediate terms of one evaluation of the underwater model, passed through the stage hooks.

    Attributes
    ----------
    geom : Geometry
        What the camera sees (after the geometry stage).
    camera : CameraModel-like (``width height fx fy cx cy``)
    a, b : ndarray (3,) float32
        Base attenuation (1/m) and background (veiling light) colour.
    rho_f : float32
        Fog density; ``fz`` (H, W) is the fog exponent (``f(z) = exp(-fz)``), 0 without fog.
    r, mask : (H, W) float32
        Range (0 where nothing is hit) and hit mask as 0/1.
    illum : (3, H, W) float32 or None
        Illumination factor of the clean radiance (radiance stage); None means 1.
    T_D, T_B : (3, H, W) float32
        Transmission of the direct signal and of the backscatter (medium stage); the same object unless a
        medium effect separates them. 0 where nothing is hit.
    veil : (3, H, W) float32 or None
        Extra additive light from the water (lamp-lit backscatter, particles); None means 0.
    D : (3, H, W) float32 or None
        Direct signal ``i' * T_D`` (only formed when a direct-stage effect needs it).
    I : (3, H, W) float32
        The image (sensor stage), values of a linear camera in [0, 1] before clipping.
    state : dict
        Per-render precomputations of the active effects (:meth:`Effect.prepare`), by effect name.
    lamps : object or None
        The vehicle lamps when ``artificial_light`` is active (``irradiance(points, a)``), for effects
        lit by them (marine snow).
    restoring : bool
        True while :meth:`UnderwaterModel.restore` builds the terms: random effects are skipped.
    """

    __slots__ = ("geom", "camera", "a", "b", "rho_f", "fog", "fz", "r", "mask", "illum", "T_D", "T_B", "veil",
                 "D", "I", "state", "lamps", "restoring")

    def __init__(self, geom, camera, a, b, rho_f, fog, fz, r, mask, state=None, restoring=False):
        self.geom = geom
        self.camera = camera
        self.a = np.asarray(a, dtype=np.float32)
        self.b = np.asarray(b, dtype=np.float32)
        self.rho_f = np.float32(rho_f)
        self.fog = fog
        self.fz = fz
        self.r = r
        self.mask = mask
        self.illum = None
        self.T_D = None
        self.T_B = None
        self.veil = None
        self.D = None
        self.I = None
        self.state = {} if state is None else state
        self.lamps = None
        self.restoring = restoring

    @property
    def shape(self) -> tuple:
        return self.r.shape

    def add_veil(self, v: np.ndarray):
        """Add (3, H, W) light to the additive veil term."""
        if self.veil is None:
            self.veil = np.array(v, dtype=np.float32, copy=True)
        else:
            self.veil += v

    def multiply_illum(self, g: np.ndarray):
        """Multiply the illumination factor by (3, H, W) or (H, W) ``g``."""
        g = np.asarray(g, dtype=np.float32)
        if g.ndim == 2:
            g = np.broadcast_to(g, (3,) + g.shape)
        if self.illum is None:
            self.illum = np.array(g, dtype=np.float32, copy=True)
        else:
            self.illum *= g


def effect_rng(seed: int, name: str) -> np.random.Generator:
    """The generator of one effect for one frame: independent streams per effect, so adding one random
    effect to a model does not change another's draws (common random numbers across candidates)."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFFFFFFFFFF, zlib.crc32(name.encode())])


_remembering = 0
_remembering_lock = threading.Lock()


@contextlib.contextmanager
def remembered_draws():
    """Within it, every :class:`RememberedDraws` remembers what effects draw, by generator state: a fit that
    simulates every candidate of a frame from the same seed (common random numbers, :func:`effect_rng`) gets
    the draws of the first one back. Outside, a live camera's new seed per frame would only fill memory. All is
    forgotten at the end."""
    global _remembering
    with _remembering_lock:
        _remembering += 1
    try:
        yield
    finally:
        with _remembering_lock:
            _remembering -= 1
            if not _remembering:
                for memo in RememberedDraws.instances:
                    memo.forget()


class RememberedDraws:
    """What one effect draws (and what it derives from the draws alone), remembered within
    :func:`remembered_draws` under the generator's state and a key, up to ``max_bytes`` (the oldest go first).

    :meth:`draw` returns what ``make(rng)`` returns and leaves the generator where ``make`` leaves it, whether
    the value comes from ``make`` or from memory; :meth:`value` remembers what does not draw (``make()``) under
    a key alone. Values must not be written to (they are handed out again)."""

    instances: list = []

    def __init__(self, max_bytes: int):
        self.max_bytes = int(max_bytes)
        self._memo: dict = {}
        self._lock = threading.Lock()          # fits simulate frames on threads
        RememberedDraws.instances.append(self)

    def __len__(self) -> int:
        return len(self._memo)

    def forget(self) -> None:
        with self._lock:
            self._memo.clear()

    @staticmethod
    def state_key(rng: np.random.Generator):
        """The generator's state as a key; None outside :func:`remembered_draws`."""
        if not _remembering:
            return None
        bg = rng.bit_generator
        return type(bg).__name__, repr(bg.state)

    def draw(self, rng: np.random.Generator, key, make: Callable):
        """``make(rng)`` -> ``(value, nbytes)``: its value, remembered under the generator's state and ``key``."""
        state = self.state_key(rng)
        if state is None:
            return make(rng)[0]
        hit = self._memo.get((state, key))
        if hit is not None:
            rng.bit_generator.state = hit[1]
            return hit[0]
        value, nbytes = make(rng)
        self._keep((state, key), (value, rng.bit_generator.state), nbytes)
        return value

    def value(self, key, make: Callable):
        """``make()`` -> ``(value, nbytes)``: its value, remembered under ``key`` (None: not remembered)."""
        if key is None or not _remembering:
            return make()[0]
        hit = self._memo.get(key)
        if hit is not None:
            return hit[0]
        value, nbytes = make()
        self._keep(key, (value,), nbytes)
        return value

    def _keep(self, key, entry, nbytes: int) -> None:
        with self._lock:
            while self._memo and sum(e[-1] for e in self._memo.values()) + nbytes > self.max_bytes:
                del self._memo[next(iter(self._memo))]
            if nbytes <= self.max_bytes:
                self._memo[key] = entry + (nbytes,)


class Effect:
    """Base class of the effects. Subclasses set the class attributes and implement :meth:`apply`.

    Attributes
    ----------
    name : str
        Registry name (also the prefix of its ROS parameters, ``<name>.<param>``).
    params : tuple of EffectParam
    severities : dict
        ``{"mild": {param: value}, "strong": {...}}``; missing parameters take their defaults.
    stage : str
        One of :data:`STAGES`.
    invertible : bool
        Whether :meth:`UnderwaterModel.restore` can undo it (sensor-stage effects then implement
        :meth:`invert`; radiance/medium/geometry effects are undone through the terms they set).
    random_per_frame : bool
        Whether it draws new random numbers every frame (from the generator it is given).
    keeps_scene : bool
        Geometry stage only: whether the scene's own surfaces stay where they are (the effect only adds
        surfaces where the scene showed water), so that their pixel coverage still holds.
    """

    name: str = ""
    params: tuple = ()
    severities: dict = {}
    stage: str = "radiance"
    invertible: bool = False
    random_per_frame: bool = False
    keeps_scene: bool = False
    summary: str = ""

    # ------------------------------------------------------------------ parameters

    @property
    def param_names(self) -> tuple:
        return tuple(p.name for p in self.params)

    def defaults(self) -> dict:
        return {p.name: float(p.default) for p in self.params}

    def values(self, values: Optional[dict] = None) -> dict:
        """A complete, checked value dict: ``values`` (a dict, a severity name, or None) over the defaults.

        Raises ValueError naming the effect and the parameter for unknown names, non-finite values or
        values outside the bounds.
        """
        if values is None:
            return self.defaults()
        if isinstance(values, str):
            return self.severity(values)
        if not isinstance(values, dict):
            raise TypeError(f"values of effect {self.name!r} must be a dict or a severity name, "
                            f"got {type(values).__name__}")
        out = self.defaults()
        for k, v in values.items():
            if k not in out:
                raise ValueError(f"effect {self.name!r} has no parameter {k!r}; "
                                 f"parameters: {', '.join(self.param_names)}")
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise ValueError(f"{self.name}.{k} must be a number, got {v!r}") from None
            out[k] = v
        self.check(out)
        return out

    def check(self, values: dict):
        for p in self.params:
            v = values[p.name]
            if not math.isfinite(v):
                raise ValueError(f"{self.name}.{p.name} is not finite")
            if not p.lo <= v <= p.hi:
                raise ValueError(f"{self.name}.{p.name} = {v:g} outside [{p.lo:g}, {p.hi:g}]"
                                 + (f" {p.unit}" if p.unit else ""))

    def severity(self, level: str) -> dict:
        """The preset values of ``level`` ("mild" or "strong")."""
        if level not in self.severities:
            raise ValueError(f"effect {self.name!r} has no severity {level!r}; "
                             f"choose one of {', '.join(self.severities)}")
        out = self.defaults()
        out.update(self.severities[level])
        return out

    def vector(self, values: Optional[dict] = None) -> np.ndarray:
        """Parameter vector (float64, order of :attr:`params`) of a value dict (defaults filled in)."""
        v = self.values(values)
        return np.array([v[n] for n in self.param_names], dtype=float)

    def from_vector(self, x) -> dict:
        """Value dict of a parameter vector (not bounds-checked: fitters may probe the box edges)."""
        x = np.asarray(x, dtype=float).ravel()
        if x.shape != (len(self.params),):
            raise ValueError(f"effect {self.name!r} takes {len(self.params)} parameters, got {x.size}")
        return {n: float(v) for n, v in zip(self.param_names, x)}

    def bounds(self) -> tuple:
        """``(lower, upper)`` float64 arrays in the order of :attr:`params`."""
        return (np.array([p.lo for p in self.params], dtype=float), np.array([p.hi for p in self.params], dtype=float))

    def is_identity(self, values: dict) -> bool:
        """True if these values leave the image unchanged (all at their defaults, by default)."""
        return all(values[p.name] == p.default for p in self.params)

    def shape_key(self, values: dict) -> tuple:
        """Geometry stage: the values the surfaces' shape depends on (depth, range, points, normals, labels, parts:
        what the other effects prepare from); two value sets with the same key differ in the surfaces' colour
        only. Default: all the values."""
        return tuple(values.values())

    def draws(self, values: dict) -> bool:
        """Whether these values make the effect draw random numbers (e.g. pose jitter > 0)."""
        return self.random_per_frame

    # ------------------------------------------------------------------ hooks

    def prepare(self, geom, camera) -> object:
        """Per-render precomputation (parameter independent), kept in ``terms.state[name]``."""
        return None

    def share(self, state, shared: dict) -> None:
        """Hand ``state`` (of :meth:`prepare`) what it may share with the states of the other geometries of one
        prepared model (the same camera and image size; ``shared``: a dict of this effect's, kept by the model):
        what does not depend on the surfaces. Default: nothing."""

    def apply(self, terms: ModelTerms, values: dict, rng: Optional[np.random.Generator]) -> None:
        """Apply the effect to ``terms`` in place (geometry effects replace ``terms.geom``).

        ``rng`` is None while restoring (and for effects that draw nothing)."""
        raise NotImplementedError

    def invert(self, I: np.ndarray, terms: ModelTerms, values: dict) -> np.ndarray:
        """Sensor stage only: undo :meth:`apply` on a (3, H, W) image, in place or as a new array."""
        raise NotImplementedError(f"effect {self.name!r} is not invertible")

    def describe(self) -> str:
        lines = [f"{self.name} ({self.stage}{', invertible' if self.invertible else ''}"
                 f"{', random per frame' if self.random_per_frame else ''}): {self.summary}"]
        for p in self.params:
            lines.append(f"  {p.name} = {p.default:g} in [{p.lo:g}, {p.hi:g}] {p.unit}: {p.description}")
        return "\n".join(lines)

    def __repr__(self):
        return f"<Effect {self.name} stage={self.stage} params={self.param_names}>"
