"""How far a camera channel's direct attenuation can fall with range in lamp-lit deep-sea water, from spectra.

A colour channel integrates many wavelengths. Its wideband direct attenuation over a path of length ``z`` is
``beta_D(z) = -ln(sum_l w_l exp(-c_l z)) / z`` (Akkaynak & Treibitz, CVPR 2018), with ``w`` the product of the
lamp's spectrum, the reflectance and the channel's response, normalized; it falls with ``z`` as the channel's most
attenuated wavelengths die out first. The plug-in ``backscatter_coefficient`` takes this as
``beta_D(r) = a (1 + decay exp(-r / 2 m))`` on the camera path (the lamp path keeps ``a``). This script asks which
``decay`` real water and real cameras can give, so that a fitted value can be judged by physics, not by the
project's own generators:

- lamp-lit path ``2 r`` (lamp beside the camera, object at range ``r``), ranges 1-5 m;
- pure sea water absorption (Pope & Fry 1997, 10 nm table, rounded), plus CDOM ``a_g(440) exp(-0.014 (l - 440))``
  (0-1 /m) and non-algal particles ``a_p(440) exp(-0.011 (l - 440))`` (0-0.5 /m), scattering
  ``b(550) (550 / l)^n`` (0.02-3 /m, n 0.3-1);
- channels as Gaussians at 600 / 540 / 460 nm, 25-45 nm wide; a cool or warm white LED (blue pump at 450 nm plus a
  broad phosphor); a grey object.

For each case the log signal over the ranges is fitted with the plug-in's form (free gain, ``a``, ``decay``). The
largest ``decay`` per channel is printed, with the case; the last line gives the largest of all.

    .venv/bin/python bench/spectral_beta_d.py
"""
from __future__ import annotations

import itertools

import numpy as np
from scipy.optimize import least_squares

from uw_sil.sim.effects.backscatter_coefficient import R0      # the plug-in's decay length

LAM10 = np.arange(380, 701, 10)
#: Pure water absorption (1/m), Pope & Fry (1997), 380-700 nm every 10 nm (rounded).
A_WATER = np.array([0.0114, 0.00851, 0.00663, 0.00473, 0.00454, 0.00495, 0.00635, 0.00922, 0.00979, 0.0106, 0.0127,
                    0.0150, 0.0204, 0.0325, 0.0409, 0.0434, 0.0474, 0.0565, 0.0619, 0.0695, 0.0896, 0.1351, 0.2224,
                    0.2644, 0.2755, 0.2916, 0.3108, 0.340, 0.410, 0.439, 0.465, 0.516, 0.624])
LAM = np.arange(400, 701, 2.0)
R = np.linspace(1.0, 5.0, 41)


def led(kind: str) -> np.ndarray:
    blue = np.exp(-0.5 * ((LAM - 450) / 10) ** 2)
    phosphor = np.exp(-0.5 * ((LAM - (555 if kind == "cool" else 590)) / 55) ** 2)
    return (0.6 if kind == "cool" else 0.3) * blue + phosphor


def fitted_decay(log_signal: np.ndarray) -> float:
    """``decay`` of ``k - a r (1 + decay exp(-r / R0)) - a r`` fitted to the log signal over ``R``."""
    def res(p):
        k, a, d = p
        return log_signal - (k - a * R * (1 + d * np.exp(-R / R0)) - a * R)
    return float(least_squares(res, [log_signal[0], 0.1, 0.0], bounds=([-np.inf, 0, 0], [np.inf, 5, 10])).x[2])


def main() -> None:
    aw = np.interp(LAM, LAM10, A_WATER)
    worst = {}
    for ag, ap, b550, n, sig, kind in itertools.product((0.0, 0.05, 0.3, 1.0), (0.0, 0.05, 0.5), (0.02, 0.3, 3.0),
                                                        (0.3, 1.0), (25, 35, 45), ("cool", "warm")):
        c = aw + ag * np.exp(-0.014 * (LAM - 440)) + ap * np.exp(-0.011 * (LAM - 440)) + b550 * (550 / LAM) ** n
        for ch, mu in zip("rgb", (600, 540, 460)):
            w = np.exp(-0.5 * ((LAM - mu) / sig) ** 2) * led(kind)
            w /= w.sum()
            log_signal = np.log((w[None] * np.exp(-2 * c[None] * R[:, None])).sum(axis=1))
            d = fitted_decay(log_signal)
            beta = -log_signal / (2 * R)
            if d > worst.get(ch, (-1.0,))[0]:
                worst[ch] = (d, beta[R.searchsorted(1.0)] / beta[R.searchsorted(4.0)],
                             f"CDOM {ag}, particles {ap}, b(550) {b550}, n {n}, channel width {sig} nm, {kind} LED")
    for ch, (d, fall, case) in worst.items():
        print(f"{ch}: decay up to {d:.2f} (beta_D over the two-way path {fall:.2f}x higher at 1 m than at 4 m): {case}")
    print(f"spectral beta_D: largest decay {max(v[0] for v in worst.values()):.2f}")


if __name__ == "__main__":
    main()
