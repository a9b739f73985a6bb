"""A "foreign" generator of concealed effects for bench_concealed.py, written independently of
uw_sil.sim.effects: other beam and PSF shapes, other noise structure, other values, other trajectories.

It exists so that the diagnosis is not only tested on data made by the same formulas it fits. Each
effect is a function ``effect(ctx) -> None`` editing ``ctx.img`` (float32 (H, W, 3) in 0..1, the
degraded frame before noise) or, for geometry effects, ``ctx.pose_recorded`` / the direct render. The
forms follow the literature (see /work/shared/notes/underwater-effects.md) but deliberately not the
forms of uw_sil.sim.effects:

- artificial_light: two lamps with a Gaussian beam (not cos^n), toe-in, Beer-Lambert on the lamp path,
  1/R^2, normalized to 1 at 2.5 m on the axis, plus a single-scatter lamp veil in the water (ray march).
- forward_scatter: an exponential (Laplacian) PSF, width growing with range, mixed with the direct signal.
- vignetting: cos^n falloff about a point off the principal point.
- sensor_noise: spatially correlated (demosaic-like) Poisson-Gaussian noise plus column fixed pattern.
- marine_snow: Gaussian blobs of random size, brighter and denser near the image centre (lit cone).
- camera_response: tone curve x^(1/g) with a black-level pedestal and white-balance gains.
- backscatter_coefficient: backscatter transmission with its own coefficients (beta_B = k * beta_D).
- unmodeled_geometry: an analytic textured seabed plane below the panel (ray-plane intersection).
- pose_error: recorded pose biased (rotation + translation) with per-frame jitter.
- port_refraction: a Brown-Conrady radial polynomial (k1 r^2 + k2 r^4, not Snell's law) about a centre off the
  principal point, a little stronger in blue.

Trajectory: 4 m to 1.2-1.8 m, yaw up to +-15 deg, pitch up to +-10 deg.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.ndimage import gaussian_filter

from uw_sil.bags.records import Sample
from uw_sil.bags.writer import write_trial
from uw_sil.sim.camera import CameraModel
from uw_sil.sim.optics import degrade
from uw_sil.sim.params import UnderwaterParams
from uw_sil.sim.render import Renderer
from uw_sil.sim.scene import facing_pose

FOREIGN_EFFECTS = ("artificial_light", "forward_scatter", "vignetting", "sensor_noise", "marine_snow",
                   "camera_response", "backscatter_coefficient", "unmodeled_geometry", "pose_error", "port_refraction")


@dataclass
class Ctx:
    img: np.ndarray          # (H, W, 3) float32 0..1
    render: object
    camera: CameraModel
    pose: np.ndarray         # true pose
    params: UnderwaterParams
    rng: np.random.Generator
    k: int
    trial: dict              # per-trial constants (fixed pattern, pose bias ...)


def _rays(cam: CameraModel):
    u = (np.arange(cam.width) - cam.cx) / cam.fx
    v = (np.arange(cam.height) - cam.cy) / cam.fy
    d = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones((1, 1))), axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


# ----------------------------------------------------------------------------- effects


def artificial_light(strength: str):
    sep = 0.45 if strength == "strong" else 0.3          # lamp offset from the camera (m)
    width = math.radians(22.0 if strength == "strong" else 34.0)   # Gaussian beam sigma
    veil = 0.10 if strength == "strong" else 0.03

    def eff(ctx: Ctx):
        cam, rr = ctx.camera, ctx.render
        lamps = [np.array([-sep, -0.12, 0.05]), np.array([sep, -0.12, 0.05])]
        axes = []
        for L in lamps:                                   # toe-in: aim at a point 2.5 m ahead
            a = np.array([0.0, 0.0, 2.5]) - L
            axes.append(a / np.linalg.norm(a))
        c = np.asarray(ctx.params.a, np.float32)
        hit = np.isfinite(rr.range)
        ray = _rays(cam)
        X = ray * np.where(hit, rr.range, 0.0)[..., None]

        def irradiance(P):
            E = np.zeros(P.shape[:-1] + (3,), np.float32)
            for L, ax in zip(lamps, axes):
                d = P - L
                R = np.linalg.norm(d, axis=-1)
                cosang = np.clip((d @ ax) / np.maximum(R, 1e-6), -1, 1)
                ang = np.arccos(cosang)
                prof = np.exp(-0.5 * (ang / width) ** 2)
                E += (prof / np.maximum(R, 0.05) ** 2)[..., None] * np.exp(-np.maximum(R, 0)[..., None] * c)
            return E

        ref = irradiance(np.array([[0.0, 0.0, 2.5]]))[0]
        g = irradiance(X) / ref
        img = ctx.img
        b = np.asarray(ctx.params.b, np.float32)
        # direct term of the frame: img = b + T (i - b); lamps scale i
        T = np.exp(-np.where(hit, rr.range, np.inf)[..., None] * c)
        T = np.where(hit[..., None], T, 0.0)
        direct = T * rr.rgb
        img = img + direct * (np.clip(g, 0, 6) - 1.0)
        # lamp veil: single scatter along each viewing ray up to the surface (or 6 m)
        if veil > 0:
            tmax = np.where(hit, rr.range, 6.0)
            acc = np.zeros_like(img)
            n = 24
            for j in range(n):
                t = (j + 0.5) / n * tmax
                P = ray * t[..., None]
                acc += irradiance(P) / ref * np.exp(-t[..., None] * c) * (tmax / n)[..., None]
            acc /= 6.0
            img = img + veil * acc * (0.5 + b)
        ctx.img = np.clip(img, 0, 1).astype(np.float32)
    return eff


def forward_scatter(strength: str):
    k_px_per_m = 1.1 if strength == "strong" else 0.45       # exponential PSF scale per metre (at 640 px)
    q = 0.75 if strength == "strong" else 0.5

    def eff(ctx: Ctx):
        rr = ctx.render
        hit = np.isfinite(rr.range)
        if not hit.any():
            return
        rmed = float(np.median(rr.range[hit]))
        w = k_px_per_m * rmed * ctx.camera.width / 640.0
        rad = int(max(2, math.ceil(6 * w)))
        yy, xx = np.mgrid[-rad:rad + 1, -rad:rad + 1]
        K = np.exp(-np.hypot(xx, yy) / max(w, 1e-3))
        K /= K.sum()
        b = np.asarray(ctx.params.b, np.float32)
        D = ctx.img - b
        import cv2
        Db = np.stack([cv2.filter2D(D[..., c], -1, K, borderType=cv2.BORDER_REFLECT) for c in range(3)], -1)
        ctx.img = np.clip(b + (1 - q) * D + q * Db, 0, 1).astype(np.float32)
    return eff


def vignetting(strength: str):
    n = 5.0 if strength == "strong" else 2.2

    def eff(ctx: Ctx):
        cam = ctx.camera
        cx, cy = cam.cx + 0.03 * cam.width, cam.cy - 0.02 * cam.height
        u = (np.arange(cam.width) - cx) / cam.fx
        v = (np.arange(cam.height) - cy) / cam.fy
        tan2 = u[None, :] ** 2 + v[:, None] ** 2
        V = (1.0 / (1.0 + tan2)) ** (n / 2.0)           # cos^n of the field angle
        ctx.img = (ctx.img * V[..., None]).astype(np.float32)
    return eff


def port_refraction(strength: str):
    # a flat port's distortion as a calibration toolbox would describe it: Brown-Conrady radial polynomial
    # (not Snell's law), about a centre off the principal point (a decentred port), a little more in blue
    k1, k2 = (0.16, 0.05) if strength == "strong" else (0.04, 0.0)
    colour = (0.97, 1.0, 1.04)

    def eff(ctx: Ctx):
        import cv2

        cam = ctx.camera
        cx, cy = cam.cx - 0.01 * cam.width, cam.cy + 0.015 * cam.height
        x = ((np.arange(cam.width) - cx) / cam.fx)[None, :]
        y = ((np.arange(cam.height) - cy) / cam.fy)[:, None]
        r2 = x * x + y * y
        out = np.empty_like(ctx.img)
        for c in range(3):
            s = 1.0 - colour[c] * (k1 * r2 + k2 * r2 * r2)     # where each recorded pixel samples the pinhole image
            mx = (cx + cam.fx * x * s).astype(np.float32)
            my = (cy + cam.fy * y * s).astype(np.float32)
            out[..., c] = cv2.remap(np.ascontiguousarray(ctx.img[..., c]), mx, my, cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_REPLICATE)
        ctx.img = out
    return eff


def sensor_noise(strength: str):
    alpha = (0.5 if strength == "strong" else 0.18) / 255.0   # shot gain, [0,1] units
    read = (3.0 if strength == "strong" else 1.5) / 255.0
    col = (2.0 if strength == "strong" else 1.0) / 255.0

    def eff(ctx: Ctx):
        cam = ctx.camera
        if "fpn" not in ctx.trial:
            r = np.random.default_rng(12345)
            ctx.trial["fpn"] = (r.standard_normal((1, cam.width, 1)) * col).astype(np.float32)
        img = ctx.img
        sd = np.sqrt(read ** 2 + alpha * np.clip(img, 0, 1))
        w = ctx.rng.standard_normal(img.shape).astype(np.float32)
        w = gaussian_filter(w, (0.7, 0.7, 0))              # demosaic-like correlation
        w /= w.std() + 1e-9
        ctx.img = np.clip(img + sd * w + ctx.trial["fpn"], 0, 1).astype(np.float32)
        ctx.trial["own_noise"] = True
    return eff


def marine_snow(strength: str):
    n = 700 if strength == "strong" else 220

    def eff(ctx: Ctx):
        cam, rng = ctx.camera, ctx.rng
        h, w = cam.height, cam.width
        # denser near the centre: Gaussian placement
        xs = np.clip(rng.normal(w / 2, w / 3.2, n), 0, w - 1)
        ys = np.clip(rng.normal(h / 2, h / 3.2, n), 0, h - 1)
        sig = rng.uniform(0.6, 2.0, n) * w / 640
        amp = rng.uniform(0.08, 0.45, n) * np.exp(-rng.uniform(0.3, 3.0, n) * 0.25)
        layer = np.zeros((h, w), np.float32)
        for x, y, s, a in zip(xs, ys, sig, amp):
            r = int(math.ceil(3 * s))
            x0, x1, y0, y1 = max(0, int(x) - r), min(w, int(x) + r + 1), max(0, int(y) - r), min(h, int(y) + r + 1)
            yy, xx = np.mgrid[y0:y1, x0:x1]
            layer[y0:y1, x0:x1] += a * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * s * s))
        tint = np.array([0.9, 1.0, 1.0], np.float32)
        ctx.img = np.clip(ctx.img + layer[..., None] * tint, 0, 1).astype(np.float32)
    return eff


def camera_response(strength: str):
    g = 1.6 if strength == "strong" else 1.25
    ped = 0.05 if strength == "strong" else 0.02
    wb = np.array([1.15, 1.0, 0.88] if strength == "strong" else [1.06, 1.0, 0.95], np.float32)

    def eff(ctx: Ctx):
        x = np.clip(ctx.img * wb, 0, 1)
        ctx.img = (ped + (1 - ped) * x ** (1.0 / g)).astype(np.float32)
    return eff


def backscatter_coefficient(strength: str):
    k = np.array([0.45, 0.55, 0.6] if strength == "strong" else [0.7, 0.75, 0.8], np.float32)

    def eff(ctx: Ctx):
        rr = ctx.render
        hit = np.isfinite(rr.range)
        a = np.asarray(ctx.params.a, np.float32)
        b = np.asarray(ctx.params.b, np.float32)
        r = np.where(hit, rr.range, 0.0)[..., None]
        TD = np.exp(-r * a) * hit[..., None]
        TB = np.exp(-r * a * k) * hit[..., None]
        # base model frame: b + TD (i - b) (fog ignored in this difference); backscatter with T_B instead
        ctx.img = np.clip(ctx.img + b * (TD - TB), 0, 1).astype(np.float32)
    return eff


def unmodeled_geometry(strength: str):
    drop = 0.35 if strength == "strong" else 0.7       # seabed this far below the panel's lower edge (m)
    alb = 0.55 if strength == "strong" else 0.35

    def eff(ctx: Ctx):
        cam, rr = ctx.camera, ctx.render
        T = ctx.pose
        R, t = T[:3, :3], T[:3, 3]
        # plane y_panel = -0.45 - drop (panel frame y up); in camera frame: n.X = d
        n_p = np.array([0.0, 1.0, 0.0])
        y0 = -0.45 - drop
        n_c = R @ n_p
        d_c = y0 + n_c @ t                                  # n_c.X_c = y0 + n_c.t
        ray = _rays(cam)
        den = ray @ n_c
        with np.errstate(divide="ignore", invalid="ignore"):
            s = d_c / den
        ok = (s > 0) & np.isfinite(s) & ~np.isfinite(rr.range) & (s < 15)
        if not ok.any():
            return
        P = ray * np.where(ok, s, 0)[..., None]
        Pp = (P - t) @ R                                    # into the panel frame
        u, w = Pp[..., 0], Pp[..., 2]
        tex = (0.5 + 0.25 * np.sin(7.1 * u + 2.3 * np.sin(3.3 * w)) * np.cos(5.3 * w)
               + 0.15 * np.sin(23.0 * u + 17.0 * w) + 0.1 * np.sin(41.0 * w - 13 * u))
        col = alb * np.clip(tex, 0.05, 1.0)[..., None] * np.array([1.0, 0.92, 0.75])
        a = np.asarray(ctx.params.a, np.float32)
        b = np.asarray(ctx.params.b, np.float32)
        Tr = np.exp(-np.minimum(s, 1e3)[..., None] * a)        # s is inf where no ray meets the seabed
        floor = b + Tr * (col - b)
        ctx.img = np.where(ok[..., None], floor, ctx.img).astype(np.float32)
    return eff


def pose_error(strength: str):
    bias_deg = 1.6 if strength == "strong" else 0.7
    bias_m = 0.03 if strength == "strong" else 0.012
    jitter_deg = 0.5 if strength == "strong" else 0.2

    def eff(ctx: Ctx):
        if "pose_bias" not in ctx.trial:
            r = np.random.default_rng(777)
            ax = r.normal(size=3)
            ax /= np.linalg.norm(ax)
            tr = r.normal(size=3)
            tr[2] *= 0.3
            tr = bias_m * tr / np.linalg.norm(tr)
            ctx.trial["pose_bias"] = (ax, tr)
        ax, tr = ctx.trial["pose_bias"]
        ang = math.radians(bias_deg) + math.radians(jitter_deg) * ctx.rng.standard_normal()
        Rb = _rotvec(ax * ang)
        Tb = np.eye(4)
        Tb[:3, :3] = Rb
        Tb[:3, 3] = tr + 0.3 * bias_m * ctx.rng.standard_normal(3)
        ctx.trial["pose_recorded"] = Tb @ ctx.pose
    return eff


def _rotvec(v):
    th = np.linalg.norm(v)
    if th < 1e-12:
        return np.eye(3)
    k = v / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


MAKERS = {"artificial_light": artificial_light, "forward_scatter": forward_scatter, "vignetting": vignetting,
          "sensor_noise": sensor_noise, "marine_snow": marine_snow, "camera_response": camera_response,
          "backscatter_coefficient": backscatter_coefficient, "unmodeled_geometry": unmodeled_geometry,
          "pose_error": pose_error, "port_refraction": port_refraction}
# application order: geometry, radiance, medium, direct, sensor
ORDER = ("pose_error", "unmodeled_geometry", "artificial_light", "backscatter_coefficient", "marine_snow",
         "forward_scatter", "port_refraction", "vignetting", "camera_response", "sensor_noise")


def foreign_trajectory(n: int, rng: np.random.Generator, start_m=4.0, end_m=None):
    end_m = float(rng.uniform(1.2, 1.8)) if end_m is None else end_m
    ph = rng.uniform(0, 2 * math.pi, 6)
    yaw_amp = math.radians(rng.uniform(8, 15))
    pitch_amp = math.radians(rng.uniform(5, 10))
    poses = []
    for k in range(n):
        s = k / max(1, n - 1)
        d = start_m + (end_m - start_m) * s ** 0.8
        tt = 2 * math.pi * s
        poses.append(facing_pose(d, x=0.08 * math.sin(1.1 * tt + ph[0]), y=0.05 * math.sin(0.8 * tt + ph[1]),
                                 yaw=yaw_amp * math.sin(0.6 * tt + ph[2]), pitch=pitch_amp * math.sin(0.9 * tt + ph[3]),
                                 roll=math.radians(3.0) * math.sin(0.5 * tt + ph[4])))
    return poses


#: effects whose draws are new in every frame: a twin draws them again
RANDOM_EFFECTS = ("marine_snow", "sensor_noise")


def synth_foreign(out, effects: dict, n_frames: int = 8, seed: int = 0, width: int = 640,
                  params: Optional[UnderwaterParams] = None, twin_out=None, twin_seed: int = 1) -> dict:
    """Write a foreign trial bag; ``effects``: {name: 'mild'|'strong'}. Returns a truth dict (not written
    next to the bag: the diagnosis is blind).

    ``twin_out``: also write the same dive (water, path, lamps, pose errors, fixed patterns) with other draws
    of what is new in every frame (particles, noise; from ``twin_seed``): what a simulation that reproduced
    everything but the draws would score against the recording. The recording is the same with or without
    its twin."""
    rng = np.random.default_rng(1000 + seed)
    if params is None:       # other values than the uw_sil default truth
        params = UnderwaterParams(a=tuple(rng.uniform([0.3, 0.07, 0.05], [0.55, 0.16, 0.12])),
                                  b=tuple(rng.uniform([0.03, 0.22, 0.3], [0.1, 0.38, 0.5])),
                                  rho_f=float(rng.uniform(0.0, 0.1)))
    cam = CameraModel.from_fov(width, width * 3 // 4, float(rng.uniform(62, 78)))
    poses = foreign_trajectory(n_frames, rng)
    effs = [(name, MAKERS[name](effects[name])) for name in ORDER if name in effects]
    trial: dict = {}
    shot = 0.03 / 255.0
    read = 1.2 / 255.0
    samples, twins = [], []
    twin_rng = np.random.default_rng([1000 + seed, 77, int(twin_seed)]) if twin_out is not None else None
    with Renderer(camera=cam) as ren:
        for k, T in enumerate(poses):
            rr = ren.render(T)
            img = degrade(rr.rgb, rr.range, rr.depth, params.as_vector(), fog="exp2")
            ctx = Ctx(img, rr, cam, T, params, rng, k, trial)
            twin = None      # the twin's frame, from the first effect that draws anew in every frame on
            for name, e in effs:
                if twin_rng is not None and twin is None and name in RANDOM_EFFECTS:
                    twin = Ctx(ctx.img.copy(), rr, cam, T, params, twin_rng, k, trial)
                e(ctx)
                if twin is not None:
                    e(twin)
            pose_rec = trial.pop("pose_recorded", T)
            stamp = 1_700_000_000_000_000_000 + seed * 10**9 + k * 10**8
            outs = [(ctx, rng, samples)] + ([(twin or ctx, twin_rng, twins)] if twin_rng is not None else [])
            for c, r, dest in outs:
                img = c.img
                if not trial.get("own_noise"):
                    sd = np.sqrt(read ** 2 + shot * np.clip(img, 0, 1))
                    img = img + sd * r.standard_normal(img.shape).astype(np.float32)
                img8 = np.clip(np.rint(img * 255), 0, 255).astype(np.uint8)
                dest.append(Sample(stamp, img8, cam, pose_rec, cam.frame_id))
    write_trial(out, iter(samples), overwrite=True)
    if twin_out is not None:
        write_trial(twin_out, iter(twins), overwrite=True)
    return {"effects": dict(effects), "params": params.as_dict(), "ranges": [float(np.linalg.norm(T[:3, 3])) for T in poses]}
