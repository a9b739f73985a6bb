"""Screening: how much of the mismatch would each physical effect explain? (cheap proxy fits)

For the effects that change the expected image (not only its noise), a small *proxy* model with the
effect's physical invariances is fitted jointly with the 7 base parameters by least squares on
low-resolution frames, and its share of the residual energy above the camera noise is measured:

    explained_e = (E_base - E_e) / (E_base - E_noise)

``E_base`` is the squared residual of the base model refitted by least squares (so no proxy gets
credit for the difference between the θ-optimum and the least-squares optimum of the base model),
``E_e`` that of base + proxy, ``E_noise`` what the camera noise alone leaves. The proxies are written
from the physics, not from any particular implementation:

========================== =====================================================================================
camera_response            one monotone-ish cubic tone curve per channel, the same for every pixel of every frame
vignetting                 one achromatic radial falloff ``exp(k1 rho^2 + k2 rho^4)`` about a free centre, every
                           frame, object and water alike
artificial_light           two lamps beside the camera (offset, height, beam width; Gaussian beam, 1/R^2,
                           Beer-Lambert on the lamp path), scaling the direct signal of object pixels only
backscatter_coefficient    backscatter transmission with its own coefficient per channel:
                           ``+ b_c (T_c - T_c^k_c)`` on object pixels
forward_scatter            a share ``q`` of the direct signal spread by a Gaussian whose angular width grows
                           in proportion to range
unmodeled_geometry         non-parametric: energy of spatially coherent residual structure in open water after
                           a smooth surface per frame (no effect parameters to fit)
========================== =====================================================================================

Pose error, blur at the pixel scale, marine snow and sensor noise are judged at full resolution by
:mod:`uw_sil.fit.signatures`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .residuals import ReducedFrame, dilate, erode

__all__ = ["ProxyResult", "screen_proxies", "PROXIES"]

PROXIES = ("camera_response", "vignetting", "artificial_light", "backscatter_coefficient", "forward_scatter",
           "unmodeled_geometry")


@dataclass
class ProxyResult:
    effect: str
    explained: float            # share of the excess residual energy removed (0..1)
    energy: float               # mean squared residual (DN^2) with the proxy
    params: dict = field(default_factory=dict)
    base: list = field(default_factory=list)


class _Frame:
    """Static arrays of one low-resolution frame for the proxies: full planes (for blurs) and the same
    quantities at a subsample of pixels (every ``stride``-th row and column), where the pixel-wise proxies
    are evaluated."""

    def __init__(self, rf: ReducedFrame, stride: int, exclude=None):
        self.rf = rf
        h, w = rf.shape
        cam = rf.camera
        self.sel = np.zeros((h, w), bool)
        self.sel[stride // 2::stride, stride // 2::stride] = True
        self.keep = np.ones((h, w), bool) if exclude is None else ~np.asarray(exclude, bool)
        self.sel &= self.keep
        x = ((np.arange(w) - cam.cx) / cam.fx).astype(np.float32)[None, :]
        y = ((np.arange(h) - cam.cy) / cam.fy).astype(np.float32)[:, None]
        self.full = {
            "cover": rf.cover.astype(np.float32), "r": rf.r_fin.astype(np.float32),
            "z": np.where(rf.cover > 0, rf.depth, np.float32(0.0)).astype(np.float32),
            "i": np.moveaxis(rf.rgb, 2, 0).astype(np.float32),
            "x": np.broadcast_to(x, (h, w)), "y": np.broadcast_to(y, (h, w)),
        }
        f = self.full
        m = self.sel
        self.cover = f["cover"][m]
        self.hit = self.cover > 0
        self.r = f["r"][m]
        self.z = f["z"][m]
        self.z2 = self.z * self.z
        self.i = f["i"][:, m]
        self.R = np.moveaxis(rf.image, 2, 0)[:, m].astype(np.float32)
        self.Rfull = np.moveaxis(rf.image, 2, 0).astype(np.float32)
        self.x, self.y = f["x"][m], f["y"][m]
        rays = np.stack([self.x, self.y, np.ones_like(self.x)], -1)
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        self.X = rays * self.r[:, None]
        self.rmed = rf.frame.range_median
        self.fx = float(cam.fx)

    def base(self, p, fog="exp2", full=False):
        """(S, T) in 0..1 of base parameters p: (3, n) at the subsample, or (3, h, w) with ``full``."""
        a, b, rho = p[0:3], p[3:6], p[6]
        if full:
            f = self.full
            r, z, cover, i = f["r"], f["z"], f["cover"], f["i"]
        else:
            r, z, cover, i = self.r, self.z, self.cover, self.i
        fz = (rho * rho) * z * z if fog == "exp2" else (rho * z if fog == "exp" else 0.0)
        T = np.empty((3,) + r.shape, np.float32)
        S = np.empty_like(T)
        for c in range(3):
            T[c] = np.exp(-(r * a[c] + fz)) * cover
            S[c] = b[c] + T[c] * (i[c] - b[c])
        return S, T


def _lamps(fr: _Frame, ox, oy, half, bal, a):
    """Relative irradiance (3, n) of two lamps at (+-ox, oy, 0) with weights (1 - bal, bal), beams along z,
    Gaussian profile of half width at half maximum ``half`` (rad), 1/R^2 and exp(-a (R - 2 m)), relative to
    2 m on the axis."""
    E = np.zeros((3,) + fr.r.shape, np.float32)
    for sx, wl in ((1.0, 1.0 - bal), (-1.0, bal)):
        v = fr.X - np.array([sx * ox, oy, 0.0], np.float32)
        R = np.sqrt(np.maximum((v * v).sum(-1), 1e-4))
        ang = np.arccos(np.clip(v[..., 2] / R, -1, 1))
        g = wl * np.exp(-math.log(2) * (ang / max(half, 1e-3)) ** 2) * (4.0 / (R * R))
        for c in range(3):
            E[c] += g * np.exp(-a[c] * (R - 2.0))
    return E


def _blur(P, sigma):
    import cv2

    if sigma < 0.3:
        return P
    return np.stack([cv2.GaussianBlur(P[c], (0, 0), float(sigma), borderType=cv2.BORDER_REFLECT) for c in range(3)])


def _model(name, fr: _Frame, p, e, fog):
    """Proxy image (3, n) in 0..1 at the frame's subsample, of base p and proxy parameters e."""
    if name == "forward_scatter":
        S, T = fr.base(p, fog, full=True)
        b = np.asarray(p[3:6], np.float32)[:, None, None]
        q, width = e
        B = b * (1 - T)
        D = S - B
        sig = width * 1e-3 * fr.rmed * fr.fx
        s = 1 - np.exp(-q * fr.rmed)
        out = B + (1 - s) * D + s * _blur(D, sig)
        return out[:, fr.sel]
    S, T = fr.base(p, fog)
    b = np.asarray(p[3:6], np.float32)[:, None]
    if name == "base":
        return S
    if name == "camera_response":
        q = np.asarray(e, np.float32).reshape(3, 3)
        return S + q[:, 0:1] + q[:, 1:2] * S + q[:, 2:3] * S * (1 - S)
    if name == "vignetting":
        k1, k2, cx, cy = e
        rho2 = (fr.x - cx) ** 2 + (fr.y - cy) ** 2
        return S * np.exp(k1 * rho2 + k2 * rho2 * rho2)[None]
    if name == "artificial_light":
        ox, oy, half, bal, fill = e
        E = _lamps(fr, ox, oy, half, bal, p[0:3])
        L = fill + (1 - fill) * E
        D = T * fr.i
        return S + (L - 1) * D * fr.hit[None]
    if name == "backscatter_coefficient":
        k = np.asarray(e, np.float32)[:, None]
        Tn = np.where(fr.hit[None], T / np.maximum(fr.cover, 1e-6)[None], 1.0)
        TB = np.power(np.maximum(Tn, 1e-12), k) * fr.cover[None]
        return S + b * (T - TB)
    raise ValueError(name)


_SPECS = {
    # name: (x0, lo, hi, names)
    "camera_response": (np.zeros(9), np.full(9, -0.5), np.full(9, 0.5),
                        [f"{c}_{t}" for c in "rgb" for t in ("offset", "gain", "curve")]),
    "vignetting": (np.array([0.0, 0.0, 0.0, 0.0]), np.array([-2.0, -2.0, -0.2, -0.2]), np.array([1.0, 2.0, 0.2, 0.2]),
                   ["k1", "k2", "cx", "cy"]),
    "artificial_light": (np.array([0.4, -0.2, 0.6, 0.35, 0.9]), np.array([0.05, -1.0, 0.15, 0.0, 0.0]),
                         np.array([1.5, 1.0, 1.4, 0.5, 1.0]), ["offset_x", "offset_y", "half_angle", "balance", "fill"]),
    "backscatter_coefficient": (np.ones(3), np.full(3, 0.2), np.full(3, 6.0), ["ratio_r", "ratio_g", "ratio_b"]),
    "forward_scatter": (np.array([0.05, 10.0]), np.array([0.0, 1.0]), np.array([1.5, 40.0]), ["strength", "width_mrad_per_m"]),
}


def _fit(name, frames, p0, fog, max_nfev=None, joint=True):
    """Least-squares fit of a proxy (``joint``: with the 7 base parameters; else base held at ``p0``)."""
    from scipy.optimize import least_squares

    from ..sim.params import DEFAULT_RGB_BOUNDS

    blo, bhi = DEFAULT_RGB_BOUNDS
    p0 = np.clip(np.asarray(p0, float), blo, bhi)
    if name == "base":
        e0, elo, ehi = np.zeros(0), np.zeros(0), np.zeros(0)
    else:
        e0, elo, ehi, _ = _SPECS[name]
    if joint:
        x0, lo, hi = np.concatenate([p0, e0]), np.concatenate([blo, elo]), np.concatenate([bhi, ehi])
    else:
        x0, lo, hi = e0.astype(float), elo, ehi
    x0 = np.clip(x0, lo + 1e-9, hi - 1e-9)

    def split(x):
        return (x[:7], x[7:]) if joint else (p0, x)

    def resid(x):
        p, e = split(x)
        out = []
        for fr in frames:
            I = _model(name, fr, p, e, fog)
            out.append((np.clip(I, 0, 1) * 255.0 - fr.R).ravel())
        return np.concatenate(out)

    res = least_squares(resid, x0, bounds=(lo, hi), method="trf", x_scale=np.maximum(hi - lo, 1e-3) * 0.1,
                        diff_step=1e-3, max_nfev=max_nfev or 8, xtol=1e-4, ftol=1e-4)
    p, e = split(res.x)
    r = res.fun
    return np.concatenate([p, e]), float(np.mean(r * r))


def screen_proxies(rframes, base_x, noise, fog: str = "exp2", stride: int = 3, names=PROXIES,
                   exclude=None) -> dict:
    """Fit each proxy (with the base parameters) and return ``{effect: ProxyResult}`` plus ``"base"``.

    ``rframes``: low-resolution reduced frames (e.g. 160x120); ``noise``: per-frame (3,) sigma at that size.
    ``exclude``: per frame, a boolean mask of pixels left out of every fit and energy (a recording's
    particles: a random process of its own, which no proxy of the expected image can explain; counted in,
    dense snow's energy made the share of a real second effect small).
    """
    if exclude is None:
        exclude = [None] * len(rframes)
    frames = [_Frame(rf, stride, ex) for rf, ex in zip(rframes, exclude)]
    n2 = float(np.mean([np.mean(np.square(s)) for s in noise]))
    xb, Eb = _fit("base", frames, np.asarray(base_x, float), fog)
    # the share is taken of the excess over the noise, but never of less than a third of the noise energy
    # (else a near-perfect fit would give any proxy a large share of almost nothing)
    exc = max(Eb - n2, n2 / 3.0, 0.5)
    out = {"base": ProxyResult("base", 0.0, Eb, {}, xb.tolist())}
    for name in names:
        if name == "unmodeled_geometry":
            out[name] = _water_structure(frames, xb, fog, Eb, n2, noise)
            continue
        x, E = _fit(name, frames, xb, fog)
        pn = _SPECS[name][3]
        out[name] = ProxyResult(name, float(np.clip((Eb - E) / exc, 0.0, 1.0)), E,
                                {k: float(v) for k, v in zip(pn, x[7:])}, x[:7].tolist())
    out["_noise_energy"] = n2
    return out


def _water_structure(frames, xb, fog, Eb, n2, noise) -> ProxyResult:
    """Energy of spatially coherent residual structure in open water (see module docstring)."""
    import cv2

    removed, npx = 0.0, 0
    total_px = 0
    for fr, s in zip(frames, noise):
        S, _ = fr.base(xb, fog, full=True)
        D = (fr.Rfull - 255 * S)                              # (3, h, w)
        w = fr.rf.water & ~dilate(fr.rf.cover > 0, 2) & fr.keep
        total_px += fr.sel.sum()
        if w.sum() < 100:
            continue
        x, y = fr.full["x"][w], fr.full["y"][w]
        A = np.stack([np.ones_like(x), x, y, x * x, y * y, x * y], 1)
        for c in range(3):
            coef, *_ = np.linalg.lstsq(A, D[c][w], rcond=None)
            E = np.zeros_like(D[c])
            E[w] = D[c][w] - A @ coef
            sm = cv2.blur(E, (5, 5)) / np.maximum(cv2.blur(w.astype(np.float32), (5, 5)), 1e-3)
            sm = np.where(erode(w, 2), sm, 0)
            # a 5x5 mean of white noise keeps sigma^2/25 of its energy: subtract that
            e = np.maximum(sm * sm - float(s[c]) ** 2 / 25.0, 0)
            removed += float(e[fr.sel].sum())
        npx += int(w[fr.sel].sum())
    n_res = total_px * 3
    E = Eb - removed / max(n_res, 1)
    exc = max(Eb - n2, n2 / 3.0, 0.5)
    return ProxyResult("unmodeled_geometry", float(np.clip((Eb - E) / exc, 0, 1)), float(E), {}, list(xb))
