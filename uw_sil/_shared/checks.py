"""Input checks shared by the image-quality criteria (FSIM, histograms, theta) and other rooms.

Images are numpy arrays of dtype uint8, or float32/float64 in the 0..255 range, grey ``(H, W)`` or
RGB ``(H, W, 3)``; masks are boolean ``(H, W)``. Each check raises with a message naming the input.
"""
from __future__ import annotations

import numpy as np

__all__ = ["as_unit_rgb", "check_image", "check_mask", "check_values"]


def check_values(arr: np.ndarray, name: str) -> None:
    """Raise unless a float array is finite and within [0, 255] (uint8 always passes).

    Two passes: NaN propagates through ``min``/``max``, so it fails the range test too.
    """
    if arr.dtype == np.uint8 or arr.size == 0:
        return
    lo, hi = arr.min(), arr.max()
    if lo >= 0.0 and hi <= 255.0:
        return
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise ValueError(f"{name} contains NaN or inf")
    raise ValueError(
        f"{name} must have values in [0, 255] (got {lo:g}..{hi:g}); "
        "clip simulated images and scale 0..1 floats by 255"
    )


def check_image(img, name: str, *, allow_batch: bool = False, values: bool = True) -> np.ndarray:
    """Validate one image (or a candidate stack) and return it.

    Accepted: numpy arrays of dtype uint8, or float32/float64 with finite values in [0, 255];
    grey ``(H, W)`` or RGB ``(H, W, 3)`` (with ``allow_batch`` also ``(N, H, W, 3)``); both
    sides at least 2. ``values=False`` skips the value scan (done later on a working copy).
    """
    if not isinstance(img, np.ndarray):
        raise TypeError(f"{name} must be a numpy array, got {type(img).__name__}")
    if img.dtype not in (np.uint8, np.float32, np.float64):
        raise TypeError(f"{name} must be uint8, float32 or float64, got dtype {img.dtype}")
    ndim_ok = img.ndim in (2, 3) or (allow_batch and img.ndim == 4)
    if not ndim_ok or (img.ndim >= 3 and img.shape[-1] != 3):
        want = "(H, W), (H, W, 3)" + (" or (N, H, W, 3)" if allow_batch else "")
        raise ValueError(f"{name} must have shape {want}, got {img.shape}")
    rows, cols = (img.shape[-2], img.shape[-1]) if img.ndim == 2 else img.shape[-3:-1]
    if img.size == 0:
        raise ValueError(f"{name} is empty (shape {img.shape})")
    if rows < 2 or cols < 2:
        raise ValueError(f"{name} must be at least 2x2 pixels, got {rows}x{cols}")
    if values:
        check_values(img, name)
    return img


def check_mask(mask, shape) -> np.ndarray:
    """A boolean (rows, cols) mask, or a clear error."""
    m = np.asarray(mask)
    if m.dtype != bool:
        raise TypeError(f"mask must be a boolean array, got dtype {m.dtype}")
    if m.shape != tuple(shape):
        raise ValueError(f"mask must have shape {tuple(shape)}, got {m.shape}")
    return m


def as_unit_rgb(image, dtype=np.float32) -> np.ndarray:
    """An RGB image ``(H, W, 3)`` as floats of ``dtype`` on the [0, 1] scale.

    uint8 is scaled by 1/255; floats must be finite and within [0, 1] (1e-6 of slack, then clipped).
    Anything else raises ValueError naming what is wrong.
    """
    arr = np.asarray(image)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"image must be an RGB array of shape (H, W, 3), got shape {arr.shape}")
    if arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"image must not be empty, got shape {arr.shape}")
    if arr.dtype == np.uint8:
        if np.dtype(dtype) == np.float32:
            return arr.astype(np.float32) * np.float32(1.0 / 255.0)
        return arr.astype(dtype) / 255.0
    if not np.issubdtype(arr.dtype, np.floating):
        raise ValueError(f"image dtype must be uint8 (0-255) or floating point (0-1), got {arr.dtype}")
    if not np.isfinite(arr).all():
        raise ValueError("image contains NaN or infinite values")
    lo, hi = float(arr.min()), float(arr.max())
    if lo < -1e-6 or hi > 1.0 + 1e-6:
        raise ValueError(f"float image values must lie in [0, 1], found [{lo:.4g}, {hi:.4g}]")
    return np.clip(arr.astype(dtype, copy=False), 0.0, 1.0)
