"""Locate the mismatch between a recording and the fitted simulation: frames, reduced copies, residual maps.

The diagnosis (:mod:`uw_sil.fit.diagnose`) works on a few frames of a recording, each rendered once at
its recorded pose (:class:`DiagFrame`). Fits and most signature tests run on a box-downsampled copy
(:class:`ReducedFrame`): the real frame is averaged over ``f x f`` blocks, and so is the render, with
the fraction of each block that hits the model kept as ``cover``. The base model (paper Eq. 1 with fog)
on such a block is then exactly ``b + cover * T * (i - b)`` (for a transmission ``T`` constant over the
block), i.e. the area average of the full-resolution simulation. Rendering at the reduced size instead
would alias the silhouettes while the real frame's are area-averaged, which looks like blur that the
recording does not have.

:func:`residual_maps` gives real - sim per frame and channel; :func:`locate` says where the mismatch
is: object vs water, a 3x3 grid of image regions, panel parts (render part ids -> node names), range
bins, each as RMS and mean residual in grey levels and as a share of the total squared residual above
the camera noise.
"""
from __future__ import annotations

import atexit
import os
import threading
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

__all__ = ["DiagFrame", "ReducedFrame", "box_down", "reduce_frame", "reduction_factor", "load_frames",
           "frames_from_samples", "split_frames", "base_sim", "residual_maps", "locate", "frame_geometry",
           "added_surface", "corrected_frame", "render_scene", "registered_pose", "LABEL_WATER", "LABEL_PANEL"]

LABEL_WATER = 0
LABEL_PANEL = 1


@dataclass
class DiagFrame:
    """One recorded frame with its render at the recorded pose (full resolution)."""

    index: int                 # position in the recording
    stamp_ns: int
    image: np.ndarray          # (H, W, 3) uint8 RGB
    render: object             # uw_sil.sim.render.RenderResult
    camera: object             # uw_sil.sim.camera.CameraModel
    pose: np.ndarray           # (4, 4) T_cam_panel as recorded
    coverage: float            # fraction of pixels on the model
    role: str = "fit"          # 'fit', 'heldout' or 'report' (set_aside)
    part_names: Sequence[str] = ()
    # the scene model the frame was rendered from (``model`` of load_frames: None for the shipped panel, a mesh
    # path or a loaded scene): a corrected pose is rendered from it (corrected_frame)
    scene: object = None

    @property
    def range_median(self) -> float:
        r = self.render.range[np.isfinite(self.render.range)]
        return float(np.median(r)) if r.size else float("inf")


def box_down(a: np.ndarray, f: int) -> np.ndarray:
    """Mean over ``f x f`` blocks of the first two axes (cropped to a multiple of ``f``), float32."""
    a = np.asarray(a)
    if f == 1:
        return a.astype(np.float32, copy=True)
    h, w = (a.shape[0] // f) * f, (a.shape[1] // f) * f
    a = a[:h, :w].astype(np.float32, copy=False)
    return a.reshape(h // f, f, w // f, f, *a.shape[2:]).mean(axis=(1, 3), dtype=np.float32)


def reduction_factor(width: int, target_width: int = 320) -> int:
    """Integer block size that brings ``width`` to about ``target_width`` (at least 1)."""
    return max(1, int(round(width / float(target_width))))


@dataclass
class ReducedFrame:
    """A :class:`DiagFrame` box-downsampled by ``factor`` (see the module docstring).

    Attributes
    ----------
    image : (h, w, 3) float32, real frame in grey levels (0..255)
    rgb : (h, w, 3) float32, clean render averaged over the block's model pixels (0 where none)
    cover : (h, w) float32, fraction of the block on the model
    range, depth : (h, w) float32, averaged over the block's model pixels; ``inf`` where ``cover == 0``
    labels : (h, w) uint8, label of the block's centre pixel where ``cover >= 0.5``, else 0 (water)
    part_ids : (h, w) uint16, part of the block's centre pixel
    obj : (h, w) bool, blocks entirely on the panel and not on a part boundary (no mixed pixels)
    water : (h, w) bool, blocks with no model pixel at least ``margin`` blocks away from the model
    normals : (h, w, 3) float32, the full-resolution surface normals averaged over the block's model pixels
        (not renormalized: a Lambert cosine ``n . l`` is linear in ``n``, so the mean normal gives the block's
        mean cosine; normals taken from the averaged depth turned the sides of knobs and levers at 1/8 of
        the resolution, and the lamp model's residual on the nearest frame of a lamp-lit dive with the true
        rig was 0.66 instead of 0.12 grey levels²); None: from the reduced depth
    """

    frame: DiagFrame
    factor: int
    image: np.ndarray
    rgb: np.ndarray
    cover: np.ndarray
    range: np.ndarray
    depth: np.ndarray
    labels: np.ndarray
    part_ids: np.ndarray
    obj: np.ndarray
    water: np.ndarray
    camera: object = None
    normals: Optional[np.ndarray] = None
    extra: dict = field(default_factory=dict)    # what is computed once per frame (θ's reference), a cache

    def __getstate__(self):
        # the cache is rebuilt where it is needed: θ's reference of a 320x240 frame pickles to ~25 MB
        return {**self.__dict__, "extra": {}}

    @property
    def shape(self) -> tuple:
        return self.cover.shape

    @property
    def r_fin(self) -> np.ndarray:
        """Range with 0 where nothing is hit."""
        return np.where(self.cover > 0, self.range, np.float32(0.0))

    def fine_geometry(self):
        """The view at twice this resolution (the full resolution at most) for detail below these pixels
        (:attr:`uw_sil.sim.model.Geometry.fine`): depth and range averaged over the model pixels of each
        block, the part of the block's centre; None at full resolution. Built once per frame and process."""
        if self.factor < 2:
            return None
        g = self.extra.get("fine_geometry")
        if g is False:
            return None
        if g is None:
            from ..sim.model import Geometry

            f = self.factor // 2
            hit, cover, dep, rng, parts = _block_geometry(self.frame.render, f)
            h, w = cover.shape
            cam = self.frame.camera.binned(f)
            g = Geometry(cam, np.zeros((h, w, 3), np.float32), dep, rng, part_ids=parts, pose=self.frame.pose)
            if g.shape != (2 * self.shape[0], 2 * self.shape[1]):
                self.extra["fine_geometry"] = False  # an odd factor, or a size not a multiple of it
                return None
            self.extra["fine_geometry"] = g
        return g


def dilate(mask: np.ndarray, r: int) -> np.ndarray:
    import cv2

    if r <= 0:
        return mask.copy()
    k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), k) > 0


def erode(mask: np.ndarray, r: int) -> np.ndarray:
    import cv2

    if r <= 0:
        return mask.copy()
    k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    return cv2.erode(mask.astype(np.uint8), k, borderValue=1) > 0


def _block_geometry(rr, f: int) -> tuple:
    """A render's geometry box-downsampled by ``f``: ``(hit, cover, depth, range, part_ids)`` with the full-resolution
    hit mask, the share of each block on the model, depth and range averaged over the block's model pixels
    (``inf`` where it has none, float32) and the part of the block's centre pixel."""
    hit = np.isfinite(rr.range) & np.isfinite(rr.depth)
    cover = box_down(hit, f)
    safe = np.maximum(cover, 1e-6)
    none = cover <= 0
    dep = np.where(none, np.inf, box_down(np.where(hit, rr.depth, 0.0), f) / safe).astype(np.float32)
    rng = np.where(none, np.inf, box_down(np.where(hit, rr.range, 0.0), f) / safe).astype(np.float32)
    h, w = cover.shape
    c = f // 2
    return hit, cover, dep, rng, rr.part_ids[c:h * f:f, c:w * f:f][:h, :w]


def reduce_frame(frame: DiagFrame, factor: int, water_margin: int = 2) -> ReducedFrame:
    """Box-downsample a frame and its render (see :class:`ReducedFrame`)."""
    rr = frame.render
    f = int(factor)
    hit, cover, dep, rng, parts_c = _block_geometry(rr, f)
    safe = np.maximum(cover, 1e-6)
    none = cover <= 0
    rgb = box_down(np.where(hit[..., None], rr.rgb, 0.0), f) / safe[..., None]
    rgb[none] = 0.0
    h, w = cover.shape
    c = f // 2
    labels_c = rr.labels[c:h * f:f, c:w * f:f][:h, :w]
    labels = np.where(cover >= 0.5, labels_c, 0).astype(np.uint8)
    # pure blocks: one part over the whole block (no silhouette, no part boundary inside)
    pmax = rr.part_ids[:h * f, :w * f].reshape(h, f, w, f).max(axis=(1, 3))
    pmin = rr.part_ids[:h * f, :w * f].reshape(h, f, w, f).min(axis=(1, 3))
    lab_min = rr.labels[:h * f, :w * f].reshape(h, f, w, f).min(axis=(1, 3))
    obj = (cover >= 1.0) & (pmax == pmin) & (lab_min == LABEL_PANEL)
    water = ~dilate(cover > 0, water_margin)
    from ..sim.model import Geometry

    n_full = Geometry.from_render(rr, frame.camera, frame.pose).normals
    normals = box_down(np.where(hit[..., None], n_full, 0.0), f) / safe[..., None]
    normals[none] = 0.0
    return ReducedFrame(frame, f, box_down(frame.image, f), rgb.astype(np.float32), cover, rng, dep, labels,
                        parts_c.astype(np.uint16), obj, water,
                        camera=frame.camera.binned(f),
                        normals=normals.astype(np.float32))


def base_sim(rf: ReducedFrame, params, fog: str = "exp2") -> np.ndarray:
    """Base model (Eq. 1 with fog) on a reduced frame, area-exact at silhouettes: (h, w, 3) in 0..1.

    ``params``: the 7-vector ``(a_r, a_g, a_b, b_r, b_g, b_b, rho_f)``.
    """
    p = np.asarray(params, dtype=np.float32).ravel()
    r = rf.r_fin
    z = np.where(rf.cover > 0, rf.depth, np.float32(0.0))
    if fog == "exp2":
        fz = (p[6] * z) ** 2
    elif fog == "exp":
        fz = p[6] * z
    else:
        fz = np.zeros_like(z)
    out = np.empty(rf.shape + (3,), np.float32)
    for c in range(3):
        T = np.exp(-(r * p[c] + fz)) * rf.cover
        out[..., c] = p[3 + c] + T * (rf.rgb[..., c] - p[3 + c])
    return out


def load_frames(bag, k: int = 8, model=None, min_coverage: float = 0.01, image_topic: str = "/camera/image_raw",
                max_frames_scan: int = 100000, renderer=None) -> list:
    """Read up to ``k`` frames spread evenly over a recording, render each at its recorded pose.

    Frames where the model covers less than ``min_coverage`` of the image are skipped (and replaced by
    other frames when the recording has more). Raises ValueError when fewer than 2 usable frames remain.
    """
    from ..bags import open_bag, read_samples

    info = open_bag(bag)
    if image_topic not in info.topics:
        raise ValueError(f"bag {bag} has no topic {image_topic!r} (topics: {', '.join(sorted(info.topics))})")
    n = int(info.topics[image_topic].count or 0)
    if n < 1:
        raise ValueError(f"bag {bag}: no images on {image_topic}")
    # candidate order: an even spread first, then the rest (to replace unusable frames)
    spread = list(dict.fromkeys(np.linspace(0, n - 1, min(k, n)).round().astype(int).tolist()))
    wanted = set(spread)
    samples = []
    for i, s in enumerate(read_samples(bag, image_topic=image_topic)):
        if i >= max_frames_scan:
            break
        samples.append((i, s) if i in wanted or n <= 4 * k else (i, None))
    return frames_from_samples(samples, k, model=model, min_coverage=min_coverage, renderer=renderer,
                               what=f"bag {bag}")


def frames_from_samples(samples: list, k: int = 8, model=None, min_coverage: float = 0.01, renderer=None,
                        what: str = "recording") -> list:
    """Up to ``k`` frames spread evenly over ``samples``, each rendered at its recorded pose.

    ``samples`` are ``(index, Sample or None)`` in recording order (None: a paired image that was not kept);
    the spread is over all of them, the frames are taken from those kept, unusable ones (the model covers
    less than ``min_coverage``) replaced by the next kept ones. :func:`load_frames` reads a bag so; the
    ``backward_fit`` node collects the samples of a live stream so. Raises ValueError (prefixed ``what``)
    when fewer than 2 usable frames remain.
    """
    from ..sim.render import Renderer

    frames, skipped = [], []
    own = renderer is None
    rend = renderer
    try:
        # the stream may hold fewer samples than the topic count (unpaired images): rebuild the spread
        avail = [i for i, s in samples]
        if not avail:
            raise ValueError(f"{what}: no image could be paired with camera_info and /panel/pose")
        by_idx = dict(samples)
        order = [avail[j] for j in dict.fromkeys(np.linspace(0, len(avail) - 1, min(k, len(avail)))
                                                .round().astype(int).tolist())]
        rest = [i for i in avail if i not in order]
        for i in order + rest:
            if len(frames) >= k:
                break
            s = by_idx.get(i)
            if s is None:
                continue
            if rend is None:
                rend = Renderer(model, camera=s.camera)
            elif rend.camera != s.camera:
                rend.camera = s.camera
            rr = rend.render(s.pose)
            cov = float(np.mean(np.isfinite(rr.range)))
            if cov < min_coverage:
                skipped.append((i, f"model covers {100 * cov:.1f}% of the image"))
                continue
            if frames and s.image.shape != frames[0].image.shape:
                raise ValueError(f"frame {i} is {s.image.shape[1]}x{s.image.shape[0]} but earlier frames are "
                                 f"{frames[0].image.shape[1]}x{frames[0].image.shape[0]}")
            frames.append(DiagFrame(i, int(s.stamp_ns), np.ascontiguousarray(s.image), rr, s.camera,
                                    np.asarray(s.pose, float), cov, part_names=tuple(rend.node_names), scene=model))
    finally:
        if own and rend is not None:
            rend.close()
    if len(frames) < 2:
        why = f"; e.g. frame {skipped[0][0]}: {skipped[0][1]}" if skipped else ""
        raise ValueError(f"{what}: only {len(frames)} usable frame(s) showing the scene model (need >= 2){why}")
    frames.sort(key=lambda f: f.index)
    return frames


def split_frames(frames: list, heldout_share: float = 0.5) -> tuple:
    """Assign roles: fit and held-out frames interleaved over range (both spread from far to near).

    Frames are sorted by median range and every second one (starting with the second farthest) is held
    out, so both sets span the approach. At least one frame of each. Returns (fit, heldout) lists.
    """
    if len(frames) < 2:
        raise ValueError("need at least 2 frames to hold some out")
    order = sorted(frames, key=lambda f: -f.range_median)
    n_held = min(len(frames) - 1, max(1, int(round(len(frames) * heldout_share))))
    # evenly interleaved positions for the held-out frames
    pos = set(np.round(np.linspace(1, len(frames) - 1, n_held)).astype(int).tolist()) if n_held < len(frames) - 1 \
        else set(range(1, len(frames)))
    if len(pos) < n_held:
        pos = set(range(1, len(frames), 2))
    fit, held = [], []
    for j, f in enumerate(order):
        (held if j in pos else fit).append(f)
        f.role = "heldout" if j in pos else "fit"
    return sorted(fit, key=lambda f: f.index), sorted(held, key=lambda f: f.index)


def set_aside(frames: list, n: int) -> tuple:
    """Keep ``n`` frames out of the fit and the selection: the *report* frames, on which only the model the
    selection ended with and the base model are scored (held-out θ chose among the models, so it flatters
    the one chosen; frames no choice saw do not). Interleaved over range, never the farthest or the nearest
    (those the fit and the selection need most). Returns ``(rest, report)``; at least 3 frames must remain."""
    n = int(n)
    if n <= 0:
        return list(frames), []
    if len(frames) - n < 3:
        raise ValueError(f"{len(frames)} frames cannot spare {n} report frame(s): at least 3 must remain")
    order = sorted(frames, key=lambda f: -f.range_median)
    # spacing (len - 1) / (n + 1) > 1: distinct positions
    pos = set(np.round(np.linspace(0, len(order) - 1, n + 2))[1:-1].astype(int).tolist())
    report = [f for j, f in enumerate(order) if j in pos]
    for f in report:
        f.role = "report"
    return ([f for f in frames if all(f is not r for r in report)], sorted(report, key=lambda f: f.index))


def residual_maps(rframes: Sequence[ReducedFrame], sims: Sequence[np.ndarray]) -> list:
    """real - sim in grey levels, (h, w, 3) float32 per frame (``sims`` in 0..1)."""
    return [rf.image - 255.0 * s for rf, s in zip(rframes, sims)]


def _stats(res: np.ndarray, mask: np.ndarray, noise2: float) -> Optional[dict]:
    n = int(mask.sum())
    if n == 0:
        return None
    v = res[mask]
    ms = float(np.mean(v * v))
    return {"pixels": n, "rms": float(np.sqrt(ms)), "mean": [float(x) for x in v.mean(axis=0)],
            "rms_rgb": [float(x) for x in np.sqrt(np.mean(v * v, axis=0))],
            "excess_ms": max(0.0, ms - noise2) * n}


def locate(rframes: Sequence[ReducedFrame], residuals: Sequence[np.ndarray], noise_sigma: Sequence = None,
           range_bins: Sequence[float] = (0.0, 1.5, 2.0, 2.5, 3.0, 3.5, np.inf)) -> dict:
    """Where real and simulated frames differ, as numbers.

    Returns ``{"regions": [...], "total_excess_ms": float}``; each region is ``{"kind", "name", "pixels",
    "rms", "mean" (per channel), "rms_rgb", "share"}`` with ``share`` the region's part of the squared
    residual above the camera noise (``noise_sigma``: per-frame per-channel sigma in grey levels at
    the reduced size), summed over all frames. Kinds: ``class`` (object / water / silhouette band),
    ``grid`` (3x3 image regions), ``part`` (panel part classes), ``range`` (object pixels per range bin).
    """
    from ..sim.scene import part_class

    acc: dict = {}

    def add(kind, name, st):
        if st is None:
            return
        key = (kind, name)
        a = acc.setdefault(key, {"kind": kind, "name": name, "pixels": 0, "ss": 0.0, "sum": np.zeros(3),
                                 "ss_rgb": np.zeros(3), "excess": 0.0})
        n = st["pixels"]
        a["pixels"] += n
        a["ss"] += st["rms"] ** 2 * n
        a["sum"] += np.asarray(st["mean"]) * n
        a["ss_rgb"] += np.asarray(st["rms_rgb"]) ** 2 * n
        a["excess"] += st["excess_ms"]

    for k, (rf, res) in enumerate(zip(rframes, residuals)):
        s2 = float(np.mean(np.square(noise_sigma[k]))) if noise_sigma is not None else 0.0
        band = (rf.cover > 0) & ~rf.obj & ~(rf.labels == LABEL_PANEL) | ((rf.cover > 0) & (rf.cover < 1))
        band |= ~rf.water & (rf.cover <= 0)
        obj = rf.obj
        add("class", "object", _stats(res, obj, s2))
        add("class", "water", _stats(res, rf.water, s2))
        add("class", "silhouette", _stats(res, band & ~obj & ~rf.water, s2))
        h, w = rf.shape
        for gi, rn in enumerate(("top", "middle", "bottom")):
            for gj, cn in enumerate(("left", "centre", "right")):
                m = np.zeros((h, w), bool)
                m[gi * h // 3:(gi + 1) * h // 3, gj * w // 3:(gj + 1) * w // 3] = True
                add("grid", f"{rn}-{cn}", _stats(res, m, s2))
        names = rf.frame.part_names
        if names:
            pids = np.unique(rf.part_ids[obj])
            classes: dict = {}
            for pid in pids:
                if pid == 0 or pid > len(names):
                    continue
                classes.setdefault(part_class(names[pid - 1]) or "part", []).append(pid)
            for cname, ids in classes.items():
                add("part", cname, _stats(res, obj & np.isin(rf.part_ids, ids), s2))
        rmed = rf.frame.range_median
        for lo, hi in zip(range_bins[:-1], range_bins[1:]):
            if lo <= rmed < hi:
                add("range", f"{lo:g}-{hi:g} m" if np.isfinite(hi) else f">{lo:g} m", _stats(res, obj, s2))
    total = sum(a["excess"] for a in acc.values() if a["kind"] == "class") or 1.0
    regions = []
    for a in acc.values():
        n = max(1, a["pixels"])
        regions.append({"kind": a["kind"], "name": a["name"], "pixels": int(a["pixels"]),
                        "rms": float(np.sqrt(a["ss"] / n)), "mean": [float(x) for x in a["sum"] / n],
                        "rms_rgb": [float(x) for x in np.sqrt(a["ss_rgb"] / n)],
                        "share": float(a["excess"] / total)})
    order = {"class": 0, "grid": 1, "part": 2, "range": 3}
    regions.sort(key=lambda r: (order[r["kind"]], -r["share"]))
    return {"regions": regions, "total_excess_ms": float(total)}


def frame_geometry(frame, geo_effects: dict) -> tuple:
    """(as rendered, with the geometry effects) full-resolution geometry of a frame: geometry-stage effects
    (a seafloor, a pose correction) applied to its render, as the simulator applies them before shading."""
    from types import SimpleNamespace

    from ..sim.effects import get_effect
    from ..sim.model import Geometry

    rr = frame.render
    geom = Geometry(frame.camera, rr.rgb, rr.depth, rr.range, rr.labels, rr.part_ids, pose=frame.pose)
    t = SimpleNamespace(geom=geom)
    for name, values in geo_effects.items():
        eff = get_effect(name)
        eff.apply(t, eff.values(values), None)
    return geom, t.geom


def added_surface(frame, geo_effects: dict, grow: int = 24) -> np.ndarray:
    """Pixels (full resolution, grown by ``grow`` px: the margin of the noise statistics) where geometry
    effects with these values add surfaces to what the frame's render saw."""
    before, after = frame_geometry(frame, geo_effects)
    return dilate(after.hit & ~before.hit, grow)


def corrected_frame(frame, geo_effects: dict):
    """The frame with its render replaced by the full-resolution geometry the effects give: for a pose
    correction ``Delta`` the frame's scene rendered at ``Delta @ T_recorded`` (exactly what a camera at that
    pose sees: what moves into view appears, what is hidden stays hidden), then the other geometry effects (a
    seafloor) applied to that render, which is reduced like any frame afterwards.

    (A pose correction used to be the recorded render warped to the new pose at full resolution. A warp cannot
    show what the recorded pose did not see and resamples the colours: at 320x240 and 3.5 m, for mild pose
    errors, the warp to the true pose removed a third to a half of the frames' misfit, a render at it two thirds
    to all of it.)"""
    import dataclasses

    from ..sim.effects import get_effect
    from ..sim.render import RenderResult

    geo = dict(geo_effects)
    pose_values = geo.pop("pose_error", None)
    if pose_values is not None:
        eff = get_effect("pose_error")
        D = eff.correction(eff.values(pose_values))          # the bias; the diagnosis fits no jitter
        if not np.array_equal(D, np.eye(4)):
            T = D @ np.asarray(frame.pose, float)
            rr = render_scene(frame, T)
            frame = dataclasses.replace(frame, render=rr, pose=T, coverage=float(np.mean(np.isfinite(rr.range))))
    if not geo:
        return frame
    _, g = frame_geometry(frame, geo)
    rr = RenderResult(rgb=g.rgb, depth=g.depth, range=g.range, labels=g.labels, part_ids=g.part_ids)
    return dataclasses.replace(frame, render=rr, coverage=float(np.mean(g.hit)))


_RENDER = {"renderer": None, "scene": None}
_RENDER_LOCK = threading.Lock()


def _close_render():
    with _RENDER_LOCK:
        if _RENDER["renderer"] is not None:
            _RENDER["renderer"].close()
        _RENDER.update(renderer=None, scene=None)


def _scene_renderer(frame):
    """The process's renderer of ``frame``'s scene with its camera (``_RENDER_LOCK`` held by the caller)."""
    from ..sim.render import Renderer

    rend, cached = _RENDER["renderer"], _RENDER["scene"]
    # a mesh path compares by value (frames unpickled in a worker process carry copies), a loaded scene by identity
    same = cached is frame.scene or (isinstance(cached, (str, os.PathLike)) and cached == frame.scene)
    if rend is None or not same:
        if rend is not None:
            rend.close()
        _RENDER["renderer"] = None
        rend = Renderer(frame.scene, camera=frame.camera)
        if not _RENDER.get("atexit"):
            # closed before the interpreter tears its modules down (PyOpenGL cannot free its buffers then)
            atexit.register(_close_render)
            _RENDER["atexit"] = True
        _RENDER.update(renderer=rend, scene=frame.scene)
    elif rend.camera != frame.camera:
        rend.camera = frame.camera
    return rend


def render_scene(frame, T_cam_panel):
    """The scene of ``frame`` (:attr:`DiagFrame.scene`) rendered at ``T_cam_panel`` with the frame's camera, full
    resolution. One renderer per process, kept for the next call of the same scene (a diagnosis renders its
    frames again at every pose refit; making the renderer costs more than a frame)."""
    with _RENDER_LOCK:
        return _scene_renderer(frame).render(T_cam_panel)


def registered_pose(frame):
    """``(Delta, info)``: the correction of ``frame``'s recorded pose (``T = Delta @ T_recorded``) that aligns its
    scene's rendered panel face with the frame itself, found for this frame alone by ECC
    (:meth:`uw_sil.sim.align.FaceAligner.correct`: a homography, coarse to fine, invariant to the gain and offset the
    water puts between the clean render and the frame; refused beyond 5 degrees or 10 % of the range). ``Delta`` is
    None where the alignment is refused (``info["refused"]``: why)."""
    from ..sim.align import FaceAligner

    with _RENDER_LOCK:
        T, info = FaceAligner(frame.scene, renderer=_scene_renderer(frame)).correct(frame.image, frame.camera,
                                                                                    frame.pose)
    return (None if T is None else T @ np.linalg.inv(np.asarray(frame.pose, float))), info
