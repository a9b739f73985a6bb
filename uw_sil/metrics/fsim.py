"""Feature similarity index FSIM / FSIMc, a faithful port of the official ``FeatureSIM.m``.

This is the paper's criterion theta_1 (Sec. 3.3, Eq. 2). It follows the MATLAB reference code of
Zhang et al. (``FeatureSIM.m`` v1.0 with Kovesi's ``phasecong2`` and ``lowpassfilter``)
operation by operation, including the details where re-implementations usually drift:

* YIQ coefficients of ``FeatureSIM.m`` (I = 0.596 R - 0.274 G - 0.322 B,
  Q = 0.211 R - 0.523 G + 0.312 B), not the 4-decimal NTSC ones;
* downsampling factor ``F = max(1, round(min(rows, cols) / 256))`` with MATLAB's ``round``
  (halves away from zero) and ``conv2(img, ones(F)/F^2, 'same')`` with zero padding followed
  by sampling ``1:F:end`` (``ceil(n/F)`` samples) for any image size and any ``F``;
* the frequency grids of ``phasecong2`` (ranges divided by ``n - 1`` for odd sizes, ``n`` for
  even sizes, ``theta = atan2(-y, x)``), its noise estimate (median of the squared amplitude
  at the smallest scale, the median of an even count averaging the two middle values) and
  ``epsilon = 1e-4`` added to ``XEnergy``;
* the chroma term ``real((S_I .* S_Q) .^ lambda)``, which for a negative product is
  ``|x|^lambda * cos(lambda * pi)`` (MATLAB's principal complex power), not ``|x|^lambda``.

Besides the one-shot :func:`fsim`, :class:`FSIMReference` caches everything that depends
on a fixed reference image only (its phase congruency, gradient magnitude and chroma) and
scores candidate images (one at a time, float32/complex64 FFTs); it is what the backward
optimizer uses through :mod:`uw_sil.metrics.theta`.
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import NamedTuple

import numpy as np
import scipy.fft as sfft

from .._shared.checks import check_image, check_mask, check_values

__all__ = [
    "FSIMResult",
    "FSIMReference",
    "downsample_factor",
    "fsim",
    "phase_congruency",
]

# ---------------------------------------------------------------------------------------------
# Constants of FeatureSIM.m and phasecong2.m
# ---------------------------------------------------------------------------------------------
_T1 = 0.85  # PC similarity stabiliser (FeatureSIM.m)
_T2 = 160.0  # gradient similarity stabiliser
_T3 = 200.0  # I chroma stabiliser
_T4 = 200.0  # Q chroma stabiliser
_LAMBDA = 0.03  # chroma exponent

_NSCALE = 4
_NORIENT = 4
_MIN_WAVELENGTH = 6.0
_MULT = 2.0
_SIGMA_ON_F = 0.55
_DTHETA_ON_SIGMA = 1.2
_K = 2.0
_EPSILON = 1e-4

# RGB -> YIQ rows exactly as written in FeatureSIM.m
_YIQ = np.array(
    [
        [0.299, 0.587, 0.114],
        [0.596, -0.274, -0.322],
        [0.211, -0.523, 0.312],
    ]
)

_COS_LAMBDA_PI = math.cos(_LAMBDA * math.pi)


class FSIMResult(NamedTuple):
    """FSIM (luminance only) and FSIMc (with chroma) of one image pair."""

    fsim: float
    fsimc: float


def _mround(x: float) -> int:
    """MATLAB ``round`` for non-negative numbers: halves go away from zero."""
    return int(math.floor(x + 0.5))


def downsample_factor(rows: int, cols: int) -> int:
    """Downsampling factor of ``FeatureSIM.m``: ``max(1, round(min(rows, cols) / 256))``.

    Parameters
    ----------
    rows, cols : int
        Image size.

    Returns
    -------
    int
        The factor ``F``; MATLAB rounding, so a minimum side of 640 gives 3 (2.5 -> 3).
    """
    rows, cols = int(rows), int(cols)
    if rows < 1 or cols < 1:
        raise ValueError(f"image size must be positive, got {rows}x{cols}")
    return max(1, _mround(min(rows, cols) / 256.0))


def _box_downsample(x: np.ndarray, f: int, axes=(-2, -1)) -> np.ndarray:
    """``conv2(x, ones(f)/f^2, 'same')`` then ``x(1:f:end, 1:f:end)`` over two axes.

    MATLAB's ``'same'`` keeps the full convolution from index ``floor(f/2) + 1``, so the
    window of the output sample at ``i`` covers ``i - (f - 1 - floor(f/2)) .. i + floor(f/2)``
    (zero outside). The samples at ``i = 0, f, 2f, ...`` (``ceil(n/f)`` of them) therefore
    average disjoint blocks of ``f`` after padding ``f - 1 - floor(f/2)`` zeros in front.
    """
    if f == 1:
        return x
    out = x
    front = f - 1 - f // 2
    for axis in axes:
        ax = axis % out.ndim
        n = out.shape[ax]
        m = -(-n // f)  # ceil(n / f) samples
        take = min(n, m * f - front)
        if front or take != n or m * f != n:
            shape = list(out.shape)
            shape[ax] = m * f
            padded = np.zeros(shape, dtype=out.dtype)
            dst = [slice(None)] * out.ndim
            src = [slice(None)] * out.ndim
            dst[ax] = slice(front, front + take)
            src[ax] = slice(0, take)
            padded[tuple(dst)] = out[tuple(src)]
            out = padded
        idx = [slice(None)] * out.ndim
        idx[ax] = slice(0, None, f)
        acc = out[tuple(idx)]
        for k in range(1, f):
            idx[ax] = slice(k, None, f)
            acc = acc + out[tuple(idx)]
        out = acc
    return out * out.dtype.type(1.0 / (f * f))


def _gradient_magnitude(y: np.ndarray) -> np.ndarray:
    """``sqrt(conv2(y, dx, 'same').^2 + conv2(y, dy, 'same').^2)`` (zero padding), last two axes.

    ``dx = [3 0 -3; 10 0 -10; 3 0 -3]/16`` and ``dy = dx.'``; computed as a correlation,
    which flips the sign of both components and leaves the magnitude unchanged.
    """
    rows, cols = y.shape[-2:]
    p = np.zeros(y.shape[:-2] + (rows + 2, cols + 2), dtype=y.dtype)
    p[..., 1:-1, 1:-1] = y
    dxc = p[..., :, 2:] - p[..., :, :-2]  # horizontal difference, (rows + 2, cols)
    gx = dxc[..., :-2, :] + dxc[..., 2:, :]
    gx *= 3.0
    gx += 10.0 * dxc[..., 1:-1, :]
    dyc = p[..., 2:, :] - p[..., :-2, :]  # vertical difference, (rows, cols + 2)
    gy = dyc[..., :, :-2] + dyc[..., :, 2:]
    gy *= 3.0
    gy += 10.0 * dyc[..., :, 1:-1]
    gx *= gx
    gy *= gy
    gx += gy
    np.sqrt(gx, out=gx)
    gx *= 1.0 / 16.0
    return gx


def _middle_order_stats(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two middle order statistics of each row of ``a`` (c, n), as float64.

    Ranks ``(n - 1) // 2`` and ``n // 2`` (0-based; equal for odd ``n``), so the MATLAB/numpy
    median of a monotone function ``g`` of the row is ``(g(lo) + g(hi)) / 2``. A strided sample brackets the
    median; only the values inside the bracket are partitioned (Floyd-Rivest selection);
    if the bracket misses, the whole row is partitioned. The result is exact either way.
    """
    c, n = a.shape
    k_lo, k_hi = (n - 1) // 2, n // 2
    out = np.empty((2, c))
    step = max(1, n // 4096)
    for i in range(c):
        x = a[i]
        vals = None
        if step > 1:
            s = np.sort(x[::step])
            ms = s.size
            d = int(2.0 * math.sqrt(ms)) + 1  # 4 standard deviations of the sample rank
            lo = s[max(ms // 2 - d, 0)]
            hi = s[min(ms // 2 + d, ms - 1)]
            below = np.count_nonzero(x < lo)
            sel = x[(x >= lo) & (x <= hi)]
            if below <= k_lo and below + sel.size > k_hi:
                part = np.partition(sel, k_lo - below)
                v_lo = part[k_lo - below]
                v_hi = v_lo if k_hi == k_lo else part[k_lo - below + 1 :].min()
                vals = (float(v_lo), float(v_hi))
        if vals is None:
            part = np.partition(x, k_lo)
            v_lo = part[k_lo]
            v_hi = v_lo if k_hi == k_lo else part[k_lo + 1 :].min()
            vals = (float(v_lo), float(v_hi))
        out[:, i] = vals
    return out[0], out[1]


# ---------------------------------------------------------------------------------------------
# phasecong2 (Kovesi), as embedded in FeatureSIM.m
# ---------------------------------------------------------------------------------------------
def _grid_range(n: int) -> np.ndarray:
    """``xrange``/``yrange`` of phasecong2/lowpassfilter for a side of ``n`` samples."""
    if n % 2:
        return np.arange(-(n - 1) / 2, (n - 1) / 2 + 1) / (n - 1)
    return np.arange(-n / 2, n / 2) / n


@lru_cache(maxsize=8)
def _pc_bank(rows: int, cols: int):
    """Filters and noise constants of phasecong2 for an image size (reference-independent).

    Returns
    -------
    filters : ndarray, shape (norient, nscale, rows, cols), float64
        ``logGabor{s} .* spread{o}`` with the zero frequency at ``[0, 0]``.
    noise_const : ndarray, shape (norient, 2)
        Per orientation ``EM_n`` (sum of the squared smallest-scale filter) and
        ``2 * sum(EstSumAn2) + 4 * sum(EstSumAiAj)`` so that
        ``EstNoiseEnergy2 = noisePower * noise_const[o, 1]``.
    """
    x, y = np.meshgrid(_grid_range(cols), _grid_range(rows))
    radius = np.sqrt(x**2 + y**2)
    theta = np.arctan2(-y, x)
    # lowpassfilter([rows, cols], .45, 15) on the unshifted radius, then ifftshift
    lp = np.fft.ifftshift(1.0 / (1.0 + (radius / 0.45) ** (2 * 15)))
    radius = np.fft.ifftshift(radius)
    theta = np.fft.ifftshift(theta)
    radius[0, 0] = 1.0
    sintheta, costheta = np.sin(theta), np.cos(theta)
    theta_sigma = math.pi / _NORIENT / _DTHETA_ON_SIGMA

    log_gabor = []
    for s in range(_NSCALE):
        wavelength = _MIN_WAVELENGTH * _MULT**s
        fo = 1.0 / wavelength
        lg = np.exp((-(np.log(radius / fo)) ** 2) / (2 * math.log(_SIGMA_ON_F) ** 2))
        lg = lg * lp
        lg[0, 0] = 0.0
        log_gabor.append(lg)

    filters = np.empty((_NORIENT, _NSCALE, rows, cols))
    noise_const = np.empty((_NORIENT, 2))
    sqrt_n = math.sqrt(rows * cols)
    for o in range(_NORIENT):
        angl = o * math.pi / _NORIENT
        ds = sintheta * math.cos(angl) - costheta * math.sin(angl)
        dc = costheta * math.cos(angl) + sintheta * math.sin(angl)
        dtheta = np.abs(np.arctan2(ds, dc))
        spread = np.exp((-(dtheta**2)) / (2 * theta_sigma**2))
        ifft_filt = []
        for s in range(_NSCALE):
            filt = log_gabor[s] * spread
            filters[o, s] = filt
            ifft_filt.append(np.real(np.fft.ifft2(filt)) * sqrt_n)
        em_n = np.sum(filters[o, 0] ** 2)
        est_sum_an2 = sum(f**2 for f in ifft_filt)
        est_sum_aiaj = np.zeros((rows, cols))
        for si in range(_NSCALE - 1):
            for sj in range(si + 1, _NSCALE):
                est_sum_aiaj = est_sum_aiaj + ifft_filt[si] * ifft_filt[sj]
        noise_const[o, 0] = em_n
        noise_const[o, 1] = 2 * np.sum(est_sum_an2) + 4 * np.sum(est_sum_aiaj)
    filters.setflags(write=False)
    noise_const.setflags(write=False)
    return filters, noise_const


@lru_cache(maxsize=8)
def _pc_bank_interleaved(rows: int, cols: int, dtype) -> np.ndarray:
    """The real filters with every value repeated twice, shape (norient, nscale, rows, 2 cols).

    Multiplying the float view of a complex spectrum by this array is the complex-by-real
    product ``imagefft .* filter`` without numpy's mixed-type (complex x complex) loop.
    """
    filters = np.repeat(_pc_bank(rows, cols)[0].astype(dtype), 2, axis=-1)
    filters.setflags(write=False)
    return filters


def _noise_threshold(median_e2n: float, em_n: float, const: float) -> float:
    """Noise threshold ``T`` of phasecong2 from the median squared smallest-scale amplitude."""
    mean_e2n = -median_e2n / math.log(0.5)
    noise_power = mean_e2n / em_n
    est_noise_energy2 = noise_power * const
    tau = math.sqrt(est_noise_energy2 / 2)
    est_noise_energy = tau * math.sqrt(math.pi / 2)
    est_noise_energy_sigma = math.sqrt((2 - math.pi / 2) * tau**2)
    return (est_noise_energy + _K * est_noise_energy_sigma) / 1.7


def _phasecong_stack(y: np.ndarray, dtype, workers, chunk: int) -> np.ndarray:
    """phasecong2 on a stack ``(N, rows, cols)``; float64 or float32 working precision.

    Images whose luminance is constant have no phase structure: their PC map is 0 (MATLAB
    divides 0 by 0 there, or by FFT rounding noise). Elsewhere pixels with total amplitude
    ``AnAll == 0`` also get 0.
    """
    n_img, rows, cols = y.shape
    dtype = np.dtype(dtype).type
    filters2 = _pc_bank_interleaved(rows, cols, dtype)
    noise_const = _pc_bank(rows, cols)[1]
    ctype = np.complex64 if dtype == np.float32 else np.complex128
    out = np.empty((n_img, rows, cols), dtype=dtype)
    for start in range(0, n_img, chunk):
        yc = np.asarray(y[start : start + chunk], dtype=dtype)
        c = yc.shape[0]
        flat = yc.reshape(c, -1)
        constant = flat.min(axis=1) == flat.max(axis=1)
        # The filters vanish at the zero frequency, so removing the mean changes nothing but
        # the rounding error of the transform (it matters in float32).
        yc = yc - flat.mean(axis=1, dtype=np.float64).astype(dtype)[:, None, None]
        spec = sfft.fft2(yc, workers=workers).astype(ctype, copy=False)
        spec_f = spec.view(dtype)  # (c, rows, 2 cols): re, im interleaved
        work = np.empty((c, _NSCALE, rows, 2 * cols), dtype=dtype)
        an = np.empty((c, _NSCALE, rows, cols), dtype=dtype)
        tmp = np.empty((c, _NSCALE, rows, cols), dtype=dtype)
        total = np.empty((c, rows, cols), dtype=ctype)
        xe = np.empty((c, rows, cols), dtype=dtype)
        energy = np.empty((c, rows, cols), dtype=dtype)
        energy_all = np.zeros((c, rows, cols), dtype=dtype)
        an_all = np.zeros((c, rows, cols), dtype=dtype)
        for o in range(_NORIENT):
            # EO{s,o} for the 4 scales at once: (c, nscale, rows, cols) complex
            np.multiply(spec_f[:, None], filters2[o], out=work)  # imagefft .* filter
            eo = sfft.ifft2(work.view(ctype), workers=workers, overwrite_x=True)
            np.abs(eo, out=an)  # An
            for s in range(_NSCALE):
                an_all += an[:, s]  # sumAn_ThisOrient, accumulated into AnAll
            np.add(eo[:, 0], eo[:, 1], out=total)  # sumE + i sumO
            for s in range(2, _NSCALE):
                total += eo[:, s]
            np.abs(total, out=xe)
            # Energy = sum_s E.*MeanE + O.*MeanO - |E.*MeanO - O.*MeanE| with
            # (MeanE, MeanO) = (sumE, sumO) ./ XEnergy, XEnergy = |sum| + epsilon, i.e.
            # (|sum|^2 - sum_s |E.*sumO - O.*sumE|) ./ XEnergy, and
            # E.*sumO - O.*sumE = -imag(conj(sum) .* EO)
            np.conjugate(total, out=total)
            np.multiply(eo, total[:, None], out=eo)  # EO is not needed any more
            np.abs(eo.imag, out=tmp)
            np.multiply(xe, xe, out=energy)
            for s in range(_NSCALE):
                energy -= tmp[:, s]
            xe += _EPSILON
            energy /= xe
            # noise: median(abs(EO{1,o}).^2), the square being monotone on amplitudes
            lo, hi = _middle_order_stats(an[:, 0].reshape(c, -1))
            med = (lo * lo + hi * hi) / 2.0
            thr = np.array(
                [_noise_threshold(float(m), noise_const[o, 0], noise_const[o, 1]) for m in med],
                dtype=dtype,
            )
            energy -= thr[:, None, None]
            np.maximum(energy, 0, out=energy)
            energy_all += energy
        pc = np.divide(energy_all, an_all, out=np.zeros_like(energy_all), where=an_all > 0)
        pc[constant] = 0.0
        out[start : start + c] = pc
    return out


def phase_congruency(image, *, workers=None) -> np.ndarray:
    """Phase congruency map of ``phasecong2`` as used by ``FeatureSIM.m``.

    Parameters
    ----------
    image : ndarray, shape (rows, cols)
        Grey image (any real dtype; used in float64). Both sides at least 2.
    workers : int, optional
        Threads for ``scipy.fft``.

    Returns
    -------
    ndarray, shape (rows, cols), float64
        ``PC_2`` of Kovesi: 4 scales (minimum wavelength 6, factor 2, sigmaOnf 0.55),
        4 orientations (dThetaOnSigma 1.2), noise threshold k = 2 rescaled by 1/1.7.

    Notes
    -----
    Where the summed amplitude is exactly zero (a constant image) MATLAB returns NaN; this
    function returns 0 there ("no phase structure").

    References
    ----------
    .. [1] P. Kovesi, "Image features from phase congruency", Videre 1(3), 1999.
    .. [2] L. Zhang, L. Zhang, X. Mou, D. Zhang, "FSIM: a feature similarity index for image
       quality assessment", IEEE TIP 20(8), 2378-2386, 2011, Sec. III (phase congruency).
    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"image must be 2-D (rows, cols), got shape {img.shape}")
    if not (np.issubdtype(img.dtype, np.integer) or np.issubdtype(img.dtype, np.floating)):
        raise TypeError(f"image must be a real integer or float array, got dtype {img.dtype}")
    if img.shape[0] < 2 or img.shape[1] < 2:
        raise ValueError(f"image must be at least 2x2 pixels, got {img.shape}")
    img = img.astype(np.float64)
    if not np.isfinite(img).all():
        raise ValueError("image contains NaN or inf")
    return _phasecong_stack(img[None], np.float64, workers, 1)[0]


# ---------------------------------------------------------------------------------------------
# FSIM / FSIMc
# ---------------------------------------------------------------------------------------------
def _chroma_term(si: np.ndarray, sq: np.ndarray) -> np.ndarray:
    """``real((SI .* SQ) .^ lambda)``: ``|x|^l`` for x >= 0, ``|x|^l cos(l pi)`` for x < 0."""
    prod = si * sq
    out = np.abs(prod) ** _LAMBDA
    return np.where(prod < 0, out * _COS_LAMBDA_PI, out)


def _pooled(sim: np.ndarray, pcm: np.ndarray, weight=None) -> np.ndarray:
    """``sum(sim .* PCm) / sum(PCm)`` over the last two axes (float64 accumulation).

    If ``sum(PCm) == 0`` (both images without any phase structure, e.g. both constant; MATLAB
    returns NaN) the unweighted mean of ``sim`` is returned instead.
    """
    w = pcm if weight is None else pcm * weight
    num = (sim * w).sum(axis=(-2, -1), dtype=np.float64)
    den = w.sum(axis=(-2, -1), dtype=np.float64)
    if weight is None:
        plain = sim.mean(axis=(-2, -1), dtype=np.float64)
    else:
        plain = (sim * weight).sum(axis=(-2, -1), dtype=np.float64) / weight.sum(dtype=np.float64)
    safe = np.where(den > 0, den, 1.0)
    return np.where(den > 0, num / safe, plain)


def fsim(ref, dist, *, workers=None) -> FSIMResult:
    """Feature similarity FSIM and FSIMc of two images, as MATLAB's ``FeatureSIM.m``.

    Parameters
    ----------
    ref, dist : ndarray, shape (H, W) or (H, W, 3)
        Reference and distorted image, same shape; uint8, or float32/float64 in 0..255.
        Colour images are RGB (not OpenCV's BGR). Both sides at least 2 pixels.
    workers : int, optional
        Threads for ``scipy.fft``.

    Returns
    -------
    FSIMResult
        ``(fsim, fsimc)``: FSIM uses luminance only (PC and gradient similarity, pooled with
        the PC maximum as weight); FSIMc multiplies in the I/Q chrominance similarity to the
        power 0.03. For grey images both are equal. Both lie in [0, 1] (the chroma factor of
        a negative I/Q product is ``|x|^0.03 cos(0.03 pi) > 0``).

    Raises
    ------
    TypeError
        Not numpy arrays, or dtype other than uint8/float32/float64.
    ValueError
        Different shapes, wrong dimensionality, empty or smaller than 2x2, NaN/inf, floats
        outside [0, 255].

    Notes
    -----
    Port of ``FeatureSIM.m`` v1.0 (see the module docstring for the details kept from
    MATLAB); computed in float64. Only deviations: where MATLAB yields NaN this function
    is defined instead. A constant luminance image has phase congruency 0 everywhere (MATLAB:
    0/0); if both images have zero phase congruency everywhere the PC-weighted mean of the
    similarity map is replaced by its unweighted mean (MATLAB: NaN), e.g. two identical
    constant images give 1. Rounding-level reorderings (the image mean is removed before
    the FFT, where the filters are zero anyway; the energy sum is regrouped) change the
    results by about 1e-15.

    References
    ----------
    .. [1] L. Zhang, L. Zhang, X. Mou, D. Zhang, "FSIM: a feature similarity index for image
       quality assessment", IEEE TIP 20(8), 2378-2386, 2011, Sec. III (FSIM and its colour
       extension FSIM_C); reference code FeatureSIM.m v1.0.
    .. [2] P. Kovesi, "Image features from phase congruency", Videre 1(3), 1999.
    """
    check_image(ref, "ref")
    check_image(dist, "dist")
    if ref.shape != dist.shape:
        raise ValueError(f"ref and dist must have the same shape, got {ref.shape} and {dist.shape}")
    rows, cols = ref.shape[:2]
    f = downsample_factor(rows, cols)
    if ref.ndim == 3:
        r64, d64 = ref.astype(np.float64), dist.astype(np.float64)
        yiq1 = [r64[..., 0] * m[0] + r64[..., 1] * m[1] + r64[..., 2] * m[2] for m in _YIQ]
        yiq2 = [d64[..., 0] * m[0] + d64[..., 1] * m[1] + d64[..., 2] * m[2] for m in _YIQ]
        y1, i1, q1 = (_box_downsample(c, f) for c in yiq1)
        y2, i2, q2 = (_box_downsample(c, f) for c in yiq2)
    else:
        y1 = _box_downsample(ref.astype(np.float64), f)
        y2 = _box_downsample(dist.astype(np.float64), f)
    if min(y1.shape) < 2:
        raise ValueError(f"downsampled image is smaller than 2x2 ({y1.shape})")
    pc = _phasecong_stack(np.stack([y1, y2]), np.float64, workers, 2)
    pc1, pc2 = pc[0], pc[1]
    g1, g2 = _gradient_magnitude(y1), _gradient_magnitude(y2)
    pc_sim = (2 * pc1 * pc2 + _T1) / (pc1**2 + pc2**2 + _T1)
    g_sim = (2 * g1 * g2 + _T2) / (g1**2 + g2**2 + _T2)
    pcm = np.maximum(pc1, pc2)
    sim_l = g_sim * pc_sim
    value = float(_pooled(sim_l, pcm))
    if ref.ndim == 2:
        return FSIMResult(value, value)
    i_sim = (2 * i1 * i2 + _T3) / (i1**2 + i2**2 + _T3)
    q_sim = (2 * q1 * q2 + _T4) / (q1**2 + q2**2 + _T4)
    value_c = float(_pooled(sim_l * _chroma_term(i_sim, q_sim), pcm))
    return FSIMResult(value, value_c)


def _planar(img: np.ndarray, dtype, out=None) -> np.ndarray:
    """Channel-first contiguous copy ``(3, H, W)`` of an ``(H, W, 3)`` image (or a copy of a grey one)."""
    src = np.moveaxis(img, -1, 0) if img.ndim == 3 else img
    if out is None:
        out = np.empty(src.shape, dtype=dtype)
    np.copyto(out, src, casting="unsafe")  # values were validated to lie in 0..255
    return out


class FSIMReference:
    """FSIM/FSIMc of many candidate images against one fixed reference image.

    Everything that depends on the reference only (downsampled Y/I/Q, phase congruency,
    gradient magnitude, the filter bank for the size) is computed once in the constructor;
    :meth:`score` then evaluates candidates one image at a time (that keeps the working set
    in cache, which is faster than wide batches).

    Parameters
    ----------
    reference : ndarray, shape (H, W, 3) or (H, W)
        Reference image (RGB or grey), uint8 or float in 0..255.
    mask : ndarray of bool, shape (H, W), optional
        Pixels that count. The downsampled mask is ``mask[::F, ::F]``; the pooling of
        FSIM/FSIMc sums over these pixels only (phase congruency and gradients are still
        computed on the whole image). ``None`` = all pixels (as :func:`fsim`).
    dtype : {numpy.float32, numpy.float64}
        Working precision for candidates (the reference is always processed in float64).
        float32 agrees with the float64 port to ~1e-7 and is about twice as fast.
    workers : int, optional
        Threads for ``scipy.fft`` (``None``: scipy's default, one thread).

    Notes
    -----
    Scores equal those of :func:`fsim` (to float32 rounding with ``dtype=float32``; to float64
    rounding otherwise, the colour transform being applied after the linear downsampling), and
    a candidate's score does not depend on the batch it is in. Not thread-safe (work buffers
    are reused): use one instance per thread.
    """

    def __init__(self, reference, *, mask=None, dtype=np.float32, workers=None):
        check_image(reference, "reference")
        if dtype not in (np.float32, np.float64):
            raise TypeError(f"dtype must be numpy.float32 or numpy.float64, got {dtype!r}")
        self.shape = reference.shape
        self.dtype = np.dtype(dtype).type
        self.workers = workers
        rows, cols = reference.shape[:2]
        self.factor = downsample_factor(rows, cols)
        self.color = reference.ndim == 3
        y, i, q = self._yiq_down(_planar(reference, np.float64))
        if min(y.shape) < 2:
            raise ValueError(f"downsampled reference is smaller than 2x2 ({y.shape})")
        self._pc = _phasecong_stack(y[None], np.float64, workers, 1)[0].astype(self.dtype)
        self._grad = _gradient_magnitude(y).astype(self.dtype)
        self._pc2 = self._pc * self._pc
        self._g2 = self._grad * self._grad
        if self.color:
            self._i, self._q = i.astype(self.dtype), q.astype(self.dtype)
            self._i2, self._q2 = self._i * self._i, self._q * self._q
        if mask is None:
            self._weight = None
        else:
            m = check_mask(mask, (rows, cols))
            w = m[:: self.factor, :: self.factor]
            if not w.any():
                raise ValueError("mask selects no pixel of the downsampled image")
            self._weight = w.astype(self.dtype)
        self._buf = None

    def _yiq_down(self, planes: np.ndarray):
        """Downsampled Y, I, Q of planar RGB ``(3, H, W)`` (grey ``(H, W)``: Y only, I = Q = None).

        Downsampling is linear, so it is done first and the colour transform on the 4x smaller
        planes (same result up to rounding).
        """
        if planes.ndim == 2:
            return _box_downsample(planes, self.factor), None, None
        r, g, b = _box_downsample(planes, self.factor)
        return tuple(r * m[0] + g * m[1] + b * m[2] for m in _YIQ.astype(planes.dtype))

    def score(self, candidates) -> tuple[np.ndarray, np.ndarray]:
        """FSIM and FSIMc of each candidate against the reference.

        Parameters
        ----------
        candidates : ndarray, shape (N, H, W, 3) or (H, W, 3) (grey: (N, H, W) or (H, W))
            uint8, or float32/float64 in 0..255, same image size as the reference.

        Returns
        -------
        fsim, fsimc : ndarray, shape (N,), float64
        """
        if not isinstance(candidates, np.ndarray):
            raise TypeError(f"candidates must be a numpy array, got {type(candidates).__name__}")
        single_ndim = len(self.shape)
        batch = candidates[None] if candidates.ndim == single_ndim else candidates
        if batch.ndim != single_ndim + 1 or batch.shape[1:] != self.shape:
            raise ValueError(
                f"candidates must have shape {self.shape} or (N, {', '.join(map(str, self.shape))}), "
                f"got {candidates.shape}"
            )
        check_image(batch[0], "candidates", values=False)  # dtype, sizes
        n = batch.shape[0]
        out_l = np.empty(n)
        out_c = np.empty(n)
        for k in range(n):
            planes = self.to_planar(batch[k])
            if batch.dtype != np.uint8:
                check_values(planes, f"candidates[{k}]")  # on the contiguous working copy
            out_l[k], out_c[k] = self.score_planar(planes)
        return out_l, out_c

    def to_planar(self, img: np.ndarray) -> np.ndarray:
        """Planar working-precision copy of a validated candidate, in a reused buffer (overwritten by the next call).

        Public for criteria that share one planar copy (:class:`uw_sil.metrics.theta.ThetaReference`).
        """
        shape = (3,) + img.shape[:2] if img.ndim == 3 else img.shape
        if self._buf is None or self._buf.shape != shape:
            self._buf = np.empty(shape, self.dtype)
        return _planar(img, self.dtype, out=self._buf)

    def score_planar(self, planes: np.ndarray) -> tuple[float, float]:
        """(FSIM, FSIMc) of one candidate given as planar ``(3, H, W)`` (or grey), already validated
        (:func:`uw_sil._shared.checks.check_image`) and in the reference's working precision."""
        y, i, q = self._yiq_down(planes)
        y = np.ascontiguousarray(y, dtype=self.dtype)
        pc = _phasecong_stack(y[None], self.dtype, self.workers, 1)[0]
        g = _gradient_magnitude(y)
        pc_sim = (2 * self._pc * pc + _T1) / (self._pc2 + pc * pc + _T1)
        g_sim = (2 * self._grad * g + _T2) / (self._g2 + g * g + _T2)
        pcm = np.maximum(self._pc, pc)
        sim_l = g_sim * pc_sim
        fl = float(_pooled(sim_l, pcm, self._weight))
        if not self.color:
            return fl, fl
        i_sim = (2 * self._i * i + _T3) / (self._i2 + i * i + _T3)
        q_sim = (2 * self._q * q + _T4) / (self._q2 + q * q + _T4)
        fc = float(_pooled(sim_l * _chroma_term(i_sim, q_sim), pcm, self._weight))
        return fl, fc
