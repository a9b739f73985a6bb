"""Flat-port refraction: the radial distortion and lateral colour of a camera behind a flat window.

A ray that leaves the scene at angle ``theta_w`` from the optical axis (in water) is bent at a flat port to
``theta_a`` in air, ``n sin(theta_w) = sin(theta_a)`` (Snell; a thin port at the entrance pupil, the glass's
two faces cancelling, ``n`` = n_water / n_air). A pinhole model calibrated in water matches the centre of the
image (its focal length is ``n`` times the lens's in air) but not the rest: the pixel that the pinhole puts at
normalized radius ``t = tan(theta_w)`` is recorded at ``tan(theta_a) / n``. The image is therefore stretched
outwards more the further from the centre (pincushion distortion, no free polynomial):

    t_recorded(t) = t / sqrt(1 - (n^2 - 1) t^2),  or, sampling the pinhole image,
    I(t) = I_pinhole(t / sqrt(1 + (n^2 - 1) t^2))                      (per pixel, about the principal point)

with ``t`` from the camera's focal lengths. That pinhole's focal length is the port's paraxial one. A camera
calibrated in water without a distortion model, or calibrated in air and corrected by a focal length matched
to the port somewhere off the centre, has a focal length that agrees with the port's image at a normalized
radius ``t0`` (``match_t``) instead: the recorded image is the one above scaled by ``s = sqrt(1 - (n^2 - 1) t0^2)``
(so that ``t0`` stays where it is: the centre shrinks towards the principal point, beyond ``t0`` the image is
stretched outwards), and the pinhole image is sampled at

    I(t) = I_pinhole(t / sqrt(s^2 + (n^2 - 1) t^2)) = I_pinhole(t / sqrt(1 + (n^2 - 1) (t^2 - t0^2)))

(``t0`` 0: the paraxial focal length; a third of the half-diagonal of a 640x480 camera with a 70 degree field is t0
~ 0.3). One focal length for the three channels: ``s`` is green's. Water's index falls with wavelength (blue 1.340,
green 1.336, red 1.331 at 450 / 550 / 650 nm): each colour channel is stretched by its own ``n`` (lateral colour,
colour fringes that grow with the radius); ``dispersion`` is ``n_blue - n_red`` and green takes ``n``. Values: an
uncorrected flat port in sea water n = 1.34 (a 640x480 camera with a 70 degree field records in its corners what the
pinhole shows 85 px nearer the centre); a calibration with a distortion model leaves a fraction of that (an
effective n nearer 1). Neutral: n = 1, dispersion 0 (``match_t`` and ``pupil_d`` then change nothing). A dome port
centred on the pupil refracts no ray (nothing to model here).

A flat port stands in front of the lens's entrance pupil, a few centimetres in a real housing (``pupil_d`` = d): the
ray leaves the pupil at ``theta_a``, meets the port at the radius ``d tan(theta_a)`` and goes on in water at
``theta_w`` to the point at planar depth z, so the point's pinhole radius is

    t_pinhole = (d / z) tan(theta_a) + (1 - d / z) tan(theta_w)                (Treibitz, Schechner & Singh 2012)

and the image depends on range: near the axis the point is recorded as if it were (n - 1) d further away (a camera
at the pupil sees a near panel smaller than the pinhole draws it; 0.6 % at 1.5 m behind a sea-water port 2.5 cm
off the pupil, 2 px at 300 px from the centre), which a thin port at the pupil cannot make. A port's glass slab of
thickness t and index n_g adds about ``t (1/n_g - 1/n) / (1 - 1/n)`` to d near the axis (-0.35 t for glass in sea
water): d is the effective distance. Per pixel, the depth is the one of the point it records (the pinhole's depth
where the thin-port mapping samples, then where this one does: silhouettes stay sharp); open water is at infinity
(the thin port's mapping). Last in the optics, first of the sensor stage: the lens's vignetting, the camera's
response and noise come after it.
"""
from __future__ import annotations

import cv2
import numpy as np

from .base import Effect, EffectParam

#: per channel (r, g, b), the share of ``dispersion`` added to ``n``
CHANNEL_OFFSETS = (-0.5, 0.0, 0.5)


class PortRefraction(Effect):
    name = "port_refraction"
    stage = "sensor"
    invertible = True
    random_per_frame = False
    summary = ("flat-port refraction: the pinhole image sampled at t / sqrt(1 + (n^2 - 1) t^2) about the principal "
               "point (pincushion), per colour channel (lateral colour)")
    params = (
        EffectParam("n", 1.0, 1.0, 1.5, "", "refractive index ratio water / air of the port's refraction (1: none)"),
        EffectParam("dispersion", 0.0, 0.0, 0.03, "", "n_blue - n_red (water: ~0.009); green takes n"),
        EffectParam("match_t", 0.0, 0.0, 0.8, "", "normalized radius where the calibrated focal length agrees with "
                    "the port (0: at the centre, the paraxial focal length)"),
        EffectParam("pupil_d", 0.0, 0.0, 0.1, "m", "distance of the port in front of the lens's entrance pupil "
                    "(0: a thin port at the pupil; the image then depends on range)"),
    )
    severities = {
        "mild": {"n": 1.08, "dispersion": 0.003},     # what a partial calibration leaves of a flat port
        "strong": {"n": 1.34, "dispersion": 0.009},   # an uncorrected flat port in sea water
    }

    def prepare(self, geom, camera):
        h, w = geom.shape
        x = ((np.arange(w, dtype=np.float64) - camera.cx) / camera.fx)[None, :]
        y = ((np.arange(h, dtype=np.float64) - camera.cy) / camera.fy)[:, None]
        t2 = (x * x + y * y).astype(np.float32)
        du = np.broadcast_to((np.arange(w, dtype=np.float32) - np.float32(camera.cx))[None, :], (h, w))
        dv = np.broadcast_to((np.arange(h, dtype=np.float32) - np.float32(camera.cy))[:, None], (h, w))
        return {"t2": t2, "du": du, "dv": dv, "cx": np.float32(camera.cx), "cy": np.float32(camera.cy),
                "depth": getattr(geom, "depth", None), "maps": {}}

    @staticmethod
    def _inverse_depth(state):
        """Inverse planar depth per pixel (0: open water, at infinity), made when a port off the pupil first needs
        it; None without a depth map."""
        if "w" not in state:
            depth = state["depth"]
            state["w"] = None if depth is None else np.where(
                np.isfinite(depth) & (depth > 0), 1.0 / np.maximum(depth, 1e-6), 0.0).astype(np.float32)
        return state["w"]

    def is_identity(self, values):
        return float(values["n"]) == 1.0 and float(values["dispersion"]) == 0.0   # (match_t, pupil_d: of a port only)

    @staticmethod
    def indices(values) -> tuple:
        """``n`` of the red, green and blue channels."""
        n, d = float(values["n"]), float(values["dispersion"])
        return tuple(n + o * d for o in CHANNEL_OFFSETS)

    @staticmethod
    def scale2(values) -> float:
        """``s^2 = 1 - (n^2 - 1) t0^2``: the calibrated focal length over the paraxial one, squared (green's)."""
        n, t0 = float(values["n"]), float(values.get("match_t", 0.0))
        return 1.0 - (n * n - 1.0) * t0 * t0

    def _map(self, state, n: float, s2: float, inverse: bool, d: float = 0.0):
        """(map_x, map_y) float32 for cv2.remap: where each pixel of the output samples its input."""
        w = self._inverse_depth(state) if d > 0.0 else None
        d = d if w is not None else 0.0           # (no depth: every point at infinity, where d changes nothing)
        key = (round(n, 12), round(s2, 12), inverse, round(d, 12))
        hit = state["maps"].get(key)
        if hit is not None:
            return hit
        c = np.float32(n * n - 1.0)
        t2, s2f = state["t2"], np.float32(s2)
        a = np.float32(n / np.sqrt(s2))           # t_pinhole / t_recorded of a ray through the port at d, per d/z
        if inverse:      # the pinhole image from a recorded one: t_recorded = s t / sqrt(1 - (n^2 - 1) t^2)
            k = np.float32(np.sqrt(s2)) / np.sqrt(np.maximum(1.0 - c * t2, np.float32(1e-6)))
            if d > 0.0:
                # off the pupil: the recorded radius t_r with t_r * K(t_r^2) = t (K: the forward scale below, the
                # pixel's own depth), by fixed-point iteration from the thin port's (a contraction: K varies
                # slowly with the radius)
                dw = np.float32(d) * w
                q = t2 * k * k
                for _ in range(6):
                    K = dw * a + (1.0 - dw) / np.sqrt(s2f + c * q)
                    q = t2 / (K * K)
                k = 1.0 / K
        else:
            k = 1.0 / np.sqrt(s2f + c * t2)
            if d > 0.0:
                # t_pinhole / t_recorded = (d/z) n / s + (1 - d/z) k_thin, z the depth of the point recorded: the
                # pinhole's depth where the thin port's mapping samples, then where this one does
                k_thin = k
                for _ in range(2):
                    wq = cv2.remap(w, (state["cx"] + state["du"] * k).astype(np.float32),
                                   (state["cy"] + state["dv"] * k).astype(np.float32), cv2.INTER_NEAREST,
                                   borderMode=cv2.BORDER_REPLICATE)
                    dw = np.float32(d) * wq
                    k = dw * a + (1.0 - dw) * k_thin
        out = ((state["cx"] + state["du"] * k).astype(np.float32), (state["cy"] + state["dv"] * k).astype(np.float32))
        if len(state["maps"]) >= 12:
            state["maps"].pop(next(iter(state["maps"])))
        state["maps"][key] = out
        return out

    def _remap(self, I, state, values, inverse: bool) -> np.ndarray:
        out = np.empty_like(I)
        s2 = self.scale2(values)
        d = float(values.get("pupil_d", 0.0))
        for c, n in enumerate(self.indices(values)):
            if n == 1.0 and s2 == 1.0:
                out[c] = I[c]
                continue
            mx, my = self._map(state, n, s2, inverse, d)
            cv2.remap(I[c], mx, my, cv2.INTER_LINEAR, dst=out[c], borderMode=cv2.BORDER_REPLICATE)
        return out

    def apply(self, terms, values, rng):
        terms.I = self._remap(terms.I, terms.state[self.name], values, inverse=False)

    def invert(self, I, terms, values):
        return self._remap(I, terms.state[self.name], values, inverse=True)

    def shift_px(self, values, camera, t: float) -> float:
        """How far (pixels, along x) from where the pinhole puts it the green channel records what it shows at
        normalized radius ``t``."""
        c = float(values["n"]) ** 2 - 1.0
        return float(camera.fx * t * (1.0 - 1.0 / np.sqrt(self.scale2(values) + c * t * t)))
