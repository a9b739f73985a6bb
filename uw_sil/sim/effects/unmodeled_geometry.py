"""Unmodeled geometry: a seafloor the scene model lacks, seen below and behind the panel.

A plane in the panel frame (y up) at height ``floor_y`` (the plate's bottom edge is at y = -0.35 m;
:func:`uw_sil.sim.scene.add_seafloor` puts it 0.5 m below the model), tilted by ``tilt`` about the panel
x axis (positive: rising towards the front), with the sandy texture of
:func:`~uw_sil.sim.scene.seafloor_texture` (2 m tile), its contrast about the mean colour scaled by
``contrast`` (0: uniform mud) and its albedo by ``albedo``, shaded like the renderer
(``0.3 + 0.7 cos`` of the normal against the optical axis). Intersected analytically with every viewing
ray (needs the pose ``T_cam_panel``); it replaces water pixels and surfaces behind it and gets label 2.
The texture is sampled from a mip level matched to the pixel footprint. (The panel's stand posts of
``add_seafloor`` are not added.) Signature: structure where the simulation says water, growing toward
the image bottom, plus range/colour changes. ``restore`` treats the floor as an object.
"""
from __future__ import annotations

import functools
import math
import threading
import weakref

import cv2
import numpy as np

from .base import Effect, EffectParam

TILE = 2.0          # m per texture repetition
TEX_SIZE = 512
SHADE_AMBIENT = 0.3
Z_FAR = 100.0
FLOOR_ENTRIES = 4   # floors kept per view (:meth:`UnmodeledGeometry.add_floor`)
_mips: tuple = ()
_mips_lock = threading.Lock()
_FLOORS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
_floors_lock = threading.Lock()


def _texture_mips() -> tuple:
    """The texture's mip levels (wrap-padded), finest first: built once per process, and published whole.
    (Built into the module's list by whichever thread came first, two threads simulating their first seafloor
    at once both appended their levels: 14 levels instead of 7, the wrong level for every pixel footprint from
    then on, and a diagnosis whose θ evaluations run on two threads refitted the seafloor to other values than
    on one.)"""
    global _mips
    if not _mips:
        with _mips_lock:
            if not _mips:
                from ..scene import seafloor_texture
                level = seafloor_texture(size=TEX_SIZE, seed=0).astype(np.float32) / 255.0
                levels = []
                while True:
                    levels.append(np.pad(level, ((1, 1), (1, 1), (0, 0)), mode="wrap"))
                    if level.shape[0] <= 8:
                        break
                    level = cv2.resize(level, (level.shape[1] // 2, level.shape[0] // 2),
                                       interpolation=cv2.INTER_AREA)
                _mips = tuple(levels)
    return _mips


def _texture_mean() -> np.ndarray:
    return _texture_mips()[-1][1:-1, 1:-1].reshape(-1, 3).mean(axis=0).astype(np.float32)


def _sample(img, mx, my) -> np.ndarray:
    """Bilinear samples (M, 3) of ``img`` at 1-D pixel coordinates (remap wants 2-D maps < 32767 wide)."""
    m = mx.size
    cols = 1024
    rows = -(-m // cols)
    pad = rows * cols - m
    mx2 = np.pad(mx, (0, pad)).reshape(rows, cols)
    my2 = np.pad(my, (0, pad)).reshape(rows, cols)
    out = cv2.remap(img, mx2, my2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, 3)[:m]


class UnmodeledGeometry(Effect):
    name = "unmodeled_geometry"
    stage = "geometry"
    invertible = True
    random_per_frame = False
    keeps_scene = True             # the seafloor only fills pixels where the scene showed water
    summary = "a textured seafloor plane below the panel (height, tilt, albedo)"
    params = (
        EffectParam("floor_y", -0.85, -5.0, -0.36, "m", "seafloor height in the panel frame (y up)"),
        EffectParam("tilt", 0.0, -0.3, 0.3, "rad", "slope about the panel x axis (> 0 rises towards the front)"),
        EffectParam("albedo", 1.0, 0.02, 1.5, "", "multiplier of the sand texture's albedo (mean ~0.5)"),
        EffectParam("contrast", 1.0, 0.0, 1.5, "", "texture contrast about its mean (0: uniform mud, 1: sand)"),
    )
    severities = {
        "mild": {"floor_y": -5.0, "tilt": 0.0, "albedo": 1.5, "contrast": 0.3},    # far, luminance ~ water
        "strong": {"floor_y": -0.85, "tilt": 0.0, "albedo": 1.0, "contrast": 1.0},  # as add_seafloor
    }

    def is_identity(self, values):
        return False                       # listed = the floor is there

    def shape_key(self, values):
        return values["floor_y"], values["tilt"]       # albedo and contrast change the floor's colour only

    def apply(self, terms, values, rng):
        terms.geom = self.add_floor(terms.geom, values)

    def add_floor(self, geom, values, colour: bool = True):
        """``geom`` with the floor in it; ``colour`` False: its shape only (depth, range, labels, parts, points,
        normals; the colour as it was), as the finer view of a reduced frame needs it (the lamps' shadow test), made
        when that view is first read."""
        if geom.pose is None:
            raise ValueError("unmodeled_geometry needs the camera pose T_cam_panel (pass pose=...)")
        # the floor's pixels, shape and texture samples per view and (height, tilt), kept for the view: the candidates
        # that change only its colour (a least-squares Jacobian's albedo and contrast columns) reuse them
        key = (float(values["floor_y"]), float(values["tilt"]), colour)
        with _floors_lock:
            memo = _FLOORS.setdefault(geom, {})
            floor = memo.get(key, memo)
        if floor is memo:
            floor = self._floor(geom, values["floor_y"], values["tilt"], colour)
            with _floors_lock:
                if len(memo) >= FLOOR_ENTRIES:
                    del memo[next(iter(memo))]
                memo[key] = floor
        if floor is None:
            return geom
        on, depth, rng_arr, labels, part, X, normals, samples, shade = floor
        rgb = geom.rgb
        if colour:
            col = samples
            if values["contrast"] != 1:
                mean = _texture_mean()
                col = mean + np.float32(values["contrast"]) * (col - mean)
            col = np.clip(col * np.float32(values["albedo"]), 0, 1) * np.float32(shade)
            rgb = geom.rgb.copy()
            rgb.reshape(-1, 3)[on] = col
        # the finer view of a reduced frame (the lamps' shadows) gets the floor too, when it is read
        fine = geom.finer_view_through(functools.partial(self.add_floor, values=dict(values), colour=False))
        return geom.replace(rgb=rgb, depth=depth, range_m=rng_arr, labels=labels, part_ids=part, X=X,
                            normals=normals, fine=fine)

    @staticmethod
    def _floor(geom, floor_y, tilt, colour: bool):
        """The floor at height ``floor_y`` and ``tilt`` in ``geom``'s view: its flat pixel indices, the view's depth,
        range, labels, part ids, points and normals with it (``colour``; else None for the last two) and the texture
        samples (M, 3) with the shading (``colour``), or None where the camera does not see it."""
        T = geom.pose
        R, t = T[:3, :3], T[:3, 3]
        n_p = np.array([0.0, math.cos(tilt), math.sin(tilt)])
        e1 = np.array([1.0, 0.0, 0.0])
        e2 = np.array([0.0, -math.sin(tilt), math.cos(tilt)])
        p0 = np.array([0.0, floor_y, 0.0])
        n_c = R @ n_p
        p0_c = R @ p0 + t
        num = float(n_c @ p0_c)                # < 0: the camera is above the floor
        if num >= 0:
            return None
        xt, yt = geom.xt, geom.yt
        den = np.float32(n_c[0]) * xt + np.float32(n_c[1]) * yt + np.float32(n_c[2])
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(den < 0, np.float32(num) / den, np.float32(np.inf)).astype(np.float32)
        sel = (z > 0) & (z < Z_FAR) & (~geom.hit | (z < geom.depth))
        if not sel.any():
            return None
        # (flat indices of the floor's pixels: a gather or a scatter by them is 2-4x faster than by the mask)
        on = np.flatnonzero(sel)
        h, w = geom.shape
        zs = z.ravel()[on]
        xs = xt[0, on % w] * zs
        ys = yt[on // w, 0] * zs
        rng_m = np.sqrt(xs * xs + ys * ys + zs * zs)
        col = shade = None
        if colour:
            # in-plane coordinates of the floor points: P = R^T (X - t), u = P.e1, v = P.e2 (per component:
            # (M, 3) @ (3, 3) products with mixed dtypes are slow in numpy)
            q1 = (R @ e1).astype(np.float32)
            q2 = (R @ e2).astype(np.float32)
            c1, c2 = np.float32(t @ (R @ e1)), np.float32(t @ (R @ e2))
            tu = (xs * q1[0] + ys * q1[1] + zs * q1[2] - c1) * np.float32(1 / TILE)
            tv = -(xs * q2[0] + ys * q2[1] + zs * q2[2] - c2) * np.float32(1 / TILE)
            # mip level from the pixel footprint on the floor
            n32 = n_c.astype(np.float32)
            cos_inc = np.abs(xs * n32[0] + ys * n32[1] + zs * n32[2]) / np.maximum(rng_m, np.float32(1e-6))
            foot = rng_m / (np.float32(geom.camera.fx) * np.maximum(cos_inc, np.float32(0.05)))   # m per pixel
            mips = _texture_mips()
            lev = np.clip(np.rint(np.log2(np.maximum(foot * np.float32(TEX_SIZE / TILE), 1))), 0, len(mips) - 1)
            lev = lev.astype(np.int8)
            col = np.empty((zs.size, 3), np.float32)
            # the texture's wrap: x - floor(x) is x % 1 bit for bit (numpy's remainder of floats: 10x slower)
            tu -= np.floor(tu)
            tv -= np.floor(tv)
            # the points by level (a stable sort of 8-bit keys: a radix sort), each level's a slice
            order = np.argsort(lev, kind="stable")
            cuts = np.searchsorted(lev[order], np.arange(len(mips) + 1))
            for L in range(len(mips)):
                m = order[cuts[L]:cuts[L + 1]]
                if m.size == 0:
                    continue
                img = mips[L]
                S = np.float32(img.shape[0] - 2)
                mx = tu[m] * S + np.float32(0.5)                 # +1 for the wrap padding, -0.5 for pixel centres
                my = tv[m] * S + np.float32(0.5)
                col[m] = _sample(img, mx, my)
            shade = SHADE_AMBIENT + (1 - SHADE_AMBIENT) * max(0.0, -float(n_c[2]))
        depth = geom.depth.copy()
        depth.ravel()[on] = zs
        rng_arr = geom.range.copy()
        rng_arr.ravel()[on] = rng_m
        labels = geom.labels.copy()
        labels.ravel()[on] = 2
        part = geom.part_ids.astype(np.uint16, copy=True)
        part.ravel()[on] = 0xFFFF
        X = normals = None                     # the shape only: made from the depth when read
        if colour:
            X = geom.X.copy()
            Xf = X.reshape(-1, 3)
            for k, v in enumerate((xs, ys, zs)):     # (x_t z, y_t z, z) on the floor, as the points of a depth map
                Xf[on, k] = v
            normals = geom.normals.copy()
            normals.reshape(-1, 3)[on] = n_c.astype(np.float32)
        return on, depth, rng_arr, labels, part, X, normals, col, shade
