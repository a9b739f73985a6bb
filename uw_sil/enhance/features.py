"""Feature matches between two frames, per descriptor (the paper's Table 2 and Fig. 5).

The paper judges a dehazing method by how many local features it lets a matcher pair between images
of the panel (Sec. 4.3): "the number of feature matches, found through k-nearest-neighbor, whose
Euclidean distance is less than a threshold of 0.25 in the feature space". Descriptors differ in kind
and scale, so that rule needs a normalization, which the paper does not give; the one used here:

========== ======================================== ====================== ===================
descriptor keypoints                                descriptor (size)      distance, in [0, *]
========== ======================================== ====================== ===================
ORB        ORB (oriented FAST, OpenCV, 500 best)    rBRIEF, binary 256 bit Hamming / 256 [0, 1]
BRIEF      STAR (CenSurE, ``cv2.xfeatures2d``);     BRIEF, binary 256 bit  Hamming / 256 [0, 1]
           FAST (threshold 20) if STAR is missing
SIFT       SIFT (OpenCV)                            float 128              L2 of unit vectors [0, √2]
SURF       SURF (mahotas.features.surf, at most     float 64               L2 of unit vectors [0, 2]
           1024 points; OpenCV's SURF is non-free
           and absent from the PyPI wheels)
KAZE       KAZE (OpenCV)                            float 64               L2 of unit vectors [0, 2]
AKAZE      AKAZE (OpenCV)                           MLDB, binary 486 bit   Hamming / 486 [0, 1]
========== ======================================== ====================== ===================

- Float descriptors are scaled to unit L2 norm; the distance is the Euclidean distance between the
  unit vectors. Binary descriptors use the fraction of differing bits. Both are scale-free and a
  match counts when the distance is below ``MATCH_THRESHOLD = 0.25`` (the paper's number). The two
  kinds are not equivalent (for ±1 vectors the unit-vector distance is 2·sqrt(bit fraction), so 0.25
  of the bits would be a distance of 1.0): compare counts down a column of the table (one descriptor,
  several dehazing methods), not across columns.
- Raw matches: mutual nearest neighbours (OpenCV's brute-force cross-check) whose distance is below
  the threshold. The paper names k-nearest-neighbour matching without k or a ratio; a cross-check
  rather than Lowe's ratio test: it needs no second parameter and is symmetric in the two frames.
- Verified matches (not in the paper, which counts the raw ones): the inliers of a homography fitted
  to the raw matches by RANSAC (reprojection error ``RANSAC_REPROJ_PX = 3`` px, 2000 iterations,
  confidence 0.995; the panel is planar). Any 4 matches fit a homography exactly, so fewer than
  ``MIN_VERIFIED = 8`` inliers count as 0. OpenCV's RNG is seeded (``cv2.setRNGSeed``) before each fit.
- Deterministic: keypoints are put in a fixed order (by position, size, angle, response) before
  matching, so a given pair of images always gives the same matches.

Images may be RGB or grey, ``uint8`` or floating point in [0, 1]; they are converted to 8-bit grey.
Optional masks (non-zero = use) restrict where keypoints are kept.
"""
from __future__ import annotations

import csv
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

__all__ = [
    "ALL_DESCRIPTORS",
    "MATCH_THRESHOLD",
    "MIN_VERIFIED",
    "MatchResult",
    "RANSAC_REPROJ_PX",
    "detect",
    "draw_matches",
    "match_features",
    "match_table",
    "table_csv",
    "table_markdown",
]

ALL_DESCRIPTORS = ("ORB", "BRIEF", "SIFT", "SURF", "KAZE", "AKAZE")
MATCH_THRESHOLD = 0.25
RANSAC_REPROJ_PX = 3.0
RANSAC_ITERS = 2000
RANSAC_CONFIDENCE = 0.995
MIN_VERIFIED = 8
RNG_SEED = 0
CSV_COLUMNS = ("pair", "descriptor", "detector", "keypoints1", "keypoints2", "raw_matches", "verified_matches")


@dataclass(frozen=True)
class _Features:
    keypoints: tuple
    descriptors: np.ndarray  # (N, D): float32 unit rows, or uint8 packed bits
    binary: bool
    nbits: int               # for binary descriptors
    detector: str


@dataclass(frozen=True)
class MatchResult:
    """Matches of one descriptor between two frames.

    ``raw_matches`` and ``verified_matches`` are (M, 2) int arrays of indices into ``keypoints1`` and
    ``keypoints2``; ``distances`` (M,) are the normalized descriptor distances of the raw matches and
    ``inlier_mask`` (M,) marks the RANSAC-verified ones; ``homography`` maps frame 1 to frame 2
    (None when fewer than ``MIN_VERIFIED`` matches agree on one).
    """

    descriptor: str
    detector: str
    keypoints1: tuple
    keypoints2: tuple
    raw_matches: np.ndarray
    distances: np.ndarray
    inlier_mask: np.ndarray
    homography: np.ndarray | None
    verified_matches: np.ndarray = field(init=False)

    def __post_init__(self):
        object.__setattr__(self, "verified_matches", self.raw_matches[self.inlier_mask])

    @property
    def n_raw(self) -> int:
        return int(len(self.raw_matches))

    @property
    def n_verified(self) -> int:
        return int(self.inlier_mask.sum())

    def points(self, which: str = "verified") -> tuple[np.ndarray, np.ndarray]:
        """Matched pixel coordinates (x, y) in frame 1 and frame 2, ``which`` = 'verified' or 'raw'."""
        m = self.verified_matches if which == "verified" else self.raw_matches
        p1 = np.array([self.keypoints1[i].pt for i in m[:, 0]], np.float32).reshape(-1, 2)
        p2 = np.array([self.keypoints2[j].pt for j in m[:, 1]], np.float32).reshape(-1, 2)
        return p1, p2


def _to_grey_u8(image, name="image") -> np.ndarray:
    arr = np.asarray(image)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if not (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[2] == 3)):
        raise ValueError(f"{name} must be (H, W) grey or (H, W, 3) RGB, got shape {arr.shape}")
    if arr.shape[0] < 16 or arr.shape[1] < 16:
        raise ValueError(f"{name} is too small for feature detection: {arr.shape[:2]}")
    if arr.dtype != np.uint8:
        if not np.issubdtype(arr.dtype, np.floating):
            raise ValueError(f"{name} dtype must be uint8 (0-255) or floating point (0-1), got {arr.dtype}")
        if not np.isfinite(arr).all():
            raise ValueError(f"{name} contains NaN or infinite values")
        if arr.min() < -1e-6 or arr.max() > 1 + 1e-6:
            raise ValueError(f"float {name} values must lie in [0, 1], found [{arr.min():.4g}, {arr.max():.4g}]")
        arr = np.rint(np.clip(arr, 0.0, 1.0) * 255.0).astype(np.uint8)
    if arr.ndim == 3:
        arr = cv2.cvtColor(np.ascontiguousarray(arr), cv2.COLOR_RGB2GRAY)
    return np.ascontiguousarray(arr)


def _to_mask(mask, shape, name) -> np.ndarray | None:
    if mask is None:
        return None
    m = np.asarray(mask)
    if m.shape != tuple(shape):
        raise ValueError(f"{name} shape {m.shape} does not match the image's {tuple(shape)}")
    return (m != 0).astype(np.uint8) * 255


def _has_star() -> bool:
    return hasattr(cv2, "xfeatures2d") and hasattr(cv2.xfeatures2d, "StarDetector_create")


def _create(factory: str):
    """``cv2.<factory>``, or ``cv2.xfeatures2d.<factory>`` where OpenCV 5 moved it (KAZE, AKAZE)."""
    fn = getattr(cv2, factory, None)
    if fn is None and hasattr(cv2, "xfeatures2d"):
        fn = getattr(cv2.xfeatures2d, factory, None)
    if fn is None:
        raise ImportError(f"this OpenCV build has no {factory} (opencv-contrib-python-headless 4.x has it)")
    return fn


def _opencv_features(name, grey, mask):
    """Keypoints and raw descriptors from OpenCV; returns (keypoints, descriptors, binary, nbits, detector)."""
    if name == "ORB":
        kp, d = cv2.ORB_create().detectAndCompute(grey, mask)
        return kp, d, True, 256, "ORB"
    if name == "SIFT":
        kp, d = cv2.SIFT_create().detectAndCompute(grey, mask)
        return kp, d, False, 0, "SIFT"
    if name == "KAZE":
        kp, d = _create("KAZE_create")().detectAndCompute(grey, mask)
        return kp, d, False, 0, "KAZE"
    if name == "AKAZE":
        kp, d = _create("AKAZE_create")().detectAndCompute(grey, mask)
        return kp, d, True, 486, "AKAZE"
    if name == "BRIEF":
        if _has_star():
            detector, det_name = cv2.xfeatures2d.StarDetector_create(), "STAR"
        else:
            detector, det_name = cv2.FastFeatureDetector_create(threshold=20), "FAST"
        kp = _sorted(detector.detect(grey, mask))
        kp, d = cv2.xfeatures2d.BriefDescriptorExtractor_create(32).compute(grey, kp)
        return kp, d, True, 256, det_name
    raise ValueError(f"unknown descriptor {name!r}; expected one of {ALL_DESCRIPTORS}")


def _surf_features(grey, mask):
    try:
        from mahotas.features import surf
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("SURF needs mahotas (OpenCV's SURF is non-free): pip install mahotas") from exc
    pts = surf.surf(grey.astype(np.float64))  # rows: y, x, scale, score, laplacian, angle, 64 values
    if mask is not None and len(pts):
        yi = np.clip(np.rint(pts[:, 0]).astype(int), 0, grey.shape[0] - 1)
        xi = np.clip(np.rint(pts[:, 1]).astype(int), 0, grey.shape[1] - 1)
        pts = pts[mask[yi, xi] != 0]
    kp = [cv2.KeyPoint(float(p[1]), float(p[0]), float(2.0 * p[2]), float(np.degrees(p[5]) % 360.0),
                       float(p[3]), 0, -1) for p in pts]
    return kp, pts[:, 6:].astype(np.float32), False, 0, "SURF"


def _order(kp) -> np.ndarray:
    if not kp:
        return np.zeros(0, dtype=int)
    a = np.array([(k.pt[1], k.pt[0], k.size, k.angle, k.response, k.octave) for k in kp], np.float64)
    return np.lexsort(a.T[::-1])


def _sorted(kp):
    return tuple(kp[i] for i in _order(kp))


def detect(image, descriptor: str, mask=None) -> _Features:
    """Keypoints (in a fixed order) and normalized descriptors of one frame for ``descriptor``."""
    name = _check_descriptor(descriptor)
    grey = _to_grey_u8(image)
    m = _to_mask(mask, grey.shape, "mask")
    if name == "SURF":
        kp, d, binary, nbits, det = _surf_features(grey, m)
    else:
        kp, d, binary, nbits, det = _opencv_features(name, grey, m)
    kp = list(kp or ())
    if d is None or len(kp) == 0:
        d = np.zeros((0, 32 if binary else 1), np.uint8 if binary else np.float32)
        kp = []
    order = _order(kp)
    kp = tuple(kp[i] for i in order)
    d = d[order]
    if not binary:
        d = d.astype(np.float32)
        norms = np.linalg.norm(d, axis=1, keepdims=True)
        d = np.divide(d, norms, out=np.zeros_like(d), where=norms > 0)
    return _Features(kp, np.ascontiguousarray(d), binary, nbits, det)


def _check_descriptor(descriptor) -> str:
    name = str(descriptor).upper()
    if name not in ALL_DESCRIPTORS:
        raise ValueError(f"unknown descriptor {descriptor!r}; expected one of {ALL_DESCRIPTORS}")
    return name


def _match(f1: _Features, f2: _Features, threshold: float):
    if len(f1.keypoints) == 0 or len(f2.keypoints) == 0:
        return np.zeros((0, 2), int), np.zeros(0)
    norm = cv2.NORM_HAMMING if f1.binary else cv2.NORM_L2
    matches = cv2.BFMatcher(norm, crossCheck=True).match(f1.descriptors, f2.descriptors)
    pairs = np.array([(m.queryIdx, m.trainIdx) for m in matches], int).reshape(-1, 2)
    dist = np.array([m.distance for m in matches], np.float64)
    if f1.binary:
        dist = dist / f1.nbits
    keep = dist < threshold
    pairs, dist = pairs[keep], dist[keep]
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    return pairs[order], dist[order]


def _verify(kp1, kp2, pairs):
    mask = np.zeros(len(pairs), bool)
    if len(pairs) < 4:
        return mask, None
    p1 = np.array([kp1[i].pt for i in pairs[:, 0]], np.float32)
    p2 = np.array([kp2[j].pt for j in pairs[:, 1]], np.float32)
    cv2.setRNGSeed(RNG_SEED)
    H, inl = cv2.findHomography(p1, p2, cv2.RANSAC, RANSAC_REPROJ_PX, maxIters=RANSAC_ITERS,
                                confidence=RANSAC_CONFIDENCE)
    if H is None or inl is None:
        return mask, None
    mask = inl.ravel().astype(bool)
    if mask.sum() < MIN_VERIFIED:
        return np.zeros(len(pairs), bool), None
    return mask, H


def match_features(img1, img2, descriptor: str, mask1=None, mask2=None, *,
                   threshold: float = MATCH_THRESHOLD) -> MatchResult:
    """Raw (mutual nearest neighbour, normalized distance < ``threshold``) and RANSAC-verified matches.

    Parameters
    ----------
    img1, img2 : array_like
        Frames, (H, W) grey or (H, W, 3) RGB, ``uint8`` or float in [0, 1]; sizes may differ.
    descriptor : str
        One of ``ALL_DESCRIPTORS`` (case-insensitive).
    mask1, mask2 : array_like, optional
        (H, W) masks of the frames; keypoints are kept where the mask is non-zero.
    threshold : float
        Normalized distance below which a mutual nearest neighbour counts (module docstring).
    """
    f1 = detect(img1, descriptor, mask1)
    f2 = detect(img2, descriptor, mask2)
    pairs, dist = _match(f1, f2, threshold)
    inliers, H = _verify(f1.keypoints, f2.keypoints, pairs)
    return MatchResult(descriptor=_check_descriptor(descriptor), detector=f1.detector,
                       keypoints1=f1.keypoints, keypoints2=f2.keypoints, raw_matches=pairs,
                       distances=dist, inlier_mask=inliers, homography=H)


def match_table(pairs: dict, descriptors=ALL_DESCRIPTORS) -> list[dict]:
    """One row per (pair, descriptor): keypoint counts, raw and verified matches.

    ``pairs`` maps a label (e.g. ``'raw'``, ``'DCP'``, ``'SIL'``) to ``(img1, img2)`` or
    ``(img1, img2, mask1, mask2)``. Rows keep the order of ``pairs`` then of ``descriptors``.
    """
    names = [_check_descriptor(d) for d in descriptors]
    rows = []
    for label, value in pairs.items():
        if len(value) not in (2, 4):
            raise ValueError(f"pair {label!r} must be (img1, img2) or (img1, img2, mask1, mask2)")
        img1, img2, *masks = value
        mask1, mask2 = masks if masks else (None, None)
        for name in names:
            r = match_features(img1, img2, name, mask1, mask2)
            rows.append({"pair": str(label), "descriptor": name, "detector": r.detector,
                         "keypoints1": len(r.keypoints1), "keypoints2": len(r.keypoints2),
                         "raw_matches": r.n_raw, "verified_matches": r.n_verified})
    return rows


def table_markdown(rows: list[dict]) -> str:
    """A Table-2-like markdown table: one line per pair, one column per descriptor, cells
    ``verified (raw)``; a footnote names the keypoint detectors and the matching rule."""
    pairs = list(dict.fromkeys(r["pair"] for r in rows))
    descs = [d for d in ALL_DESCRIPTORS if any(r["descriptor"] == d for r in rows)]
    cell = {(r["pair"], r["descriptor"]): r for r in rows}
    detectors = {}
    for r in rows:
        detectors.setdefault(r["descriptor"], r["detector"])
    lines = ["| pair | " + " | ".join(descs) + " |", "|---|" + "---:|" * len(descs)]
    for p in pairs:
        vals = []
        for d in descs:
            r = cell.get((p, d))
            vals.append("—" if r is None else f"{r['verified_matches']} ({r['raw_matches']})")
        lines.append(f"| {p} | " + " | ".join(vals) + " |")
    det = ", ".join(f"{d}: {detectors[d]} keypoints" for d in descs if detectors[d] != d)
    lines.append("")
    lines.append(f"Cells: RANSAC-verified homography inliers (raw matches: mutual nearest neighbours with "
                 f"normalized descriptor distance < {MATCH_THRESHOLD}; unit-L2 for float descriptors, "
                 f"bit fraction for binary ones)." + (f" {det}." if det else "")
                 + (f" SURF: mahotas {_mahotas_version()} (OpenCV's SURF is non-free)." if "SURF" in descs else ""))
    return "\n".join(lines) + "\n"


def _mahotas_version() -> str:
    try:
        from importlib.metadata import version
        return version("mahotas")
    except Exception:  # pragma: no cover - depends on the install
        return "(version unknown)"


def table_csv(rows: list[dict], path) -> Path:
    """Write the rows as CSV (columns ``CSV_COLUMNS``); the file appears whole or not at all."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=CSV_COLUMNS, extrasaction="ignore")
            w.writeheader()
            w.writerows(rows)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def _to_rgb_u8(image) -> np.ndarray:
    arr = np.asarray(image)
    if arr.dtype != np.uint8:
        arr = np.rint(np.clip(np.nan_to_num(arr.astype(np.float64)), 0, 1) * 255).astype(np.uint8)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim == 2:
        arr = np.repeat(arr[..., None], 3, axis=2)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"image must be (H, W) or (H, W, 3), got shape {arr.shape}")
    return arr


def draw_matches(img1, img2, result: MatchResult, *, verified_only: bool = True,
                 max_lines: int | None = None, thickness: int = 1) -> np.ndarray:
    """Both frames side by side with lines between matched keypoints (a Fig.-5-like picture).

    Verified matches are drawn green; with ``verified_only=False`` the rejected raw matches too, in
    red. ``max_lines`` keeps the matches of smallest descriptor distance. Returns RGB ``uint8``.
    """
    a, b = _to_rgb_u8(img1), _to_rgb_u8(img2)
    h = max(a.shape[0], b.shape[0])
    canvas = np.zeros((h, a.shape[1] + b.shape[1], 3), np.uint8)
    canvas[:a.shape[0], :a.shape[1]] = a
    canvas[:b.shape[0], a.shape[1]:] = b
    idx = np.arange(result.n_raw)
    if verified_only:
        idx = idx[result.inlier_mask]
    idx = idx[np.argsort(result.distances[idx], kind="stable")]
    if max_lines is not None:
        idx = idx[:max_lines]
    off = a.shape[1]
    for k in idx[::-1]:  # the best drawn last, on top
        i, j = result.raw_matches[k]
        p = tuple(int(round(v)) for v in result.keypoints1[i].pt)
        q = result.keypoints2[j].pt
        q = (int(round(q[0])) + off, int(round(q[1])))
        colour = (0, 200, 0) if result.inlier_mask[k] else (220, 0, 0)
        cv2.line(canvas, p, q, colour, thickness, cv2.LINE_AA)
        cv2.circle(canvas, p, 3, colour, 1, cv2.LINE_AA)
        cv2.circle(canvas, q, 3, colour, 1, cv2.LINE_AA)
    return canvas
