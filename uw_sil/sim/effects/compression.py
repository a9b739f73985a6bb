"""Compression: the JPEG round trip (block-DCT quantization) of compressed recordings.

Field bags store JPEG / MJPEG frames (H.264 intra frames quantize 4x4/8x8 integer transforms alike): a
fit whose simulated candidates are not compressed the same way is biased by the blocking and the lost
chroma detail. This effect runs the baseline JPEG pipeline of ITU-T T.81 / JFIF in floating point:

1. 8-bit scale: ``x = 255 * clip(I, 0, 1)``; RGB -> YCbCr (ITU-R BT.601 full range, as JFIF);
2. chroma 4:2:0 (``chroma >= 0.5``): Cb, Cr averaged over 2x2 boxes;
3. level shift by 128, 8x8 block DCT-II (orthonormal, which is the DCT of T.81 A.3.3);
4. quantization by the T.81 Annex K tables (K.1 luminance, K.2 chrominance) scaled by the IJG quality
   ``q`` (scale ``floor(5000 / q)`` below 50, ``200 - 2 q`` from 50; entries ``floor((t * scale + 50) / 100)``
   clamped to [1, 255]), rounding half away from zero, dequantization;
5. inverse DCT; chroma back to full size by the decoder's "fancy" upsampling of libjpeg (a triangle
   filter: bilinear with half-pixel centres, edges replicated); YCbCr -> RGB, clipped to [0, 255], / 255.

Sides that are not multiples of the MCU (8 px; 16 px with 4:2:0) are padded by edge replication, as
encoders do, and cropped afterwards. Pixel values are not rounded to 8 bits on either side (the
quantization of the DCT coefficients is the effect; 8-bit rounding of the decoded frame adds < 0.3 DN).
Against OpenCV's libjpeg (integer DCT, fixed-point colour conversion): see ``test/test_compression.py``.

Deterministic (no random numbers); not invertible. The default (``quality`` 100, ``chroma`` 0: q 100 at
4:4:4, whose quantization steps are all 1, i.e. < 0.5 DN per coefficient) is taken as lossless and
skipped, so the defaults leave the image unchanged.
"""
from __future__ import annotations

import numpy as np

from .base import Effect, EffectParam

__all__ = ["Compression", "jpeg_roundtrip", "quant_tables", "LUMA_TABLE", "CHROMA_TABLE"]

#: ITU-T T.81 Annex K, Table K.1: luminance quantization table (row = vertical frequency).
LUMA_TABLE = np.array([
    [16, 11, 10, 16, 24, 40, 51, 61],
    [12, 12, 14, 19, 26, 58, 60, 55],
    [14, 13, 16, 24, 40, 57, 69, 56],
    [14, 17, 22, 29, 51, 87, 80, 62],
    [18, 22, 37, 56, 68, 109, 103, 77],
    [24, 35, 55, 64, 81, 104, 113, 92],
    [49, 64, 78, 87, 103, 121, 120, 101],
    [72, 92, 95, 98, 112, 100, 103, 99]], dtype=np.float64)

#: ITU-T T.81 Annex K, Table K.2: chrominance quantization table.
CHROMA_TABLE = np.array([
    [17, 18, 24, 47, 99, 99, 99, 99],
    [18, 21, 26, 66, 99, 99, 99, 99],
    [24, 26, 56, 99, 99, 99, 99, 99],
    [47, 66, 99, 99, 99, 99, 99, 99],
    [99, 99, 99, 99, 99, 99, 99, 99],
    [99, 99, 99, 99, 99, 99, 99, 99],
    [99, 99, 99, 99, 99, 99, 99, 99],
    [99, 99, 99, 99, 99, 99, 99, 99]], dtype=np.float64)


def _dct_matrix() -> np.ndarray:
    """The orthonormal 8-point DCT-II matrix ``C`` (rows: frequency), ``F = C X C^T``."""
    k = np.arange(8)
    c = np.sqrt(2.0 / 8.0) * np.cos((2 * k[None, :] + 1) * k[:, None] * np.pi / 16.0)
    c[0] /= np.sqrt(2.0)
    return c.astype(np.float32)


_C = _dct_matrix()

# JFIF (ITU-R BT.601 full range): rows Y, Cb, Cr of R, G, B (offset 128 on Cb, Cr).
_RGB2YCC = np.array([[0.299, 0.587, 0.114],
                     [-0.168735892, -0.331264108, 0.5],
                     [0.5, -0.418687589, -0.081312411]], dtype=np.float32)
_YCC2RGB = np.array([[1.0, 0.0, 1.402],
                     [1.0, -0.344136286, -0.714136286],
                     [1.0, 1.772, 0.0]], dtype=np.float32)


def quant_tables(quality: float) -> tuple:
    """The (luminance, chrominance) 8x8 quantization steps of IJG quality ``quality`` in [1, 100].

    As libjpeg's ``jpeg_set_quality`` (baseline): scale ``floor(5000 / q)`` for ``q < 50`` else
    ``200 - 2 q`` (percent), entries ``floor((t * scale + 50) / 100)`` clamped to [1, 255] (the same
    tables as libjpeg, OpenCV and Pillow at integer ``q``). Non-integer qualities are allowed (for
    ``q >= 50`` the scale is then not an integer). Returns float32 arrays (8, 8).
    """
    q = float(quality)
    if not np.isfinite(q) or not 1.0 <= q <= 100.0:
        raise ValueError(f"JPEG quality must be in [1, 100], got {quality!r}")
    scale = np.floor(5000.0 / q) if q < 50 else 200.0 - 2.0 * q     # integer division in libjpeg
    out = []
    for t in (LUMA_TABLE, CHROMA_TABLE):
        out.append(np.clip(np.floor((t * scale + 50.0) / 100.0), 1.0, 255.0).astype(np.float32))
    return tuple(out)


def _pad(plane: np.ndarray, mh: int, mw: int) -> np.ndarray:
    """``plane`` (..., H, W) padded at the bottom/right by edge replication to multiples of (mh, mw)."""
    h, w = plane.shape[-2:]
    ph, pw = -h % mh, -w % mw
    if ph == 0 and pw == 0:
        return plane
    pad = [(0, 0)] * (plane.ndim - 2) + [(0, ph), (0, pw)]
    return np.pad(plane, pad, mode="edge")


def _quantize_blocks(planes: np.ndarray, table: np.ndarray) -> np.ndarray:
    """DCT, quantize, dequantize and inverse-DCT the 8x8 blocks of level-shifted ``planes`` (n, H, W),
    H and W multiples of 8, all blocks at once.

    The blocks are laid out as (8 rows, 8 columns, n_blocks) and the separable DCT ``F = C X C^T`` is two
    contractions over the leading axes, by ``np.einsum`` (its own loops, not BLAS): on a busy 2-core
    machine multi-threaded BLAS products of this shape were 10-20x slower than single-threaded ones, the
    einsum contractions 1.0 ms per 640x480 plane (single-threaded BLAS: 0.45 ms).
    """
    n, h, w = planes.shape
    nby, nbx = h // 8, w // 8
    x = planes.reshape(n, nby, 8, nbx, 8).transpose(2, 4, 0, 1, 3).reshape(8, 8, -1)   # (y, x, block)
    f = np.einsum("vx,uxm->uvm", _C, np.einsum("uy,yxm->uxm", _C, x))                   # (u, v, block)
    q = table[:, :, None]
    f /= q
    np.copysign(np.floor(np.abs(f) + 0.5), f, out=f)       # round half away from zero, as libjpeg
    f *= q
    y = np.einsum("uy,uxm->yxm", _C, np.einsum("vx,uvm->uxm", _C, f))                   # (y, x, block)
    return np.ascontiguousarray(y.reshape(8, 8, n, nby, nbx).transpose(2, 3, 0, 4, 1)).reshape(n, h, w)


def _downsample2(p: np.ndarray) -> np.ndarray:
    """2x2 box average of (n, H, W) with even H, W."""
    out = p[:, 0::2, 0::2] + p[:, 1::2, 0::2]
    out += p[:, 0::2, 1::2]
    out += p[:, 1::2, 1::2]
    out *= np.float32(0.25)
    return out


def _upsample2(p: np.ndarray) -> np.ndarray:
    """libjpeg's h2v2 "fancy" upsampling of (n, h, w) to (n, 2h, 2w): each output sample is 3/4 of the
    nearest input sample and 1/4 of the next one in each direction (edges replicated)."""
    n, h, w = p.shape
    e = np.pad(p, ((0, 0), (1, 1), (0, 0)), mode="edge")
    v = np.empty((n, h, 2, w), np.float32)
    v[:, :, 0] = 0.75 * p + 0.25 * e[:, :-2]
    v[:, :, 1] = 0.75 * p + 0.25 * e[:, 2:]
    v = v.reshape(n, 2 * h, w)
    e = np.pad(v, ((0, 0), (0, 0), (1, 1)), mode="edge")
    out = np.empty((n, 2 * h, w, 2), np.float32)
    out[..., 0] = 0.75 * v + 0.25 * e[:, :, :-2]
    out[..., 1] = 0.75 * v + 0.25 * e[:, :, 2:]
    return out.reshape(n, 2 * h, 2 * w)


def jpeg_roundtrip(img, quality: float, subsample: bool = True, channel_axis: int = -1) -> np.ndarray:
    """Compress and decompress an RGB image as baseline JPEG does (module docstring), in floating point.

    Parameters
    ----------
    img : array_like, float, values in [0, 1] (clipped)
        RGB image, ``(H, W, 3)`` with ``channel_axis=-1`` or planar ``(3, H, W)`` with ``channel_axis=0``.
    quality : float
        IJG quality in [1, 100] (libjpeg / OpenCV / Pillow ``quality``).
    subsample : bool
        True: chroma 4:2:0 (the default of libjpeg and of most cameras); False: 4:4:4.
    channel_axis : {-1, 0}
        Where the three channels are, in ``img`` and in the result.

    Returns
    -------
    ndarray float32, the shape of ``img``, values in [0, 1]
        The decoded image (not rounded to 8 bits).
    """
    if channel_axis not in (-1, 0, 2):
        raise ValueError(f"channel_axis must be -1 (or 2) or 0, got {channel_axis!r}")
    a = np.asarray(img, dtype=np.float32)
    planar = channel_axis == 0
    if a.ndim != 3 or a.shape[0 if planar else -1] != 3:
        raise ValueError(f"image must be {'(3, H, W)' if planar else '(H, W, 3)'} RGB, got shape {a.shape}")
    if not planar:
        a = np.moveaxis(a, -1, 0)
    _, h, w = a.shape
    if h < 1 or w < 1:
        raise ValueError(f"image is empty: shape {tuple(np.asarray(img).shape)}")
    qy, qc = quant_tables(quality)
    m = 16 if subsample else 8
    rgb = _pad(np.clip(a, 0.0, 1.0) * np.float32(255.0), m, m)
    ycc = np.einsum("ij,jhw->ihw", _RGB2YCC, rgb)              # (3, ph, pw), Cb/Cr centred on 0
    ycc[0] -= 128.0                                          # level shift (T.81 A.3.1)
    luma = _quantize_blocks(ycc[:1], qy)[0]
    if subsample:
        chroma = _upsample2(_quantize_blocks(_downsample2(ycc[1:]), qc))
    else:
        chroma = _quantize_blocks(ycc[1:], qc)
    luma += 128.0
    out = np.einsum("ij,jhw->ihw", _YCC2RGB, np.concatenate([luma[None], chroma])[:, :h, :w])
    np.clip(out, 0.0, 255.0, out=out)
    out *= np.float32(1.0 / 255.0)
    out = out.astype(np.float32, copy=False)
    return np.ascontiguousarray(out if planar else np.moveaxis(out, 0, -1))


class Compression(Effect):
    name = "compression"
    stage = "sensor"
    invertible = False
    random_per_frame = False
    summary = ("JPEG round trip: YCbCr, chroma 4:2:0, 8x8 block DCT quantized by the T.81 tables at IJG "
               "quality q (MJPEG/JPEG bags; last of the sensor stage)")
    params = (
        EffectParam("quality", 100.0, 1.0, 100.0, "", "IJG quality (libjpeg/OpenCV scale); 100 with chroma 0 "
                    "is taken as lossless (skipped)"),
        EffectParam("chroma", 0.0, 0.0, 1.0, "", "chroma subsampling, thresholded at 0.5: below 4:4:4, "
                    "from 0.5 4:2:0"),
    )
    severities = {
        "mild": {"quality": 90.0, "chroma": 1.0},
        "strong": {"quality": 50.0, "chroma": 1.0},
    }

    def is_identity(self, values):
        return values["quality"] >= 100.0 and values["chroma"] < 0.5

    def apply(self, terms, values, rng):
        terms.I = jpeg_roundtrip(terms.I, values["quality"], subsample=values["chroma"] >= 0.5, channel_axis=0)
