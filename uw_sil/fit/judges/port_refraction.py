"""Diagnosis plug-in of flat-port refraction (:mod:`uw_sil.sim.effects.port_refraction`)."""
from __future__ import annotations

import math

import numpy as np

from .base import Judge, theta_refit

#: Water's refractive index against air, 1.33 (fresh, red) to 1.35 (sea, blue): a flat port bends no more than
#: that; a fitted ratio well beyond it is another distortion (a lens's own) or a stretched fit.
MAX_PLAUSIBLE_N = 1.40


class PortRefractionJudge(Judge):
    effect = "port_refraction"
    # (not ``pupil_d``: a port off the pupil changes a near panel's scale by (n - 1) d / z, 0.6 % at 1.5 m for 2.5 cm,
    # a quarter pixel at the least-squares fits' 80 px and the same as a pose error along the axis; freed, it was
    # fitted 0 in both refits of a literature dive with a port 2.5-3.5 cm off the pupil)
    free = ("n", "dispersion", "match_t")
    # the distortion moves edges by a few pixels near the panel's corners at the recording's size: judged where
    # they are a pixel or more
    res = "high"
    sigma = 0.1
    cost = 2.0
    # Its θ gain grows with the panel's size in the image (the distortion with the cube of the radius): on an own
    # approach (4 m to 1.2 m) with a strong port, held-out θ +0.005, +0.004, +0.067, +0.105 from the farthest
    # frame to the nearest, +0.045 against a bootstrap margin of 0.058, while the least-squares fit (n 1.330 for
    # a true 1.34) removed 63-88 % of every frame's residual. The pooled residual weighs each frame by what it
    # shows: the held-out residual may accept it (a radial stretch about the principal point, two parameters:
    # little to soak up other effects' leftovers with)
    residual_evidence = True
    # and accepted by it only where θ rises too (:meth:`accept`): its model is θ's. Its least-squares fit (80 px)
    # finds the distortion but not θ's edges: on a literature dive's strong port it scored held-out θ +0.0009 where
    # its θ refit scored +0.028, and a forward scatter's +0.033 beside it then stayed below its margin
    adopts_least_squares = False

    def refit(self, job, current, x_starts=None, parent=None):
        """:func:`~uw_sil.fit.judges.base.theta_refit`, then also the port of its least-squares fit on the base
        parameters θ chose, kept where it scores higher on the fit frames. The least-squares fit (80 px) finds
        the distortion; θ's best start can be another base: on a foreign strong port (a decentred polynomial) the
        least-squares fits put n at 1.155, but θ's best start was the base alone with a green attenuation
        moved from 0.107 to 0.094 /m (fit θ 0.9361 against 0.9327 for the port on the old base), and the
        refit ended without the port. No start combined them."""
        from dataclasses import replace

        r = theta_refit(job, current, self, x_starts=x_starts, parent=parent)
        ls = r.extra.get("ls_params")
        if r.model is None or ls is None or self.effect not in ls["effects"]:
            return r
        port = ls["effects"][self.effect]
        if all(abs(port[k] - r.params["effects"][self.effect][k]) < 1e-9 for k in port):
            return r
        base = [r.params["base"][k] for k in r.params["base"]]
        x2 = r.model.x0(base, {**r.params["effects"], self.effect: port})
        t = job.frame_theta(r.model, job.fit_f, np.stack([r.x, x2])).mean(axis=1)
        if not t[1] > t[0]:
            return r
        params = r.model.params_of(x2)
        return replace(r, x=x2, params=params, theta_fit=float(t[1]), started_at_current=False,
                       sel_pf=job.frame_theta(r.model, job.sel_f, x2, seed_offset=50)[0],
                       extra={**r.extra, "neutral": self.neutral(params["effects"][self.effect], job.camera),
                              "ls_port_on_theta_base": True})

    def accept(self, r, current, margin, residual=None):
        """As every plug-in's (:meth:`Judge.accept`), but the held-out residual accepts a port only where θ rises
        too: a port moves edges, which θ sees. On a lamp-lit physical dive without a port (406, diagnosis seed 2)
        its least-squares fit (n 1.04-1.05) lowered the held-out residual by 8-11 % against margins of 4-5 %, soaking
        up the lamps' leftovers, while held-out θ fell by 0.002; the true ports measured gained θ (+0.001 to
        +0.045)."""
        ok, strength, crit = super().accept(r, current, margin, residual)
        gain = float(np.mean(r.sel_pf - current.sel_pf))
        if ok and crit == "residual" and not gain > 0:
            return False, gain / margin, "theta"
        return ok, strength, crit

    def start(self, job):
        return {"n": 1.15, "dispersion": 0.004}

    #: Also from a sea-water port whose camera's focal length was matched a third of the way out (a calibration
    #: without a distortion model): its image shrinks towards the centre inside that radius and stretches beyond.
    #: On an own trial with that port (n 1.34, t0 0.3), least squares from n 1.15 matched at the centre ended at
    #: n 1.13 matched at 0.20 (fit θ 0.910 against 0.958 from here).
    alt_starts = ({"n": 1.34, "dispersion": 0.009, "match_t": 0.3},)

    def explain(self, e, gain, sig, camera=None):
        n, d, t0 = e.get("n", 1.0), e.get("dispersion", 0.0), e.get("match_t", 0.0)
        where = ""
        if camera is not None:
            from ...sim.effects import get_effect

            corner = math.hypot(camera.width / 2 / camera.fx, camera.height / 2 / camera.fy)
            shift = get_effect(self.effect).shift_px(e, camera, corner)
            where = f"the image's corners show what the pinhole model puts ~{shift:.0f} px nearer the centre, "
        colour = f"; blue bent {d:.3f} more than red (colour fringes at the edges)" if d >= 0.001 else ""
        calib = ""
        if t0 >= 0.02 and camera is not None:
            calib = (f"; the camera's focal length agrees with the port ~{t0 * camera.fx:.0f} px from the centre "
                     f"(nearer, the recording is shrunk towards it: a calibration without a distortion model)")
        return (f"the recording is stretched outwards more the further from the centre (pincushion), as a flat port "
                f"bends the rays: {where}a water-to-air index ratio of {n:.3f}{colour}{calib}; {gain}")

    def ranges(self, e):
        n = e.get("n", 1.0)
        if n > MAX_PLAUSIBLE_N:
            return [f"port_refraction.n = {n:.3f} beyond water's index against air (1.33-1.35): more distortion "
                    f"than a flat port makes (a lens's own distortion, or a stretched fit)"]
        return []
