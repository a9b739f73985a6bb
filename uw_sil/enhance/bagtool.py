"""Offline forward half on a recorded trial: render the sim geometry at every recorded pose, enhance the
frames (SIL, DCP or UDCP), and evaluate (quality against the truth of synthetic trials, feature matches).

:func:`enhance_bag` writes a new bag with ``/camera/image_enhanced`` next to the inputs (``uw-sil
enhance``); :func:`frames_with_geometry`, :func:`quality_rows` and :func:`feature_rows` feed ``uw-sil
features`` and the demo's report.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from ..bags.augment import cdr_header_stamp_ns, write_augmented_bag
from ..bags.reader import iter_raw, open_bag, read_samples
from ..bags.records import IMAGE_TYPE
from .sil import METHODS, Enhancer

__all__ = ["ENHANCED_TOPIC", "EnhanceBagResult", "enhance_bag", "frames_with_geometry", "enhance_all",
           "quality_rows", "feature_rows", "default_feature_frames", "LABELS"]

log = logging.getLogger(__name__)

ENHANCED_TOPIC = "/camera/image_enhanced"
#: Display names of the methods (the rows of Table 2).
LABELS = {"raw": "raw", "dcp": "DCP", "udcp": "UDCP", "sil": "SIL"}


@dataclass
class EnhanceBagResult:
    path: Path
    frames_in: int
    frames_out: int
    copied: int
    skipped_topics: list
    restored_fraction_mean: float
    warnings: list


def _image_msg(ts, stamp_ns: int, frame_id: str, rgb: np.ndarray):
    T_ = ts.types
    Header, Time, Image = T_["std_msgs/msg/Header"], T_["builtin_interfaces/msg/Time"], T_[IMAGE_TYPE]
    h, w = rgb.shape[:2]
    hdr = Header(stamp=Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000), frame_id=frame_id)
    msg = Image(header=hdr, height=h, width=w, encoding="rgb8", is_bigendian=0, step=3 * w,
                data=np.ascontiguousarray(rgb).reshape(-1))
    return ts.serialize_cdr(msg, IMAGE_TYPE)


def enhance_bag(bag, out, model, method: str = "sil", fog: Optional[str] = None, t0: float = 0.1,
                b_from_frame: bool = False, image_topic: str = "/camera/image_raw", scene_model=None,
                overwrite: bool = False, progress: Optional[Callable[[int, int], None]] = None,
                interrupted: Optional[Callable[[], None]] = None) -> EnhanceBagResult:
    """Enhance every frame of a trial into a new bag with ``/camera/image_enhanced`` (rgb8, the frame's
    header) next to all recorded topics.

    Parameters
    ----------
    bag, out : path
        Input trial and output bag (``enhanced.mcap`` -> ``enhanced/``); written atomically.
    model : UnderwaterParams or UnderwaterModel
        Fitted model (``method='sil'``).
    method : {'sil', 'dcp', 'udcp'}
    fog, t0, b_from_frame
        See :class:`uw_sil.enhance.sil.Enhancer`.
    scene_model : path, optional
        Scene to render (default: the shipped panel).
    progress : callable(done, total), optional
    interrupted : callable, optional
        Called between frames; raises to abort (then nothing is written).

    Notes
    -----
    Frames are paired with their pose and camera_info by stamp (:func:`uw_sil.bags.read_samples`);
    frames without a pose are not enhanced (counted in ``frames_in - frames_out``). The enhanced message
    is stored at the receive time of its recorded frame.
    """
    from rosbags.typesys import Stores, get_typestore

    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; expected one of {METHODS}")
    info = open_bag(bag)
    if image_topic not in info.topics:
        raise ValueError(f"bag {info.path} has no {image_topic}; it has {sorted(info.topics)}")
    if info.topics[image_topic].msgtype != IMAGE_TYPE:
        raise ValueError(f"{image_topic} is {info.topics[image_topic].msgtype}; enhance needs {IMAGE_TYPE}")
    enhancer = Enhancer(model, fog, t0=t0, b_from_frame=b_from_frame) if method == "sil" else Enhancer()
    log_time = {}
    with iter_raw(bag, [image_topic]) as stream:            # receive time of each frame, by header stamp
        for m in stream:
            log_time.setdefault(cdr_header_stamp_ns(m.data), m.log_time_ns)
    total = len(log_time)
    ts = get_typestore(Stores.ROS2_KILTED)
    stats = {"out": 0, "restored": [], "warnings": []}

    def added():
        renderer = None
        try:
            for s in read_samples(bag, image_topic=image_topic):
                if interrupted:
                    interrupted()
                if method == "sil":
                    if renderer is None:
                        from ..sim.render import Renderer

                        renderer = Renderer(scene_model, camera=s.camera)
                    elif renderer.camera != s.camera:
                        renderer.camera = s.camera
                    geo = renderer.render(s.pose)
                    r = enhancer.enhance(s.image, "sil", geometry=geo, camera=s.camera)
                else:
                    r = enhancer.enhance(s.image, method)
                for wmsg in r.warnings:
                    if wmsg not in stats["warnings"]:
                        stats["warnings"].append(wmsg)
                        log.warning("%s", wmsg)
                stats["restored"].append(r.restored_fraction)
                stats["out"] += 1
                if progress:
                    progress(stats["out"], total)
                yield log_time.get(s.stamp_ns, s.stamp_ns), ENHANCED_TOPIC, _image_msg(ts, s.stamp_ns, s.frame_id,
                                                                                        r.image)
        finally:
            if renderer is not None:
                renderer.close()

    res = write_augmented_bag(bag, out, added(), {ENHANCED_TOPIC: IMAGE_TYPE}, overwrite=overwrite)
    if progress and stats["out"] < total:
        progress(total, total)
    frac = float(np.mean(stats["restored"])) if stats["restored"] else 0.0
    return EnhanceBagResult(res.path, total, stats["out"], res.copied, res.skipped_topics, frac, stats["warnings"])


# ----------------------------------------------------------------------------------------- evaluation


def frames_with_geometry(bag, indices: Sequence[int], scene_model=None) -> list:
    """``[(index, Sample, RenderResult)]`` for the frames ``indices`` (positions among the bag's paired
    frames), rendered at their recorded poses."""
    from ..sim.render import Renderer

    want = sorted(set(int(i) for i in indices))
    if not want or want[0] < 0:
        raise ValueError(f"frame indices must be >= 0, got {list(indices)}")
    out, renderer = {}, None
    try:
        for i, s in enumerate(read_samples(bag)):
            if i in want:
                renderer = renderer or Renderer(scene_model, camera=s.camera)
                if renderer.camera != s.camera:
                    renderer.camera = s.camera
                out[i] = (i, s, renderer.render(s.pose))
            if i >= want[-1]:
                break
    finally:
        if renderer is not None:
            renderer.close()
    missing = [i for i in want if i not in out]
    if missing:
        raise ValueError(f"bag {bag} has no frame(s) {missing} (frames are counted from 0 among the images "
                         f"paired with a pose)")
    return [out[i] for i in indices]


def enhance_all(frames, model, fog=None, t0: float = 0.1, b_from_frame: bool = False,
                methods=("raw", "dcp", "udcp", "sil")) -> list:
    """For each ``(index, sample, render)``: ``{method: uint8 image}`` (``'raw'`` = as recorded)."""
    e = Enhancer(model, fog, t0=t0, b_from_frame=b_from_frame)
    out = []
    for _, s, geo in frames:
        d = {}
        for m in methods:
            d[m] = s.image if m == "raw" else e.enhance(s.image, m, geometry=geo, camera=s.camera).image
        out.append(d)
    return out


def quality_rows(frames, images) -> list:
    """Per frame and method: PSNR and SSIM against the clean render on object pixels (meaningful where the
    render is the truth: synthetic trials), UIQM and UCIQE of the whole frame."""
    from ..metrics.fidelity import psnr, ssim
    from ..metrics.uiqm import uciqe, uiqm

    rows = []
    for (i, s, geo), d in zip(frames, images):
        obj = geo.labels > 0
        for m, img in d.items():
            rows.append({"frame": i, "range_m": float(np.linalg.norm(s.pose[:3, 3])), "method": LABELS[m],
                         "psnr_db": psnr(img, geo.rgb, obj) if obj.any() else float("nan"),
                         "ssim": ssim(img, geo.rgb, obj) if obj.any() else float("nan"),
                         "uiqm": uiqm(img), "uciqe": uciqe(img)})
    return rows


def quality_markdown(rows) -> str:
    lines = ["| frame | range [m] | method | PSNR [dB] (object) | SSIM (object) | UIQM | UCIQE |",
             "|---:|---:|---|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['frame']} | {r['range_m']:.2f} | {r['method']} | {r['psnr_db']:.2f} | {r['ssim']:.4f} | "
                     f"{r['uiqm']:.3f} | {r['uciqe']:.3f} |")
    return "\n".join(lines) + "\n"


def default_feature_frames(n_frames: int) -> tuple:
    """Two frames of an approach from different poses: at 55 % and 70 % of the trial."""
    if n_frames < 2:
        raise ValueError(f"need at least 2 frames to match features, the bag has {n_frames}")
    i = int(round(0.55 * (n_frames - 1)))
    j = min(n_frames - 1, max(i + 1, int(round(0.70 * (n_frames - 1)))))
    return i, j


def feature_rows(frames, images, descriptors=None) -> list:
    """Table 2 rows (:func:`uw_sil.enhance.features.match_table`) for the two ``frames`` under each method."""
    from .features import ALL_DESCRIPTORS, match_table

    if len(frames) != 2:
        raise ValueError(f"feature matching needs exactly two frames, got {len(frames)}")
    pairs = {LABELS[m]: (images[0][m], images[1][m]) for m in images[0]}
    return match_table(pairs, descriptors or ALL_DESCRIPTORS)
