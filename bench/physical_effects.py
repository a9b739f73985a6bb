"""A third, physically based generator of concealed-effect test recordings (deep sea, vehicle lamps only).

Written from radiative transfer (Jaffe-McGlamery single scattering), independently of
``uw_sil.sim.effects`` and ``foreign_effects.py``; only the plumbing is shared (the project's panel model
rendered for geometry, ``CameraModel``, ``facing_pose`` and ``write_trial``). The bag holds only what a real
camera bag holds: images, camera info and the panel pose. The truth is returned to the caller, never written.

Scene, per dive (seed): the panel seen by an ROV camera approaching from 4 m to 1.2-1.8 m with yaw / pitch /
roll sway; 2-4 lamps fixed to the vehicle 0.3-1.0 m from the camera, toed in, each with a super-Gaussian beam
``I(theta) = I0 * exp(-ln2 * (theta / theta_h) ** p)`` (half-power half-angle theta_h 30-50 deg, edge
sharpness p 2.5-6) and its own LED colour. Water per RGB channel: absorption ``a`` (pure sea water plus a
little CDOM), particle scattering ``b ~ lambda ** -0.6``, ``c = a + b``, Henyey-Greenstein phase with
g = 0.85-0.95. All radiometry is linear (radiance, arbitrary units) until the camera.

Base physics (always on, the "control" of this generator; counts as ``artificial_light`` in the truth):

- surface irradiance from each lamp ``E = I(theta) cos(phi) exp(-c R_s) / R_s**2`` with a shadow test
  against a depth map rendered from the lamp (3x3 percentage-closer filtering: soft shadow edges, as from a
  lamp of a few cm);
- Lambertian panel, radiance ``rho / pi * sum E``, seen through ``exp(-c R_c)``; ``rho`` is the model's
  albedo (the scene model defines the panel's reflectance);
- backscatter: single-scatter volume integral along each viewing ray,
  ``L_bs = int_0^{R_c} b * p_HG(psi) * sum_i I_i(theta) exp(-c r_i) / r_i**2 * exp(-c t) dt``,
  ray-marched on log-spaced steps (0.03-12 m) every ``bs_step``-th pixel; the cumulative integral is
  interpolated to every pixel at that pixel's own surface range (sharp at silhouettes);
- the camera's ordinary noise at low gain (20 e-/DN, 15 e- read noise, Poisson): photons are counted
  whatever the camera;
- a fixed exposure for the whole dive, set so that the mean of the panel (brightest channel) at the
  closest frame lands at 85-115 DN (deep-sea footage is dark: the panel at 4 m sits at a few to a few tens
  of DN, open water near 0 except the backscatter; white details of the closest frames may clip); linear
  response, 8 bits.

Effects that can be concealed on top (``effects={name: 'mild'|'strong'}``):

- forward_scatter: small-angle scattered light ``(exp(-(c - eta b) R) - exp(-c R))`` spread by Jaffe's
  PSF ``F^-1{exp(-B R f)}``, i.e. the 2D kernel ``w / (2 pi (r**2 + w**2) ** 1.5)`` with ``w`` growing
  linearly with range (applied per range layer of the source pixels);
- port_refraction: the flat port bends the rays (Snell's law at each channel's wavelength, sea water's index:
  pincushion and lateral colour); strong uncorrected, mild what a one-coefficient radial calibration leaves;
- vignetting: lens relative illumination ``cos^m`` of the in-air angle behind a flat port (Snell), the
  port's Fresnel transmission (water-glass-air, unpolarised) and, strong, a mechanical housing clip;
- sensor_noise: a high-gain camera instead (6 / 2.5 e-/DN): Bayer RGGB mosaic of the raw signal, Poisson
  shot noise in electrons, Gaussian read noise (strong: also row noise and a fixed dark pattern), bilinear
  demosaic;
- camera_response: white balance gains and a Rec.709 (mild) or sRGB with black pedestal (strong) OETF,
  exposure set on the output;
- marine_snow: particles (power-law sizes 0.4-6 / 0.4-10 mm, 0.4 / 2 per litre) fixed in the water and
  drifting, lit by the lamps (beam, 1/r**2, attenuation, phase of a lit sphere), attenuated to the camera,
  spread by their projected size and the lens defocus (thin lens, focus at the working range), occluding
  what is behind them;
- unmodeled_geometry: a textured seafloor (with the panel's stand) below the panel, which the scene model
  lacks, lit and shadowed by the lamps;
- compression: JPEG (OpenCV, 4:2:0) at quality 70 / 25 (not a registry effect).

``backscatter_coefficient`` has no physical switch here: backscatter is always computed from ``b`` and the
phase function (it is part of the water), so it is not offered.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
from scipy.ndimage import gaussian_filter

from uw_sil.bags.records import Sample
from uw_sil.bags.writer import write_trial
from uw_sil.sim.camera import CameraModel
from uw_sil.sim.render import Renderer
from uw_sil.sim.scene import add_seafloor, facing_pose, load_model

PHYSICAL_EFFECTS = ("forward_scatter", "vignetting", "sensor_noise", "camera_response", "marine_snow",
                    "unmodeled_geometry", "compression", "port_refraction")
LEVELS = ("mild", "strong")
LAMBDA_NM = np.array([610.0, 540.0, 465.0])      # effective RGB wavelengths of the camera


# ----------------------------------------------------------------------------- dive description


@dataclass
class Lamp:
    pos: np.ndarray          # camera frame, metres
    axis: np.ndarray         # unit vector, camera frame
    half_angle: float        # half-power half-angle, rad
    sharp: float             # super-Gaussian exponent
    rgb: np.ndarray          # on-axis radiant intensity per channel (arbitrary units)

    def profile(self, cos_t: np.ndarray) -> np.ndarray:
        th = np.arccos(np.clip(cos_t, -1.0, 1.0))
        return np.where(cos_t > 0.0, np.exp(-math.log(2.0) * (th / self.half_angle) ** self.sharp), 0.0)

    def T_lamp_cam(self) -> np.ndarray:
        z = self.axis / np.linalg.norm(self.axis)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        T = np.eye(4)
        T[:3, :3] = np.stack([x, y, z])
        T[:3, 3] = -T[:3, :3] @ self.pos
        return T


@dataclass
class Dive:
    camera: CameraModel
    a: np.ndarray
    b: np.ndarray
    g: float
    lamps: list
    poses: list
    target_dn: float
    focus_m: float
    aperture_m: float
    dt_s: float
    extra: dict = field(default_factory=dict)

    @property
    def c(self) -> np.ndarray:
        return self.a + self.b


def make_dive(seed: int, n_frames: int, width: int) -> Dive:
    rng = np.random.default_rng(7700 + seed)
    cam = CameraModel.from_fov(width, width * 3 // 4, float(rng.uniform(58, 72)))    # in water, behind a flat port
    # pure sea water absorption at the three wavelengths (roughly Pope & Fry) plus CDOM / detritus
    a_w = np.array([0.27, 0.055, 0.015])
    a = a_w + rng.uniform(0.0, 0.03) * np.exp(-0.014 * (LAMBDA_NM - 440.0)) + rng.uniform(0.01, 0.08) * np.array([1, .5, .4])
    b550 = math.exp(rng.uniform(math.log(0.04), math.log(0.5)))     # clear .. slightly turbid
    b = b550 * (LAMBDA_NM / 550.0) ** -0.6
    g = float(rng.uniform(0.85, 0.95))
    n_l = int(rng.integers(2, 5))
    lamps = []
    aim = float(rng.uniform(1.8, 4.0))
    tilt = float(rng.uniform(-0.2, 0.3))      # + aims a bit below the optical axis
    for i in range(n_l):
        if i < 2:     # left / right pair
            side = -1.0 if i == 0 else 1.0
            pos = np.array([side * rng.uniform(0.3, 0.75), rng.uniform(-0.35, 0.15), rng.uniform(-0.2, 0.1)])
        else:         # a top (and bottom) lamp
            pos = np.array([rng.uniform(-0.2, 0.2), (-1.0 if i == 2 else 1.0) * rng.uniform(0.3, 0.6),
                            rng.uniform(-0.2, 0.1)])
        target = np.array([rng.uniform(-0.2, 0.2), tilt * aim, aim])
        axis = (target - pos) / np.linalg.norm(target - pos)
        cct = rng.uniform(-1, 1)       # warm .. cool white LED
        rgb = np.array([1.0 + 0.12 * cct * -1, 1.0, 0.9 + 0.15 * cct]) * rng.uniform(0.7, 1.3)
        lamps.append(Lamp(pos, axis, math.radians(rng.uniform(30, 50)), float(rng.uniform(2.5, 6.0)), rgb))
    end = float(rng.uniform(1.2, 1.8))
    ph = rng.uniform(0, 2 * math.pi, 6)
    yaw_a, pitch_a = math.radians(rng.uniform(6, 14)), math.radians(rng.uniform(4, 9))
    poses = []
    for k in range(n_frames):
        s = k / max(1, n_frames - 1)
        d = 4.0 + (end - 4.0) * (1 - (1 - s) ** 1.3)
        poses.append(facing_pose(d, x=0.1 * math.sin(2.1 * s + ph[0]), y=0.06 * math.sin(1.7 * s + ph[1]),
                                 yaw=yaw_a * math.sin(3.0 * s + ph[2]), pitch=pitch_a * math.sin(2.5 * s + ph[3]),
                                 roll=math.radians(2.5) * math.sin(2.0 * s + ph[4])))
    return Dive(cam, a, b, g, lamps, poses, target_dn=float(rng.uniform(85, 115)), focus_m=float(rng.uniform(1.8, 3.0)),
                aperture_m=float(rng.uniform(0.002, 0.004)), dt_s=1.5)


# ----------------------------------------------------------------------------- geometry


def _rays(cam: CameraModel):
    """Unit viewing rays (H, W, 3) in the camera optical frame and the tangent coordinates."""
    xt = (np.arange(cam.width) - cam.cx) / cam.fx
    yt = (np.arange(cam.height) - cam.cy) / cam.fy
    d = np.stack(np.broadcast_arrays(xt[None, :], yt[:, None], np.ones((1, 1))), axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True), xt, yt


def _one_sided_diff(w: np.ndarray, part: np.ndarray, axis: int) -> np.ndarray:
    """Derivative of ``w`` along ``axis``: the smaller of the forward / backward differences within a part."""
    f = np.diff(w, axis=axis)
    same = np.diff(part.astype(np.int32), axis=axis) == 0
    f = np.where(same, f, np.nan)
    pad_end = [(0, 0), (0, 0)]
    pad_end[axis] = (0, 1)
    pad_start = [(0, 0), (0, 0)]
    pad_start[axis] = (1, 0)
    fwd = np.pad(f, pad_end, constant_values=np.nan)
    bwd = np.pad(f, pad_start, constant_values=np.nan)
    out = np.where(np.isnan(fwd) | (np.abs(bwd) < np.abs(fwd)), bwd, fwd)
    return np.nan_to_num(out, nan=0.0)


def surface_normals(depth, part_ids, hit, cam: CameraModel, xt, yt) -> np.ndarray:
    """Unit normals (H, W, 3), camera frame, facing the camera, from the gradient of the inverse depth.

    On a plane n.X = d seen through X = z (xt, yt, 1): 1/z = (n_x xt + n_y yt + n_z) / d, so the normal is
    proportional to (fx dw/du, fy dw/dv, w - xt fx dw/du - yt fy dw/dv) with w = 1/z.
    """
    w = np.where(hit, 1.0 / np.where(hit, depth, 1.0), 0.0)
    mx = cam.fx * _one_sided_diff(w, part_ids, 1)
    my = cam.fy * _one_sided_diff(w, part_ids, 0)
    mz = w - xt[None, :] * mx - yt[:, None] * my
    n = -np.stack([mx, my, mz], axis=-1)
    nn = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(nn > 0, n / np.maximum(nn, 1e-12), np.array([0.0, 0.0, -1.0]))
    return n


def lamp_visibility(P, hit, lamp: Lamp, T_cam_panel, shadow_ren: Renderer) -> np.ndarray:
    """Fraction of the lamp seen from each surface point (H, W): depth map from the lamp, 3x3 PCF."""
    Tl = lamp.T_lamp_cam()
    rr = shadow_ren.render(Tl @ T_cam_panel)
    zmap = rr.depth
    sc = shadow_ren.camera
    Pl = P[hit] @ Tl[:3, :3].T + Tl[:3, 3]
    z = Pl[:, 2]
    ok = z > 1e-3
    zs = np.where(ok, z, 1.0)
    ui = np.rint(sc.fx * Pl[:, 0] / zs + sc.cx).astype(np.int64) + 1      # +1: the padded map
    vi = np.rint(sc.fy * Pl[:, 1] / zs + sc.cy).astype(np.int64) + 1
    ok &= (ui >= 1) & (ui <= sc.width) & (vi >= 1) & (vi <= sc.height)
    zpad = np.pad(zmap, 1, mode="edge").astype(np.float32)
    Wp = sc.width + 2
    flat = np.where(ok, vi * Wp + ui, Wp + 1)
    zt = (z - 0.01) / 1.01                  # lit when z <= zmap * 1.01 + 0.01 (depth bias)
    vis = np.zeros(len(z), np.float32)
    n = 0
    for dv in (-1, 0, 1):
        for du in (-1, 0, 1):
            vis += zpad.ravel()[flat + dv * Wp + du] >= zt
            n += 1
    vis = np.where(ok, vis / n, 1.0)        # outside the lamp's map: lit (the beam is weak there)
    out = np.ones(hit.shape)
    out[hit] = vis
    return out


# ----------------------------------------------------------------------------- optics


def hg_phase(cos_psi, g):
    return (1 - g * g) / (4 * math.pi * (1 + g * g - 2 * g * cos_psi) ** 1.5)


def surface_radiance(P, N, albedo, hit, dive: Dive, vis: list) -> np.ndarray:
    """Radiance leaving the Lambertian surface (H, W, 3), before the path to the camera."""
    c = dive.c
    E = np.zeros(P.shape[:2] + (3,))
    Ph = P[hit]
    Nh = N[hit]
    Eh = np.zeros((len(Ph), 3))
    for lamp, vv in zip(dive.lamps, vis):
        v = Ph - lamp.pos                      # lamp -> surface
        r = np.linalg.norm(v, axis=-1)
        vh = v / r[:, None]
        prof = lamp.profile(vh @ lamp.axis)
        cos_phi = np.clip(-(vh * Nh).sum(-1), 0.0, None)
        Eh += (vv[hit] * prof * cos_phi / (r * r))[:, None] * lamp.rgb[None, :] * np.exp(-c[None, :] * r[:, None])
    E[hit] = Eh
    return albedo / math.pi * E


def backscatter(cam: CameraModel, dirs, rng_map, dive: Dive, step: int = 8, n_t: int = 72,
                t_min: float = 0.03, t_max: float = 12.0) -> np.ndarray:
    """Single-scattered lamp light along each viewing ray up to the surface (H, W, 3)."""
    H, W = rng_map.shape
    nu = int(math.ceil((W - 1) / step)) + 1
    nv = int(math.ceil((H - 1) / step)) + 1
    uc = np.linspace(0, W - 1, nu)
    vc = np.linspace(0, H - 1, nv)
    xt = (uc - cam.cx) / cam.fx
    yt = (vc - cam.cy) / cam.fy
    d = np.stack(np.broadcast_arrays(xt[None, :], yt[:, None], np.ones((1, 1))), axis=-1)
    d = (d / np.linalg.norm(d, axis=-1, keepdims=True)).reshape(-1, 3)           # (Nr, 3)
    lt = np.linspace(math.log(t_min), math.log(t_max), n_t + 1)
    edges = np.exp(lt)
    tm = np.sqrt(edges[:-1] * edges[1:])
    dt = np.diff(edges)
    X = d[:, None, :] * tm[None, :, None]                                         # (Nr, K, 3)
    c, b = dive.c, dive.b
    acc = np.zeros(X.shape[:2] + (3,))
    for lamp in dive.lamps:
        v = X - lamp.pos
        r = np.linalg.norm(v, axis=-1)
        vh = v / r[..., None]
        prof = lamp.profile(vh @ lamp.axis)
        cos_psi = -(vh * d[:, None, :]).sum(-1)      # light propagates along vh, leaves towards the camera (-d)
        w = prof * hg_phase(cos_psi, dive.g) / (r * r)
        acc += w[..., None] * lamp.rgb * np.exp(-c * r[..., None])
    acc *= (b * np.exp(-c[None, None, :] * tm[None, :, None])) * dt[None, :, None]
    C = np.concatenate([np.zeros((acc.shape[0], 1, 3)), np.cumsum(acc, axis=1)], axis=1)
    C = C.reshape(nv * nu, n_t + 1, 3).astype(np.float32)
    # every pixel: bilinear over the 4 neighbouring coarse rays, each read at the pixel's own range
    u = np.arange(W) / ((W - 1) / (nu - 1))
    v = np.arange(H) / ((H - 1) / (nv - 1))
    u0 = np.minimum(np.floor(u).astype(int), nu - 2)
    v0 = np.minimum(np.floor(v).astype(int), nv - 2)
    fu = (u - u0)[None, :, None]
    fv = (v - v0)[:, None, None]
    R = np.where(np.isfinite(rng_map), rng_map, t_max)
    kf = np.clip((np.log(np.clip(R, t_min, t_max)) - lt[0]) / (lt[1] - lt[0]), 0, n_t - 1e-6)
    k0 = np.floor(kf).astype(int)
    fk = (kf - k0)[..., None].astype(np.float32)
    out = np.zeros((H, W, 3), np.float32)
    for dv_, wv in ((0, 1 - fv), (1, fv)):
        for du_, wu in ((0, 1 - fu), (1, fu)):
            ray = (v0 + dv_)[:, None] * nu + (u0 + du_)[None, :]
            flat = (ray * (n_t + 1) + k0).ravel()
            Cf = C.reshape(-1, 3)
            val = Cf[flat].reshape(H, W, 3) * (1 - fk) + Cf[flat + 1].reshape(H, W, 3) * fk
            out += (wv * wu).astype(np.float32) * val
    return out.astype(float)


def forward_scatter_add(L_s, R, hit, dive: Dive, level: str, fx: float) -> np.ndarray:
    """Small-angle forward-scattered light reaching the camera (H, W, 3)."""
    import cv2

    eta, kappa = {"mild": (0.35, 0.006), "strong": (0.7, 0.014)}[level]
    c, b = dive.c, dive.b
    Rh = np.where(hit, R, np.nan)
    if not np.isfinite(Rh).any():
        return np.zeros_like(L_s)
    frac = np.where(hit[..., None], np.exp(-(c - eta * b) * np.nan_to_num(Rh)[..., None])
                    - np.exp(-c * np.nan_to_num(Rh)[..., None]), 0.0)
    src = L_s * frac
    lo, hi = np.nanpercentile(Rh, 1), np.nanpercentile(Rh, 99)
    layers = np.linspace(lo, hi, 4) if hi > lo * 1.02 else np.array([lo])
    out = np.zeros_like(L_s)
    Rs = np.nan_to_num(Rh, nan=lo)
    for j, Rj in enumerate(layers):
        if len(layers) == 1:
            wj = np.ones_like(Rs)
        else:            # hat weights over the range layers
            step = layers[1] - layers[0]
            wj = np.clip(1 - np.abs(Rs - Rj) / step, 0, 1)
            if j == 0:
                wj = np.where(Rs < Rj, 1.0, wj)
            if j == len(layers) - 1:
                wj = np.where(Rs > Rj, 1.0, wj)
        w = max(0.3, fx * kappa * Rj)          # Cauchy-like PSF width, pixels
        rad = int(min(max(3, round(10 * w)), 90))
        yy, xx = np.mgrid[-rad:rad + 1, -rad:rad + 1]
        k = w / (2 * math.pi * (xx * xx + yy * yy + w * w) ** 1.5)
        k /= k.sum()
        img = (src * wj[..., None]).astype(np.float32)
        out += cv2.filter2D(img, -1, k.astype(np.float32), borderType=cv2.BORDER_CONSTANT)
    return out


def sea_water_index(lam_nm) -> np.ndarray:
    """Refractive index of sea water (35 PSU, ~20 C) against air at wavelengths ``lam_nm``: a Cauchy fit of fresh
    water's index, 1.3247 + 3.3e3 / lam^2 - 3.2e7 / lam^4, plus 0.0058 for the salt."""
    lam = np.asarray(lam_nm, float)
    return 1.3247 + 3.3e3 / lam ** 2 - 3.2e7 / lam ** 4 + 0.0058


def port_remap(img: np.ndarray, cam: CameraModel, level: str) -> np.ndarray:
    """A flat port (thin, at the entrance pupil) in front of a camera whose pinhole model was calibrated in water:
    Snell's law per channel at the channel's wavelength (the recorded pixel at normalized radius t sees what the
    pinhole puts at ``t / sqrt(1 + (n^2 - 1) t^2)``). Strong: uncorrected. Mild: the images rectified by a
    calibration that fitted one radial coefficient (Brown's k1) to the green channel's distortion over the inner
    half of the radius: what is left is the higher orders towards the corners and the colour."""
    import cv2

    xt = ((np.arange(cam.width) - cam.cx) / cam.fx)[None, :]
    yt = ((np.arange(cam.height) - cam.cy) / cam.fy)[:, None]
    t2 = xt * xt + yt * yt
    n = sea_water_index(LAMBDA_NM)
    scale = np.ones_like(t2)
    if level == "mild":
        # the calibration's k1, fitted where its target was seen (radii up to half the corner's): recorded radius
        # ~ t (1 + k1 t^2); beyond, Snell's higher orders remain (pincushion)
        tt = np.linspace(0.0, 0.5 * math.sqrt(float(t2.max())), 200)
        c = n[1] ** 2 - 1
        rec = tt / np.sqrt(1 - np.minimum(c * tt * tt, 0.95))
        k1 = float(np.sum((rec - tt) * tt ** 3) / np.sum(tt ** 6))
        scale = 1.0 + k1 * t2               # rectified pixel at t samples the recording at t (1 + k1 t^2)
    t2r = t2 * scale * scale                # the recording's radius where the rectified pixel at t samples it
    out = np.empty_like(img)
    for ch in range(3):
        s = scale / np.sqrt(1.0 + (n[ch] ** 2 - 1.0) * t2r)
        mx = (cam.cx + cam.fx * xt * s).astype(np.float32)
        my = (cam.cy + cam.fy * yt * s).astype(np.float32)
        out[..., ch] = cv2.remap(np.ascontiguousarray(img[..., ch], dtype=np.float32), mx, my, cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REPLICATE)
    return out


def vignetting_map(cam: CameraModel, dirs, level: str) -> np.ndarray:
    n_w, n_g = 1.34, 1.5
    m = {"mild": 0.6, "strong": 1.2}[level]
    sin_w = np.sqrt(1 - np.clip(dirs[..., 2], 0, 1) ** 2)
    th_w = np.arcsin(sin_w)
    th_a = np.arcsin(np.clip(n_w * sin_w, 0, 0.999))
    th_g = np.arcsin(np.clip(n_w * sin_w / n_g, 0, 0.999))

    def fresnel_t(n1, t1, n2, t2):
        rs = ((n1 * np.cos(t1) - n2 * np.cos(t2)) / (n1 * np.cos(t1) + n2 * np.cos(t2))) ** 2
        rp = ((n1 * np.cos(t2) - n2 * np.cos(t1)) / (n1 * np.cos(t2) + n2 * np.cos(t1))) ** 2
        return 1 - 0.5 * (rs + rp)

    T = fresnel_t(n_w, th_w, n_g, th_g) * fresnel_t(n_g, th_g, 1.0, th_a)
    T0 = fresnel_t(n_w, 0 * th_w, n_g, 0 * th_w) * fresnel_t(n_g, 0 * th_w, 1.0, 0 * th_w)
    V = np.cos(th_a) ** m * T / T0
    if level == "strong":      # the housing's port ring clips the corners (smooth edge)
        xx = (np.arange(cam.width) - cam.cx)[None, :]
        yy = (np.arange(cam.height) - cam.cy)[:, None]
        r = np.sqrt(xx ** 2 + yy ** 2) / math.hypot(cam.width / 2, cam.height / 2)
        s = np.clip((r - 0.82) / 0.3, 0, 1)
        V = V * (1 - 0.45 * s * s * (3 - 2 * s))
    return V


def snow_field(rng: np.random.Generator, level: str) -> dict:
    dens, dmax = {"mild": (0.4, 6e-3), "strong": (2.0, 10e-3)}[level]
    lo, hi = np.array([-3.3, -2.6, 0.0]), np.array([3.3, 2.6, 4.6])
    n = int(rng.poisson(dens * 1000 * np.prod(hi - lo)))
    X = lo + (hi - lo) * rng.random((n, 3))
    dmin, k = 0.4e-3, 2.5        # n(d) ~ d^-k on [dmin, dmax]: inverse CDF
    u = rng.random(n)
    d = (dmin ** (1 - k) + u * (dmax ** (1 - k) - dmin ** (1 - k))) ** (1 / (1 - k))
    vel = np.array([rng.normal(0, 0.02), -0.002, rng.normal(0, 0.01)]) + rng.normal(0, 0.005, (n, 3))
    return {"X": X, "d": d, "rho": rng.uniform(0.3, 0.8, n), "vel": vel, "lo": lo, "hi": hi}


def add_snow(img, field_, k: int, T, depth, dive: Dive):
    """Composite the lamp-lit particles over ``img`` (H, W, 3, camera radiance); in place-free."""
    cam = dive.camera
    H, W = depth.shape
    lo, hi = field_["lo"], field_["hi"]
    Xp = lo + np.mod(field_["X"] + field_["vel"] * k * dive.dt_s - lo, hi - lo)    # drifting, periodic box
    Xc = Xp @ T[:3, :3].T + T[:3, 3]
    z = Xc[:, 2]
    sel = z > 0.12
    Xc, z = Xc[sel], z[sel]
    dd, rho = field_["d"][sel], field_["rho"][sel]
    u = cam.fx * Xc[:, 0] / z + cam.cx
    v = cam.fy * Xc[:, 1] / z + cam.cy
    inside = (u > -2) & (u < W + 1) & (v > -2) & (v < H + 1)
    ui = np.clip(np.rint(u), 0, W - 1).astype(int)
    vi = np.clip(np.rint(v), 0, H - 1).astype(int)
    inside &= z < depth[vi, ui]          # in front of the surface
    Xc, z, dd, rho, u, v = Xc[inside], z[inside], dd[inside], rho[inside], u[inside], v[inside]
    if len(z) == 0:
        return img
    D = np.linalg.norm(Xc, axis=-1)
    c = dive.c
    E = np.zeros((len(z), 3))
    to_cam = -Xc / D[:, None]
    for lamp in dive.lamps:
        vv = Xc - lamp.pos
        r = np.linalg.norm(vv, axis=-1)
        vh = vv / r[:, None]
        lit = 0.5 * (1 + (-vh * to_cam).sum(-1))      # lit fraction of the sphere seen from the camera
        E += (lamp.profile(vh @ lamp.axis) * lit / (r * r))[:, None] * lamp.rgb * np.exp(-c * r[:, None])
    L = rho[:, None] / math.pi * E * np.exp(-c * D[:, None])
    s = cam.fx * dd / D                                       # projected diameter, px
    blur = cam.fx * dive.aperture_m * np.abs(D - dive.focus_m) / (D * dive.focus_m)   # defocus circle, px
    sig = np.sqrt((s / 4) ** 2 + (blur / 4) ** 2 + 0.3 ** 2)
    area = math.pi * s * s / 4                                # px^2 covered
    edges = np.array([0, 0.5, 0.8, 1.2, 1.8, 2.7, 4, 6, 9, 14, 1e9])
    cover = np.zeros((H, W))
    energy = np.zeros((H, W, 3))
    for i in range(len(edges) - 1):
        m = (sig >= edges[i]) & (sig < edges[i + 1])
        if not m.any():
            continue
        a_img = np.zeros((H, W))
        e_img = np.zeros((H, W, 3))
        x0 = np.floor(u[m]).astype(int)
        y0 = np.floor(v[m]).astype(int)
        fx_, fy_ = u[m] - x0, v[m] - y0
        for ox, oy, wgt in ((0, 0, (1 - fx_) * (1 - fy_)), (1, 0, fx_ * (1 - fy_)), (0, 1, (1 - fx_) * fy_),
                            (1, 1, fx_ * fy_)):
            xx, yy = x0 + ox, y0 + oy
            ok = (xx >= 0) & (xx < W) & (yy >= 0) & (yy < H)
            idx = yy[ok] * W + xx[ok]
            a_img += np.bincount(idx, (wgt * area[m])[ok], minlength=H * W).reshape(H, W)
            for ch in range(3):
                e_img[..., ch] += np.bincount(idx, (wgt * area[m] * L[m, ch])[ok], minlength=H * W).reshape(H, W)
        sg = float(np.median(sig[m]))
        sg = math.sqrt(max(sg * sg - 0.25, 0.0))
        if sg > 0.05:
            a_img = gaussian_filter(a_img, sg)
            e_img = gaussian_filter(e_img, (sg, sg, 0))
        cover += a_img
        energy += e_img
    alpha = np.clip(cover, 0, 1)
    scale = np.where(cover > 1, 1 / np.maximum(cover, 1e-9), 1.0)[..., None]
    return img * (1 - alpha[..., None]) + energy * scale


# ----------------------------------------------------------------------------- camera


def rec709(x):
    x = np.clip(x, 0, 1)
    return np.where(x < 0.018, 4.5 * x, 1.099 * x ** 0.45 - 0.099)


def srgb(x):
    x = np.clip(x, 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def _tone(level: Optional[str]):
    """(wb gains, oetf, pedestal DN) of the camera; None: linear."""
    if level is None:
        return np.ones(3), (lambda x: np.clip(x, 0, None)), 0.0
    if level == "mild":
        return np.array([1.12, 1.0, 1.08]), rec709, 0.0
    return np.array([1.55, 1.0, 1.3]), srgb, 6.0


def _base_noise(lin_dn, rng, gain_e: float = 20.0, read_e: float = 15.0):
    """The camera's ordinary noise at low gain (no effect): Poisson electrons plus read noise; DN."""
    e = rng.poisson(np.clip(lin_dn, 0, None) * gain_e).astype(float) + rng.normal(0, read_e, lin_dn.shape)
    return np.clip(e / gain_e, 0, None)


def _bayer_noise(lin_dn, rng, level: str, fpn: dict):
    """Linear DN image (H, W, 3) -> mosaic, electrons with shot + read noise, demosaic; DN (H, W, 3)."""
    import cv2

    gain_e, read_e = {"mild": (6.0, 5.0), "strong": (2.5, 5.0)}[level]
    H, W, _ = lin_dn.shape
    raw = np.empty((H, W))
    raw[0::2, 0::2] = lin_dn[0::2, 0::2, 0]     # R G / G B
    raw[0::2, 1::2] = lin_dn[0::2, 1::2, 1]
    raw[1::2, 0::2] = lin_dn[1::2, 0::2, 1]
    raw[1::2, 1::2] = lin_dn[1::2, 1::2, 2]
    e = rng.poisson(np.clip(raw, 0, None) * gain_e).astype(float) + rng.normal(0, read_e, raw.shape)
    if level == "strong":
        if "dsnu" not in fpn:
            fpn["dsnu"] = rng.gamma(2.0, 0.5, raw.shape)          # dark-signal fixed pattern, electrons
        e += fpn["dsnu"] + rng.normal(0, 0.8, (H, 1))                # and row noise
    dn = np.clip(e / gain_e, 0, 1023)
    raw16 = np.clip(np.rint(dn * 64), 0, 65535).astype(np.uint16)
    return cv2.cvtColor(raw16, fpn.setdefault("code", _bayer_code())).astype(float) / 64.0


def _bayer_code():
    """The OpenCV demosaic code matching the RGGB layout written above (checked on a flat colour)."""
    import cv2

    img = np.zeros((8, 8, 3))
    img[:] = (200.0, 100.0, 30.0)
    raw = np.empty((8, 8))
    raw[0::2, 0::2], raw[0::2, 1::2], raw[1::2, 0::2], raw[1::2, 1::2] = 200, 100, 100, 30
    for name in ("COLOR_BayerRG2RGB", "COLOR_BayerBG2RGB", "COLOR_BayerGR2RGB", "COLOR_BayerGB2RGB"):
        code = getattr(cv2, name)
        out = cv2.cvtColor(raw.astype(np.uint16), code)[3, 3]
        if np.allclose(out, (200, 100, 30), atol=1):
            return code
    raise RuntimeError("no matching Bayer code")


# ----------------------------------------------------------------------------- the generator


def synth_physical(out, effects: dict, n_frames: int = 8, seed: int = 0, width: int = 640,
                   bs_step: int = 8, return_images: bool = False, twin_out=None, twin_seed: int = 1,
                   noise: bool = True, draws: Optional[dict] = None) -> dict:
    """Write a physically based trial bag; ``effects``: {name: 'mild'|'strong'} from :data:`PHYSICAL_EFFECTS`.

    Returns the truth (not written anywhere): the effects with ``artificial_light`` (always on), the water,
    lamps, ranges and exposure.

    ``twin_out``: also write the same dive (water, lamps, path, exposure, the sensor's fixed pattern) with
    other draws of the particles and the photon / read noise (from ``twin_seed``): what a simulation that
    reproduced everything but the draws would score against the recording. The recording is the same with or
    without its twin.

    ``noise=False``: no photon, read or sensor noise (the image the camera's noise scatters about: what an
    effect changes in a dive is the difference of two such images). ``draws``: the effects whose names seed the
    random draws (the particles' field, the noise; default ``effects``): two dives that differ by one effect
    draw the same particles when given the same ``draws``.
    """
    import cv2

    effects = dict(effects or {})
    bad = [e for e in effects if e not in PHYSICAL_EFFECTS or effects[e] not in LEVELS]
    if bad:
        raise ValueError(f"unknown physical effects / levels: {[(e, effects[e]) for e in bad]}")
    dive = make_dive(seed, n_frames, width)
    rng = np.random.default_rng(99000 + seed * 31 + sum(PHYSICAL_EFFECTS.index(e) * 7 + LEVELS.index(v)
                                                        for e, v in (effects if draws is None else draws).items()))
    cam = dive.camera
    model = load_model()
    if "unmodeled_geometry" in effects:
        clearance = {"mild": 0.7, "strong": 0.25}[effects["unmodeled_geometry"]]
        model = add_seafloor(model, clearance=clearance, seed=seed)
    dirs, xt, yt = _rays(cam)
    snow = snow_field(rng, effects["marine_snow"]) if "marine_snow" in effects else None
    twin_rng = np.random.default_rng([99000 + seed, 77, int(twin_seed)]) if twin_out is not None else None
    snow_twin = snow_field(twin_rng, effects["marine_snow"]) if snow is not None and twin_rng is not None else None
    lin, masks, lin_twin = [], [], []
    with Renderer(model, camera=cam, shading="flat") as ren, \
            Renderer(model, camera=CameraModel.from_fov(384, 384, 110.0), shading="flat") as sren:
        for k, T in enumerate(dive.poses):
            rr = ren.render(T)
            hit = rr.hit
            albedo = rr.rgb.astype(float)
            if "unmodeled_geometry" in effects:
                albedo = np.where((rr.labels == 2)[..., None], 0.7 * albedo, albedo)
            R = np.where(hit, rr.range, np.inf).astype(float)
            P = dirs * np.where(hit, R, 0.0)[..., None]
            N = surface_normals(rr.depth.astype(float), rr.part_ids, hit, cam, xt, yt)
            vis = [lamp_visibility(P, hit, lamp, T, sren) for lamp in dive.lamps]
            L_s = surface_radiance(P, N, albedo, hit, dive, vis)
            Rz = np.where(hit, R, 0.0)[..., None]
            img = L_s * np.exp(-dive.c * Rz)
            if "forward_scatter" in effects:
                img = img + forward_scatter_add(L_s, R, hit, dive, effects["forward_scatter"], cam.fx)
            img = img + backscatter(cam, dirs, R, dive, step=bs_step)
            twin = img if twin_rng is not None else None
            if snow is not None:
                img = add_snow(img, snow, k, T, np.where(hit, rr.depth, np.inf), dive)
                if snow_twin is not None:
                    twin = add_snow(twin, snow_twin, k, T, np.where(hit, rr.depth, np.inf), dive)
            if "port_refraction" in effects:
                img = port_remap(img, cam, effects["port_refraction"])
                twin = None if twin is None else port_remap(twin, cam, effects["port_refraction"])
            if "vignetting" in effects:
                vig = vignetting_map(cam, dirs, effects["vignetting"])[..., None]
                img = img * vig
                twin = None if twin is None else twin * vig
            lin.append(img)
            lin_twin.append(twin)
            masks.append(rr.labels == 1)
    # fixed exposure for the dive: the panel's mean at the closest frame
    wb, oetf, ped = _tone(effects.get("camera_response"))
    closest = int(np.argmin([np.linalg.norm(T[:3, 3]) for T in dive.poses]))
    ref = float((lin[closest] * wb)[masks[closest]].mean(axis=0).max()) if masks[closest].any() else 1.0
    # output DN of a linear value x (0..1 full scale): ped + (255 - ped) * oetf(wb x); solve for the exposure
    y = (dive.target_dn - ped) / (255.0 - ped)
    xs = np.linspace(1e-5, 1, 20001)
    x_ref = float(xs[np.searchsorted(oetf(xs), y)])
    K = x_ref / ref                     # radiance -> fraction of full scale
    fpn: dict = {}
    samples, twins = [], []

    def camera_out(img, r):
        x = img * K
        if noise and "sensor_noise" in effects:
            x = _bayer_noise(x * 255.0, r, effects["sensor_noise"], fpn) / 255.0
        elif noise:     # photons are counted whatever the camera: a low-gain sensor's shot and read noise
            x = _base_noise(x * 255.0, r) / 255.0
        dn = ped + (255.0 - ped) * oetf(np.clip(x * wb, 0, 1))
        img8 = np.clip(np.rint(dn), 0, 255).astype(np.uint8)
        if "compression" in effects:
            q = {"mild": 70, "strong": 25}[effects["compression"]]
            ok, buf = cv2.imencode(".jpg", img8[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, q])
            img8 = np.ascontiguousarray(cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1])
        return img8

    for k, (T, img, twin) in enumerate(zip(dive.poses, lin, lin_twin)):
        stamp = 1_700_000_000_000_000_000 + seed * 10**9 + int(k * dive.dt_s * 1e9)
        samples.append(Sample(stamp, camera_out(img, rng), cam, T, cam.frame_id))
        if twin_rng is not None:        # after the recording's frame: the fixed pattern is the recording's
            twins.append(Sample(stamp, camera_out(twin, twin_rng), cam, T, cam.frame_id))
    write_trial(out, iter(samples), overwrite=True)
    if twin_out is not None:
        write_trial(twin_out, iter(twins), overwrite=True)
    truth = {"effects": {"artificial_light": "always", **effects},
             "water": {"a": dive.a.tolist(), "b": dive.b.tolist(), "c": dive.c.tolist(), "g": dive.g},
             "lamps": [{"pos": l.pos.tolist(), "axis": l.axis.tolist(), "half_angle_deg": math.degrees(l.half_angle),
                        "sharp": l.sharp, "rgb": l.rgb.tolist()} for l in dive.lamps],
             "ranges": [float(np.linalg.norm(T[:3, 3])) for T in dive.poses], "exposure": K,
             "hfov_deg": math.degrees(2 * math.atan(cam.width / 2 / cam.fx))}
    if return_images:
        truth["_images"] = [s.image for s in samples]
    return truth


if __name__ == "__main__":      # quick look: python bench/physical_effects.py OUT_DIR [seed=N] [width=W] [effect=level ...]
    import sys
    import time

    import cv2

    outdir = sys.argv[1] if len(sys.argv) > 1 else "."
    eff = dict(a.split("=") for a in sys.argv[2:])
    seed = int(eff.pop("seed", 0))
    width = int(eff.pop("width", 640))
    t0 = time.perf_counter()
    tr = synth_physical(f"{outdir}/phys.mcap", eff, n_frames=8, seed=seed, width=width, return_images=True)
    print(f"{time.perf_counter() - t0:.1f} s; ranges {np.round(tr['ranges'], 2)}; water c {np.round(tr['water']['c'], 3)}")
    for i, im in enumerate(tr["_images"]):
        cv2.imwrite(f"{outdir}/phys_{i}.png", im[..., ::-1])
