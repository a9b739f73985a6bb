"""Pose error: the recorded pose of the panel is off by a bias (the same all trial) plus per-frame jitter.

The camera actually saw the scene from ``T_true = Delta T_recorded`` with ``Delta = [R(rx, ry, rz) | t]``
acting on points of the recorded camera frame (``X_true = R X_rec + t``; ``(rx, ry, rz)`` a rotation
vector in radians, ``t = (tx, ty, tz)`` metres, optical frame: x right, y down, z forward). Jitter adds
independent zero-mean Gaussian errors of standard deviation ``jitter_t`` (each axis, m) and ``jitter_r``
(each axis, rad) per frame. As a model this is the per-trial pose correction a fitter estimates (the
bias; jitter is set to 0 when fitting).

Rendering at the true pose is approximated by warping the render made at the recorded pose with its own
depth (a fixed-point iteration of the inverse warp, 4 steps, background pixels starting at the
median scene depth): exact for rotations, and for translations
wherever the surface seen at a pixel does not change (everything but a band at depth discontinuities of
the width of the parallax, a few pixels for centimetre errors). Colours are interpolated bilinearly
inside surfaces, labels, depth and normals taken from the nearest pixel; a pixel whose surface point
does not project back onto it (within a pixel) sees what the recorded view did not (image border,
disoccluded background) and becomes water. The simulated camera (:class:`uw_sil.sim.simcam.SimCamera`,
``sim_camera``, ``uw-sil synth``), which renders every frame anyway, renders the corrected pose instead: the
exact view, at no cost. Signature: an edge-aligned residual that shifts with the pose. ``restore`` uses the
corrected geometry (bias only).
"""
from __future__ import annotations

import contextlib
import functools
import threading

import cv2
import numpy as np

from .base import Effect, EffectParam

Z_FAR = 1.0e4


def rotation_matrix(rvec) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))[0]


_CARRY = threading.local()


@contextlib.contextmanager
def carrying_shadows():
    """Within it (this thread), a warped geometry carries the lamps' cast shadows of the geometry it was warped from
    (``carried_from``: that geometry and, per pixel, the source pixel and whether it found one), as the warp
    carries the labels, instead of the lamps testing the warped geometry again
    (:meth:`uw_sil.sim.effects.artificial_light.ArtificialLight._shadows`). For the least-squares fit of a pose
    correction: every evaluation warps the geometry, and the shadow test of each warped view was about 10 of
    the 14 s of a lamp-lit pose refit. An approximation: the lamps move with the camera against the scene, so for
    a correction of a few centimetres the shadows on the surfaces move by a fraction of that."""
    before = getattr(_CARRY, "on", False)
    _CARRY.on = True
    try:
        yield
    finally:
        _CARRY.on = before


def warp_geometry(geom, R: np.ndarray, t: np.ndarray, iterations: int = 4, colour: bool = True):
    """Geometry seen from the camera moved by ``X_true = R X_rec + t`` (see the module docstring). ``colour``
    False: its shape only (depth, range, labels, parts, points; the colour black, the normals made from the depth
    when read), as the finer view of a reduced frame needs it (the lamps' shadow test), made when that view is
    first read."""
    cam = geom.camera
    h, w = geom.shape
    fx, fy, cx, cy = (np.float32(v) for v in (cam.fx, cam.fy, cam.cx, cam.cy))
    xt, yt = geom.xt, geom.yt
    Rt = R.T.astype(np.float32)
    R32 = R.astype(np.float32)
    t32 = np.asarray(t, np.float32)
    depth = geom.depth
    # start background pixels at the median scene depth, so that pixels the object moves into find it
    z_fill = np.float32(np.median(depth[geom.hit])) if geom.hit.any() else np.float32(Z_FAR)
    zt = np.where(geom.hit, depth, z_fill).astype(np.float32)
    depth_flat = depth.ravel()
    for _ in range(iterations):
        # point on the true ray at the current depth estimate, in the recorded frame
        X = zt * xt - t32[0], zt * yt - t32[1], zt - t32[2]
        Xr = [Rt[i, 0] * X[0] + Rt[i, 1] * X[1] + Rt[i, 2] * X[2] for i in range(3)]
        zr = np.maximum(Xr[2], np.float32(1e-6))
        u = fx * Xr[0] / zr + cx
        v = fy * Xr[1] / zr + cy
        iu = np.rint(u).astype(np.int32)
        iv = np.rint(v).astype(np.int32)
        inside = (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h) & (Xr[2] > 0)
        idx = np.clip(iv, 0, h - 1) * w + np.clip(iu, 0, w - 1)           # nearest source pixel (flat)
        zs = np.where(inside, depth_flat.take(idx), np.float32(np.inf))
        hit = np.isfinite(zs)
        zs0 = np.where(hit, zs, np.float32(0))
        Xs = zs0 * (u - cx) / fx, zs0 * (v - cy) / fy, zs0
        Xn = [R32[i, 0] * Xs[0] + R32[i, 1] * Xs[1] + R32[i, 2] * Xs[2] + t32[i] for i in range(3)]
        zt = np.where(hit & (Xn[2] > 0), Xn[2], np.float32(Z_FAR)).astype(np.float32)
    # a correspondence must be consistent: the surface point found projects back onto the pixel (else the
    # pixel sees something the recorded view did not: background)
    zn = np.maximum(Xn[2], np.float32(1e-6))
    back_u = fx * Xn[0] / zn + cx - np.arange(w, dtype=np.float32)[None, :]
    back_v = fy * Xn[1] / zn + cy - np.arange(h, dtype=np.float32)[:, None]
    hit = hit & (Xn[2] > 0) & (np.abs(back_u) < 1.0) & (np.abs(back_v) < 1.0)
    if colour:
        mapx, mapy = u.astype(np.float32), v.astype(np.float32)
        rgb_lin = cv2.remap(geom.rgb, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        cover = cv2.remap(geom.hit.astype(np.float32), mapx, mapy, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT)
        rgb_near = geom.rgb.reshape(-1, 3).take(idx, axis=0)
        rgb = np.where((cover > 0.999)[..., None], rgb_lin, rgb_near)
        rgb[~hit] = 0.0
    else:
        rgb = np.zeros(geom.rgb.shape, np.float32)
    Xn = [np.where(hit, x, np.float32(0)) for x in Xn]
    X = np.stack(Xn, axis=-1).astype(np.float32)
    depth_new = np.where(hit, Xn[2], np.float32(np.inf)).astype(np.float32)
    range_new = np.where(hit, np.sqrt(Xn[0] * Xn[0] + Xn[1] * Xn[1] + Xn[2] * Xn[2]), np.float32(np.inf))
    normals = None
    if colour:
        ns = [geom.normals[..., k].ravel().take(idx) for k in range(3)]
        normals = np.stack([np.where(hit, R32[i, 0] * ns[0] + R32[i, 1] * ns[1] + R32[i, 2] * ns[2], np.float32(0))
                            for i in range(3)], axis=-1).astype(np.float32)
    labels = np.where(hit, geom.labels.ravel().take(idx), 0).astype(np.uint8)
    part_ids = np.where(hit, geom.part_ids.ravel().take(idx), 0).astype(geom.part_ids.dtype)
    pose = None
    if geom.pose is not None:
        D = np.eye(4)
        D[:3, :3] = R
        D[:3, 3] = t
        pose = D @ geom.pose
    # the finer view of a reduced frame (the lamps' shadows) is seen from the moved camera too, when it is read
    fine = geom.finer_view_through(functools.partial(warp_geometry, R=R, t=t, iterations=iterations, colour=False))
    out = geom.replace(rgb=rgb.astype(np.float32), depth=depth_new, range_m=range_new.astype(np.float32),
                       labels=labels, part_ids=part_ids, pose=pose, X=X, normals=normals, fine=fine)
    if colour and getattr(_CARRY, "on", False):
        prev = geom.carried_from
        if prev is None:
            out.carried_from = geom, idx, hit
        else:                           # a warp of a warp: its source pixels in the first view
            src, idx0, hit0 = prev
            out.carried_from = src, idx0.ravel().take(idx), hit & hit0.ravel().take(idx)
    return out


class PoseError(Effect):
    name = "pose_error"
    stage = "geometry"
    invertible = True
    random_per_frame = True
    summary = "recorded pose off by a bias (t, rotation vector) plus per-frame Gaussian jitter"
    params = (
        EffectParam("tx", 0.0, -0.15, 0.15, "m", "translation bias, x (right)"),
        EffectParam("ty", 0.0, -0.15, 0.15, "m", "translation bias, y (down)"),
        EffectParam("tz", 0.0, -0.15, 0.15, "m", "translation bias, z (forward)"),
        EffectParam("rx", 0.0, -0.06, 0.06, "rad", "rotation bias about x (rotation vector)"),
        EffectParam("ry", 0.0, -0.06, 0.06, "rad", "rotation bias about y"),
        EffectParam("rz", 0.0, -0.06, 0.06, "rad", "rotation bias about z"),
        EffectParam("jitter_t", 0.0, 0.0, 0.03, "m", "per-frame translation jitter (std per axis)"),
        EffectParam("jitter_r", 0.0, 0.0, 0.02, "rad", "per-frame rotation jitter (std per axis)"),
    )
    severities = {
        "mild": {"tx": 0.002, "ty": -0.0015, "tz": 0.004, "rx": 0.0, "ry": 0.0004, "rz": 0.0005,
                 "jitter_t": 0.0005, "jitter_r": 0.0001},
        "strong": {"tx": 0.04, "ty": -0.03, "tz": 0.06, "rx": 0.01, "ry": -0.015, "rz": 0.01,
                   "jitter_t": 0.01, "jitter_r": 0.003},
    }

    def draws(self, values):
        return values["jitter_t"] > 0 or values["jitter_r"] > 0

    def correction(self, values, rng=None) -> np.ndarray:
        """4x4 ``Delta`` (``T_true = Delta @ T_recorded``) of these values, with jitter if ``rng`` is given."""
        t = np.array([values["tx"], values["ty"], values["tz"]], float)
        r = np.array([values["rx"], values["ry"], values["rz"]], float)
        if rng is not None and self.draws(values):
            t = t + values["jitter_t"] * rng.standard_normal(3)
            r = r + values["jitter_r"] * rng.standard_normal(3)
        D = np.eye(4)
        D[:3, :3] = rotation_matrix(r)
        D[:3, 3] = t
        return D

    @staticmethod
    def bias_of(D) -> dict:
        """The bias values (``tx`` ... ``rz``) whose :meth:`correction` is the rigid 4x4 ``D``."""
        r = cv2.Rodrigues(np.asarray(D, np.float64)[:3, :3])[0].ravel()
        return {"tx": float(D[0, 3]), "ty": float(D[1, 3]), "tz": float(D[2, 3]),
                "rx": float(r[0]), "ry": float(r[1]), "rz": float(r[2])}

    def apply(self, terms, values, rng):
        D = self.correction(values, rng)
        if np.allclose(D, np.eye(4), atol=0, rtol=0):
            return
        terms.geom = warp_geometry(terms.geom, D[:3, :3], D[:3, 3])
