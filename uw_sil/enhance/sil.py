"""Dehazing recorded frames with the simulation (SIL, the paper's forward half), behind one interface with
the image-only baselines DCP and UDCP.

``method='sil'`` inverts the fitted underwater model with the simulated geometry of the frame (depth and
object mask rendered at the recorded pose)::

    i_c = b_c + (I_c - b_c) / max(T_c, t0),   T_c = exp(-a_c r) f(z)           (object pixels)

and leaves every pixel the simulation has no geometry for as recorded (water, and anything the scene
model lacks, such as a seafloor). The inverse is the model's own: :class:`uw_sil.sim.optics.PreparedInverse`
for the 7-parameter model, ``UnderwaterModel.restore`` when the model carries effects. ``method='dcp'``
and ``'udcp'`` run :func:`uw_sil.enhance.dcp.dehaze_dcp` (He et al. 2011; Drews et al. 2013) on the
image alone.

The background ``b``: the fitted one, or with ``b_from_frame`` re-estimated on every frame from the real
water pixels (:func:`estimate_background`: the sim's water mask eroded by ``erode_px``, per-channel
median), for drifting lamps or turbidity. The paper takes "the average intensity value of the free
(water) region" of the frame (Sec. 4.2); the erosion and the median are ours (reasons there). A frame
without enough water falls back to the fitted ``b``, with a warning in :attr:`EnhanceResult.warnings`.

``t0`` (default 0.1) caps the gain ``1/T`` at ``1/t0``: far pixels are restored only partly and their
noise is amplified by up to ``1/t0`` (see :class:`~uw_sil.sim.optics.PreparedInverse`).

References
----------
.. [1] T. Doernbach, A. Gomez Chavez, C. A. Mueller and A. Birk, "High-Fidelity Deep-Sea Perception
   Using Simulation in the Loop", IFAC conference paper, 2018 (Sec. 4.2: Eq. 5 and Eq. 1 solved for
   ``i_c``; Sec. 4.3, Fig. 4, Table 2).
.. [2] K. He, J. Sun, X. Tang, "Single Image Haze Removal Using Dark Channel Prior", IEEE TPAMI
   33(12):2341-2353, 2011.
.. [3] P. Drews Jr., E. do Nascimento, F. Moraes, S. Botelho, M. Campos, "Transmission Estimation in
   Underwater Single Images", ICCV Workshops 2013.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from ..sim.camera import CameraModel
from ..sim.optics import FOG_MODES, PreparedInverse
from ..sim.params import RGB_NAMES, UnderwaterParams

__all__ = ["METHODS", "EnhanceResult", "Enhancer", "enhance", "estimate_background", "frame_geometry",
           "load_model_yaml", "load_params_yaml", "model_from_parameters", "model_parts"]

METHODS = ("sil", "dcp", "udcp")
#: Water pixels closer than this to the sim's object silhouette are not used to estimate ``b``.
ERODE_PX = 8
#: Fewest (subsampled) water pixels for a per-frame ``b``.
MIN_WATER_PIXELS = 400


@dataclass
class EnhanceResult:
    """One enhanced frame.

    Attributes
    ----------
    image : ndarray (H, W, 3)
        The enhanced frame in the input's encoding (uint8, or float32 in [0, 1]).
    method : str
    restored_fraction : float
        Fraction of the frame's pixels the method restored: for SIL the pixels with sim geometry (the
        rest are left as recorded); 1.0 for DCP/UDCP, which change every pixel.
    restored_mask : ndarray (H, W) bool or None
        SIL: the restored pixels.
    background : tuple of 3 floats
        SIL: ``b`` used; DCP/UDCP: the atmospheric light ``A`` (both on the [0, 1] scale).
    b_source : str
        ``'fit'``, ``'frame'`` (re-estimated from the water), ``'fit (no water)'`` or ``'image'`` (DCP).
    skipped : tuple of str
        Effects of the model that the inverse cannot undo (``UnderwaterModel.restore``).
    warnings : tuple of str
    """

    image: np.ndarray
    method: str
    restored_fraction: float
    restored_mask: Optional[np.ndarray] = None
    background: tuple = ()
    b_source: str = ""
    skipped: tuple = ()
    warnings: tuple = field(default_factory=tuple)


# ----------------------------------------------------------------------------------------- inputs


def _check_image(image) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 1):
        raise ValueError(f"image is grey {img.shape[:2]}: SIL and DCP restore each colour channel with its own "
                         f"attenuation and background; give an RGB (H, W, 3) image")
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"image must be RGB (H, W, 3), got shape {img.shape}")
    if img.shape[0] < 2 or img.shape[1] < 2:
        raise ValueError(f"image is too small: {img.shape}")
    if img.dtype == np.uint8:
        return img
    if not np.issubdtype(img.dtype, np.floating):
        raise ValueError(f"image must be uint8 (0-255) or float in [0, 1], got {img.dtype}")
    lo, hi = float(img.min()), float(img.max())
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise ValueError("image contains NaN or infinite values")
    if lo < -1e-6 or hi > 1 + 1e-6:
        raise ValueError(f"float image values must lie in [0, 1], found [{lo:.4g}, {hi:.4g}]")
    return img


def model_parts(model, fog: Optional[str] = None) -> tuple:
    """``(params (7,), fog mode, effects_active)`` of ``model``: an :class:`UnderwaterParams` (then ``fog``,
    default ``'exp2'``), or an ``UnderwaterModel`` (``.params``, ``.fog``, ``.effects``)."""
    if model is None:
        raise ValueError("SIL needs the fitted model (model=UnderwaterParams or UnderwaterModel)")
    if isinstance(model, UnderwaterParams):
        f = fog or "exp2"
        if f not in FOG_MODES:
            raise ValueError(f"unknown fog mode {f!r}; expected one of {FOG_MODES}")
        return model.as_vector(), f, False
    params, mfog = getattr(model, "params", None), getattr(model, "fog", None)
    if not isinstance(params, UnderwaterParams) or mfog not in FOG_MODES:
        raise TypeError(f"model must be UnderwaterParams or an UnderwaterModel, got {type(model).__name__}")
    if fog is not None and fog != mfog:
        raise ValueError(f"fog={fog!r} contradicts the model's fog mode {mfog!r}")
    return params.as_vector(), mfog, bool(getattr(model, "effects", None))


@dataclass
class FrameGeometry:
    """The simulated geometry of one frame, checked: planar depth and range (m, inf off the geometry),
    labels (0 water), the pixels to restore (``hit``: labels > 0, finite depth) and the water pixels."""

    depth: np.ndarray
    range: np.ndarray
    labels: np.ndarray
    hit: np.ndarray
    camera: Optional[CameraModel] = None
    part_ids: Optional[np.ndarray] = None      # surfaces of the render (normals of lamp effects), if known

    @property
    def water(self) -> np.ndarray:
        return (self.labels == 0) & np.isinf(self.depth)


_RAY_NORMS: dict = {}
_RAY_LOCK = threading.Lock()


def _ray_norm(camera: CameraModel) -> np.ndarray:
    key = (camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy)
    with _RAY_LOCK:
        rn = _RAY_NORMS.get(key)
        if rn is None:
            if len(_RAY_NORMS) > 8:
                _RAY_NORMS.clear()
            rn = _RAY_NORMS[key] = camera.ray_norm().astype(np.float32)
    return rn


def frame_geometry(shape=None, *, geometry=None, depth=None, mask=None, camera: Optional[CameraModel] = None,
                   range_m=None) -> FrameGeometry:
    """Check and complete a frame's sim geometry.

    Parameters
    ----------
    shape : (H, W), optional
        The image size the geometry must have.
    geometry : object, optional
        With ``depth`` and ``labels`` (or ``mask``) and optionally ``range`` (a
        :class:`~uw_sil.sim.render.RenderResult`); or give the arrays:
    depth : (H, W) float
        Planar depth z in metres (REP 118), ``+inf`` where the simulation hit nothing.
    mask : (H, W) uint8/bool
        Sim labels, 0 water, > 0 object (``sim/mask``).
    camera : CameraModel
        Needed when no range is given (``r = z * ray_norm``).

    Raises
    ------
    ValueError
        Depth with NaN, zero, negative or ``-inf`` values; object pixels (mask > 0) with infinite depth;
        sizes that differ from each other, from ``shape`` or from the camera.
    """
    part_ids = None
    if geometry is not None:
        part_ids = getattr(geometry, "part_ids", None)
        depth = geometry.depth
        mask = getattr(geometry, "labels", getattr(geometry, "mask", None))
        range_m = getattr(geometry, "range", range_m)
        camera = camera or getattr(geometry, "camera", None)
    if depth is None or mask is None:
        raise ValueError("SIL needs the frame's simulated depth and mask (or a render with both)")
    d = np.asarray(depth)
    if d.ndim != 2:
        raise ValueError(f"sim depth must be (H, W), got shape {d.shape}")
    if not np.issubdtype(d.dtype, np.floating):
        raise ValueError(f"sim depth must be float metres (32FC1), got {d.dtype}")
    d = d.astype(np.float32, copy=False)
    m = np.asarray(mask)
    if m.ndim == 3 and m.shape[2] == 1:
        m = m[..., 0]
    if m.shape != d.shape:
        raise ValueError(f"sim mask {m.shape} and sim depth {d.shape} differ in size")
    if shape is not None and tuple(shape) != d.shape:
        raise ValueError(f"sim depth is {d.shape[1]}x{d.shape[0]} but the image is {shape[1]}x{shape[0]}")
    if np.isnan(d).any():
        raise ValueError(f"sim depth has {int(np.isnan(d).sum())} NaN pixels")
    if not (d > 0).all():
        raise ValueError(f"sim depth has {int((d <= 0).sum())} pixels <= 0 (zero, negative or -inf): a render "
                         f"never sees surfaces at or behind the camera")
    labels = m.astype(np.uint8, copy=False) if m.dtype != bool else m.view(np.uint8)
    hit = labels > 0
    far = np.count_nonzero(hit & np.isinf(d))
    if far:
        raise ValueError(f"sim mask marks {far} pixels as object where the sim depth is inf (no surface)")
    if range_m is None:
        if camera is None:
            raise ValueError("need the camera (intrinsics) to turn the sim depth into range")
        if camera.shape != d.shape:
            raise ValueError(f"camera is {camera.width}x{camera.height} but the sim depth is {d.shape[1]}x{d.shape[0]}")
        import cv2

        r = cv2.multiply(d, _ray_norm(camera))
    else:
        r = np.asarray(range_m, dtype=np.float32)
        if r.shape != d.shape:
            raise ValueError(f"sim range {r.shape} and sim depth {d.shape} differ in size")
    return FrameGeometry(d, r, labels, hit, camera, part_ids)


def estimate_background(image, water, erode_px: int = ERODE_PX, min_pixels: int = MIN_WATER_PIXELS,
                        stride: int = 2) -> Optional[np.ndarray]:
    """Background colour ``b`` (3,) on [0, 1] from the water pixels of a recorded frame, or None.

    The sim's water mask is eroded by ``erode_px`` pixels (render and frame never align to the pixel at the
    silhouette, and blur spreads the object into the water), sampled every ``stride`` pixels, and the
    per-channel median taken (robust to particles and fish). None when fewer than ``min_pixels`` samples
    remain (a frame filled by the object).

    In the model water pixels have ``T = 0``, so their colour is ``b`` plus noise; anything real that the
    scene model lacks (a seafloor, another structure) is mistaken for water and biases ``b`` once it covers
    a large part of the remaining water.
    """
    import cv2

    img = np.asarray(image)
    w = np.asarray(water, dtype=np.uint8)
    if w.shape != img.shape[:2]:
        raise ValueError(f"water mask {w.shape} does not match the image {img.shape[:2]}")
    if erode_px > 0:
        k = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * erode_px + 1, 2 * erode_px + 1))
        w = cv2.erode(w, k, borderType=cv2.BORDER_CONSTANT, borderValue=1)
    w = np.ascontiguousarray(w[::stride, ::stride])
    n = int(np.count_nonzero(w))
    if n < min_pixels:
        return None
    sub = np.ascontiguousarray(img[::stride, ::stride])
    if img.dtype != np.uint8:
        return np.clip(np.median(sub[w != 0], axis=0).astype(float), 0.0, 1.0)
    b = np.empty(3)
    for c in range(3):   # median from the histogram (exact; no gather and sort of the pixels)
        cum = np.cumsum(cv2.calcHist([sub], [c], w, [256], [0, 256]).ravel())
        lo, hi = np.searchsorted(cum, (n - 1) // 2 + 1), np.searchsorted(cum, n // 2 + 1)
        b[c] = 0.5 * (lo + hi) / 255.0
    return b


# ----------------------------------------------------------------------------------------- the enhancer


class Enhancer:
    """Enhances frames one at a time with SIL, DCP or UDCP, keeping buffers and caches between frames
    (what the ``enhancer`` node and ``uw-sil enhance`` use; :func:`enhance` is the one-call form).

    Parameters
    ----------
    model : UnderwaterParams or UnderwaterModel, optional
        The fitted model (needed for SIL). Replace it with :meth:`set_model` (e.g. after a backward fit).
    fog : {'exp2', 'exp', 'none'}, optional
        Fog mode for an :class:`UnderwaterParams` model (default ``'exp2'``).
    t0 : float
        Lowest transmission divided by (gain cap ``1/t0``), SIL; DCP/UDCP use He et al.'s own 0.1.
    max_gain : float
        Cap of the lamp-illumination gain (``UnderwaterModel.restore`` with an ``artificial_light`` effect).
    b_from_frame : bool
        Re-estimate ``b`` on every frame from its water pixels (:func:`estimate_background`).
    erode_px : int
        Erosion of the sim water mask for ``b_from_frame``.
    """

    def __init__(self, model=None, fog: Optional[str] = None, t0: float = 0.1, max_gain: float = 8.0,
                 b_from_frame: bool = False, erode_px: int = ERODE_PX):
        if not 0 < float(t0) <= 1:
            raise ValueError(f"t0 must lie in (0, 1], got {t0}")
        if not float(max_gain) >= 1:
            raise ValueError(f"max_gain must be >= 1, got {max_gain}")
        if int(erode_px) < 0:
            raise ValueError(f"erode_px must be >= 0, got {erode_px}")
        self.t0, self.max_gain = float(t0), float(max_gain)
        self.b_from_frame, self.erode_px = bool(b_from_frame), int(erode_px)
        self.model = None
        self._fog = fog
        if model is not None:
            self.set_model(model, fog)
        self._inv = PreparedInverse()
        self._geometry_key = None

    def set_model(self, model, fog: Optional[str] = None) -> None:
        """Use another fitted model from the next frame on (validated first)."""
        parts = model_parts(model, fog or self._fog)
        self.model, self._fog, self._parts = model, fog or self._fog, parts

    def enhance(self, image, method: str = "sil", *, geometry=None, depth=None, mask=None,
                camera: Optional[CameraModel] = None, range_m=None, b_from_frame: Optional[bool] = None,
                geometry_key=None) -> EnhanceResult:
        """Enhance one RGB frame (uint8 or float in [0, 1]); see :func:`enhance`.

        ``geometry_key``: any hashable naming the geometry; when it equals the previous call's, the
        prepared geometry (and its gain map, for the same model) is reused.
        """
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; expected one of {METHODS}")
        img = _check_image(image)
        if method in ("dcp", "udcp"):
            from .dcp import dehaze_dcp

            r = dehaze_dcp(img, variant=method)
            return EnhanceResult(r.image, method, 1.0, None, tuple(float(x) for x in r.atmospheric_light), "image")
        if self.model is None:
            raise ValueError("SIL needs the fitted model: Enhancer(model=...) or set_model()")
        params, fog, with_effects = self._parts
        reuse = geometry_key is not None and geometry_key == self._geometry_key and not with_effects
        geo = None
        if not reuse:
            geo = frame_geometry(img.shape[:2], geometry=geometry, depth=depth, mask=mask, camera=camera,
                                 range_m=range_m)
            self._geo = geo
        geo = self._geo
        warnings = []
        b, source = params[3:6], "fit"
        if self.b_from_frame if b_from_frame is None else b_from_frame:
            est = estimate_background(img, geo.water, self.erode_px)
            if est is None:
                warnings.append(f"too little water in the frame to estimate b (fewer than {MIN_WATER_PIXELS} "
                                f"samples after eroding the sim water mask by {self.erode_px} px): using the "
                                f"fitted b")
                source = "fit (no water)"
            else:
                b, source = est, "frame"
        if with_effects:
            res = self._restore_with_effects(img, geo, camera, b if source == "frame" else None)
            out, hit, skipped = res.image, res.restored_mask, tuple(res.skipped)
            if img.dtype == np.uint8:
                out = np.clip(np.rint(out * 255.0), 0, 255).astype(np.uint8)
        else:
            if not reuse:
                self._inv.set_geometry(geo.range, geo.depth, geo.hit, fog)
                self._geometry_key = geometry_key
            out = self._inv(img, params, self.t0, b)
            hit, skipped = geo.hit, ()
        frac = float(np.count_nonzero(hit)) / hit.size
        return EnhanceResult(out, "sil", frac, hit, tuple(float(x) for x in b), source, skipped, tuple(warnings))

    def _restore_with_effects(self, img, geo: FrameGeometry, camera, b_override):
        """``UnderwaterModel.restore`` (the effects' inverses) on a render-like view of the geometry."""
        if camera is None:
            raise ValueError("SIL with model effects needs the camera")
        view = _RenderView(np.zeros(geo.depth.shape + (3,), np.float32), geo.depth, geo.range, geo.labels,
                           geo.part_ids)
        return self.model.restore(img, view, camera, t0=self.t0, max_gain=self.max_gain, b_override=b_override)


@dataclass
class _RenderView:
    """The fields of a render that ``UnderwaterModel.restore`` reads (the clean radiance is not needed)."""

    rgb: np.ndarray
    depth: np.ndarray
    range: np.ndarray
    labels: np.ndarray
    part_ids: Optional[np.ndarray] = None


def enhance(image, method: str = "sil", *, geometry=None, depth=None, mask=None, camera=None, range_m=None,
            model=None, fog: Optional[str] = None, t0: float = 0.1, max_gain: float = 8.0,
            b_from_frame: bool = False, erode_px: int = ERODE_PX) -> EnhanceResult:
    """Enhance one recorded frame with SIL (the fitted model inverted on the sim geometry), DCP or UDCP.

    Parameters
    ----------
    image : (H, W, 3) uint8 or float in [0, 1]
        The recorded RGB frame (grey images are refused: the model is per colour channel).
    method : {'sil', 'dcp', 'udcp'}
    geometry : render-like, optional
        The frame's sim geometry (``depth``, ``labels``, ``range``), e.g. ``Renderer.render(pose)``; or
        ``depth`` + ``mask`` + ``camera`` (+ ``range_m``) as the enhancer node receives them.
    model : UnderwaterParams or UnderwaterModel
        The fitted model (SIL).
    fog, t0, max_gain, b_from_frame, erode_px
        See :class:`Enhancer`.

    Returns
    -------
    EnhanceResult
        ``image`` in the input's encoding, ``restored_fraction``, the background used.
    """
    e = Enhancer(model, fog, t0=t0, max_gain=max_gain, b_from_frame=b_from_frame, erode_px=erode_px) \
        if method == "sil" else Enhancer()
    return e.enhance(image, method, geometry=geometry, depth=depth, mask=mask, camera=camera, range_m=range_m)


# ----------------------------------------------------------------------------------------- parameters file


def load_params_yaml(path, node: Optional[str] = None) -> tuple:
    """Fitted parameters from a ROS 2 parameters file (``uw-sil fit --out fit.yaml``).

    Returns ``(UnderwaterParams, fog_mode, ros_parameters dict)``. The node key is ``node`` when given,
    else ``/**``, ``sim_camera`` or ``/sim_camera``, or the file's only key.

    Raises
    ------
    FileNotFoundError
        No such file.
    ValueError
        Not YAML, not a parameters file, missing or invalid parameters (the message names them).
    """
    import yaml

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"parameters file {p} does not exist")
    try:
        doc = yaml.safe_load(p.read_text())
    except yaml.YAMLError as e:
        raise ValueError(f"parameters file {p} is not valid YAML: {e}") from None
    if not isinstance(doc, dict) or not doc:
        raise ValueError(f"parameters file {p} must map a node name to {{ros__parameters: ...}}")
    keys = [node] if node else [k for k in ("/**", "sim_camera", "/sim_camera") if k in doc] or list(doc)
    if len(keys) != 1 or keys[0] not in doc:
        raise ValueError(f"parameters file {p}: cannot tell which node's parameters to use among {list(doc)}")
    body = doc[keys[0]]
    ros = body.get("ros__parameters") if isinstance(body, dict) else None
    if not isinstance(ros, dict):
        raise ValueError(f"parameters file {p}: {keys[0]!r} has no ros__parameters mapping")
    missing = [n for n in RGB_NAMES if n not in ros]
    if missing:
        raise ValueError(f"parameters file {p} lacks {', '.join(missing)}")
    try:
        params = UnderwaterParams.from_dict({n: float(ros[n]) for n in RGB_NAMES})
    except (TypeError, ValueError) as e:
        raise ValueError(f"parameters file {p}: {e}") from None
    fog = ros.get("fog_mode", "exp2")
    if fog not in FOG_MODES:
        raise ValueError(f"parameters file {p}: fog_mode {fog!r} is not one of {FOG_MODES}")
    return params, fog, dict(ros)


def model_from_parameters(values: dict):
    """The ``UnderwaterModel`` of flat ROS parameters as ``sim_camera`` holds them: ``a_r ... rho_f``,
    ``fog_mode`` (default exp2) and any effect parameters ``<effect>.<param>`` (other names are ignored).
    ValueError names a missing or invalid parameter."""
    from ..sim.model import UnderwaterModel, flat_to_effect_params

    missing = [n for n in RGB_NAMES if n not in values]
    if missing:
        raise ValueError(f"missing parameters: {', '.join(missing)}")
    try:
        params = UnderwaterParams.from_dict({n: float(values[n]) for n in RGB_NAMES})
    except TypeError as e:
        raise ValueError(str(e)) from None
    fog = values.get("fog_mode", "exp2")
    if fog not in FOG_MODES:
        raise ValueError(f"fog_mode {fog!r} is not one of {FOG_MODES}")
    return UnderwaterModel(params, flat_to_effect_params(values) or None, fog)


def load_model_yaml(path, node: Optional[str] = None):
    """The fitted ``UnderwaterModel`` of a ROS 2 parameters file (see :func:`load_params_yaml`), with the
    effects its ``<effect>.<param>`` entries name."""
    _, _, ros = load_params_yaml(path, node)
    try:
        return model_from_parameters(ros)
    except ValueError as e:
        raise ValueError(f"parameters file {path}: {e}") from None
