"""The simulator's 7 parameters: attenuation ``a``, background ``b`` (three channels each) and fog ``rho_F``.

Two parameterizations of the same vector:

``rgb`` (canonical, UUV Simulator camera plugin)
    ``(a_r, a_g, a_b, b_r, b_g, b_b, rho_f)``: attenuation per RGB channel in 1/m, background
    (veiling light) colour per channel in [0, 1], fog density ``rho_F`` in 1/m.
``hsv`` (paper Table 1)
    ``(a_h, a_s, a_v, b_h, b_s, b_v, rho_f)``: the attenuation vector and the background colour, each
    written as hue / saturation / value. Hue is circular in [0, 1) (1 = 360 degrees) and wraps;
    ``a_v = max(a_r, a_g, a_b)`` keeps its unit (1/m), ``a_s = (max - min) / max`` is unitless.

Both describe the same model; :func:`hsv_to_rgb_params` and :func:`rgb_to_hsv_params` convert
(batched, on the last axis). Where saturation or value is 0 the hue is undefined; conversion to
rgb is still exact there.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "RGB_NAMES", "HSV_NAMES", "UNITS", "DEFAULT_RGB_BOUNDS", "DEFAULT_HSV_BOUNDS",
    "rgb_to_hsv", "hsv_to_rgb", "rgb_to_hsv_params", "hsv_to_rgb_params",
    "UnderwaterParams", "ParamSpace", "validate_rgb_params",
]

RGB_NAMES = ("a_r", "a_g", "a_b", "b_r", "b_g", "b_b", "rho_f")
HSV_NAMES = ("a_h", "a_s", "a_v", "b_h", "b_s", "b_v", "rho_f")
UNITS = {
    "a_r": "1/m", "a_g": "1/m", "a_b": "1/m", "b_r": "", "b_g": "", "b_b": "", "rho_f": "1/m",
    "a_h": "turn", "a_s": "", "a_v": "1/m", "b_h": "turn", "b_s": "", "b_v": "",
}
DESCRIPTIONS = {
    "a": "attenuation coefficient (exp(-r*a_c))",
    "b": "background / veiling-light colour",
    "rho_f": "fog density (Gazebo fog, f = exp(-(rho_f*z)^2))",
}
# Attenuation realistic up to ~0.6 /m for red in clear deep water; a little headroom for turbid water.
A_MAX = 1.0
RHO_MAX = 0.5
DEFAULT_RGB_BOUNDS = (
    np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]),
    np.array([A_MAX, A_MAX, A_MAX, 1.0, 1.0, 1.0, RHO_MAX]),
)
DEFAULT_HSV_BOUNDS = (
    np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]),
    np.array([1.0, 1.0, A_MAX, 1.0, 1.0, 1.0, RHO_MAX]),
)


def rgb_to_hsv(rgb) -> np.ndarray:
    """Convert non-negative triplets (..., 3) to (hue in [0, 1), saturation, value); value keeps the scale."""
    rgb = np.asarray(rgb, dtype=float)
    if rgb.shape[-1:] != (3,):
        raise ValueError(f"expected (..., 3) triplets, got shape {rgb.shape}")
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    v = rgb.max(axis=-1)
    c = v - rgb.min(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.where(v > 0, c / np.where(v > 0, v, 1.0), 0.0)
        cs = np.where(c > 0, c, 1.0)
        h = np.where(v == r, ((g - b) / cs) % 6.0, np.where(v == g, (b - r) / cs + 2.0, (r - g) / cs + 4.0))
    h = np.where(c > 0, h / 6.0, 0.0) % 1.0
    return np.stack([h, s, v], axis=-1)


def hsv_to_rgb(hsv) -> np.ndarray:
    """Inverse of :func:`rgb_to_hsv`; hue wraps (any real number), s is clipped to [0, 1]."""
    hsv = np.asarray(hsv, dtype=float)
    if hsv.shape[-1:] != (3,):
        raise ValueError(f"expected (..., 3) triplets, got shape {hsv.shape}")
    h = (hsv[..., 0] % 1.0) * 6.0
    s = np.clip(hsv[..., 1], 0.0, 1.0)
    v = hsv[..., 2]
    # Standard piecewise form written with the k-function: f(n) = v - v*s*max(0, min(k, 4-k, 1)).
    out = []
    for n in (5.0, 3.0, 1.0):
        k = (n + h) % 6.0
        out.append(v - v * s * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0))
    return np.stack(out, axis=-1)


def rgb_to_hsv_params(p) -> np.ndarray:
    """(..., 7) rgb parameter vectors -> (..., 7) hsv parameter vectors."""
    p = _as_param_array(p)
    return np.concatenate([rgb_to_hsv(p[..., 0:3]), rgb_to_hsv(p[..., 3:6]), p[..., 6:7]], axis=-1)


def hsv_to_rgb_params(p) -> np.ndarray:
    """(..., 7) hsv parameter vectors -> (..., 7) rgb parameter vectors."""
    p = _as_param_array(p)
    return np.concatenate([hsv_to_rgb(p[..., 0:3]), hsv_to_rgb(p[..., 3:6]), p[..., 6:7]], axis=-1)


def _as_param_array(p) -> np.ndarray:
    p = np.asarray(p, dtype=float)
    if p.shape[-1:] != (7,):
        raise ValueError(f"expected parameter vectors of length 7, got shape {p.shape}")
    return p


def validate_rgb_params(p, names=RGB_NAMES) -> np.ndarray:
    """Check physical validity of (..., 7) rgb vectors: finite, a >= 0, 0 <= b <= 1, rho_f >= 0."""
    p = _as_param_array(p)
    bad = ~np.isfinite(p)
    if bad.any():
        i = int(np.argwhere(bad)[0][-1])
        raise ValueError(f"parameter {names[i]} is not finite")
    checks = [(slice(0, 3), 0.0, np.inf), (slice(3, 6), 0.0, 1.0), (slice(6, 7), 0.0, np.inf)]
    for sl, lo, hi in checks:
        v = p[..., sl]
        bad = (v < lo) | (v > hi)
        if bad.any():
            i = sl.start + int(np.argwhere(bad)[0][-1])
            raise ValueError(f"parameter {names[i]} = {float(v[bad].flat[0]):g} outside [{lo:g}, {hi:g}]")
    return p


@dataclass(frozen=True)
class UnderwaterParams:
    """One parameter set of the underwater model, stored in the canonical rgb parameterization.

    Examples
    --------
    >>> p = UnderwaterParams(a=(0.35, 0.12, 0.09), b=(0.05, 0.30, 0.40), rho_f=0.05)
    >>> p.as_vector()
    array([0.35, 0.12, 0.09, 0.05, 0.3 , 0.4 , 0.05])
    """

    a: tuple = (0.35, 0.12, 0.09)
    b: tuple = (0.05, 0.30, 0.40)
    rho_f: float = 0.05

    def __post_init__(self):
        object.__setattr__(self, "a", tuple(float(x) for x in self.a))
        object.__setattr__(self, "b", tuple(float(x) for x in self.b))
        object.__setattr__(self, "rho_f", float(self.rho_f))
        if len(self.a) != 3 or len(self.b) != 3:
            raise ValueError("a and b need three channels each")
        validate_rgb_params(self.as_vector())

    def as_vector(self) -> np.ndarray:
        return np.array([*self.a, *self.b, self.rho_f])

    @classmethod
    def from_vector(cls, v, model: str = "rgb") -> "UnderwaterParams":
        v = _as_param_array(v)
        if v.shape != (7,):
            raise ValueError(f"expected one vector of 7 parameters, got shape {v.shape}")
        if model == "hsv":
            v = hsv_to_rgb_params(v)
        elif model != "rgb":
            raise ValueError(f"unknown colour model {model!r} (expected 'rgb' or 'hsv')")
        return cls(tuple(v[0:3]), tuple(v[3:6]), float(v[6]))

    def to_hsv(self) -> np.ndarray:
        return rgb_to_hsv_params(self.as_vector())

    def as_dict(self) -> dict:
        return dict(zip(RGB_NAMES, (float(x) for x in self.as_vector())))

    @classmethod
    def from_dict(cls, d: dict) -> "UnderwaterParams":
        """From a mapping with the 7 names of :data:`RGB_NAMES` (other keys are ignored); values must be numbers."""
        missing = [n for n in RGB_NAMES if n not in d]
        if missing:
            raise ValueError(f"missing parameters: {', '.join(missing)}")
        for n in RGB_NAMES:
            v = d[n]
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
                raise ValueError(f"{n} must be a number, got {v!r}")
        return cls.from_vector([d[n] for n in RGB_NAMES])


@dataclass(frozen=True)
class ParamSpace:
    """The box an optimizer searches, in either parameterization, and its map to rgb vectors.

    Parameters
    ----------
    model : {'rgb', 'hsv'}
    lower, upper : array_like (7,), optional
        Bounds in the chosen parameterization (defaults: :data:`DEFAULT_RGB_BOUNDS` /
        :data:`DEFAULT_HSV_BOUNDS`). Must be finite with ``lower < upper`` component-wise.
    """

    model: str = "rgb"
    lower: np.ndarray = field(default=None)
    upper: np.ndarray = field(default=None)

    def __post_init__(self):
        if self.model not in ("rgb", "hsv"):
            raise ValueError(f"unknown colour model {self.model!r} (expected 'rgb' or 'hsv')")
        dlo, dhi = DEFAULT_RGB_BOUNDS if self.model == "rgb" else DEFAULT_HSV_BOUNDS
        lo = dlo.copy() if self.lower is None else np.asarray(self.lower, dtype=float).copy()
        hi = dhi.copy() if self.upper is None else np.asarray(self.upper, dtype=float).copy()
        for which, v in (("lower", lo), ("upper", hi)):
            if v.shape != (7,):
                raise ValueError(f"{which} bounds need 7 values, got shape {v.shape}")
            if not np.isfinite(v).all():
                raise ValueError(f"{which} bound of {self.names[int(np.argmin(np.isfinite(v)))]} is not finite")
        for i in range(7):
            if not lo[i] < hi[i]:
                raise ValueError(f"empty or inverted bounds for {self.names[i]}: [{lo[i]:g}, {hi[i]:g}]")
        physical = (np.array([0, 0, 0, 0, 0, 0, 0.0]), np.array([np.inf, np.inf, np.inf, 1, 1, 1, np.inf]))
        if self.model == "hsv":
            physical = (np.zeros(7), np.array([1, 1, np.inf, 1, 1, 1, np.inf]))
        for i in range(7):
            if lo[i] < physical[0][i] or hi[i] > physical[1][i]:
                raise ValueError(f"bounds of {self.names[i]} [{lo[i]:g}, {hi[i]:g}] leave the physical range "
                                 f"[{physical[0][i]:g}, {physical[1][i]:g}]")
        lo.flags.writeable = False
        hi.flags.writeable = False
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)

    @property
    def names(self) -> tuple:
        return RGB_NAMES if self.model == "rgb" else HSV_NAMES

    def to_rgb(self, x) -> np.ndarray:
        """Map (..., 7) vectors of this space to rgb parameter vectors."""
        x = _as_param_array(x)
        return hsv_to_rgb_params(x) if self.model == "hsv" else x.copy()

    def from_rgb(self, p) -> np.ndarray:
        """Map (..., 7) rgb vectors into this space (not clipped to the bounds)."""
        p = _as_param_array(p)
        return rgb_to_hsv_params(p) if self.model == "hsv" else p.copy()

    def contains(self, x) -> np.ndarray:
        x = _as_param_array(x)
        return np.all((x >= self.lower) & (x <= self.upper), axis=-1)
