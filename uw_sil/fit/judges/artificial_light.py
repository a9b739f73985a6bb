"""Diagnosis plug-in of the vehicle lamps (:mod:`uw_sil.sim.effects.artificial_light`)."""
from __future__ import annotations

import math

import numpy as np

from .base import Judge


#: Lamps fitted closer to the camera than this (m) are doubted: nothing but a ring light sits there.
MIN_DISTANCE = 0.1
#: Where ROV lamps sit, metres from the camera (deep-sea ROV practice: 0.3-1.5 m).
ROV_DISTANCE = (0.3, 1.5)
#: Share of the lamps' light below which the top and bottom lamps are not there
#: (:meth:`ArtificialLightJudge.on_bounds`).
NO_CROSS = 0.01
#: The lowest attenuation of clear deep-sea water, red, green, blue (1/m): the least the alternative starts give the
#: base model when the lamps take the falloff from it (:meth:`ArtificialLightJudge.alt_base`).
CLEAR_WATER_A = (0.35, 0.07, 0.03)


class ArtificialLightJudge(Judge):
    effect = "artificial_light"
    # power is free: how bright the lamps are against the render's light level is the recording's, not ours
    # (fixed at 1, a foreign rig normalized at 2.5 m instead of 2 m could not be fitted)
    # the lamps' colour (tint) too: a white LED is not the white light the renders assume, and a colour the lamp
    # model cannot take is left to a per-channel gain of the camera response, named beside the lamps.
    # offset_z (lamps ahead of or behind the camera's plane) is held at 0, the camera's plane: freed, it
    # found the physical dives' lamps' depth offsets (408: -0.19 m, the truth's lamps -0.08 to -0.16; 405: +0.07,
    # truth +0.01 to +0.09), but on the nine dives it lost the lamps on 401, a true vignetting on 403 and added a
    # β_B≠β_D on 402 (named right 17 -> 16; docs/diagnosis-log.md, 2026-12-07, night II)
    free = ("offset_x", "offset_y", "toe_in", "tilt", "half_angle", "shape", "balance", "fill", "power", "veil",
            "tint_r", "tint_b", "cross", "cross_y", "cross_balance")
    res = "low"
    cost = 9.0
    residual_evidence = True
    sigma = 0.12
    # no uniform light at all (lamps alone: the deep sea), one lamp only, a symmetric pair; no top or bottom lamp,
    # a top or a bottom lamp alone
    physical_bounds = ("fill", "balance", "cross", "cross_balance")
    # a super-Gaussian beam tends to a top-hat as its exponent grows; a beam far wider than the view lights it
    # evenly
    saturates = {"shape": +1, "half_angle": +1}
    # far-apart rigs tried as least-squares starts (a symmetric toed-in pair; one strong lamp to one side;
    # lamps as the only light; a cross of four lamps around the camera, which the pair's start cannot reach: with
    # no cross light its height and balance change nothing): least squares from each, and θ picks
    alt_starts = ({"offset_x": 0.5, "offset_y": -0.1, "toe_in": 0.2, "half_angle": 0.45, "balance": 0.5, "fill": 0.2},
                  {"offset_x": 0.8, "offset_y": -0.3, "toe_in": 0.0, "half_angle": 0.7, "balance": 0.1, "fill": 0.3},
                  {"offset_x": 0.4, "offset_y": -0.2, "toe_in": 0.1, "half_angle": 0.6, "balance": 0.5, "fill": 0.0,
                   "veil": 0.01},
                  {"offset_x": 0.55, "offset_y": -0.1, "toe_in": 0.1, "half_angle": 0.6, "balance": 0.5, "fill": 0.1,
                   "cross": 0.4, "cross_y": 0.45, "cross_balance": 0.4})

    def order(self, job):
        return self.proxy_share(job)

    def start(self, job):
        p = job.prox.get(self.effect)
        if p is not None and p.params:
            q = p.params
            return {"offset_x": float(np.clip(q["offset_x"], 0.05, 1.5)), "offset_y": float(q["offset_y"]),
                    "half_angle": float(q["half_angle"]), "balance": float(q["balance"]),
                    "fill": float(np.clip(q["fill"], 0.0, 0.95)), "veil": 0.002}
        return {"fill": 0.8}

    def on_bounds(self, values):
        """As every plug-in's, but for the top and bottom lamps' height where they give none of the light (``cross``
        below :data:`NO_CROSS`): lamps that are not there have no height, and the image does not depend on it (a
        physical dive's lamps fitted with ``cross`` 0.0001 and ``cross_y`` on its bound lost their round to a camera
        response the recording lacks, for that doubt)."""
        out = super().on_bounds(values)
        if values.get("cross", 0.0) < NO_CROSS:
            out = [(n, side) for n, side in out if n != "cross_y"]
        return out

    def alt_base(self, job, base):
        """The alternative starts make the lamps most of the light (fill 0-0.3): then the lamps, not the base model's
        attenuation, carry the brightness's fall with range. A model without lamps fits that fall as ``exp(-a r)``
        (the direct term); lit by lamps beside the camera it is ``r^-2 exp(-2 a' r)`` (1/r² and the lamp->surface
        path in the same water). Matched in slope of the log over the fit frames' ranges (``s``, the slope of
        ``ln r`` against ``r`` there): ``a' = (a - 2 s) / 2``, not below clear deep-sea water's
        (:data:`CLEAR_WATER_A`; an ``a`` already below that is kept). Started from the current attenuation, the
        lamps' least-squares fits stay where it already takes the falloff (a physical dive with a camera response:
        ``a`` 0.7-1.0 /m against a true 0.2-0.4, and every start ended with the lamps at a fifth of the light)."""
        r = np.array([f.range_median for f in job.fit_f], float)
        r = r[np.isfinite(r) & (r > 0)]
        if r.size == 0:
            return base
        s = float(np.polyfit(r, np.log(r), 1)[0]) if np.ptp(r) > 0.1 * r.mean() else 1.0 / float(r.mean())
        out = np.array(base, float)
        floor = np.asarray(CLEAR_WATER_A)
        a = out[:3]
        out[:3] = np.where(a > floor, np.maximum(floor, (a - 2.0 * s) / 2.0), a)
        return out

    def explain(self, e, gain, sig, camera=None):
        side, other = ("right", "left") if e.get("offset_x", 0) >= 0 else ("left", "right")
        bal = e.get("balance", 0)
        off = abs(e.get("offset_x", 0))
        if bal > 0.35:
            lamp = f"two lamps about {off:.2f} m left and right of the camera"
        elif bal > 0.05:
            lamp = (f"a lamp about {off:.2f} m {side} of the camera (and a weaker one, {100 * bal:.0f} % of the "
                    f"light, {other})")
        else:
            lamp = f"a lamp about {off:.2f} m {side} of the camera"
        cross = e.get("cross", 0.0)
        if cross > 0.05:
            cb = e.get("cross_balance", 0.0)
            where = ("above" if cb < 0.2 else "below" if cb > 0.8 else
                     f"above and below ({100 * (1 - cb):.0f} / {100 * cb:.0f} % of it)")
            lamp += (f", and lamps {e.get('cross_y', 0):.2f} m {where} the camera with {100 * cross:.0f} % of the "
                     f"lamps' light")
        tilt = math.degrees(e.get("tilt", 0.0))
        aim = f", aimed {abs(tilt):.0f}° {'below' if tilt > 0 else 'above'} the optical axis" if abs(tilt) >= 3 else ""
        return (f"the recording is lit by vehicle lamps the simulation lacks: brightness on the panel falls "
                f"~1/r² from {lamp} ({100 * (1 - e.get('fill', 1)):.0f} % of the light from the lamps, beam half "
                f"width {math.degrees(e.get('half_angle', 0)):.0f}°{aim}{self._colour(e)}); {gain}")

    @staticmethod
    def _colour(e) -> str:
        r, b = e.get("tint_r", 1.0), e.get("tint_b", 1.0)
        if max(abs(r - 1), abs(b - 1)) < 0.05:
            return ""
        warm = "warm" if r > b else "cool"
        return f", {warm} light: red {r:.2f} and blue {b:.2f} of its green"

    def ranges(self, e):
        out = []
        d = math.hypot(e.get("offset_x", 0), e.get("offset_y", 0))
        if d < MIN_DISTANCE:
            # (the model's rig is a pair of lamps; lamps on all sides of the camera light a facing scene nearly
            # as one lamp at their centre would, and are fitted there: on seed 402 of the physical dives a ring of
            # four at 0.4-0.7 m was fitted 0.01 m from the camera)
            out.append(f"lamps {d:.2f} m from the camera: ROV lamps sit {ROV_DISTANCE[0]:g}-{ROV_DISTANCE[1]:g} m "
                       f"from it (lamps on all sides of the camera light the view nearly as one lamp at their "
                       f"centre)")
        return out

    def pinned(self, e):
        """Lamps fitted closer to the camera than lamps can sit (mild lamps barely fix their position: the
        same brightening with range from almost any rig): held at the nearest distance ROV lamps sit at, in
        the same direction from the camera (beside it when the fit put them on its axis)."""
        ox, oy = e.get("offset_x", 0.0), e.get("offset_y", 0.0)
        d = math.hypot(ox, oy)
        if d >= MIN_DISTANCE:
            return {}
        if d < 1e-3:
            ox, oy, d = 1.0, 0.0, 1.0
        k = ROV_DISTANCE[0] / d
        return {"offset_x": ox * k, "offset_y": oy * k}
