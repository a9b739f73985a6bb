"""The effects' code as it was before their speed-ups (issue 20, goal 3), kept for the equivalence tests
(``test_effects_equivalence``): the lamps' shadow test (:mod:`uw_sil.sim.effects.artificial_light` at bc1afe9,
verbatim but for the constants it imports) and forward scatter's blur (:mod:`uw_sil.sim.effects.forward_scatter`
at bc1afe9, its method as a function), the seafloor (:class:`OldFloor`); at 2fcbd2c the render's normals from its depth
(:func:`normals_from_depth`, :mod:`uw_sil.sim.model`), the camera noise (:func:`sensor_noise`), the particles'
blur (:class:`OldSnow`) and the lamps' irradiance (:class:`OldLamps`); at 9642fb9 the model's geometry for a set of
geometry effects' values (:func:`prep_for`, :meth:`uw_sil.sim.model.PreparedModel._prep_for`) and the lamps' irradiance
and veil (:class:`LampsBefore`). Slow on purpose; not used by the package."""
import functools
import math
from typing import Optional

import cv2
import numpy as np

from uw_sil.sim.effects.artificial_light import (HG_G, N_S, R0, SHADOW_BIAS, SHADOW_CHUNK, SHADOW_GRID, SHADOW_PX,
                                                 SHADOW_T, SHADOW_THICK, ArtificialLight, LampRig)
from uw_sil.sim.effects.marine_snow import _SIGMA_BINS, Z_MAX, Z_MIN, MarineSnow, _draw, _lit, _placed
from uw_sil.sim.effects.unmodeled_geometry import (SHADE_AMBIENT, TEX_SIZE, TILE, Z_FAR, UnmodeledGeometry, _sample,
                                                   _texture_mean, _texture_mips)
from uw_sil.sim.normals import plane_terms


def _shadow_grid(geom, planes=None) -> dict:
    """What the screen-space shadow test needs, on ``geom.fine`` where there is one: depth map (inf where
    nothing is hit; ``zfin``: 1e6 m there), hit mask, surface points as planes (``planes``: those of ``geom`` where
    already split), part ids, intrinsics, the block size ``sub`` and the hit pixels per block (``hit_blocks``),
    ``floor``: the seafloor's pixels or None, ``bands``: the hit pixels grouped by depth (:func:`_depth_bands`), and
    ``cand``: the points the test keeps for each set of parallax radii, filled as lamps are tested (they depend on
    the lamp only through the radii, so the candidates of a fit share them)."""
    g = geom.fine if geom.fine is not None else geom
    cam = g.camera
    if g is not geom or planes is None:
        planes = [np.ascontiguousarray(g.X[..., k]) for k in range(3)]
    f = g.shape[0] // geom.shape[0]
    h, w = g.shape[0] // f, g.shape[1] // f
    zfin = np.where(g.hit, g.depth, np.float32(1e6)).astype(np.float32)
    floor = g.hit & (g.labels == 2)
    floor = floor if floor.any() else None
    return {"z": np.where(g.hit, g.depth, np.float32(np.inf)).astype(np.float32), "hit": g.hit, "X": planes,
            "zfin": zfin, "floor": floor,
            # what can hide a point of the seafloor: anything but the seafloor (1e6 m there)
            "zsolid": None if floor is None else np.where(floor, np.float32(1e6), zfin),
            "parts": np.ascontiguousarray(g.part_ids), "K": tuple(float(v) for v in (cam.fx, cam.fy, cam.cx, cam.cy)),
            "sub": f, "hit_blocks": g.hit.reshape(h, f, w, f).sum(axis=(1, 3), dtype=np.float32), "cand": {},
            "blocks": {}, "bands": _depth_bands(g.depth, g.hit, floor)}


#: Ratio of the depth bands' edges of the shadow test's pruning (:func:`_depth_bands`).
BAND_RATIO = 1.25


def _depth_bands(z: np.ndarray, hit: np.ndarray, floor) -> list:
    """The hit pixels grouped by depth for the shadow test's pruning: bands ``[z0 q^k, z0 q^(k+1))`` from the nearest
    depth ``z0`` (``q`` = :data:`BAND_RATIO`), each as ``(nearest depth in the band, flat indices, their depth less
    the bias, on the seafloor)``; the points of a band use the parallax radius of its nearest depth
    (:func:`_candidates`)."""
    idx = np.flatnonzero(hit)
    if idx.size == 0:
        return []
    zs = z.ravel()[idx]
    z0 = float(zs.min())
    k = np.floor(np.log(np.maximum(zs / np.float32(z0), 1)) / math.log(BAND_RATIO)).astype(np.int32)
    order = np.argsort(k, kind="stable")
    k, idx = k[order], idx[order]
    cuts = np.flatnonzero(np.diff(k)) + 1
    bands = []
    for part in np.split(np.arange(idx.size), cuts):
        i = idx[part]
        bands.append((float(z.ravel()[i].min()), i, z.ravel()[i] - np.float32(SHADOW_BIAS),
                      None if floor is None else floor.ravel()[i]))
    return bands


#: Block size of the shadow test's pruning erosion for large radii (:func:`_nearest_within`).
PRUNE_BLOCK = 4


def _block_min(z: np.ndarray) -> np.ndarray:
    """The minimum of ``z`` over :data:`PRUNE_BLOCK`-pixel blocks (1e6 beyond the image)."""
    h, w = z.shape
    f = PRUNE_BLOCK
    hb, wb = -(-h // f), -(-w // f)
    pad = np.full((hb * f, wb * f), np.float32(1e6), np.float32)
    pad[:h, :w] = z
    return pad.reshape(hb, f, wb, f).min(axis=(1, 3))


def _nearest_within(z: np.ndarray, r: int, blocks: Optional[np.ndarray] = None) -> tuple:
    """At most the smallest ``z`` within ``r`` pixels (a square window), a lower bound that the shadow test's pruning
    can use as well as the exact minimum (it can only keep more points to test), as ``(map, f)``: pixel ``(v, u)``
    reads ``map[v // f, u // f]``. Radii up to two blocks: the exact minimum (``f`` 1). Above: the minimum over
    :data:`PRUNE_BLOCK`-pixel blocks (``blocks``: :func:`_block_min` of ``z``, where already made), eroded over
    ``ceil(r / block)`` blocks (which covers every pixel within ``r`` of any pixel of a block); 16x fewer pixels to
    erode."""
    f = PRUNE_BLOCK
    if r <= 2 * f:
        return cv2.erode(z, cv2.getStructuringElement(cv2.MORPH_RECT, (2 * r + 1, 2 * r + 1)),
                         borderType=cv2.BORDER_CONSTANT, borderValue=1e6), 1
    rb = -(-r // f)
    return cv2.erode(_block_min(z) if blocks is None else blocks,
                     cv2.getStructuringElement(cv2.MORPH_RECT, (2 * rb + 1, 2 * rb + 1)),
                     borderType=cv2.BORDER_CONSTANT, borderValue=1e6), f


def _parallax_radius(g: dict, lxy: float, z: float) -> int:
    """How far (pixels) from a point at depth ``z`` or deeper the samples of its way to a lamp ``lxy`` from the
    optical axis can project (:func:`_visibility_on`), the image's size where the samples reach the camera."""
    h, w = g["z"].shape
    tmax = float(SHADOW_T[-1])
    gap = z - tmax
    r = max(h, w) if gap <= 0.05 else int(math.ceil(max(g["K"][0], g["K"][1]) * lxy * tmax / (z * gap))) + 2
    return min(r, max(h, w))


def _candidates(g: dict, radii: tuple) -> np.ndarray:
    """Flat indices, ascending, of the points that can be in shadow (:func:`_visibility_on`): those of each depth band
    (``g["bands"]``) with a pixel at least the bias nearer than themselves within the band's radius (``radii``); for
    points of the seafloor a pixel of something else."""
    w = g["z"].shape[1]
    maps = {}
    keep = []
    for (_, i, zb, on_floor), r in zip(g["bands"], radii):
        rows, cols = i // w, i % w

        def near(kind):
            got = maps.get((kind, r))
            if got is None:
                if kind not in g["blocks"]:
                    g["blocks"][kind] = _block_min(g[kind])
                got = maps[kind, r] = _nearest_within(g[kind], r, g["blocks"][kind])
            m, f = got
            return m[rows // f, cols // f]

        ok = near("zfin") < zb
        if on_floor is not None and on_floor.any():
            ok = np.where(on_floor, near("zsolid") < zb, ok)
        keep.append(i[ok])
    return np.sort(np.concatenate(keep)) if keep else np.zeros(0, np.int64)


def _visibility_on(g: dict, L: np.ndarray, prune: bool = True) -> np.ndarray:
    """The shadow test of the module's docstring on one grid (:func:`_shadow_grid`): (H, W) share of the lamp at
    ``L`` seen from each surface point, 1 where nothing is hit.

    Only points that can be in shadow are tested: a point ``X`` at depth ``z`` is shadowed by a surface seen where
    a sample ``t`` along its way to the lamp projects, at least the bias nearer than ``X``; with the lamp in the
    camera's plane (``L_z = 0``) a sample ``d`` nearer than ``X`` projects ``fx |L_xy| d / (z (z - d))`` pixels
    from it, and ``d <= t <= max(SHADOW_T)``, so a point with no pixel at least the bias nearer within that
    radius is lit. The radius falls with ``z``: each band of depths (:func:`_depth_bands`) takes it at its nearest
    depth. The pruning drops only points the test would find lit (``prune=False`` tests every point, for the test
    that checks this).

    A point of the seafloor is not hidden by the seafloor: with the lamp on the camera's side of that plane the
    segment to the lamp stays on that side, and with the lamp below it the floor gets none of the lamp's light
    (Lambert). Its samples are compared with the depth of everything else (the panel, 1e6 m on the floor),
    which also leaves out what rounding to whole pixels would make of the plane at grazing angles."""
    z, hit, X = g["z"], g["hit"], g["X"]
    h, w = z.shape
    fx, fy, cx, cy = g["K"]
    vis = np.ones((h, w), np.float32)
    if not hit.any():
        return vis
    lxy = math.hypot(float(L[0]), float(L[1])) + abs(float(L[2]))     # (L_z: lamps ahead or behind the camera)
    if prune:
        radii = tuple(_parallax_radius(g, lxy, z_lo) for z_lo, *_ in g["bands"])
        memo = g["cand"]            # kept per set of radii (at most 16: 5 MB per 640x480 frame)
        idx = memo.get(radii)
        if idx is None:
            if len(memo) >= 16:
                memo.clear()
            idx = memo[radii] = _candidates(g, radii)
    else:
        idx = np.flatnonzero(hit)
    if idx.size == 0:
        return vis
    Xc = [X[k].ravel()[idx] for k in range(3)]
    D = [np.float32(L[k]) - Xc[k] for k in range(3)]
    dist = np.sqrt(D[0] * D[0] + D[1] * D[1] + D[2] * D[2])
    inv = np.float32(1.0) / np.maximum(dist, np.float32(1e-6))
    for k in range(3):
        D[k] *= inv
    # the depth each point's samples are compared with: a point of the seafloor cannot be hidden by the seafloor
    # (a plane with the lamp on the camera's side; with the lamp below it the floor gets none of its light), so
    # it looks up the depth of what else there is (the second half of ``zz``)
    if g["floor"] is None:
        zz, base = g["zfin"].ravel(), 0
    else:
        zz = np.concatenate([g["zfin"].ravel(), g["zsolid"].ravel()])
        base = g["floor"].ravel()[idx] * np.int64(h * w)
    shadow = np.zeros(idx.size, bool)
    # the samples along the way to the lamp as rows of one array (a few thousand points: one numpy call per
    # operation for all samples instead of one per sample; the same float32 arithmetic), in chunks of rows
    rows = max(1, min(len(SHADOW_T), SHADOW_CHUNK // idx.size))
    for s in range(0, len(SHADOW_T), rows):
        t = SHADOW_T[s:s + rows, None]
        S2 = np.maximum(Xc[2] + t * D[2], np.float32(1e-3))
        u = np.rint((Xc[0] + t * D[0]) / S2 * np.float32(fx) + np.float32(cx))
        v = np.rint((Xc[1] + t * D[1]) / S2 * np.float32(fy) + np.float32(cy))
        ok = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1) & (dist > np.float32(1.5) * t)
        # outside the image, or the lamp itself: no shadow; water reads as far away (1e6 m)
        zq = zz[np.where(ok, v * w + u, 0).astype(np.int64) + base]
        zq += np.float32(SHADOW_BIAS)
        zq += S2 * np.float32(SHADOW_PX / fx)
        shadow |= (ok & (zq < S2) & (zq > S2 - np.float32(SHADOW_THICK - SHADOW_BIAS))).any(axis=0)
    dark = idx[shadow]
    if dark.size == 0:
        return vis
    vis.ravel()[dark] = 0.0
    # soft edges: the mean over the 3x3 pixels of the same surface part, in the box around the shadows
    # (the box's outer ring only feeds the pixels next to it; the image's border pads as another part)
    rows, cols = dark // w, dark % w
    r0, r1 = max(int(rows.min()) - 2, 0), min(int(rows.max()) + 3, h)
    c0, c1 = max(int(cols.min()) - 2, 0), min(int(cols.max()) + 3, w)
    bh, bw = r1 - r0, c1 - c0
    parts = g["parts"][r0:r1, c0:c1]
    hb = hit[r0:r1, c0:c1]
    num = np.zeros((bh, bw), np.float32)
    den = np.zeros((bh, bw), np.float32)
    pv = np.pad(vis[r0:r1, c0:c1], 1)
    pp = np.pad(parts, 1)
    for dv in (0, 1, 2):
        for du in (0, 1, 2):
            same = (pp[dv:dv + bh, du:du + bw] == parts) & hb
            num += np.where(same, pv[dv:dv + bh, du:du + bw], np.float32(0))
            den += same
    soft = np.where(hb, num / np.maximum(den, 1), np.float32(1.0))
    i0, i1 = (1 if r0 > 0 else 0), bh - (1 if r1 < h else 0)
    j0, j1 = (1 if c0 > 0 else 0), bw - (1 if c1 < w else 0)
    vis[r0 + i0:r0 + i1, c0 + j0:c0 + j1] = soft[i0:i1, j0:j1]
    return vis


# ---------------------------------------------------------------------------- forward scatter (bc1afe9)

SIGMA0 = 0.5


def _blur_plane(x: np.ndarray, sigma: float, out=None) -> np.ndarray:
    if sigma <= 3.0:
        return cv2.GaussianBlur(x, (0, 0), sigma, dst=out, borderType=cv2.BORDER_REFLECT)
    h, w = x.shape
    f = int(sigma // 1.5)
    small = cv2.resize(x, (max(1, w // f), max(1, h // f)), interpolation=cv2.INTER_AREA)
    s = float(np.sqrt(max(sigma * sigma - 0.35 * f * f, 0.25 * f * f))) / f
    small = cv2.GaussianBlur(small, (0, 0), s, borderType=cv2.BORDER_REFLECT)
    return cv2.resize(small, (w, h), dst=out, interpolation=cv2.INTER_LINEAR)


def _fs_pos(sigma):
    lin = sigma / np.float32(SIGMA0)
    with np.errstate(divide="ignore"):
        lg = 1 + np.log2(np.maximum(lin, 1e-6))
    return np.where(lin < 1, lin, lg).astype(np.float32)


def _fs_index(pos, n: int) -> tuple:
    j = np.clip(np.floor(pos).astype(np.intp), 0, n - 1)
    f = np.clip(pos - j, 0, 1).astype(np.float32)
    flat = np.arange(j.size, dtype=np.intp).reshape(j.shape)
    return j * j.size + flat, np.minimum(j + 1, n - 1) * j.size + flat, f


def _fs_interp(levels, at):
    lo_i, hi_i, f = at
    lo = levels.ravel()[lo_i]
    return lo + f * (levels.ravel()[hi_i] - lo)


def forward_scatter(D: np.ndarray, r_eff: np.ndarray, fx: float, values: dict) -> None:
    """``ForwardScatter.apply`` on the direct signal ``D`` (3, H, W), in place, with the state ``(r_eff, fx)``."""
    s = 1 - np.exp(-np.float32(values["strength"]) * r_eff)
    sigma = np.float32(fx * values["width"] * 1e-3) * r_eff
    tail = float(values["tail"])
    pos = _fs_pos(sigma)
    pos_t = _fs_pos(4 * sigma)
    top = int(np.ceil(max(pos.max(), pos_t.max() if tail > 0 else 0)))
    at = _fs_index(pos, top + 1)
    at_t = _fs_index(pos_t, top + 1) if tail > 0 else None
    blurred = np.empty_like(D)
    levels = np.empty((top + 1,) + D.shape[1:], D.dtype)
    for c in range(3):
        levels[0] = D[c]
        for k in range(1, top + 1):
            _blur_plane(D[c], SIGMA0 * 2 ** (k - 1), out=levels[k])
        acc = _fs_interp(levels, at)
        if tail > 0:
            acc = (1 - tail) * acc + tail * _fs_interp(levels, at_t)
        blurred[c] = acc
    D += s[None] * (blurred - D)


# ---------------------------------------------------------------------------- the seafloor (bc1afe9)


class OldFloor(UnmodeledGeometry):
    """The seafloor effect with the ``add_floor`` of bc1afe9."""

    def add_floor(self, geom, values, colour: bool = True):
        """``geom`` with the floor in it; ``colour`` False: its shape only (depth, range, labels, parts, points,
        normals; the colour as it was), as the finer view of a reduced frame needs it (the lamps' shadow test), made
        when that view is first read."""
        if geom.pose is None:
            raise ValueError("unmodeled_geometry needs the camera pose T_cam_panel (pass pose=...)")
        T = geom.pose
        R, t = T[:3, :3], T[:3, 3]
        tilt = values["tilt"]
        n_p = np.array([0.0, math.cos(tilt), math.sin(tilt)])
        e1 = np.array([1.0, 0.0, 0.0])
        e2 = np.array([0.0, -math.sin(tilt), math.cos(tilt)])
        p0 = np.array([0.0, values["floor_y"], 0.0])
        n_c = R @ n_p
        p0_c = R @ p0 + t
        num = float(n_c @ p0_c)                # < 0: the camera is above the floor
        if num >= 0:
            return geom
        xt, yt = geom.xt, geom.yt
        den = np.float32(n_c[0]) * xt + np.float32(n_c[1]) * yt + np.float32(n_c[2])
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(den < 0, np.float32(num) / den, np.float32(np.inf)).astype(np.float32)
        sel = (z > 0) & (z < Z_FAR) & (~geom.hit | (z < geom.depth))
        if not sel.any():
            return geom
        zs = z[sel]
        xs = np.broadcast_to(xt, geom.shape)[sel] * zs
        ys = np.broadcast_to(yt, geom.shape)[sel] * zs
        rng_m = np.sqrt(xs * xs + ys * ys + zs * zs)
        rgb = geom.rgb
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
            for L in range(len(mips)):
                m = lev == L
                if not m.any():
                    continue
                img = mips[L]
                S = np.float32(img.shape[0] - 2)
                mx = (tu[m] % 1) * S + np.float32(0.5)           # +1 for the wrap padding, -0.5 for pixel centres
                my = (tv[m] % 1) * S + np.float32(0.5)
                col[m] = _sample(img, mx, my)
            shade = SHADE_AMBIENT + (1 - SHADE_AMBIENT) * max(0.0, -float(n_c[2]))
            if values["contrast"] != 1:
                mean = _texture_mean()
                col = mean + np.float32(values["contrast"]) * (col - mean)
            col = np.clip(col * np.float32(values["albedo"]), 0, 1) * np.float32(shade)

            rgb = geom.rgb.copy()
            rgb[sel] = col
        depth = geom.depth.copy()
        depth[sel] = zs
        rng_arr = geom.range.copy()
        rng_arr[sel] = rng_m
        labels = geom.labels.copy()
        labels[sel] = 2
        part = geom.part_ids.astype(np.uint16, copy=True)
        part[sel] = 0xFFFF
        X = normals = None                     # the shape only: made from the depth when read
        if colour:
            zf = np.where(sel, z, np.float32(0))
            X = np.where(sel[..., None], np.stack([xt * zf, yt * zf, zf], axis=-1), geom.X)
            normals = np.where(sel[..., None], n_c.astype(np.float32), geom.normals)
        # the finer view of a reduced frame (the lamps' shadows) gets the floor too, when it is read
        fine = geom.finer_view_through(functools.partial(self.add_floor, values=dict(values), colour=False))
        return geom.replace(rgb=rgb, depth=depth, range_m=rng_arr, labels=labels, part_ids=part, X=X,
                            normals=normals, fine=fine)


def normals_from_depth(depth, part, hit, camera, xt, yt) -> np.ndarray:
    """Unit normals towards the camera from planar depth (``uw_sil.sim.model._normals_from_depth`` at 2fcbd2c)."""
    w = np.where(hit, np.float32(1.0) / np.where(hit, depth, np.float32(1.0)), np.float32(0.0))
    part = np.where(hit, part, 0)
    mx, my, mz = plane_terms(w, part, camera.fx, camera.fy, xt, yt)
    norm = np.sqrt(mx * mx + my * my + mz * mz)
    ok = hit & (norm > 0)
    safe = np.where(ok, norm, np.float32(1.0))
    n = np.stack([-mx / safe, -my / safe, -mz / safe], axis=-1)
    n[~ok] = 0.0
    n[hit & ~ok] = (0.0, 0.0, -1.0)              # isolated pixels face the camera
    return n.astype(np.float32)


def correlated_normal(rng, shape, sigma_px: float) -> np.ndarray:
    """``uw_sil.sim.effects.sensor_noise.correlated_normal`` at 2fcbd2c."""
    from uw_sil.sim.effects.sensor_noise import white_normal

    n = white_normal(rng, shape)
    if sigma_px <= 0:
        return n
    k = cv2.getGaussianKernel(int(2 * np.ceil(4 * sigma_px) + 1), sigma_px, cv2.CV_32F).ravel()
    scale = np.float32(1.0 / float((k * k).sum()))      # std of blurred white noise is sum(k^2) (separable)
    out = np.empty(n.shape, np.float32)
    for c in range(shape[0]):
        out[c] = cv2.sepFilter2D(n[c], -1, k, k, borderType=cv2.BORDER_REFLECT) * scale
    return out


def sensor_noise(I: np.ndarray, values: dict, rng) -> None:
    """The camera noise on the planar image ``I`` in place (``SensorNoiseEffect.apply`` at 2fcbd2c)."""
    from uw_sil.sim.effects.sensor_noise import fixed_pattern

    if values["fpn"] > 0:
        I *= 1 + np.float32(values["fpn"]) * fixed_pattern(I.shape)
    for kind in ("col", "row"):
        if values[kind] > 0:
            I += np.float32(values[kind] / 255.0) * fixed_pattern(I.shape, kind)
    if rng is None or not (values["shot"] > 0 or values["read"] > 0):
        return
    var = np.clip(I, 0, 1) * np.float32(values["shot"] / 255.0) + np.float32((values["read"] / 255.0) ** 2)
    I += np.sqrt(var) * correlated_normal(rng, I.shape, values["corr"])


class OldSnow(MarineSnow):
    """The marine snow effect with the ``particles`` of 2fcbd2c (every size class blurred over the whole image)."""

    def particles(self, terms, values, rng):
        cam = terms.camera
        h, w = terms.shape
        fx, fy, cx, cy = float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy)
        volume = (Z_MAX ** 3 - Z_MIN ** 3) / 3.0 * (w / fx) * (h / fy)
        lam = values["density"] * volume
        # where the particles are, and the light on them, depend on the density, the seed and the scene, not on
        # the particles' size or brightness: a fit of those (the diagnosis's grid) gets them from memory
        state = _placed.state_key(rng)
        u, v, z, logn = _placed.draw(rng, (lam, h, w), lambda g: _draw(g, lam, h, w))
        if u.size == 0:
            return None
        depth = terms.geom.depth
        a = terms.a.astype(float)
        lamps = None if terms.lamps is None else terms.lamps.light_key
        key = None if state is None else (state, lam, h, w, fx, fy, cx, cy, id(depth), a.tobytes(), lamps)
        placed = _placed.value(key, lambda: _lit(terms, depth, a, u, v, z, (fx, fy, cx, cy)))
        if placed is None:
            return None
        vis, lit, att = placed[:3]
        u, v, z = u[vis], v[vis], z[vis]
        diam = values["size"] * 1e-3 * logn[vis]
        amp = values["brightness"] * lit * att                              # (M, 3) peak radiance
        d_px = fx * diam / z
        sigma = np.maximum(0.5, d_px / 2.8)
        energy = amp * (np.pi / 4.0 * d_px * d_px)[:, None]                  # radiance x area (px^2)
        k = np.clip(np.rint(np.log2(sigma / 0.5)).astype(np.int64), 0, len(_SIGMA_BINS) - 1)
        out = np.zeros((3, h, w), np.float32)
        x0 = np.floor(u).astype(np.int64)
        y0 = np.floor(v).astype(np.int64)
        fx_, fy_ = u - x0, v - y0
        corners = ((0, 0, (1 - fx_) * (1 - fy_)), (1, 0, fx_ * (1 - fy_)), (0, 1, (1 - fx_) * fy_), (1, 1, fx_ * fy_))
        for b in np.unique(k):
            sel = np.nonzero(k == b)[0]
            idx, wts, src = [], [], []
            for dx, dy, wt in corners:                         # bilinear splat: four corners at once
                xx, yy = x0[sel] + dx, y0[sel] + dy
                ok = (xx >= 0) & (xx < w) & (yy >= 0) & (yy < h)
                idx.append((yy * w + xx)[ok])
                wts.append(wt[sel][ok])
                src.append(sel[ok])
            idx, wts, src = np.concatenate(idx), np.concatenate(wts), np.concatenate(src)
            sb = float(_SIGMA_BINS[b])
            for c in range(3):
                plane = np.bincount(idx, weights=energy[src, c] * wts, minlength=h * w).astype(np.float32)
                out[c] += cv2.GaussianBlur(plane.reshape(h, w), (0, 0), sb, borderType=cv2.BORDER_CONSTANT)
        return out


class OldLamps(ArtificialLight):
    """The lamps with the ``_irradiance`` of 2fcbd2c (added into the image per lamp and channel)."""

    def _irradiance(self, st, rig: LampRig, a) -> np.ndarray:
        """(3, H, W) ``E_c`` of the module's formula (power, fill and tint not applied)."""
        h, w = st["hit"].shape
        idx, P = st["hit_idx"], st["on_hit"]
        X, n = P["X"], P["n"]
        E = np.zeros((3, h * w), np.float32)
        for l, wl in rig.weights:
            L, ax = rig.pos[l], rig.axis[l]
            XL = X[0] * L[0] + X[1] * L[1] + X[2] * L[2]
            R2 = P["X2"] - 2 * XL + np.float32(L @ L)
            R = np.sqrt(np.maximum(R2, np.float32(1e-4)))
            cos_t = (X[0] * ax[0] + X[1] * ax[1] + X[2] * ax[2] - np.float32(L @ ax)) / R
            nL = n[0] * L[0] + n[1] * L[1] + n[2] * L[2]
            lamb = np.clip((nL - P["nX"]) / R, 0.0, 1.0)        # n . (L - X) / R
            g = np.float32(wl * R0 * R0) * rig.beam(cos_t) * lamb / (R * R)
            # the shadows of a lamp position rounded to SHADOW_GRID, kept for many positions: a fit's candidates
            # share them
            Lq = np.round(L / np.float32(SHADOW_GRID)) * np.float32(SHADOW_GRID)
            S = self._cached(st, "_S", tuple(map(float, Lq)), lambda: self._visibility(st, Lq), entries=64)
            g *= S.ravel()[idx]
            for c in range(3):
                E[c, idx] += g * np.exp(-np.float32(a[c]) * (R - np.float32(R0)))
        return E.reshape(3, h, w)


def prep_for(self, vals, seed):
    """:meth:`uw_sil.sim.model.PreparedModel._prep_for` of 9642fb9: every geometry prepared from scratch."""
    from uw_sil.sim.effects.base import ModelTerms, effect_rng
    from uw_sil.sim.model import _Prepared

    active = [(k, e) for k, e in self._geo_effects if not e.is_identity(vals[k])]
    if not active:
        if self._base_prep is None:
            self._base_prep = self._covered(_Prepared(self.geom0, self.fog, self._other))
        return self._base_prep
    draws = any(e.draws(vals[k]) for k, e in active) and seed is not None
    key = tuple((k, tuple(vals[k].values())) for k, _ in active) + ((seed,) if draws else ())
    p = self._cache.get(key)
    if p is None:
        terms = ModelTerms(self.geom0, self.camera, np.zeros(3), np.zeros(3), 0.0, self.fog, None, None, None,
                           restoring=seed is None)
        for k, e in active:
            e.apply(terms, vals[k], None if seed is None else effect_rng(seed, e.name))
        p = self._covered(_Prepared(terms.geom, self.fog, self._other))
        if len(self._cache) >= 8:
            self._cache.clear()
        self._cache[key] = p
    return p


class LampsBefore(OldLamps):
    """The lamps with the ``_veil_unit`` of 9642fb9 (every lamp's terms made anew) and :class:`OldLamps`' light on
    surfaces, which 9642fb9's equals bit for bit (``test_the_lamps_irradiance_is_the_one_before_bit_for_bit``)."""

    def _veil_unit(self, st, rig: LampRig, a) -> np.ndarray:
        """(3, H, W) the veil of unit strength."""
        d, s = st["d"], st["s"][:, None, None]
        gh, gw = st["grid"]
        f = np.zeros((3, N_S, gh, gw), np.float32)
        hg_norm = np.float32((1 + HG_G) ** 3)
        for l, wl in rig.weights:
            L, ax = rig.pos[l], rig.axis[l]
            dL = d[0] * L[0] + d[1] * L[1] + d[2] * L[2]             # (gh, gw)
            da = d[0] * ax[0] + d[1] * ax[1] + d[2] * ax[2]
            R2 = s * s - 2 * s * dL + np.float32(L @ L)             # (K, gh, gw): |s d - L|^2
            R = np.sqrt(np.maximum(R2, np.float32(1e-4)))
            cos_t = (s * da - np.float32(L @ ax)) / R
            cos_psi = (dL - s) / R                                  # incoming (s d - L)/R, outgoing -d
            q = np.float32(1 + HG_G * HG_G) - np.float32(2 * HG_G) * cos_psi
            hg = hg_norm / (q * np.sqrt(q))                          # HG(psi) / HG(pi)
            g = np.float32(wl) * rig.beam(cos_t) * hg / R2.clip(1e-4)
            for c in range(3):
                f[c] += g * np.exp(-np.float32(a[c]) * (R + s))
        # cumulative trapezoid along the distances, then into an atlas of distance layers side by side
        # (each padded by one duplicated column, one padded row) for two bilinear lookups per pixel
        inc = (f[:, 1:] + f[:, :-1]) * (np.float32(0.5) * st["ds"])[None, :, None, None]
        inc = np.ascontiguousarray(inc.transpose(1, 2, 3, 0))
        C = np.zeros((N_S, gh, gw, 3), np.float32)
        for k in range(1, N_S):                                     # (np.cumsum is slower here)
            np.add(C[k - 1], inc[k - 1], out=C[k])
        tile = gw + 1
        atlas = np.empty((gh + 1, N_S * tile, 3), np.float32)
        layers = atlas[:gh].reshape(gh, N_S, tile, 3)
        layers[:, :, :gw] = C.transpose(1, 0, 2, 3)
        layers[:, :, gw] = C[:, :, -1].transpose(1, 0, 2)
        atlas[gh] = atlas[gh - 1]
        lo = cv2.remap(atlas, st["mapx_lo"], st["mapy"], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        hi = cv2.remap(atlas, st["mapx_hi"], st["mapy"], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        V = lo + st["frac"] * (hi - lo)
        return np.ascontiguousarray(np.moveaxis(V, 2, 0))
