"""The underwater image model of the simulator (paper Eq. 1, plus Gazebo fog).

Per colour channel c, with ``r`` the Euclidean range and ``z`` the planar depth of a pixel,
``i`` the clean (in-air) radiance, ``a_c`` the attenuation, ``b_c`` the background (veiling light)
and ``f(z)`` the fog factor of density ``rho_F``:

    e_c(r) = exp(-r * a_c)                                         (transmission)
    I_c    = e_c(r) * [f(z) * i_c + (1 - f(z)) * b_c] + (1 - e_c(r)) * b_c     (Eq. 1 with fog)

Fog is applied to the rendered scene before attenuation, with the background as fog colour
(Gazebo's ``exp2`` fog ``f = exp(-(rho_F z)^2)`` by default, ``exp``: ``f = exp(-rho_F z)``).
Without fog (``rho_F = 0``, ``f = 1``) this is Eq. 1, ``I = i e + (1 - e) b`` (with the range for the
paper's z, below), as in the UUV Simulator camera plugin. Expanding the brackets gives the form used
for computation,

    I_c = b_c + T_c * (i_c - b_c),   T_c = e_c(r) * f(z),

one exponential per pixel and channel. Pixels where nothing was hit (``r = inf``) take ``b_c``.

The same model runs backwards on recorded frames (the paper's forward half, SIL dehazing, Sec. 4.2):
where the simulation has geometry, ``i_c = b_c + (I_c - b_c) / max(T_c, t0)`` (:func:`restore`, and
:class:`PreparedInverse` for the online per-frame path); other pixels are left as recorded.

Deviations from the paper [1]_ (Sec. 3.1, Eq. 1 ``i*_c = i_c e^{-z a_c} + (1 - e^{-z a_c}) b_c``;
Sec. 4.2, Eq. 5 ``t(z) = e^{-z a_c}``):

* Range instead of depth: the paper writes the exponent with "the distance z to the object projected
  on the camera pixel", taken from the simulator's depth camera. Here it is the Euclidean range ``r``
  of the pixel: light travels along the ray, and the UUV Simulator camera plugin whose model Eq. 1
  cites [2]_ also converts its depth image to range (``depth2rangeLUT``) before ``exp(-r a_c)``.
* Fog: the paper adds the fog of its simulator, Gazebo, with its density as the 7th parameter
  (Table 1), and says nothing of its law, its colour or how it combines with Eq. 1; the choices here
  are those above (``exp2`` on the planar depth, colour ``b``, on the rendered scene before the
  attenuation, as a renderer's fog acts).
* The inverse divides by ``max(T, t0)``: the paper solves Eq. 1 for ``i_c`` with Eq. 5 unbounded,
  which amplifies noise without limit on far pixels (see :class:`PreparedInverse`).

References
----------
.. [1] T. Doernbach, A. Gomez Chavez, C. A. Mueller and A. Birk, "High-Fidelity Deep-Sea Perception
   Using Simulation in the Loop", IFAC conference paper, 2018 (Eq. 1, Eq. 5, Table 1). ("the paper"
   throughout uw_sil.)
.. [2] M. Marcusso, S. Scherer, M. Voss, L. Douat and T. Rauschenbach, "UUV Simulator: A Gazebo-based
   package for underwater intervention and multi-robot simulation", OCEANS 2016 (Monterey), as the
   paper cites it; the simulator's ``UnderwaterCameraROSPlugin`` (``uuv_sensor_ros_plugins``) applies
   Eq. 1 per RGB channel on the range.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from .params import validate_rgb_params

__all__ = ["transmission", "fog_factor", "degrade", "PreparedRender", "FOG_MODES", "invert_transmission",
           "restoration_gain", "restore",
           "PreparedInverse"]

FOG_MODES = ("exp2", "exp", "none")


def _check_distance(name: str, arr) -> None:
    """Ranges and depths are >= 0 metres or +inf (nothing hit); NaN and negative values are refused."""
    arr = np.asarray(arr)
    bad = np.isnan(arr) | (arr < 0)
    if bad.any():
        first = tuple(int(i) for i in np.argwhere(bad)[0])
        n_nan, n_neg = int(np.isnan(arr).sum()), int((arr < 0).sum())
        raise ValueError(f"{name} has {n_nan} NaN and {n_neg} negative value(s) (first at index {first}: "
                         f"{float(arr[first])}): must be >= 0 metres, or +inf where nothing was hit")


def transmission(range_m, a) -> np.ndarray:
    """Direct transmission ``exp(-r * a_c)`` (Eq. 1), shape (..., 3); 0 where ``r = inf``.

    Raises ValueError for NaN or negative ranges and for attenuations that are negative or not finite.
    """
    _check_distance("range", range_m)
    a_in = np.asarray(a, dtype=float)
    if not np.all(np.isfinite(a_in)) or np.any(a_in < 0):
        raise ValueError(f"attenuation must be finite and >= 0 (1/m), got {a_in.tolist()}")
    r = np.asarray(range_m, dtype=np.float32)[..., None]
    a = a_in.astype(np.float32)
    with np.errstate(invalid="ignore"):
        e = np.exp(-r * a)
    return np.where(np.isfinite(r), e, np.float32(0.0))


def fog_factor(depth_m, rho_f: float, mode: str = "exp2") -> np.ndarray:
    """Fraction of the scene radiance that survives fog at planar depth ``z``; 0 where ``z = inf``.

    ``exp2``: ``exp(-(rho_F z)^2)`` (Gazebo's default), ``exp``: ``exp(-rho_F z)``, ``none``: 1.
    """
    _check_distance("depth", depth_m)
    z = np.asarray(depth_m, dtype=np.float32)
    if mode not in FOG_MODES:
        raise ValueError(f"unknown fog mode {mode!r}; expected one of {FOG_MODES}")
    if rho_f < 0 or not np.isfinite(rho_f):
        raise ValueError(f"fog density must be finite and >= 0, got {rho_f}")
    finite = np.isfinite(z)
    zf = np.where(finite, z, np.float32(0.0))
    if mode == "exp2":
        f = np.exp(-np.square(np.float32(rho_f) * zf))
    elif mode == "exp":
        f = np.exp(-np.float32(rho_f) * zf)
    else:
        f = np.ones_like(zf)
    return np.where(finite, f, np.float32(0.0))


def _check_render(rgb, range_m, depth_m):
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"clean image must be (H, W, 3), got shape {rgb.shape}")
    if not np.issubdtype(rgb.dtype, np.floating):
        raise TypeError(f"clean image must be float in [0, 1], got dtype {rgb.dtype}")
    range_m = np.asarray(range_m)
    depth_m = np.asarray(depth_m)
    for name, arr in (("range", range_m), ("depth", depth_m)):
        if arr.shape != rgb.shape[:2]:
            raise ValueError(f"{name} shape {arr.shape} does not match image shape {rgb.shape[:2]}")
        _check_distance(name, arr)
    return rgb, range_m, depth_m


def degrade(rgb, range_m, depth_m, params, fog: str = "exp2") -> np.ndarray:
    """Apply the underwater model (Eq. 1 with fog) to a clean render.

    Parameters
    ----------
    rgb : ndarray (H, W, 3), float
        Clean render in [0, 1].
    range_m, depth_m : ndarray (H, W)
        Euclidean range and planar depth in metres, ``inf`` where nothing was hit.
    params : array_like (7,) or (N, 7)
        rgb parameter vectors ``(a_r, a_g, a_b, b_r, b_g, b_b, rho_f)``.
    fog : {'exp2', 'exp', 'none'}

    Returns
    -------
    ndarray (H, W, 3) or (N, H, W, 3), float32 in [0, 1].

    Notes
    -----
    For many parameter sets on the same render (an optimizer's inner loop) build a
    :class:`PreparedRender` once and call it instead: it skips the validation and the water pixels.
    """
    return PreparedRender(rgb, range_m, depth_m, fog=fog)(params)


class PreparedRender:
    """A clean render cached for applying many parameter sets quickly (the optimizer's inner loop).

    Computation runs per channel on contiguous planes, and only on the pixels where the model is hit
    (water pixels are ``b_c``, exactly what the full-plane arithmetic gives them: transmission 0).

    Parameters
    ----------
    rgb, range_m, depth_m, fog : as in :func:`degrade`.
    cover : ndarray (H, W), optional
        Fraction of each pixel on the model, for box-downsampled renders whose ``rgb``, range and depth
        are averages over the model part of each block: ``I_c = b_c + cover * T_c * (i_c - b_c)``, the
        block average of the full-resolution model when ``T_c`` is constant over the block. Default: 1
        where the model is hit (finite range and depth), else 0.
    """

    def __init__(self, rgb, range_m, depth_m, fog: str = "exp2", cover=None):
        rgb, range_m, depth_m = _check_render(rgb, range_m, depth_m)
        if fog not in FOG_MODES:
            raise ValueError(f"unknown fog mode {fog!r}; expected one of {FOG_MODES}")
        self.shape = rgb.shape
        self.fog = fog
        hit = np.isfinite(range_m) & np.isfinite(depth_m)
        if cover is not None:
            cover = np.asarray(cover, dtype=np.float32)
            if cover.shape != hit.shape or not np.all((cover >= 0) & (cover <= 1)):
                raise ValueError(f"cover must be ({hit.shape[0]}, {hit.shape[1]}) fractions in [0, 1]")
            hit = hit & (cover > 0)
        self.hit = hit
        self.mask = hit.astype(np.float32) if cover is None else np.where(hit, cover, np.float32(0.0))
        self.r = np.where(hit, range_m, 0).astype(np.float32)
        z = np.where(hit, depth_m, 0).astype(np.float32)
        self.zf = z * z if fog == "exp2" else z                      # fog exponent grows with this
        self.planes = np.ascontiguousarray(np.moveaxis(rgb.astype(np.float32), 2, 0))  # (3, H, W)
        # the hit pixels alone, for the inner loop (water pixels are b_c)
        self._idx = np.flatnonzero(hit)
        self._r = self.r.ravel()[self._idx]
        self._zf = self.zf.ravel()[self._idx]
        self._cover = None if cover is None or np.all(self.mask.ravel()[self._idx] == 1) \
            else self.mask.ravel()[self._idx]
        self._i = self.planes.reshape(3, -1)[:, self._idx]

    @property
    def hit_fraction(self) -> float:
        return float(self.hit.mean())

    def work_buffers(self) -> tuple:
        """Work buffers for :meth:`planar`; one set per thread (a PreparedRender may be shared by threads)."""
        n = self._idx.size
        return np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.float32)

    def planar(self, params, out=None, work=None) -> np.ndarray:
        """Degraded image for one rgb parameter vector (7,), as planes (3, H * W) float32 in [0, 1].

        The parameters are used as float32 and not validated (the batched :meth:`__call__` validates).
        ``work``: buffers of :meth:`work_buffers` to reuse (default: new ones).
        """
        a_r, a_g, a_b, b_r, b_g, b_b, rho = np.asarray(params, dtype=np.float32)
        h, w, _ = self.shape
        if out is None:
            out = np.empty((3, h * w), dtype=np.float32)
        t, fz, d = self.work_buffers() if work is None else work
        if self.fog == "none" or rho == 0:
            fz.fill(0.0)
        else:
            np.multiply(self._zf, rho * rho if self.fog == "exp2" else rho, out=fz)
        for c, (a, b) in enumerate(((a_r, b_r), (a_g, b_g), (a_b, b_b))):
            np.multiply(self._r, a, out=t)              # optical thickness r a_c + fog term
            t += fz
            np.negative(t, out=t)
            np.exp(t, out=t)                            # T_c = e_c(r) f(z)
            if self._cover is not None:
                t *= self._cover                        # area-exact: the block's share on the model
            np.subtract(self._i[c], b, out=d)
            t *= d
            t += b                                      # I_c = b_c + T_c (i_c - b_c): paper Eq. 1 with fog
            out[c].fill(b)                              # no hit: T = 0
            out[c, self._idx] = t
        return out

    def __call__(self, params, out=None) -> np.ndarray:
        """Degraded image(s) for (7,) or (N, 7) rgb parameter vectors: (H, W, 3) or (N, H, W, 3) float32."""
        p = np.asarray(params, dtype=float)
        single = p.ndim == 1
        p = validate_rgb_params(np.atleast_2d(p)).astype(np.float32)
        h, w, _ = self.shape
        if out is None:
            out = np.empty((p.shape[0], h, w, 3), dtype=np.float32)
        elif single and out.ndim == 3:
            out = out[None]                             # a view: results land in the caller's array
        planes = np.empty((3, h * w), dtype=np.float32)
        for k in range(p.shape[0]):
            self.planar(p[k], out=planes)
            out[k] = np.moveaxis(planes.reshape(3, h, w), 0, -1)
        return out[0] if single else out


# ================================================================================== the inverse


def invert_transmission(image, b, T, t0: float = 0.1) -> np.ndarray:
    """Paper Eq. 1 solved for the clean radiance (Sec. 4.2): ``i = b + (I - b) / max(T, t0)`` (elementwise).

    The one place of the inverse equation: :func:`restore`, :class:`PreparedInverse` (as the gain map
    ``1 / max(T, t0)``) and :meth:`uw_sil.sim.model.UnderwaterModel.restore` (after removing the
    backscatter its effects add) all restore through it. ``t0`` bounds the gain (see
    :class:`PreparedInverse`).
    """
    T = np.asarray(T, dtype=np.float32)
    return b + (np.asarray(image, dtype=np.float32) - b) / np.maximum(T, np.float32(_check_t0(t0)))


def restoration_gain(range_m, depth_m, params, fog: str = "exp2", t0: float = 0.1, hit=None) -> np.ndarray:
    """Gain ``g_c = 1 / max(T_c, t0)`` of the inverse model, (H, W, 3) float32; 1 where nothing was hit.

    ``T_c = e_c(r) f(z)`` is the transmission of :func:`degrade`. Reference implementation (plain
    numpy, any size); :class:`PreparedInverse` computes the same faster.
    """
    p = validate_rgb_params(np.asarray(params, dtype=float).reshape(7))
    _check_t0(t0)
    r = np.asarray(range_m, dtype=np.float32)
    z = np.asarray(depth_m, dtype=np.float32)
    if hit is None:
        hit = np.isfinite(r) & np.isfinite(z)
    T = transmission(np.where(hit, r, np.inf), p[0:3]) * fog_factor(np.where(hit, z, 0), p[6], fog)[..., None]
    g = np.float32(1.0) / np.maximum(T, np.float32(t0))
    return np.where(np.asarray(hit)[..., None], g, np.float32(1.0)).astype(np.float32)


def restore(image, range_m, depth_m, params, fog: str = "exp2", t0: float = 0.1, hit=None, b=None) -> np.ndarray:
    """Invert the underwater model on the pixels with geometry (reference implementation).

    ``i_c = b_c + (I_c - b_c) / max(T_c, t0)`` where ``hit`` (default: finite range and depth), ``I``
    unchanged elsewhere, clamped to [0, 1]. ``image`` is (H, W, 3) float in [0, 1]; ``b`` overrides the
    background of ``params``. Returns float32. See :class:`PreparedInverse` for ``t0`` and speed.
    """
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"image must be (H, W, 3), got shape {img.shape}")
    p = validate_rgb_params(np.asarray(params, dtype=float).reshape(7)).copy()
    if b is not None:
        p[3:6] = np.asarray(b, dtype=float).reshape(3)
        validate_rgb_params(p)
    r = np.asarray(range_m, dtype=np.float32)
    z = np.asarray(depth_m, dtype=np.float32)
    if hit is None:
        hit = np.isfinite(r) & np.isfinite(z)
    T = transmission(np.where(hit, r, np.inf), p[0:3]) * fog_factor(np.where(hit, z, 0), p[6], fog)[..., None]
    out = invert_transmission(img, p[3:6].astype(np.float32), T, t0)
    out = np.where(np.asarray(hit)[..., None], out, img)
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def _check_t0(t0) -> float:
    t0 = float(t0)
    if not 0.0 < t0 <= 1.0:
        raise ValueError(f"t0 (lowest transmission divided by) must lie in (0, 1], got {t0}")
    return t0


class PreparedInverse:
    """The inverse of the underwater model for one frame's geometry, prepared for restoring recorded frames
    fast (the enhancer's per-frame work: one geometry, one parameter set, one image).

    On pixels with geometry (``hit``), per channel c::

        i_c = b_c + (I_c - b_c) * g_c,     g_c = 1 / max(T_c, t0) = exp(min(a_c r + phi(z), ln(1/t0)))

    with ``T_c = e_c(r) f(z)`` and ``phi(z) = (rho_F z)^2`` (``exp2`` fog), ``rho_F z`` (``exp``) or 0; every
    other pixel keeps its recorded value. The result is clamped to [0, 1] and returned in the input's
    encoding (uint8 rounded to nearest, or float32).

    ``t0`` and the gain cap: the gain ``1/T`` grows exponentially with range (``exp(a_r r)``: 8 at 5 m for
    ``a_r = 0.42``/m) and multiplies the camera noise and any model error with it. ``t0`` caps the gain at
    ``1/t0`` (10 for the default 0.1, He et al.'s lower bound of the transmission); where ``T < t0`` (far
    pixels) the restoration is partial: the pixel moves towards the clean radiance by the factor ``1/t0``
    only, and its noise is amplified ``1/t0`` times (2 grey levels of camera noise become 20).

    Speed: only the bounding box of the geometry is computed (everything else is copied); every map is
    float32 in buffers kept between frames (allocating 4 MB arrays per frame costs page faults, several
    ms); the arithmetic is OpenCV's (vectorized, no Python per pixel: one ``cv2.transform`` gives the
    optical thickness of all three channels); the gain map is cached for the last ``(params, t0)``.

    Examples
    --------
    >>> inv = PreparedInverse().set_geometry(render.range, render.depth)          # doctest: +SKIP
    >>> clean = inv(recorded_uint8, params.as_vector(), t0=0.1)                    # doctest: +SKIP
    """

    def __init__(self):
        self.shape = None
        self._gain_key = None
        self._cap = 0

    def _view(self, name: str, shape, dtype) -> np.ndarray:
        """A contiguous array of ``shape`` on a buffer kept between frames (grown when needed)."""
        n = int(np.prod(shape))
        buf = self.__dict__.get("_buf_" + name)
        if buf is None or buf.size < n or buf.dtype != dtype:
            buf = np.empty(max(n, self._cap), dtype)
            self.__dict__["_buf_" + name] = buf
        return buf[:n].reshape(shape)

    def set_geometry(self, range_m, depth_m, hit=None, fog: str = "exp2") -> "PreparedInverse":
        """Take a new frame's geometry: range and planar depth (H, W) in metres, ``inf`` where nothing was hit.

        ``hit`` (H, W) bool: the pixels to restore (default: finite range and depth); range and depth must
        be finite there. Returns self.
        """
        import cv2

        if fog not in FOG_MODES:
            raise ValueError(f"unknown fog mode {fog!r}; expected one of {FOG_MODES}")
        r = np.asarray(range_m, dtype=np.float32)
        z = np.asarray(depth_m, dtype=np.float32)
        if r.ndim != 2 or r.shape != z.shape:
            raise ValueError(f"range {r.shape} and depth {z.shape} must be (H, W) arrays of one shape")
        if hit is None:
            hit = np.isfinite(r) & np.isfinite(z)
        else:
            hit = np.asarray(hit, dtype=bool)
            if hit.shape != r.shape:
                raise ValueError(f"hit mask {hit.shape} does not match the geometry {r.shape}")
        self.shape = r.shape
        self._cap = max(self._cap, r.size * 3)
        self.fog = fog
        self.hit = hit
        hit_u8 = hit.view(np.uint8)
        x, y, w, h = cv2.boundingRect(hit_u8)
        self.roi = (slice(y, y + h), slice(x, x + w)) if w > 0 and h > 0 else None
        self._gain_key = None
        if self.roi is None:
            return self
        m = np.ascontiguousarray(hit_u8[self.roi])
        rr = self._view("r", (h, w), np.float32)
        zf = self._view("zf", (h, w), np.float32)
        rr.fill(0.0)
        cv2.copyTo(r[self.roi], m, rr)
        zf.fill(0.0)
        if fog == "exp2":
            zr = z[self.roi]
            cv2.copyTo(cv2.multiply(zr, zr, dst=self._view("tmp", (h, w), np.float32)), m, zf)
        elif fog == "exp":
            cv2.copyTo(z[self.roi], m, zf)
        if not (np.isfinite(rr).all() and np.isfinite(zf).all()):
            raise ValueError("range and depth must be finite on the pixels to restore")
        self._rz = cv2.merge([rr, zf], dst=self._view("rz", (h, w, 2), np.float32))
        return self

    @property
    def hit_fraction(self) -> float:
        return float(np.count_nonzero(self.hit)) / self.hit.size

    def gain(self, params, t0: float = 0.1) -> Optional[np.ndarray]:
        """Gain map ``g`` (h, w, 3) float32 over the geometry's bounding box (:attr:`roi`) for rgb parameters
        ``params`` (7,), 1 off the geometry; None without geometry. Cached for the last call and reused
        between calls: copy it to keep it."""
        import cv2

        if self.shape is None:
            raise RuntimeError("set_geometry() first")
        p = np.asarray(params, dtype=float).reshape(7)
        key = (tuple(p[[0, 1, 2, 6]]), float(t0))
        if key == self._gain_key:
            return self._g
        validate_rgb_params(p)
        kmax = -np.log(_check_t0(t0))
        if self.roi is None:
            self._g, self._gain_key = None, key
            return None
        rho = p[6]
        phi = rho * rho if self.fog == "exp2" else rho if self.fog == "exp" else 0.0
        M = np.array([[p[0], phi], [p[1], phi], [p[2], phi]], np.float64)
        h, w = self._rz.shape[:2]
        g = cv2.transform(self._rz, M, dst=self._view("g", (h, w, 3), np.float32))  # a_c r + phi(z), per channel
        cv2.min(g, (float(kmax),) * 4, dst=g)                 # gain cap 1/t0 (a Scalar per channel)
        cv2.exp(g, dst=g)                                     # 1 / max(T_c, t0); 1 off the geometry (r = z = 0)
        self._g, self._gain_key = g, key
        return g

    def __call__(self, image, params, t0: float = 0.1, b=None) -> np.ndarray:
        """Restored image (new array, the input's dtype: uint8 or float32) of a recorded (H, W, 3) frame."""
        import cv2

        img = np.asarray(image)
        if self.shape is None:
            raise RuntimeError("set_geometry() first")
        if img.shape != self.shape + (3,):
            raise ValueError(f"image shape {img.shape} does not match the geometry {self.shape} (+ 3 channels)")
        p = np.asarray(params, dtype=float).reshape(7)
        bb = p[3:6] if b is None else np.asarray(b, dtype=float).reshape(3)
        if not (np.isfinite(bb).all() and (bb >= 0).all() and (bb <= 1).all()):
            raise ValueError(f"background b must be 3 values in [0, 1], got {bb.tolist()}")
        g = self.gain(p, t0)
        if img.dtype == np.uint8:
            out = img.copy()
            if g is None:
                return out
            B = (float(bb[0]) * 255.0, float(bb[1]) * 255.0, float(bb[2]) * 255.0, 0.0)
            d = cv2.subtract(img[self.roi], B, dst=self._view("d", g.shape, np.float32), dtype=cv2.CV_32F)
            cv2.multiply(d, g, dst=d)
            o8 = cv2.add(d, B, dst=self._view("o8", g.shape, np.uint8), dtype=cv2.CV_8U)  # rounds, saturates
            out[self.roi] = o8                                 # off-geometry: g = 1 gives back I exactly
            return out
        if not np.issubdtype(img.dtype, np.floating):
            raise TypeError(f"image must be uint8 or float in [0, 1], got {img.dtype}")
        f = img.astype(np.float32)
        if g is None:
            return f
        B = (float(bb[0]), float(bb[1]), float(bb[2]), 0.0)
        roi = f[self.roi]
        res = cv2.add(cv2.multiply(cv2.subtract(roi, B), g), B)
        np.clip(res, 0.0, 1.0, out=res)
        np.copyto(roi, res, where=self.hit[self.roi][..., None])   # float: off-geometry pixels bit-exact
        return f
