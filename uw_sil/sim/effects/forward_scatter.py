"""Forward scatter: range-dependent blur of the direct signal (Jaffe 1990, McGlamery 1980).

Light from a surface point that is scattered through small angles on its way to the camera arrives
spread around the point's image. After McGlamery/Jaffe the forward-scattered part of the direct signal
``D`` at range ``r`` is the fraction ``1 - exp(-strength r)`` (``strength`` ~ the forward part of the
scattering coefficient, ``c - G``), spread by a point-spread function whose angular width grows in
proportion to the range::

    D' = (1 - s) D + s (PSF_w * D),   s = 1 - exp(-strength r),   w = width * r   (angular scale, mrad)
    PSF_w = (1 - tail) G_w + tail J_w

``J_w`` is Jaffe's filter itself, ``F^-1{exp(-B R f)}`` with ``f`` the angular frequency (cycles/rad) and
``B R = 2 pi w``: the two-dimensional Poisson kernel ``J_w(rho) = w / (2 pi (rho^2 + w^2)^(3/2))``, whose
``rho^-3`` tail carries a tenth of the light beyond ten widths (the wide halo of single small-angle scattering
that measured underwater PSFs show). ``G_w`` is the Gaussian of standard deviation ``w`` to which many orders of
small-angle scattering tend (the central limit: the halo gives way to a smooth blur); ``tail`` is the share of
the light in Jaffe's kernel.

The range-varying blur is computed from a few precomputed Gaussian blurs of the whole image at scales
``SIGMA0 2^(k-1)`` pixels (k >= 1; level 0 is the image): ``G_w`` interpolates per pixel between the two levels
around ``w`` in log-scale; ``J_w`` is their sum weighted by the Poisson kernel's Gaussian scale mixture (a
Gaussian whose variance is Levy distributed with scale ``w^2``: the mass of ``sigma <= s`` is
``erfc(w / (sqrt 2 s))``), each level taking the mass of its octave (edges at ``sqrt 2`` times a level's
scale), the widest level (its scale at least the image's size, the image's mean in effect) the mass beyond.
Water pixels (no range) take the range of the nearby object (normalized convolution), so object light spreads
into the water as a halo. Signature: lost edge and high-frequency energy, worse with range, and light spread
from the bright panel into the water around it. Not invertible (a deconvolution).
"""
from __future__ import annotations

import math
import threading

import cv2
import numpy as np

from .base import Effect, EffectParam

SIGMA0 = 0.5            # px, finest precomputed blur
#: Table of ``erfc(2^x)`` on ``x`` in ``[-LUT_LO, LUT_HI]``, ``LUT_STEP`` apart: the mass of Jaffe's kernel below
#: a level's lower edge (erfc(w / (sqrt 2 s)) with w / s = 2^x); beyond its ends it is 1 and 0 (erfc(2^-16) = 1 -
#: 1e-5, erfc(16) = 0 to float32).
LUT_LO, LUT_HI, LUT_STEP = 16.0, 4.0, 1.0 / 512
_ERFC2 = np.array([math.erfc(2.0 ** x) for x in np.arange(-LUT_LO, LUT_HI + LUT_STEP / 2, LUT_STEP)], np.float32)


def _blur_plane(x: np.ndarray, sigma: float, out=None) -> np.ndarray:
    """Gaussian blur of a (H, W) float32 plane; large sigmas through a downsampled copy. ``out``: a
    C-contiguous (H, W) float32 plane to write into."""
    if sigma <= 3.0:
        return cv2.GaussianBlur(x, (0, 0), sigma, dst=out, borderType=cv2.BORDER_REFLECT)
    h, w = x.shape
    f = int(sigma // 1.5)
    small = cv2.resize(x, (max(1, w // f), max(1, h // f)), interpolation=cv2.INTER_AREA)
    s = float(np.sqrt(max(sigma * sigma - 0.35 * f * f, 0.25 * f * f))) / f
    small = cv2.GaussianBlur(small, (0, 0), s, borderType=cv2.BORDER_REFLECT)
    return cv2.resize(small, (w, h), dst=out, interpolation=cv2.INTER_LINEAR)


def _area_mean(ii: np.ndarray, hs: int, ws: int) -> np.ndarray:
    """``cv2.resize(x, (ws, hs), interpolation=INTER_AREA)`` of a (H, W, C) image ``x`` from its integral
    ``ii = cv2.integral(x, sdepth=CV_64F)``: the mean of ``x`` over each output pixel's box, whose edges fall between
    pixels when H / hs or W / ws is not whole (the integral is linear in between). OpenCV's own path for such
    ratios costs 1.2 ms per 640x480 image, this one 0.1-0.5 ms for the wide levels; the two agree to 5e-7."""
    h, w = ii.shape[0] - 1, ii.shape[1] - 1
    sx, sy = w / ws, h / hs

    def edges(n: int, step: float, size: int):
        e = np.arange(n + 1) * step
        i0 = np.minimum(np.floor(e).astype(np.intp), size - 1)
        return i0, e - i0

    x0, fx = edges(ws, sx, w)
    y0, fy = edges(hs, sy, h)
    cx = ii[:, x0] * (1 - fx)[None, :, None] + ii[:, x0 + 1] * fx[None, :, None]
    c = cx[y0] * (1 - fy)[:, None, None] + cx[y0 + 1] * fy[:, None, None]
    box = c[1:, 1:] - c[:-1, 1:] - c[1:, :-1] + c[:-1, :-1]
    return (box * (1.0 / (sx * sy))).astype(np.float32)


def _blur_small(img: np.ndarray, sigma: float, integral: list) -> np.ndarray:
    """The downsampled blur of :func:`_blur_plane` for a sigma above 3 px, of a (H, W, C) image (the channels at
    once), before its resize back: the box means through the image's integral (``integral``: a list of one item,
    made on first use) where the size does not divide."""
    h, w = img.shape[:2]
    f = int(sigma // 1.5)
    hs, ws = max(1, h // f), max(1, w // f)
    if h % hs == 0 and w % ws == 0:
        small = cv2.resize(img, (ws, hs), interpolation=cv2.INTER_AREA)
    else:
        if integral[0] is None:
            integral[0] = cv2.integral(img, sdepth=cv2.CV_64F)
        small = _area_mean(integral[0], hs, ws)
    s = float(np.sqrt(max(sigma * sigma - 0.35 * f * f, 0.25 * f * f))) / f
    return cv2.GaussianBlur(small, (0, 0), s, borderType=cv2.BORDER_REFLECT)


_flat: dict = {}
_scratch = threading.local()


def _buffer(name: str, shape: tuple, dtype=np.float32) -> np.ndarray:
    """A work array of this thread's, kept between calls: a fresh one of the size of the levels' stack
    (13 planes at 640x480, 16 MB) costs its page faults on every frame (the Gaussian blur alone at 640x480: 17 ms
    with fresh arrays, 9 ms with these)."""
    bufs = getattr(_scratch, "bufs", None)
    if bufs is None:
        bufs = _scratch.bufs = {}
    a = bufs.get(name)
    if a is None or a.shape != shape or a.dtype != dtype:
        a = bufs[name] = np.empty(shape, dtype)
    return a


def _flat_index(shape: tuple) -> np.ndarray:
    """``arange(H * W).reshape(H, W)`` (intp, read-only), made once per image size."""
    a = _flat.get(shape)
    if a is None:
        a = np.arange(shape[0] * shape[1], dtype=np.intp).reshape(shape)
        a.setflags(write=False)
        if len(_flat) > 8:
            _flat.clear()
        _flat[shape] = a
    return a


def range_for_blur(geom) -> np.ndarray:
    """Per-pixel range for the blur weights: the range on objects, a smooth fill-in from nearby objects
    on water pixels (normalized Gaussian convolution), the mean object range where none is near."""
    hit = geom.hit
    r = np.where(hit, geom.range, 0).astype(np.float32)
    if not hit.any():
        return r
    h, w = r.shape
    sigma = 0.06 * max(h, w)
    wgt = _blur_plane(hit.astype(np.float32), sigma)
    num = _blur_plane(r, sigma)
    fill = np.where(wgt > 1e-3, num / np.maximum(wgt, 1e-6), float(r[hit].mean()))
    return np.where(hit, r, fill).astype(np.float32)


class ForwardScatter(Effect):
    name = "forward_scatter"
    stage = "direct"
    invertible = False
    random_per_frame = False
    summary = ("range-dependent blur of the direct signal: fraction 1-exp(-strength r), PSF width ~ r (Jaffe's "
               "kernel and a Gaussian)")
    params = (
        EffectParam("strength", 0.0, 0.0, 1.5, "1/m", "forward-scattering coefficient: scattered fraction 1-exp(-strength r)"),
        EffectParam("width", 8.0, 0.5, 40.0, "mrad/m", "angular scale of the PSF per metre of range"),
        EffectParam("tail", 0.3, 0.0, 1.0, "", "share of the PSF in Jaffe's heavy-tailed kernel (the rest: Gaussian)"),
    )
    severities = {
        "mild": {"strength": 0.12, "width": 8.0, "tail": 0.3},
        "strong": {"strength": 0.5, "width": 15.0, "tail": 0.4},
    }

    def is_identity(self, values):
        return values["strength"] == 0

    def prepare(self, geom, camera):
        return range_for_blur(geom), float(camera.fx)

    def apply(self, terms, values, rng):
        r_eff, fx = terms.state[self.name]
        D = terms.D
        s = 1 - np.exp(-np.float32(values["strength"]) * r_eff)                # (H, W)
        w_px = np.float32(fx * values["width"] * 1e-3) * r_eff                   # px: G's sigma and J's scale
        tail = float(values["tail"])
        h, w = D.shape[1:]
        pos = self._pos(w_px)
        if tail > 0:
            u = self._level(w_px)
            n = self._top(h, w) + 1
            # Jaffe's kernel below the lower edge of the level two under its scale: < erfc(4) = 2e-8 of its light
            lowest = min(float(pos.min()) if tail < 1 else np.inf, float(u.min()) - 2)
        else:
            n = int(np.ceil(pos.max())) + 1
            lowest = float(pos.min())
        # only the levels from the lowest one a pixel takes are made (the Gaussian's: the one under its smallest sigma;
        # Jaffe's kernel: two under its smallest scale, up to the image's size)
        k0 = int(min(max(np.floor(lowest), 0), n - 1))
        at = self._index(pos, n, k0) if tail < 1 else None                       # the same for every channel
        wj = self._jaffe_weights(u, n, k0) if tail > 0 else None
        # the wide levels' downsampled blurs of the three channels at once (OpenCV's filters on interleaved channels
        # are 1.5-2.5x faster than three planes), each resized back per channel
        wide = [k for k in range(k0, n) if SIGMA0 * 2 ** (k - 1) > 3.0]
        small = {}
        if wide:
            img = cv2.merge([D[0], D[1], D[2]])
            integral = [None]
            small = {k: cv2.split(_blur_small(img, SIGMA0 * 2 ** (k - 1), integral)) for k in wide}
        blurred = np.empty_like(D)
        levels = _buffer("levels", (n - k0,) + D.shape[1:], D.dtype)
        for c in range(3):
            for k in range(k0, n):
                if k == 0:
                    levels[0] = D[c]
                elif k in small:
                    cv2.resize(small[k][c], (w, h), dst=levels[k - k0], interpolation=cv2.INTER_LINEAR)
                else:
                    _blur_plane(D[c], SIGMA0 * 2 ** (k - 1), out=levels[k - k0])
            if tail < 1:
                acc = self._interp(levels, at)
            if tail > 0:
                j = np.einsum("khw,khw->hw", wj, levels)
                acc = j if tail == 1 else (1 - tail) * acc + tail * j
            blurred[c] = acc
        D += s[None] * (blurred - D)

    @staticmethod
    def _level(w_px):
        """Level index of a scale, not clipped below: ``1 + log2(w / SIGMA0)`` (level k's scale is SIGMA0 2^(k-1))."""
        return (1 + np.log2(np.maximum(w_px, np.float32(1e-6)) / np.float32(SIGMA0))).astype(np.float32)

    @staticmethod
    def _top(h: int, w: int) -> int:
        """The widest level: the first whose scale is at least the image's larger side."""
        return 1 + int(math.ceil(math.log2(max(h, w) / SIGMA0)))

    @staticmethod
    def _jaffe_weights(u, n: int, k0: int) -> np.ndarray:
        """Per pixel, the share of Jaffe's kernel of scale level ``u`` (:meth:`_level`) that each level ``k0..n-1``
        carries, (n - k0, H, W): level k the Levy mixture's mass between its edges ``SIGMA0 2^(k-1) / sqrt 2`` and
        ``sqrt 2`` times that (mass below the lower edge ``erfc(2^(u - k))``), level ``k0`` all below its upper edge,
        the top level all beyond its lower edge."""
        below = _buffer("below", (n - k0 + 1,) + u.shape)              # mass below each level's lower edge
        below[0] = 0.0
        below[-1] = 1.0
        # the table's index of u - k is u's own less k / LUT_STEP (a whole number): rounded once
        i = np.rint((u + np.float32(LUT_LO)) * np.float32(1 / LUT_STEP)).astype(np.intp)
        per = int(round(1 / LUT_STEP))
        for k in range(k0 + 1, n):
            _ERFC2.take(i - per * k, mode="clip", out=below[k - k0])
        return np.subtract(below[1:], below[:-1], out=_buffer("weights", (n - k0,) + u.shape))

    @staticmethod
    def _pos(sigma):
        """Fractional level index of a blur sigma: 0 = no blur, k >= 1 = SIGMA0 * 2^(k-1)."""
        lin = sigma / np.float32(SIGMA0)
        return np.where(lin < 1, lin, ForwardScatter._level(sigma)).astype(np.float32)

    @staticmethod
    def _index(pos, n: int, k0: int = 0) -> tuple:
        """Per pixel: the flat indices of the two levels (of ``n``) around a fractional level in a stack of the levels
        from ``k0`` on (no pixel's below it), and the weight of the upper one. (The level and its weight in float32:
        ``pos - floor(pos)`` is exact, as it was in float64.)"""
        j = np.floor(pos)
        np.clip(j, 0, n - 1, out=j)
        f = pos - j
        np.clip(f, 0, 1, out=f)
        size = j.size
        lo = j.astype(np.intp)
        lo -= k0
        lo *= size
        lo += _flat_index(j.shape)
        hi = lo + size
        np.copyto(hi, lo, where=j >= n - 1)
        return lo, hi, f

    @staticmethod
    def _interp(levels, at):
        """Linear interpolation between the stacked blur levels (L, H, W) at the indices of :meth:`_index`."""
        lo_i, hi_i, f = at
        lo = levels.ravel()[lo_i]
        return lo + f * (levels.ravel()[hi_i] - lo)
