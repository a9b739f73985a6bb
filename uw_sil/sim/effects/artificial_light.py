"""Vehicle lamps: the scene is lit by lamps next to the camera, not by uniform light.

The base model (and the renderer's shading) assume light that does not depend on where a surface is. At depth the
only light is the vehicle's: lamp ``l`` at ``L_l`` in the camera frame (lamp 1 at ``(offset_x, offset_y,
offset_z)``, lamp 2 mirrored at ``(-offset_x, offset_y, offset_z)``, weights ``1 - balance`` and ``balance``; beam
axes turned towards the optical axis by ``toe_in`` and pitched down by ``tilt``: an ROV's lamps are aimed at the
work area in front of and below the camera, ``(-+sin(toe_in) cos(tilt), sin(tilt), cos(toe_in) cos(tilt))``, y
down). ROVs carry more lamps than a pair: a top light on the frame above the camera and often one below it. With
``cross`` > 0 the rig is a cross: that share of the light comes from a top lamp at ``(0, -cross_y, offset_z)`` and a
bottom lamp at ``(0, cross_y, offset_z)`` (weights ``1 - cross_balance`` and ``cross_balance`` of it), aimed at the
pair's work area ``(0, offset_y + R0 tan(tilt), R0)``; the pair keeps ``1 - cross`` of the light. The lamps sit on
the vehicle's frame, which is rarely the camera's plane: on a toolskid ahead of the camera (``offset_z`` > 0) or on
the top frame behind it (< 0). Over a dive's ranges that moves the inverse-square falloff: from lamps 0.2 m behind
the camera a panel at 1.2 m gets 19 % less light, relative to one at 4 m, than from lamps in the camera's plane
(``(r + 0.2)^-2`` against ``r^-2``), a change with range that no attenuation coefficient takes. Lamps all around the
camera light a facing scene nearly as one lamp at its centre, which a pair alone can only imitate by sitting on the
camera. Lamp ``l`` gives a surface point ``X`` with normal ``n`` the relative irradiance::

    E_c(X) = sum_l w_l P(theta_l) max(0, n . (L_l - X) / R_l) (R0 / R_l)^2 exp(-a_c (R_l - R0))
    P(theta) = exp(-ln 2 (theta / half_angle)^shape)              (beam profile, theta off the lamp axis)

``R_l = |X - L_l|``; ``a_c`` is the base model's attenuation (the lamp->surface path is in the same
water; the camera path is the base model's). ``E`` is relative to a surface facing the lamp on its axis
at ``R0 = 2 m``, so at that distance the base model's brightness and colour are kept and the effect adds
the variation: the radiance becomes ``i' = i * L_c`` with

    L_c = fill + (1 - fill) * power * t_c * E_c

(``fill``: share of uniform light the base model already describes; 1 = no effect; ``t_c``: the lamps'
colour, ``tint_r`` and ``tint_b`` against green, since a white LED's spectrum, warm to cool, seen through the
camera's channels is not the white light the renders assume; 1 = white). The renderer's
headlight shading stays in ``i``: for surfaces tilted away from the optical axis the orientation is
counted in both (documented approximation; on a panel facing the camera the renderer's term is 1).

Cast shadows: a lamp beside the camera lights the surface around a handle or a valve that the camera sees,
but the handle hides the lamp from part of it, so each lamp's term is multiplied by its visibility ``S_l(X)``
(the fill light is not: it has no direction). The shadow test runs in screen space on the camera's own depth
map: points on the segment from ``X`` towards ``L_l`` (1.5 cm to 60 cm from the surface) are projected into
the image, and the point is in shadow when the surface seen there lies in front of the segment by more
than a bias (1 cm plus 0.75 pixel footprints) and less than 30 cm (a thin object far in front of the segment
does not hide it). With the lamps within a metre of the camera the occluders of the panel's relief are in
view, which is what makes the camera's depth map sufficient; what the camera cannot see (the back of an
object) casts no shadow here, and a seafloor does not shadow itself (a plane cannot hide a lamp on the camera's
side from its own points). The binary test is averaged over 3x3 pixels of the same surface (soft edges:
a lamp of a few centimetres); on a reduced frame it runs at twice its resolution (``Geometry.fine``) and is
averaged over each block, since a lever's shadow is a few full-resolution pixels wide (a seafloor the model adds
and a pose it corrects are applied to that view too; the least-squares fit of a pose correction, which warps
the view at every evaluation, carries the shadows of the recorded view through its warps instead:
:func:`uw_sil.sim.effects.pose_error.carrying_shadows`). The lamp positions are
rounded to 5 cm for it, so that the candidates of a fit share their shadows: a lamp housing is 5-10 cm across
(its penumbra is wider than what 2.5 cm of position moves), and at 1.3 m moving the lamp by 2.5 cm in x and y
changed 7 % of the shadows' mass (2-4 % of the panel is in shadow). No parameter: shadows follow from the
geometry and the lamp positions, and they move with the vehicle, which neither a seafloor, nor a backscatter
coefficient, nor a response curve does.

Lamp-lit backscatter (single scattering, the veil in the water, brightest where beams cross the view)::

    V_c(p) = veil * t_c * int_0^{R_c} sum_l w_l P(theta_l) HG(psi) / HG(pi) / R_l(s)^2 exp(-a_c (R_l(s) + s)) ds

along the viewing ray ``s d`` of pixel ``p`` up to the surface (or 12 m in open water), with
Henyey-Greenstein phase ``g = 0.9`` normalized to its backscatter value. The integral is evaluated on a
coarse grid of viewing directions (a quarter of the image's columns, 12-48) and 32 log-spaced distances (cumulative
trapezoid), then interpolated per pixel at its own range (trilinear), so silhouettes stay sharp.

The veil is light of the same lamps, so it cannot be stronger than their light on surfaces allows. Written
in camera units with the lamps' intensity ``I`` on their axis, a Lambertian surface of albedo 1 facing a lamp
at ``R0`` gets ``C I exp(-a R0) / (pi R0^2)`` from it, where the renders give such a surface the value
``i_white = 1`` (:mod:`uw_sil.sim.render`), so ``(1 - fill) power = C I exp(-a R0) / (pi R0^2)``; the
single-scatter veil is ``C b p(pi) I`` times the integral above, so ``veil = C b p(pi) I``. Hence::

    veil <= pi R0^2 (b p(pi))_max exp(a R0) (1 - fill) power

with ``(b p(pi))_max = 0.03 /(m sr)``: particle scattering ``b`` up to 3 /m (a sediment plume; deep water
0.02-0.3) times a backscatter phase value ``p(pi)`` up to 0.01 /sr (Henyey-Greenstein ``g`` 0.85-0.95 gives
0.001-0.0035; ``b_b / b`` 0.01-0.02), and the largest channel's ``a`` (the loosest bound). The model applies
``min(veil, cap)`` (:func:`veil_cap`): lamps that light no surface (``fill`` 1) cast no veil either, and a
glow in the water that their light on the scene cannot explain is not theirs to take (a lit seafloor below
the panel is a surface). Fits of lamp-lit dives from three generators put the ratio at 0-0.05, the bound at
``0.38 exp(a R0)``.

Signature: a smooth multiplicative log-residual on objects, slope about -2 against ln R plus a term in
-a, a hotspot that moves with range (parallax of the offset lamps); additive, lamp-side-skewed light in
open water. Invertible (``restore`` divides by ``L`` with a capped gain and subtracts the veil).
"""
from __future__ import annotations

import math
from typing import Optional

import cv2
import numpy as np

from .base import Effect, EffectParam

R0 = 2.0                   # m, reference distance of the normalization
SHADOW_T = np.geomspace(0.015, 0.6, 24).astype(np.float32)   # m from the surface towards the lamp
SHADOW_BIAS = 0.01         # m, plus SHADOW_PX pixel footprints: no shadow from the surface itself
SHADOW_PX = 0.75
SHADOW_THICK = 0.3         # m, the deepest an occluder is assumed to be
SHADOW_GRID = 0.05         # m, lamp positions rounded for the shadow test (its cache key): a lamp's own size
SHADOW_CHUNK = 1 << 17     # points x samples per array of the shadow test (2-3 MB per float32 temporary)
LAMP_ENTRIES = 8           # lamp positions and axes whose terms are kept: a Jacobian's column moves at most 4 lamps
# veil integrals kept per camera: a Jacobian's (up to 15 that move the lamps or the attenuation), found again by
# the fit's next frame, which the Jacobian reaches after all of them on the one before
VEIL_ENTRIES = 32
HG_G = 0.9                 # Henyey-Greenstein asymmetry of the veil
S_MIN, S_MAX, N_S = 0.02, 12.0, 32
GRID_W = 48
GRID_MIN = 12
LN2 = math.log(2.0)
#: Largest particle scattering coefficient (1/m) times backscatter phase value (1/sr) of the veil's bound
#: (module docstring): b up to 3 /m (a sediment plume), p(pi) up to 0.01 /sr.
B_P_PI_MAX = 0.03


def veil_cap(values: dict, a) -> float:
    """The strongest veil (1/m) the lamps' light on surfaces allows, ``pi R0^2 (b p(pi))_max exp(R0 max(a))
    (1 - fill) power`` (module docstring): 0 when the lamps light no surface."""
    light = (1.0 - float(values["fill"])) * float(values["power"])
    return math.pi * R0 * R0 * B_P_PI_MAX * math.exp(R0 * float(np.max(a))) * max(light, 0.0)


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
    the bias, on the seafloor, their flat indices in the maps of :data:`PRUNE_BLOCK`-pixel blocks)``; the points of a
    band use the parallax radius of its nearest depth (:func:`_candidates`)."""
    idx = np.flatnonzero(hit)
    if idx.size == 0:
        return []
    zs = z.ravel()[idx]
    z0 = float(zs.min())
    # (int16: a stable sort of 16-bit keys is a radix sort, linear; the same order)
    k = np.floor(np.log(np.maximum(zs / np.float32(z0), 1)) / math.log(BAND_RATIO)).astype(np.int16)
    order = np.argsort(k, kind="stable")
    k, idx = k[order], idx[order]
    cuts = np.flatnonzero(np.diff(k)) + 1
    bands = []
    h, w = z.shape
    f = PRUNE_BLOCK
    blocks = ((np.arange(h) // f)[:, None] * -(-w // f) + (np.arange(w) // f)[None, :]).ravel()
    for part in np.split(np.arange(idx.size), cuts):
        i = idx[part]
        bands.append((float(z.ravel()[i].min()), i, z.ravel()[i] - np.float32(SHADOW_BIAS),
                      None if floor is None else floor.ravel()[i],
                      blocks[i]))
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
    # (a minimum is exact in any order: over strided slices, 5x faster than a reduction over two inner axes)
    cols = pad[:, 0::f].copy()
    for k in range(1, f):
        np.minimum(cols, pad[:, k::f], out=cols)
    out = cols[0::f].copy()
    for k in range(1, f):
        np.minimum(out, cols[k::f], out=out)
    return out


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
    maps = {}
    keep = []
    for (_, i, zb, on_floor, ib), r in zip(g["bands"], radii):

        def near(kind):
            got = maps.get((kind, r))
            if got is None:
                if kind not in g["blocks"]:
                    g["blocks"][kind] = _block_min(g[kind])
                got = maps[kind, r] = _nearest_within(g[kind], r, g["blocks"][kind])
            m, f = got
            return m.ravel()[i if f == 1 else ib]

        ok = near("zfin") < zb
        if on_floor is not None and on_floor.any():
            ok = np.where(on_floor, near("zsolid") < zb, ok)
        keep.append(i[ok])
    return np.sort(np.concatenate(keep)) if keep else np.zeros(0, np.int64)


def _padded_depths(g: dict) -> np.ndarray:
    """The shadow test's depths plus the bias in a frame of 1e6 m one pixel wide, flat: ``zfin``, then (with a
    seafloor) ``zsolid`` (made once per grid)."""
    zpad = g.get("zpad")
    if zpad is None:
        h, w = g["z"].shape
        kinds = ("zfin",) if g["floor"] is None else ("zfin", "zsolid")
        zpad = np.full((len(kinds), h + 2, w + 2), np.float32(1e6), np.float32)
        for k, kind in enumerate(kinds):
            zpad[k, 1:-1, 1:-1] = g[kind]
            zpad[k, 1:-1, 1:-1] += np.float32(SHADOW_BIAS)
        zpad = g["zpad"] = zpad.ravel()
    return zpad


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
    # the depth each point's samples are compared with (plus the bias), in a frame of 1e6 m one pixel wide: a sample
    # projected outside the image reads as far away as water does and hides nothing. A point of the seafloor cannot
    # be hidden by the seafloor (a plane with the lamp on the camera's side; with the lamp below it the floor gets
    # none of its light), so it looks up the depth of what else there is (the second half of ``zpad``)
    zpad = _padded_depths(g)
    wp = w + 2
    off = np.float32(wp + 1)                  # (u, v) -> (v + 1) wp + u + 1
    if g["floor"] is not None:
        off = np.where(g["floor"].ravel()[idx], np.float32((h + 2) * wp), np.float32(0)) + off
    # a sample at most 2/3 of the way to the lamp (the lamp itself hides nothing): only where a point is that near
    near_lamp = bool((dist <= np.float32(1.5) * SHADOW_T[-1]).any())
    thick = np.float32(SHADOW_THICK - SHADOW_BIAS)
    shadow = np.zeros(idx.size, bool)
    # the samples along the way to the lamp as rows of one array (a few thousand points: one numpy call per
    # operation for all samples instead of one per sample; the same float32 arithmetic), in chunks of rows
    rows = max(1, min(len(SHADOW_T), SHADOW_CHUNK // idx.size))
    for s in range(0, len(SHADOW_T), rows):
        t = SHADOW_T[s:s + rows, None]
        S2 = np.maximum(Xc[2] + t * D[2], np.float32(1e-3))
        u = np.rint((Xc[0] + t * D[0]) / S2 * np.float32(fx) + np.float32(cx))
        v = np.rint((Xc[1] + t * D[1]) / S2 * np.float32(fy) + np.float32(cy))
        np.clip(u, -1, w, out=u)
        np.clip(v, -1, h, out=v)
        v *= np.float32(wp)                   # (whole numbers below 2^24: exact in float32)
        v += u
        v += off
        zq = zpad[v.astype(np.intp)]
        zq += S2 * np.float32(SHADOW_PX / fx)
        hid = zq < S2
        hid &= zq > S2 - thick
        if near_lamp:
            hid &= dist > np.float32(1.5) * t
        shadow |= hid.any(axis=0)
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


class LampRig:
    """Lamp positions, axes, weights and beam of one parameter set (camera optical frame).

    Lamps 0 and 1 are the pair beside the camera; lamps 2 and 3 (when ``cross`` > 0) the top and the bottom lamp
    of the cross, on the camera's vertical at ``(0, -+cross_y, offset_z)``, aimed at the pair's work area ``R0``
    ahead."""

    def __init__(self, values):
        ox, oy, toe, tilt = values["offset_x"], values["offset_y"], values["toe_in"], values["tilt"]
        oz = values["offset_z"]
        sgn = 1.0 if ox >= 0 else -1.0
        st, ct = math.sin(toe), math.cos(toe)
        sp, cp = math.sin(tilt), math.cos(tilt)
        cross, cy, cb = values["cross"], values["cross_y"], values["cross_balance"]
        self.pos = np.array([[ox, oy, oz], [-ox, oy, oz], [0.0, -cy, oz], [0.0, cy, oz]], np.float32)
        ax = [[-sgn * st * cp, sp, ct * cp], [sgn * st * cp, sp, ct * cp]]
        # the cross's lamps aim where the pair's tilt aims at R0 ahead: (0, oy + R0 tan(tilt), R0)
        aim_y = oy + R0 * math.tan(tilt)
        for y in (-cy, cy):
            d = np.array([0.0, aim_y - y, R0 - oz])
            ax.append(list(d / np.linalg.norm(d)))
        self.axis = np.array(ax, np.float32)
        wb = values["balance"]
        pair = [(0, 1.0 - wb), (1, wb)] if wb > 0 else [(0, 1.0)]
        if cross > 0:
            self.weights = [(l, (1.0 - cross) * w) for l, w in pair]
            self.weights += [(l, cross * w) for l, w in ((2, 1.0 - cb), (3, cb)) if w > 0]
        else:
            self.weights = pair
        self.half = np.float32(values["half_angle"])
        self.shape = np.float32(values["shape"])
        self.power = float(values["power"])
        self.fill = float(values["fill"])
        # the lamps' colour against the light the renders assume (white): per-channel gain, green 1
        self.tint = np.array([values["tint_r"], 1.0, values["tint_b"]], np.float32)
        # what the shape of the light depends on (power, fill, veil and tint only scale it)
        self.key = (float(ox), float(oy), float(oz), float(toe), float(tilt), float(values["half_angle"]),
                    float(values["shape"]), float(wb))
        if cross > 0:
            self.key += (float(cross), float(cy), float(cb))
        # what the light on a point (:meth:`irradiance`) depends on
        self.light_key = self.key + (self.power, self.fill, self.tint.tobytes())

    def beam(self, cos_theta):
        theta = np.arccos(np.clip(cos_theta, -1.0, 1.0))
        return np.exp(np.float32(-LN2) * np.power(theta / self.half, self.shape))

    def irradiance(self, X, a) -> np.ndarray:
        """Relative illumination ``fill + (1 - fill) power E`` (M, 3) at points X (M, 3) without a Lambert
        term (particles), capped at 50."""
        X = np.asarray(X, np.float32)
        E = np.zeros((X.shape[0], 3), np.float32)
        for l, wl in self.weights:
            v = X - self.pos[l]
            R = np.maximum(np.linalg.norm(v, axis=1), 0.05)
            g = wl * self.beam((v @ self.axis[l]) / R) * (R0 / R) ** 2
            E += g[:, None] * np.exp(-np.outer(R - R0, a)).astype(np.float32)
        return np.minimum(self.fill + (1 - self.fill) * self.power * E * self.tint[None], 50.0)


class ArtificialLight(Effect):
    name = "artificial_light"
    stage = "radiance"
    invertible = True
    random_per_frame = False
    summary = ("vehicle lamps (a pair, a top and a bottom lamp): beam profile, 1/R^2, exp(-a R_s), Lambert; "
               "lamp-lit backscatter veil")
    params = (
        EffectParam("offset_x", 0.3, -1.5, 1.5, "m", "lamp 1 position right of the camera (lamp 2 at -offset_x)"),
        EffectParam("offset_y", -0.2, -1.0, 1.0, "m", "lamp height in the optical frame (y down: < 0 is above)"),
        EffectParam("offset_z", 0.0, -0.4, 0.4, "m", "lamps ahead of (> 0) or behind (< 0) the camera's plane"),
        EffectParam("toe_in", 0.0, -0.5, 0.8, "rad", "beam axes turned towards the optical axis"),
        EffectParam("tilt", 0.0, -0.6, 0.6, "rad", "beam axes pitched down (y down: > 0 aims below the optical axis)"),
        EffectParam("half_angle", 0.6, 0.15, 1.4, "rad", "beam half width at half maximum"),
        EffectParam("shape", 2.0, 0.5, 8.0, "", "beam profile exponent: exp(-ln2 (theta/half_angle)^shape)"),
        EffectParam("balance", 0.5, 0.0, 0.5, "", "share of lamp 2 (0: one lamp, 0.5: a symmetric pair)"),
        EffectParam("cross", 0.0, 0.0, 0.7, "",
                    "share of the light from a top and a bottom lamp on the camera's vertical (0: the pair alone)"),
        EffectParam("cross_y", 0.4, 0.1, 1.0, "m", "the top and the bottom lamp's distance above and below the camera"),
        EffectParam("cross_balance", 0.0, 0.0, 1.0, "", "the bottom lamp's share of the cross (0: a top lamp only)"),
        EffectParam("power", 1.0, 0.1, 5.0, "", "lamp irradiance relative to the base model's light at 2 m"),
        EffectParam("fill", 1.0, 0.0, 1.0, "", "share of uniform light (1: no lamp effect)"),
        EffectParam("veil", 0.0, 0.0, 0.5, "1/m",
                    "lamp-lit backscatter strength (scattering x lamp radiance); at most veil_cap, what the lamps' "
                    "light on surfaces allows"),
        EffectParam("tint_r", 1.0, 0.5, 2.0, "", "lamp light's red against its green (LED colour; 1: white)"),
        EffectParam("tint_b", 1.0, 0.5, 2.0, "", "lamp light's blue against its green (LED colour; 1: white)"),
    )
    severities = {
        "mild": {"offset_x": 0.35, "offset_y": -0.15, "half_angle": 0.8, "balance": 0.5, "fill": 0.82,
                 "veil": 0.004},
        "strong": {"offset_x": 0.6, "offset_y": -0.3, "toe_in": 0.15, "half_angle": 0.45, "shape": 2.0,
                   "balance": 0.15, "power": 1.0, "fill": 0.0, "veil": 0.05},
    }

    def is_identity(self, values):
        return values["fill"] == 1          # no lamp light on surfaces: no veil either (veil_cap)

    # ------------------------------------------------------------------ per render

    def prepare(self, geom, camera):
        h, w = geom.shape
        hit = geom.hit
        X = geom.X
        n = geom.normals
        st = {"hit": hit, "nohit": ~hit[None]}
        # surface terms as planes: |X - L|^2 = |X|^2 - 2 X.L + |L|^2, n.(X - L) = n.X - n.L; the light on surfaces
        # is computed on the pixels that see one only (the others get no lamp light, :meth:`illumination`)
        st["X"] = [np.ascontiguousarray(X[..., k]) for k in range(3)]
        idx = st["hit_idx"] = np.flatnonzero(hit)
        Xh, nh = [v.ravel()[idx] for v in st["X"]], [n[..., k].ravel()[idx] for k in range(3)]
        # (|X|^2 and n.X on the hit pixels' planes: what an einsum over the whole image gave, bit for bit, 100x faster)
        st["on_hit"] = {"X": Xh, "n": nh, "X2": Xh[0] * Xh[0] + Xh[1] * Xh[1] + Xh[2] * Xh[2],
                        "nX": nh[0] * Xh[0] + nh[1] * Xh[1] + nh[2] * Xh[2]}
        # cast shadows: built on the first shadow test (the geometry, or its finer view, see _shadow_grid)
        st["geom"] = geom
        # veil: a coarse grid of unit viewing directions and log-spaced distances along them
        gw = min(w, GRID_W, max(GRID_MIN, w // 4))     # the veil is smooth: a quarter of the columns suffices
        gh = min(h, max(2, int(round(gw * h / w)))) if h > 1 else 1
        xs = np.linspace(0, w - 1, gw)
        ys = np.linspace(0, h - 1, gh)
        d = np.empty((gh, gw, 3), np.float32)
        d[..., 0] = ((xs - camera.cx) / camera.fx)[None, :]
        d[..., 1] = ((ys - camera.cy) / camera.fy)[:, None]
        d[..., 2] = 1.0
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        st["d"] = [np.ascontiguousarray(d[..., k]) for k in range(3)]
        s = np.geomspace(S_MIN, S_MAX, N_S).astype(np.float32)
        st["s"] = s
        st["ds"] = np.diff(s)
        # per-pixel position in the (direction grid, distance) volume, for trilinear lookup
        r = np.where(hit, geom.range, np.float32(S_MAX))
        ls = np.log(np.clip(r, S_MIN, S_MAX)) - math.log(S_MIN)
        pos = ls / (math.log(S_MAX / S_MIN) / (N_S - 1))
        j = np.clip(np.floor(pos).astype(np.int32), 0, N_S - 2)
        st["frac"] = np.clip(pos - j, 0, 1).astype(np.float32)[..., None]
        ug = (np.arange(w, dtype=np.float32) * ((gw - 1) / max(w - 1, 1)))[None, :]
        vg = (np.arange(h, dtype=np.float32) * ((gh - 1) / max(h - 1, 1)))[:, None]
        tile = gw + 1
        st["mapx_lo"] = (j * tile + ug).astype(np.float32)
        st["mapx_hi"] = ((j + 1) * tile + ug).astype(np.float32)
        st["mapy"] = np.broadcast_to(vg, (h, w)).astype(np.float32)
        st["grid"] = (gh, gw)
        # what the veil's grid depends on (its integral, kept in st["camera"], shared by geometries of this camera)
        st["camera_key"] = (h, w, float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy))
        st["camera"] = {}
        return st

    # ------------------------------------------------------------------ per parameter set

    # A fit evaluates many parameter sets on one render; power, fill, veil and tint only scale the light, so the
    # forward-difference Jacobian of a least-squares fit (one column per parameter) needs the light's shape for
    # only the columns that move the lamps or the attenuation: the last shapes are kept per render (LRU).
    cache_entries = 8
    CACHE_BYTES = 64 << 20

    def _cached(self, st, kind: str, key, compute, entries: Optional[int] = None):
        """``compute()`` (an array or a tuple of arrays, read-only) kept in ``st[kind]`` under ``key`` (LRU)."""
        cache = st.setdefault(kind, {})
        hit = cache.pop(key, None)
        if hit is None:
            hit = compute()
            parts = hit if isinstance(hit, tuple) else (hit,)
            for a in parts:
                a.setflags(write=False)
            nbytes = sum(a.nbytes for a in parts)
            room = min(self.cache_entries if entries is None else entries, self.CACHE_BYTES // max(nbytes, 1))
            while cache and len(cache) >= room:
                cache.pop(next(iter(cache)))         # least recently used first
        if self.cache_entries > 0:
            cache[key] = hit
        return hit

    def illumination(self, st, rig: LampRig, a) -> np.ndarray:
        """(3, H, W) relative illumination ``L`` (1 on pixels without a hit)."""
        key = (rig.key, *map(float, a))
        E = self._cached(st, "_E", key, lambda: self._irradiance(st, rig, a))
        Lc = np.float32(rig.fill) + (np.float32((1 - rig.fill) * rig.power) * rig.tint)[:, None, None] * E
        np.copyto(Lc, np.float32(1.0), where=st["nohit"])
        return Lc

    def _irradiance(self, st, rig: LampRig, a) -> np.ndarray:
        """(3, H, W) ``E_c`` of the module's formula (power, fill and tint not applied)."""
        h, w = st["hit"].shape
        idx = st["hit_idx"]
        Eh = np.zeros((3, idx.size), np.float32)           # on the hit pixels, spread into the image at the end
        for l, wl in rig.weights:
            # a lamp's terms that do not depend on its weight, beam or the attenuation are kept per lamp position and
            # axis, its beam and its attenuation per channel on top (the Jacobian's columns of the weights, the beam,
            # the attenuation and the lamps that another column does not move find them)
            gk = (rig.pos[l].tobytes(), rig.axis[l].tobytes())
            cos_t, lamb, RR, S, Rm = self._cached(st, "_El", gk, lambda: self._lamp_terms(st, rig.pos[l], rig.axis[l]),
                                                  entries=LAMP_ENTRIES)
            B = self._cached(st, "_Eb", gk + (float(rig.half), float(rig.shape)), lambda: rig.beam(cos_t),
                             entries=LAMP_ENTRIES)
            g = np.float32(wl * R0 * R0) * B * lamb / RR
            g *= S
            for c in range(3):
                Eh[c] += g * self._cached(st, "_Ee", gk + (c, float(a[c])), lambda: np.exp(-np.float32(a[c]) * Rm),
                                          entries=3 * LAMP_ENTRIES)
        E = np.zeros((3, h * w), np.float32)
        E[:, idx] = Eh
        return E.reshape(3, h, w)

    def _lamp_terms(self, st, L, ax) -> tuple:
        """A lamp's terms on the hit pixels (:meth:`_irradiance`): ``cos(theta)`` off its axis, the Lambert term,
        ``R^2``, its shadows and ``R - R0``."""
        idx, P = st["hit_idx"], st["on_hit"]
        X, n = P["X"], P["n"]
        XL = X[0] * L[0] + X[1] * L[1] + X[2] * L[2]
        R2 = P["X2"] - 2 * XL + np.float32(L @ L)
        R = np.sqrt(np.maximum(R2, np.float32(1e-4)))
        cos_t = (X[0] * ax[0] + X[1] * ax[1] + X[2] * ax[2] - np.float32(L @ ax)) / R
        nL = n[0] * L[0] + n[1] * L[1] + n[2] * L[2]
        lamb = np.clip((nL - P["nX"]) / R, 0.0, 1.0)        # n . (L - X) / R
        # the shadows of a lamp position rounded to SHADOW_GRID, kept for many positions: a fit's candidates share them
        Lq = np.round(L / np.float32(SHADOW_GRID)) * np.float32(SHADOW_GRID)
        S = self._cached(st, "_S", tuple(map(float, Lq)), lambda: self._shadows(st, Lq), entries=64)
        return cos_t, lamb, R * R, S.ravel()[idx], R - np.float32(R0)

    def _shadows(self, st, L) -> np.ndarray:
        """:meth:`_visibility` of the lamp at ``L``; for a geometry warped with the shadows carried
        (:func:`uw_sil.sim.effects.pose_error.carrying_shadows`), that of the geometry it was warped from at the
        source pixels, tested there once per lamp position for every warp of a fit."""
        carried = st["geom"].carried_from
        if carried is None:
            return self._visibility(st, L)
        src, idx, hit = carried
        own = src.__dict__.setdefault("_lamp_shadows", {"geom": src, "X": None})     # (_shadow_grid makes X)
        vis = self._cached(own, "_S", tuple(map(float, L)), lambda: self._visibility(own, L), entries=64)
        return np.where(hit, vis.ravel()[idx], np.float32(1.0))

    @staticmethod
    def _visibility(st, L) -> np.ndarray:
        """(H, W) share of the lamp at ``L`` seen from each surface point (1 on pixels without a hit): the
        screen-space shadow test of the module's docstring at the shadow grid's resolution, averaged over the hit
        pixels of each block."""
        g = st.get("shadow")
        if g is None:
            g = st["shadow"] = _shadow_grid(st["geom"], st["X"])
        vis = _visibility_on(g, np.asarray(L, np.float32))
        if g["sub"] == 1:
            return vis
        f = g["sub"]
        h, w = g["z"].shape[0] // f, g["z"].shape[1] // f
        if f != 2:
            lit = np.where(g["hit"], vis, np.float32(0)).reshape(h, f, w, f).sum(axis=(1, 3), dtype=np.float32)
            hit = g["hit_blocks"]
            return np.where(hit > 0, lit / np.maximum(hit, 1), np.float32(1.0)).astype(np.float32)
        out = np.ones((h, w), np.float32)
        # only the 2x2 blocks around the shadows are averaged: elsewhere every hit pixel is lit, and the mean is 1
        # (the sum in the order numpy's sum over a whole grid takes, (top pair) + (bottom pair), which it does
        # not keep on a part of one)
        dark = vis < 1
        rows, cols = np.flatnonzero(dark.any(axis=1)), np.flatnonzero(dark.any(axis=0))
        if rows.size == 0:
            return out
        r0, r1, c0, c1 = rows[0] // 2, rows[-1] // 2 + 1, cols[0] // 2, cols[-1] // 2 + 1
        q = np.where(g["hit"][2 * r0:2 * r1, 2 * c0:2 * c1], vis[2 * r0:2 * r1, 2 * c0:2 * c1], np.float32(0))
        lit = (q[0::2, 0::2] + q[0::2, 1::2]) + (q[1::2, 0::2] + q[1::2, 1::2])
        hit = g["hit_blocks"][r0:r1, c0:c1]
        out[r0:r1, c0:c1] = np.where(hit > 0, lit / np.maximum(hit, 1), np.float32(1.0))
        return out

    def veil_field(self, st, rig: LampRig, a, strength: float) -> np.ndarray:
        """(3, H, W) lamp-lit backscatter (linear in ``strength``)."""
        V1 = self._cached(st, "_V", (rig.key, *map(float, a)), lambda: self._veil_unit(st, rig, a))
        return (np.float32(strength) * rig.tint)[:, None, None] * V1

    def share(self, st, shared: dict) -> None:
        # the veil's integral along the viewing directions does not depend on the surfaces, only on the camera:
        # kept for every geometry of a prepared model (a seafloor's height moved in a Jacobian's column) and for the
        # other frames of a fit that share the prepared models' dict (:class:`uw_sil.sim.model.PreparedModel`)
        st["camera"] = shared.setdefault(st["camera_key"], st["camera"])

    def _veil_unit(self, st, rig: LampRig, a) -> np.ndarray:
        """(3, H, W) the veil of unit strength."""
        atlas = self._cached(st["camera"], "_Va", (rig.key, *map(float, a)), lambda: self._veil_atlas(st, rig, a),
                             entries=VEIL_ENTRIES)
        lo = cv2.remap(atlas, st["mapx_lo"], st["mapy"], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        hi = cv2.remap(atlas, st["mapx_hi"], st["mapy"], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        V = lo + st["frac"] * (hi - lo)
        return np.ascontiguousarray(np.moveaxis(V, 2, 0))

    def _veil_atlas(self, st, rig: LampRig, a) -> np.ndarray:
        """The veil's integral on the grid of viewing directions and distances (cumulative trapezoid) as an atlas of
        distance layers side by side (each padded by one duplicated column, one padded row) for two bilinear lookups
        per pixel (:meth:`_veil_unit`)."""
        cam = st["camera"]
        gh, gw = st["grid"]
        f = np.zeros((3, N_S, gh, gw), np.float32)
        for l, wl in rig.weights:
            # per lamp position and axis, beam and attenuation per channel, as the light on surfaces (_irradiance)
            gk = (rig.pos[l].tobytes(), rig.axis[l].tobytes())
            cos_t, hg, R2, Rs = self._cached(cam, "_Vl", gk, lambda: self._veil_lamp(st, rig.pos[l], rig.axis[l]),
                                             entries=LAMP_ENTRIES)
            B = self._cached(cam, "_Vb", gk + (float(rig.half), float(rig.shape)), lambda: rig.beam(cos_t),
                             entries=LAMP_ENTRIES)
            g = np.float32(wl) * B * hg / R2
            for c in range(3):
                f[c] += g * self._cached(cam, "_Ve", gk + (c, float(a[c])), lambda: np.exp(-np.float32(a[c]) * Rs),
                                         entries=3 * LAMP_ENTRIES)
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
        return atlas

    @staticmethod
    def _veil_lamp(st, L, ax) -> tuple:
        """A lamp's terms on the veil's grid (:meth:`_veil_atlas`): ``cos(theta)`` off its axis, the phase
        ``HG(psi) / HG(pi)``, ``|s d - L|^2`` (at least 1e-4) and ``R + s``."""
        d, s = st["d"], st["s"][:, None, None]
        hg_norm = np.float32((1 + HG_G) ** 3)
        dL = d[0] * L[0] + d[1] * L[1] + d[2] * L[2]             # (gh, gw)
        da = d[0] * ax[0] + d[1] * ax[1] + d[2] * ax[2]
        R2 = s * s - 2 * s * dL + np.float32(L @ L)             # (K, gh, gw): |s d - L|^2
        R = np.sqrt(np.maximum(R2, np.float32(1e-4)))
        cos_t = (s * da - np.float32(L @ ax)) / R
        cos_psi = (dL - s) / R                                  # incoming (s d - L)/R, outgoing -d
        q = np.float32(1 + HG_G * HG_G) - np.float32(2 * HG_G) * cos_psi
        hg = hg_norm / (q * np.sqrt(q))                          # HG(psi) / HG(pi)
        return cos_t, hg, R2.clip(1e-4), R + s

    def apply(self, terms, values, rng):
        rig = LampRig(values)
        terms.lamps = rig
        a = terms.a
        st = terms.state[self.name]
        if values["fill"] != 1:
            terms.multiply_illum(self.illumination(st, rig, a))
        veil = min(float(values["veil"]), veil_cap(values, a))
        if veil > 0:
            terms.add_veil(self.veil_field(st, rig, a, veil))
