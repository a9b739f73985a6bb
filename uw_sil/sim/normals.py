"""Normals of planar faces from a planar depth map: the renderer's Lambert shading and the effects' geometry.

On a plane ``n . X = d`` seen through a pinhole the inverse depth ``w = 1/z`` is affine in the normalized image
coordinates ``xt = (u - cx)/fx``, ``yt = (v - cy)/fy``: ``w = (n_x xt + n_y yt + n_z) / d``. Hence

    n / d = (fx dw/du, fy dw/dv, w - xt fx dw/du - yt fy dw/dv)

with ``n`` pointing away from the camera. The derivatives are one-sided differences towards the neighbour of the
same part with the smaller change, so they never cross a silhouette or a change of part (exact on planar faces
up to rounding); a pixel with no neighbour of its part gets 0 (it counts as facing the camera).
"""
from __future__ import annotations

import numpy as np

__all__ = ["one_sided_derivative", "plane_terms"]


def one_sided_derivative(w: np.ndarray, part_ids: np.ndarray, axis: int) -> np.ndarray:
    """(H, W) float32 derivative of ``w`` along ``axis`` (1: columns, 0: rows): per pixel the forward or the
    backward difference within its part, the one of smaller magnitude (the forward one on a tie), 0 where neither
    neighbour is of the same part."""
    inf = np.float32(np.inf)
    n = w.shape[axis]

    def cut(a, lo, hi):          # a[lo:hi] along the axis
        return a[:, lo:hi] if axis == 1 else a[lo:hi]

    # E[j + 1] = w[j + 1] - w[j] within a part, inf across parts and beyond the image (along the axis): pixel j's
    # forward difference is E[j + 1], its backward one E[j]
    shape = list(w.shape)
    shape[axis] = n + 1
    E = np.empty(shape, np.float32)
    cut(E, 0, 1)[...] = inf
    cut(E, n, n + 1)[...] = inf
    d = cut(E, 1, n)
    np.subtract(cut(w, 1, n), cut(w, 0, n - 1), out=d)
    np.copyto(d, inf, where=cut(part_ids, 1, n) != cut(part_ids, 0, n - 1))
    A = np.abs(E)
    out = np.where(cut(A, 1, n + 1) <= cut(A, 0, n), cut(E, 1, n + 1), cut(E, 0, n))
    np.copyto(out, np.float32(0.0), where=np.isinf(out))
    return out


def plane_terms(w: np.ndarray, part_ids: np.ndarray, fx: float, fy: float, xt: np.ndarray, yt: np.ndarray):
    """``(mx, my, mz)``, each (H, W) float32: ``n / d`` of the module's formula from the inverse depth ``w`` (0
    where nothing is hit) and the parts; ``xt`` (1, W) and ``yt`` (H, 1) the normalized image coordinates."""
    mx = np.float32(fx) * one_sided_derivative(w, part_ids, 1)
    my = np.float32(fy) * one_sided_derivative(w, part_ids, 0)
    mz = w - xt * mx - yt * my
    return mx, my, mz
