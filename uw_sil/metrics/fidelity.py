"""Full-reference fidelity of a restored image against the known clean radiance: PSNR and SSIM, over a
pixel mask (the object pixels of a synthetic frame).

Input convention (both): RGB (H, W, 3) or grey (H, W) images, ``uint8`` (0-255, divided by 255) or
floating point in [0, 1]; the data range ``L`` is 1. ``mask`` (H, W), non-zero = evaluated, default all
pixels.

PSNR = 10 log10(L^2 / MSE), MSE averaged over the masked pixels and the channels.

SSIM (Wang et al. 2004) with Wang et al.'s constants: Gaussian window of standard deviation 1.5 truncated
to 11x11 (OpenCV ``GaussianBlur``, borders reflected), ``K1 = 0.01``, ``K2 = 0.03``; the SSIM map is
computed per channel over the whole image, averaged over the channels, then over the masked pixels (a
window near the mask's edge sees its neighbourhood, as it does in the full image).

References
----------
.. [1] Z. Wang, A. C. Bovik, H. R. Sheikh, E. P. Simoncelli, "Image Quality Assessment: From Error
   Visibility to Structural Similarity", IEEE Transactions on Image Processing 13(4):600-612, 2004.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["psnr", "ssim", "ssim_map"]

SSIM_SIGMA = 1.5
SSIM_WINDOW = 11
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def _as_unit(image, name: str) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] not in (1, 3):
        raise ValueError(f"{name} must be (H, W) or (H, W, 3), got shape {np.shape(image)}")
    if a.dtype == np.uint8:
        return a.astype(np.float64) / 255.0
    if not np.issubdtype(a.dtype, np.floating):
        raise ValueError(f"{name} must be uint8 or float in [0, 1], got {a.dtype}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    return a.astype(np.float64)


def _pair(x, y, mask):
    a, b = _as_unit(x, "image"), _as_unit(y, "reference")
    if a.shape != b.shape:
        raise ValueError(f"image {a.shape} and reference {b.shape} differ in shape")
    m = np.ones(a.shape[:2], bool) if mask is None else np.asarray(mask) != 0
    if m.shape != a.shape[:2]:
        raise ValueError(f"mask {m.shape} does not match the images {a.shape[:2]}")
    if not m.any():
        raise ValueError("mask selects no pixel")
    return a, b, m


def psnr(image, reference, mask=None) -> float:
    """Peak signal-to-noise ratio in dB over the masked pixels (``inf`` for identical pixels)."""
    a, b, m = _pair(image, reference, mask)
    mse = float(np.mean((a[m] - b[m]) ** 2))
    return math.inf if mse == 0 else 10.0 * math.log10(1.0 / mse)


def ssim_map(image, reference) -> np.ndarray:
    """(H, W) SSIM map (mean over the channels), see the module docstring."""
    import cv2

    a, b, _ = _pair(image, reference, None)
    c1, c2 = (SSIM_K1 * 1.0) ** 2, (SSIM_K2 * 1.0) ** 2

    def blur(x):
        return cv2.GaussianBlur(x, (SSIM_WINDOW, SSIM_WINDOW), SSIM_SIGMA, borderType=cv2.BORDER_REFLECT)

    out = np.zeros(a.shape[:2])
    for c in range(a.shape[2]):
        x, y = a[..., c], b[..., c]
        mx, my = blur(x), blur(y)
        sxx = blur(x * x) - mx * mx
        syy = blur(y * y) - my * my
        sxy = blur(x * y) - mx * my
        out += ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return out / a.shape[2]


def ssim(image, reference, mask=None) -> float:
    """Mean SSIM over the masked pixels (1 for identical images)."""
    _, _, m = _pair(image, reference, mask)
    return float(ssim_map(image, reference)[m].mean())
