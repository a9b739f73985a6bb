"""The underwater model with optional effects: one object that degrades clean renders and restores images.

Base model (as :mod:`uw_sil.sim.optics`), per channel c, ``r`` range, ``z`` planar depth::

    I_c = b_c + T_c (i_c - b_c),   T_c = exp(-a_c r) f(z),   f(z) = exp(-(rho_F z)^2)   ('exp2' fog)

Effects (:mod:`uw_sil.sim.effects`) extend it. Composition order, with ``i`` the clean render::

    geometry   what is seen: corrected pose, a seafloor the scene lacks          (pose_error, unmodeled_geometry)
    radiance   i' = i * illumination                                             (artificial_light)
    medium     D = i' T_D,  B = b (1 - T_B) + veil                               (backscatter_coefficient,
                                                                                  marine_snow; lamp veil)
    direct     D <- filter(D)                                                    (forward_scatter)
               I = D + B
    sensor     I <- vignetting, camera response, noise, JPEG; clipped to [0, 1]  (vignetting, camera_response,
                                                                                  sensor_noise, compression)

Without effects ``T_D = T_B = T`` and no veil: ``D + B = b + T (i - b)``, computed in exactly the
arithmetic of :func:`uw_sil.sim.optics.degrade` (the results are bit-identical).

:meth:`UnderwaterModel.restore` runs the model backwards on object pixels: invertible sensor effects
are undone (camera response, vignetting), then ``i' = b + (I - B - b T_D) / max(T_D, t0)`` (which is
``b + (I - b) / max(T, t0)`` without effects), then the lamp illumination is divided out with the gain
capped at ``max_gain``. Forward scatter (a deconvolution), noise and marine snow (random) are not
inverted; they are listed in :attr:`RestoreResult.skipped`.

For fitting, :meth:`UnderwaterModel.prepare` returns a :class:`PreparedModel` holding everything that
depends only on the render (geometry, normals, per-effect grids); calling it with ``(N, 7)`` base vectors
and ``(N, k)`` effect vectors gives ``(N, H, W, 3)`` images. Random effects (noise, marine snow, pose
jitter) draw from a generator seeded by ``seed`` for every candidate (common random numbers), so an
objective built on it is deterministic.

Parameters of the effects as ROS parameters: ``<effect>.<param>`` (:func:`effect_params_to_flat`,
:func:`flat_to_effect_params`).
"""
from __future__ import annotations

import functools
import weakref
from typing import NamedTuple, Optional

import numpy as np

from .effects import EFFECTS, EFFECT_ORDER, get_effect, parse_effects
from .effects.base import ModelTerms, effect_rng
from .normals import plane_terms
from .optics import FOG_MODES, invert_transmission
from .params import UnderwaterParams, validate_rgb_params

__all__ = ["Geometry", "ModelTerms", "UnderwaterModel", "PreparedModel", "RestoreResult",
           "effect_params_to_flat", "flat_to_effect_params", "normalize_effects"]


# ============================================================================ geometry


class Geometry:
    """What the camera sees in one frame, in the camera optical frame (REP 103: x right, y down, z forward).

    Attributes (float32 unless noted; "no hit" pixels: ``depth = range = inf``, ``X = normals = 0``)
    ----------
    camera : CameraModel (``width height fx fy cx cy``)
    rgb : (H, W, 3) clean radiance in [0, 1], 0 where nothing is hit
    depth, range : (H, W) planar depth z and Euclidean range, metres
    hit : (H, W) bool, finite range and depth
    labels : (H, W) uint8 (0 water, 1 panel, 2 seafloor)
    part_ids : (H, W) uint16 (surfaces that are differentiated together for normals)
    pose : (4, 4) float64 ``T_cam_panel`` or None (needed by effects placed in the panel frame)
    xt, yt : (1, W) and (H, 1) normalized image coordinates ``(u - cx)/fx``, ``(v - cy)/fy``
    rays : (H, W, 3) unit viewing directions (lazy, cached)
    X : (H, W, 3) surface points (lazy, cached)
    normals : (H, W, 3) unit surface normals pointing to the camera's side, from the depth map (lazy,
        cached): on a plane ``n.X = d`` the inverse depth is affine in ``(xt, yt)``; derivatives are
        one-sided differences towards the smoother neighbour of the same part (never across silhouettes).
    fine : Geometry or None
        The same view at an integer multiple of this resolution, for effects whose detail is finer than these
        pixels (the lamps' cast shadows of a handle a few pixels wide): they compute on it and average over
        each block. None: this geometry is the finest there is. May be given as a function that makes it,
        called when it is first read (a geometry effect's finer view costs nothing where no effect reads it).
    carried_from : tuple or None
        ``(source geometry, source pixel per pixel, found)`` of a view warped with the lamps' shadows carried
        (:func:`uw_sil.sim.effects.pose_error.carrying_shadows`); None otherwise (not kept by :meth:`replace`).
    """

    def __init__(self, camera, rgb, depth, range_m, labels=None, part_ids=None, pose=None,
                 X=None, normals=None, fine=None):
        h, w = int(camera.height), int(camera.width)
        rgb = np.asarray(rgb, dtype=np.float32)
        depth = np.asarray(depth, dtype=np.float32)
        range_m = np.asarray(range_m, dtype=np.float32)
        if rgb.shape != (h, w, 3):
            raise ValueError(f"clean image must be ({h}, {w}, 3) for this camera, got {rgb.shape}")
        for name, arr in (("depth", depth), ("range", range_m)):
            if arr.shape != (h, w):
                raise ValueError(f"{name} shape {arr.shape} does not match the camera ({h}, {w})")
            if np.isnan(arr).any() or (arr < 0).any():
                raise ValueError(f"{name} must be >= 0 or inf (no hit), found NaN or negative values")
        self.camera = camera
        self.rgb = rgb
        self.depth = depth
        self.range = range_m
        self.hit = np.isfinite(range_m) & np.isfinite(depth)
        if labels is None:
            labels = self.hit.astype(np.uint8)
        self.labels = np.asarray(labels, dtype=np.uint8)
        if part_ids is None:
            part_ids = np.where(self.hit, self.labels.astype(np.uint16) + 1, 0).astype(np.uint16)
        self.part_ids = np.asarray(part_ids)
        self.pose = None if pose is None else np.asarray(pose, dtype=float)
        self.xt = ((np.arange(w) - camera.cx) / camera.fx).astype(np.float32)[None, :]
        self.yt = ((np.arange(h) - camera.cy) / camera.fy).astype(np.float32)[:, None]
        self._X = X
        self._normals = normals
        self._rays = None
        self._fine = fine
        self.carried_from = None
        if fine is not None and not callable(fine):
            self._check_fine(fine)

    def _check_fine(self, fine) -> None:
        h, w = self.shape
        if fine.shape[0] % h or fine.shape[1] % w or fine.shape[0] // h != fine.shape[1] // w:
            raise ValueError(f"fine geometry {fine.shape} is not an integer multiple of ({h}, {w})")

    @property
    def has_finer_view(self) -> bool:
        """Whether :attr:`fine` is (or will be made) a finer view, without making it."""
        return self._fine is not None

    def finer_view_through(self, make):
        """For ``replace(fine=...)`` of a geometry effect: this view's finer view passed through ``make`` (a picklable
        function of one geometry), when it is first read; None where there is no finer view."""
        return functools.partial(_through, make, self) if self._fine is not None else None

    @property
    def fine(self) -> "Optional[Geometry]":
        if callable(self._fine):
            g = self._fine()
            if g is not None:
                self._check_fine(g)
            self._fine = g
        return self._fine

    @property
    def shape(self) -> tuple:
        return self.depth.shape

    @property
    def rays(self) -> np.ndarray:
        if self._rays is None:
            h, w = self.shape
            d = np.empty((h, w, 3), np.float32)
            d[..., 0] = self.xt
            d[..., 1] = self.yt
            d[..., 2] = 1.0
            d /= np.sqrt((d * d).sum(-1, keepdims=True))
            self._rays = d
        return self._rays

    @property
    def X(self) -> np.ndarray:
        if self._X is None:
            z = np.where(self.hit, self.depth, np.float32(0.0))
            X = np.empty(self.shape + (3,), np.float32)
            X[..., 0] = z * self.xt
            X[..., 1] = z * self.yt
            X[..., 2] = z
            self._X = X
        return self._X

    @property
    def normals(self) -> np.ndarray:
        if self._normals is None:
            self._normals = _normals_from_depth(self.depth, self.part_ids, self.hit, self.camera, self.xt, self.yt)
        return self._normals

    def replace(self, **kw) -> "Geometry":
        """A new geometry with some arrays replaced (``rgb depth range_m labels part_ids pose X normals fine``);
        cached derived arrays and the finer view are dropped unless given."""
        args = dict(rgb=self.rgb, depth=self.depth, range_m=self.range, labels=self.labels,
                    part_ids=self.part_ids, pose=self.pose, X=None, normals=None)
        args.update(kw)
        return Geometry(self.camera, **args)

    @classmethod
    def from_render(cls, render, camera, pose=None) -> "Geometry":
        """Geometry of a render result (``rgb depth range`` and optionally ``labels part_ids``), cached per
        render object, camera and pose (normals are computed once per render)."""
        key = (_camera_key(camera), None if pose is None else np.asarray(pose, dtype=float).tobytes())
        try:
            per = _GEOM_CACHE.setdefault(render, {})
        except TypeError:              # not weak-referenceable: no cache
            per = {}
        g = per.get(key)
        if g is None:
            g = cls(camera, render.rgb, render.depth, render.range, getattr(render, "labels", None),
                    getattr(render, "part_ids", None), pose)
            if len(per) > 4:
                per.clear()
            per[key] = g
        return g


_GEOM_CACHE: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _through(make, geom: Geometry):
    """``make`` of ``geom``'s finer view (:meth:`Geometry.finer_view_through`)."""
    return make(geom.fine)


def _camera_key(camera) -> tuple:
    return (int(camera.width), int(camera.height), float(camera.fx), float(camera.fy), float(camera.cx),
            float(camera.cy))


def _normals_from_depth(depth, part, hit, camera, xt, yt) -> np.ndarray:
    """Unit normals towards the camera from planar depth (see :class:`Geometry`)."""
    w = np.where(hit, np.float32(1.0) / np.where(hit, depth, np.float32(1.0)), np.float32(0.0))
    part = np.where(hit, part, 0)
    mx, my, mz = plane_terms(w, part, camera.fx, camera.fy, xt, yt)   # n / d for the plane n.X = d (n away from camera)
    norm = np.sqrt(mx * mx + my * my + mz * mz)
    ok = hit & (norm > 0)
    bad = ~ok
    safe = np.where(ok, norm, np.float32(1.0))
    n = np.empty(depth.shape + (3,), np.float32)
    for k, m in enumerate((mx, my, mz)):          # -m / |m| into each component's plane, +0 where not ok
        np.negative(m, out=m)
        np.copyto(m, np.float32(0.0), where=bad)  # (on the (H, W) planes: 0.5 ms; on the (H, W, 3) normals: 4)
        np.divide(m, safe, out=n[..., k])
    odd = hit & bad
    if odd.any():
        n[odd] = (0.0, 0.0, -1.0)                 # isolated pixels face the camera
    return n


# ============================================================================ effects as values


def normalize_effects(effects) -> dict:
    """``{name: complete value dict}`` in composition order from a dict (values: dict, severity name or
    None), a ``parse_effects`` string, or a list of names (strong presets)."""
    if effects is None:
        return {}
    if isinstance(effects, str):
        effects = parse_effects(effects)
    elif isinstance(effects, (list, tuple, set, frozenset)):
        effects = parse_effects(",".join(effects))
    if not isinstance(effects, dict):
        raise TypeError(f"effects must be a dict, a string or a list of names, got {type(effects).__name__}")
    out = {}
    for name in effects:
        get_effect(name)                          # raises for unknown names
    for name in EFFECT_ORDER:
        if name in effects:
            out[name] = get_effect(name).values(effects[name])
    return out


def effect_params_to_flat(effects: dict) -> dict:
    """``{"vignetting": {"k1": -0.3, ...}}`` -> ``{"vignetting.k1": -0.3, ...}`` (defaults filled in)."""
    out = {}
    for name, values in normalize_effects(effects).items():
        for k, v in values.items():
            out[f"{name}.{k}"] = float(v)
    return out


def flat_to_effect_params(flat: dict) -> dict:
    """Inverse of :func:`effect_params_to_flat`: picks the ``<effect>.<param>`` keys of known effects out of a
    flat parameter dict (other keys, e.g. the base ``a_r``, are ignored), fills in defaults and checks
    bounds. An unknown parameter of a known effect raises ValueError."""
    grouped: dict = {}
    for key, v in flat.items():
        if not isinstance(key, str) or "." not in key:
            continue
        name, _, param = key.partition(".")
        if name not in EFFECTS:
            continue
        grouped.setdefault(name, {})[param] = v
    return normalize_effects(grouped)


# ============================================================================ the model


class _RestoreFields(NamedTuple):
    image: np.ndarray            # (H, W, 3) float32 in [0, 1]
    restored_mask: np.ndarray    # (H, W) bool: object pixels that were restored
    restored_fraction: float


class RestoreResult(_RestoreFields):
    """``(image, restored_mask, restored_fraction)``, plus the attribute ``skipped`` (not unpacked): the
    active effects restore could not undo."""

    def __new__(cls, image, restored_mask, restored_fraction, skipped=()):
        self = super().__new__(cls, image, restored_mask, restored_fraction)
        self.skipped = tuple(skipped)
        return self


class UnderwaterModel:
    """The underwater model (base 7 parameters + optional effects) that both degrades and restores.

    Parameters
    ----------
    params : UnderwaterParams, optional
    effects : dict, str or list, optional
        ``{name: values}`` with values a dict of parameters (missing ones take defaults), a severity name
        ("mild", "strong") or None (defaults); or a :func:`~uw_sil.sim.effects.parse_effects` string.
    fog : {'exp2', 'exp', 'none'}

    Examples
    --------
    >>> model = UnderwaterModel(UnderwaterParams(), {"vignetting": "strong", "artificial_light": "mild"})
    >>> img = model.degrade(render, camera)                 # doctest: +SKIP
    >>> res = model.restore(img, render, camera)            # doctest: +SKIP
    """

    def __init__(self, params: Optional[UnderwaterParams] = None, effects=None, fog: str = "exp2"):
        if fog not in FOG_MODES:
            raise ValueError(f"unknown fog mode {fog!r}; expected one of {FOG_MODES}")
        self.params = UnderwaterParams() if params is None else params
        if not isinstance(self.params, UnderwaterParams):
            raise TypeError(f"params must be UnderwaterParams, got {type(self.params).__name__}")
        self.fog = fog
        self.effects = normalize_effects(effects)

    # ------------------------------------------------------------------ parameters

    @property
    def effect_names(self) -> tuple:
        return tuple(self.effects)

    def effect_vector(self) -> np.ndarray:
        """Concatenated effect parameter vectors (composition order)."""
        parts = [get_effect(n).vector(v) for n, v in self.effects.items()]
        return np.concatenate(parts) if parts else np.zeros(0)

    def effect_bounds(self) -> tuple:
        lo = [get_effect(n).bounds()[0] for n in self.effects]
        hi = [get_effect(n).bounds()[1] for n in self.effects]
        return (np.concatenate(lo) if lo else np.zeros(0), np.concatenate(hi) if hi else np.zeros(0))

    def effect_param_names(self) -> tuple:
        return tuple(f"{n}.{p}" for n in self.effects for p in get_effect(n).param_names)

    def with_vectors(self, base=None, effect_vector=None) -> "UnderwaterModel":
        """A copy with new base (7,) and/or effect (k,) vectors."""
        params = self.params if base is None else UnderwaterParams.from_vector(base)
        effects = dict(self.effects)
        if effect_vector is not None:
            effects = _split_effect_vector(tuple(self.effects), effect_vector)
        return UnderwaterModel(params, effects, self.fog)

    def flat_params(self) -> dict:
        """Base and effect parameters as flat ROS parameter names (``a_r`` ..., ``<effect>.<param>``)."""
        d = self.params.as_dict()
        d.update(effect_params_to_flat(self.effects))
        return d

    def __repr__(self):
        return f"UnderwaterModel({self.params}, effects={list(self.effects)}, fog={self.fog!r})"

    # ------------------------------------------------------------------ evaluation

    def prepare(self, render, camera, pose=None, seed: int = 0, cover=None,
                shared: Optional[dict] = None) -> "PreparedModel":
        """Batched evaluator for fitting (see :class:`PreparedModel`)."""
        return PreparedModel(self, render, camera, pose=pose, seed=seed, cover=cover, shared=shared)

    def degrade(self, render, camera, rng: Optional[np.random.Generator] = None, pose=None) -> np.ndarray:
        """Underwater image (H, W, 3) float32 in [0, 1] of a clean render.

        ``rng`` feeds the random effects (a new draw per call); None uses a fixed seed (0). ``pose``
        (``T_cam_panel``) is needed by ``unmodeled_geometry``.
        """
        pm = PreparedModel(self, render, camera, pose=pose)
        seed = 0 if rng is None else int(rng.integers(0, 2 ** 63))
        return pm(self.params.as_vector(), self.effect_vector(), seed=seed)

    def restore(self, image, render, camera, t0: float = 0.1, max_gain: float = 8.0, b_override=None,
                pose=None) -> RestoreResult:
        """Invert the model on the object pixels of a recorded (or degraded) image.

        Parameters
        ----------
        image : (H, W, 3) float in [0, 1] or uint8
        render, camera, pose : the frame's clean render (its geometry is what matters), camera, pose
        t0 : float
            Floor of the direct transmission ``T_D`` (keeps the gain ``1/T`` finite at long range).
        max_gain : float
            Cap of the gain ``1/illumination`` that undoes the vehicle lamps (dark beam edges are not
            amplified beyond it).
        b_override : array_like (3,), optional
            Background colour to use instead of the model's ``b`` (e.g. estimated from the water).

        Returns
        -------
        RestoreResult
            ``image``: restored where ``restored_mask`` (hit pixels with finite range), recorded
            elsewhere (water), clamped to [0, 1]; ``skipped``: active effects not inverted.
        """
        img = np.asarray(image)
        if img.dtype == np.uint8:
            img = img.astype(np.float32) / np.float32(255.0)
        img = img.astype(np.float32, copy=False)
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"image must be (H, W, 3), got {img.shape}")
        if not (t0 > 0 and max_gain >= 1):
            raise ValueError(f"need t0 > 0 and max_gain >= 1, got t0={t0}, max_gain={max_gain}")
        base = self.params.as_vector()
        if b_override is not None:
            bo = np.asarray(b_override, dtype=float).ravel()
            if bo.shape != (3,):
                raise ValueError(f"b_override needs 3 values, got {bo.shape}")
            base[3:6] = bo
            validate_rgb_params(base)
        pm = PreparedModel(self, render, camera, pose=pose)
        if img.shape[:2] != pm.shape:
            raise ValueError(f"image shape {img.shape[:2]} does not match the render {pm.shape}")
        terms, vals, _ = pm._terms(base, self.effect_vector(), seed=None, restoring=True)
        I = np.ascontiguousarray(np.moveaxis(img, 2, 0))
        for eff, v in reversed(list(zip(pm.effects, vals))):
            if eff.stage == "sensor" and eff.invertible and not eff.is_identity(v):
                I = eff.invert(I, terms, v)
        b = terms.b[:, None, None]
        TD = terms.T_D
        if terms.T_B is not TD or terms.veil is not None:
            # Backscatter beyond the base model's b (1 - T_D) (beta_B != beta_D, the lamps' veil) is
            # subtracted first; what remains is the base model, inverted by the one inverse of Eq. 1.
            B = b * (1 - terms.T_B)
            if terms.veil is not None:
                B = B + terms.veil
            I = I - (B - b * (1 - TD))
        ip = invert_transmission(I, b, TD, t0)
        if terms.illum is not None:
            gain = np.minimum(np.float32(1.0) / np.maximum(terms.illum, np.float32(1e-12)), np.float32(max_gain))
            ip = ip * gain
        geom = terms.geom
        obj = geom.hit & np.isfinite(geom.range)
        out = np.where(obj[..., None], np.moveaxis(ip, 0, 2), img)
        np.clip(out, 0.0, 1.0, out=out)
        skipped = tuple(e.name for e, v in zip(pm.effects, vals) if not e.invertible and not e.is_identity(v))
        return RestoreResult(out.astype(np.float32, copy=False), obj, float(obj.mean()), skipped)


def _split_effect_vector(names: tuple, x) -> dict:
    x = np.asarray(x, dtype=float).ravel()
    k = sum(len(get_effect(n).params) for n in names)
    if x.shape != (k,):
        raise ValueError(f"effect vector of {list(names)} needs {k} values, got {x.size}")
    out, i = {}, 0
    for n in names:
        e = get_effect(n)
        out[n] = e.from_vector(x[i:i + len(e.params)])
        i += len(e.params)
    return out


# ============================================================================ prepared (batched) evaluation


class _Prepared:
    """Everything that depends on the geometry only (reused across parameter sets)."""

    __slots__ = ("geom", "r", "zf", "mask", "planes", "state")

    def __init__(self, geom: Geometry, fog: str, effects, like: Optional["_Prepared"] = None,
                 shared: Optional[dict] = None):
        self.geom = geom
        if like is not None:
            # ``like``: made for surfaces of the same shape (a geometry effect's values that change their colour
            # only, :meth:`uw_sil.sim.effects.base.Effect.shape_key`); what depends on the shape is the same
            # (the effects' per-render state too, none of which reads the colour): shared, the colour made anew
            self.mask, self.r, self.zf, self.state = like.mask, like.r, like.zf, like.state
            self.planes = np.ascontiguousarray(np.moveaxis(geom.rgb, 2, 0))
            return
        hit = geom.hit
        self.mask = hit.astype(np.float32)
        self.r = np.where(hit, geom.range, 0).astype(np.float32)
        z = np.where(hit, geom.depth, 0).astype(np.float32)
        self.zf = z * z if fog == "exp2" else z
        self.planes = np.ascontiguousarray(np.moveaxis(geom.rgb, 2, 0))
        self.state = {e.name: e.prepare(geom, geom.camera) for e in effects if e.stage != "geometry"}
        if shared is not None:          # what the effects share across the geometries of one prepared model
            for e in effects:
                if e.stage != "geometry":
                    e.share(self.state[e.name], shared.setdefault(e.name, {}))


class PreparedModel:
    """A model bound to one render: evaluates many parameter sets quickly (the fitter's inner loop).

    ``pm(base_vectors, effect_vectors)`` with ``(N, 7)`` rgb base vectors and ``(N, k)`` vectors of the
    active effects (:attr:`effect_names`, concatenated in :attr:`param_names` order; None: the model's
    values) returns ``(N, H, W, 3)`` float32 (``(H, W, 3)`` for 1-D inputs). Random effects use
    ``seed`` (default: the one given at preparation) for every candidate.

    Effect vectors are bounds-checked (ValueError naming the parameter); base vectors are validated.

    ``cover`` (H, W), optional: the fraction of each pixel the render's surfaces cover (a reduced render's
    area-exact silhouettes); it scales the transmission of those pixels when the model keeps the scene's
    surfaces where they are (no geometry effect, or only ones that ``keeps_scene``; with a pose error the
    silhouettes move, and the coverage applies to no parameter value, so the objective stays continuous at
    the identity). Default: the hit mask.

    ``shared`` (a dict, optional): what the effects' states share (:meth:`uw_sil.sim.effects.base.Effect.share`), the
    same dict for the evaluators of several renders of one camera (the frames of a fit): the lamps' veil integral,
    which depends on the camera only, is then made once for all of them.
    """

    def __init__(self, model: UnderwaterModel, render, camera, pose=None, seed: int = 0, cover=None,
                 shared: Optional[dict] = None):
        self.model = model
        self.fog = model.fog
        self.seed = int(seed)
        self.effect_names = model.effect_names
        self.effects = [get_effect(n) for n in self.effect_names]
        self.param_names = model.effect_param_names()
        self.lower, self.upper = model.effect_bounds()
        self.slices = []
        i = 0
        for e in self.effects:
            self.slices.append(slice(i, i + len(e.params)))
            i += len(e.params)
        self.n_effect_params = i
        self.geom0 = render if isinstance(render, Geometry) else Geometry.from_render(render, camera, pose)
        if pose is not None and self.geom0.pose is None:
            self.geom0 = self.geom0.replace(pose=pose, X=self.geom0._X, normals=self.geom0._normals)
        self.camera = self.geom0.camera
        self.shape = self.geom0.shape
        self._geo_effects = [(k, e) for k, e in enumerate(self.effects) if e.stage == "geometry"]
        self._other = [e for e in self.effects if e.stage != "geometry"]
        self.cover = None if cover is None else np.asarray(cover, np.float32)
        if self.cover is not None and self.cover.shape != self.shape:
            raise ValueError(f"cover has shape {self.cover.shape}, the render {self.shape}")
        if not all(e.keeps_scene for _, e in self._geo_effects):
            self.cover = None
        self._base_prep = None
        self._cache = {}
        self._shapes = {}                # shape key -> a prepared geometry of that shape (in _cache)
        # effect name -> what its states share across geometries (Effect.share)
        self._shared = {} if shared is None else shared
        # the first random sensor effect (camera noise): the image before it is kept between calls
        self._cut = next((k for k, e in enumerate(self.effects) if e.stage == "sensor" and e.random_per_frame), None)
        self._before_cut = None
        self._scratch = None
        self.base_vector = model.params.as_vector()
        self.effect_vector = model.effect_vector()

    def bounds(self) -> tuple:
        return self.lower.copy(), self.upper.copy()

    # ------------------------------------------------------------------ internals

    def _covered(self, prep: _Prepared) -> _Prepared:
        """``prep`` with the scene's pixel coverage as transmission mask on the scene's own pixels."""
        if self.cover is not None:
            prep.mask = np.where(self.geom0.hit, self.cover, prep.mask).astype(np.float32)
        return prep

    def _prep_for(self, vals, seed) -> _Prepared:
        active = [(k, e) for k, e in self._geo_effects if not e.is_identity(vals[k])]
        if not active:
            if self._base_prep is None:
                self._base_prep = self._covered(_Prepared(self.geom0, self.fog, self._other, shared=self._shared))
            return self._base_prep
        draws = any(e.draws(vals[k]) for k, e in active) and seed is not None
        key = tuple((k, tuple(vals[k].values())) for k, _ in active) + ((seed,) if draws else ())
        p = self._cache.get(key)
        if p is None:
            terms = ModelTerms(self.geom0, self.camera, np.zeros(3), np.zeros(3), 0.0, self.fog, None, None, None,
                               restoring=seed is None)
            for k, e in active:
                e.apply(terms, vals[k], None if seed is None else effect_rng(seed, e.name))
            # a kept geometry of the same shape (a least-squares Jacobian's column of the seafloor's albedo or
            # contrast): its shape's terms and the effects' state (the lamps' shadows) are shared, not made again
            shape = tuple((k, e.shape_key(vals[k])) for k, e in active) + ((seed,) if draws else ())
            twin = self._shapes.get(shape)
            if twin is not None:
                p = _Prepared(terms.geom, self.fog, self._other, like=twin)
            else:
                p = self._covered(_Prepared(terms.geom, self.fog, self._other, shared=self._shared))
            if len(self._cache) >= 8:
                self._cache.clear()
                self._shapes.clear()
            self._cache[key] = p
            self._shapes.setdefault(shape, p)
        return p

    def _terms(self, base, effect_vector, seed, restoring=False):
        """Terms through the medium stage for one candidate: (terms, list of value dicts, _Prepared)."""
        vals = [e.from_vector(effect_vector[s]) for e, s in zip(self.effects, self.slices)]
        prep = self._prep_for(vals, None if restoring else seed)
        p = np.asarray(base, dtype=np.float32)
        a, b, rho = p[0:3], p[3:6], p[6]
        if self.fog == "none" or rho == 0:
            fz = None
        else:
            fz = prep.zf * (rho * rho if self.fog == "exp2" else rho)
        terms = ModelTerms(prep.geom, self.camera, a, b, rho, self.fog, fz, prep.r, prep.mask, prep.state, restoring)
        order = [(e, v) for e, v in zip(self.effects, vals) if e.stage != "geometry" and not e.is_identity(v)]

        def rng_for(e):
            if restoring or not e.random_per_frame:
                return None
            return effect_rng(seed, e.name)

        for e, v in order:
            if e.stage == "radiance" and not (restoring and e.random_per_frame):
                e.apply(terms, v, rng_for(e))
        h, w = self.shape
        if restoring:
            T = np.empty((3, h, w), np.float32)
        else:                                        # one buffer per evaluator (results are copied out)
            if self._scratch is None:
                self._scratch = np.empty((3, h, w), np.float32)
            T = self._scratch
        for c in range(3):
            t = T[c]
            np.multiply(prep.r, a[c], out=t)        # same arithmetic as uw_sil.sim.optics.PreparedRender
            if fz is not None:
                t += fz
            np.negative(t, out=t)
            np.exp(t, out=t)
            t *= prep.mask
        terms.T_D = terms.T_B = T
        for e, v in order:
            if e.stage == "medium" and not (restoring and e.random_per_frame):
                e.apply(terms, v, rng_for(e))
        return terms, vals, prep

    def _evaluate(self, base, effect_vector, seed) -> np.ndarray:
        cut = self._cut
        if cut is not None:
            # everything before the first random sensor effect (the camera noise) is the same for candidates
            # that differ only from there on (a noise fit): kept from the last call and reused, bit for bit
            key = (np.asarray(base, float).tobytes(),
                   np.asarray(effect_vector[:self.slices[cut].start], float).tobytes(), seed)
            if self._before_cut is not None and self._before_cut[0] == key:
                terms, I0 = self._before_cut[1:]
                terms.I = I0.copy()
                vals = [e.from_vector(effect_vector[s]) for e, s in zip(self.effects, self.slices)]
                return self._sensor(terms, vals, seed, range(cut, len(self.effects)))
        terms, vals, prep = self._terms(base, effect_vector, seed)
        b = terms.b
        ip = prep.planes if terms.illum is None else prep.planes * terms.illum
        active = [(e, v) for e, v in zip(self.effects, vals) if not e.is_identity(v)]
        direct = [(e, v) for e, v in active if e.stage == "direct"]
        h, w = self.shape
        if direct:
            terms.D = ip * terms.T_D
            for e, v in direct:
                e.apply(terms, v, effect_rng(seed, e.name) if e.random_per_frame else None)
            I = terms.D + b[:, None, None] * (1 - terms.T_B)
        elif terms.T_B is terms.T_D:
            I = terms.T_D                                # reuse: T is not needed afterwards
            for c in range(3):
                I[c] *= ip[c] - b[c]                     # I_c = b_c + T_c (i_c - b_c), as uw_sil.sim.optics
                I[c] += b[c]
        else:
            I = ip * terms.T_D + b[:, None, None] * (1 - terms.T_B)
        if terms.veil is not None:
            I += terms.veil
        terms.I = I
        if cut is None:
            return self._sensor(terms, vals, seed, range(len(self.effects)))
        self._sensor(terms, vals, seed, range(cut), last=False)
        self._before_cut = (key, terms, terms.I.copy())
        return self._sensor(terms, vals, seed, range(cut, len(self.effects)))

    def _sensor(self, terms, vals, seed, which, last: bool = True) -> np.ndarray:
        """The sensor-stage effects among ``which`` (effect indices) on ``terms.I``; ``last``: then the clip to
        [0, 1] (not needed by the base model alone, which stays there by itself)."""
        for k in which:
            e, v = self.effects[k], vals[k]
            if e.stage == "sensor" and not e.is_identity(v):
                e.apply(terms, v, effect_rng(seed, e.name) if e.random_per_frame else None)
        I = terms.I
        if last and any(not e.is_identity(v) for e, v in zip(self.effects, vals)):
            np.clip(I, 0.0, 1.0, out=I)
        return I

    # ------------------------------------------------------------------ call

    def __call__(self, base_vectors, effect_vectors=None, seed: Optional[int] = None, out=None) -> np.ndarray:
        base = np.asarray(base_vectors, dtype=float)
        single = base.ndim == 1
        base = validate_rgb_params(np.atleast_2d(base))
        n = base.shape[0]
        if effect_vectors is None:
            ev = np.broadcast_to(self.effect_vector, (n, self.n_effect_params))
        else:
            ev = np.asarray(effect_vectors, dtype=float)
            ev = np.atleast_2d(ev) if ev.ndim == 1 else ev
            if ev.shape != (n, self.n_effect_params):
                raise ValueError(f"effect vectors must have shape ({n}, {self.n_effect_params}) for "
                                 f"{list(self.effect_names)}, got {ev.shape}")
            self._check_bounds(ev)
        seed = self.seed if seed is None else int(seed)
        h, w = self.shape
        if out is None:
            out = np.empty((n, h, w, 3), np.float32)
        elif single and out.ndim == 3:
            out = out[None]
        for k in range(n):
            I = self._evaluate(base[k], ev[k], seed)
            for c in range(3):
                out[k, :, :, c] = I[c]
        return out[0] if single else out

    def _check_bounds(self, ev):
        if not np.isfinite(ev).all():
            j = int(np.argwhere(~np.isfinite(ev))[0][1])
            raise ValueError(f"effect parameter {self.param_names[j]} is not finite")
        bad = (ev < self.lower) | (ev > self.upper)
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise ValueError(f"effect parameter {self.param_names[j]} = {ev[i, j]:g} outside "
                             f"[{self.lower[j]:g}, {self.upper[j]:g}]")
