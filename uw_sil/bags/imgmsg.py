"""Conversion between ``sensor_msgs/Image`` / ``CompressedImage`` messages and RGB numpy arrays.

The functions take any object with the message's fields (an rclpy message, a rosbags message, a
``SimpleNamespace``), so the bag reader and the ROS nodes share one conversion and no ROS import is
needed here. The underwater image model works on 8-bit RGB: 8-bit colour and grey encodings are read as
they are, raw Bayer mosaics (``bayer_rggb8`` ..., as a camera driver's ``image_raw`` often is) are
demosaiced, and 16-bit encodings keep their high byte (a 16-bit image holds 0..65535 for 0..255; either byte
order).
"""
from __future__ import annotations

import numpy as np

__all__ = ["SUPPORTED_ENCODINGS", "image_to_rgb", "rgb_to_image_fields", "depth_to_image_fields", "compressed_to_rgb",
           "message_bytes", "image_to_depth", "image_to_mono", "rgb_to_compressed"]

# encoding -> (channels, order of R, G, B among the channels); mono is replicated.
_LAYOUT = {
    "rgb8": (3, (0, 1, 2)),
    "bgr8": (3, (2, 1, 0)),
    "rgba8": (4, (0, 1, 2)),
    "bgra8": (4, (2, 1, 0)),
    "mono8": (1, (0, 0, 0)),
    "8UC1": (1, (0, 0, 0)),
}

# Bayer mosaics (sensor_msgs names: the colours of the top-left 2x2 block, row by row) -> OpenCV's demosaicing
# code; OpenCV names a pattern by the second row's second and third pixels (as cv_bridge maps them)
_BAYER = {"rggb": "COLOR_BayerBG2RGB", "bggr": "COLOR_BayerRG2RGB", "gbrg": "COLOR_BayerGR2RGB",
          "grbg": "COLOR_BayerGB2RGB"}
# (not 16UC1: on an image topic that is a depth image in millimetres, REP 118's other encoding, not grey levels)
_LAYOUT16 = {"rgb16": "rgb8", "bgr16": "bgr8", "rgba16": "rgba8", "bgra16": "bgra8", "mono16": "mono8"}

#: Encodings :func:`image_to_rgb` accepts (``8UC1`` is read like ``mono8``).
SUPPORTED_ENCODINGS = (tuple(_LAYOUT) + tuple(f"bayer_{p}8" for p in _BAYER) + tuple(_LAYOUT16)
                       + tuple(f"bayer_{p}16" for p in _BAYER))


def message_bytes(data) -> np.ndarray:
    """The ``uint8[]`` field of a message as a 1-D uint8 array, without copying when possible.

    Accepts what the ROS Python stacks put there: a numpy array (rosbags), ``array.array('B')``
    (rclpy), ``bytes`` / ``bytearray`` / ``memoryview``, or a list of ints.
    """
    if isinstance(data, np.ndarray):
        if data.dtype != np.uint8:
            raise TypeError(f"image data must be uint8, got a {data.dtype} array")
        return data.reshape(-1)
    if isinstance(data, (list, tuple)):
        return np.asarray(data, dtype=np.uint8)
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except TypeError:
        raise TypeError(f"cannot read image data of type {type(data).__name__}") from None


def image_to_rgb(msg) -> np.ndarray:
    """RGB image of a ``sensor_msgs/Image``.

    Parameters
    ----------
    msg : object
        With ``height``, ``width``, ``encoding``, ``step`` and ``data`` (and ``is_bigendian`` for the
        16-bit encodings).

    Returns
    -------
    ndarray
        (height, width, 3) uint8, RGB order. ``bgr8``/``bgra8`` are reordered, alpha is dropped,
        ``mono8`` is replicated to three channels, Bayer mosaics are demosaiced (OpenCV, bilinear), 16-bit
        values keep their high byte. The result may share memory with ``msg.data``
        when no conversion is needed (``rgb8`` without row padding); treat it as read-only or copy.

    Raises
    ------
    ValueError
        Unknown encoding (the message names the supported ones), ``step`` shorter than a row, or
        ``len(data) != step * height``.
    """
    enc = str(msg.encoding)
    if enc not in SUPPORTED_ENCODINGS:
        raise ValueError(f"unsupported image encoding {enc!r}; supported: {', '.join(SUPPORTED_ENCODINGS)}")
    bayer = enc[6:10] if enc.startswith("bayer_") else None
    wide = enc in _LAYOUT16 or enc.endswith("16")
    base = "mono8" if bayer else (_LAYOUT16[enc] if enc in _LAYOUT16 else enc)
    ch, order = _LAYOUT[base]
    size = 2 if wide else 1
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise ValueError(f"image has no pixels: {w}x{h}")
    if step < w * ch * size:
        raise ValueError(f"image step {step} is shorter than a row of {w} {enc} pixels ({w * ch * size} bytes)")
    buf = message_bytes(msg.data)
    if buf.size != step * h:
        raise ValueError(f"image data has {buf.size} bytes, expected step*height = {step}*{h} = {step * h} "
                         f"for a {w}x{h} {enc} image")
    rows = buf.reshape(h, step)[:, : w * ch * size]
    if wide:        # the high byte of each 16-bit value (in the byte order the message states)
        rows = rows.reshape(h, w * ch, 2)[:, :, 0 if getattr(msg, "is_bigendian", 0) else 1]
    rows = rows.reshape(h, w, ch)
    if bayer:
        import cv2

        return cv2.cvtColor(np.ascontiguousarray(rows[:, :, 0]), getattr(cv2, _BAYER[bayer]))
    if base == "rgb8":
        return rows if rows.flags.c_contiguous else np.ascontiguousarray(rows)
    return np.ascontiguousarray(rows[:, :, list(order)])


def rgb_to_image_fields(arr: np.ndarray, encoding: str = "rgb8") -> dict:
    """Fields of a ``sensor_msgs/Image`` holding ``arr``.

    Parameters
    ----------
    arr : ndarray
        (H, W, 3) uint8 RGB, or (H, W) uint8 grey for ``mono8``.
    encoding : {'rgb8', 'bgr8', 'mono8'}
        Encoding of the message. ``bgr8`` reorders the channels.

    Returns
    -------
    dict
        ``height``, ``width``, ``encoding``, ``is_bigendian`` (0), ``step`` and ``data`` (``bytes``:
        assign it as is; rclpy converts ``bytes`` fast, while assigning an ndarray is ~400x slower).
    """
    a = np.asarray(arr)
    if a.dtype != np.uint8:
        raise ValueError(f"image must be uint8, got {a.dtype}")
    if encoding in ("rgb8", "bgr8"):
        if a.ndim != 3 or a.shape[2] != 3:
            raise ValueError(f"{encoding} needs an (H, W, 3) array, got shape {a.shape}")
        if encoding == "bgr8":
            a = a[:, :, ::-1]
        ch = 3
    elif encoding == "mono8":
        if a.ndim != 2:
            raise ValueError(f"mono8 needs an (H, W) array, got shape {a.shape}")
        ch = 1
    else:
        raise ValueError(f"cannot write encoding {encoding!r}; use rgb8, bgr8 or mono8")
    h, w = a.shape[:2]
    if h == 0 or w == 0:
        raise ValueError(f"image has no pixels: shape {a.shape}")
    return {"height": int(h), "width": int(w), "encoding": encoding, "is_bigendian": 0, "step": int(w * ch),
            "data": np.ascontiguousarray(a).tobytes()}


def depth_to_image_fields(depth: np.ndarray) -> dict:
    """Fields of a ``sensor_msgs/Image`` holding a depth image in the REP 118 convention.

    Parameters
    ----------
    depth : ndarray
        (H, W) planar depth in metres; ``+inf`` where nothing was hit (as
        :class:`uw_sil.sim.render.RenderResult` gives it), NaN where unknown.

    Returns
    -------
    dict
        ``height``, ``width``, ``encoding`` (``32FC1``), ``is_bigendian`` (0: the data are little-endian
        float32 whatever the machine), ``step`` (``4 * W``) and ``data`` (``bytes``).

    References
    ----------
    REP 118, Depth Images: 32-bit float metres; ``+Inf`` too far / nothing hit, ``-Inf`` too close, NaN
    invalid.
    """
    d = np.asarray(depth)
    if d.ndim != 2 or 0 in d.shape:
        raise ValueError(f"depth must be a non-empty (H, W) array, got shape {d.shape}")
    if not np.issubdtype(d.dtype, np.floating):
        raise ValueError(f"depth must be floating point metres, got {d.dtype}")
    h, w = d.shape
    return {"height": int(h), "width": int(w), "encoding": "32FC1", "is_bigendian": 0, "step": 4 * int(w),
            "data": np.ascontiguousarray(d, dtype="<f4").tobytes()}


def _rows(msg, bytes_per_pixel: int, what: str) -> tuple:
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise ValueError(f"{what} has no pixels: {w}x{h}")
    if step < w * bytes_per_pixel:
        raise ValueError(f"{what} step {step} is shorter than a row of {w} pixels ({w * bytes_per_pixel} bytes)")
    buf = message_bytes(msg.data)
    if buf.size != step * h:
        raise ValueError(f"{what} data has {buf.size} bytes, expected step*height = {step}*{h} = {step * h}")
    return buf.reshape(h, step)[:, : w * bytes_per_pixel], h, w


def image_to_depth(msg) -> np.ndarray:
    """(H, W) float32 depth in metres of a ``32FC1`` ``sensor_msgs/Image`` (REP 118; inverse of
    :func:`depth_to_image_fields`), either byte order, native-order copy. Other encodings: ValueError."""
    if str(msg.encoding) != "32FC1":
        raise ValueError(f"depth image encoding is {msg.encoding!r}, expected 32FC1 (REP 118 metres)")
    rows, h, w = _rows(msg, 4, "depth image")
    dt = ">f4" if int(msg.is_bigendian) else "<f4"
    return np.ascontiguousarray(rows).view(dt).reshape(h, w).astype(np.float32)


def image_to_mono(msg) -> np.ndarray:
    """(H, W) uint8 of a ``mono8`` / ``8UC1`` ``sensor_msgs/Image`` (e.g. ``sim/mask`` labels); may share
    memory with ``msg.data``. Other encodings: ValueError."""
    if str(msg.encoding) not in ("mono8", "8UC1"):
        raise ValueError(f"image encoding is {msg.encoding!r}, expected mono8 or 8UC1")
    rows, _, _ = _rows(msg, 1, "mono image")
    return rows


def compressed_to_rgb(msg) -> np.ndarray:
    """RGB image of a ``sensor_msgs/CompressedImage`` (JPEG or PNG, 8-bit), decoded with OpenCV.

    ``msg.format`` is e.g. ``"jpeg"``, ``"png"`` or ``"rgb8; jpeg compressed bgr8"`` (the form
    ``compressed_image_transport`` writes); the payload itself tells OpenCV the codec.
    """
    import cv2  # heavy: imported only where compressed images are actually read

    fmt = str(msg.format)
    if "compressedDepth" in fmt:
        raise ValueError(f"compressed depth images are not colour images (format {fmt!r})")
    buf = message_bytes(msg.data)
    if buf.size == 0:
        raise ValueError("compressed image has no data")
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"OpenCV could not decode the compressed image (format {fmt!r}, {buf.size} bytes)")
    if img.dtype != np.uint8:
        raise ValueError(f"compressed image decodes to {img.dtype}, only 8-bit images are supported")
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    if img.shape[2] == 4:
        return np.ascontiguousarray(img[:, :, 2::-1])
    return np.ascontiguousarray(img[:, :, ::-1])


def rgb_to_compressed(arr: np.ndarray, fmt: str = "jpeg", quality: int = 95) -> bytes:
    """Encode an RGB (or grey) uint8 image as the payload of a ``sensor_msgs/CompressedImage``.

    Parameters
    ----------
    arr : ndarray
        (H, W, 3) uint8 RGB or (H, W) uint8 grey.
    fmt : {'jpeg', 'png'}
        The message's ``format`` field should say the same (``compressed_image_transport`` writes
        ``"jpeg"`` / ``"png"``, or ``"rgb8; jpeg compressed bgr8"``).
    quality : int
        JPEG quality 1..100 (ignored for PNG, which is lossless).

    Returns
    -------
    bytes
    """
    import cv2

    a = np.asarray(arr)
    if a.dtype != np.uint8 or not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)) or 0 in a.shape:
        raise ValueError(f"image must be a non-empty (H, W, 3) or (H, W) uint8 array, got {a.dtype} {a.shape}")
    if fmt not in ("jpeg", "png"):
        raise ValueError(f"compressed format must be 'jpeg' or 'png', got {fmt!r}")
    bgr = a if a.ndim == 2 else np.ascontiguousarray(a[:, :, ::-1])
    params = [cv2.IMWRITE_JPEG_QUALITY, int(quality)] if fmt == "jpeg" else [cv2.IMWRITE_PNG_COMPRESSION, 3]
    ok, buf = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", bgr, params)
    if not ok:
        raise ValueError(f"OpenCV could not encode the image as {fmt}")
    return buf.tobytes()
