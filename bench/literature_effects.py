"""Independent generator of test recordings with concealed physical effects, written from the literature.

Written WITHOUT reading the project's own effect code (``uw_sil/sim/effects``, ``optics.py``, ``model.py``,
``uw_sil/fit``, ``bench/foreign_effects.py``, ``bench/physical_effects.py``, ``bench/bench_concealed.py``, the READMEs
or docs). Only the public APIs of ``Renderer`` (clean albedo / shading, depth, range, part ids), ``CameraModel``,
``facing_pose``, ``Sample`` and ``write_trial`` are used, plus the physics notes in
``/work/shared/notes/underwater-effects.md``. Every formula below was written from the cited publications.

Usage::

    truth = synth_literature("/tmp/x/trial.mcap", {"artificial_light": "strong", "sensor_noise": "mild"}, seed=3)

The truth dict is returned, never written next to the bag.

The dive (every trial, the effect-free control included)
---------------------------------------------------------
An ROV approaches the panel from 3.5-4.5 m to 1.2-1.8 m (slightly uneven speed), with a slowly varying yaw (<= 12 deg),
pitch (<= 8 deg), roll (<= 3 deg) and lateral drift (<= 0.3 m) drawn from ``seed`` (two-sinusoid series); the camera
aims at a drifting point of the panel (``facing_pose``), so the panel stays in view. Camera:
``CameraModel.from_fov(width, width*3//4, fov)``, fov 55-85 deg. Frames 1 s apart.

Base water (Duntley / Jaffe 1990 single-coefficient form): ``I_c = J_c e^(-c_c r) + B_inf,c (1 - e^(-c_c r))``, water
pixels ``B_inf,c``; c (R 0.25-0.6, G 0.06-0.2, B 0.04-0.15 /m), B_inf (R 0.02-0.1, G 0.15-0.4, B 0.2-0.5), J the
clean render (linear 0..1, 1 -> 255 DN). Default camera: Poisson-Gaussian, ``var = k DN + s_r^2`` with
k 0.02-0.04 DN/DN, s_r ~1 DN, rounding to 8 bits.

Order of the pipeline: scene light -> water (direct, backscatter) -> forward scatter -> marine snow (in the water
volume) -> port refraction -> lens vignetting -> sensor (mosaic, PRNU, shot, DSNU, row, read, ADC) -> ISP (white
balance, demosaic, tone curve) -> JPEG.

Effects (registry name: form [source]; presets)
-----------------------------------------------
artificial_light
    Vehicle lamps as point sources (Jaffe 1990; McGlamery 1980): surface irradiance
    ``E = sum_l I_l(theta_l) col_l cos(phi) e^(-c d_l) / d_l^2``, Lambertian radiance ``rho E / pi``. Beam profile
    of a TIR/reflector LED spot: flat top with a raised-cosine edge between inner and outer half-angles given in air
    (data-sheet) and refracted into water by the lamp's flat window (Snell), plus a 2-6 % cos^2 spill. Warm-white
    LED colour (R 1, G .78-.88, B .50-.68 of G). Single-scattering veil ray-marched along each camera ray on a 1/8
    grid (80 quadratic steps to 8 m): ``L_bs = int b beta~(psi) E_l(x) e^(-c s) ds`` with the Fournier-Forand
    phase function (Fournier & Forand 1994; Fournier & Jonasz 1999; n = 1.10, Junge slope 3.5-3.65, b_b/b ~1.5 %),
    b = omega c (omega R .3-.5, G .6-.8, B .6-.85), plus the molecular scattering of seawater (Morel 1974:
    b_sw = 0.00288 (lambda/500)^-4.32, phase 0.06225 (1 + 0.835 cos^2 psi)), interpolated per pixel at its range
    from the coarse cumulative
    integral. Ambient light (and its B_inf veil) scaled by ``a``. Exposure fixed per dive so that a 0.7-albedo
    frontal surface on the axis at the geometric mean of the start and end distances gives the target green DN
    (fixed exposure: the panel goes from ~10-15 DN at the start to ~100+ DN at the end of the approach, 1/d^2 and
    e^(-2cd)). No lamp shadows (occlusion of beams by the panel's parts), no lamp flare.
    mild: 2 lamps (beside or above), a = 0.05-0.12, target 32 DN; strong: 4 lamps, a = 0, target 35 DN.
forward_scatter
    Wells (1973) small-angle MTF of the water path (as used by Hou et al. 2007):
    ``M(psi, r) = exp(-c r + b_s r [1 - exp(-2 pi theta0 psi)] / (2 pi theta0 psi))`` (psi in cycles/rad), applied
    to the direct signal (already carrying e^(-cr)) per range layer (6 hat-weighted layers, FFT, reflect padding).
    b_s = omega_s c. mild: omega_s 0.45, theta0 0.05 rad; strong: omega_s 0.8, theta0 0.03 rad.
backscatter_coefficient
    Akkaynak & Treibitz (2018) revised model: ``J e^(-beta_D r) + B_inf (1 - e^(-beta_B r))`` with beta_D = c and
    beta_B = q_c c, q_c drawn per channel: mild q in [1/1.35, 1/1.15] U [1.15, 1.35], strong [1/2, 1/1.6] U [1.6, 2].
camera_response
    White-balance gains then a tone curve on the 12-bit linear raw. mild: sRGB OETF (IEC 61966-2-1) with a 2-4 DN
    black pedestal, gains R 1.2-1.5, B 0.8-0.95; strong: ITU-R BT.709 OETF with a broadcast highlight knee (point
    0.75-0.85, slope 0.2-0.35) in limited video range 16-235, gains R 1.8-2.4, B 0.65-0.8.
vignetting
    Relative illumination ``cos^n(theta)`` (generalised cos^4 law; Kerr 2007, Asada et al. 1996; n lens dependent)
    times mechanical vignetting by the housing's port tube: fraction of the entrance pupil (radius a) inside the
    tube aperture (radius R) seen shifted by ``L tan(theta) - o`` (two-circle overlap, "cat's eye"), o a decentre.
    mild: n 2.0-3.0, onset at 0.9-0.95 of the corner field, centred; strong: n 3.5-4.5, onset at 0.55-0.7, decentred
    by 1.5-3 mm.
sensor_noise
    EMVA 1288 (release 3.1/4.0) linear camera model: PRNU (gain map), Poisson shot noise at system gain K, DSNU
    (offset map) with hot pixels, row noise (temporal, per row), column FPN, read noise, ADC. mild: K 0.12 DN/e-,
    PRNU 1 %, DSNU 0.6 DN, row 0.4, column 0.3, read 1.5 DN; strong: K 0.4 DN/e-, PRNU 2 %, DSNU 1.5 DN + 0.05 %
    hot pixels, row 1.2, column 0.8, read 3 DN, RGGB Bayer mosaic with bilinear demosaicing.
marine_snow
    A drifting particle population in the panel frame (current 2-8 cm/s plus a random walk), Junge power-law
    diameters ``N(D) ~ D^-xi`` (xi 3.2-3.8, 0.5-5 mm; McCave 1984, Jackson et al. 1997), Lambert-sphere particles
    (albedo 0.35-0.6, phase law ``(2/3 pi) rho E R^2 [sin a + (pi - a) cos a]``) lit by the lamps (beam, 1/d^2,
    attenuation) or by the ambient light, attenuated and veiled to the camera, defocused by a thin lens (blur
    ``A f |1/z - 1/z_f|``, A 5-10 mm, focus 1.5-2.5 m), occluding what is behind them. New draws for a twin.
    mild: 0.2 /L; strong: 1 /L (in a 5 x 4 x 10 m box around the panel and the path).
unmodeled_geometry
    A sediment seafloor 0.5-1.5 m below the panel, ray-plane intersection per pixel, occluded by the panel: height
    field of sand ripples (wavelength 8-20 cm, phase-distorted by 1/f noise) and half-buried stones, normals from
    the height gradient, lit like the rest of the scene and put under the same water. mild: 1.1-1.5 m below;
    strong: 0.5-0.8 m below, more stones.
pose_error
    Recorded pose = T_err T_true: constant bias (mild 2 cm / 0.2 deg, strong 6 cm / 0.6 deg) plus per-frame jitter
    (mild 3 mm / 0.05 deg, strong 8 mm / 0.15 deg); the jitter is part of the dive (not redrawn for a twin).
compression
    JPEG (cv2.imencode, 4:2:0) of the 8-bit frames, stored decoded as raw rgb8. mild q 75; strong q 30.
port_refraction
    Flat port (Treibitz, Schechner & Singh 2012; Agrawal et al. 2012): per-channel Snell refraction air -> glass ->
    water, window at d0 from the entrance pupil, thickness t; the non-single-viewpoint ray is traced to the scene depth
    (2 fixed-point iterations on the depth map) and the pinhole radiance resampled per channel (dispersion: seawater
    n 1.3375/1.3413/1.3464, glass). The recorded camera info stays the pinhole. mild: acrylic 8 mm at 8-12 mm,
    in-air focal calibrated to the pinhole at 35 % of the half-diagonal (2 m); strong: BK7 15 mm at 25-35 mm,
    paraxial focal (f_air = fx / n_water).

Randomness: each part draws from its own stream of ``seed`` (the control and every effect bag of one seed share the
dive and the water); what is new in every frame (particles, temporal noise) comes from streams that a twin replaces.
"""
from __future__ import annotations

import math
import os

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from uw_sil.bags.records import Sample  # noqa: E402
from uw_sil.bags.writer import write_trial  # noqa: E402
from uw_sil.sim.camera import CameraModel  # noqa: E402
from uw_sil.sim.scene import facing_pose  # noqa: E402

__all__ = ["LITERATURE_EFFECTS", "synth_literature"]

LITERATURE_EFFECTS = ("artificial_light", "forward_scatter", "backscatter_coefficient", "camera_response",
                      "vignetting", "sensor_noise", "marine_snow", "unmodeled_geometry", "pose_error", "compression",
                      "port_refraction")
_LEVELS = ("mild", "strong")

# random streams (one per part, so adding an effect changes no other draw)
_S = dict(dive=1, water=2, lamps=3, fscat=4, betab=5, resp=6, vign=7, sensor=8, snow=9, floor=10, pose=11, port=13,
          cam=14)
_TEMPORAL, _TWIN = 100, 200

_PANEL_HALF = (0.5, 0.35)      # plate half-size (m), panel frame
_DT = 1.0                      # s between frames


def _rng(seed, stream, *more):
    return np.random.default_rng([int(seed), int(stream), *[int(m) for m in more]])


# ------------------------------------------------------------------------------------------------ dive and water


def _slow(r, n, amp):
    """A slowly varying series in [-amp, amp]: two sinusoids of low frequency with random phases."""
    t = np.linspace(0.0, 1.0, n) if n > 1 else np.zeros(1)
    f1, f2 = r.uniform(0.25, 0.7), r.uniform(0.7, 1.4)
    p1, p2 = r.uniform(0, 2 * np.pi, 2)
    w = r.uniform(0.5, 0.8)
    return amp * (w * np.sin(2 * np.pi * f1 * t + p1) + (1 - w) * np.sin(2 * np.pi * f2 * t + p2))


def _draw_dive(seed, n):
    r = _rng(seed, _S["dive"])
    fov = r.uniform(55.0, 85.0)
    d0, d1 = r.uniform(3.5, 4.5), r.uniform(1.2, 1.8)
    t = np.linspace(0.0, 1.0, n) if n > 1 else np.zeros(1)
    prog = t + r.uniform(-0.1, 0.1) * np.sin(np.pi * t)        # uneven speed, monotone
    dist = d0 + (d1 - d0) * prog
    yaw = _slow(r, n, math.radians(r.uniform(5.0, 12.0)))
    pitch = _slow(r, n, math.radians(r.uniform(3.0, 8.0)))
    roll = _slow(r, n, math.radians(r.uniform(1.0, 3.0)))
    x = _slow(r, n, r.uniform(0.08, 0.24))
    y = _slow(r, n, r.uniform(0.04, 0.16))
    poses = [facing_pose(float(dist[i]), float(x[i]), float(y[i]), float(yaw[i]), float(pitch[i]), float(roll[i]))
             for i in range(n)]
    return dict(fov=fov, dist=dist, yaw=yaw, pitch=pitch, roll=roll, x=x, y=y, poses=poses)


def _draw_water(seed):
    r = _rng(seed, _S["water"])
    c = np.array([r.uniform(0.25, 0.6), r.uniform(0.06, 0.2), r.uniform(0.04, 0.15)])
    binf = np.array([r.uniform(0.02, 0.1), r.uniform(0.15, 0.4), r.uniform(0.2, 0.5)])
    omega = np.array([r.uniform(0.3, 0.5), r.uniform(0.6, 0.8), r.uniform(0.6, 0.85)])   # single-scatter albedo
    ff_n, ff_mu = 1.10, r.uniform(3.5, 3.65)
    return dict(c=c, binf=binf, b=omega * c, ff_n=ff_n, ff_mu=ff_mu)


# ------------------------------------------------------------------------------------------------ phase function


def _ff(psi, n, mu):
    """Fournier-Forand phase function (Fournier & Jonasz 1999 form), sr^-1, psi in rad (0, pi]."""
    nu = (3.0 - mu) / 2.0
    k = 4.0 / (3.0 * (n - 1.0) ** 2)
    s2 = np.sin(psi / 2.0) ** 2
    d = k * s2
    d = np.where(np.abs(d - 1.0) < 1e-7, 1.0 + 1e-7, d)
    t1 = (nu * (1 - d) - (1 - d ** nu) + (d * (1 - d ** nu) - nu * (1 - d)) / s2) / (4 * np.pi * (1 - d) ** 2 * d ** nu)
    t2 = (1 - k ** nu) / (16 * np.pi * (k - 1) * k ** nu) * (3 * np.cos(psi) ** 2 - 1)
    return t1 + t2


class _Phase:
    """Tabulated FF phase function over cos(psi) for the backward and side angles the veil needs (psi >= 2 deg)."""

    def __init__(self, n, mu):
        psi = np.concatenate([np.logspace(-7, -1, 3000), np.linspace(0.1, np.pi, 6000)[1:]])
        p = _ff(psi, n, mu)
        w = 2 * np.pi * p * np.sin(psi)
        total = np.trapezoid(w, psi)
        p = p / total
        back = psi >= np.pi / 2
        self.bb_ratio = float(np.trapezoid(w[back], psi[back]) / total)
        self.mu_grid = np.linspace(-1.0, math.cos(math.radians(2.0)), 2048)
        self.table = np.interp(np.arccos(self.mu_grid), psi, p).astype(np.float32)

    def __call__(self, cos_psi):
        return np.interp(cos_psi, self.mu_grid, self.table).astype(np.float32)


# ------------------------------------------------------------------------------------------------ lamps


def _draw_lamps(seed, level, dist_ref):
    r = _rng(seed, _S["lamps"])
    n = 2 if level == "mild" else 4
    lamps = []
    layout = "beside" if (n == 2 and r.uniform() < 0.5) else ("above" if n == 2 else "beside+above")
    spots = []
    if layout in ("beside", "beside+above"):
        s = r.uniform(0.25, 0.7)
        yv = r.uniform(-0.15, 0.05)
        spots += [(-s * r.uniform(0.9, 1.1), yv), (s * r.uniform(0.9, 1.1), yv)]
    if layout in ("above", "beside+above"):
        yv = -r.uniform(0.2, 0.5)
        s = r.uniform(0.1, 0.4)
        spots += [(-s, yv), (s, yv)]
    col_g, col_b = r.uniform(0.78, 0.88), r.uniform(0.50, 0.68)
    aim_d = r.uniform(1.5, 3.0)
    aim = np.array([r.uniform(-0.1, 0.1), r.uniform(-0.1, 0.1), aim_d])
    inner_air, width_air = r.uniform(20.0, 35.0), r.uniform(10.0, 20.0)
    n_win = 1.34
    for (x, y) in spots:
        p = np.array([x, y, r.uniform(-0.15, 0.15)])
        a = aim + np.array([r.uniform(-0.15, 0.15), r.uniform(-0.15, 0.15), 0.0])
        axis = (a - p) / np.linalg.norm(a - p)
        ti = math.asin(math.sin(math.radians(inner_air)) / n_win)
        to = math.asin(math.sin(math.radians(inner_air + width_air)) / n_win)
        col = np.array([1.0, col_g, col_b]) / col_g * r.uniform(0.9, 1.1)
        lamps.append(dict(pos=p, axis=axis, inner=ti, outer=to, spill=r.uniform(0.02, 0.06), col=col))
    ambient = r.uniform(0.05, 0.12) if level == "mild" else 0.0
    target = 32.0 if level == "mild" else 35.0
    return dict(lamps=lamps, layout=layout, ambient=ambient, target_dn=target, aim=aim, dist_ref=float(dist_ref),
                inner_air_deg=inner_air, outer_air_deg=inner_air + width_air)


def _beam(cos_t, lamp):
    t = np.arccos(np.clip(cos_t, -1.0, 1.0))
    ti, to = lamp["inner"], lamp["outer"]
    edge = 0.5 * (1.0 + np.cos(np.pi * np.clip((t - ti) / (to - ti), 0.0, 1.0)))
    spill = np.maximum(cos_t, 0.0) ** 2
    return ((1.0 - lamp["spill"]) * edge + lamp["spill"] * spill).astype(np.float32)


def _lamp_field(X, lamp, c):
    """For points X (..., 3) in the camera frame: irradiance on a surface normal to the lamp direction (..., 3), the
    unit vector from X to the lamp and the distance."""
    v = lamp["pos"].astype(np.float32) - X
    d = np.sqrt(np.sum(v * v, axis=-1))
    d = np.maximum(d, 1e-3)
    u = v / d[..., None]
    cos_t = -np.sum(u * lamp["axis"].astype(np.float32), axis=-1)
    prof = _beam(cos_t, lamp)
    e = (prof / (d * d))[..., None] * lamp["col"].astype(np.float32) * np.exp(-c.astype(np.float32) * d[..., None])
    return e, u, d


def _calibrate_lamps(L, water):
    """Exposure K: a 0.7-albedo surface facing the camera on the axis at ``dist_ref`` gives the target DN (green)."""
    D = L["dist_ref"]
    X = np.array([[0.0, 0.0, D]], np.float32)
    n = np.array([0.0, 0.0, -1.0], np.float32)
    E = np.zeros(3)
    for lamp in L["lamps"]:
        e, u, _ = _lamp_field(X, lamp, water["c"])
        E += e[0] * max(0.0, float(u[0] @ n))
    sig = 0.7 / np.pi * E[1] * math.exp(-water["c"][1] * D)
    return (L["target_dn"] / 255.0) / sig


def _normals(P, ids):
    """Surface normals from the camera-frame points of a depth map: one-sided differences that stay on one part and
    take the side with the smaller depth step; oriented towards the camera."""
    H, W, _ = P.shape
    hit = ids > 0

    def pick(axis):
        f = np.zeros_like(P)
        b = np.zeros_like(P)
        okf = np.zeros((H, W), bool)
        okb = np.zeros((H, W), bool)
        if axis == 1:
            f[:, :-1] = P[:, 1:] - P[:, :-1]
            okf[:, :-1] = hit[:, :-1] & (ids[:, 1:] == ids[:, :-1])
            b[:, 1:] = P[:, 1:] - P[:, :-1]
            okb[:, 1:] = hit[:, 1:] & (ids[:, 1:] == ids[:, :-1])
        else:
            f[:-1] = P[1:] - P[:-1]
            okf[:-1] = hit[:-1] & (ids[1:] == ids[:-1])
            b[1:] = P[1:] - P[:-1]
            okb[1:] = hit[1:] & (ids[1:] == ids[:-1])
        f = np.where(okf[..., None], f, 0)
        b = np.where(okb[..., None], b, 0)
        use_f = okf & (~okb | (np.abs(f[..., 2]) <= np.abs(b[..., 2])))
        g = np.where(use_f[..., None], f, b)
        return g, okf | okb

    gx, ox = pick(1)
    gy, oy = pick(0)
    N = np.cross(gy, gx)
    nn = np.linalg.norm(N, axis=-1)
    ok = ox & oy & (nn > 0)
    Pn = P / np.maximum(np.linalg.norm(P, axis=-1, keepdims=True), 1e-9)
    N = np.where(ok[..., None], N / np.maximum(nn, 1e-12)[..., None], -Pn)
    flip = np.sum(N * P, axis=-1) > 0
    N[flip] *= -1
    return N.astype(np.float32)


def _surface_irradiance(P, N, L, water):
    E = np.zeros(P.shape, np.float32)
    for lamp in L["lamps"]:
        e, u, _ = _lamp_field(P, lamp, water["c"])
        cosphi = np.maximum(np.sum(u * N, axis=-1), 0.0)
        E += e * cosphi[..., None]
    return E


#: molecular scattering coefficient of seawater at the channels' effective wavelengths 600/530/465 nm,
#: b_sw(500 nm) = 0.00288 /m and a lambda^-4.32 law (Morel 1974)
_B_SEAWATER = 0.00288 * (np.array([600.0, 530.0, 465.0]) / 500.0) ** -4.32


class _Veil:
    """Single-scattering veil of the lamps: cumulative along each ray of a coarse grid, sampled at any range."""

    def __init__(self, cam, L, water, phase, K, step=8, n_samples=80, s_max=8.0):
        H, W = cam.height, cam.width
        h, w = max(2, H // step), max(2, W // step)
        uc = (np.arange(w) + 0.5) * W / w - 0.5
        vc = (np.arange(h) + 0.5) * H / h - 0.5
        dx = ((uc - cam.cx) / cam.fx)[None, :] * np.ones((h, 1))
        dy = ((vc - cam.cy) / cam.fy)[:, None] * np.ones((1, w))
        d = np.stack([dx, dy, np.ones_like(dx)], -1)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        d = d.astype(np.float32)
        k = np.arange(n_samples + 1) / n_samples
        edges = s_max * k ** 2
        mids = 0.5 * (edges[1:] + edges[:-1])
        ds = np.diff(edges)
        c = water["c"].astype(np.float32)
        b = water["b"].astype(np.float32)
        bw = _B_SEAWATER.astype(np.float32)
        X = d[:, :, None, :] * mids.astype(np.float32)[None, None, :, None]      # (h, w, S, 3)
        integ = np.zeros(X.shape, np.float32)
        for lamp in L["lamps"]:
            e, u, _ = _lamp_field(X, lamp, water["c"])
            # light travels along -u (lamp -> X) and leaves towards the camera along -d
            cos_psi = np.sum(u * d[:, :, None, :], axis=-1)
            # particles (Fournier-Forand) plus the molecular scattering of seawater (Morel 1974, Rayleigh-like)
            pw = np.float32(0.06225) * (1 + np.float32(0.835) * cos_psi * cos_psi)
            integ += e * (b * phase(cos_psi)[..., None] + bw * pw[..., None])
        integ *= np.exp(-c * mids.astype(np.float32)[:, None])[None, None] * ds.astype(np.float32)[:, None]
        cum = np.concatenate([np.zeros((h, w, 1, 3), np.float32), np.cumsum(integ, axis=2)], axis=2) * np.float32(K)
        self.edges, self.cum, self.shape, self.small = edges, cum, (H, W), (h, w)
        self.s_max = s_max

    def at_range(self, rng):
        """Veil radiance (H, W, 3) for a per-pixel range map (inf: the whole ray)."""
        H, W = self.shape
        r = np.minimum(np.where(np.isfinite(rng), rng, self.s_max), self.s_max)
        j = np.clip(np.searchsorted(self.edges, r, side="right") - 1, 0, len(self.edges) - 2)
        t = ((r - self.edges[j]) / (self.edges[j + 1] - self.edges[j])).astype(np.float32)
        out = np.zeros((H, W, 3), np.float32)
        for jj in np.unique(j):
            m = j == jj
            lo = cv2.resize(self.cum[:, :, jj], (W, H), interpolation=cv2.INTER_LINEAR)
            hi = cv2.resize(self.cum[:, :, jj + 1], (W, H), interpolation=cv2.INTER_LINEAR)
            tt = t[m][:, None]
            out[m] = lo[m] * (1 - tt) + hi[m] * tt
        return out

    def at_points(self, u, v, z):
        """Veil in front of points at pixel (u, v) and distance z (nearest coarse ray)."""
        H, W = self.shape
        h, w = self.small
        i = np.clip(np.round((v + 0.5) * h / H - 0.5).astype(int), 0, h - 1)
        k = np.clip(np.round((u + 0.5) * w / W - 0.5).astype(int), 0, w - 1)
        r = np.minimum(z, self.s_max)
        j = np.clip(np.searchsorted(self.edges, r, side="right") - 1, 0, len(self.edges) - 2)
        t = ((r - self.edges[j]) / (self.edges[j + 1] - self.edges[j]))[:, None]
        return self.cum[i, k, j] * (1 - t) + self.cum[i, k, j + 1] * t


# ------------------------------------------------------------------------------------------------ forward scatter


def _draw_fscat(level):
    return dict(omega_s=0.45, theta0=0.05) if level == "mild" else dict(omega_s=0.8, theta0=0.03)


def _forward_scatter(D, rng, cam, water, P, n_layers=6):
    """Wells' small-angle MTF applied per range layer to the direct signal D (which carries e^(-c r) already)."""
    import scipy.fft as sfft

    H, W, _ = D.shape
    fin = np.isfinite(rng)
    if not fin.any():
        return D
    r = np.minimum(np.where(fin, rng, 0.0), 15.0)       # beyond 15 m the direct signal is nil (e^(-c r))
    lo, hi = float(r[fin].min()), float(r[fin].max())
    nodes = np.linspace(lo, hi, n_layers) if hi > lo + 1e-3 else np.array([lo])
    pad = 96
    Hp, Wp = sfft.next_fast_len(H + 2 * pad, real=True), sfft.next_fast_len(W + 2 * pad, real=True)
    fy = sfft.fftfreq(Hp)[:, None] * cam.fy
    fx = sfft.rfftfreq(Wp)[None, :] * cam.fx
    psi = np.sqrt(fx * fx + fy * fy)
    x = 2 * np.pi * P["theta0"] * psi
    g = np.where(x > 1e-9, (1 - np.exp(-x)) / np.maximum(x, 1e-9), 1.0)
    bs = P["omega_s"] * water["c"]
    acc = [np.zeros((Hp, Wp // 2 + 1), np.complex64) for _ in range(3)]
    for k, rk in enumerate(nodes):
        if len(nodes) == 1:
            wgt = fin.astype(np.float32)
        else:
            step = nodes[1] - nodes[0]
            wgt = np.clip(1 - np.abs(r - rk) / step, 0, 1).astype(np.float32) * fin
        if not wgt.any():
            continue
        for ch in range(3):
            layer = D[:, :, ch] * wgt
            big = np.zeros((Hp, Wp), np.float32)
            big[:H + 2 * pad, :W + 2 * pad] = np.pad(layer, pad, mode="reflect")
            F = sfft.rfft2(big, workers=2)
            acc[ch] += (F * np.exp(bs[ch] * rk * g)).astype(np.complex64)
    out = np.empty_like(D)
    for ch in range(3):
        out[:, :, ch] = sfft.irfft2(acc[ch], s=(Hp, Wp), workers=2)[pad:pad + H, pad:pad + W]
    return np.maximum(out, 0.0)


# ------------------------------------------------------------------------------------------------ beta_B


def _draw_betab(seed, level):
    r = _rng(seed, _S["betab"])
    lo, hi = (1.15, 1.35) if level == "mild" else (1.6, 2.0)
    q = r.uniform(lo, hi, 3) ** r.choice([-1.0, 1.0], 3)
    if np.all(q > 1) or np.all(q < 1):          # channel-dependent: at least one of each side
        q[int(r.integers(3))] **= -1
    return dict(ratio=q)


# ------------------------------------------------------------------------------------------------ tone curves


def _draw_resp(seed, level):
    r = _rng(seed, _S["resp"])
    if level == "mild":
        return dict(curve="srgb", pedestal=r.uniform(2.0, 4.0), white=255.0,
                    gains=np.array([r.uniform(1.2, 1.5), 1.0, r.uniform(0.8, 0.95)]))
    return dict(curve="bt709_knee", pedestal=16.0, white=235.0, knee=r.uniform(0.75, 0.85),
                knee_slope=r.uniform(0.2, 0.35), gains=np.array([r.uniform(1.8, 2.4), 1.0, r.uniform(0.65, 0.8)]))


def _tone(x, P):
    x = np.clip(x, 0.0, 1.0)
    if P["curve"] == "srgb":
        y = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    else:
        y = np.where(x < 0.018, 4.5 * x, 1.099 * np.power(np.maximum(x, 0.018), 0.45) - 0.099)
        kp, ks = P["knee"], P["knee_slope"]
        y = np.where(y > kp, kp + (y - kp) * ks, y)
    return P["pedestal"] + (P["white"] - P["pedestal"]) * y


# ------------------------------------------------------------------------------------------------ vignetting


def _draw_vign(seed, level, cam):
    r = _rng(seed, _S["vign"])
    corner = math.hypot(max(cam.cx, cam.width - 1 - cam.cx) / cam.fx, max(cam.cy, cam.height - 1 - cam.cy) / cam.fy)
    a, L = 4.0e-3, r.uniform(0.03, 0.05)
    if level == "mild":
        n, onset, off = r.uniform(2.0, 3.0), r.uniform(0.9, 0.95), 0.0
    else:
        n, onset, off = r.uniform(3.5, 4.5), r.uniform(0.55, 0.7), r.uniform(1.5e-3, 3e-3)
    R = a + L * onset * corner
    ang = r.uniform(0, 2 * np.pi)
    return dict(n=n, pupil_r=a, tube_L=L, tube_R=R, offset=(off * math.cos(ang), off * math.sin(ang)),
                onset_frac=onset)


def _circle_overlap(d, a, R):
    d = np.maximum(d, 1e-12)
    out = np.zeros_like(d)
    inside = d <= R - a
    out[inside] = 1.0
    part = (~inside) & (d < R + a)
    dd = d[part]
    c1 = np.clip((dd ** 2 + a ** 2 - R ** 2) / (2 * dd * a), -1, 1)
    c2 = np.clip((dd ** 2 + R ** 2 - a ** 2) / (2 * dd * R), -1, 1)
    k = np.sqrt(np.maximum((-dd + a + R) * (dd + a - R) * (dd - a + R) * (dd + a + R), 0))
    out[part] = (a * a * np.arccos(c1) + R * R * np.arccos(c2) - 0.5 * k) / (np.pi * a * a)
    return out


def _vignette_map(cam, P):
    u = (np.arange(cam.width) - cam.cx) / cam.fx
    v = (np.arange(cam.height) - cam.cy) / cam.fy
    tx, ty = np.meshgrid(u, v)
    cos_t = 1.0 / np.sqrt(1 + tx * tx + ty * ty)
    d = np.hypot(P["tube_L"] * tx - P["offset"][0], P["tube_L"] * ty - P["offset"][1])
    return (cos_t ** P["n"] * _circle_overlap(d, P["pupil_r"], P["tube_R"])).astype(np.float32)


# ------------------------------------------------------------------------------------------------ sensor


def _draw_sensor(seed, level, cam):
    r = _rng(seed, _S["sensor"])
    H, W = cam.shape
    if level == "mild":
        P = dict(K=0.12, prnu=0.01, dsnu=0.6, row=0.4, col=0.3, read=1.5, hot=0.0, bayer=False, offset=0.5)
    else:
        P = dict(K=0.4, prnu=0.02, dsnu=1.5, row=1.2, col=0.8, read=3.0, hot=5e-4, bayer=True, offset=1.0)
    shape = (H, W) if P["bayer"] else (H, W, 3)
    prnu = 1.0 + P["prnu"] * r.standard_normal(shape)
    colfpn = P["col"] * r.standard_normal(W)
    dsnu = P["dsnu"] * r.standard_normal(shape) + (colfpn[None, :] if P["bayer"] else colfpn[None, :, None])
    if P["hot"] > 0:
        m = r.uniform(size=shape) < P["hot"]
        dsnu[m] += r.exponential(20.0, int(m.sum()))
    fixed = dict(prnu=prnu.astype(np.float32), dsnu=dsnu.astype(np.float32))
    return P, fixed


def _mosaic(x):
    m = np.empty(x.shape[:2], x.dtype)
    m[0::2, 0::2] = x[0::2, 0::2, 0]
    m[0::2, 1::2] = x[0::2, 1::2, 1]
    m[1::2, 0::2] = x[1::2, 0::2, 1]
    m[1::2, 1::2] = x[1::2, 1::2, 2]
    return m


def _bayer_gains(shape, gains):
    g = np.empty(shape, np.float32)
    g[0::2, 0::2] = gains[0]
    g[0::2, 1::2] = gains[1]
    g[1::2, 0::2] = gains[1]
    g[1::2, 1::2] = gains[2]
    return g


def _camera(dn, rng, cam_default, sensor, resp):
    """Linear DN (8-bit scale, float) -> uint8 rgb through sensor, ISP and quantisation."""
    H, W, _ = dn.shape
    dn = np.clip(dn, 0.0, 2000.0)                 # far above saturation: the pixel clips anyway
    if sensor is None:
        k = cam_default["k"]
        x = k * rng.poisson(np.maximum(dn, 0) / k).astype(np.float32)
        x += rng.normal(0.0, cam_default["read"], x.shape).astype(np.float32)
        raw, bayer = x, False
    else:
        P, F = sensor
        bayer = P["bayer"]
        x = _mosaic(dn) if bayer else dn
        x = np.maximum(x * F["prnu"], 0)
        x = P["K"] * rng.poisson(x / P["K"]).astype(np.float32)
        x += F["dsnu"] + P["offset"]
        rown = rng.normal(0.0, P["row"], H).astype(np.float32)
        x += rown[:, None] if bayer else rown[:, None, None]
        x += rng.normal(0.0, P["read"], x.shape).astype(np.float32)
        raw = x
    if resp is None:
        if bayer:
            q = np.clip(np.round(raw * 16), 0, 4095).astype(np.uint16)
            rgb = cv2.cvtColor(q, cv2.COLOR_BayerBG2RGB).astype(np.float32) / 16.0
            return np.clip(np.round(rgb), 0, 255).astype(np.uint8)
        return np.clip(np.round(raw), 0, 255).astype(np.uint8)
    q = np.clip(np.round(raw * 16), 0, 4095).astype(np.float32)          # 12-bit ADC
    if bayer:
        q = np.clip(q * _bayer_gains(q.shape, resp["gains"]), 0, 4095).astype(np.uint16)
        lin = cv2.cvtColor(q, cv2.COLOR_BayerBG2RGB).astype(np.float32) / 4080.0
    else:
        lin = q * resp["gains"].astype(np.float32) / 4080.0
    return np.clip(np.round(_tone(lin, resp)), 0, 255).astype(np.uint8)


# ------------------------------------------------------------------------------------------------ marine snow


def _draw_snow(seed, level, cam):
    r = _rng(seed, _S["snow"])
    return dict(conc_per_l=0.2 if level == "mild" else 1.0, xi=r.uniform(3.2, 3.8), dmin=0.5e-3, dmax=5e-3,
                albedo=r.uniform(0.35, 0.6), aperture=r.uniform(5e-3, 10e-3), focus=r.uniform(1.5, 2.5),
                current=r.uniform(0.02, 0.08) * np.array([*(lambda a: (math.cos(a), 0.0, math.sin(a)))(
                    r.uniform(0, 2 * np.pi))]) + np.array([0.0, -0.001, 0.0]))


def _snow_population(rng, S, n_frames):
    box_lo, box_hi = np.array([-2.5, -2.0, -4.0]), np.array([2.5, 2.0, 6.0])
    vol_l = float(np.prod(box_hi - box_lo)) * 1000.0
    n = int(rng.poisson(S["conc_per_l"] * vol_l))
    X0 = rng.uniform(box_lo, box_hi, (n, 3))
    u = rng.uniform(size=n)
    a = 1.0 - S["xi"]                        # inverse CDF of N(D) ~ D^-xi on [dmin, dmax]
    D = (S["dmin"] ** a + u * (S["dmax"] ** a - S["dmin"] ** a)) ** (1.0 / a)
    walk = np.cumsum(rng.normal(0.0, 0.01 * math.sqrt(_DT), (n_frames, n, 3)), axis=0)
    return dict(X0=X0, D=D, walk=walk, box_lo=box_lo, box_hi=box_hi)


def _render_snow(img, i, T, cam, S, pop, water, lamps, K, ambient, veil, binf_vis, betab, depth_ok):
    """Composite the particles (camera-frame) into the linear radiance image (in place)."""
    H, W, _ = img.shape
    X = pop["X0"] + S["current"] * (i * _DT) + pop["walk"][i]
    span = pop["box_hi"] - pop["box_lo"]
    X = pop["box_lo"] + np.mod(X - pop["box_lo"], span)            # the water keeps flowing through the box
    Xc = X @ T[:3, :3].T + T[:3, 3]
    z = Xc[:, 2]
    keep = z > 0.12
    Xc, D = Xc[keep], pop["D"][keep]
    z = Xc[:, 2]
    u = cam.fx * Xc[:, 0] / z + cam.cx
    v = cam.fy * Xc[:, 1] / z + cam.cy
    inside = (u > -40) & (u < W + 40) & (v > -40) & (v < H + 40)
    Xc, D, z, u, v = Xc[inside], D[inside], z[inside], u[inside], v[inside]
    rr = np.linalg.norm(Xc, axis=1)
    R = D / 2
    c = water["c"]
    # light reflected by a Lambert sphere, per steradian, divided by pi R^2: mean radiance of its disk
    Lp = np.zeros((len(z), 3))
    if lamps is not None:
        for lamp in lamps["lamps"]:
            e, ul, _ = _lamp_field(Xc.astype(np.float32), lamp, c)
            to_cam = -Xc / rr[:, None]
            alpha = np.arccos(np.clip(np.sum(ul * to_cam, axis=1), -1, 1))
            phase = (2.0 / (3.0 * np.pi)) * (np.sin(alpha) + (np.pi - alpha) * np.cos(alpha))
            Lp += K * S["albedo"] * e * (phase / np.pi)[:, None]
    if ambient > 0:
        Lp += ambient * S["albedo"] * 0.77
    Lp = Lp * np.exp(-c * rr[:, None])
    front = binf_vis * (1 - np.exp(-betab * rr[:, None]))
    if veil is not None:
        front = front + veil.at_points(u, v, rr)
    dg = 2 * R * cam.fx / z
    dd = cam.fx * S["aperture"] * np.abs(1 / z - 1 / S["focus"])
    db = np.sqrt(dg ** 2 + dd ** 2)
    area_b = np.pi * (np.maximum(db, 1.0) / 2) ** 2                   # pixels the light spreads over (>= 1 px)
    cov = np.minimum(np.pi * (dg / 2) ** 2 / area_b, 1.0)            # occluded fraction there
    # occlusion only where the particle is in front of the surface
    ui, vi = np.clip(np.round(u).astype(int), 0, W - 1), np.clip(np.round(v).astype(int), 0, H - 1)
    vis = depth_ok[vi, ui] > z
    small = vis & (db < 2.0)
    big = np.nonzero(vis & (db >= 2.0))[0]
    occ = np.zeros((H, W), np.float32)
    fg = np.zeros((H, W, 3), np.float32)          # coverage-weighted (particle + veil in front)
    # small ones: bilinear splat of the coverage
    if small.any():
        us, vs = u[small], v[small]
        x0, y0 = np.floor(us).astype(int), np.floor(vs).astype(int)
        fx_, fy_ = us - x0, vs - y0
        cv_ = np.minimum(np.pi * (dg[small] / 2) ** 2, 1.0)          # blocked area, px (all within ~1 px)
        val = (Lp[small] + front[small])
        for ox, oy, wgt in ((0, 0, (1 - fx_) * (1 - fy_)), (1, 0, fx_ * (1 - fy_)), (0, 1, (1 - fx_) * fy_),
                            (1, 1, fx_ * fy_)):
            xx, yy = x0 + ox, y0 + oy
            ok = (xx >= 0) & (xx < W) & (yy >= 0) & (yy < H)
            a_ = (cv_ * wgt)[ok]
            np.add.at(occ, (yy[ok], xx[ok]), a_)
            for ch in range(3):
                np.add.at(fg[:, :, ch], (yy[ok], xx[ok]), a_ * val[ok, ch])
    for j in big:
        rad = db[j] / 2
        x0, x1 = int(math.floor(u[j] - rad - 1)), int(math.ceil(u[j] + rad + 1))
        y0, y1 = int(math.floor(v[j] - rad - 1)), int(math.ceil(v[j] + rad + 1))
        xa, xb, ya, yb = max(x0, 0), min(x1 + 1, W), max(y0, 0), min(y1 + 1, H)
        if xa >= xb or ya >= yb:
            continue
        yy, xx = np.mgrid[ya:yb, xa:xb]
        dist = np.hypot(xx - u[j], yy - v[j])
        k = np.clip(rad + 0.5 - dist, 0.0, 1.0).astype(np.float32)      # anti-aliased uniform disk (defocus)
        a_ = k * cov[j]
        occ[ya:yb, xa:xb] += a_
        fg[ya:yb, xa:xb] += a_[..., None] * (Lp[j] + front[j]).astype(np.float32)
    occ = np.minimum(occ, 1.0)
    img *= (1.0 - occ)[..., None]
    img += fg
    return int(vis.sum())


# ------------------------------------------------------------------------------------------------ seafloor


def _draw_floor(seed, level):
    r = _rng(seed, _S["floor"])
    gap = r.uniform(1.1, 1.5) if level == "mild" else r.uniform(0.5, 0.8)
    res = 0.015
    x0, x1, z0, z1 = -8.0, 8.0, -10.0, 8.0
    nx, nz = int((x1 - x0) / res), int((z1 - z0) / res)
    fz = np.fft.fftfreq(nz)[:, None]
    fx = np.fft.fftfreq(nx)[None, :]
    k = np.sqrt(fx * fx + fz * fz)
    k[0, 0] = 1.0
    spec = (r.standard_normal((nz, nx)) + 1j * r.standard_normal((nz, nx))) / k ** 1.5
    spec[0, 0] = 0
    noise = np.fft.ifft2(spec).real
    noise = (noise / noise.std()).astype(np.float32)
    zz, xx = np.mgrid[0:nz, 0:nx].astype(np.float32) * res
    lam = r.uniform(0.08, 0.2)
    ang = r.uniform(0, np.pi)
    amp = r.uniform(0.006, 0.015)
    phase = 2 * np.pi * (xx * math.cos(ang) + zz * math.sin(ang)) / lam + 1.2 * noise
    height = amp * np.sin(phase) + 0.01 * noise
    base = np.array([r.uniform(0.30, 0.40), r.uniform(0.27, 0.35), r.uniform(0.20, 0.27)], np.float32)
    fine = r.standard_normal((nz, nx)).astype(np.float32)
    shade = 1.0 + 0.12 * noise + 0.05 * np.sin(phase) + 0.04 * fine
    alb = shade[..., None] * base
    n_st = int((x1 - x0) * (z1 - z0) * (1.5 if level == "mild" else 4.0))
    st_mask = np.zeros((nz, nx), np.float32)
    st_alb = np.zeros((nz, nx, 3), np.float32)
    for _ in range(n_st):
        cx_, cz_ = r.uniform(0, nx), r.uniform(0, nz)
        rad = (r.pareto(2.5) * 0.02 + 0.02) / res
        rad = min(rad, 0.25 / res)
        ax = (int(cx_), int(cz_)), (max(1, int(rad)), max(1, int(rad * r.uniform(0.5, 1.0))))
        tone = r.uniform(0.08, 0.22) if r.uniform() < 0.7 else r.uniform(0.35, 0.5)
        col = tone * np.array([1.0, r.uniform(0.9, 1.0), r.uniform(0.8, 0.95)])
        m = np.zeros((nz, nx), np.uint8)
        cv2.ellipse(m, ax[0], ax[1], r.uniform(0, 180), 0, 360, 1, -1, cv2.LINE_AA)
        mm = m.astype(bool)
        st_mask[mm] = 1.0
        st_alb[mm] = col
    st_soft = cv2.GaussianBlur(st_mask, (0, 0), 1.5)
    alb = alb * (1 - st_mask[..., None]) + st_alb * (1 + 0.1 * fine[..., None]) * st_mask[..., None]
    height = height + 0.03 * st_soft
    gz, gx = np.gradient(height, res)
    return dict(gap=gap, y=-_PANEL_HALF[1] - gap, x0=x0, z0=z0, res=res, nx=nx, nz=nz,
                alb=np.clip(alb, 0, 1).astype(np.float32), gx=gx.astype(np.float32), gz=gz.astype(np.float32),
                ripple_wavelength=lam, stones=n_st)


def _floor_hit(cam, T, F):
    """Per pixel: camera-frame points, normals, albedo and range of the seafloor plane (inf where missed)."""
    H, W = cam.shape
    u = (np.arange(W) - cam.cx) / cam.fx
    v = (np.arange(H) - cam.cy) / cam.fy
    dx, dy = np.meshgrid(u, v)
    d = np.stack([dx, dy, np.ones_like(dx)], -1)                 # camera frame, z = 1
    R, t = T[:3, :3], T[:3, 3]
    o = -R.T @ t                                                 # camera centre in the panel frame
    w = d @ R                                                    # = (R^T d) row-wise
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (F["y"] - o[1]) / w[..., 1]
    ok = np.isfinite(s) & (s > 0)
    s = np.where(ok, s, np.inf)
    Xp = o + w * np.where(ok, s, 0)[..., None]
    mx = ((Xp[..., 0] - F["x0"]) / F["res"]).astype(np.float32)
    mz = ((Xp[..., 2] - F["z0"]) / F["res"]).astype(np.float32)
    mx = np.mod(mx, F["nx"] - 1).astype(np.float32)
    mz = np.mod(mz, F["nz"] - 1).astype(np.float32)
    alb = cv2.remap(F["alb"], mx, mz, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    gx = cv2.remap(F["gx"], mx, mz, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    gz = cv2.remap(F["gz"], mx, mz, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    n_p = np.stack([-gx, np.ones_like(gx), -gz], -1)
    n_p /= np.linalg.norm(n_p, axis=-1, keepdims=True)
    N = n_p @ R.T                                                # to the camera frame
    P = d * np.where(ok, s, 0)[..., None]
    rng = np.where(ok, s * np.linalg.norm(d, axis=-1), np.inf)
    return P.astype(np.float32), N.astype(np.float32), alb, rng.astype(np.float32), s.astype(np.float32)


# ------------------------------------------------------------------------------------------------ port refraction


_N_WATER = np.array([1.3375, 1.3413, 1.3464])
_N_GLASS = {"acrylic": np.array([1.4905, 1.4937, 1.4990]), "BK7": np.array([1.5155, 1.5187, 1.5246])}


def _port_radius(rho_s, f_air, z, P, ch):
    """Sensor radius (px) -> pinhole radius (px, pinhole focal fx=1 scale returned as tan) for a point at depth z."""
    ta = rho_s / f_air
    sa = ta / np.sqrt(1 + ta * ta)
    sg = sa / P["n_glass"][ch]
    sw = sa / P["n_water"][ch]
    tg = sg / np.sqrt(1 - sg * sg)
    tw = sw / np.sqrt(1 - sw * sw)
    rho0 = P["d0"] * ta + P["t"] * tg
    zp = P["d0"] + P["t"]
    return (rho0 + (z - zp) * tw) / z                              # tan of the pinhole angle


def _draw_port(seed, level, cam):
    r = _rng(seed, _S["port"])
    if level == "mild":
        P = dict(glass="acrylic", t=8e-3, d0=r.uniform(8e-3, 12e-3),
                 calib="pinhole fit at 35% of the half-diagonal, 2 m")
    else:
        P = dict(glass="BK7", t=15e-3, d0=r.uniform(25e-3, 35e-3), calib="paraxial")
    P["n_glass"], P["n_water"] = _N_GLASS[P["glass"]], _N_WATER
    f_par = cam.fx / _N_WATER[1]
    if level == "mild":
        rho = 0.35 * math.hypot(cam.width / 2, cam.height / 2)
        lo, hi = 0.5 * f_par, 1.5 * f_par
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if _port_radius(rho, mid, 2.0, P, 1) * cam.fx > rho:
                lo = mid                                       # sees too wide: longer focal
            else:
                hi = mid
        P["f_air"] = 0.5 * (lo + hi)
    else:
        P["f_air"] = f_par
    return P


def _port_remap(img, depth, cam, P):
    H, W, _ = img.shape
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    du, dv = u - cam.cx, v - cam.cy
    rho = np.hypot(du, dv)
    cu, cv_ = np.where(rho > 0, du / np.maximum(rho, 1e-9), 0), np.where(rho > 0, dv / np.maximum(rho, 1e-9), 0)
    zmap = np.where(np.isfinite(depth), depth, 20.0)
    z = zmap
    for _ in range(3):
        tp = _port_radius(rho, P["f_air"], z, P, 1)
        uu = np.clip(np.round(cam.cx + cam.fx * tp * cu), 0, W - 1).astype(int)
        vv = np.clip(np.round(cam.cy + cam.fy * tp * cv_), 0, H - 1).astype(int)
        z = zmap[vv, uu]
    out = np.empty_like(img)
    for ch in range(3):
        tp = _port_radius(rho, P["f_air"], z, P, ch)
        mx = (cam.cx + cam.fx * tp * cu).astype(np.float32)
        my = (cam.cy + cam.fy * tp * cv_).astype(np.float32)
        out[:, :, ch] = cv2.remap(img[:, :, ch], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return out


# ------------------------------------------------------------------------------------------------ pose error


def _rotvec(w):
    th = float(np.linalg.norm(w))
    if th < 1e-15:
        return np.eye(3)
    k = w / th
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * Kx + (1 - math.cos(th)) * Kx @ Kx


def _unit(r):
    v = r.standard_normal(3)
    return v / np.linalg.norm(v)


def _draw_pose_error(seed, level, n):
    r = _rng(seed, _S["pose"])
    tb, rb, tj, rj = (0.02, 0.2, 0.003, 0.05) if level == "mild" else (0.06, 0.6, 0.008, 0.15)
    bias_t = tb * r.uniform(0.7, 1.0) * _unit(r)
    bias_r = math.radians(rb) * r.uniform(0.7, 1.0) * _unit(r)
    errs = []
    for _ in range(n):
        t = bias_t + r.normal(0, tj, 3)
        w = bias_r + r.normal(0, math.radians(rj), 3)
        E = np.eye(4)
        E[:3, :3] = _rotvec(w)
        E[:3, 3] = t
        errs.append(E)
    return dict(bias_t=bias_t, bias_rotvec=bias_r, jitter_t=tj, jitter_r_deg=rj), errs


# ------------------------------------------------------------------------------------------------ main


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items() if not (isinstance(v, np.ndarray) and v.size > 64)}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating,)):
        return float(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    return x


def synth_literature(out, effects: dict, n_frames: int = 8, seed: int = 0, width: int = 640,
                     twin_out=None, twin_seed: int = 1) -> dict:
    """Write a trial bag at `out` (a path like /tmp/x/trial.mcap: write_trial makes the rosbag2 directory);
    effects: {registry_name: 'mild'|'strong'}; returns a truth dict (effects, the water parameters, the ranges
    of the frames) that is NOT written next to the bag. twin_out: also write the same dive with other draws of
    what is new in every frame (particles, temporal noise) from twin_seed; the recording must be bit-identical with
    or without its twin."""
    from uw_sil.sim.render import Renderer

    effects = dict(effects or {})
    for k, lv in effects.items():
        if k not in LITERATURE_EFFECTS:
            raise ValueError(f"unknown effect {k!r}; known: {LITERATURE_EFFECTS}")
        if lv not in _LEVELS:
            raise ValueError(f"effect {k}: level must be 'mild' or 'strong', got {lv!r}")
    n_frames, seed, width = int(n_frames), int(seed), int(width)
    if n_frames < 1 or seed < 0 or width < 16:
        raise ValueError("need n_frames >= 1, seed >= 0, width >= 16")
    has = effects.__contains__
    height = width * 3 // 4

    dive = _draw_dive(seed, n_frames)
    cam = CameraModel.from_fov(width, height, dive["fov"])
    water = _draw_water(seed)
    rc = _rng(seed, _S["cam"])
    cam_default = dict(k=rc.uniform(0.02, 0.04), read=rc.uniform(0.8, 1.2))
    params: dict = {}

    c = water["c"]
    beta_b = c.copy()
    if has("backscatter_coefficient"):
        params["backscatter_coefficient"] = _draw_betab(seed, effects["backscatter_coefficient"])
        beta_b = c * params["backscatter_coefficient"]["ratio"]
    water["beta_D"], water["beta_B"] = c, beta_b

    lamps, K, ambient, phase = None, 0.0, 1.0, None
    if has("artificial_light"):
        lamps = _draw_lamps(seed, effects["artificial_light"], float(np.sqrt(dive["dist"][0] * dive["dist"][-1])))
        K = _calibrate_lamps(lamps, water)
        ambient = lamps["ambient"]
        phase = _Phase(water["ff_n"], water["ff_mu"])
        params["artificial_light"] = dict(
            layout=lamps["layout"], ambient=ambient, exposure_K=K, target_dn=lamps["target_dn"],
            inner_air_deg=lamps["inner_air_deg"], outer_air_deg=lamps["outer_air_deg"],
            lamps=[dict(pos=l["pos"], axis=l["axis"], inner_water_deg=math.degrees(l["inner"]),
                        outer_water_deg=math.degrees(l["outer"]), spill=l["spill"], colour=l["col"])
                   for l in lamps["lamps"]], ff_bb_ratio=phase.bb_ratio)
    fscat = _draw_fscat(effects["forward_scatter"]) if has("forward_scatter") else None
    resp = _draw_resp(seed, effects["camera_response"]) if has("camera_response") else None
    vign = _draw_vign(seed, effects["vignetting"], cam) if has("vignetting") else None
    vmap = _vignette_map(cam, vign) if vign else None
    sensor = _draw_sensor(seed, effects["sensor_noise"], cam) if has("sensor_noise") else None
    snow = _draw_snow(seed, effects["marine_snow"], cam) if has("marine_snow") else None
    floor = _draw_floor(seed, effects["unmodeled_geometry"]) if has("unmodeled_geometry") else None
    port = _draw_port(seed, effects["port_refraction"], cam) if has("port_refraction") else None
    perr = _draw_pose_error(seed, effects["pose_error"], n_frames) if has("pose_error") else None
    jpeg_q = (75 if effects["compression"] == "mild" else 30) if has("compression") else None
    for name, p in (("forward_scatter", fscat), ("camera_response", resp), ("vignetting", vign),
                    ("sensor_noise", sensor[0] if sensor else None), ("marine_snow", snow),
                    ("port_refraction", port), ("pose_error", perr[0] if perr else None)):
        if p is not None:
            params[name] = p
    if floor is not None:
        params["unmodeled_geometry"] = dict(gap_below_panel=floor["gap"], floor_y=floor["y"],
                                            ripple_wavelength=floor["ripple_wavelength"], stones=floor["stones"])
    if jpeg_q is not None:
        params["compression"] = dict(quality=jpeg_q, subsampling="4:2:0")

    runs = [(out, lambda i: _rng(seed, _TEMPORAL, i), _rng(seed, _TEMPORAL, 10 ** 6))]
    if twin_out is not None:
        runs.append((twin_out, lambda i: _rng(seed, _TWIN, int(twin_seed), i),
                     _rng(seed, _TWIN, int(twin_seed), 10 ** 6)))
    pops = [(_snow_population(pr, snow, n_frames) if snow else None) for _, _, pr in runs]

    binf_vis = water["binf"] * ambient
    frames = [[] for _ in runs]
    frame_truth = []
    t0 = 1_700_000_000 * 10 ** 9 + seed * 10 ** 9
    with Renderer(camera=cam) as rend:
        for i in range(n_frames):
            T = dive["poses"][i]
            raw = rend.draw(T)
            res = rend.develop(raw)
            rend.shading = "flat"
            alb = rend.develop(raw).rgb
            rend.shading = "lambert"
            J = res.rgb.astype(np.float32)
            depth = res.depth.copy()
            rng_map = res.range.astype(np.float32).copy()
            ids = res.part_ids.astype(np.int32)
            xt = ((np.arange(width) - cam.cx) / cam.fx)[None, :]
            yt = ((np.arange(height) - cam.cy) / cam.fy)[:, None]
            dfin = np.where(np.isfinite(depth), depth, 0.0)
            P = np.stack([dfin * xt, dfin * yt, dfin], -1).astype(np.float32)
            panel_mask = ids > 0
            panel_r = res.range[panel_mask]
            N = _normals(P, ids) if lamps is not None else None
            if floor is not None:
                Pf, Nf, albf, rf, sf = _floor_hit(cam, T, floor)
                use = rf < rng_map
                cosv = np.maximum(-Nf[..., 2], 0.0)
                Jf = albf * (0.3 + 0.7 * cosv)[..., None]
                J = np.where(use[..., None], Jf, J)
                alb = np.where(use[..., None], albf, alb)
                P = np.where(use[..., None], Pf, P)
                if N is not None:
                    N = np.where(use[..., None], Nf, N)
                rng_map = np.where(use, rf, rng_map)
                depth = np.where(use, sf, depth)
                ids = np.where(use, 60000, ids)
            hit = np.isfinite(rng_map)
            r = np.where(hit, rng_map, 0.0)[..., None]
            # scene light
            if lamps is not None:
                E = _surface_irradiance(P, N, lamps, water)
                Jl = np.float32(K / np.pi) * alb * E + np.float32(ambient) * J
                Jl[~hit] = 0
            else:
                Jl = J
            # water
            Dsig = Jl * np.exp(-c * r).astype(np.float32)
            Dsig[~hit] = 0
            if fscat is not None:
                Dsig = _forward_scatter(Dsig, rng_map, cam, water, fscat)
            Bs = np.where(hit[..., None], binf_vis * (1 - np.exp(-beta_b * r)), binf_vis).astype(np.float32)
            veil = None
            if lamps is not None:
                veil = _Veil(cam, lamps, water, phase, K)
                Bs = Bs + veil.at_range(rng_map)
            base = (Dsig + Bs).astype(np.float32)
            depth_ok = np.where(hit, depth, np.inf)
            stamp = t0 + int(round(i * _DT * 1e9))
            T_rec = perr[1][i] @ T if perr else T
            nsnow = []
            for ri, (_, trng, _) in enumerate(runs):
                img = base.copy()
                if snow is not None:
                    nsnow.append(_render_snow(img, i, T, cam, snow, pops[ri], water, lamps, K, ambient, veil,
                                              binf_vis, beta_b, depth_ok))
                if port is not None:
                    img = _port_remap(img, depth_ok, cam, port)
                if vmap is not None:
                    img = img * vmap[..., None]
                u8 = _camera(img * 255.0, trng(i), cam_default, sensor, resp)
                if jpeg_q is not None:
                    params_j = [cv2.IMWRITE_JPEG_QUALITY, jpeg_q]
                    if hasattr(cv2, "IMWRITE_JPEG_SAMPLING_FACTOR"):
                        params_j += [cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420]
                    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(u8, cv2.COLOR_RGB2BGR), params_j)
                    u8 = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
                frames[ri].append(Sample(stamp_ns=stamp, image=np.ascontiguousarray(u8), camera=cam,
                                         pose=T_rec, frame_id="camera_optical_frame", index=i))
            frame_truth.append(dict(
                index=i, stamp_ns=stamp, camera_distance=float(dive["dist"][i]),
                panel_range_min=float(panel_r.min()) if panel_r.size else None,
                panel_range_median=float(np.median(panel_r)) if panel_r.size else None,
                panel_range_max=float(panel_r.max()) if panel_r.size else None,
                panel_fraction=float(panel_mask.mean()),
                floor_fraction=float((ids == 60000).mean()) if floor is not None else 0.0,
                snow_visible=nsnow[0] if nsnow else 0,
                yaw_deg=math.degrees(dive["yaw"][i]), pitch_deg=math.degrees(dive["pitch"][i]),
                roll_deg=math.degrees(dive["roll"][i]), target_x=float(dive["x"][i]), target_y=float(dive["y"][i]),
                pose_true=T, pose_recorded=T_rec))

    bag = write_trial(out, frames[0], overwrite=True)
    twin_bag = write_trial(twin_out, frames[1], overwrite=True) if twin_out is not None else None
    truth = dict(generator="bench.literature_effects", seed=seed, twin_seed=int(twin_seed) if twin_out else None,
                 effects=effects, params=params, bag=str(bag), twin_bag=str(twin_bag) if twin_bag else None,
                 camera=dict(width=width, height=height, hfov_deg=dive["fov"], fx=cam.fx, fy=cam.fy, cx=cam.cx,
                             cy=cam.cy),
                 water=dict(c=c, B_inf=water["binf"], beta_D=c, beta_B=beta_b, b=water["b"],
                            ff_n=water["ff_n"], ff_mu=water["ff_mu"], ambient_scale=ambient,
                            model="J e^(-beta_D r) + a B_inf (1 - e^(-beta_B r))"),
                 default_camera=cam_default, frames=frame_truth)
    return _jsonable(truth)


if __name__ == "__main__":          # python -m bench.literature_effects OUT.mcap [name=level ...] [--seed N]
    import argparse
    import json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("effects", nargs="*", help="name=mild|strong")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--width", type=int, default=640)
    a = ap.parse_args()
    eff = dict(e.split("=", 1) for e in a.effects)
    print(json.dumps(synth_literature(a.out, eff, a.frames, a.seed, a.width), indent=1)[:4000])
