"""Diagnosis of footage without a scene model or poses (``uw-sil diagnose --images``).

Without geometry there is no simulation to compare with, so only footprints that show in the images
themselves can be judged:

- ``vignetting``: radial darkening about the image centre in the *smooth* (water-like) parts of the
  frames, the same in every frame of a sequence; told apart from a vertical gradient (sunlight from
  above, or a lamp above the camera) by fitting both;
- ``artificial_light``: the shape of the falloff in open water that is *not* radial about the centre:
  a gradient or an off-centre bright region (lamp-lit backscatter, skewed towards the lamp side);
- ``sensor_noise``: noise level from flat regions and how its variance rises with intensity (a
  Poisson-Gaussian fit, Foi et al. 2008), spatial correlation (lag-1 vs lag-3 differences) and 8x8
  block artefacts of JPEG/MJPEG coding;
- ``marine_snow``: sparse small bright outliers; with a sequence, whether they persist between frames;
- ``camera_response``: black-level pedestal (the darkest pixels of *every* channel stay above 20 grey
  levels); a white-balance cast (grey-world gains) is reported but not counted: the water's attenuation
  casts colour too.

Not judged (they need the scene model, the range or the poses): ``forward_scatter`` (the sharp
reference is unknown), ``backscatter_coefficient`` (needs range), ``unmodeled_geometry`` (needs the
scene model), ``pose_error`` (needs poses), ``port_refraction`` (needs the scene model and poses). They are
listed under ``not_judged``.

The output follows the diagnosis JSON schema (:mod:`uw_sil.fit.diagnose`) with ``"mode": "images"``:
``candidates`` is empty and the θ fields are ``null`` (nothing was fitted).

References
----------
.. [1] A. Foi, M. Trimeche, V. Katkovnik and K. Egiazarian, "Practical Poissonian-Gaussian noise modeling
   and fitting for single-image raw-data", IEEE TIP 17(10), 1737-1754, 2008.
.. [2] D. Akkaynak and T. Treibitz, "Sea-thru: a method for removing water from underwater images",
   CVPR 2019 (backscatter and illuminant without geometry are ill-posed; what is left is judged here).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from .signatures import jsonable, trimmed_sigma

__all__ = ["load_images", "diagnose_images", "IMAGE_EXTENSIONS", "NOT_JUDGED"]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm")
NOT_JUDGED = {
    "forward_scatter": "needs the sharp scene (a scene model and poses) to measure lost detail against",
    "backscatter_coefficient": "needs the range of every pixel",
    "unmodeled_geometry": "needs a scene model to say what should be open water",
    "pose_error": "needs recorded poses and a scene model",
    "port_refraction": "needs a scene model and poses: where the pinhole model puts the edges",
}
_MAD = 1.4826
_LUMA = np.array([0.299, 0.587, 0.114], np.float32)


def load_images(src, image_topic: str = "/camera/image_raw", k: int = 12) -> list:
    """Up to ``k`` RGB uint8 images spread over a folder (sorted names) or a bag's image topic: [(name, img)]."""
    import cv2

    p = Path(src)
    if p.is_dir() and not (p / "metadata.yaml").exists() and not any(p.glob("*.mcap")) and not any(p.glob("*.db3")):
        files = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_EXTENSIONS)
        if not files:
            raise ValueError(f"{src}: no images ({', '.join(IMAGE_EXTENSIONS)}) in this folder")
        pick = sorted(set(np.linspace(0, len(files) - 1, min(k, len(files))).round().astype(int).tolist()))
        out = []
        for i in pick:
            img = cv2.imread(str(files[i]), cv2.IMREAD_COLOR)
            if img is None:
                raise ValueError(f"{files[i]}: not a readable image")
            out.append((files[i].name, cv2.cvtColor(img, cv2.COLOR_BGR2RGB)))
        return out
    if not p.exists():
        raise FileNotFoundError(f"{src}: no such folder or bag")
    from ..bags import open_bag
    from ..bags.imgmsg import compressed_to_rgb, image_to_rgb
    from ..bags.reader import iter_messages

    info = open_bag(src)
    if image_topic not in info.topics:
        raise ValueError(f"bag {src} has no topic {image_topic!r} (topics: {', '.join(sorted(info.topics))})")
    n = int(info.topics[image_topic].count or 0)
    pick = set(np.linspace(0, max(n - 1, 0), min(k, max(n, 1))).round().astype(int).tolist())
    out = []
    for i, (_, msg) in enumerate(iter_messages(src, image_topic)):
        if i in pick:
            img = compressed_to_rgb(msg) if hasattr(msg, "format") and not hasattr(msg, "encoding") else image_to_rgb(msg)
            out.append((f"{image_topic}#{i}", img))
    if not out:
        raise ValueError(f"bag {src}: no images on {image_topic}")
    return out


def _lum(img):
    return np.asarray(img, np.float32) @ _LUMA


def _smooth_mask(Y: np.ndarray, frac: float = 0.35) -> np.ndarray:
    """Water-like pixels: the smoothest ``frac`` of the image by local gradient energy (7x7)."""
    import cv2

    gx = cv2.Sobel(Y, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(Y, cv2.CV_32F, 0, 1, ksize=3)
    e = cv2.blur(gx * gx + gy * gy, (15, 15))
    thr = np.quantile(e, frac)
    m = e <= thr
    m &= (Y > 8) & (Y < 247)
    return m


def _falloff(frames) -> dict:
    """Radial vs gradient structure of log-brightness in the smooth regions, per frame and in common."""
    rows = []
    for name, img in frames:
        Y = _lum(img)
        h, w = Y.shape
        m = _smooth_mask(Y)
        if m.sum() < 500:
            continue
        x = (np.arange(w) - (w - 1) / 2) / (0.5 * math.hypot(w, h))
        y = (np.arange(h) - (h - 1) / 2) / (0.5 * math.hypot(w, h))
        X, Yc = np.meshgrid(x, y)
        L = np.log(Y[m] + 1.0)
        rho2 = (X * X + Yc * Yc)[m]
        A_rad = np.stack([np.ones_like(rho2), rho2, rho2 * rho2], 1)
        A_grad = np.stack([np.ones_like(rho2), X[m], Yc[m]], 1)
        A_all = np.concatenate([A_rad, A_grad[:, 1:]], 1)
        ss = float(np.sum((L - L.mean()) ** 2)) or 1e-9
        res = {}
        for key, A in (("radial", A_rad), ("gradient", A_grad), ("both", A_all)):
            c, *_ = np.linalg.lstsq(A, L, rcond=None)
            r = L - A @ c
            res[key] = (c, 1 - float(np.sum(r * r)) / ss)
        c = res["both"][0]
        corner = math.exp(c[1] + c[2]) - 1                       # radial part at the corner (rho = 1)
        grad = math.hypot(c[3], c[4])                            # log-brightness change per half-diagonal
        rows.append({"frame": name, "corner_falloff": -corner, "gradient": grad,
                     "gradient_direction_deg": math.degrees(math.atan2(c[4], c[3])),
                     "r2_radial": res["radial"][1], "r2_gradient": res["gradient"][1], "r2_both": res["both"][1],
                     "smooth_share": float(m.mean())})
    return {"frames": rows}


def _noise(frames) -> dict:
    import cv2

    rows = []
    for name, img in frames:
        Y = _lum(img)
        gx = cv2.Sobel(cv2.GaussianBlur(Y, (0, 0), 1.5), cv2.CV_32F, 1, 0)
        gy = cv2.Sobel(cv2.GaussianBlur(Y, (0, 0), 1.5), cv2.CV_32F, 0, 1)
        flat = np.hypot(gx, gy) < np.quantile(np.hypot(gx, gy), 0.3)
        d1 = Y[:, 1:] - Y[:, :-1]
        d3 = Y[:, 3:] - Y[:, :-3]
        ok1 = flat[:, 1:] & flat[:, :-1]
        ok3 = flat[:, 3:] & flat[:, :-3]
        if ok1.sum() < 500 or ok3.sum() < 500:
            continue
        s1 = trimmed_sigma(d1[ok1])
        s3 = trimmed_sigma(d3[ok3])
        # intensity dependence: sigma in intensity bins of the flat pixels (lag-1 differences)
        I = 0.5 * (Y[:, 1:] + Y[:, :-1])[ok1]
        D = d1[ok1]
        edges = np.quantile(I, np.linspace(0, 1, 7))
        pts = []
        for lo, hi in zip(edges[:-1], edges[1:]):
            sel = (I >= lo) & (I <= hi)
            if sel.sum() > 200:
                dd = D[sel]
                pts.append((float(I[sel].mean()), float(trimmed_sigma(dd) ** 2)))
        slope = None
        if len(pts) >= 3 and np.ptp([p[0] for p in pts]) > 30:
            A = np.stack([np.ones(len(pts)), [p[0] for p in pts]], 1)
            c, *_ = np.linalg.lstsq(A, [p[1] for p in pts], rcond=None)
            slope = float(c[1])
        # 8x8 block artefacts: mean |horizontal difference| at columns 8k-1|8k against the others
        ad = np.abs(d1).mean(axis=0)
        cols = np.arange(ad.size)
        on = ad[(cols % 8) == 7].mean() if ad.size > 16 else 0.0
        off = ad[(cols % 8) != 7].mean() if ad.size > 16 else 1.0
        rows.append({"frame": name, "sigma_lag1": float(s1), "sigma_lag3": float(s3),
                     "lag1_over_lag3": float(s1 / s3) if s3 > 0 else 1.0, "shot_gain_dn": slope,
                     "block_ratio": float(on / max(off, 1e-6)), "variance_by_intensity": pts})
    return {"frames": rows}


def _particles(frames) -> dict:
    """Small bright (and dark) outliers against the frame's own 7x7 median (what a particle smaller than the
    window leaves), counted away from the edges of larger structures (:func:`~uw_sil.fit.signatures.own_specks`)."""
    import cv2

    from .signatures import own_specks

    rows = []
    prev = None
    for name, img in frames:
        pos, neg, ok = own_specks(_lum(img))
        npos = cv2.connectedComponentsWithStats(pos.astype(np.uint8), 8)[0] - 1
        nneg = cv2.connectedComponentsWithStats(neg.astype(np.uint8), 8)[0] - 1
        mp = max(ok.sum(), 1) / 1e6
        persist = None
        if prev is not None and prev.shape == pos.shape and pos.sum() and prev.sum():
            persist = float((pos & cv2.dilate(prev.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)).sum()
                            / pos.sum())
        rows.append({"frame": name, "positive_per_mpx": npos / mp, "negative_per_mpx": nneg / mp,
                     "persistence": persist})
        prev = pos
    return {"frames": rows}


def _response(frames) -> dict:
    rows = []
    for name, img in frames:
        x = np.asarray(img, np.float32).reshape(-1, 3)
        dark = np.quantile(x, 0.001, axis=0)
        bright = np.quantile(x, 0.999, axis=0)
        mean = x.mean(axis=0)
        gw = mean.mean() / np.maximum(mean, 1e-3)            # grey-world gains
        rows.append({"frame": name, "black_dn": dark.tolist(), "white_dn": bright.tolist(),
                     "grey_world_gains": gw.tolist(), "mean_rgb": mean.tolist()})
    return {"frames": rows}


def _med(vals):
    vals = [v for v in vals if v is not None]
    return float(np.median(vals)) if vals else None


def diagnose_images(src, image_topic: str = "/camera/image_raw", k: int = 12,
                    progress: Optional[Callable[[str], None]] = None, sequence: Optional[bool] = None) -> dict:
    """Judge footage without a scene model (module docstring); returns the JSON document (with ``summary``
    lines). ``sequence``: whether the images are consecutive frames of one camera (default: a bag is, a
    folder is if all images have the same size)."""
    say = progress or (lambda m: None)
    frames = load_images(src, image_topic=image_topic, k=k)
    say(f"{len(frames)} images from {src}")
    if sequence is None:
        sizes = {f[1].shape for f in frames}
        sequence = (not Path(src).is_dir() or (Path(src) / "metadata.yaml").exists()) or len(sizes) == 1
    fall = _falloff(frames)
    noise = _noise(frames)
    parts = _particles(frames)
    resp = _response(frames)
    verdict, signatures, summary = [], {}, []
    fr = fall["frames"]
    # vignetting: radial falloff that dominates a gradient, consistent between frames
    if fr:
        corner = np.array([r["corner_falloff"] for r in fr])
        grad = np.array([r["gradient"] for r in fr])
        r2r = np.array([r["r2_radial"] for r in fr])
        r2g = np.array([r["r2_gradient"] for r in fr])
        c_med = float(np.median(corner))
        spread = float(np.std(corner)) if len(corner) > 1 else 0.0
        consistent = (spread < 0.5 * abs(c_med)) if sequence and len(corner) > 1 else None
        score_v = max(0.0, c_med) / 0.15 * (1.0 if float(np.median(r2r)) >= float(np.median(r2g)) else 0.5)
        if consistent is False:
            score_v *= 0.5
        signatures["vignetting"] = {"score": score_v, "corner_falloff_median": c_med, "frame_spread": spread,
                                    "consistent_between_frames": consistent, "r2_radial_median": float(np.median(r2r)),
                                    "r2_gradient_median": float(np.median(r2g))}
        g_med = float(np.median(grad))
        dirs = [r["gradient_direction_deg"] for r in fr]
        # image y grows downwards: -90 deg = brighter towards the top (daylight from the surface)
        up = float(np.mean([abs(((d + 90) + 180) % 360 - 180) < 45 for d in dirs]))
        score_l = g_med / 0.3 * (1.0 if float(np.median(r2g)) > float(np.median(r2r)) else 0.6)
        if up > 0.5:
            score_l *= 0.3        # mostly brighter towards the surface: downwelling daylight, not a vehicle lamp
        signatures["artificial_light"] = {"score": score_l, "water_gradient_median": g_med, "share_brighter_up": up,
                                          "gradient_direction_deg": dirs, "note": "judged from the water only: a "
                                          "non-radial brightness gradient in open water (lamp veil or daylight from "
                                          "above; the two cannot be told apart without range)"}
    nr = noise["frames"]
    if nr:
        lag = _med([r["lag1_over_lag3"] for r in nr])
        shot = _med([r["shot_gain_dn"] for r in nr])
        block = _med([r["block_ratio"] for r in nr])
        sig = _med([r["sigma_lag3"] for r in nr])
        parts_n = {"correlation": max(0.0, 1 - (lag or 1)) / 0.15, "intensity_dependence": max(0.0, shot or 0) / 0.12,
                   "blocking": max(0.0, (block or 1) - 1) / 0.15}
        # the structure of noise matters only where there is noise to see: at 0.5 DN (half a quantization
        # step) and below, a correlated or blocky residue is the codec's, not a camera noise the
        # simulation lacks; full weight from 1.5 DN
        visible = float(np.clip(((sig or 0.0) - 0.5) / 1.0, 0.0, 1.0))
        signatures["sensor_noise"] = {"score": max(parts_n.values()) * visible, "sigma_dn": sig, "lag1_over_lag3": lag,
                                      "shot_gain_dn": shot, "block_ratio": block, "parts": parts_n}
    pr = parts["frames"]
    if pr:
        pos = _med([r["positive_per_mpx"] for r in pr])
        neg = _med([r["negative_per_mpx"] for r in pr])
        per = _med([r["persistence"] for r in pr])
        score_s = max(0.0, pos - neg) / 40.0 * (1.0 if per is None else max(0.0, 1 - per / 0.5))
        signatures["marine_snow"] = {"score": score_s, "positive_per_mpx": pos, "negative_per_mpx": neg,
                                     "persistence": per}
    rr = resp["frames"]
    if rr:
        black = np.median([r["black_dn"] for r in rr], axis=0)
        gains = np.median([r["grey_world_gains"] for r in rr], axis=0)
        # a pedestal lifts the darkest pixels of *every* channel; a colour cast alone is what the water's
        # attenuation does too, so it is reported but not counted as camera response
        score_c = float(np.min(black)) / 20.0
        signatures["camera_response"] = {"score": score_c, "black_level_dn": black.tolist(),
                                         "grey_world_gains": gains.tolist(),
                                         "note": "a colour cast is also what the water's attenuation gives: "
                                                 "without range the two are not separated"}
    texts = {
        "vignetting": lambda s: (f"the smooth (water) parts darken radially towards the corners by "
                                 f"{100 * s['corner_falloff_median']:.0f} % (radial fit R² {s['r2_radial_median']:.2f} vs "
                                 f"gradient {s['r2_gradient_median']:.2f})"),
        "artificial_light": lambda s: (f"open water is not uniformly lit: log-brightness changes by "
                                       f"{s['water_gradient_median']:.2f} per half-diagonal along a gradient "
                                       f"(lamp veil or daylight from above)"),
        "sensor_noise": lambda s: (f"noise {s['sigma_dn']:.1f} DN, lag-1/lag-3 ratio {s['lag1_over_lag3']:.2f} "
                                   f"(< 1: correlated), variance slope {s['shot_gain_dn'] or 0:.2f} DN/DN, "
                                   f"8x8 block ratio {s['block_ratio']:.2f} (> 1: JPEG/MJPEG blocking)"),
        "marine_snow": lambda s: (f"{s['positive_per_mpx']:.0f} small bright specks per megapixel against "
                                  f"{s['negative_per_mpx']:.0f} dark ones"),
        "camera_response": lambda s: (f"black level {', '.join(f'{v:.0f}' for v in s['black_level_dn'])} DN (r, g, b), "
                                      f"grey-world gains {', '.join(f'{v:.2f}' for v in s['grey_world_gains'])}"),
    }
    for e, s in signatures.items():
        if s["score"] >= 1.0:
            conf = float(np.clip(0.35 + 0.15 * min(s["score"], 4.0), 0.05, 0.9))
            verdict.append({"effect": e, "confidence": conf, "explanation": texts[e](s),
                            "params": {k: v for k, v in s.items() if isinstance(v, (int, float)) and k != "score"}})
    verdict.sort(key=lambda v: -v["confidence"])
    for v in verdict:
        summary.append(f"verdict: {v['effect']} (confidence {v['confidence']:.2f}): {v['explanation']}")
    if not verdict:
        summary.append("verdict: none of the judgeable effects shows")
    for e, why in NOT_JUDGED.items():
        summary.append(f"not judged: {e}: {why}")
    regions = []
    for r in fr:
        regions.append({"kind": "frame", "name": r["frame"], "rms": 0.0, "share": 0.0,
                        "corner_falloff": r["corner_falloff"], "gradient": r["gradient"],
                        "smooth_share": r["smooth_share"]})
    return jsonable({
        "schema_version": 1, "mode": "images",
        "verdict": verdict, "candidates": [],
        "base": {"theta_train": None, "theta_heldout": None, "params": {}},
        "final": {"theta_heldout": None},
        "mismatch": {"regions": regions},
        "signatures": signatures,
        "not_judged": [{"effect": e, "reason": why} for e, why in NOT_JUDGED.items()],
        "measurements": {"falloff": fall, "noise": noise, "particles": parts, "response": resp},
        "frames": [{"name": n, "width": int(i.shape[1]), "height": int(i.shape[0])} for n, i in frames],
        "sequence": bool(sequence), "source": str(src), "summary": summary,
    })
