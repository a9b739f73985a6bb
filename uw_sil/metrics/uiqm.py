"""No-reference underwater image quality: UIQM (Panetta et al. 2016) and UCIQE (Yang & Sowmya 2015).

Published implementations of both measures disagree with each other (input range, colour space
scaling, saturation definition, block handling), so the values here are comparable only with values
computed by this module. The conventions, written from the papers:

Input (both measures)
    An RGB image (H, W, 3), channel order R, G, B (as the project's rgb8 frames), either ``uint8``
    (0-255) or floating point in [0, 1] (multiplied by 255 for UIQM). Values are sRGB-encoded
    (gamma, not linear light).

UIQM = 0.0282 UICM + 0.2953 UISM + 3.5753 UIConM   (Panetta et al.; c1, c2, c3)
    All three sub-measures work on the 0-255 scale, in float64.

    UICM (colourfulness): opponent channels ``RG = R - G`` and ``YB = (R + G)/2 - B``; for each the
    asymmetric alpha-trimmed mean ``mu`` with alpha_L = alpha_R = 0.1 over the K pixels sorted
    ascending (drop the ``T_L = ceil(alpha_L K)`` smallest and the ``T_R = floor(alpha_R K)``
    largest values, average the rest), and ``sigma^2 = (1/K) sum_p (x_p - mu)^2`` over *all* pixels;
    ``UICM = -0.0268 sqrt(mu_RG^2 + mu_YB^2) + 0.1586 sqrt(sigma_RG^2 + sigma_YB^2)``.

    UISM (sharpness): per channel c, the Sobel edge map (3x3 Sobel, gradient magnitude
    ``sqrt(gx^2 + gy^2)``, borders reflected) multiplied pixel by pixel with the channel itself (the
    paper's "grayscale edge map"); ``EME = (2 / (k1 k2)) sum_blocks ln(I_max / I_min)`` over
    non-overlapping 8x8-pixel blocks (k1 = floor(H/8) block rows, k2 = floor(W/8) block columns;
    the remaining H mod 8 bottom rows and W mod 8 right columns are left out), natural logarithm;
    a block whose minimum is 0 contributes 0 (its ratio is undefined: a flat block or a block
    touching a flat area); ``UISM = 0.299 EME_R + 0.587 EME_G + 0.114 EME_B``.

    UIConM (contrast): logAMEE of the intensity ``0.299 R + 0.587 G + 0.114 B`` over the same 8x8
    blocks, with PLIP operations (parameterized logarithmic image processing) applied to the 0-255
    intensities directly (no grey-tone inversion), gamma = k = 1026:
    ``a (+) b = a + b - a b / gamma``, ``a (-) b = k (a - b) / (k - b)``,
    ``c (x) a = gamma - gamma (1 - a / gamma)^c``. Per block ``q = (I_max (-) I_min) / (I_max (+) I_min)``
    (a block with ``q = 0`` contributes 0), ``S = sum_blocks q ln q`` (ordinary sum, ``S <= 0``) and
    ``UIConM = -((1 / (k1 k2)) (x) S)``. The sign makes UIConM >= 0 and rising with contrast (the
    paper reports positive values). Through the PLIP scalar product the value depends mildly on the
    number of blocks (image size): compare images of one size.

UCIQE = 0.4680 sigma_c + 0.2745 con_l + 0.2576 mu_s   (Yang & Sowmya)
    CIELab from sRGB with the D65 white (OpenCV's ``RGB2Lab`` on float input), then **all three**
    coordinates divided by 100: ``L`` in [0, 1], ``a``, ``b`` roughly in [-1.3, 1.3] (one scale, so
    the geometry of Lab and the ratio ``C / L`` are kept).

    sigma_c: standard deviation (population, ddof 0) of the chroma ``C = sqrt(a^2 + b^2)``;
    con_l: ``L`` at the 99th percentile minus ``L`` at the 1st percentile (numpy's linear
    interpolation between order statistics), i.e. the spread between the top 1 % and the bottom 1 %;
    mu_s: mean saturation, saturation = chroma / lightness ``C / L`` (the CIELab saturation
    ``s_ab = C*_ab / L*``), 0 for pixels with ``L = 0``. It is unbounded for dark coloured pixels.

References
----------
.. [1] K. Panetta, C. Gao, S. Agaian, "Human-Visual-System-Inspired Underwater Image Quality
   Measures", IEEE Journal of Oceanic Engineering 41(3):541-551, 2016.
.. [2] M. Yang, A. Sowmya, "An Underwater Color Image Quality Evaluation Metric", IEEE Transactions
   on Image Processing 24(12):6062-6071, 2015.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from .._shared.checks import as_unit_rgb

__all__ = [
    "PLIP_GAMMA",
    "PLIP_K",
    "UCIQE_COEFFS",
    "UIQM_COEFFS",
    "eme",
    "uciqe",
    "uciqe_terms",
    "uicm",
    "uiconm",
    "uiqm",
    "uism",
]

UIQM_COEFFS = (0.0282, 0.2953, 3.5753)   # c1 UICM, c2 UISM, c3 UIConM [1]
UCIQE_COEFFS = (0.4680, 0.2745, 0.2576)  # c1 sigma_c, c2 con_l, c3 mu_s [2]
PLIP_GAMMA = 1026.0
PLIP_K = 1026.0
_BLOCK = 8
_LUMA = np.array([0.299, 0.587, 0.114])


def _as_rgb(image) -> np.ndarray:
    """The image as float64 RGB on the [0, 1] scale; ValueError for anything else."""
    return as_unit_rgb(image, np.float64)


def _blocks(x: np.ndarray, block: int) -> np.ndarray:
    """Non-overlapping ``block`` x ``block`` tiles, shape (k1, k2, block*block); the remainder is cut."""
    if block < 1:
        raise ValueError(f"block must be >= 1, got {block}")
    k1, k2 = x.shape[0] // block, x.shape[1] // block
    if k1 == 0 or k2 == 0:
        raise ValueError(f"image of shape {x.shape[:2]} is smaller than one {block}x{block} block")
    t = x[:k1 * block, :k2 * block].reshape(k1, block, k2, block).swapaxes(1, 2)
    return t.reshape(k1, k2, block * block)


def _trimmed_stats(x: np.ndarray, alpha_l: float, alpha_r: float) -> tuple[float, float]:
    """Asymmetric alpha-trimmed mean [1] and the spread around it [1]."""
    v = np.sort(x, axis=None)
    K = v.size
    t_l = math.ceil(alpha_l * K - 1e-9)   # the tolerance keeps 0.1 * 30 = 3.0000000000000004 at 3
    t_r = math.floor(alpha_r * K + 1e-9)
    if K - t_l - t_r < 1:
        raise ValueError(f"alpha trimming leaves no pixels (K={K}, alpha_L={alpha_l}, alpha_R={alpha_r})")
    mu = float(v[t_l:K - t_r].mean())
    var = float(np.mean((v - mu) ** 2))
    return mu, var


def uicm(image, *, alpha_l: float = 0.1, alpha_r: float = 0.1) -> float:
    """Underwater image colourfulness measure [1] (see the module docstring)."""
    rgb = _as_rgb(image) * 255.0
    R, G, B = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    mu_rg, var_rg = _trimmed_stats(R - G, alpha_l, alpha_r)
    mu_yb, var_yb = _trimmed_stats((R + G) / 2.0 - B, alpha_l, alpha_r)
    return -0.0268 * math.hypot(mu_rg, mu_yb) + 0.1586 * math.sqrt(var_rg + var_yb)


def eme(x, block: int = _BLOCK) -> float:
    """Measure of enhancement ``(2 / (k1 k2)) sum ln(I_max / I_min)`` over ``block``-pixel blocks [1].

    ``x`` is a non-negative 2-D array; blocks whose minimum is 0 contribute 0.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2:
        raise ValueError(f"eme expects a 2-D array, got shape {x.shape}")
    if (x < 0).any():
        raise ValueError("eme expects non-negative values")
    t = _blocks(x, block)
    lo, hi = t.min(axis=2), t.max(axis=2)
    ok = lo > 0
    terms = np.zeros_like(lo)
    terms[ok] = np.log(hi[ok] / lo[ok])
    return float(2.0 / lo.size * terms.sum())


def _grey_edge_map(channel: np.ndarray) -> np.ndarray:
    gx = cv2.Sobel(channel, cv2.CV_64F, 1, 0, ksize=3)
    gy = cv2.Sobel(channel, cv2.CV_64F, 0, 1, ksize=3)
    return np.sqrt(gx * gx + gy * gy) * channel


def uism(image, *, block: int = _BLOCK) -> float:
    """Underwater image sharpness measure [1]: luma-weighted EME of the grey edge maps."""
    rgb = _as_rgb(image) * 255.0
    return float(sum(w * eme(_grey_edge_map(np.ascontiguousarray(rgb[..., c])), block)
                     for c, w in enumerate(_LUMA)))


def _plip_add(a, b):
    return a + b - a * b / PLIP_GAMMA


def _plip_sub(a, b):
    return PLIP_K * (a - b) / (PLIP_K - b)


def _plip_scalar(c, a):
    return PLIP_GAMMA - PLIP_GAMMA * (1.0 - a / PLIP_GAMMA) ** c


def uiconm(image, *, block: int = _BLOCK) -> float:
    """Underwater image contrast measure: logAMEE of the intensity with PLIP operations [1]."""
    intensity = (_as_rgb(image) * 255.0) @ _LUMA
    t = _blocks(intensity, block)
    lo, hi = t.min(axis=2), t.max(axis=2)
    num, den = _plip_sub(hi, lo), _plip_add(hi, lo)
    ok = (num > 0) & (den > 0)
    q = np.zeros_like(lo)
    q[ok] = num[ok] / den[ok]
    terms = np.zeros_like(lo)
    terms[ok] = q[ok] * np.log(q[ok])
    S = float(terms.sum())                  # <= 0
    return float(-_plip_scalar(1.0 / lo.size, S))


def uiqm(image) -> float:
    """UIQM = 0.0282 UICM + 0.2953 UISM + 3.5753 UIConM [1] (conventions: module docstring)."""
    c1, c2, c3 = UIQM_COEFFS
    return c1 * uicm(image) + c2 * uism(image) + c3 * uiconm(image)


def uciqe_terms(image) -> dict[str, float]:
    """The three UCIQE terms [2]: ``sigma_c`` (chroma std), ``con_l`` (luminance contrast, top 1 % -
    bottom 1 %), ``mu_s`` (mean saturation C / L); Lab divided by 100 (module docstring)."""
    rgb = _as_rgb(image).astype(np.float32)
    lab = cv2.cvtColor(rgb, cv2.COLOR_RGB2Lab).astype(np.float64) / 100.0
    L, a, b = lab[..., 0], lab[..., 1], lab[..., 2]
    chroma = np.hypot(a, b)
    sigma_c = float(chroma.std())
    lo, hi = np.quantile(L, [0.01, 0.99])
    con_l = float(hi - lo)
    sat = np.zeros_like(chroma)
    np.divide(chroma, L, out=sat, where=L > 0)
    return {"sigma_c": sigma_c, "con_l": con_l, "mu_s": float(sat.mean())}


def uciqe(image) -> float:
    """UCIQE = 0.4680 sigma_c + 0.2745 con_l + 0.2576 mu_s [2] (conventions: module docstring)."""
    t = uciqe_terms(image)
    c1, c2, c3 = UCIQE_COEFFS
    return c1 * t["sigma_c"] + c2 * t["con_l"] + c3 * t["mu_s"]
