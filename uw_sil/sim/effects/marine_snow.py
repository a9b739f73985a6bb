"""Marine snow: sparse bright particles in the water, lit by the vehicle's lamps, new in every frame.

Particles (aggregates of ``size`` mm mean diameter, log-normal spread) are placed uniformly in the
camera's viewing volume between 0.15 m and 4 m at ``density`` per cubic metre (deep sea: 0.1-10 per
litre, of which only the lit, near ones show). A particle in front of the scene adds the light it
scatters towards the camera::

    A_c = brightness * lit_c(X) * exp(-a_c z)                    (peak radiance of its image)

with ``lit`` the lamp irradiance at the particle: the vehicle lamps of ``artificial_light`` when that
effect is active, otherwise a camera-mounted lamp (Gaussian beam, half-angle 0.7 rad, ``1/z^2`` from
1 m, ``exp(-a z)`` on the way out). Its image is a Gaussian blob of the particle's projected size
(at least 0.5 px; smaller particles add proportionally less light), splatted with sub-pixel weights and
blurred per size class (standard deviations 0.5-8 px in octaves; a wider blob is blurred by 8 px). A lens focused
at ``focus`` with an entrance pupil of ``aperture`` mm images a particle at depth ``z`` as a disc of diameter
``fx * aperture * |1/z - 1/focus|`` pixels (thin lens): the near particles of a camera focused on the work area are
the large faint discs of ROV footage, not sharp specks. The disc is taken as a Gaussian of the same second moment
(standard deviation a quarter of the diameter), combined with the particle's own size in quadrature; the light is
conserved, so a defocused particle is fainter. ``aperture`` 0 (the default): a pinhole, every particle in focus.
Particles behind the scene surface are hidden. The light is added to the veil
term, so vignetting and the camera response act on it. Signature: sparse, positive, heavy-tailed
outliers that do not persist between frames, concentrated in the lit volume. Not invertible.
"""
from __future__ import annotations

import cv2
import numpy as np

from .base import Effect, EffectParam, RememberedDraws

Z_MIN, Z_MAX = 0.15, 4.0
MAX_PARTICLES = 200_000
_SIGMA_BINS = np.array([0.5, 1.0, 2.0, 4.0, 8.0], np.float32)


def default_lit(X: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Irradiance (M, 3) of a camera-mounted lamp at points X (M, 3): Gaussian beam, 1/z^2 from 1 m."""
    z = np.maximum(X[:, 2], 1e-3)
    r = np.linalg.norm(X, axis=1)
    theta = np.arccos(np.clip(z / np.maximum(r, 1e-6), -1, 1))
    beam = np.exp(-np.log(2.0) * (theta / 0.7) ** 2)
    return (np.minimum(1.0 / (r * r), 25.0) * beam)[:, None] * np.exp(-np.outer(r, a))


#: Particle draws and their light within :func:`uw_sil.sim.effects.base.remembered_draws` (up to 64 MB).
_placed = RememberedDraws(64 * 2 ** 20)


def _draw(rng, lam: float, h: int, w: int):
    """The particles' number (Poisson, mean ``lam``), image positions, depths and log-normal size factors:
    ``((u, v, z, size_factor), nbytes)``."""
    n = int(min(rng.poisson(lam), MAX_PARTICLES))
    if n == 0:
        e = np.zeros(0)
        return (e, e, e, e), 0
    u = rng.uniform(-0.5, w - 0.5, n)
    v = rng.uniform(-0.5, h - 0.5, n)
    z = np.cbrt(Z_MIN ** 3 + rng.uniform(0, 1, n) * (Z_MAX ** 3 - Z_MIN ** 3))
    logn = rng.lognormal(0.0, 0.5, n)
    return (u, v, z, logn), 4 * 8 * n


def _lit(terms, depth, a, u, v, z, K):
    """Which particles are in front of the scene, the irradiance on them (the lamps', else a camera lamp's) and
    their light's attenuation on the way to the camera: ``((visible, lit, attenuation, depth), nbytes)``, or
    ``(None, 0)`` where none is in front (``depth`` is kept so that its ``id`` in a key stays its own)."""
    fx, fy, cx, cy = K
    h, w = depth.shape
    iu = np.clip(np.rint(u).astype(np.int64), 0, w - 1)
    iv = np.clip(np.rint(v).astype(np.int64), 0, h - 1)
    vis = z < depth[iv, iu]                                  # depth is inf on water
    if not vis.any():
        return None, 0
    u, v, z = u[vis], v[vis], z[vis]
    X = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=1)
    lit = terms.lamps.irradiance(X, a) if terms.lamps is not None else default_lit(X, a)
    att = np.exp(-np.outer(z, a))
    return (vis, lit, att, depth), vis.nbytes + lit.nbytes + att.nbytes


class MarineSnow(Effect):
    name = "marine_snow"
    stage = "medium"
    invertible = False
    random_per_frame = True
    summary = "sparse lit particles between camera and scene, new every frame, brighter/denser in the light"
    params = (
        EffectParam("density", 0.0, 0.0, 3000.0, "1/m^3", "particles per cubic metre of water"),
        EffectParam("brightness", 0.6, 0.0, 3.0, "", "peak radiance of a fully resolved particle at unit irradiance"),
        EffectParam("size", 2.0, 0.3, 10.0, "mm", "mean particle diameter"),
        EffectParam("aperture", 0.0, 0.0, 30.0, "mm", "lens entrance pupil diameter (defocus of particles off the "
                    "focus; 0: in focus)"),
        EffectParam("focus", 2.0, 0.3, 10.0, "m", "distance the lens is focused at"),
    )
    severities = {
        "mild": {"density": 60.0, "brightness": 0.6, "size": 1.5},
        "strong": {"density": 400.0, "brightness": 1.0, "size": 3.0},
    }

    def is_identity(self, values):
        return values["density"] == 0 or values["brightness"] == 0

    def draws(self, values):
        return not self.is_identity(values)

    def apply(self, terms, values, rng):
        if rng is None or self.is_identity(values):
            return
        snow = self.particles(terms, values, rng)
        if snow is not None:
            terms.add_veil(snow)

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
        if values.get("aperture", 0.0) > 0:
            disc = fx * values["aperture"] * 1e-3 * np.abs(1.0 / z - 1.0 / values["focus"])     # blur disc, px
            sigma = np.sqrt(sigma * sigma + (disc / 4.0) ** 2)
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
            tiles = _tiles(idx, h, w, sb)
            for c in range(3):
                plane = np.bincount(idx, weights=energy[src, c] * wts, minlength=h * w).astype(np.float32)
                plane = plane.reshape(h, w)
                if tiles is None:
                    out[c] += cv2.GaussianBlur(plane, (0, 0), sb, borderType=cv2.BORDER_CONSTANT)
                    continue
                for (ty0, ty1, tx0, tx1), (wy0, wy1, wx0, wx1) in tiles:
                    blob = cv2.GaussianBlur(plane[wy0:wy1, wx0:wx1], (0, 0), sb, borderType=cv2.BORDER_CONSTANT)
                    out[c, ty0:ty1, tx0:tx1] += blob[ty0 - wy0:ty1 - wy0, tx0 - wx0:tx1 - wx0]
        return out


#: Side of the tiles in which a size class of few particles is blurred (:func:`_tiles`), pixels.
TILE = 64


def _tiles(idx: np.ndarray, h: int, w: int, sigma: float):
    """Where a size class of few particles (its splats' flat indices ``idx``) needs its blur of ``sigma`` px: the
    :data:`TILE`-pixel tiles within the kernel's reach of a splat, each as ``((y0, y1, x0, x1), window)`` with the
    window the tile and the kernel's reach around it, clipped to the image. Elsewhere the blur of the whole image
    is 0 (+0: the kernel's taps there read zeros only), and on a tile the blur of its window is the whole image's
    (BORDER_CONSTANT: zeros beyond the image either way; within the window the same taps read the same values).
    None where the windows would cover more than a third of the image (the whole image is blurred then)."""
    r = int(4 * sigma) + 2            # beyond OpenCV's reach of the kernel it makes for float32 (its radius ~4 sigma)
    if r >= TILE or idx.size == 0 or 3 * TILE * TILE * idx.size >= 4 * h * w:
        return None
    ys, xs = np.divmod(idx, w)
    ny, nx = -(-h // TILE), -(-w // TILE)
    need = np.zeros((ny, nx), bool)
    need[ys // TILE, xs // TILE] = True
    if 3 * TILE * TILE * np.count_nonzero(need) >= h * w:      # the tiles of the splats alone: too many
        return None
    for yy in (np.maximum(ys - r, 0) // TILE, ys // TILE, np.minimum(ys + r, h - 1) // TILE):
        for xx in (np.maximum(xs - r, 0) // TILE, xs // TILE, np.minimum(xs + r, w - 1) // TILE):
            need[yy, xx] = True                   # (r < TILE: a splat's reach spans at most three tiles per axis)
    tiles = []
    for ty, tx in zip(*np.nonzero(need)):
        y0, y1, x0, x1 = ty * TILE, min((ty + 1) * TILE, h), tx * TILE, min((tx + 1) * TILE, w)
        tiles.append(((y0, y1, x0, x1), (max(y0 - r, 0), min(y1 + r, h), max(x0 - r, 0), min(x1 + r, w))))
    area = sum((b[1] - b[0]) * (b[3] - b[2]) for _, b in tiles)
    return tiles if 3 * area < h * w else None
