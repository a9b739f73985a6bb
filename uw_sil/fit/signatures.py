"""Residual signatures: one test per physical effect the base model leaves out.

Each test looks at the residual between the recording and the fitted base model (paper Eq. 1 with fog)
for the footprint that one kind of physics leaves, described by what the physics does, not by any
particular implementation of it (forms and signatures: Jaffe 1990, McGlamery 1980, Akkaynak & Treibitz
2018/2019, and ``underwater-effects.md`` of this project):

============================  ==============================================================================
effect                        footprint tested
============================  ==============================================================================
``artificial_light``          multiplicative structure on the object (log-residual) that is smooth, not in the
                              water, and changes with range (hotspot moving with range: parallax of offset
                              lamps); brightness level vs ln(range) slope
``vignetting``                radial falloff about the principal point, the same in every frame, in the water
                              as on the object, the same in every colour channel (multiplicative, achromatic)
``forward_scatter``           loss of edge / high-frequency energy: the recording matches a *blurred*
                              simulation better (best Gaussian width, after aligning), more so with range;
                              power-spectrum ratio real/sim per frame
``backscatter_coefficient``   additive bias on the object, independent of the object's brightness, zero in
                              the water and varying with range (beta_D != beta_B)
``sensor_noise``              noise structure the base model's constant white Gaussian lacks: variance rising
                              with intensity, spatial correlation, fixed pattern (columns/rows, across frames)
``marine_snow``               sparse, small, positive outliers that do not persist between frames
``camera_response``           residual as a smooth *function of intensity*, the same in every frame and in
                              object and water pixels (tone curve, pedestal, white balance)
``unmodeled_geometry``        structure (texture, coherent regions) where the simulation shows open water
``pose_error``                edge-aligned residual dipoles: the recording matches a *shifted / rotated*
                              simulation better; the shift varies between frames
============================  ==============================================================================

Every test returns a :class:`Signature` with a ``score``: 1 is the detection threshold (0 = nothing),
``stats`` (the measured numbers), ``hint`` (rough effect-parameter estimates for the refit, in
physical terms) and ``plot`` (data for the report). Thresholds are physical magnitudes (percent of
falloff, pixels of blur or shift, grey levels of bias, ratios of noise), stated next to each test.

References
----------
.. [1] J. S. Jaffe, "Computer modeling and the design of optimal underwater imaging systems", IEEE J.
   Oceanic Eng. 15(2), 101-111, 1990.
.. [2] B. L. McGlamery, "A computer model for underwater camera systems", Proc. SPIE 208, 1980.
.. [3] D. Akkaynak and T. Treibitz, "A revised underwater image formation model", CVPR 2018.
.. [4] D. Akkaynak and T. Treibitz, "Sea-thru: a method for removing water from underwater images", CVPR 2019.
.. [5] G. D. Evangelidis and E. Z. Psarakis, "Parametric image alignment using enhanced correlation
   coefficient maximization", IEEE TPAMI 30(10), 1858-1865, 2008 (shift estimation, via OpenCV).
.. [6] A. Foi, M. Trimeche, V. Katkovnik and K. Egiazarian, "Practical Poissonian-Gaussian noise modeling
   and fitting for single-image raw-data", IEEE TIP 17(10), 1737-1754, 2008 (intensity-dependent noise).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Optional, Sequence

import numpy as np

from .residuals import ReducedFrame, dilate, erode

__all__ = ["Signature", "SignatureContext", "run_signatures", "luminance", "jsonable",
           "speck_masks", "speck_sizes", "own_specks", "persistent_specks", "scene_specks", "particle_masks",
           "noise_statistics", "NoisePixels", "trimmed_sigma", "median_filter"]

_MAD = 1.4826
_LUMA = np.array([0.299, 0.587, 0.114], np.float32)
# Below this luminance noise (grey levels; 0.7-1.0 per channel) the rounding of 8-bit channels makes the
# median of a line step with the share of its pixels on either side of a grey level: the fixed-pattern
# statistics move from line medians (above) to winsorized line means (below), blended in between (measured
# on white noise rounded per channel: median-based ratios 9-21x the white value at 0.28-0.33 grey levels of
# luminance noise, 1.6x at 0.44, 1.0x from 0.57 up).
ROUNDING_NOISE_DN = (0.5, 0.7)
WINSOR_Z = 1.5


def _winsor_var(c: float) -> float:
    """E[clip(z, -c, c)^2] of a standard normal z: the white-noise variance (in sigma^2 / n) of a mean of n
    values winsorized at c sigma."""
    inside = math.erf(c / math.sqrt(2))
    return inside - 2 * c * math.exp(-c * c / 2) / math.sqrt(2 * math.pi) + c * c * (1 - inside)


def luminance(img: np.ndarray) -> np.ndarray:
    return np.asarray(img, np.float32) @ _LUMA


@dataclass
class Signature:
    """Outcome of one signature test."""

    effect: str
    score: float                       # 1 = detection threshold
    stats: dict = field(default_factory=dict)
    hint: dict = field(default_factory=dict)
    plot: dict = field(default_factory=dict)
    judged: bool = True                # False: could not be judged from this data
    reason: str = ""

    def to_dict(self) -> dict:
        return {"effect": self.effect, "score": float(self.score), "judged": self.judged, "reason": self.reason,
                "stats": jsonable(self.stats), "hint": jsonable(self.hint)}


def jsonable(v):
    if isinstance(v, dict):
        return {str(k): jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return jsonable(v.tolist())
    if isinstance(v, (np.floating, float)):
        return float(v) if math.isfinite(float(v)) else None
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.bool_,)):
        return bool(v)
    return v


class SignatureContext:
    """Everything the tests look at: reduced frames with base simulations and residuals, and the
    full-resolution frames (for tests of fine structure: blur, shifts, particles, noise).

    Parameters
    ----------
    rframes : list of ReducedFrame
    sims : list of (h, w, 3) float32 in 0..1, noise-free base simulation of each reduced frame
    noise : list of (3,) camera noise (grey levels) of each reduced frame
    base_x : (7,) fitted base parameters
    fog : str
    """

    def __init__(self, rframes: Sequence[ReducedFrame], sims, noise, base_x, fog: str = "exp2"):
        self.rframes = list(rframes)
        self.sims = [np.asarray(s, np.float32) for s in sims]
        self.res = [rf.image - 255.0 * s for rf, s in zip(self.rframes, self.sims)]
        self.noise = [np.asarray(n, float) for n in noise]
        self.base_x = np.asarray(base_x, float)
        self.fog = fog
        self._full = {}

    def full_sim(self, k: int) -> np.ndarray:
        """Noise-free base simulation of frame k at full resolution, (H, W, 3) in 0..255."""
        if k not in self._full:
            from ..sim.optics import degrade

            rr = self.rframes[k].frame.render
            p = np.clip(self.base_x, 0, None)
            p[3:6] = np.clip(p[3:6], 0, 1)
            self._full[k] = degrade(rr.rgb, rr.range, rr.depth, p, fog=self.fog) * 255.0
        return self._full[k]

    def tan_coords(self, k: int):
        """Normalized image coordinates (tan of the field angle) of reduced frame k: (x (1, w), y (h, 1))."""
        cam = self.rframes[k].camera
        h, w = self.rframes[k].shape
        x = ((np.arange(w) - cam.cx) / cam.fx).astype(np.float32)[None, :]
        y = ((np.arange(h) - cam.cy) / cam.fy).astype(np.float32)[:, None]
        return x, y


# ----------------------------------------------------------------------------------------------- helpers


def _wls(A: np.ndarray, y: np.ndarray, w: Optional[np.ndarray] = None):
    """Weighted least squares: (coef, residual, R^2)."""
    if w is None:
        w = np.ones(len(y))
    sw = np.sqrt(w)
    coef, *_ = np.linalg.lstsq(A * sw[:, None], y * sw, rcond=None)
    fit = A @ coef
    r = y - fit
    ss = float(np.sum(w * (y - np.average(y, weights=w)) ** 2)) or 1e-12
    return coef, r, 1.0 - float(np.sum(w * r * r)) / ss


def _log_ratio(real, sim255, floor=2.0):
    return np.log(np.maximum(real, 0) + floor) - np.log(np.maximum(sim255, 0) + floor)


def _radial_bins(rho, values, mask, nbins=10, rmax=None):
    """Median of ``values`` in radial bins of ``rho`` over ``mask``: (centres, medians, counts)."""
    if rmax is None:
        rmax = float(rho.max())
    edges = np.linspace(0, rmax, nbins + 1)
    idx = np.clip(np.digitize(rho[mask], edges) - 1, 0, nbins - 1)
    v = values[mask]
    cen, med, cnt = [], [], []
    for i in range(nbins):
        sel = v[idx == i]
        if sel.size >= 20:
            cen.append(0.5 * (edges[i] + edges[i + 1]))
            med.append(float(np.median(sel, axis=0)) if sel.ndim == 1 else np.median(sel, axis=0))
            cnt.append(sel.shape[0])
    return np.array(cen), np.array(med), np.array(cnt)


# ----------------------------------------------------------------------------------------------- tests


def sig_vignetting(ctx: SignatureContext) -> Signature:
    """Radial, frame-invariant, achromatic falloff, in water and on the object alike.

    Log-ratio real/sim in the water (where the simulation is the flat background) is fitted, over all
    frames jointly, by ``c_f + k1 rho^2 + k2 rho^4`` (``rho``: tan of the field angle; per-frame offsets
    ``c_f``), per channel. Measured: corner falloff ``A = 1 - exp(k1 rho_c^2 + k2 rho_c^4)``; the spread of
    A between channels (vignetting is achromatic; a lamp veil in the water is not proportional to the
    background colour) and between frames (vignetting is fixed to the image); and how well the same
    radial profile explains the object's log-ratio (slope 1 for vignetting; a lamp veil does not
    darken the object's corners). Threshold: 3 % corner falloff, consistent across channels/frames.
    """
    rows = {c: [] for c in range(3)}
    per_frame = []
    rho_c = 0.0
    prof = []
    for k, rf in enumerate(ctx.rframes):
        x, y = ctx.tan_coords(k)
        rho = np.sqrt(x * x + y * y)
        rho_c = max(rho_c, float(rho.max()))
        L = _log_ratio(rf.image, 255 * ctx.sims[k])
        m = rf.water
        if m.sum() < 200:
            continue
        cen, med, cnt = _radial_bins(rho, L, m, nbins=12)
        if len(cen) < 4:
            continue
        for c in range(3):
            rows[c].append((k, cen, med[:, c], cnt))
        prof.append((k, cen, med.mean(axis=1)))
        A = np.stack([np.ones_like(cen), cen ** 2, cen ** 4], 1)
        coef, _, _ = _wls(A, med.mean(axis=1), np.sqrt(cnt))
        per_frame.append(float(1 - np.exp(coef[1] * rho_c ** 2 + coef[2] * rho_c ** 4)))
    if not rows[0]:
        return Signature("vignetting", 0.0, judged=False, reason="too little open water to judge radial falloff")
    ks = sorted({k for k, *_ in rows[0]})
    kidx = {k: i for i, k in enumerate(ks)}
    falloff, coefs = [], []
    for c in range(3):
        A, yv, wv = [], [], []
        for k, cen, med, cnt in rows[c]:
            for ce, me, cn in zip(cen, med, cnt):
                row = np.zeros(len(ks) + 2)
                row[kidx[k]] = 1
                row[-2] = ce ** 2
                row[-1] = ce ** 4
                A.append(row)
                yv.append(me)
                wv.append(np.sqrt(cn))
        coef, _, _ = _wls(np.array(A), np.array(yv), np.array(wv))
        coefs.append(coef[-2:])
        falloff.append(float(1 - np.exp(coef[-2] * rho_c ** 2 + coef[-1] * rho_c ** 4)))
    falloff = np.array(falloff)
    k_mean = np.mean(coefs, axis=0)
    A_mean = float(falloff.mean())
    chroma_spread = float(falloff.max() - falloff.min())
    frame_spread = float(np.std(per_frame)) if len(per_frame) > 1 else 0.0
    # object agreement: regress the object's log-ratio (per-frame offsets) on the water radial profile
    xs, ys = [], []
    for k, rf in enumerate(ctx.rframes):
        m = rf.obj
        if m.sum() < 50:
            continue
        x, y = ctx.tan_coords(k)
        rho = np.broadcast_to(np.sqrt(x * x + y * y), rf.shape)
        v = k_mean[0] * rho[m] ** 2 + k_mean[1] * rho[m] ** 4
        L = _log_ratio(rf.image, 255 * ctx.sims[k])[m].mean(axis=1)
        if np.ptp(v) < 0.01:
            continue
        xs.append(v - v.mean())
        ys.append(L - L.mean())
    obj_slope = None
    if xs:
        xv, yv = np.concatenate(xs), np.concatenate(ys)
        den = float(np.sum(xv * xv))
        obj_slope = float(np.sum(xv * yv) / den) if den > 0 else None
    score = max(0.0, A_mean) / 0.03
    if A_mean > 0:
        score *= max(0.0, 1.0 - chroma_spread / max(A_mean, 1e-6) / 1.5)   # chromatic -> not a lens
        score *= max(0.0, 1.0 - frame_spread / max(A_mean, 1e-6) / 1.5)   # frame-varying -> not a lens
        if obj_slope is not None:
            score *= float(np.clip(obj_slope, 0.0, 1.0)) ** 0.5
    stats = {"corner_falloff": A_mean, "falloff_rgb": falloff.tolist(), "channel_spread": chroma_spread,
             "frame_spread": frame_spread, "object_slope": obj_slope, "rho_corner": rho_c,
             "k1": float(k_mean[0]), "k2": float(k_mean[1])}
    return Signature("vignetting", float(score), stats, {"corner_falloff": A_mean, "k1": float(k_mean[0]),
                                                          "k2": float(k_mean[1])},
                     {"radial": [(int(k), c.tolist(), m.tolist()) for k, c, m in prof]})


def sig_artificial_light(ctx: SignatureContext) -> Signature:
    """Multiplicative, smooth structure on the object that the water lacks and that changes with range.

    Per frame, the object's log-ratio real/sim (channel mean) is fitted by a quadratic surface in image
    coordinates: its spread (std over the object, minus what the water's radial profile would put there)
    is lamp beam and distance falloff across the object. Across frames, the object's mean log-ratio is
    regressed on ln(range): lamps give a power-law falloff (slope about -2 before the base fit absorbs
    part of it into attenuation) that the exponential base model cannot follow exactly. Also measured:
    the bright spot (maximum of the surface) and how it moves between frames. Threshold: 4 % spread of
    the smooth object pattern, or a level residual of 4 % rms against range.
    """
    spreads, levels, ranges, spots, water_spread = [], [], [], [], []
    surfaces = []
    for k, rf in enumerate(ctx.rframes):
        m = erode(rf.obj, 1)
        if m.sum() < 40:
            continue
        x, y = ctx.tan_coords(k)
        X = np.broadcast_to(x, rf.shape)[m]
        Y = np.broadcast_to(y, rf.shape)[m]
        L = _log_ratio(rf.image, 255 * ctx.sims[k])[m].mean(axis=1)
        A = np.stack([np.ones_like(X), X, Y, X * X, Y * Y, X * Y], 1)
        if np.ptp(X) < 0.05 or np.ptp(Y) < 0.05:
            A = A[:, :3]
        coef, r, r2 = _wls(A, L)
        fit = A @ coef
        sp = float(np.std(fit))
        # what a frame-fixed radial pattern measured in the water would give here
        w = rf.water
        if w.sum() > 200:
            Lw = _log_ratio(rf.image, 255 * ctx.sims[k]).mean(axis=2)
            rho = np.sqrt(x * x + y * y)
            Aw = np.stack([np.ones(w.sum()), np.broadcast_to(rho, rf.shape)[w] ** 2], 1)
            cw, _, _ = _wls(Aw, Lw[w])
            rho_o = np.sqrt(X * X + Y * Y)
            water_spread.append(float(np.std(cw[1] * rho_o ** 2)))
            sp = max(0.0, sp - float(np.std(cw[1] * rho_o ** 2)))
        spreads.append(sp * np.sqrt(max(0.0, r2)))
        levels.append(float(np.mean(L)))
        ranges.append(rf.frame.range_median)
        j = int(np.argmax(fit))
        spots.append((float(X[j]), float(Y[j])))
        surfaces.append((k, coef.tolist()))
    if not spreads:
        return Signature("artificial_light", 0.0, judged=False, reason="object too small in every frame")
    spread = float(np.median(spreads))
    ranges = np.array(ranges)
    levels = np.array(levels)
    level_rms, slope = 0.0, None
    if len(levels) >= 3 and np.ptp(np.log(ranges)) > 0.2:
        A = np.stack([np.ones_like(ranges), np.log(ranges)], 1)
        coef, r, _ = _wls(A, levels)
        slope = float(coef[1])
        level_rms = float(np.sqrt(np.mean((levels - levels.mean()) ** 2)))
    spot_move = float(np.std(np.array(spots), axis=0).sum()) if len(spots) > 1 else 0.0
    score = max(spread / 0.04, level_rms / 0.04 if slope is not None and slope < 0 else 0.0)
    stats = {"object_spread": spread, "object_spread_per_frame": spreads, "level_rms": level_rms,
             "level_slope_vs_ln_range": slope, "spot_motion": spot_move, "ranges": ranges.tolist(),
             "levels": levels.tolist(), "water_radial_spread": water_spread}
    return Signature("artificial_light", float(score), stats, {"slope_ln_range": slope, "spots": spots},
                     {"levels": (ranges.tolist(), levels.tolist()), "surfaces": surfaces})


def sig_backscatter_coefficient(ctx: SignatureContext) -> Signature:
    """Additive bias on the object that does not depend on its brightness, absent in the water, varying
    with range (beta_D != beta_B).

    Per frame and channel, the object residual is regressed on the simulated intensity: ``d = alpha +
    beta s`` (s centred). An additive term ``alpha`` beyond the water's own bias, with ``beta`` near 0, is
    what a separate backscatter coefficient leaves (``b (T_D - T_B)`` is the same for dark and bright
    parts at one range); a gain (``beta``) is what lamps or white balance leave. Threshold: 1.5 grey
    levels rms of the additive object-minus-water bias over frames, and larger than the gain's effect.
    """
    alphas, gains, ranges, wbias = [], [], [], []
    for k, rf in enumerate(ctx.rframes):
        m = erode(rf.obj, 1)
        if m.sum() < 40:
            continue
        S = 255 * ctx.sims[k][m]
        D = ctx.res[k][m]
        al, be = [], []
        for c in range(3):
            s = S[:, c] - S[:, c].mean()
            A = np.stack([np.ones_like(s), s], 1)
            coef, _, _ = _wls(A, D[:, c])
            al.append(coef[0])
            be.append(coef[1] * max(1.0, float(np.std(S[:, c]))))   # effect of the gain in grey levels
        w = rf.water
        wb = ctx.res[k][w].mean(axis=0) if w.sum() > 100 else np.zeros(3)
        alphas.append(np.array(al) - wb)
        gains.append(np.array(be))
        wbias.append(wb)
        ranges.append(rf.frame.range_median)
    if len(alphas) < 2:
        return Signature("backscatter_coefficient", 0.0, judged=False, reason="object too small in most frames")
    alphas = np.array(alphas)
    gains = np.array(gains)
    add_rms = float(np.sqrt(np.mean(alphas ** 2)))
    gain_rms = float(np.sqrt(np.mean(gains ** 2)))
    order = np.argsort(ranges)
    score = add_rms / 1.5 * min(1.0, add_rms / max(gain_rms, 1e-6))
    stats = {"additive_rms": add_rms, "gain_rms": gain_rms, "ranges": np.array(ranges)[order].tolist(),
             "additive_rgb": alphas[order].tolist(), "water_bias": np.array(wbias)[order].tolist()}
    return Signature("backscatter_coefficient", float(score), stats, {"additive_rgb": alphas.mean(axis=0).tolist()},
                     {"additive": (np.array(ranges)[order].tolist(), alphas[order].tolist())})


def sig_camera_response(ctx: SignatureContext) -> Signature:
    """Residual as a smooth function of intensity, the same in every frame (tone curve, pedestal, white
    balance).

    Per channel, the residual of all pixels (object and water, all frames) is binned by simulated
    intensity; the bin medians are fitted by a cubic in intensity. Measured: the curve's departure from
    its best straight line (curvature: gamma), its value at the dark end (pedestal) and, per frame, the
    agreement of each frame's bins with the common curve (a camera's response does not change with
    range; range-dependent biases do). Threshold: 2 grey levels of curvature or 3 of dark-end
    offset, consistent over frames.
    """
    curves, curv, ped, consist = [], [], [], []
    for c in range(3):
        S = np.concatenate([255 * ctx.sims[k][..., c][rf.obj | rf.water] for k, rf in enumerate(ctx.rframes)])
        D = np.concatenate([ctx.res[k][..., c][rf.obj | rf.water] for k, rf in enumerate(ctx.rframes)])
        F = np.concatenate([np.full(int((rf.obj | rf.water).sum()), k) for k, rf in enumerate(ctx.rframes)])
        edges = np.linspace(0, 255, 33)
        idx = np.clip(np.digitize(S, edges) - 1, 0, 31)
        cen, med, cnt = [], [], []
        for i in range(32):
            sel = idx == i
            n = int(sel.sum())
            if n >= 30:
                cen.append(0.5 * (edges[i] + edges[i + 1]))
                med.append(float(np.median(D[sel])))
                cnt.append(n)
        if len(cen) < 5:
            continue
        cen, med, cnt = np.array(cen), np.array(med), np.array(cnt)
        t = cen / 255.0
        w = np.sqrt(cnt)
        A3 = np.stack([np.ones_like(t), t, t * t, t ** 3], 1)
        c3, _, _ = _wls(A3, med, w)
        A1 = A3[:, :2]
        c1, _, _ = _wls(A1, med, w)
        tt = np.linspace(t.min(), t.max(), 50)
        f3 = np.stack([np.ones_like(tt), tt, tt * tt, tt ** 3], 1) @ c3
        f1 = np.stack([np.ones_like(tt), tt], 1) @ c1
        curv.append(float(np.max(np.abs(f3 - f1))))
        ped.append(float(f3[0]))
        curves.append((c, cen.tolist(), med.tolist()))
        # per-frame agreement with the common curve
        errs = []
        for k in np.unique(F):
            sel = F == k
            pred = np.stack([np.ones(sel.sum()), S[sel] / 255, (S[sel] / 255) ** 2, (S[sel] / 255) ** 3], 1) @ c3
            errs.append(float(np.median(np.abs(D[sel] - pred))))
        consist.append(float(np.median(errs)))
    if not curv:
        return Signature("camera_response", 0.0, judged=False, reason="too narrow an intensity range")
    curv_m = float(np.max(curv))
    ped_m = float(np.max(np.abs(ped)))
    noise = float(np.mean([np.mean(n) for n in ctx.noise]))
    score = max(curv_m / 2.0, ped_m / 3.0 * 0.5)
    stats = {"curvature_dn": curv, "dark_end_dn": ped, "frame_disagreement_dn": consist, "noise_dn": noise}
    return Signature("camera_response", float(score), stats, {"curvature_dn": curv, "dark_end_dn": ped},
                     {"curves": curves})


def sig_unmodeled_geometry(ctx: SignatureContext, margin: int = 4) -> Signature:
    """Structure where the simulation shows open water: texture and coherent regions.

    In water pixels at least ``margin`` (reduced) pixels from the rendered model, the residual minus a
    smooth quadratic surface per frame and channel (lamp veil, vignetting) is median-filtered (5x5:
    isolated particles vanish) and compared with the camera noise: the share of water pixels where its
    local mean (over 7x7) departs by more than 3 noise standard errors, or whose local contrast exceeds
    the noise by 50 %. Threshold: 0.6 % of the water area (frames with open water and noise only give 0).
    """
    import cv2

    shares, texture = [], []
    maps = []
    for k, rf in enumerate(ctx.rframes):
        w = rf.water & ~dilate(rf.cover > 0, margin)
        if w.sum() < 300:
            continue
        x, y = ctx.tan_coords(k)
        X = np.broadcast_to(x, rf.shape)
        Y = np.broadcast_to(y, rf.shape)
        A = np.stack([np.ones(w.sum()), X[w], Y[w], X[w] ** 2, Y[w] ** 2, X[w] * Y[w]], 1)
        D = luminance(ctx.res[k])
        coef, _, _ = _wls(A, D[w])
        full = np.stack([np.ones_like(X), X, Y, X * X, Y * Y, X * Y], -1) @ coef
        E = np.where(w, D - full, 0).astype(np.float32)
        E = cv2.medianBlur(E, 5)
        sig = float(np.mean(ctx.noise[k]) * 0.7)           # luminance noise after the median (~0.7 of pixel noise... a bound)
        wm = w.astype(np.float32)
        n = cv2.blur(wm, (7, 7))
        mean = cv2.blur(E * wm, (7, 7)) / np.maximum(n, 1e-6)
        sq = cv2.blur(E * E * wm, (7, 7)) / np.maximum(n, 1e-6)
        std = np.sqrt(np.maximum(sq - mean * mean, 0))
        inner = erode(w, 3)
        if inner.sum() < 100:
            continue
        coherent = np.abs(mean) > 3.0 * max(sig, 0.3) / 7.0 * 3.0
        textured = std > 1.5 * max(sig, 0.3)
        share = float(np.mean((coherent | textured)[inner]))
        shares.append(share)
        texture.append(float(np.mean(textured[inner])))
        maps.append((k, (coherent | textured) & inner))
    if not shares:
        return Signature("unmodeled_geometry", 0.0, judged=False, reason="too little open water")
    share = float(np.median(shares))
    horizon = _horizon_ramps(ctx, margin)
    ramp = float(np.median([h["excess"] for h in horizon])) if horizon else 0.0
    score = max(share / 0.006, ramp / 3.0)
    return Signature("unmodeled_geometry", float(score), {"structured_share": share, "per_frame": shares,
                                                           "textured_share": texture, "horizon_ramp": horizon},
                     {"share": share}, {"maps": maps})


def _horizon_ramps(ctx: SignatureContext, margin: int) -> list:
    """A seafloor far below fades into the water colour towards its horizon: in open water, the row profile
    of the residual is flat above a horizon row and ramps below it (a kink a smooth surface does not have).
    Per frame: the median residual per row of the open water (luminance, grey levels), fitted by a quadratic
    in the row and by a constant plus a ramp below a horizon (searched); ``excess`` is how much better the
    ramp fits, in units of the row medians' noise (rms improvement / standard error), signed by nothing."""
    out = []
    for k, rf in enumerate(ctx.rframes):
        w = rf.water & ~dilate(rf.cover > 0, margin)
        D = luminance(ctx.res[k])
        rows = [(i, float(np.median(D[i][w[i]])), int(w[i].sum())) for i in range(rf.shape[0]) if w[i].sum() >= 20]
        if len(rows) < 20:
            continue
        yy = np.array([r[0] for r in rows], float) / rf.shape[0]
        m = np.array([r[1] for r in rows])
        n = np.array([r[2] for r in rows], float)
        se = 1.25 * float(np.mean(ctx.noise[k])) * 0.6 / np.sqrt(n)      # median of n: ~1.25 sigma/sqrt(n)
        wgt = 1.0 / se ** 2
        Aq = np.stack([np.ones_like(yy), yy, yy * yy], 1)
        _, rq, _ = _wls(Aq, m, wgt)
        best = None
        for h in np.linspace(0.2, 0.9, 29):
            Ar = np.stack([np.ones_like(yy), np.maximum(0.0, yy - h), np.maximum(0.0, yy - h) ** 2], 1)
            if np.sum(yy > h) < 8:
                continue
            _, rr, _ = _wls(Ar, m, wgt)
            chi = float(np.sum(wgt * rr * rr))
            if best is None or chi < best[0]:
                best = (chi, h)
        if best is None:
            continue
        chi_q = float(np.sum(wgt * rq * rq))
        # improvement of the fit per row, in standard errors
        excess = max(0.0, (chi_q - best[0]) / len(yy)) ** 0.5
        out.append({"frame": int(rf.frame.index), "horizon_row_share": float(best[1]), "excess": float(excess)})
    return out


def trimmed_sigma(d: np.ndarray, keep: float = 0.9) -> float:
    """Noise sigma from pixel differences: RMS of the smallest ``keep`` share of |d|, corrected to a Gaussian
    (robust to edges; unlike the MAD it does not step with the integer grey levels of 8-bit frames), divided
    by sqrt(2) for a difference of two pixels.

    Single-precision differences (luminance) are selected in single precision: every float32 is a float64, so
    the smallest ``keep`` share is the same set of values, and its mean square is taken in double precision
    (:func:`_smallest_squares`)."""
    a = np.asarray(d)
    a = np.abs(a if a.dtype == np.float32 else a.astype(np.float64)).ravel()
    if a.size == 0:
        return float("nan")
    n = max(1, int(keep * a.size))
    return float(np.sqrt(_smallest_squares(a, n) / n / _truncated_second_moment(keep)) / math.sqrt(2))


def _smallest_squares(a: np.ndarray, n: int) -> float:
    """The sum of squares (double precision) of the ``n`` smallest values of ``a`` (1-D, not negative).

    The noise fit takes this of hundreds of thousands of differences, three times per simulated frame: the whole
    sum less the largest ``a.size - n``, found among the values above a threshold that a 1/64 sample puts below
    them (about 15 % of the values), 2.1x faster than a partition of all (286,000 values: 1.2 ms against 2.6 ms).
    The same sum to about 1e-14 relative (another order of summation); where the sample's threshold leaves fewer
    values than the largest, a partition of all."""
    m = a.size - n
    if m > 0 and a.size >= 20_000:
        j = int(a[::64].size * (1.0 - 1.5 * m / a.size))
        big = a[a > np.partition(a[::64], j)[j]]
        if big.size >= m:
            return _sum_of_squares(a) - _sum_of_squares(np.partition(big, big.size - m)[big.size - m:])
    return _sum_of_squares(np.partition(a, n - 1)[:n])


def _sum_of_squares(a: np.ndarray) -> float:
    """The sum of squares of ``a`` in double precision, without BLAS: with a dot product (BLAS's threads) a trimmed
    sigma of 286,000 differences took 6.3 ms against 2.2 ms on a 2-core machine with both cores busy."""
    a = a.astype(np.float64)
    a *= a
    return float(a.sum())


@lru_cache(maxsize=8)
def _truncated_second_moment(keep: float) -> float:
    """E[x^2 | |x| < q] of a standard normal x, with q its ``keep`` two-sided quantile (the standard library's
    normal distribution: a worker process that measures noise need not import scipy.stats, 0.7 s, for it)."""
    from statistics import NormalDist

    q = NormalDist().inv_cdf(0.5 + keep / 2)
    return float(1 - 2 * q * NormalDist().pdf(q) / keep)


def _hp(img, s=3.0):
    import cv2

    return img - cv2.GaussianBlur(img, (0, 0), s)


def particle_exclusion(Y: np.ndarray, S: np.ndarray, hit: np.ndarray, grow: int = 3) -> Optional[np.ndarray]:
    """Pixels of a recording's sparse bright outliers (particles: :func:`speck_masks`), grown by ``grow``
    pixels to take their blurred wings; None when there are none. Noise statistics leave them out: a speck
    of a few pixels is correlated, bright structure that white-noise statistics would read as noise."""
    pos = speck_masks(Y, S, hit)[0]
    return dilate(pos, grow) if pos.any() else None


def particle_masks(ctx: "SignatureContext", grow: int = 1) -> list:
    """:func:`particle_exclusion` of every frame of ``ctx`` at full resolution (all False without particles)."""
    out = []
    for k, rf in enumerate(ctx.rframes):
        fr = rf.frame
        m = particle_exclusion(luminance(fr.image.astype(np.float32)), luminance(ctx.full_sim(k)),
                               np.isfinite(fr.render.range), grow)
        out.append(np.zeros(fr.image.shape[:2], bool) if m is None else m)
    return out


def _median(block: np.ndarray, axis: int) -> np.ndarray:
    """``np.median(block, axis)`` of a 2-D block, the same values and type, from one sort of each line made
    contiguous (``np.median`` partitions along ``axis`` in place of a copy: 5 ms for the column medians of a
    640x480 frame's water, the sort 0.5 ms)."""
    s = np.sort(np.ascontiguousarray(block if axis == 1 else block.T), axis=1)
    m = s.shape[1]
    return s[:, (m - 1) // 2] if m % 2 else 0.5 * (s[:, m // 2 - 1] + s[:, m // 2])


def _masked_median(block: np.ndarray, keep: np.ndarray, axis: int, n: np.ndarray) -> np.ndarray:
    """Median along ``axis`` of the ``keep`` values of ``block`` (``n``: their count per line, all > 0): what
    ``np.nanmedian`` gives with the rest NaN, in one sort (nanmedian sorts each line through a masked array,
    half the cost of the noise fit's statistics)."""
    s = np.sort(np.where(keep, block, np.inf), axis=axis)
    lo, hi = np.expand_dims((n - 1) // 2, axis), np.expand_dims(n // 2, axis)
    return (0.5 * (np.take_along_axis(s, lo, axis) + np.take_along_axis(s, hi, axis))).squeeze(axis)


class NoisePixels:
    """The pixels one frame's noise statistics use (:func:`noise_statistics`), fixed by its noise-free
    simulation ``S`` (luminance, grey levels), its model pixels ``hit`` and the pixels left out
    (``exclude``: the recording's particles, see :func:`particle_exclusion`). Built once per frame, it measures
    any number of images of that frame (:meth:`statistics`): the noise fit measures dozens of simulations of
    each frame against the same pixels."""

    def __init__(self, S: np.ndarray, hit: np.ndarray, exclude: Optional[np.ndarray] = None):
        self.S, self.hit, self.exclude = S, hit, exclude
        # open water well away from the model (a pose error moves real edges several pixels off the render)
        self.open_water = ~dilate(hit, 24)
        self.water = self.open_water if exclude is None else self.open_water & ~exclude
        self.n_water = int(self.water.sum())
        self.enough = self.n_water >= 2000
        w = self.water
        self.pairs1 = w[:, 1:] & w[:, :-1]
        self.pairs3 = w[:, 3:] & w[:, :-3]
        self.rows_w = self.open_water.all(axis=1)
        self.cols_w = self.open_water.all(axis=0)
        gy, gx = np.gradient(S)
        self.flat_sim = erode(hit, 3) & (np.hypot(gx, gy) < 0.5)       # flat in the simulation
        # the box around those pixels that :meth:`statistics` smooths and differentiates: FLAT_REACH pixels on
        # every side, so that every pixel of flat_sim gets what the whole frame would give it
        ys, xs = np.nonzero(self.flat_sim)
        r = self.FLAT_REACH
        self.flat_box = None if not ys.size else (slice(max(int(ys.min()) - r, 0), int(ys.max()) + r + 1),
                                                  slice(max(int(xs.min()) - r, 0), int(xs.max()) + r + 1))

    #: Pixels a flat object pixel's test reaches: the Gaussian blur's half width (8 px at sigma 2: OpenCV's
    #: kernel of 17), the gradient's 1 and the erosion's 2, with room.
    FLAT_REACH = 16

    def statistics(self, Y: np.ndarray, intensities: bool = True) -> Optional[dict]:
        """:func:`noise_statistics` of luminance ``Y`` (grey levels) of this frame; ``intensities=False``
        leaves out the median intensities of water and object (``i_water``, ``i_object``: None)."""
        import cv2

        if not self.enough:
            return None
        water, open_water, exclude = self.water, self.open_water, self.exclude
        hp = _hp(Y, 2.0)
        d1 = (Y[:, 1:] - Y[:, :-1])[self.pairs1]
        d3 = (Y[:, 3:] - Y[:, :-3])[self.pairs3]
        s1, s3 = trimmed_sigma(d1), trimmed_sigma(d3)
        out = {"sigma_water": s3, "lag_ratio": s1 / s3 if s3 > 0 else 1.0, "col_ratio": 1.0, "row_ratio": 1.0,
               "sigma_object": None, "i_object": None,
               "i_water": float(np.median(Y[water])) if intensities else None, "hp": hp, "water": water}
        # fixed pattern: column (row) statistics of the high-passed water against what white noise gives for n
        # values (n: the pixels left in the line after the exclusion). The statistic is the median, robust to
        # the particles the exclusion missed; but in water darker than about a grey level of noise the rounding
        # to grey levels makes medians step (a line's median jumps a grey level as the share of pixels on
        # either side of it crosses one half: the quantization is no additive noise below about one level of
        # noise, Widrow), and there each line's mean winsorized at 1.5 sigma (at least a grey level) is taken
        # instead (ROUNDING_NOISE_DN), linear in what it measures. Each is scaled to its white-noise variance
        # (pi/2 sigma^2 / n for the median, _winsor_var sigma^2 / n for the winsorized mean).
        hw = hp[water]
        sig = trimmed_sigma(hw[1:] - hw[:-1]) if self.n_water > 100 else 0.0
        sig2 = sig * sig
        lo, hi = ROUNDING_NOISE_DN
        w_median = min(max((sig - lo) / (hi - lo), 0.0), 1.0)  # blended between: continuous in the noise

        def line_var_ratio(block, keep, axis):
            if keep is None:
                keep = np.ones(block.shape, bool)
            n = keep.sum(axis=axis)
            ok = n >= 0.5 * block.shape[axis]
            if ok.sum() < 20:
                return 1.0
            n = n[ok]
            block, keep = (block[:, ok], keep[:, ok]) if axis == 0 else (block[ok], keep[ok])  # too few left: skipped
            ratio = 0.0
            if w_median > 0:
                med = _median(block, axis) if keep.all() else _masked_median(block, keep, axis, n)
                ratio += w_median * np.var(med) / np.mean(np.pi / 2 * sig2 / n)
            if w_median < 1:
                c = max(WINSOR_Z * sig, 1.0)          # a pixel a grey level off its line passes unclipped
                mean = np.where(keep, np.clip(block, -c, c), 0.0).sum(axis=axis) / n
                ratio += (1 - w_median) * np.var(mean) / np.mean(_winsor_var(c / sig) * sig2 / n)
            return float(ratio)

        rows_w, cols_w = self.rows_w, self.cols_w
        if rows_w.sum() >= 20 and sig2 > 0:
            out["col_ratio"] = line_var_ratio(hp[rows_w], None if exclude is None else ~exclude[rows_w], 0)
        if cols_w.sum() >= 20 and sig2 > 0:
            out["row_ratio"] = line_var_ratio(hp[:, cols_w], None if exclude is None else ~exclude[:, cols_w], 1)
        if self.flat_box is None:
            return out
        # flat in the simulation and in the recording (a pose error puts real edges where the render is flat),
        # in the box around the simulation's flat pixels (the rest of the frame has none)
        box = self.flat_box
        Yb = Y[box]
        ry, rx = np.gradient(cv2.GaussianBlur(Yb, (0, 0), 2.0))
        flat = self.flat_sim[box] & (np.hypot(rx, ry) < 1.5)
        flat &= erode(flat, 2)
        if exclude is not None:
            flat &= ~exclude[box]
        if flat.sum() > 300:
            dd = (Yb[:, 3:] - Yb[:, :-3])
            ok = flat[:, 3:] & flat[:, :-3]
            out["sigma_object"] = trimmed_sigma(dd[ok])
            out["i_object"] = float(np.median(self.S[box][flat])) if intensities else None
        return out


def noise_statistics(Y: np.ndarray, S: np.ndarray, hit: np.ndarray,
                     exclude: Optional[np.ndarray] = None) -> Optional[dict]:
    """Noise statistics of one full-resolution frame (luminance ``Y``, grey levels) against its noise-free
    simulation ``S`` (luminance) with model pixels ``hit``: water noise sigma (lag-3 differences), lag-1 over
    lag-3 sigma (1 for white noise), column and row fixed-pattern variance ratios, the noise sigma on flat
    object parts and the intensities of both. ``exclude``: pixels left out (particles of the recording, see
    :func:`particle_exclusion`; give a simulation of the same frame the same mask). None when the frame has
    too little open water. Measuring many images of one frame: :class:`NoisePixels`."""
    return NoisePixels(S, hit, exclude).statistics(Y)


def sig_sensor_noise(ctx: SignatureContext) -> Signature:
    """Noise structure beyond constant white Gaussian noise (what the base model adds), at full resolution
    (:func:`noise_statistics` per frame).

    - intensity dependence: noise std on flat object parts (bright) against flat water, as a ratio of
      variances corrected for the intensities (Poisson-Gaussian ``var = s_r^2 + alpha I``; [6]);
    - spatial correlation: robust noise std from lag-1 against lag-3 pixel differences in the water
      (equal for white noise; demosaicing and compression correlate neighbours);
    - fixed pattern: column/row means of the high-passed water residual against what white noise gives,
      and correlation of that residual between frames.
    Thresholds (the tests give exactly white, constant noise 1.0 / 0 / 0 on frames with white noise): shot
    gain alpha > 0.05 grey levels per grey level, correlation ratio < 0.95, fixed-pattern variance > 2x
    white, inter-frame correlation > 0.05. Passing them only makes the effect a candidate.
    """
    lag13, colr, rowr, alphas, sig_w = [], [], [], [], []
    hps = []
    for k, rf in enumerate(ctx.rframes):
        fr = rf.frame
        Y = luminance(fr.image.astype(np.float32))
        hit = np.isfinite(fr.render.range)
        S = luminance(ctx.full_sim(k))
        st = noise_statistics(Y, S, hit, particle_exclusion(Y, S, hit))
        if st is None:
            continue
        lag13.append(st["lag_ratio"])
        sig_w.append(st["sigma_water"])
        colr.append(st["col_ratio"])
        rowr.append(st["row_ratio"])
        hps.append((st["hp"], st["water"]))
        if st["sigma_object"] is not None and st["i_object"] - st["i_water"] > 40:
            alphas.append(float((st["sigma_object"] ** 2 - st["sigma_water"] ** 2) / (st["i_object"] - st["i_water"])))
    if not sig_w:
        return Signature("sensor_noise", 0.0, judged=False, reason="too little open water to measure noise")
    inter = []
    for (h1, w1), (h2, w2) in zip(hps[:-1], hps[1:]):
        m = w1 & w2
        if m.sum() > 2000:
            inter.append(float(np.corrcoef(h1[m], h2[m])[0, 1]))
    corr = float(np.median(lag13)) if lag13 else 1.0
    fpn = float(max(np.median(colr) if colr else 1.0, np.median(rowr) if rowr else 1.0))
    alpha = float(np.median(alphas)) if alphas else None
    inter_c = float(np.median(inter)) if inter else 0.0
    parts = {"correlation": max(0.0, (1.0 - corr)) / 0.05, "fixed_pattern": max(0.0, fpn - 1.0) / 1.0,
             "temporal_fixed_pattern": max(0.0, inter_c) / 0.05,
             "intensity_dependence": max(0.0, alpha or 0.0) / 0.05}
    score = max(parts.values())
    stats = {"lag1_over_lag3": corr, "column_row_variance_ratio": fpn, "shot_gain_dn": alpha,
             "interframe_correlation": inter_c, "water_sigma_dn": float(np.median(sig_w)), "parts": parts}
    return Signature("sensor_noise", float(score), stats, {"shot_gain_dn": alpha, "sigma_dn": float(np.median(sig_w)),
                                                            "lag_ratio": corr})


def speck_masks(R: np.ndarray, S: np.ndarray, hit: np.ndarray, k: float = 5.0):
    """Small positive and negative outliers of a frame against its (noise-free) simulation.

    ``R``, ``S``: luminance (H, W) in grey levels; ``hit``: pixels of the model. The residual minus its
    7x7 median is compared with a local robust scale (31x31 mean absolute residual); pixels beyond
    +-``k`` scales away from edges of the simulation and of the silhouette count. Returns (pos, neg, ok)
    boolean masks (``ok``: pixels that were tested)."""
    import cv2

    D = (R - S).astype(np.float32)
    hp = D - median_filter(D, 7)
    gy, gx = np.gradient(S)
    edge = dilate(np.hypot(gx, gy) > 4.0, 3)
    edge |= dilate(hit, 2) & ~erode(hit, 2)
    a = np.abs(hp)
    scale = _MAD * cv2.blur(np.minimum(a, 50.0), (31, 31)) / 0.8453 + 0.5   # mean |x| of N(0,1) = 0.798
    ok = ~edge
    return (hp > k * scale) & ok, (hp < -k * scale) & ok, ok


def own_specks(Y: np.ndarray) -> tuple:
    """:func:`speck_masks` of a frame's luminance against its own 7x7 median (what a speck smaller than the window
    leaves), no model: ``(pos, neg, ok)``."""
    return speck_masks(Y, median_filter(Y, 7), np.zeros(Y.shape, bool))


def speck_sizes(R: np.ndarray, S: np.ndarray, hit: np.ndarray, exclude: Optional[np.ndarray] = None) -> tuple:
    """(positive outlier blobs per megapixel of tested area, their mean area in pixels (nan without blobs), the
    median of ``R - S`` between them in grey levels, the tested area in megapixels): the statistics a particle
    model is fitted to (:func:`speck_masks`). The count alone leaves size, number and brightness free: a few bright
    particles, many faint ones whose brightest show, and large blurred ones give as many blobs; the faint ones also
    lay a haze between the blobs. ``exclude``: pixels not tested (the sensor's :func:`persistent_specks`)."""
    import cv2

    pos, _, ok = speck_masks(R, S, hit)
    if exclude is not None:
        ok = ok & ~exclude
        pos = pos & ok
    n, _, stats, _ = cv2.connectedComponentsWithStats(pos.astype(np.uint8), 8)
    area = float(stats[1:, cv2.CC_STAT_AREA].mean()) if n > 1 else float("nan")
    between = ok & ~dilate(pos, 1)
    haze = float(np.median((R - S)[between])) if between.any() else float("nan")
    mpx = max(int(ok.sum()), 1) / 1e6
    return (n - 1) / mpx, area, haze, mpx


#: A speck at the same pixel in at least this many frames is the sensor's, not a particle's (:func:`persistent_specks`).
PERSISTENT_FRAMES = 3


def persistent_specks(images, min_frames: int = PERSISTENT_FRAMES) -> Optional[np.ndarray]:
    """Pixels that are a small bright outlier in at least ``min_frames`` of a recording's frames (full resolution,
    each frame against its own 7x7 median: :func:`speck_masks`), or None where there are none or too few frames.

    A particle in the water drifts and the vehicle moves: its speck is at another pixel in every frame (of the
    particles of the literature generator's strong marine snow, 211 speck pixels in 8 frames, none twice). A hot
    pixel (the dark-signal non-uniformity's tail, EMVA 1288) is at the same pixel in every frame that does not
    drown it in light or noise: 12 of the 15 speck pixels of its strong sensor noise were specks in 3 frames or more
    (8 frames). Counted as particles, they made the diagnosis name marine snow beside that noise."""
    images = list(images)
    if len(images) < min_frames:
        return None
    count = None
    for img in images:
        pos = own_specks(luminance(np.asarray(img, np.float32)))[0]
        count = pos.astype(np.uint8) if count is None else count + pos
    fixed = count >= min_frames
    return fixed if fixed.any() else None


def scene_specks(points, poses, camera, ranges, radius_px: float = 3.0, span=(0.5, 2.0), alpha: float = 1e-3) -> list:
    """Which specks of a recording are a still point of the scene seen again, not a particle: per frame a boolean
    array over its specks.

    ``points``: per frame, the specks' (M, 2) pixel coordinates (u, v) at ``camera``'s resolution; ``poses``: the
    frames' ``T_cam_panel``; ``ranges``: a range (m) per frame, the scene's (the panel's median). A point of the
    scene that the model lacks (a stand post, a stone on the seafloor near the panel) lies on its speck's ray at
    some depth between ``span`` times the frame's range; seen from another frame's pose, that part of the ray is a
    short curve (the epipolar segment). A particle drifts and is at another place in every frame: its curve meets
    another frame's specks only by chance, at the rate of that frame's specks per pixel over the curve's area
    (within ``radius_px``). A speck whose curves meet the other frames' specks in at least two frames, and more
    often than chance makes likely (Poisson, the expected meetings summed over the frames: ``alpha``), is the
    scene's. On the physically based seafloor dive (seed 407, 320x240) the lit feet of the panel's posts, which the
    model lacks, made 10 specks on the 4 held-out frames, pairs of them 3-7 px apart and a few pixels lower in every
    nearer frame: taken for particles, they made the diagnosis name marine snow there."""
    from scipy.spatial import cKDTree
    from scipy.stats import poisson

    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    h, w = camera.height, camera.width
    n = len(points)
    out = [np.zeros(len(p), bool) for p in points]
    trees = [cKDTree(np.asarray(p, float)) if len(p) else None for p in points]
    for k in range(n):
        pk = np.asarray(points[k], float)
        if not len(pk) or not np.isfinite(ranges[k]):
            continue
        z = np.geomspace(span[0] * ranges[k], span[1] * ranges[k], 48)
        rays = np.stack([(pk[:, 0] - cx) / fx, (pk[:, 1] - cy) / fy, np.ones(len(pk))], -1)       # (M, 3)
        Tk_inv = np.linalg.inv(np.asarray(poses[k], float))
        Xp = (rays[:, None, :] * z[None, :, None]) @ Tk_inv[:3, :3].T + Tk_inv[:3, 3]                 # (M, S, 3)
        met, expected = np.zeros(len(pk), int), np.zeros(len(pk))
        for j in range(n):
            if j == k or trees[j] is None:
                continue
            Tj = np.asarray(poses[j], float)
            Xj = Xp @ Tj[:3, :3].T + Tj[:3, 3]
            front = Xj[..., 2] > 0.05
            zj = np.where(front, Xj[..., 2], 1.0)
            uv = np.stack([fx * Xj[..., 0] / zj + cx, fy * Xj[..., 1] / zj + cy], -1)
            inside = front & (uv[..., 0] > -radius_px) & (uv[..., 0] < w + radius_px) & \
                (uv[..., 1] > -radius_px) & (uv[..., 1] < h + radius_px)
            seg = np.where(inside[:, 1:] & inside[:, :-1], np.linalg.norm(np.diff(uv, axis=1), axis=-1), 0.0)
            area = np.where(inside.any(axis=1), 2 * radius_px * seg.sum(axis=1) + np.pi * radius_px ** 2, 0.0)
            expected += np.minimum(len(points[j]) * area / float(h * w), 1.0)
            d, _ = trees[j].query(uv.reshape(-1, 2), distance_upper_bound=radius_px)
            met += (np.isfinite(d).reshape(uv.shape[:2]) & inside).any(axis=1)
        out[k] = (met >= 2) & (poisson.sf(met - 1, np.maximum(expected, 1e-12)) < alpha)
    return out


def sig_marine_snow(ctx: SignatureContext) -> Signature:
    """Sparse, small, positive outliers that do not persist between frames (full resolution).

    The residual real - sim (luminance) minus its 7x7 median is compared with a local robust noise
    scale; blobs above +5 scale and below -5 scale are counted away from the simulation's edges
    (:func:`speck_masks`). Particles lit by the lamps give many more positive than negative blobs, at new
    places in every frame. Threshold: 40 excess positive blobs per megapixel, at least 3x the negative ones.
    """
    import cv2

    pos_d, neg_d, overlap, sizes = [], [], [], []
    prev = None
    for k, rf in enumerate(ctx.rframes):
        fr = rf.frame
        R = luminance(fr.image.astype(np.float32))
        S = luminance(ctx.full_sim(k))
        pos, neg, ok = speck_masks(R, S, np.isfinite(fr.render.range))
        npos, lab_p, st_p, _ = cv2.connectedComponentsWithStats(pos.astype(np.uint8), 8)
        nneg = cv2.connectedComponentsWithStats(neg.astype(np.uint8), 8)[0]
        mp = ok.sum() / 1e6
        pos_d.append((npos - 1) / mp)
        neg_d.append((nneg - 1) / mp)
        if npos > 1:
            sizes.append(float(np.median(st_p[1:, cv2.CC_STAT_AREA])))
        if prev is not None and pos.sum() > 0 and prev.sum() > 0:
            overlap.append(float((pos & dilate(prev, 1)).sum() / pos.sum()))
        prev = pos
    if not pos_d:
        return Signature("marine_snow", 0.0, judged=False, reason="no frames")
    pd, nd = float(np.median(pos_d)), float(np.median(neg_d))
    ov = float(np.median(overlap)) if overlap else 0.0
    excess = max(0.0, pd - nd)
    score = excess / 40.0 * min(1.0, (pd + 1) / (3 * (nd + 1))) * max(0.0, 1.0 - ov / 0.5)
    stats = {"positive_per_mpx": pd, "negative_per_mpx": nd, "persistence": ov,
             "blob_area_px": float(np.median(sizes)) if sizes else None, "per_frame_positive": pos_d}
    return Signature("marine_snow", float(score), stats, {"density_per_mpx": excess,
                                                           "blob_area_px": stats["blob_area_px"]})


def median_filter(img, k):
    import cv2

    lo, hi = float(img.min()), float(img.max())
    if hi - lo < 1e-6:
        return img.copy()
    # cv2.medianBlur on float32 supports ksize 3 and 5 only: quantize to 16 bits for larger kernels
    q = np.round((img - lo) / (hi - lo) * 65535).astype(np.uint16)
    m = cv2.medianBlur(q, 5) if k > 5 else cv2.medianBlur(q, k)
    if k > 5:
        m = cv2.medianBlur(m, 5)
    return m.astype(np.float32) / 65535 * (hi - lo) + lo


def _object_window(hit: np.ndarray, pad: int = 12):
    ys, xs = np.nonzero(hit)
    if ys.size == 0:
        return None
    h, w = hit.shape
    return (max(0, ys.min() - pad), min(h, ys.max() + pad + 1), max(0, xs.min() - pad), min(w, xs.max() + pad + 1))


def _align(R: np.ndarray, S: np.ndarray):
    """Alignment of S to R by ECC [5]: affine (shift, rotation, scale, shear: a small pose error seen on a
    roughly planar object), returns (dx, dy, angle_rad, ok, 2x3 warp)."""
    import cv2

    warp = np.eye(2, 3, dtype=np.float32)
    try:
        cc, warp = cv2.findTransformECC(R.astype(np.float32), S.astype(np.float32), warp, cv2.MOTION_AFFINE,
                                        (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5), None, 3)
    except cv2.error:
        return 0.0, 0.0, 0.0, False, np.eye(2, 3, dtype=np.float32)
    h, w = R.shape
    # displacement of the window centre and the rotation part of the affine map
    c = np.array([(w - 1) / 2, (h - 1) / 2, 1.0])
    d = warp @ c - c[:2]
    ang = 0.5 * (math.atan2(warp[1, 0], warp[0, 0]) - math.atan2(warp[0, 1], warp[1, 1]))
    return float(d[0]), float(d[1]), float(ang), True, warp


def _fit_energy(R, S, mask):
    """Residual energy of R against alpha + beta S on mask (photometric affine fit)."""
    s, r = S[mask], R[mask]
    A = np.stack([np.ones_like(s), s], 1)
    coef, *_ = np.linalg.lstsq(A, r, rcond=None)
    e = r - A @ coef
    return float(np.mean(e * e))


def sig_blur_and_shift(ctx: SignatureContext) -> tuple:
    """Forward-scatter blur and pose error from the object's edges at full resolution.

    Per frame, in a window around the rendered object: (1) the simulation is aligned to the recording by
    ECC (shift + rotation, [5]); the alignment's shift and the energy it removes measure pose error.
    (2) On the aligned simulation, the Gaussian width that best matches the recording (photometric
    affine fit per width; widths 0-6 px, parabolic refinement) and the energy it removes measure blur.
    (3) Power spectra of recording and simulation in the window (noise floor removed) give the
    high-frequency ratio. Thresholds: pose error 0.15 px median shift or 0.05 deg rotation removing
    >= 10 % of the edge energy (an exactly aligned simulation gives < 0.01 px); blur 0.6 px median width
    removing >= 8 % of the edge energy.
    """
    import cv2

    shifts, angles, e_shift, sig_px, e_blur, ranges, hf = [], [], [], [], [], [], []
    motion = []                                  # (range, dx, dy, angle, fx, fy) per frame, full resolution
    spectra = []
    widths = np.array([0.0, 0.4, 0.6, 0.8, 1.0, 1.3, 1.7, 2.2, 2.8, 3.6, 4.5, 6.0])
    for k, rf in enumerate(ctx.rframes):
        fr = rf.frame
        hit = np.isfinite(fr.render.range)
        win = _object_window(hit, 14)
        if win is None:
            continue
        y0, y1, x0, x1 = win
        if (y1 - y0) < 40 or (x1 - x0) < 50:
            continue
        R = luminance(fr.image.astype(np.float32))[y0:y1, x0:x1]
        S = luminance(ctx.full_sim(k))[y0:y1, x0:x1]
        dx, dy, ang, ok, M = _align(R, S)
        Sa = cv2.warpAffine(S, M, (S.shape[1], S.shape[0]), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                            borderMode=cv2.BORDER_REPLICATE)
        gy, gx = np.gradient(S)
        edges = dilate(np.hypot(gx, gy) > 3.0, 3)
        inner = np.zeros_like(edges)
        inner[8:-8, 8:-8] = True
        m = edges & inner
        if m.sum() < 200:
            continue
        E0 = _fit_energy(R, S, m)
        E1 = _fit_energy(R, Sa, m)
        Es = []
        for wd in widths:
            Sb = cv2.GaussianBlur(Sa, (0, 0), wd) if wd > 0 else Sa
            Es.append(_fit_energy(R, Sb, m))
        Es = np.array(Es)
        j = int(np.argmin(Es))
        wbest = widths[j]
        if 0 < j < len(widths) - 1:
            x3, y3 = widths[j - 1:j + 2], Es[j - 1:j + 2]
            den = (x3[0] - x3[1]) * (x3[0] - x3[2]) * (x3[1] - x3[2])
            a = (x3[2] * (y3[1] - y3[0]) + x3[1] * (y3[0] - y3[2]) + x3[0] * (y3[2] - y3[1])) / den
            b = (x3[2] ** 2 * (y3[0] - y3[1]) + x3[1] ** 2 * (y3[2] - y3[0]) + x3[0] ** 2 * (y3[1] - y3[2])) / den
            if a > 0:
                wbest = float(np.clip(-b / (2 * a), x3[0], x3[2]))
        noise2 = float(np.mean(np.square(ctx.noise[k]))) * rf.factor ** 2    # full-resolution noise variance
        cam = fr.camera
        motion.append((float(fr.range_median), float(dx), float(dy), float(ang), float(cam.fx), float(cam.fy),
                       int(fr.index)))
        shifts.append(float(math.hypot(dx, dy)))
        angles.append(float(abs(ang)))
        e_shift.append(max(0.0, (E0 - E1) / max(E0 - noise2 * 0.5, 1e-6)))
        e_blur.append(max(0.0, (E1 - Es.min()) / max(E1 - noise2 * 0.5, 1e-6)))
        sig_px.append(float(wbest))
        ranges.append(fr.range_median)
        # power spectra (Hann window)
        hw = np.outer(np.hanning(R.shape[0]), np.hanning(R.shape[1])).astype(np.float32)
        PR = np.abs(np.fft.rfft2((R - R.mean()) * hw)) ** 2
        PS = np.abs(np.fft.rfft2((Sa - Sa.mean()) * hw)) ** 2
        fy = np.fft.fftfreq(R.shape[0])[:, None]
        fx = np.fft.rfftfreq(R.shape[1])[None, :]
        fr_ = np.hypot(fx, fy)
        PR = PR - noise2 * float(np.sum(hw ** 2))
        bins = np.linspace(0.02, 0.5, 13)
        ratio = []
        for lo, hi in zip(bins[:-1], bins[1:]):
            sel = (fr_ >= lo) & (fr_ < hi)
            ratio.append(float(np.sum(PR[sel]) / max(np.sum(PS[sel]), 1e-9)))
        spectra.append((fr.range_median, (0.5 * (bins[:-1] + bins[1:])).tolist(), ratio))
        hf.append(float(np.mean(ratio[6:])) / max(float(np.mean(ratio[:3])), 1e-6))
    if not shifts:
        none = Signature("forward_scatter", 0.0, judged=False, reason="object too small for edge analysis")
        return none, Signature("pose_error", 0.0, judged=False, reason="object too small for edge analysis")
    ranges = np.array(ranges)
    sh, an, es, eb, sp = map(np.array, (shifts, angles, e_shift, e_blur, sig_px))
    shift_m = float(np.median(sh))
    ang_m = float(np.degrees(np.median(an)))
    pose_score = max(shift_m / 0.15, ang_m / 0.05) * min(1.0, float(np.median(es)) / 0.10)
    blur_m = float(np.median(sp))
    trend = None
    if len(sp) >= 3 and np.ptp(ranges) > 0.5:
        trend = float(np.polyfit(ranges, sp, 1)[0])
    blur_score = blur_m / 0.6 * min(1.0, float(np.median(eb)) / 0.08)
    pose = Signature("pose_error", float(pose_score),
                     {"shift_px_median": shift_m, "rotation_deg_median": ang_m, "shift_px": sh.tolist(),
                      "energy_removed_by_alignment": es.tolist(), "ranges": ranges.tolist()},
                     {"shift_px": shift_m, "rotation_deg": ang_m, "motion": motion})
    blur = Signature("forward_scatter", float(blur_score),
                     {"blur_px_median": blur_m, "blur_px": sp.tolist(), "blur_px_per_m": trend,
                      "energy_removed_by_blur": eb.tolist(), "hf_ratio": hf, "ranges": ranges.tolist()},
                     {"blur_px": blur_m, "blur_px_per_m": trend},
                     {"spectra": spectra, "blur": (ranges.tolist(), sp.tolist())})
    return blur, pose



def run_signatures(ctx: SignatureContext) -> dict:
    """All tests: ``{effect: Signature}``."""
    out = {}
    for fn in (sig_vignetting, sig_artificial_light, sig_backscatter_coefficient, sig_camera_response,
               sig_unmodeled_geometry, sig_sensor_noise, sig_marine_snow):
        s = fn(ctx)
        out[s.effect] = s
    blur, pose = sig_blur_and_shift(ctx)
    out["forward_scatter"] = blur
    out["pose_error"] = pose
    return out
