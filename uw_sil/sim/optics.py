"""The underwater image model of the simulator (paper Eq. 1, plus Gazebo fog).

Per colour channel c, with ``r`` the Euclidean range and ``z`` the planar depth of a pixel,
``i`` the clean (in-air) radiance, ``a_c`` the attenuation, ``b_c`` the background (veiling light)
and ``f(z)`` the fog factor of density ``rho_F``:

    e_c(r) = exp(-r * a_c)                                         (transmission)
    I_c    = e_c(r) * [f(z) * i_c + (1 - f(z)) * b_c] + (1 - e_c(r)) * b_c     (Eq. 1 with fog)

Fog is applied to the rendered scene before attenuation, with the background as fog colour
(Gazebo's ``exp2`` fog ``f = exp(-(rho_F z)^2)`` by default, ``exp``: ``f = exp(-rho_F z)``).
Without fog (``rho_F = 0``, ``f = 1``) this is exactly Eq. 1, ``I = i e + (1 - e) b``, as in the
UUV Simulator camera plugin. Expanding the brackets gives the form used for computation,

    I_c = b_c + T_c * (i_c - b_c),   T_c = e_c(r) * f(z),

one exponential per pixel and channel. Pixels where nothing was hit (``r = inf``) take ``b_c``.

References
----------
.. [1] O. Álvarez-Tuñón, A. Jardón and C. Balaguer, "Generation and Processing of Simulated
   Underwater Images for Infrastructure Visual Inspection with UUVs", Sensors 19(24), 5497, 2019,
   doi:10.3390/s19245497. ("the paper" throughout uw_sil.)
.. [2] UUV Simulator, ``uuv_gazebo_plugins`` underwater camera plugin (the same Eq. 1 per channel).
"""
from __future__ import annotations

import numpy as np

from .params import validate_rgb_params

__all__ = ["transmission", "fog_factor", "degrade", "PreparedRender", "FOG_MODES"]

FOG_MODES = ("exp2", "exp", "none")


def transmission(range_m, a) -> np.ndarray:
    """Direct transmission ``exp(-r * a_c)`` (Eq. 1), shape (..., 3); 0 where ``r = inf``."""
    r = np.asarray(range_m, dtype=np.float32)[..., None]
    a = np.asarray(a, dtype=np.float32)
    with np.errstate(invalid="ignore"):
        e = np.exp(-r * a)
    return np.where(np.isfinite(r), e, np.float32(0.0))


def fog_factor(depth_m, rho_f: float, mode: str = "exp2") -> np.ndarray:
    """Fraction of the scene radiance that survives fog at planar depth ``z``; 0 where ``z = inf``.

    ``exp2``: ``exp(-(rho_F z)^2)`` (Gazebo's default), ``exp``: ``exp(-rho_F z)``, ``none``: 1.
    """
    z = np.asarray(depth_m, dtype=np.float32)
    if mode not in FOG_MODES:
        raise ValueError(f"unknown fog mode {mode!r}; expected one of {FOG_MODES}")
    if rho_f < 0 or not np.isfinite(rho_f):
        raise ValueError(f"fog density must be finite and >= 0, got {rho_f}")
    finite = np.isfinite(z)
    zf = np.where(finite, z, np.float32(0.0))
    if mode == "exp2":
        f = np.exp(-np.square(np.float32(rho_f) * zf))
    elif mode == "exp":
        f = np.exp(-np.float32(rho_f) * zf)
    else:
        f = np.ones_like(zf)
    return np.where(finite, f, np.float32(0.0))


def _check_render(rgb, range_m, depth_m):
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"clean image must be (H, W, 3), got shape {rgb.shape}")
    if not np.issubdtype(rgb.dtype, np.floating):
        raise TypeError(f"clean image must be float in [0, 1], got dtype {rgb.dtype}")
    range_m = np.asarray(range_m)
    depth_m = np.asarray(depth_m)
    for name, arr in (("range", range_m), ("depth", depth_m)):
        if arr.shape != rgb.shape[:2]:
            raise ValueError(f"{name} shape {arr.shape} does not match image shape {rgb.shape[:2]}")
        if np.isnan(arr).any() or (arr < 0).any():
            raise ValueError(f"{name} must be >= 0 or inf (no hit), found NaN or negative values")
    return rgb, range_m, depth_m


def degrade(rgb, range_m, depth_m, params, fog: str = "exp2") -> np.ndarray:
    """Apply the underwater model (Eq. 1 with fog) to a clean render.

    Parameters
    ----------
    rgb : ndarray (H, W, 3), float
        Clean render in [0, 1].
    range_m, depth_m : ndarray (H, W)
        Euclidean range and planar depth in metres, ``inf`` where nothing was hit.
    params : array_like (7,) or (N, 7)
        rgb parameter vectors ``(a_r, a_g, a_b, b_r, b_g, b_b, rho_f)``.
    fog : {'exp2', 'exp', 'none'}

    Returns
    -------
    ndarray (H, W, 3) or (N, H, W, 3), float32 in [0, 1].

    Notes
    -----
    For many parameter sets on the same render (an optimizer's inner loop) build a
    :class:`PreparedRender` once and call it instead: it skips the validation and the water pixels.
    """
    return PreparedRender(rgb, range_m, depth_m, fog=fog)(params)


class PreparedRender:
    """A clean render cached for applying many parameter sets quickly (the optimizer's inner loop).

    Computation runs per channel on contiguous (H, W) planes (about 4x faster than broadcasting
    over a trailing axis of 3); water pixels get transmission 0 through a mask, hence ``b``.

    Parameters
    ----------
    rgb, range_m, depth_m, fog : as in :func:`degrade`.
    """

    def __init__(self, rgb, range_m, depth_m, fog: str = "exp2"):
        rgb, range_m, depth_m = _check_render(rgb, range_m, depth_m)
        if fog not in FOG_MODES:
            raise ValueError(f"unknown fog mode {fog!r}; expected one of {FOG_MODES}")
        self.shape = rgb.shape
        self.fog = fog
        hit = np.isfinite(range_m) & np.isfinite(depth_m)
        self.hit = hit
        self.mask = hit.astype(np.float32)
        self.r = np.where(hit, range_m, 0).astype(np.float32)
        z = np.where(hit, depth_m, 0).astype(np.float32)
        self.zf = z * z if fog == "exp2" else z                      # fog exponent grows with this
        self.planes = np.ascontiguousarray(np.moveaxis(rgb.astype(np.float32), 2, 0))  # (3, H, W)

    @property
    def hit_fraction(self) -> float:
        return float(self.hit.mean())

    def __call__(self, params, out=None) -> np.ndarray:
        """Degraded image(s) for (7,) or (N, 7) rgb parameter vectors: (H, W, 3) or (N, H, W, 3) float32."""
        p = np.asarray(params, dtype=float)
        single = p.ndim == 1
        p = validate_rgb_params(np.atleast_2d(p)).astype(np.float32)
        h, w, _ = self.shape
        if out is None:
            out = np.empty((p.shape[0], h, w, 3), dtype=np.float32)
        elif single and out.ndim == 3:
            out = out[None]                             # a view: results land in the caller's array
        t = np.empty((h, w), dtype=np.float32)
        fz = np.empty((h, w), dtype=np.float32)
        for k, (a_r, a_g, a_b, b_r, b_g, b_b, rho) in enumerate(p):
            if self.fog == "none" or rho == 0:
                fz.fill(0.0)
            else:
                np.multiply(self.zf, rho * rho if self.fog == "exp2" else rho, out=fz)
            for c, (a, b) in enumerate(((a_r, b_r), (a_g, b_g), (a_b, b_b))):
                np.multiply(self.r, a, out=t)           # optical thickness r a_c + fog term
                t += fz
                np.negative(t, out=t)
                np.exp(t, out=t)                        # T_c = e_c(r) f(z)
                t *= self.mask                          # no hit: T = 0
                t *= self.planes[c] - b
                t += b                                  # I_c = b_c + T_c (i_c - b_c): paper Eq. 1 with fog
                out[k, :, :, c] = t
        return out[0] if single else out
