"""Dark channel prior dehazing (He et al. 2011) and its underwater variant UDCP (Drews et al. 2013).

The image-only baselines of the SIL dehazing. (The paper, Doernbach et al. 2018, compares SIL with
another DCP method, Zeng & Dai 2016, in its Fig. 4 and Table 2; that one is not implemented here.)
Both methods invert the haze model

    I(x) = J(x) t(x) + A (1 - t(x))                                   (He et al., haze imaging model)

with a transmission ``t`` estimated from the image alone: DCP assumes that the dark channel of a
haze-free image is ~0; UDCP makes the same assumption on the green and blue channels only, since
water absorbs red so strongly that the red channel is dark everywhere underwater.

Choices where the papers leave room (all documented in :func:`dehaze_dcp`):

- atmospheric light: among the brightest 0.1 % of the dark channel (ties at the cut taken in
  raster order), the pixel(s) of highest input intensity, intensity = mean over the channels used
  (R, G, B for DCP; G, B for UDCP); when several candidates share that highest intensity their
  colours are averaged;
- transmission refinement: the guided filter (He, Sun & Tang, "Guided Image Filtering", TPAMI 2013,
  which recommends it for dehazing in place of the 2011 paper's soft matting), guide = grey input;
- UDCP uses the same ω (0.95) and t0 (0.1) as DCP.

Equation numbers. He et al. published the method at CVPR 2009 and, extended, in TPAMI 2011; the longer
journal version need not number its equations and sections like the conference one, so the formula is
written out next to every number. The numbers given here are the CVPR 2009 ones, as two independent
reimplementations quote them in their source (GitHub ``joyeecheung/dark-channel-prior-dehazing``,
``src/dehaze.py``, and ``cssartori/image-dehazing``, ``src/*.py``, both citing the CVPR 2009 paper):
Eq. 5 the dark channel, Sec. 4.4 the atmospheric light and Eq. 16 the recovery with ``t0`` (in both),
Eq. 12 the transmission with ``ω`` (in the first; the second calls it Eq. 11, so that number is
uncertain). No copy of either paper's text was found to check them against; the TPAMI 2011 numbers
(e.g. 22 for the recovery) could not be confirmed and are not used, nor are numbers for the haze model
and the intermediate steps. Drews et al. is cited by formula only.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .._shared.checks import as_unit_rgb

__all__ = ["DehazeResult", "dehaze_dcp"]

_VARIANTS = {"dcp": (0, 1, 2), "udcp": (1, 2)}  # channels (of RGB) the dark channel is taken over
_TOP_FRACTION = 0.001  # He et al. (CVPR 2009 Sec. 4.4): the top 0.1 % brightest pixels of the dark channel


@dataclass(frozen=True)
class DehazeResult:
    """Result of :func:`dehaze_dcp`.

    Attributes
    ----------
    image : ndarray, (H, W, 3)
        Restored scene radiance ``J`` clamped to [0, 1], same dtype as the input (uint8 or float).
    transmission : ndarray, (H, W) float32
        Refined transmission ``t`` (before the lower bound ``t0``).
    atmospheric_light : ndarray, (3,) float64
        Atmospheric (veiling) light ``A`` in RGB, on the [0, 1] scale whatever the input dtype.
    """

    image: np.ndarray
    transmission: np.ndarray
    atmospheric_light: np.ndarray


def _as_float_rgb(image) -> tuple[np.ndarray, np.dtype]:
    return as_unit_rgb(image, np.float32), np.asarray(image).dtype


def _dark_channel(img: np.ndarray, channels, patch: int) -> np.ndarray:
    """min over ``channels`` then min over a ``patch`` x ``patch`` square (erosion; He et al. CVPR 2009 Eq. 5).

    ``cv2.erode``'s default border ignores pixels outside the image, so near the border the patch is
    the part of the square that lies inside the image.
    """
    per_pixel = np.min(img[..., list(channels)], axis=2)
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (patch, patch))
    return cv2.erode(per_pixel, kernel)


def _atmospheric_light(img: np.ndarray, dark: np.ndarray, channels) -> np.ndarray:
    """He et al. (CVPR 2009 Sec. 4.4): among the top 0.1 % brightest dark-channel pixels, the one(s) of highest
    input intensity (mean over ``channels``); ties in intensity are averaged. Exactly n = 0.1 % of the
    pixels are candidates; pixels tied with the n-th brightest dark-channel value are taken in raster
    order (a deterministic rule, and in practice ties at that value share the colour of the veil)."""
    flat_dark = dark.ravel()
    n = max(1, int(round(_TOP_FRACTION * flat_dark.size)))
    kth = np.sort(flat_dark)[flat_dark.size - n]   # a full sort: faster than a partition with many ties
    above = np.flatnonzero(flat_dark > kth)
    tied = np.flatnonzero(flat_dark == kth)[:n - above.size]
    candidates = np.concatenate([above, tied])
    pixels = img.reshape(-1, 3)[candidates].astype(np.float64)
    intensity = pixels[:, list(channels)].mean(axis=1)
    best = intensity == intensity.max()
    return pixels[best].mean(axis=0)


def _check_params(variant, patch, omega, t0, guided_radius, guided_eps):
    if variant not in _VARIANTS:
        raise ValueError(f"variant must be one of {sorted(_VARIANTS)}, got {variant!r}")
    if isinstance(patch, bool) or not isinstance(patch, (int, np.integer)) or patch < 1 or patch % 2 == 0:
        raise ValueError(f"patch must be a positive odd integer, got {patch!r}")
    if not (0.0 < omega <= 1.0):
        raise ValueError(f"omega must lie in (0, 1], got {omega!r}")
    if not (0.0 < t0 <= 1.0):
        raise ValueError(f"t0 must lie in (0, 1], got {t0!r}")
    if isinstance(guided_radius, bool) or not isinstance(guided_radius, (int, np.integer)) or guided_radius < 0:
        raise ValueError(f"guided_radius must be an integer >= 0 (0: no refinement), got {guided_radius!r}")
    if not (guided_eps > 0.0):
        raise ValueError(f"guided_eps must be > 0, got {guided_eps!r}")


def dehaze_dcp(image, *, variant: str = "dcp", patch: int = 15, omega: float = 0.95, t0: float = 0.1,
               guided_radius: int = 60, guided_eps: float = 1e-4) -> DehazeResult:
    """Remove haze with the dark channel prior (DCP) or its underwater variant (UDCP).

    Steps, with ``Ω(x)`` the ``patch`` x ``patch`` square around ``x`` and ``C`` the channels used
    (R, G, B for ``'dcp'``; G, B for ``'udcp'``):

    Equation and section numbers are those of He et al.'s CVPR 2009 version (see the module notes
    for how they were checked).

    1. dark channel ``I_dark(x) = min_{y∈Ω(x)} min_{c∈C} I^c(y)`` (He et al. Eq. 5; Drews et al.'s
       underwater dark channel for C = {G, B});
    2. atmospheric light ``A``: the top 0.1 % brightest pixels of ``I_dark`` (ties at the cut taken
       in raster order) are candidates; ``A`` is the input colour of the candidate with the highest
       intensity, intensity = mean of ``I^c`` over ``C`` (He et al. Sec. 4.4). Candidates tied at
       that intensity are averaged. ``A`` has all three channels also for UDCP, whose restoration
       is applied to R, G and B;
    3. raw transmission ``t̃(x) = 1 - ω min_{y∈Ω(x)} min_{c∈C} I^c(y) / A^c``: the haze model divided
       by ``A^c``, the dark channel of both sides taken and ``J``'s dropped, a little haze kept with
       ``ω`` (He et al. Sec. 4.1, Eq. 12, or 11: see the module notes; Drews et al.'s transmission for
       C = {G, B});
    4. refined transmission ``t``: guided filter of ``t̃`` with the grey input as guide, radius
       ``guided_radius``, regularization ``guided_eps`` (He, Sun & Tang 2013, replacing the soft
       matting of He et al.); ``guided_radius=0`` skips the refinement (``t = t̃``);
    5. scene radiance ``J(x) = (I(x) - A) / max(t(x), t0) + A`` (He et al. Eq. 16), clamped to
       [0, 1].

    Parameters
    ----------
    image : array_like, (H, W, 3)
        RGB image, ``uint8`` (0-255) or floating point in [0, 1].
    variant : {'dcp', 'udcp'}
        ``'dcp'``: He et al.; ``'udcp'``: Drews et al. (dark channel over G and B).
    patch : int
        Side of the square local patch ``Ω``, odd (He et al.: 15).
    omega : float
        Haze kept for depth perception, in (0, 1] (He et al.: 0.95).
    t0 : float
        Lower bound of the transmission in the recovery, in (0, 1] (He et al.: 0.1).
    guided_radius : int
        Guided filter radius in pixels; 0 disables refinement (He, Sun & Tang 2013 for dehazing: 60).
    guided_eps : float
        Guided filter regularization on the [0, 1] scale (He, Sun & Tang 2013: 1e-4).

    Returns
    -------
    DehazeResult
        ``image`` (same dtype as the input), ``transmission`` (H, W) float32, ``atmospheric_light``
        (3,) on the [0, 1] scale.

    Raises
    ------
    ValueError
        If the image is not (H, W, 3), not uint8 / floating point, holds NaN / inf, or a float image
        leaves [0, 1]; or if a parameter is out of range.

    References
    ----------
    .. [1] K. He, J. Sun, X. Tang, "Single Image Haze Removal Using Dark Channel Prior", IEEE TPAMI
       33(12):2341-2353, 2011.
    .. [2] P. Drews Jr., E. do Nascimento, F. Moraes, S. Botelho, M. Campos, "Transmission Estimation
       in Underwater Single Images", ICCV Workshops 2013, pp. 825-830.
    .. [3] K. He, J. Sun, X. Tang, "Guided Image Filtering", IEEE TPAMI 35(6):1397-1409, 2013.
    .. [4] T. Doernbach, A. Gomez Chavez, C. A. Mueller and A. Birk, "High-Fidelity Deep-Sea
       Perception Using Simulation in the Loop", IFAC conference paper, 2018 (Sec. 4.1, 4.3).
    .. [5] L. Zeng and Y. Dai, "Single Image Dehazing Based on Combining Dark Channel Prior and Scene
       Radiance Constraint", Chinese Journal of Electronics 25(6), 1114-1120, 2016 (as [4] cites it).
    .. [6] K. He, J. Sun, X. Tang, "Single Image Haze Removal Using Dark Channel Prior", CVPR 2009,
       pp. 1956-1963 (the equation numbers used here).
    """
    _check_params(variant, patch, omega, t0, guided_radius, guided_eps)
    img, in_dtype = _as_float_rgb(image)
    channels = _VARIANTS[variant]

    dark = _dark_channel(img, channels, patch)                                  # [6] Eq. 5 / [2] (C = {G, B})
    A = _atmospheric_light(img, dark, channels)                                 # [6] Sec. 4.4
    A_safe = np.maximum(A, 1e-6).astype(np.float32)
    normalized = img / A_safe                                                   # I^c / A^c
    t_raw = 1.0 - np.float32(omega) * _dark_channel(normalized, channels, patch)  # [6] Eq. 12 (or 11) / [2]
    t_raw = t_raw.astype(np.float32, copy=False)
    if guided_radius > 0:
        grey = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        t = cv2.ximgproc.guidedFilter(grey, t_raw, int(guided_radius), float(guided_eps), -1)  # [3]
    else:
        t = t_raw
    t_bounded = np.maximum(t, np.float32(t0))[..., None]
    A32 = A.astype(np.float32)
    J = (img - A32) / t_bounded + A32                                           # [6] Eq. 16
    np.clip(J, 0.0, 1.0, out=J)

    if in_dtype == np.uint8:
        out = np.rint(J * 255.0).astype(np.uint8)
    else:
        out = J.astype(in_dtype, copy=False)
    return DehazeResult(image=out, transmission=np.asarray(t, dtype=np.float32), atmospheric_light=A)
